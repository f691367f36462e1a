"""The per-frame pipeline: estimator, tracker, then the sinks (link, poses file).

``Pipeline.process(frame, capture_ns)`` runs one frame and returns what was
published. One estimator failing on a frame is a status, never an exit.
Telemetry keeps per-stage timings, grab-to-output latency and failure counts in
bounded memory.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .estimate import Estimate, PoseEstimate
from .methods import Estimator
from .recording import PoseWriter
from .sources import Frame
from .tracking import Tracker


class PoseSink(Protocol):
    """Where published poses go: a serial link, a poses file, a test list."""

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        ...


class PoseFileSink:
    """Writes ``poses.csv`` rows; latency from capture to the row being written."""

    def __init__(self, writer: PoseWriter, clock: Callable[[], int] = time.monotonic_ns):
        self.writer = writer
        self.clock = clock

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        self.writer.write(est, (self.clock() - capture_ns) / 1e6)


class ListSink:
    """Keeps everything published (a fake for tests)."""

    def __init__(self) -> None:
        self.items: list[tuple[Estimate, bool]] = []

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        self.items.append((est, relocalized))


_WINDOW = 4096  # samples kept for percentiles: bounded memory on long runs


@dataclass
class Telemetry:
    """Counts and timings of a run."""

    frames: int = 0
    estimated: int = 0
    relocalizations: int = 0
    dropped: int = 0
    failures: Counter = field(default_factory=Counter)
    estimate_ms: deque = field(default_factory=lambda: deque(maxlen=_WINDOW))
    output_ms: deque = field(default_factory=lambda: deque(maxlen=_WINDOW))
    latency_ms: deque = field(default_factory=lambda: deque(maxlen=_WINDOW))

    @staticmethod
    def _pct(values: Sequence[float], q: float) -> float:
        return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")

    def summary(self) -> list[str]:
        """Human lines for the end of a run."""
        share = 100.0 * self.estimated / self.frames if self.frames else 0.0
        out = [f"frames {self.frames}, estimated {self.estimated} ({share:.1f}%), "
               f"dropped {self.dropped}, relocalizations {self.relocalizations}"]
        if self.failures:
            out.append("failures: " + ", ".join(f"{k} {v}" for k, v in
                                               self.failures.most_common()))
        if self.latency_ms:
            out.append(
                f"estimate {self._pct(self.estimate_ms, 50):.2f} ms median "
                f"(p95 {self._pct(self.estimate_ms, 95):.2f}); output "
                f"{self._pct(self.output_ms, 50):.2f} ms; latency "
                f"{self._pct(self.latency_ms, 50):.2f} ms median "
                f"(p95 {self._pct(self.latency_ms, 95):.2f}, "
                f"max {max(self.latency_ms):.2f})")
        return out

    def live_line(self) -> str:
        lat = self.latency_ms[-1] if self.latency_ms else float("nan")
        return (f"frame {self.frames} est {self.estimated} drop {self.dropped} "
                f"fail {sum(self.failures.values())} latency {lat:.1f} ms")


class Pipeline:
    """Estimator, optional tracker, then every sink, for one frame at a time."""

    def __init__(self, estimator: Estimator, sinks: Sequence[PoseSink] = (),
                 tracker: Tracker | None = None,
                 clock: Callable[[], int] = time.monotonic_ns):
        self.estimator = estimator
        self.sinks = list(sinks)
        self.tracker = tracker
        self.clock = clock
        self.telemetry = Telemetry()

    def process(self, frame: Frame, capture_ns: int | None = None) -> Estimate:
        """Run one frame. ``capture_ns`` is when it was grabbed, on ``clock``
        (defaults to ``frame.t_ns``, right for live sources stamped at grab)."""
        capture_ns = frame.t_ns if capture_ns is None else capture_ns
        tel = self.telemetry
        t0 = self.clock()
        prior = self.tracker.predict(frame.t_ns) if self.tracker else None
        est = self.estimator.estimate(frame.image, frame.t_ns, prior)
        t1 = self.clock()
        relocalized = False
        if self.tracker is not None:
            res = self.tracker.update(est)
            est, relocalized = res.estimate, res.relocalized
        for sink in self.sinks:
            sink.send(est, relocalized, capture_ns)
        t2 = self.clock()
        tel.frames += 1
        if isinstance(est, PoseEstimate):
            tel.estimated += 1
        else:
            tel.failures[est.reason] += 1
        tel.relocalizations += int(relocalized)
        tel.estimate_ms.append((t1 - t0) / 1e6)
        tel.output_ms.append((t2 - t1) / 1e6)
        tel.latency_ms.append((t2 - capture_ns) / 1e6)
        return est
