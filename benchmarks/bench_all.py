"""One run of every method, baseline and reference kernel, interleaved frame by frame.

The frames come from SPEC recordings made outside the estimators' code paths: by
``ceilkit.calib.simulate.simulate_recording`` (what ``ceilcal simulate`` runs) into
``benchmarks/out/recordings/`` (kept between runs; ``--fresh`` writes them again), then
read back with ``ceilkit.runtime.io.recording.Recording`` from their own ``rig.yaml``
and ``site.yaml``, as data from another tool would be. ``--recording DIR`` adds any
other SPEC recording with a ``truth.csv``.

For every frame, in one process on one OpenCV thread (``cv2.setNumThreads(1)``), every
entry is called once, in an order rotated from frame to frame (so no entry always
runs first, with the caches warm or cold after another); **every call** is timed with
``time.perf_counter_ns`` and the median and the 95th percentile of all calls are
reported (no best-of-N: a shared machine slows calls down, and that is part of what a
vehicle sees too; compare the ratios measured in one run). PNG decoding is not timed:
the frames are decoded once before the loop.

Entries per recording:

* **methods** without a prior (every frame on its own, the ``--no-track`` path), and
  ``lights`` with its other spot stage (``spot_stage=windowed``); with ``--detectors``
  also the corridor's global path with each other line detector, and with its
  full-resolution search alone (``coarse_search=false``);
* **methods with a prior**: the estimator's ``window_search`` option on (the default),
  the prior from the project's :class:`~ceilkit.runtime.tracking.Tracker` fed by that
  entry's own estimates (as ``ceilrun`` runs it), so a lost track falls back to the
  global path and is counted in the timing;
* **baselines** (``paper-corridor``, ``paper-lights``, ``paper-block``;
  ``paper-lights`` with both centroid readings when it has the option);
* **reference kernels**: a full-frame memory pass (``cv2.mean``), the line
  detectors alone (FastLineDetector as the corridor estimator configures it, and on
  the frame decimated by 2 as its coarse search runs it; FastLineDetector's defaults,
  LSD, EdgeDrawing, all on the full frame), one global threshold plus
  ``connectedComponentsWithStats``, the spot stage's Niblack mask and the windowed
  stage's (on the frame decimated by 2), and for blocks the quad search's
  decimation, threshold and ``findContours``.

The recordings: a corridor drive, a lights drive, a drive along configs/block's
blocks and markers (a site with ``blocks`` or ``markers`` runs the ``block`` method,
its ``block +prior`` entry the window path of docs/methods/block.md), and two
tiled-ceiling drives at 640x480 (issue 38, :func:`tiled_recordings`): ``tiles``, a plain
0.6 m tile grid under configs/block's upward camera (the corridor method; every frame
is ``ambiguous`` without a prior, so its entries with a prior start from the drive's
first true pose, as ``--start-pose`` does), and ``tiles_markers``, the issue's
wide-angle view of tiles with a hatch and 16 cm AprilTags (the block method).

Accuracy per method entry: yaw error and lateral (corridor) or position (lights,
block) error against ``truth.csv``, median and p95 over the frames estimated (a
block frame's heading-only cue is not counted as estimated), and the share of
frames estimated. On a block site, each entry's median and p95 are also given over the
frames with a marker or an asymmetric block fully in view (from the truth, as
``bench_block.py`` counts them: 3 px inside the frame; a symmetric block alone is
``ambiguous`` without a prior), the frames issue 11's 2 ms is about.

Output: a table on stdout and ``benchmarks/out/bench_all.csv`` (``--out``), whose
``#`` header lines give the provenance: date, command, git commit, Python, NumPy and
OpenCV versions, CPU model, OpenCV threads, load average before and after.

    .venv/bin/python benchmarks/bench_all.py [--frames 200] [--fresh] [--recording DIR]\
        [--detectors]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from bench_ambiguity import loop, small_markers, tiles_site
from bench_block import in_view, targets
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.estimators.odometry import PlaneOdometry
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.spots import niblack_mask
from ceilkit.runtime.features.working import decimate
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, straight_drive
from ceilkit.runtime.tracking import Tracker

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
CONFIGS = ROOT / "configs"


# ----------------------------------------------------------------------------- data
def make_recordings(folder: Path, frames: int, fresh: bool) -> list[Path]:
    """The two simulated drives (corridor, lights) as SPEC recordings in ``folder``."""
    out = []
    specs = [
        # a weaving drive down the corridor, 30 fps, 0.8 m/s, heading wobble 4 deg
        ("corridor", dict(speed_mps=0.8, x0_m=0.0, y_m=0.1, weave_m=0.25,
                          yaw_wobble_rad=math.radians(4.0))),
        # a drive across the hall at 30 deg, 0.8 m/s
        ("lights", dict(speed_mps=0.8, x0_m=2.0, y_m=-2.5, yaw_rad=math.radians(30.0),
                        weave_m=0.3)),
        # along configs/block's blocks and markers, 0.8 m/s, weaving 0.2 m
        ("block", dict(speed_mps=0.8, x0_m=0.3, y_m=0.0, weave_m=0.2)),
    ]
    for name, kw in specs:
        rec = _fresh(folder / f"{name}_{frames}", fresh)
        if not rec.exists():
            rig = Rig.load(CONFIGS / name / "rig.yaml")
            site = Site.load(CONFIGS / name / "site.yaml")
            traj = straight_drive(frames, 30.0, rng=np.random.default_rng(5), **kw)
            simulate_recording(rig, site, traj, rec,
                               SimOptions(noise_sigma=2.0, blur_px=0.8), seed=7)
        out.append(rec)
    return out + tiled_recordings(folder, frames, fresh)


def _fresh(rec: Path, fresh: bool) -> Path:
    """``rec``, deleted first when ``fresh``."""
    if rec.exists() and fresh:
        for p in sorted(rec.rglob("*"), reverse=True):
            p.unlink() if p.is_file() else p.rmdir()
        rec.rmdir()
    return rec


def tiled_recordings(folder: Path, frames: int, fresh: bool) -> list[Path]:
    """The tiled-ceiling drives (issue 38), 640x480, noise 2, blur 0.8: ``tiles``, a
    plain 0.6 m drop-tile grid (``corridor`` lines along and across every 0.6 m) under
    configs/block's upward camera, driven round a loop at 10 fps (the corridor method:
    bench_ambiguity's ``tiles`` case, every frame ``ambiguous`` without a prior); and
    ``tiles_markers``, the issue's wide-angle view (f = 310 px) of tiles with a hatch and
    five 16 cm AprilTags at about 3.2 px a cell (the block method:
    ``bench_tiles_markers.py``'s rig, site and loop)."""
    out = []
    rec = _fresh(folder / f"tiles_{frames}", fresh)
    if not rec.exists():
        folder.mkdir(parents=True, exist_ok=True)
        site = Site.load(tiles_site(folder))          # folder/tiles.yaml
        simulate_recording(Rig.load(CONFIGS / "block" / "rig.yaml"), site,
                           loop(frames, 10.0, 1.0, 0.0, 1.5, 0.4), rec,
                           SimOptions(noise_sigma=2.0, blur_px=0.8), seed=7)
    out.append(rec)
    rec = _fresh(folder / f"tiles_markers_{frames}", fresh)
    if not rec.exists():
        rig, site, traj = small_markers(frames)
        simulate_recording(rig, site, traj, rec, SimOptions(noise_sigma=2.0, blur_px=0.8),
                           seed=7)
    out.append(rec)
    return out


@dataclass
class Data:
    """A recording read back: its rig, site, grey frames, stamps and truth."""

    name: str
    rig: Rig
    site: Site
    grey: list[np.ndarray]
    t_ns: list[int]
    truth: np.ndarray            # (N, 3) x, y, yaw_rad
    in_view: np.ndarray | None = None   # (N,) an asymmetric target fully in view (blocks)
    start: bool = False          # the tracked entries start from the first true pose


def load(folder: Path) -> Data:
    rec = Recording(folder)
    if rec.truth is None:
        raise SystemExit(f"{folder}: no truth.csv")
    grey, stamps, truth = [], [], []
    for k in range(len(rec)):
        f = rec.frame(k)
        pose = rec.truth.lookup(f.t_ns)
        if pose is None:
            continue
        grey.append(np.ascontiguousarray(to_grey(f.image)))
        stamps.append(int(f.t_ns))
        truth.append(pose)
    truth_a = np.array(truth, float)
    seen = None
    if rec.site.has_section("blocks") or rec.site.has_section("markers"):
        geo, tg = PlanarGeometry.of(rec.rig, rec.site), targets(rec.site)
        seen = np.array([any(not sym for _, sym in in_view(rec.rig, geo, tg, pose))
                         for pose in truth_a])
    # a plain tile grid is ambiguous without a prior (issue 36): the entries with a
    # prior start from the drive's first pose, as ``--start-pose`` does
    start = folder.name.startswith("tiles_") and seen is None
    return Data(folder.name, rec.rig, rec.site, grey, stamps, truth_a, seen, start)


# ----------------------------------------------------------------------------- entries
@dataclass
class Entry:
    """One timed thing: ``call(k)`` runs it on frame k and returns what it returns."""

    name: str
    kind: str                               # method | tracked | baseline | stage | kernel
    call: Callable[[int], object]
    times_ns: list[int] = field(default_factory=list)
    results: list[object] = field(default_factory=list)
    keep: bool = False                      # keep results (estimates) for accuracy
    reset: Callable[[], None] | None = None  # forget any track (after the warm-up)


def method_entry(name: str, kind: str, est, data: Data, track: bool) -> Entry:
    tracker = Tracker() if track else None

    def call(k: int):
        prior = tracker.predict(data.t_ns[k]) if tracker is not None else None
        out = est.estimate(data.grey[k], data.t_ns[k], prior)
        if tracker is not None:
            tracker.update(out)
        return out

    def reset() -> None:
        tracker.reset()
        if data.start:
            tracker.set_start_pose(data.t_ns[0], *data.truth[0])

    return Entry(name, kind, call, keep=True, reset=None if tracker is None else reset)


def has_option(est_cls_options, name: str) -> bool:
    return name in {f.name for f in dataclasses.fields(est_cls_options)}


DETECTOR_VARIANTS = (("detector=lsd", {"detector": "lsd"}), ("detector=ed", {"detector": "ed"}),
                     ("detector=hough", {"detector": "hough"}),
                     ("full-resolution search only", {"coarse_search": False}))
"""``--detectors``: the corridor's global path with each other line detector (the
coarse search first, as by default), and with the full-frame search alone."""


def entries(data: Data, detectors: bool = False) -> list[Entry]:
    g = data.grey
    rig, site = data.rig, data.site
    out: list[Entry] = []
    is_block = site.has_section("blocks") or site.has_section("markers")
    is_corridor = site.corridor is not None and not is_block
    main = "block" if is_block else "corridor" if is_corridor else "lights"
    est = make_estimator(main, rig, site, stated(main))
    out.append(method_entry(main, "method", est, data, False))
    if has_option(type(est.options), "window_search"):
        tracked = make_estimator(main, rig, site, stated(main, {"window_search": True}))
        out.append(method_entry(f"{main} +prior", "tracked", tracked, data, True))
    if has_option(type(est.options), "spot_stage"):      # the other spot stage
        out.append(method_entry(f"{main} spot_stage=windowed", "method",
                                make_estimator(main, rig, site, {"spot_stage": "windowed"}),
                                data, False))
    glob = {"window_search": False} if has_option(type(est.options), "window_search") else {}
    out.append(method_entry(f"{main} +prior (global)", "tracked-global",
                            make_estimator(main, rig, site, stated(main, glob)), data, True))
    if is_corridor and detectors:
        for label, opts in DETECTOR_VARIANTS:
            variant = make_estimator(main, rig, site, stated(main, opts))
            out.append(method_entry(f"{main} {label}", "method", variant, data, False))
    paper = make_estimator(f"paper-{main}", rig, site, None)
    out.append(method_entry(f"paper-{main}", "baseline", paper, data, False))
    if main == "lights" and has_option(type(paper.options), "weighted"):
        for w in (False, True):
            out.append(method_entry(f"paper-lights weighted={w}", "baseline",
                                    make_estimator("paper-lights", rig, site, {"weighted": w}),
                                    data, False))
    # reference kernels
    out.append(Entry("kernel: cv2.mean (full-frame pass)", "kernel",
                     lambda k: cv2.mean(g[k])))
    if is_block:
        def thr_contours(k: int):     # the quad search's kernels on the decimated frame
            small = cv2.resize(g[k], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
            _, m = cv2.threshold(small, 100, 255, cv2.THRESH_BINARY_INV)
            return cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)

        out.append(Entry("kernel: decimate + threshold + findContours", "kernel",
                         thr_contours))
        # the stage between blocks: one ceiling-plane odometry step per frame (from the
        # previous frame), as the block method runs it on frames without a fix
        odo = PlaneOdometry(PlanarGeometry.of(rig, site), site)
        out.append(Entry("block: ceiling-plane odometry step", "stage",
                         lambda k: odo.step(g[k]), reset=odo.reset))
    elif is_corridor:
        det = est.detector
        out.append(Entry(f"kernel: {det.method} alone (as configured)", "kernel",
                         lambda k: det(g[k])))
        coarse = getattr(est, "coarse_detector", None)
        if coarse is not None:
            out.append(Entry(f"kernel: {coarse.method} on the frame decimated by "
                             f"{coarse.factor} (the coarse search)", "kernel",
                             lambda k: coarse(g[k])))
        fld = cv2.ximgproc.createFastLineDetector()
        out.append(Entry("kernel: FastLineDetector default, full frame", "kernel",
                         lambda k: fld.detect(g[k])))
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        out.append(Entry("kernel: LSD, full frame", "kernel", lambda k: lsd.detect(g[k])))
        if hasattr(cv2.ximgproc, "createEdgeDrawing"):
            ed = cv2.ximgproc.createEdgeDrawing()

            def edlines(k: int):
                ed.detectEdges(g[k])
                return ed.detectLines()

            out.append(Entry("kernel: EdgeDrawing/EDLines, full frame", "kernel", edlines))
    else:
        def thr_cc(k: int):
            _, m = cv2.threshold(g[k], 200, 255, cv2.THRESH_BINARY)
            return cv2.connectedComponentsWithStats(m, connectivity=8)

        out.append(Entry("kernel: threshold + connectedComponentsWithStats", "kernel", thr_cc))
        out.append(Entry("kernel: Niblack mask (spot stage)", "kernel",
                         lambda k: niblack_mask(g[k])))
        out.append(Entry("kernel: decimate by 2 + Niblack mask (windowed stage)", "kernel",
                         lambda k: niblack_mask(decimate(g[k], 2), 21)))
    return out


def run(data: Data, ents: list[Entry], warmup: int = 3, cpu_time: bool = False) -> None:
    """Every entry on every frame, interleaved, the order rotated per frame; timed by the
    wall clock, or with ``cpu_time`` by this thread's CPU time (``time.thread_time_ns``:
    what the call itself spent, without the time other processes held the core)."""
    for k in range(min(warmup, len(data.grey))):
        for e in ents:
            e.call(k)
    for e in ents:                       # the tracked entries start over after warm-up
        if e.reset is not None:
            e.reset()
    n = len(ents)
    clock = time.thread_time_ns if cpu_time else time.perf_counter_ns
    for k in range(len(data.grey)):
        r = k % n
        for e in ents[r:] + ents[:r]:
            t = clock()
            res = e.call(k)
            e.times_ns.append(clock() - t)
            if e.keep:
                e.results.append(res)


# ----------------------------------------------------------------------------- report
def accuracy(e: Entry, data: Data) -> dict[str, float]:
    yaw_e, pos_e, ok = [], [], 0
    for res, (x, y, yaw) in zip(e.results, data.truth, strict=True):
        if not res or (res.x_m is None and res.y_m is None):   # a heading-only cue
            continue
        ok += 1
        yaw_e.append(abs(math.degrees(math.remainder(res.yaw_rad - yaw, 2 * math.pi))))
        if res.x_m is not None:
            pos_e.append(1e3 * math.hypot(res.x_m - x, res.y_m - y))
        else:
            pos_e.append(1e3 * abs(res.y_m - y))
    n = len(e.results)

    def q(a: list[float], p: float) -> float:
        return float(np.percentile(a, p)) if a else float("nan")

    return {"ok_share": ok / n if n else float("nan"),
            "yaw_err_med_deg": q(yaw_e, 50), "yaw_err_p95_deg": q(yaw_e, 95),
            "pos_err_med_mm": q(pos_e, 50), "pos_err_p95_mm": q(pos_e, 95)}


def git_commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        return "?"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"


def provenance(script: str, load_before: tuple[float, float, float],
               load_after: tuple[float, float, float], notes: list[str]) -> list[str]:
    """The ``#`` header of a benchmark's CSV: date, command, versions, CPU and OpenCV
    threads, the load average before and after (a shared machine), then ``notes``."""
    return [
        f"# {script}: {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}",
        f"# command: {' '.join(sys.argv)}",
        f"# git: {git_commit()}  python {platform.python_version()}  numpy {np.__version__}"
        f"  opencv {cv2.__version__}",
        f"# cpu: {cpu_model()} x {os.cpu_count()}  opencv threads {cv2.getNumThreads()}",
        f"# load average before {load_before[0]:.2f} {load_before[1]:.2f} "
        f"{load_before[2]:.2f}, after {load_after[0]:.2f} {load_after[1]:.2f} "
        f"{load_after[2]:.2f} (a shared machine: read the ratios)",
        *notes]


COLUMNS = ["recording", "entry", "kind", "calls", "median_ms", "p95_ms", "mean_ms",
           "median_in_view_ms", "p95_in_view_ms",
           "ratio_to_mean_pass", "ratio_to_line_detector", "ok_share", "yaw_err_med_deg",
           "yaw_err_p95_deg", "pos_err_med_mm", "pos_err_p95_mm"]


def rows_of(data: Data, ents: list[Entry]) -> list[dict[str, object]]:
    med = {e.name: 1e-6 * float(np.median(e.times_ns)) for e in ents}
    ref_mean = next(v for k, v in med.items() if k.startswith("kernel: cv2.mean"))
    ref_det = next((v for k, v in med.items() if "alone (as configured)" in k), float("nan"))
    rows = []
    for e in ents:
        t = 1e-6 * np.asarray(e.times_ns, float)
        row: dict[str, object] = {
            "recording": data.name, "entry": e.name, "kind": e.kind, "calls": t.size,
            "median_ms": float(np.median(t)), "p95_ms": float(np.percentile(t, 95)),
            "mean_ms": float(t.mean()), "ratio_to_mean_pass": float(np.median(t)) / ref_mean,
            "ratio_to_line_detector": float(np.median(t)) / ref_det}
        if data.in_view is not None and data.in_view.any() and t.size == data.in_view.size:
            # issue 11's figure: the frames with a block or marker fully in view
            row["median_in_view_ms"] = float(np.median(t[data.in_view]))
            row["p95_in_view_ms"] = float(np.percentile(t[data.in_view], 95))
        if e.keep:
            row.update(accuracy(e, data))
        rows.append(row)
    return rows


def fmt(v: object) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200, help="frames per simulated drive")
    ap.add_argument("--fresh", action="store_true", help="write the recordings again")
    ap.add_argument("--recording", type=Path, action="append", default=[],
                    help="also run on this SPEC recording (with truth.csv)")
    ap.add_argument("--detectors", action="store_true",
                    help="also the corridor's global path with LSD, EDLines, Hough, and "
                         "with its full-resolution search alone (coarse_search=false)")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time each call by the thread's CPU time, not the wall clock (a "
                         "machine shared with other jobs)")
    ap.add_argument("--out", type=Path, default=OUT / "bench_all.csv")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    recs = make_recordings(OUT / "recordings", args.frames, args.fresh) + args.recording
    all_rows: list[dict[str, object]] = []
    for folder in recs:
        data = load(folder)
        ents = entries(data, args.detectors)
        t0 = time.perf_counter()
        run(data, ents, cpu_time=args.cpu_time)
        rows = rows_of(data, ents)
        all_rows += rows
        print(f"== {data.name}: {len(data.grey)} frames "
              f"{data.grey[0].shape[1]}x{data.grey[0].shape[0]}, {len(ents)} entries "
              f"interleaved ({time.perf_counter() - t0:.0f} s)")
        if data.in_view is not None:
            print(f"(a marker or an asymmetric block fully in view in "
                  f"{int(data.in_view.sum())} of {data.in_view.size} frames: 'in view' is "
                  "the median over those)")
        print(f"{'entry':48s} {'med ms':>8s} {'p95 ms':>8s} {'in view':>8s} {'x det':>6s} "
              f"{'ok':>5s} {'yaw med/p95 deg':>17s} {'pos med/p95 mm':>16s}")
        for r in rows:
            acc = ""
            if "ok_share" in r:
                acc = (f"{r['ok_share']:5.2f} {r['yaw_err_med_deg']:8.4f}/"
                       f"{r['yaw_err_p95_deg']:<8.4f} {r['pos_err_med_mm']:7.2f}/"
                       f"{r['pos_err_p95_mm']:<7.2f}")
            print(f"{r['entry']:48s} {r['median_ms']:8.3f} {r['p95_ms']:8.3f} "
                  f"{fmt(r.get('median_in_view_ms', float('nan'))):>8s} "
                  f"{fmt(r['ratio_to_line_detector']):>6s} {acc}", flush=True)
    load_after = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    header = provenance("bench_all.py", load_before, load_after, [
        f"# every call timed ({'thread_time_ns: CPU' if args.cpu_time else 'perf_counter_ns: wall'}"
        " time), entries interleaved frame by frame in one process; times in ms; errors "
        "against truth.csv"])
    lines = header + [",".join(COLUMNS)]
    for r in all_rows:
        lines.append(",".join(fmt(r.get(c, float("nan"))) for c in COLUMNS))
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(header[2:5]))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
