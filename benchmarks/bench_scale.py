"""What the size of the light map costs the ``lights`` method (issue 38).

The frames: the lights drive of ``bench_all.py`` (``configs/lights``, 40 irregular
lights on a 3 m ceiling; a drive across the hall at 30 deg, 0.8 m/s), written as a SPEC
recording by ``ceilkit.calib.simulate.simulate_recording`` into
``benchmarks/out/recordings/lights_<frames>`` and read back with ``Recording``. The
maps: the recording's own lights, and the same with an irregular field of lights beside
the hall (a 1.6 m grid, each light moved by up to 0.4 m on each axis, seeded; filled
from its corner square by square, so a smaller field is the corner of a larger one), up
to 100 000 lights in all, 12 m from the hall: no frame of the hall drive sees the field,
and every map must give the same poses. A second drive (``field``), the same drive 8 m
inside the field's corner (rendered from the smallest map that holds 1 000 field
lights), runs on the maps that hold its part of the field, the smallest the reference:
inside the field a frame's constellations are like many others (the hard case).

Per map, in a fresh process (``--child``): ``Site.load`` of its ``site.yaml`` and the
estimator's construction, each timed by the process's CPU time (``time.process_time``)
and the wall clock, and the resident memory (``VmRSS``) before and after the
construction and its peak during it (``VmHWM``, started over from the resident memory
just before it).

Then per drive in one process on one OpenCV thread (``cv2.setNumThreads(1)``), for
every frame, each map's estimator (the global path: no prior) and the reference kernel
(one global threshold plus ``connectedComponentsWithStats``, as ``bench_all.py`` runs
it) are called once, in an order rotated from frame to frame; every call is timed by
this thread's CPU time (``time.thread_time_ns``). Reported per drive and map: the median
and p95 ms, the kernel's median, the ratio to it and to the drive's first map, the share
of frames estimated and the median position error against ``truth.csv``, and the
frames whose pose differs from the first map's by more than 1 mm.

Output: a table on stdout and ``benchmarks/out/bench_scale.csv`` (``--out``) with the
provenance header of ``bench_all.py``.

    .venv/bin/python benchmarks/bench_scale.py [--frames 30] [--sizes 40 1040 10040 100000]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import yaml
from bench_all import fmt, provenance

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.lights import LightsEstimator
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, straight_drive

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
FIELD_PITCH_M = 1.6
FIELD_JITTER_M = 0.4
FIELD_GAP_M = 12.0
FIELD_MAX_SIDE = 400                 # cells per side of the largest field (160 000)
KERNEL = "threshold + connectedComponentsWithStats"
FIELD_DRIVE_MIN = 1000   # field lights a map needs to hold the field drive's view
COLUMNS = ("drive", "lights", "parse_cpu_s", "parse_wall_s", "build_cpu_s", "build_wall_s",
           "rss_before_mb", "rss_after_mb", "rss_peak_mb", "median_ms", "p95_ms",
           "kernel_median_ms", "ratio_to_kernel", "ratio_to_smallest", "estimated_share",
           "pos_err_med_mm", "frames_differing")


def recording(frames: int, site_path: Path | None = None) -> Path:
    """The lights drive of ``bench_all.py`` (written once, then kept); with
    ``site_path`` (a site with a field) the same drive inside the field, 8 m from its
    corner, rendered from that site."""
    name = f"lights_{frames}" if site_path is None else f"lights_field_{frames}"
    rec = OUT / "recordings" / name
    if not rec.exists():
        rig = Rig.load(ROOT / "configs" / "lights" / "rig.yaml")
        hall = Site.load(ROOT / "configs" / "lights" / "site.yaml")
        x0, y0 = (2.0, -2.5) if site_path is None else field_origin(hall.lights_m) + 8.0
        site = hall if site_path is None else Site.load(site_path)
        traj = straight_drive(frames, 30.0, rng=np.random.default_rng(5), speed_mps=0.8,
                              x0_m=float(x0), y_m=float(y0), yaw_rad=math.radians(30.0),
                              weave_m=0.3)
        simulate_recording(rig, site, traj, rec, SimOptions(noise_sigma=2.0, blur_px=0.8),
                           seed=7)
    return rec


def field(lights_m: np.ndarray, n: int, seed: int = 3) -> np.ndarray:
    """``(n, 2)`` lights of an irregular field beside ``lights_m`` (+x of it): the cells
    of a :data:`FIELD_PITCH_M` grid from its corner outwards, square shell by shell,
    each light moved by a seeded draw of up to :data:`FIELD_JITTER_M` per axis (the same
    for every ``n``: a smaller field is the corner of a larger one)."""
    if n <= 0:
        return np.zeros((0, 2))
    side = int(math.ceil(math.sqrt(n)))
    gx, gy = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    first = np.lexsort((gy, gx, np.maximum(gx, gy)))[:n]
    jitter = np.random.default_rng(seed).uniform(-FIELD_JITTER_M, FIELD_JITTER_M,
                                                 (FIELD_MAX_SIDE, FIELD_MAX_SIDE, 2))
    g = np.stack([gx[first], gy[first]], 1)
    return (g * FIELD_PITCH_M + jitter[g[:, 0], g[:, 1]]) + field_origin(lights_m)


def field_origin(lights_m: np.ndarray) -> np.ndarray:
    """The field's corner: :data:`FIELD_GAP_M` beyond the hall's last light in x."""
    return np.array([lights_m[:, 0].max() + FIELD_GAP_M, lights_m[:, 1].min()])


def write_site(base: Path, n: int, out: Path) -> Path:
    """``base``'s site.yaml with its lights and a field beside them, ``n`` in all."""
    doc = yaml.safe_load(base.read_text())
    lights = np.asarray(doc.pop("lights"), float)
    every = np.concatenate([lights, field(lights, n - lights.shape[0])])
    head = yaml.safe_dump(doc, sort_keys=False)
    out.write_text(head + "lights:\n" + "".join(f"  - [{x:.4f}, {y:.4f}]\n"
                                                for x, y in every))
    return out


