"""The lights method under a grid of rectangular lamps, seen by a tilted fisheye, frames
thresholded to 0/255 (issue 36): tracked from a prior, and with no prior.

Scene (the recorded RC-car drive of the issue, simulated): 640x480, a 170° equidistant
fisheye (f = 205 px) tilted 22° from vertical (mount tilt 68°); a 3.05 x 3.66 m grid
(7 x 5) of 1.2 x 0.47 m lamps (``light_size``, long side along y: ``light_yaw`` 90)
2.5 m above the lens; three lamps of the map off and three lamps that are not in the
map (clutter); ``runtime/sim.render_frame`` with noise 2 and blur 0.8, then
``np.where(img > 200, 255, 0)`` as the recording stored them. A 30 fps drive at
0.6 m/s turning at 0.25 rad/s, every frame.

Runs, each over every frame, on one core (``cv2.setNumThreads(1)``):

* ``prior``: the estimator given the previous frame's true pose perturbed by 2 cm /
  1° (per axis, Gaussian);
* ``tracker``: behind ``runtime.tracking.Tracker`` started at the true first pose
  (the estimator's prior is the tracker's prediction);
* ``none``: no prior (every frame a global fix);
* ``none, relaxed``: no prior, the spot checks off (``light_diameter_m=0``) and only
  the vote's candidates compared (``twins=False``): what options could do before.

Printed and written to ``bench_rect_lamps.json`` beside this file: frames posed,
position median / p95 / max (cm) and yaw max (deg) of the poses, valid poses wrong by
more than 10 cm or 2°, the poses' mean NEES (3 dof: the estimator's own covariance
against the truth, no filter), failure reasons, provenance, and ms per frame (median,
p95).

Usage::

    .venv/bin/python benchmarks/bench_rect_lamps.py [--frames 200] [--seed 1] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import Node
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.lights import LightsEstimator
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.tracking import Tracker

PITCH = (3.05, 3.66)
GRID = (7, 5)
LAMP = (1.2, 0.47)
OFF = ((2, 1), (4, 3), (5, 0))
CLUTTER = ((1.5, 1.8), (7.6, 9.1), (12.0, 4.0))
THRESHOLD = 200
FPS = 30.0
WRONG = (0.10, 2.0)   # m, deg: a valid pose further off is wrong


def rig() -> Rig:
    cam = CameraModel.pinhole(640, 480, 205.0, dist=[0.02, -0.005, 0.0, 0.0],
                              model="equidistant")
    return Rig(cam, Mount(tilt_rad=math.radians(68.0), x_m=0.1, z_m=0.3))


def site(missing=(), extra=()) -> Site:
    pts = [[i * PITCH[0], j * PITCH[1]] for i in range(GRID[0]) for j in range(GRID[1])
           if (i, j) not in missing] + [list(p) for p in extra]
    return Site.from_node(Node({"ceiling_height": 2.8, "lights": pts,
                                "light_size": list(LAMP), "light_yaw": 90.0}, None, ""))


def drive(n: int) -> list[tuple[float, float, float, float]]:
    out, x, y, yaw = [], 3.5, 4.5, 0.2
    for k in range(n):
        out.append((k / FPS, x, y, yaw))
        yaw += 0.25 / FPS
        x += 0.6 / FPS * math.cos(yaw)
        y += 0.6 / FPS * math.sin(yaw)
    return out


def run(name: str, est: LightsEstimator, poses, frames, mode: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    tracker = Tracker()
    if mode == "tracker":
        tracker.set_start_pose(0, *poses[0][1:])
    errs, yaws, ms, nees, wrong = [], [], [], [], 0
    fails: Counter = Counter()
    prov: Counter = Counter()
    for k, ((t, x, y, yaw), img) in enumerate(zip(poses, frames, strict=True)):
        t_ns = int(t * 1e9)
        prior = None
        if mode == "prior":
            _, px, py, pyaw = poses[max(k - 1, 0)]
            prior = PoseEstimate(0, "truth", px + rng.normal(0, 0.02), py + rng.normal(0, 0.02),
                                 pyaw + math.radians(rng.normal(0, 1.0)), 1.0)
        elif mode == "tracker":
            prior = tracker.predict(t_ns)
        t0 = time.perf_counter()
        e = est.estimate(img, t_ns, prior)
        ms.append(1e3 * (time.perf_counter() - t0))
        if mode == "tracker":
            tracker.update(e)
        if isinstance(e, PoseEstimate):
            d = math.hypot(e.x_m - x, e.y_m - y)
            dy = abs(math.degrees(math.remainder(e.yaw_rad - yaw, 2 * math.pi)))
            errs.append(d)
            yaws.append(dy)
            wrong += d > WRONG[0] or dy > WRONG[1]
            dv = np.array([e.x_m - x, e.y_m - y, math.remainder(e.yaw_rad - yaw, 2 * math.pi)])
            if e.cov is not None and np.all(np.isfinite(e.cov)):
                nees.append(float(dv @ np.linalg.solve(e.cov, dv)))
            prov[e.provenance.name] += 1
        else:
            fails[e.reason] += 1
    e = np.array(errs) if errs else np.array([np.nan])
    out = {"run": name, "frames": len(frames), "posed": len(errs),
           "median_cm": round(100 * float(np.median(e)), 2),
           "p95_cm": round(100 * float(np.percentile(e, 95)), 2),
           "max_cm": round(100 * float(np.max(e)), 2),
           "yaw_max_deg": round(float(max(yaws)), 3) if yaws else None,
           "wrong_valid": int(wrong),
           "nees": round(float(np.mean(nees)), 2) if nees else None,
           "failures": dict(fails), "provenance": dict(prov),
           "ms_median": round(float(np.median(ms)), 1),
           "ms_p95": round(float(np.percentile(ms, 95)), 1)}
    print(f"{name:16s} posed {out['posed']:3d}/{out['frames']}  median {out['median_cm']:6.2f} "
          f"p95 {out['p95_cm']:6.2f} max {out['max_cm']:7.2f} cm  yaw max "
          f"{out['yaw_max_deg']} deg  wrong valid {wrong:3d}  NEES {out['nees']}  {dict(fails)}  "
          f"{dict(prov)}  "
          f"{out['ms_median']} / {out['ms_p95']} ms")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).with_name("bench_rect_lamps.json"))
    a = ap.parse_args()
    cv2.setNumThreads(1)
    r = rig()
    shown = site(OFF, CLUTTER)
    poses = drive(a.frames)
    t0 = time.perf_counter()
    frames = []
    for k, (_, x, y, yaw) in enumerate(poses):
        img = render_frame(r, shown, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=0.8),
                           np.random.default_rng(a.seed * 100_000 + k))
        frames.append(np.where(img > THRESHOLD, 255, 0).astype(np.uint8))
    print(f"{len(frames)} frames rendered in {time.perf_counter() - t0:.0f} s; the drive "
          f"from ({poses[0][1]:.2f}, {poses[0][2]:.2f}) to ({poses[-1][1]:.2f}, "
          f"{poses[-1][2]:.2f})")
    m = site()
    est = LightsEstimator(r, m)
    est.estimate(frames[0], 0, None)           # compiled loops loaded before timing
    rows = [run("prior", est, poses, frames, "prior", a.seed),
            run("tracker", LightsEstimator(r, m), poses, frames, "tracker", a.seed),
            run("none", est, poses, frames, "none", a.seed),
            run("none, relaxed", LightsEstimator(r, m, {"light_diameter_m": 0.0,
                                                        "twins": False}),
                poses, frames, "none", a.seed)]
    scene = {"grid": GRID, "pitch_m": PITCH, "lamp_m": LAMP, "off": OFF, "clutter": CLUTTER,
             "threshold": THRESHOLD, "fps": FPS, "seed": a.seed}
    a.out.write_text(json.dumps({"scene": scene, "runs": rows}, indent=1) + "\n")
    print(f"written {a.out}")


if __name__ == "__main__":
    main()
