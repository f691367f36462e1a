"""The live loop: read the newest frame, run the pipeline, record the frame, until told to stop.

Stopping is cooperative (a ``threading.Event`` set by SIGINT/SIGTERM/SIGHUP handlers):
the frame in hand is finished, every logged frame is written as a PNG, files are
closed, the summary is returned.

Recording (:class:`AsyncRecorder`) is crash-safe and off the latency path: before a
frame is processed, its raw bytes are appended to the recording's write-ahead log on
the loop's thread (one ``writev``, ~0.1 ms for 640x480 grey: in the kernel's page cache
when it returns, so a SIGKILL the next instant loses nothing); the PNG (~5 ms) is
encoded on a background thread, which deletes the log segments it has turned into
PNGs. ``fsync_every_s`` bounds what a power cut can lose.

Outputs degrade, they do not stop the localizer: with an
:class:`~ceilkit.runtime.pipeline.OutputGuard` a full disk pauses the recording with
one line, counts the frames not recorded, and resumes when space returns; the link
goes on meanwhile.

Faults are reported while running, rate-limited (:class:`FaultWatch`): a frame whose
size is not the camera's (the link reports ``wrong_frame_size``), and a run of
frames failing with the same reason.

A camera that stops delivering (unplugged) is a state, not an exit: after
``fault_after_s`` without a frame the pipeline's sinks are told ``camera_lost`` (the
link sends ``$PCEIS ... F`` or stops its HEARTBEAT), the camera source reopens with
back-off, and the first frame back clears the fault.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from ceilkit.runtime.errors import OutputError
from ceilkit.runtime.estimators.base import Estimate, Failure
from ceilkit.runtime.io.recording import GuardedRecorder, RecordingWriter, guarded_log
from ceilkit.runtime.io.sources import Frame, FrameSource, LiveSource
from ceilkit.runtime.pipeline import OutputGuard, Pipeline, Telemetry

log = logging.getLogger("ceilkit.live")

WRONG_SIZE_FAULT = "wrong_frame_size"
"""The fault the link reports while frames are not of the camera's calibrated size."""
FAILURE_STREAK_FRAMES = 30
"""Consecutive failures with one reason before it is reported while running."""
REPORT_EVERY_S = 10.0
"""At most one report of a continuing fault per this many seconds."""
DAMAGE_LINES = 10
"""Damaged frames (a truncated JPEG) named one line each; later ones only counted."""


