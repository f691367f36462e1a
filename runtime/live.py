"""The live loop: read the newest frame, record it, run the pipeline, until told to stop.

Stopping is cooperative (a ``threading.Event`` set by SIGINT/SIGTERM handlers in the
CLI): the frame in hand is finished, files are closed, the summary is returned.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from .pipeline import Pipeline, Telemetry
from .recording import RecordingWriter
from .sources import SourceBase


@dataclass(frozen=True, eq=False)
class LiveResult:
    telemetry: Telemetry
    recorded: int
    elapsed_s: float
    stopped: bool  # by a signal rather than the end of the source


def run_live(source: SourceBase, pipeline: Pipeline, recorder: RecordingWriter | None = None,
             stop: threading.Event | None = None, max_frames: int = 0,
             on_frame: Callable[[Telemetry], None] | None = None,
             clock: Callable[[], int] = time.monotonic_ns) -> LiveResult:
    """Run until the source ends, ``max_frames`` frames ran, or ``stop`` is set."""
    stop = stop or threading.Event()
    live = bool(getattr(source, "live", False))
    start = clock()
    while not stop.is_set():
        if max_frames and pipeline.telemetry.frames >= max_frames:
            break
        frame = source.read()
        if frame is None:
            break
        capture_ns = frame.t_ns if live else clock()
        if recorder is not None:
            recorder.write(frame)
        pipeline.process(frame, capture_ns)
        pipeline.telemetry.dropped = int(getattr(source, "dropped", 0))
        if on_frame is not None:
            on_frame(pipeline.telemetry)
    return LiveResult(pipeline.telemetry, recorder.count if recorder else 0,
                      (clock() - start) / 1e9, stop.is_set())
