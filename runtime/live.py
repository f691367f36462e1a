"""The live loop: read the newest frame, run the pipeline, record the frame, until told to stop.

Stopping is cooperative (a ``threading.Event`` set by SIGINT/SIGTERM handlers in the
CLI): the frame in hand is finished, every queued frame is recorded, files are
closed, the summary is returned.

Recording happens on its own thread (:class:`AsyncRecorder`): a PNG of 640x480 takes
about 5 ms to encode, which would otherwise sit in every frame's capture-to-bytes
latency. Every frame the loop took is queued before it is processed, and the queue
blocks when full (it never drops), so the recording holds every processed frame once
the loop returns.

A camera that stops delivering (unplugged) is a state, not an exit: after
``fault_after_s`` without a frame the pipeline's sinks are told ``camera_lost`` (the
link sends ``$PCEIS ... F`` or stops its HEARTBEAT), the camera source reopens with
back-off, and the first frame back clears the fault.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from ceilkit.runtime.io.recording import RecordingWriter
from ceilkit.runtime.io.sources import Frame, FrameSource, LiveSource
from ceilkit.runtime.pipeline import Pipeline, Telemetry

log = logging.getLogger("ceilkit.live")

_END = object()


class AsyncRecorder:
    """Writes frames through a :class:`RecordingWriter` on a background thread, in order.

    Args:
        writer: the recording writer (closed by :meth:`close`).
        max_queue: frames that may wait; :meth:`write` blocks beyond (never drops).
        nice: the writer thread's nice value (Linux; lower priority than the loop).

    A write error on the thread (disk full) is raised by the next :meth:`write` or by
    :meth:`close`.
    """

    def __init__(self, writer: RecordingWriter, max_queue: int = 64, nice: int = 10):
        self.writer = writer
        self.nice = nice
        self._q: queue.Queue = queue.Queue(maxsize=max_queue)
        self._error: BaseException | None = None
        self.queued = 0
        self._thread = threading.Thread(target=self._run, name="ceilkit-record", daemon=True)
        self._thread.start()

    @property
    def count(self) -> int:
        """Frames written so far."""
        return self.writer.count

    def _run(self) -> None:
        try:  # Linux: a thread's own nice value; the estimator wins a contended core
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
        except (AttributeError, OSError):
            pass
        while True:
            item = self._q.get()
            if item is _END:
                return
            if self._error is None:
                try:
                    self.writer.write(item)
                except BaseException as exc:  # noqa: BLE001 - reported to the loop
                    self._error = exc

    def write(self, frame: Frame) -> None:
        if self._error is not None:
            raise self._error
        self._q.put(frame)
        self.queued += 1

    def close(self) -> None:
        """Write every queued frame, stop the thread, close the writer."""
        if self._thread.is_alive():
            self._q.put(_END)
            self._thread.join()
        self.writer.close()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> AsyncRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class LiveResult:
    telemetry: Telemetry
    recorded: int
    elapsed_s: float
    stopped: bool  # by a signal rather than the end of the source


def run_live(source: FrameSource, pipeline: Pipeline,
             recorder: RecordingWriter | AsyncRecorder | None = None,
             stop: threading.Event | None = None, max_frames: int = 0,
             on_frame: Callable[[Telemetry], None] | None = None,
             clock: Callable[[], int] = time.monotonic_ns,
             fault_after_s: float = 0.5) -> LiveResult:
    """Run until the source ends, ``max_frames`` frames ran, or ``stop`` is set.

    Args:
        source: a frame source; a :class:`~ceilkit.runtime.io.sources.LiveSource` (a
            camera) is waited on in short slices so ``stop`` is honoured and a lost
            camera is reported. Frames of a source that is not ``live`` are stamped
            with ``clock`` when taken.
        pipeline: estimator, tracker and sinks.
        recorder: a :class:`RecordingWriter` (wrapped in an :class:`AsyncRecorder` and
            closed here) or an :class:`AsyncRecorder` (closed here too), or ``None``.
        stop: set it to stop after the frame in hand.
        max_frames: stop after this many frames (0: no limit).
        on_frame: called after each frame with the telemetry (a status line).
        clock: the clock live frames are stamped with (integer ns).
        fault_after_s: seconds without a frame from a live camera before the sinks
            are told ``camera_lost``.

    Returns:
        The telemetry, the number of frames recorded, the elapsed time and whether
        ``stop`` ended the run.
    """
    stop = stop or threading.Event()
    waited = isinstance(source, LiveSource)
    rec = AsyncRecorder(recorder) if isinstance(recorder, RecordingWriter) else recorder
    tel = pipeline.telemetry
    start = clock()
    last_frame_ns = start
    faulted = False
    try:
        while not stop.is_set():
            if max_frames and tel.frames >= max_frames:
                break
            if waited:
                frame = source.wait_frame(0.05)
                if frame is None:
                    if source.closed:
                        break
                    now = clock()
                    if not faulted and now - last_frame_ns > fault_after_s * 1e9:
                        faulted = True
                        tel.camera_losses += 1
                        log.warning("no frame for %.1f s: camera lost, waiting for it "
                                    "(the link reports camera_lost)",
                                    (now - last_frame_ns) / 1e9)
                        pipeline.set_fault("camera_lost")
                    continue
            else:
                frame = source.read()
                if frame is None:
                    break
            capture_ns = frame.t_ns if source.live else clock()
            if faulted:
                faulted = False
                log.warning("camera back after %.1f s; running again",
                            (capture_ns - last_frame_ns) / 1e9)
                pipeline.set_fault(None)
            last_frame_ns = capture_ns
            if rec is not None:
                rec.write(frame)  # queued first: a processed frame is always recorded
            pipeline.process(frame, capture_ns)
            tel.dropped = source.dropped
            if on_frame is not None:
                on_frame(tel)
    finally:
        if rec is not None:
            rec.close()
    return LiveResult(tel, rec.count if rec is not None else 0,
                      (clock() - start) / 1e9, stop.is_set())
