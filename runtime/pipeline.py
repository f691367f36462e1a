"""The per-frame pipeline: estimator, tracker, then the sinks (link, poses file).

``Pipeline.process(frame, capture_ns)`` runs one frame and returns what was
published. One estimator failing on a frame is a status, never an exit.
Telemetry keeps per-stage timings, grab-to-output latency and failure counts in
bounded memory.

:func:`build_pipeline` assembles one for a live run and a replay alike (the same
order of sinks, the same metering); :func:`open_ros2` opens the ROS 2 node of both.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ceilkit.runtime.errors import OutputError
from ceilkit.runtime.estimators.base import BAD_FRAME, Estimate, Failure, PoseEstimate
from ceilkit.runtime.estimators.registry import Estimator
from ceilkit.runtime.io.recording import PoseWriter, device_of
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.metrics import AccuracyMeter, MeterSink
from ceilkit.runtime.tracking import Tracker
from ceilkit.runtime.viz.tap import EstimateTap

log = logging.getLogger("ceilkit.outputs")

RETRY_S = 1.0
"""Seconds between attempts to write again to an output that failed (a full disk)."""


class PoseSink(Protocol):
    """Where published poses go: a serial link, a poses file, a test list."""

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        ...


@runtime_checkable
class FaultSink(PoseSink, Protocol):
    """A sink that can also report the localizer's state (a link: ``$PCEIS ... F``)."""

    def set_fault(self, reason: str | None) -> None:
        ...


class OutputGuard:
    """An output that degrades instead of stopping the run (a logger on the vehicle).

    When a write fails, one line says so (``no space left on /dev/sda1 (/data);
    recording stopped at frame 812, localization continues``); while paused, what is
    not written is counted (:meth:`skip`) and a write is tried again every ``retry_s``
    (:meth:`due`); the first that succeeds logs ``... resumed``. Several writers (the
    loop's thread and an encoder thread) may report to one guard: it is paused while
    any of them fails.

    Args:
        what: the output's name in messages (``recording``, ``poses.csv``).
        path: a path on its file system (the device named in messages).
        unit: what :meth:`skip` counts (``frame``, ``row``).
        retry_s: seconds between attempts while paused.
        clock: seconds (monotonic).
    """

    def __init__(self, what: str, path, unit: str = "frame", retry_s: float = RETRY_S,
                 clock: Callable[[], float] = time.monotonic):
        self.what = what
        self.path = path
        self.unit = unit
        self.retry_s = retry_s
        self.clock = clock
        self.lost = 0           # units not written
        self.pauses = 0
        self.reason = ""        # why the last pause began
        self._failing: dict[str, float] = {}   # writer -> when it may try again
        self._lock = threading.Lock()

    @property
    def paused(self) -> bool:
        return bool(self._failing)

    def due(self, writer: str = "main") -> bool:
        """Whether ``writer`` should write now (not failing, or its retry is due)."""
        with self._lock:
            t = self._failing.get(writer)
            return t is None or self.clock() >= t

    def failed(self, exc: OutputError, at: int, writer: str = "main") -> None:
        """``writer`` failed at unit ``at``: pause (one line when the pause begins)."""
        with self._lock:
            first = not self._failing
            self._failing[writer] = self.clock() + self.retry_s
        if first:
            self.pauses += 1
            dev = device_of(self.path)
            code = getattr(exc, "errno", None)
            self.reason = (f"no space left on {dev}" if code == errno.ENOSPC
                           else f"cannot write on {dev} ({exc.detail})")
            log.warning("%s; %s stopped at %s %d, localization continues", self.reason,
                        self.what, self.unit, at)

    def ok(self, at: int, writer: str = "main") -> None:
        """``writer`` wrote unit ``at``: resume when nothing else is failing."""
        if writer not in self._failing:
            return
        with self._lock:
            self._failing.pop(writer, None)
            resumed = not self._failing
        if resumed:
            log.warning("%s resumed at %s %d (%d %ss not written since it stopped)",
                        self.what, self.unit, at, self.lost, self.unit)

    def skip(self) -> None:
        self.lost += 1

    def lines(self) -> list[str]:
        """A report line when anything was not written."""
        if not self.pauses:
            return []
        return [f"{self.what}: {self.lost} {self.unit}s not written, paused {self.pauses}x "
                f"({self.reason})"]


