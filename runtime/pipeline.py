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
from typing import Protocol, runtime_checkable

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.estimators.registry import Estimator
from ceilkit.runtime.io.recording import PoseWriter
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.tracking import Tracker


class PoseSink(Protocol):
    """Where published poses go: a serial link, a poses file, a test list."""

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        ...


@runtime_checkable
class FaultSink(PoseSink, Protocol):
    """A sink that can also report the localizer's state (a link: ``$PCEIS ... F``)."""

    def set_fault(self, reason: str | None) -> None:
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


def _window() -> deque:
    return deque(maxlen=_WINDOW)


@dataclass
class Telemetry:
    """Counts and timings of a run, in bounded memory (the last 4096 frames' timings).

    Per frame, in ms on the pipeline's clock: ``wait_ms`` from capture to the
    pipeline taking the frame (queueing behind the previous frame), ``estimate_ms``,
    ``track_ms`` (prior and gate), ``output_ms`` (every sink: link bytes written,
    poses row), and ``latency_ms`` from capture to the last sink done, which bounds
    the capture-to-bytes latency (the link is the first sink).
    """

    frames: int = 0
    estimated: int = 0
    relocalizations: int = 0
    dropped: int = 0
    camera_losses: int = 0
    failures: Counter = field(default_factory=Counter)
    wait_ms: deque = field(default_factory=_window)
    estimate_ms: deque = field(default_factory=_window)
    track_ms: deque = field(default_factory=_window)
    output_ms: deque = field(default_factory=_window)
    latency_ms: deque = field(default_factory=_window)

    @staticmethod
    def _pct(values: Sequence[float], q: float) -> float:
        return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")

    def summary(self) -> list[str]:
        """Human lines for the end of a run."""
        share = 100.0 * self.estimated / self.frames if self.frames else 0.0
        out = [f"frames {self.frames}, estimated {self.estimated} ({share:.1f}%), "
               f"dropped {self.dropped}, relocalizations {self.relocalizations}"
               + (f", camera lost {self.camera_losses}x" if self.camera_losses else "")]
        if self.failures:
            out.append("failures: " + ", ".join(f"{k} {v}" for k, v in
                                               self.failures.most_common()))
        if self.latency_ms:
            out.append(
                f"estimate {self._pct(self.estimate_ms, 50):.2f} ms median "
                f"(p95 {self._pct(self.estimate_ms, 95):.2f}); wait "
                f"{self._pct(self.wait_ms, 50):.2f}, track "
                f"{self._pct(self.track_ms, 50):.2f}, output "
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
    """Estimator, optional tracker, then every sink, for one frame at a time.

    Put the serial link first among ``sinks``: it is written before the others.
    """

    def __init__(self, estimator: Estimator, sinks: Sequence[PoseSink] = (),
                 tracker: Tracker | None = None,
                 clock: Callable[[], int] = time.monotonic_ns):
        self.estimator = estimator
        self.sinks = list(sinks)
        self.tracker = tracker
        self.clock = clock
        self.telemetry = Telemetry()

    def set_fault(self, reason: str | None) -> None:
        """Tell every sink that can hear it (a link's ``set_fault``) that the localizer is
        faulted (``reason``, e.g. ``camera_lost``) or healthy again (``None``)."""
        for sink in self.sinks:
            if isinstance(sink, FaultSink):
                sink.set_fault(reason)

    def process(self, frame: Frame, capture_ns: int | None = None) -> Estimate:
        """Run one frame. ``capture_ns`` is when it was grabbed, on ``clock``
        (defaults to ``frame.t_ns``, right for live sources stamped at grab)."""
        capture_ns = frame.t_ns if capture_ns is None else capture_ns
        tel = self.telemetry
        tracker = self.tracker
        clock = self.clock
        t0 = clock()
        prior = tracker.predict(frame.t_ns) if tracker is not None else None
        t1 = clock()
        est = self.estimator.estimate(frame.image, frame.t_ns, prior)
        t2 = clock()
        relocalized = False
        if tracker is not None:
            res = tracker.update(est)
            est, relocalized = res.estimate, res.relocalized
        t3 = clock()
        for sink in self.sinks:
            sink.send(est, relocalized, capture_ns)
        t4 = clock()
        tel.frames += 1
        if isinstance(est, PoseEstimate):
            tel.estimated += 1
        else:
            tel.failures[est.reason] += 1
        tel.relocalizations += int(relocalized)
        tel.wait_ms.append((t0 - capture_ns) / 1e6)
        tel.estimate_ms.append((t2 - t1) / 1e6)
        tel.track_ms.append((t1 - t0 + t3 - t2) / 1e6)
        tel.output_ms.append((t4 - t3) / 1e6)
        tel.latency_ms.append((t4 - capture_ns) / 1e6)
        return est
