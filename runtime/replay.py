"""Replay: the live pipeline on a stored recording (SPEC §3).

``replay(RECORDING)`` reads the recording with its own ``rig.yaml`` and
``site.yaml`` unless told otherwise, writes ``OUT/poses.csv`` (OUT defaults to
``RECORDING/replay/``), optionally a TUM trajectory beside it, and measures the
errors against ``truth.csv`` when there is one. It completes whatever share of
frames could be estimated; only bad input raises.

With ``track=False`` (``ceilrun replay --no-track``) every frame is estimated with no
prior and written as the estimator gave it, with no tracking, gating or fusion
between frames: one row per frame, failures included.

The pipeline is a live run's (:func:`~ceilkit.runtime.pipeline.build_pipeline`), its
sinks in the same order: the link, the ROS 2 node, the poses file, the caller's sinks,
the accuracy meter against ``truth.csv``. No existing output is overwritten without
``force``, none may be an input or lie inside one, and ``OUT`` is locked while the
replay writes there (:mod:`~ceilkit.runtime.io.outputs`). A frame whose file is damaged
is a ``bad_frame`` failure naming the file (a failed row), never a pose.

Example::

    res = replay("rec", "out", method="lights", track=False)
    print("\n".join(res.lines()))
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.fusion import Fusion, FusionReport
from ceilkit.runtime.io.link.transport import is_serial_path
from ceilkit.runtime.io.mcap_rec import is_mcap, open_recording, replay_folder
from ceilkit.runtime.io.outputs import claim_outputs, recording_inputs
from ceilkit.runtime.io.provenance import RUN_METADATA
from ceilkit.runtime.io.recording import (
    Odometry,
    PoseWriter,
    Recording,
    load_odometry,
    write_truth_tum,
)
from ceilkit.runtime.io.ros2 import Ros2Node
from ceilkit.runtime.live import DAMAGE_LINES
from ceilkit.runtime.metrics import Accuracy, AccuracyMeter
from ceilkit.runtime.multi import make_localizer
from ceilkit.runtime.pipeline import (
    Pipeline,
    PoseFileSink,
    PoseSink,
    Telemetry,
    build_pipeline,
    open_ros2,
)
from ceilkit.runtime.session import LinkConfig, check_inputs, link_lines, opened_link
from ceilkit.runtime.viz.report import ReplayViews
from ceilkit.runtime.viz.tap import EstimateTap

log = logging.getLogger("ceilkit.replay")


@dataclass(frozen=True, eq=False)
class ReplayResult:
    """How a replay went.

    Attributes:
        recording, poses_path: the folder read and the ``poses.csv`` written.
        method: the estimator's name.
        telemetry: counts and timings.
        accuracy: errors against ``truth.csv``, or ``None`` without one.
        elapsed_s: wall time of the replay.
        tracked: whether the tracker ran (``False``: the estimator's own output).
        link: report lines of the link's counters (empty without a link).
    """

    recording: Path
    poses_path: Path
    method: str
    telemetry: Telemetry
    accuracy: Accuracy | None
    elapsed_s: float
    tracked: bool = True
    link: tuple[str, ...] = ()
    report: Path | None = None
    overlays: int = 0
    fusion: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """The report: a heading, then indented details."""
        how = "" if self.tracked else " (no tracking)"
        out = [f"replay {self.recording} with {self.method}{how}: {self.telemetry.frames} "
               f"frames in {self.elapsed_s:.2f} s -> {self.poses_path}"]
        out += ["  " + line for line in self.telemetry.summary() + list(self.link)
                + list(self.fusion)]
        if self.accuracy is not None:
            out.append("  against truth.csv:")
            out += ["    " + line for line in self.accuracy.lines()]
        if self.overlays:
            out.append(f"  {self.overlays} overlays written")
        if self.report is not None:
            out.append(f"  report: {self.report}")
        return out


def replay(recording: str | Path, out_dir: str | Path | None = None,
           rig: Rig | str | Path | None = None, site: Site | str | Path | None = None,
           method: str | None = None, tum: bool = False, realtime: bool = False,
           track: bool = True, sinks: Sequence[PoseSink] = (),
           progress: Callable[[int, int], None] | None = None,
           options: Mapping[str, Any] | None = None, link: LinkConfig | None = None,
           clock: Callable[[], int] = time.monotonic_ns,
           overlays: str | Path | None = None, overlays_only_failures: bool = False,
           report: bool = False, start_pose: tuple[float, ...] | None = None,
           odometry: str | Path | None = None, ros2: Any = None,
           force: bool = False, limits: tuple[float, float] | None = None) -> ReplayResult:
    """Run the pipeline over a recording as fast as possible (or at recorded timing).

    Args:
        recording: the recording folder (SPEC §2).
        out_dir: where ``poses.csv`` (and ``poses.tum``) go; ``RECORDING/replay/`` by default.
        rig, site: files or objects replacing the recording's own.
        method: an estimator name, ``auto`` (every method of the site, fused:
            :mod:`~ceilkit.runtime.multi`), or ``None`` for the site's default.
        tum: also write ``poses.tum``.
        realtime: wait between frames as recorded.
        track: ``False``: no tracker; each frame is estimated with no prior.
        sinks: further pose sinks (after the link, the ROS 2 node and the poses file).
        progress: called as ``progress(done, total)`` after each frame.
        options: the estimator's options by name (values may be strings).
        link: also stream the poses over this link (the first sink, as live).
        clock: the clock of latencies and of ``realtime``.
        overlays: write each frame's overlay (:mod:`~ceilkit.runtime.viz.overlay`) here
            as ``NNNNNN.png``; ``overlays_only_failures``: only failures and frames of
            quality below 0.5.
        report: also write ``OUT/report.html`` (:mod:`~ceilkit.runtime.viz.report`);
            with ``tum`` and a ``truth.csv``, ``truth.tum`` is written beside ``poses.tum``.
        start_pose: ``(x_m, y_m, yaw_rad[, sigma_m, sigma_rad])``: the first prior.
        limits: the vehicle's maximum ``(m/s, rad/s)`` (``--max-speed``; docs/config.md).
        odometry: an ``odometry.csv`` replacing the recording's own; the rows are fed
            to the fusion (``auto``) at their stamps.
        ros2: a :class:`~ceilkit.runtime.io.ros2.Ros2Config`: also publish on ROS 2
            (stamps are the recording's) and take ``/initialpose`` and odometry in.

    ``recording`` may be an ``.mcap`` file (:mod:`~ceilkit.runtime.io.mcap_rec`); its
    default output folder is then ``NAME.replay/`` beside it.

    Raises:
        ConfigError: a broken recording, rig, site, method or option; an existing output
            without ``force`` (which replaces it); one over an input or another output.
        LinkError, OutputError: a link or output that cannot be opened or written (or
            another run's lock on ``out_dir``).
    """
    out = Path(out_dir) if out_dir is not None else replay_folder(recording)
    _check_given(rig, site, odometry)   # a missing input is said before an existing output
    with contextlib.ExitStack() as locked:  # the output folders locked to the end
        check_replay_outputs(recording, out, rig, site, link, tum, force, overlays,
                             report, odometry, locked)
        rec = open_recording(recording, rig=rig, site=site)
        check_inputs(rec.rig, rec.site, link)   # before the method's loops load
        odo = load_odometry(odometry) if odometry is not None else rec.odometry
        estimator, tracker = make_localizer(  # --ros2: the same method
            method, rec.rig, rec.site, options, start_pose, odo is not None and track,
            limits=limits)
        tracker = tracker if track else None
        poses_path = out / "poses.csv"
        tap, views = _views(estimator, rec, overlays, overlays_only_failures, report)
        if tum and rec.truth is not None:
            write_truth_tum(rec.truth, out / "truth.tum")
        meter = None if rec.truth is None else AccuracyMeter(rec.truth)
        with PoseWriter(poses_path, out / "poses.tum" if tum else None) as writer, \
                opened_link(link, rec.rig, rec.site) as the_link, \
                contextlib.ExitStack() as stack:
            pipeline = build_pipeline(
                tap or estimator, tracker, link=the_link,
                ros2=None if ros2 is None else _open_ros2(ros2, tracker, stack, rec, odo),
                poses=PoseFileSink(writer, clock), more=sinks, meter=meter, clock=clock)
            res = _run(rec, pipeline, realtime, progress, clock,
                       None if tap is None else (tap, views), odo)
        result = ReplayResult(rec.folder, poses_path, estimator.name, pipeline.telemetry,
                              meter.result() if meter is not None else None, res[0], track,
                              tuple(link_lines(the_link)) + _node_lines(pipeline), None,
                              0 if views is None else views.written,
                              tuple(res[1].lines()) if res[1] is not None else ())
        return _with_report(result, views, out) if report else result


def _check_given(*given: Any) -> None:
    """Refuse a file given by path (``--rig``, ``--site``, ``--odometry``) that is not
    there (``ConfigError`` naming it)."""
    for g in given:
        if isinstance(g, str | Path) and not Path(g).exists():
            raise ConfigError(Path(g), None, "file not found")


def _with_report(result: ReplayResult, views: Any, out: Path) -> ReplayResult:
    """``result`` once ``OUT/report.html`` is written from ``views``."""
    path = views.write_report(out / "report.html", f"replay of {result.recording.name}",
                              result.lines())
    return dataclasses.replace(result, report=path)


def _open_ros2(config: Any, tracker: Any, stack: contextlib.ExitStack, rec: Any,
               odometry: Odometry | None) -> Any:
    """The ROS 2 node of a replay; the recording's odometry, when the fusion takes it,
    integrated into its ``odom`` frame (``map → odom → base_link``)."""
    node = open_ros2(config, tracker, stack, rig=rec.rig, site=rec.site)
    if odometry is not None and isinstance(tracker, Fusion):
        for k in range(len(odometry)):
            node.add_odometry(int(odometry.t_ns[k]), float(odometry.dx_m[k]),
                              float(odometry.dy_m[k]), float(odometry.dyaw_rad[k]))
    return node


def _node_lines(pipeline: Pipeline) -> tuple[str, ...]:
    """The report line of the pipeline's ROS 2 node, if it has one."""
    return tuple(s.describe() for s in pipeline.sinks if isinstance(s, Ros2Node))


def _views(estimator: Any, rec: Recording, overlays: str | Path | None,
           only_failures: bool, report: bool
           ) -> tuple[EstimateTap | None, ReplayViews | None]:
    """The tap on ``estimator`` and the views it feeds (overlays, the report's frames),
    or ``(None, None)`` when neither is asked for."""
    if overlays is None and not report:
        return None, None
    return EstimateTap(estimator), ReplayViews(
        rec.rig, rec.site, Path(overlays) if overlays is not None else None,
        only_failures, rec.truth)


def check_replay_outputs(recording: str | Path, out: Path, rig: Any, site: Any,
                         link: LinkConfig | None, tum: bool, force: bool,
                         overlays: str | Path | None = None, report: bool = False,
                         odometry: str | Path | None = None,
                         stack: contextlib.ExitStack | None = None) -> None:
    """Refuse, before anything is read or written, a replay that would overwrite an
    output without ``force`` (``OUT/poses.csv``, ``run.yaml``, ``poses.tum``,
    ``truth.tum``, ``report.html``, an overlay, a ``--serial`` file), write over or
    inside one of its own inputs (a link to ``REC/truth.csv`` or
    ``REC/frames/000000.png``, overlays into ``REC/frames``), or write two outputs into
    one file (a link to ``OUT/poses.csv``); with ``stack``, lock ``OUT``, the overlays'
    folder and a ``--serial`` file until it closes
    (:func:`~ceilkit.runtime.io.outputs.claim_outputs`).

    Raises:
        ConfigError: naming the existing file (and ``force=True``), or keyed by the
            output's parameter (``out``, ``link``, ``overlays``) and naming the input.
        OutputError: another run is writing into ``OUT`` or the overlays' folder.
    """
    recording = Path(recording)
    if not recording.exists():      # before any output folder (or its lock) is made
        raise ConfigError(recording, None, "not a recording folder (not found)")
    inputs = recording_inputs(recording)
    inputs += [Path(p) for p in (rig, site, odometry) if isinstance(p, str | Path)]
    truth = is_mcap(recording) or (recording / "truth.csv").exists()
    outputs = {"out": [out / "poses.csv", out / RUN_METADATA]
               + ([out / "poses.tum"] if tum else [])
               + ([out / "truth.tum"] if tum and truth else [])
               + ([out / "report.html"] if report else [])}
    folders = {"out": [out]}
    if overlays is not None:
        folders["overlays"] = [Path(overlays)]
        outputs["overlays"] = overlay_files(Path(overlays))
    if link is not None and link.target != "-" and not is_serial_path(link.target):
        outputs["link"] = [Path(link.target)]
    claim_outputs(outputs, folders=folders, inputs=inputs, force=force, stack=stack)


def overlay_files(folder: Path) -> list[Path]:
    """The overlays already in ``folder`` (``NNNNNN.png``): a replay's would replace them."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob("*.png") if len(p.stem) == 6 and p.stem.isdigit())


def _run(rec: Recording, pipeline: Pipeline, realtime: bool,
         progress: Callable[[int, int], None] | None,
         clock: Callable[[], int], viewed: tuple[EstimateTap, ReplayViews] | None = None,
         odometry: Odometry | None = None) -> tuple[float, FusionReport | None]:
    """Every frame of ``rec`` through ``pipeline``: the elapsed time and the fusion's
    report (a fusion run); ``viewed``: each frame's raw estimate (from the tap) handed to
    the views too; ``odometry``: rows fed to the fusion up to each frame."""
    fusion = pipeline.tracker if isinstance(pipeline.tracker, Fusion) else None
    fused = FusionReport(fusion, rec.truth) if fusion is not None else None
    fed = damaged = 0
    n = len(rec)
    start = clock()
    t_first = int(rec.t_ns[0]) if n else 0
    for k in range(n):
        frame = rec.frame(k)
        if fusion is not None and odometry is not None:
            fed = fusion.feed(odometry, fed, frame.t_ns)
        if realtime:
            due = start + (frame.t_ns - t_first)
            wait = due - clock()
            if wait > 0:
                time.sleep(wait / 1e9)
        est = pipeline.process(frame, capture_ns=clock())
        if frame.damage and (damaged := damaged + 1) <= DAMAGE_LINES:
            log.warning("frame %d: %s: no pose from it (bad_frame)", k, frame.damage)
        if fused is not None:
            fused.add(est)
        if viewed is not None:  # a damaged frame never reached the tap: no image
            image, raw = (None, est) if frame.damage else viewed[0].latest
            viewed[1].frame(k, image, raw, est, pipeline.telemetry.latency_ms[-1])
        if progress is not None:
            progress(k + 1, n)
    return (clock() - start) / 1e9, fused
