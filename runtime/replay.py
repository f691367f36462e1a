"""Replay: the live pipeline on a stored recording (SPEC §3).

``replay(RECORDING)`` reads the recording with its own ``rig.yaml`` and
``site.yaml`` unless told otherwise, writes ``OUT/poses.csv`` (OUT defaults to
``RECORDING/replay/``), optionally a TUM trajectory beside it, and measures the
errors against ``truth.csv`` when there is one. It completes whatever share of
frames could be estimated; only bad input raises.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.recording import PoseWriter, Recording
from ceilkit.runtime.metrics import Accuracy, AccuracyMeter
from ceilkit.runtime.pipeline import Pipeline, PoseFileSink, PoseSink, Telemetry
from ceilkit.runtime.tracking import Tracker


@dataclass(frozen=True, eq=False)
class ReplayResult:
    recording: Path
    poses_path: Path
    method: str
    telemetry: Telemetry
    accuracy: Accuracy | None
    elapsed_s: float


def replay(recording: str | Path, out_dir: str | Path | None = None,
           rig: Rig | str | Path | None = None, site: Site | str | Path | None = None,
           method: str | None = None, tum: bool = False, realtime: bool = False,
           track: bool = True, sinks: Sequence[PoseSink] = (),
           progress: Callable[[int, int], None] | None = None,
           estimator_options: dict[str, Any] | None = None,
           clock: Callable[[], int] = time.monotonic_ns) -> ReplayResult:
    """Run the pipeline over a recording as fast as possible (or at recorded timing)."""
    rec = Recording(recording, rig=rig, site=site)
    check_rig_site(rec.rig, rec.site)
    estimator = make_estimator(method, rec.rig, rec.site, estimator_options)
    out = Path(out_dir) if out_dir is not None else rec.folder / "replay"
    poses_path = out / "poses.csv"
    writer = PoseWriter(poses_path, out / "poses.tum" if tum else None)
    meter = AccuracyMeter(rec.truth) if rec.truth is not None else None
    pipeline = Pipeline(estimator, [PoseFileSink(writer, clock), *sinks],
                        Tracker() if track else None, clock)
    n = len(rec)
    start = clock()
    t_first = int(rec.t_ns[0]) if n else 0
    try:
        for k in range(n):
            frame = rec.frame(k)
            if realtime:
                due = start + (frame.t_ns - t_first)
                wait = due - clock()
                if wait > 0:
                    time.sleep(wait / 1e9)
            est = pipeline.process(frame, capture_ns=clock())
            if meter is not None:
                meter.add(est)
            if progress is not None:
                progress(k + 1, n)
    finally:
        writer.close()
    return ReplayResult(rec.folder, poses_path, estimator.name, pipeline.telemetry,
                        meter.result() if meter is not None else None,
                        (clock() - start) / 1e9)