def rss_mb(key: str = "VmRSS") -> float:
    """This process's resident memory (``VmRSS``) or its peak (``VmHWM``), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def reset_peak() -> None:
    """Start the peak (``VmHWM``) over from the current resident memory (Linux 4.0+)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def child(rec: Path, site_path: Path) -> None:
    """Parse ``site_path`` and build the estimator in this (fresh) process; print the
    figures as one JSON line."""
    rig = Recording(rec).rig
    small = LightsEstimator(rig, Site.load(rec / "site.yaml"))   # imports, compiled code
    del small
    c0, w0 = time.process_time(), time.perf_counter()
    site = Site.load(site_path)
    c1, w1 = time.process_time(), time.perf_counter()
    before = rss_mb()
    reset_peak()
    est = LightsEstimator(rig, site)
    c2, w2 = time.process_time(), time.perf_counter()
    print(json.dumps({"lights": int(site.lights_m.shape[0]), "parse_cpu_s": c1 - c0,
                      "parse_wall_s": w1 - w0, "build_cpu_s": c2 - c1,
                      "build_wall_s": w2 - w1, "rss_before_mb": before,
                      "rss_after_mb": rss_mb(), "rss_peak_mb": rss_mb("VmHWM"),
                      "pairs": int(est.matcher.pair_d.size)}))


def frames_of(rec: Recording) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The grey frames of a recording that have a truth pose, and those poses."""
    frames, truth = [], []
    for k in range(len(rec)):
        f = rec.frame(k)
        pose = rec.truth.lookup(f.t_ns)
        if pose is not None:
            frames.append(np.ascontiguousarray(to_grey(f.image)))
            truth.append(pose)
    return frames, truth


def thr_cc(g: np.ndarray, _t: int = 0):
    """The reference kernel: one global threshold plus connected components."""
    _, m = cv2.threshold(g, 200, 255, cv2.THRESH_BINARY)
    return cv2.connectedComponentsWithStats(m, connectivity=8)


def interleaved(frames: list[np.ndarray], calls: list[tuple[str, Callable]]
                ) -> tuple[dict[str, list[float]], dict[str, list[object]]]:
    """Every call on every frame, the order rotated per frame, each timed by this
    thread's CPU time (ms); three frames of warm-up first."""
    for g in frames[:3]:
        for _, f in calls:
            f(g, 0)
    times: dict[str, list[float]] = {name: [] for name, _ in calls}
    outs: dict[str, list[object]] = {name: [] for name, _ in calls}
    for k, g in enumerate(frames):
        r = k % len(calls)
        for name, f in calls[r:] + calls[:r]:
            t = time.thread_time_ns()
            out = f(g, k)
            times[name].append((time.thread_time_ns() - t) * 1e-6)
            outs[name].append(out)
    return times, outs