class PoseFileSink:
    """Writes ``poses.csv`` rows; latency from capture to the row being written.

    With ``guard`` a failed write (a full disk) pauses the file instead of raising:
    the link and the other sinks go on (see :class:`OutputGuard`).
    """

    def __init__(self, writer: PoseWriter, clock: Callable[[], int] = time.monotonic_ns,
                 guard: OutputGuard | None = None):
        self.writer = writer
        self.clock = clock
        self.guard = guard

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        guard = self.guard
        if guard is None:
            self.writer.write(est, (self.clock() - capture_ns) / 1e6)
            return
        if not guard.due():
            guard.skip()
            return
        row = self.writer.rows
        try:
            self.writer.write(est, (self.clock() - capture_ns) / 1e6)
        except OutputError as exc:
            guard.skip()
            guard.failed(exc, row)
            return
        guard.ok(row)


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
    link_state: str = ""  # set by the live loop: "stalled", "disconnected", ...
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
        if self.failures.get("ambiguous", 0) and not self.estimated:
            out.append("  (ambiguous: several poses explain every frame alike, a symmetric "
                       "or repeating ceiling; a --start-pose singles one out, or for the "
                       "corridor method --option assume_heading_deg=DEG: "
                       "docs/methods/honesty.md)")
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
                f"fail {sum(self.failures.values())} latency {lat:.1f} ms"
                + (f" link {self.link_state}" if self.link_state else ""))


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
        (defaults to ``frame.t_ns``, right for live sources stamped at grab). A damaged
        frame (``frame.damage``: its file was cut short) is a ``bad_frame`` failure
        whose detail names the file; the estimator never sees it."""
        capture_ns = frame.t_ns if capture_ns is None else capture_ns
        tel = self.telemetry
        tracker = self.tracker
        clock = self.clock
        t0 = clock()
        if tracker is not None:
            prior = tracker.predict(frame.t_ns)
        else:               # no tracker: each frame as if it were the first
            prior = None
            forget = getattr(self.estimator, "forget", None)
            if forget is not None:
                forget()
        t1 = clock()
        if frame.damage:    # a file that was no image: never handed on as one
            est = Failure(int(frame.t_ns), getattr(self.estimator, "name", ""), BAD_FRAME,
                          frame.damage)
        else:
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


def build_pipeline(estimator: Estimator, tracker: Tracker | None = None, *,
                   link: PoseSink | None = None, ros2: PoseSink | None = None,
                   poses: PoseSink | None = None, more: Sequence[PoseSink] = (),
                   meter: AccuracyMeter | None = None,
                   watch: Callable[[Estimator, list[PoseSink]], Estimator] | None = None,
                   clock: Callable[[], int] = time.monotonic_ns) -> Pipeline:
    """The pipeline of a live run or a replay, its sinks in the one order both use.

    The order: the serial ``link`` first (its bytes are the latency that matters), the
    ``ros2`` node, the ``poses`` file, ``more`` (a recording's pose sink, a caller's
    sinks), then the accuracy ``meter`` (a :class:`~ceilkit.runtime.metrics.MeterSink`);
    ``watch(estimator, sinks)`` (the live view's) may wrap the estimator and append a
    sink of its own, last. A ``ros2`` node with a ``tap`` attribute gets an
    :class:`~ceilkit.runtime.viz.tap.EstimateTap` of the estimator there (its overlay).

    Example::

        pipeline = build_pipeline(estimator, tracker, link=link,
                                  poses=PoseFileSink(writer), meter=meter)
    """
    sinks: list[PoseSink] = [s for s in (link, ros2, poses) if s is not None]
    if ros2 is not None and hasattr(ros2, "tap"):   # the ROS 2 overlay sees each frame
        estimator = ros2.tap = EstimateTap(estimator)
    sinks += more
    if meter is not None:
        sinks.append(MeterSink(meter))
    if watch is not None:
        estimator = watch(estimator, sinks)
    return Pipeline(estimator, sinks, tracker, clock)


def open_ros2(config: Any, tracker: Any, stack: contextlib.ExitStack,
              live: bool = False, rig: Any = None, site: Any = None) -> Any:
    """The ROS 2 node of ``config`` (a :class:`~ceilkit.runtime.io.ros2.Ros2Config`),
    opened and closed by ``stack``, fed by and feeding ``tracker`` (``/initialpose``,
    odometry) unless it is ``None``. ``live``: the frames carry a camera's monotonic
    stamps, published as wall-clock time (other stamps as they are, or from the wall
    clock at the first frame when they are not wall-clock times: a simulator's, a
    camera recording's). ``rig``/``site``: ``camera_info``, ``/tf_static`` and the
    overlay image (:func:`build_pipeline` gives the node the frames). rclpy is imported
    only here."""
    from ceilkit.runtime.io.ros2 import Ros2Node
    from ceilkit.runtime.viz.overlay import draw_overlay

    offset = time.time_ns() - time.monotonic_ns() if live else None
    draw = None if site is None else (lambda image, est: draw_overlay(image, est, rig, site))
    node = Ros2Node(config, clock_offset_ns=offset, rig=rig, draw=draw)
    if tracker is not None:
        node.attach(tracker)
    return stack.enter_context(node)
