"""Pose errors against ground truth: what a replay prints and a benchmark reports.

Heading errors are wrapped to (-180°, 180°]; the corridor method does not observe
x, so its position error is the lateral (y) error alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.io.recording import Truth


@dataclass(frozen=True)
class ErrorStats:
    """Median, 95th percentile and maximum of absolute errors; ``n`` samples."""

    median: float
    p95: float
    max: float
    n: int

    @classmethod
    def of(cls, values: Sequence[float] | np.ndarray) -> ErrorStats:
        a = np.abs(np.asarray(values, dtype=float))
        a = a[np.isfinite(a)]
        if a.size == 0:
            return cls(math.nan, math.nan, math.nan, 0)
        return cls(float(np.median(a)), float(np.percentile(a, 95)), float(a.max()), int(a.size))


@dataclass(frozen=True)
class Accuracy:
    """Errors of a run against truth.

    Attributes:
        frames: frames with a truth row.
        estimated: frames with a pose.
        heading_deg, y_m, x_m, position_m: error statistics (absolute values).
    """

    frames: int
    estimated: int
    heading_deg: ErrorStats
    y_m: ErrorStats
    x_m: ErrorStats
    position_m: ErrorStats

    @property
    def share_estimated(self) -> float:
        return self.estimated / self.frames if self.frames else math.nan

    def lines(self) -> list[str]:
        """A short human report."""
        out = [f"estimated {self.estimated}/{self.frames} frames "
               f"({100 * self.share_estimated:.1f}%)"]

        def row(name: str, s: ErrorStats, scale: float, unit: str, digits: int) -> None:
            if s.n:
                out.append(f"{name:<9} median {s.median * scale:.{digits}f} {unit}  "
                           f"p95 {s.p95 * scale:.{digits}f} {unit}  "
                           f"max {s.max * scale:.{digits}f} {unit}")

        row("heading", self.heading_deg, 1.0, "deg", 3)
        row("lateral", self.y_m, 1000.0, "mm", 1)
        if self.x_m.n:
            row("x", self.x_m, 1000.0, "mm", 1)
            row("position", self.position_m, 1000.0, "mm", 1)
        return out


class AccuracyMeter:
    """Accumulates errors frame by frame (a few floats a frame, never the frames)."""

    def __init__(self, truth: Truth):
        self.truth = truth
        self.frames = 0
        self.estimated = 0
        self._dh: list[float] = []
        self._dy: list[float] = []
        self._dx: list[float] = []
        self._dp: list[float] = []

    def add(self, est: Estimate) -> None:
        row = self.truth.lookup(est.t_ns)
        if row is None:
            return
        self.frames += 1
        if not isinstance(est, PoseEstimate):
            return
        self.estimated += 1
        x, y, yaw = row
        self._dh.append(math.degrees(wrap_pi(est.yaw_rad - yaw)))
        if est.y_m is not None:
            self._dy.append(est.y_m - y)
        if est.x_m is not None and est.y_m is not None:
            self._dx.append(est.x_m - x)
            self._dp.append(math.hypot(est.x_m - x, est.y_m - y))

    def result(self) -> Accuracy:
        return Accuracy(self.frames, self.estimated, ErrorStats.of(self._dh),
                        ErrorStats.of(self._dy), ErrorStats.of(self._dx),
                        ErrorStats.of(self._dp))


class MeterSink:
    """A pipeline sink that feeds an :class:`AccuracyMeter` (runs with known truth)."""

    def __init__(self, meter: AccuracyMeter):
        self.meter = meter

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        self.meter.add(est)


def source_truth(source: object) -> Truth | None:
    """The ground truth a source carries: a recording's ``truth.csv`` or the
    simulator's trajectory; ``None`` for a camera."""
    truth = getattr(source, "truth", None)
    if isinstance(truth, Truth):
        return truth
    traj = getattr(source, "trajectory", None)
    if traj is not None:
        return Truth(np.asarray(traj.t_ns), np.asarray(traj.x_m), np.asarray(traj.y_m),
                     np.asarray(traj.yaw_rad))
    return None