def drive_rows(drive: str, rec: Path, sizes: list[int], sites: list[Path],
               built: dict[int, dict]) -> list[dict]:
    """One drive's frames through each map's estimator (no prior) and the kernel,
    interleaved (:func:`interleaved`); a row per map, the first map the reference."""
    data = Recording(rec)
    frames, truth = frames_of(data)
    ests = [LightsEstimator(data.rig, Site.load(p)) for p in sites]
    calls: list[tuple[str, Callable]] = [(f"{n}", e.estimate) for n, e in zip(sizes, ests,
                                                                              strict=True)]
    calls.append((KERNEL, thr_cc))
    times, outs = interleaved(frames, calls)
    k_med = float(np.median(times[KERNEL]))
    ref, s_med = outs[calls[0][0]], float(np.median(times[calls[0][0]]))
    rows = []
    for n, (name, _) in zip(sizes, calls[:-1], strict=True):
        med = float(np.median(times[name]))
        errs, differ = [], 0
        for k, (p, p0) in enumerate(zip(outs[name], ref, strict=True)):
            if p:
                errs.append(1e3 * math.hypot(p.x_m - truth[k][0], p.y_m - truth[k][1]))
            if bool(p) != bool(p0) or (p and math.hypot(p.x_m - p0.x_m, p.y_m - p0.y_m) > 1e-3):
                differ += 1
        rows.append({**built[n], "drive": drive, "median_ms": med,
                     "p95_ms": float(np.percentile(times[name], 95)),
                     "kernel_median_ms": k_med, "ratio_to_kernel": med / k_med,
                     "ratio_to_smallest": med / s_med,
                     "estimated_share": len(errs) / len(frames),
                     "pos_err_med_mm": float(np.median(errs)) if errs else float("nan"),
                     "frames_differing": differ})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sizes", type=int, nargs="+", default=[40, 1040, 10040, 100000])
    ap.add_argument("--out", type=Path, default=OUT / "bench_scale.csv")
    ap.add_argument("--child", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    rec = recording(args.frames)
    sites = [write_site(rec / "site.yaml", n, OUT / f"scale_site_{n}.yaml") for n in args.sizes]
    built = {}
    for n, path in zip(args.sizes, sites, strict=True):
        got = subprocess.run([sys.executable, __file__, "--child", str(rec), str(path)],
                             capture_output=True, text=True, check=True)
        built[n] = json.loads(got.stdout.strip().splitlines()[-1])
        print(f"built {built[n]}", flush=True)
    rows = drive_rows("hall", rec, args.sizes, sites, built)
    # the same drive inside the field, on the maps that hold its part of the field
    n_hall = Site.load(rec / "site.yaml").lights_m.shape[0]
    inner = [k for k, n in enumerate(args.sizes) if n - n_hall >= FIELD_DRIVE_MIN]
    if inner:
        rec_f = recording(args.frames, sites[inner[0]])
        rows += drive_rows("field", rec_f, [args.sizes[k] for k in inner],
                           [sites[k] for k in inner], built)
    print(" ".join(f"{c:>12s}" for c in COLUMNS))
    for row in rows:
        print(" ".join(f"{fmt(row[c]):>12s}" for c in COLUMNS))
    header = provenance("bench_scale.py", load_before, os.getloadavg(), [
        "# thread_time_ns per call (CPU), each drive's estimators (one per map) and the "
        f"kernel ({KERNEL}) interleaved frame by frame in one process;",
        "# parse and build in a fresh process per map (process CPU time and wall clock); "
        "rss: VmRSS, peak: VmHWM during the construction"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(header + [",".join(COLUMNS)] + [
        ",".join(fmt(r[c]) if c != "drive" else r[c] for c in COLUMNS) for r in rows])
        + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
