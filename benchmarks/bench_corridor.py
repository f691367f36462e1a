"""Benchmark of the corridor estimators on simulated frames: ms per frame and accuracy.

Runs ``corridor`` (ours; optionally each segment detector) and ``paper-corridor`` on
the same simulated frames of configs/corridor at 640x480 and 1280x720
(``CameraModel.scaled``), noise sigma 2 grey levels, blur 0.8 px, and prints the
median / p95 heading and lateral errors, the share of frames estimated and the
median time per frame (one process, whatever core it gets).

    .venv/bin/python benchmarks/bench_corridor.py [--frames 60] [--clutter] [--detectors]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from ceilkit.runtime.corridor import CorridorEstimator
from ceilkit.runtime.paper_corridor import PaperCorridorEstimator
from ceilkit.runtime.rig import Rig
from ceilkit.runtime.sim import SimOptions, render_frame
from ceilkit.runtime.site import Site

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "corridor"


def run(est, frames) -> str:
    errs, times, fails = [], [], {}
    for _x, y, yaw, img in frames:
        t = time.perf_counter()
        r = est.estimate(img, 0)
        times.append(time.perf_counter() - t)
        if r:
            errs.append((abs(math.degrees(math.remainder(r.yaw_rad - yaw, 2 * math.pi))),
                         abs(r.y_m - y) * 1e3))
        else:
            fails[r.reason] = fails.get(r.reason, 0) + 1
    e = np.array(errs).reshape(-1, 2)
    if e.shape[0] == 0:
        e = np.full((1, 2), np.nan)
    return (f"ok {len(errs):3d}/{len(frames)}  heading deg med {np.median(e[:, 0]):7.4f} "
            f"p95 {np.percentile(e[:, 0], 95):7.4f}  lateral mm med {np.median(e[:, 1]):7.2f} "
            f"p95 {np.percentile(e[:, 1], 95):7.2f}  ms {1e3 * np.median(times):6.2f}  "
            f"fails {fails}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clutter", action="store_true")
    ap.add_argument("--detectors", action="store_true", help="also fld+refine, lsd, hough")
    args = ap.parse_args()
    rig0, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    rng = np.random.default_rng(args.seed)
    poses = [(rng.uniform(0, 3), rng.uniform(-0.4, 0.4), math.radians(rng.uniform(-40, 40)))
             for _ in range(args.frames)]
    opts = SimOptions(noise_sigma=2.0, blur_px=0.8, clutter=args.clutter)
    for w, h in ((640, 480), (1280, 720)):
        rig = Rig(rig0.camera.scaled(w, h), rig0.mount)
        frames = [(x, y, yaw, render_frame(rig, site, x, y, yaw, options=opts, rng=rng))
                  for x, y, yaw in poses]
        print(f"== {w}x{h}, {len(frames)} frames, clutter={args.clutter}")
        ests = [("corridor", CorridorEstimator(rig, site))]
        if args.detectors:
            ests += [("fld+refine", CorridorEstimator(rig, site, refine=True)),
                     ("lsd", CorridorEstimator(rig, site, detector="lsd")),
                     ("hough", CorridorEstimator(rig, site, detector="hough"))]
        ests.append(("paper-corridor", PaperCorridorEstimator(rig, site)))
        for name, est in ests:
            print(f"{name:15s} {run(est, frames)}", flush=True)


if __name__ == "__main__":
    main()