class AsyncRecorder(GuardedRecorder):
    """Records frames through a :class:`RecordingWriter`: the raw frame into its
    write-ahead log at once (:meth:`write`), the PNG on a background thread, in order.

    Args:
        writer: the recording writer (closed by :meth:`close`).
        max_queue: frames kept in memory for the encoder (beyond, it reads them back
            from the log); :meth:`write` never blocks.
        nice: the encoder thread's nice value (Linux; lower priority than the loop).
        fsync_every_s: fsync the recording at this period (0: leave it to the
            operating system); a power cut then loses at most the frames of the last
            period.
        guard: degrade on write errors (pause, count, resume; see
            :class:`~ceilkit.runtime.pipeline.OutputGuard`); ``None``: a write error
            is raised by the next :meth:`write` or by :meth:`close`.
    """

    def __init__(self, writer: RecordingWriter, max_queue: int = 64, nice: int = 10,
                 fsync_every_s: float = 0.0, guard: OutputGuard | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.writer = writer
        writer.keep_images = max_queue
        self.nice = nice
        self.fsync_every_s = fsync_every_s
        self.guard = guard
        self.clock = clock
        self._error: BaseException | None = None
        self._wake = threading.Event()
        self._closing = threading.Event()
        self.queued = 0
        self.skipped_images = 0
        self._pending: collections.deque[int] = collections.deque()  # run frame numbers
        self._thread = threading.Thread(target=self._run, name="ceilkit-record", daemon=True)
        self._thread.start()

    def write(self, frame: Frame) -> None:
        """Log ``frame`` (on the caller's thread: it is on disk when this returns)."""
        if self._error is not None:
            raise self._error
        self._pending.append(frame.index)   # before the log: the encoder may take it at once
        if guarded_log(self, lambda: self.writer.log(frame), frame.index):
            self.queued += 1
            self._wake.set()
        else:
            self._pending.pop()

    def _convert(self) -> bool:
        """One frame to PNG; whether the encoder should try again at once."""
        guard, writer = self.guard, self.writer
        if guard is not None and not guard.due("encode"):
            return False
        try:
            done = writer.convert_next()
        except OutputError as exc:
            if getattr(exc, "errno", 0) is None:
                writer.skip_next()
                self._next_frame(pop=True)
                return True
            if guard is None:
                self._error = exc
            else:
                guard.failed(exc, self._next_frame(), "encode")
            return False
        if done:
            at = self._next_frame(pop=True)
            if guard is not None:
                guard.ok(at, "encode")
        return done

    def _next_frame(self, pop: bool = False) -> int:
        """The run's frame number of the next frame to encode (the messages name it)."""
        if not self._pending:
            return self.writer.converted
        return self._pending.popleft() if pop else self._pending[0]

    def _sync(self) -> None:
        try:
            self.writer.sync(durable=self.fsync_every_s > 0)
        except OutputError as exc:
            if self.guard is None:
                self._error = exc
            else:
                self.guard.failed(exc, self._next_frame(), "encode")

    def _run(self) -> None:
        try:  # Linux: a thread's own nice value; the estimator wins a contended core
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
        except (AttributeError, OSError):
            pass
        next_sync = self.clock() + self.fsync_every_s
        try:
            while self._error is None:
                closing = self._closing.is_set()
                progressed = self._convert()
                if self.fsync_every_s <= 0 or self.clock() >= next_sync:
                    self._sync()
                    next_sync = self.clock() + self.fsync_every_s
                if closing and (not progressed or not self.writer.pending):
                    break  # done, or the disk is still full: the rest stays in the log
                if not progressed:
                    self._wake.wait(0.05)
                    self._wake.clear()
            if self.fsync_every_s > 0 and self._error is None:
                self._sync()
        except BaseException as exc:  # noqa: BLE001 - a bug: raised by close()
            self._error = exc

    def close(self) -> None:
        """Write every logged frame as a PNG (as far as the disk allows), stop the
        thread, close the writer (the log stays for frames that are not PNGs)."""
        self._closing.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join()
        self.writer.close()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> AsyncRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FaultWatch:
    """Reports faults while running, on the log (stderr) and rate-limited.

    * A frame whose size is not ``camera_size``: one line per new size, and the
      pipeline's sinks are told :data:`WRONG_SIZE_FAULT` until a frame of the right
      size comes.
    * :data:`FAILURE_STREAK_FRAMES` consecutive failures with one reason: a line, then
      one every :data:`REPORT_EVERY_S` while it lasts, and one when poses come back.
    * A damaged frame (its file cut short): a line naming the file, for the first
      :data:`DAMAGE_LINES` of them (the summary counts them all as ``bad_frame``).
    """

    def __init__(self, pipeline: Pipeline, camera_size: tuple[int, int] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.pipeline = pipeline
        self.camera_size = camera_size
        self.clock = clock
        self.wrong_size: tuple[int, int] | None = None
        self._reason = ""
        self._streak = 0
        self._reported_at: float | None = None
        self.reports = 0
        self.damaged = 0

    def frame(self, frame: Frame, number: int) -> None:
        """Check a frame before it is processed (``number``: its place in the run)."""
        if frame.damage:
            self.damaged += 1
            if self.damaged <= DAMAGE_LINES:
                self.reports += 1
                log.warning("frame %d: %s: no pose from it (bad_frame)%s", number,
                            frame.damage, "; further damaged frames are only counted"
                            if self.damaged == DAMAGE_LINES else "")
            return
        if self.camera_size is None:
            return
        shape = getattr(frame.image, "shape", (0, 0))
        size = (int(shape[1]), int(shape[0])) if len(shape) >= 2 else (0, 0)
        if size != self.camera_size:
            if size != self.wrong_size:
                self.wrong_size = size
                self.reports += 1
                log.warning("frame %d is %dx%d but the camera is calibrated at %dx%d: no "
                            "pose can come from it (the link reports %s)", number, *size,
                            *self.camera_size, WRONG_SIZE_FAULT)
                self.pipeline.set_fault(WRONG_SIZE_FAULT)
        elif self.wrong_size is not None:
            self.wrong_size = None
            log.warning("frame %d is of the camera's size again", number)
            self.pipeline.set_fault(None)

    def result(self, est: Estimate) -> None:
        """Follow the run of failures after a frame was processed."""
        if not isinstance(est, Failure):
            if self._reported_at is not None:
                log.warning("poses again after %d frames that failed with %s",
                            self._streak, self._reason)
            self._reason, self._streak, self._reported_at = "", 0, None
            return
        if est.reason != self._reason:
            self._reason, self._streak, self._reported_at = est.reason, 0, None
        self._streak += 1
        now = self.clock()
        if self._streak >= FAILURE_STREAK_FRAMES and (
                self._reported_at is None or now - self._reported_at >= REPORT_EVERY_S):
            self._reported_at = now
            self.reports += 1
            log.warning("no pose for %d frames: each failed with %s", self._streak,
                        self._reason)


class CameraLoss:
    """A live camera that sends no frame for ``fault_after_s`` is lost: one line, the
    pipeline's sinks are told ``camera_lost`` (``telemetry.camera_losses`` counts it),
    and the fault is cleared by the next frame."""

    def __init__(self, pipeline: Pipeline, watch: FaultWatch, fault_after_s: float,
                 start_ns: int) -> None:
        self.pipeline = pipeline
        self.watch = watch
        self.fault_after_ns = fault_after_s * 1e9
        self.last_frame_ns = start_ns
        self.faulted = False

    def waiting(self, now_ns: int) -> None:
        """No frame came in a wait slice ending at ``now_ns``."""
        if not self.faulted and now_ns - self.last_frame_ns > self.fault_after_ns:
            self.faulted = True
            self.pipeline.telemetry.camera_losses += 1
            log.warning("no frame for %.1f s: camera lost, waiting for it "
                        "(the link reports camera_lost)",
                        (now_ns - self.last_frame_ns) / 1e9)
            self.pipeline.set_fault("camera_lost")

    def frame(self, capture_ns: int) -> None:
        """A frame captured at ``capture_ns`` arrived."""
        if self.faulted:
            self.faulted = False
            log.warning("camera back after %.1f s; running again",
                        (capture_ns - self.last_frame_ns) / 1e9)
            self.pipeline.set_fault(None)
            self.watch.wrong_size = None
        self.last_frame_ns = capture_ns


@dataclass(frozen=True, eq=False)
class LiveResult:
    """How the live loop went.

    Attributes:
        telemetry: counts and timings.
        recorded: frames in the recording (as PNGs or in its write-ahead log).
        elapsed_s: wall time.
        stopped: by a signal (``stop``) rather than the end of the source.
        not_recorded: frames a failing disk kept out of the recording.
        left_in_log: frames left only in the write-ahead log (the disk was still full
            at the end; they replay, :func:`~ceilkit.runtime.io.recording.repair_recording`
            makes them PNGs).
    """

    telemetry: Telemetry
    recorded: int
    elapsed_s: float
    stopped: bool
    not_recorded: int = 0
    left_in_log: int = 0


def run_live(source: FrameSource, pipeline: Pipeline,
             recorder: RecordingWriter | AsyncRecorder | None = None,
             stop: threading.Event | None = None, max_frames: int = 0,
             on_frame: Callable[[Telemetry], None] | None = None,
             clock: Callable[[], int] = time.monotonic_ns,
             fault_after_s: float = 0.5,
             camera_size: tuple[int, int] | None = None) -> LiveResult:
    """Run until the source ends, ``max_frames`` frames ran, or ``stop`` is set.

    Args:
        source: a frame source; a :class:`~ceilkit.runtime.io.sources.LiveSource` (a
            camera) is waited on in short slices so ``stop`` is honoured and a lost
            camera is reported. Frames of a source that is not ``live`` are stamped
            with ``clock`` when taken.
        pipeline: estimator, tracker and sinks.
        recorder: a :class:`RecordingWriter` (wrapped in an :class:`AsyncRecorder` and
            closed here) or an :class:`AsyncRecorder` (closed here too), or ``None``.
            Each frame is recorded before its pose is published.
        stop: set it to stop after the frame in hand.
        max_frames: stop after this many frames (0: no limit).
        on_frame: called after each frame with the telemetry (a status line).
        clock: the clock live frames are stamped with (integer ns).
        fault_after_s: seconds without a frame from a live camera before the sinks
            are told ``camera_lost``.
        camera_size: ``(width, height)`` the rig's camera is calibrated at: a frame of
            another size is reported (:class:`FaultWatch`).

    Returns:
        The telemetry, the number of frames recorded, the elapsed time and whether
        ``stop`` ended the run.
    """
    stop = stop or threading.Event()
    waited = isinstance(source, LiveSource)
    rec = AsyncRecorder(recorder) if isinstance(recorder, RecordingWriter) else recorder
    tel = pipeline.telemetry
    watch = FaultWatch(pipeline, camera_size)
    start = clock()
    camera = CameraLoss(pipeline, watch, fault_after_s, start)
    try:
        while not stop.is_set():
            if max_frames and tel.frames >= max_frames:
                break
            if waited:
                frame = source.wait_frame(0.05)
                if frame is None:
                    if source.closed:
                        break
                    camera.waiting(clock())
                    continue
            else:
                frame = source.read()
                if frame is None:
                    break
            capture_ns = frame.t_ns if source.live else clock()
            camera.frame(capture_ns)
            if rec is not None:
                rec.write(frame)  # in the log before its pose goes out
            watch.frame(frame, tel.frames)
            watch.result(pipeline.process(frame, capture_ns))
            tel.dropped = source.dropped
            if on_frame is not None:
                on_frame(tel)
    finally:
        if rec is not None:
            rec.close()
    return LiveResult(tel, rec.count if rec is not None else 0,
                      (clock() - start) / 1e9, stop.is_set(),
                      rec.not_recorded if rec is not None else 0,
                      rec.writer.pending if rec is not None else 0)
