"""Benchmark: the office scatter (configs/office/scene.yaml) against plain tiles: render
time and how much a frame holds for a feature-based (``texture``) method.

Renders ``--frames`` frames at poses spread over the scatter (x 1..31 m, y -2..2 m,
any heading; seeded) through the packaged office rig (640x480, upward, supersample 3,
noise and blur on), each twice: with the scene's scatter and with plain tiles (the
same site, ``SimOptions.scatter=None``). Per frame it measures the render time (wall
and process CPU, after a warm-up frame that builds the ray cache) and the ORB
keypoints (``cv2.ORB_create(1000)``) and how many of them lie off the tile seams
(their ceiling point more than 3 cm from every ``lines_along`` and ``lines_across``):
the seams and their crossings repeat every tile, so only off-seam keypoints tell one
frame from another.

Prints the medians and writes the numbers (JSON) to ``--out``.

    .venv/bin/python benchmarks/bench_scatter.py [--frames 30] [--seed 0]
        [--out benchmarks/out/bench_scatter.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.sim.scatter_file import scene_beside

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "configs" / "office"
OFF_SEAM_M = 0.03


def ceiling_points(rig: Rig, site: Site, pose: tuple[float, float, float],
                   px: np.ndarray) -> np.ndarray:
    """Where pixels ``(N, 2)`` see the ceiling plane, ``(N, 2)`` in W."""
    xy = rig.camera.unproject(px)
    d = np.c_[xy, np.ones(len(xy))] @ rig.mount.R_world_cam(pose[2]).T
    c = rig.mount.camera_position(*pose)
    t = (site.ceiling_height_m - c[2]) / d[:, 2]
    return c[:2] + t[:, None] * d[:, :2]


def seam_distance(site: Site, pts: np.ndarray) -> np.ndarray:
    """Distance (m) of ceiling points ``(N, 2)`` to the nearest tile seam."""
    cor = site.corridor
    ys = np.asarray(cor.lines_along_m)
    d_along = np.min(np.abs(pts[:, 1:2] - ys[None, :]), axis=1)
    first, sp = cor.lines_across.first_m, cor.lines_across.spacing_m
    u = (pts[:, 0] - first) / sp
    d_across = np.abs(u - np.rint(u)) * sp
    return np.minimum(d_along, d_across)


def measure(rig: Rig, site: Site, poses: np.ndarray, options: SimOptions) -> dict:
    orb = cv2.ORB_create(1000)
    render_frame(rig, site, *poses[0], options)           # the ray cache, once
    wall, cpu, kps, off = [], [], [], []
    for k, pose in enumerate(poses):
        rng = np.random.default_rng([7, k])
        t0, c0 = time.perf_counter(), time.process_time()
        img = render_frame(rig, site, *pose, options, rng)
        wall.append(1e3 * (time.perf_counter() - t0))
        cpu.append(1e3 * (time.process_time() - c0))
        pts = np.array([kp.pt for kp in orb.detect(img, None)]).reshape(-1, 2)
        kps.append(len(pts))
        d = seam_distance(site, ceiling_points(rig, site, tuple(pose), pts)) if len(pts) \
            else np.zeros(0)
        off.append(int(np.sum(d > OFF_SEAM_M)))
    return {"render_ms_wall": wall, "render_ms_cpu": cpu, "orb_keypoints": kps,
            "orb_off_seam": off}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" /
                    "bench_scatter.json")
    args = ap.parse_args()
    rig, site = Rig.load(OFFICE / "rig.yaml"), Site.load(OFFICE / "site.yaml")
    scatter = scene_beside(site)
    rng = np.random.default_rng(args.seed)
    poses = np.c_[rng.uniform(1.0, 31.0, args.frames), rng.uniform(-2.0, 2.0, args.frames),
                  rng.uniform(-np.pi, np.pi, args.frames)]
    res = {"scene": scatter.describe(), "frames": args.frames, "seed": args.seed,
           "scatter": measure(rig, site, poses, SimOptions(scatter=scatter)),
           "plain": measure(rig, site, poses, SimOptions())}
    for name in ("scatter", "plain"):
        r = res[name]
        print(f"{name:8s} render {np.median(r['render_ms_wall']):6.1f} ms wall "
              f"({np.median(r['render_ms_cpu']):6.1f} ms CPU) median, "
              f"ORB keypoints median {np.median(r['orb_keypoints']):.0f} "
              f"(min {min(r['orb_keypoints'])}), off the seams median "
              f"{np.median(r['orb_off_seam']):.0f} (min {min(r['orb_off_seam'])})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
