"""Benchmark of the corridor estimators on simulated frames: ms per frame and accuracy.

Runs ``corridor`` (ours; optionally each segment detector) and ``paper-corridor`` on
the same simulated frames of configs/corridor (camera 2.0 m below the ceiling) at
640x480 and 1280x720 (``CameraModel.scaled``), noise sigma 2 grey levels, blur 0.8 px,
heading +-40 deg, lateral position +-``--lateral`` m, and prints for each: the median /
p95 heading and lateral errors, the share of frames estimated, the share estimated
of the frames with two or more forward lines in view at the true pose (the site's
``lines_along`` projected through the rig: a visible stretch of at least the
estimator's ``min_length_px``; a lamp edge only where its lamps are), and the
median / p95 milliseconds per frame.

OpenCV runs on one thread (``cv2.setNumThreads(1)``): the times are one core's. Every
call is timed and the median and p95 are of all calls (``--repeat`` calls per frame,
default 1; never the fastest of them: a shared machine slows calls down and the ratios
measured in one run are what to read). The line detector alone (FLD, as the estimator
configures it) is timed on the same frame right after each estimator call, interleaved
in the same loop, and its median is printed beside each estimator's
(``benchmarks/bench_all.py`` times every method, baseline and kernel that way).

The 640x480 frames are also written as a SPEC recording by
``ceilkit.calib.simulate.simulate_recording`` (PNG frames, ``truth.csv``) and read
back with ``ceilkit.runtime.io.recording.Recording``, as data from outside the project
would be; ``--recording DIR`` runs on an existing recording (with ``truth.csv``)
instead.

``--chord-px 48,96,144 --recording DIR`` instead runs the window search
(``window_search=true``, the prior from the project's ``Tracker`` fed by each entry's own
estimates) with each chord length (``track.CHORD_PX``) on a recorded drive, the entries
interleaved frame by frame, every call timed by the thread's CPU time: how the time and
the accuracy move with the number of chords searched.

    .venv/bin/python benchmarks/bench_corridor.py [--frames 60] [--clutter] [--detectors]
        [--lateral 0.8] [--recording DIR] [--repeat 3] [--chord-px 48,96]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.corridor import CorridorEstimator, track, visible_along_lines
from ceilkit.runtime.estimators.corridor.track import CHORD_PX
from ceilkit.runtime.estimators.paper_corridor import PaperCorridorEstimator
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory, render_frame
from ceilkit.runtime.tracking import Tracker

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "corridor"


def timed(fn, repeat: int):
    """``(result, [seconds of every call])``: ``repeat`` calls, all of them timed."""
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        r = fn()
        out.append(time.perf_counter() - t)
    return r, out


def run(est, frames, in_view: np.ndarray, repeat: int, detector=None) -> str:
    """One estimator over ``frames`` ``[(x, y, yaw, image)]``; ``in_view`` (N,) bool:
    two or more forward lines in view; ``detector``: a line detector timed on each
    frame right after the estimator (interleaved)."""
    errs, times, det_times, fails, ok = [], [], [], {}, []
    for *_, img in frames[:3]:          # warm-up (first calls allocate)
        est.estimate(img, 0)
    for _x, y, yaw, img in frames:
        r, dt = timed(lambda img=img: est.estimate(img, 0), repeat)
        times += dt
        if detector is not None:
            g = to_grey(img)
            det_times += timed(lambda g=g: detector(g), repeat)[1]
        ok.append(bool(r))
        if r:
            errs.append((abs(math.degrees(math.remainder(r.yaw_rad - yaw, 2 * math.pi))),
                         abs(r.y_m - y) * 1e3))
        else:
            fails[r.reason] = fails.get(r.reason, 0) + 1
    e = np.array(errs).reshape(-1, 2)
    if e.shape[0] == 0:
        e = np.full((1, 2), np.nan)
    ok_a = np.array(ok)
    share = (f"{np.count_nonzero(ok_a & in_view)}/{np.count_nonzero(in_view)}"
             if np.any(in_view) else "-")
    return (f"ok {len(errs):3d}/{len(frames)}  >=2 in view {share:>7s}  heading deg med "
            f"{np.median(e[:, 0]):7.4f} p95 {np.percentile(e[:, 0], 95):7.4f}  lateral mm med "
            f"{np.median(e[:, 1]):7.2f} p95 {np.percentile(e[:, 1], 95):7.2f}  ms med "
            f"{1e3 * np.median(times):6.2f} p95 {1e3 * np.percentile(times, 95):6.2f}  "
            f"(detector alone, interleaved: {1e3 * np.median(det_times):5.2f})  "
            f"fails {fails}")


def report(rig: Rig, site: Site, frames, detectors: bool, title: str, repeat: int) -> None:
    ours = CorridorEstimator(rig, site, stated("corridor"))
    min_len = ours.detector.min_length_px
    in_view = np.array([np.count_nonzero(visible_along_lines(rig, site, x, y, yaw, min_len))
                        >= 2 for x, y, yaw, _ in frames])
    print(f"== {title}: {len(frames)} frames, {np.count_nonzero(in_view)} with >= 2 forward "
          "lines in view", flush=True)
    ests = [("corridor", ours)]
    if detectors:
        variants = [("fld+refine", {"refine": True}), ("no edge_fit", {"edge_fit": False}),
                    ("lsd", {"detector": "lsd"}), ("hough", {"detector": "hough"}),
                    ("ed", {"detector": "ed"})]
        ests += [(name, CorridorEstimator(rig, site, stated("corridor", opts)))
                 for name, opts in variants]
    ests.append(("paper-corridor", PaperCorridorEstimator(rig, site)))
    for name, est in ests:
        print(f"{name:15s} {run(est, frames, in_view, repeat, ours.detector)}", flush=True)


def recording_frames(folder: Path, rig: Rig | None = None, site: Site | None = None):
    """``(rig, site, [(x, y, yaw, image)])`` of a SPEC recording with ``truth.csv``."""
    rec = Recording(folder)
    if rec.truth is None:
        raise SystemExit(f"{folder}: no truth.csv")
    frames = []
    for k in range(len(rec)):
        f = rec.frame(k)
        pose = rec.truth.lookup(f.t_ns)
        if pose is not None:
            frames.append((*pose, f.image))
    return rec.rig, rec.site, frames


def chord_sweep(folder: Path, chord_px: list[float]) -> None:
    """The tracked path with each chord length on the drive recorded in ``folder``
    (module doc, ``--chord-px``)."""
    rec = Recording(folder)
    if rec.truth is None:
        raise SystemExit(f"{folder}: no truth.csv")
    frames = [rec.frame(k) for k in range(len(rec))]
    truth = [rec.truth.lookup(f.t_ns) for f in frames]
    grey = [to_grey(f.image) for f in frames]
    tracked = stated("corridor", {"window_search": True})
    ents = [(c, CorridorEstimator(rec.rig, rec.site, tracked), Tracker()) for c in chord_px]

    def call(c: float, est: CorridorEstimator, tr: Tracker, k: int):
        track.CHORD_PX = c
        out = est.estimate(grey[k], frames[k].t_ns, tr.predict(frames[k].t_ns))
        tr.update(out)
        return out

    for c, est, tr in ents:                        # warm-up, then start the tracks over
        for k in range(min(3, len(frames))):
            call(c, est, tr, k)
        tr.reset()
    times = {c: [] for c in chord_px}
    errs = {c: [] for c in chord_px}
    for k in range(len(frames)):
        r = k % len(ents)
        for c, est, tr in ents[r:] + ents[:r]:
            t = time.thread_time_ns()
            out = call(c, est, tr, k)
            times[c].append((time.thread_time_ns() - t) * 1e-6)
            if out and truth[k] is not None:
                _x, y, yaw = truth[k]
                errs[c].append((abs(math.degrees(math.remainder(out.yaw_rad - yaw,
                                                                2 * math.pi))),
                                abs(out.y_m - y) * 1e3))
    track.CHORD_PX = CHORD_PX
    print(f"== tracked path by chord length, {folder}, {len(frames)} frames, CPU time")
    for c in chord_px:
        e = np.array(errs[c]).reshape(-1, 2) if errs[c] else np.full((1, 2), np.nan)
        t = np.array(times[c])
        print(f"chord {c:5.0f} px  ok {len(errs[c]):3d}/{len(frames)}  heading deg med "
              f"{np.median(e[:, 0]):.4f} p95 {np.percentile(e[:, 0], 95):.4f}  lateral mm med "
              f"{np.median(e[:, 1]):.3f} p95 {np.percentile(e[:, 1], 95):.3f}  ms med "
              f"{np.median(t):.3f} p95 {np.percentile(t, 95):.3f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--lateral", type=float, default=0.8, help="|y| range of the poses, m")
    ap.add_argument("--clutter", action="store_true")
    ap.add_argument("--detectors", action="store_true",
                    help="also fld+refine, no edge_fit, lsd, hough")
    ap.add_argument("--recording", type=Path, help="run on this SPEC recording instead")
    ap.add_argument("--repeat", type=int, default=1,
                    help="call each frame this many times (every call is timed)")
    ap.add_argument("--chord-px", help="with --recording: the tracked path with each of "
                    "these chord lengths (comma-separated px)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.chord_px:
        if args.recording is None:
            raise SystemExit("--chord-px needs --recording DIR (a drive: the tracker's prior)")
        chord_sweep(args.recording, [float(v) for v in args.chord_px.split(",")])
        return
    print("OpenCV threads: 1 (cv2.setNumThreads(1)); times are one core's, median and p95 "
          f"of every call ({args.repeat} per frame)")
    if args.recording is not None:
        rig, site, frames = recording_frames(args.recording)
        report(rig, site, frames, args.detectors, f"recording {args.recording}", args.repeat)
        return
    rig0, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    rng = np.random.default_rng(args.seed)
    poses = [(rng.uniform(0, 3), rng.uniform(-args.lateral, args.lateral),
              math.radians(rng.uniform(-40, 40))) for _ in range(args.frames)]
    opts = SimOptions(noise_sigma=2.0, blur_px=0.8, clutter=args.clutter)
    for w, h in ((640, 480), (1280, 720)):
        rig = Rig(rig0.camera.scaled(w, h), rig0.mount)
        frames = [(x, y, yaw, render_frame(rig, site, x, y, yaw, options=opts, rng=rng))
                  for x, y, yaw in poses]
        report(rig, site, frames, args.detectors,
               f"{w}x{h}, clutter={args.clutter}, |y| <= {args.lateral} m", args.repeat)
        if w == 640:
            # the same poses through a SPEC recording on disk, read back
            p = np.array(poses)
            traj = Trajectory(np.arange(len(poses), dtype=np.int64) * 100_000_000,
                              p[:, 0], p[:, 1], p[:, 2])
            with tempfile.TemporaryDirectory() as tmp:
                folder = simulate_recording(rig, site, traj, Path(tmp) / "rec", opts,
                                            seed=args.seed)
                rrig, rsite, rframes = recording_frames(folder)
                report(rrig, rsite, rframes, False,
                       f"{w}x{h} SPEC recording (PNG, read back), clutter={args.clutter}",
                       args.repeat)


if __name__ == "__main__":
    main()
