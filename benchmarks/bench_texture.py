"""Benchmark: the ``texture`` method on the office scene (configs/office): a map built
from one drive with truth poses, single frames of a second drive localized on it.

The map drive: rows along x every ``--row`` m across y -1.8..1.8, a frame every 0.4 m
over x 1..``--length`` (truth poses; ``build_map``). The second drive: ``--frames``
poses on a diagonal path with headings all round (noise 2, blur 0.8, supersample
``--supersample``). Per frame: the global estimate (no prior) and the tracked one (the
truth, 1 cm and 0.5° off, σ 1 cm and 0.57°, as the prior: the fast path of
``texture/track.py``), each timed as thread CPU (``time.thread_time``, OpenCV held to
one thread so that the thread's time is all of the work), beside ``cv2.ORB``
detect-and-compute (1000 keypoints) on the same 640x480 frame, interleaved. Both
paths again against a map of ``--big-m2`` m²: the map's features tiled over that
area, each copy's descriptors with 8 % of their bits flipped (a site that size holds
as many features, its descriptors alike but not equal; the accuracy there is not
what is measured, the time is).

Prints the figures and writes them (JSON) to ``--out``.

    .venv/bin/python benchmarks/bench_texture.py [--frames 60] [--length 8]
        [--supersample 2] [--big-m2 1000] [--out benchmarks/out/bench_texture.json]

Measured (2026-12-06, the shared 2-core machine under load, ``--frames 60 --length 8
--supersample 2``, a map of 1,192 features over 71 m²): global 60/60 valid, position
median 1.4 mm, worst 3.6 mm and 0.15°, thread CPU 4.8 ms (1.10 x ``cv2.ORB(1000)``'s
4.4 ms on the same frames); tracked 60/60 (59 by the fast path), 2.1 mm, 2.4 ms
(0.55 x); against 17,880 features (1,000 m²) 5.4 ms (1.24 x) and 2.4 ms (0.54 x).
docs/methods/texture.md, "Figures", has the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.texture import TextureEstimator, build_map
from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.sim.scatter_file import scene_beside

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "configs" / "office"


def timed(fn, *args, **kw):
    t = time.thread_time()
    out = fn(*args, **kw)
    return out, 1e3 * (time.thread_time() - t)


def tiled(cmap: CeilingMap, area_m2: float, seed: int = 0) -> CeilingMap:
    """The map's features repeated over ``area_m2`` (shifted copies, each copy's
    descriptors with 8 % of their bits flipped), same mosaic."""
    x0, y0, x1, y1 = cmap.extent_xy
    w, h = x1 - x0, y1 - y0
    copies = max(1, int(math.ceil(area_m2 / (w * h))))
    shifts = np.array([[w * (k % 40), h * (k // 40)] for k in range(copies)])
    pts = (cmap.points_xy[None] + shifts[:, None]).reshape(-1, 2)
    desc = np.tile(cmap.descriptors, (copies, 1))
    flips = np.random.default_rng(seed).random((*desc.shape, 8)) < 0.08
    flips[: len(cmap.descriptors)] = False               # the first copy: the map itself
    desc = desc ^ np.packbits(flips, axis=-1).reshape(desc.shape)
    return dataclasses.replace(cmap, points_xy=pts, descriptors=desc,
                               sigma_m=np.tile(cmap.sigma_m, copies))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--length", type=float, default=8.0)
    ap.add_argument("--row", type=float, default=1.2)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--big-m2", type=float, default=1000.0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" /
                    "bench_texture.json")
    args = ap.parse_args()
    cv2.setNumThreads(1)       # thread CPU is then all of the work (remap, LK, ORB)
    rig, site = Rig.load(OFFICE / "rig.yaml"), Site.load(OFFICE / "site.yaml")
    opts = SimOptions(scatter=scene_beside(site), supersample=args.supersample)
    ys = np.arange(-1.8, 1.81, args.row)
    map_poses = [(x, y, 0.0 if i % 2 == 0 else math.pi / 2) for i, y in enumerate(ys)
                 for x in np.arange(1.0, args.length + 1e-9, 0.4)]
    frames = [render_frame(rig, site, *p, opts, np.random.default_rng([1, k]))
              for k, p in enumerate(map_poses)]
    cmap, build_ms = timed(build_map, frames, map_poses, rig, site.ceiling_height_m)
    tmp = Path(tempfile.mkdtemp())
    cmap.save(tmp / "map.npz")
    tiled(cmap, args.big_m2).save(tmp / "big.npz")
    est = TextureEstimator(rig, dataclasses.replace(site, ceiling_map=str(tmp / "map.npz")),
                           {"plane_odometry": False})
    big = TextureEstimator(rig, dataclasses.replace(site, ceiling_map=str(tmp / "big.npz")),
                           {"plane_odometry": False})
    n = args.frames
    drive = [(1.5 + (args.length - 2.0) * k / max(n - 1, 1), -1.4 + 2.8 * k / max(n - 1, 1),
              -math.pi + 2 * math.pi * k / max(n, 1)) for k in range(n)]
    orb = cv2.ORB_create(1000)
    rows = []
    for k, p in enumerate(drive):
        img = render_frame(rig, site, *p, opts, np.random.default_rng([2, k]))
        prior = PoseEstimate(0, "track", p[0] + 0.01, p[1], p[2] + math.radians(0.5), 0.9,
                             cov=np.diag([1e-4, 1e-4, 1e-4]))
        g, g_ms = timed(est.estimate, img, k)
        t, t_ms = timed(est.estimate, img, k, prior)
        _, orb_ms = timed(orb.detectAndCompute, img, None)
        b, big_ms = timed(big.estimate, img, k)
        bt, big_t_ms = timed(big.estimate, img, k, prior)
        rows.append({"truth": p, "global": _row(g, p), "global_ms": g_ms,
                     "tracked": _row(t, p), "tracked_ms": t_ms, "orb_ms": orb_ms,
                     "big_ms": big_ms, "big": _row(b, p), "big_tracked_ms": big_t_ms,
                     "big_tracked": _row(bt, p)})
    res = {"map_frames": len(map_poses), "map_features": int(len(cmap.points_xy)),
           "map_m2": float(np.prod(np.subtract(cmap.extent_xy[2:], cmap.extent_xy[:2]))),
           "big_features": int(len(big.map.points_xy)), "build_ms": build_ms, "rows": rows}
    _report(res)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


def _row(est, truth) -> dict:
    if not est:
        return {"valid": False, "reason": est.reason}
    d = math.hypot(est.x_m - truth[0], est.y_m - truth[1])
    a = abs(math.degrees((est.yaw_rad - truth[2] + math.pi) % (2 * math.pi) - math.pi))
    return {"valid": True, "error_m": d, "error_deg": a, "provenance": est.provenance.value,
            "search": est.diagnostics.get("search")}


def _report(res: dict) -> None:
    rows = res["rows"]
    orb = np.median([r["orb_ms"] for r in rows])
    for key, ms in (("global", "global_ms"), ("tracked", "tracked_ms"), ("big", "big_ms"),
                    ("big_tracked", "big_tracked_ms")):
        ok = [r[key] for r in rows if r[key]["valid"]]
        err = [o["error_m"] for o in ok]
        worst = max((o["error_m"] for o in ok), default=math.nan)
        worst_deg = max((o["error_deg"] for o in ok), default=math.nan)
        fails = Counter(r[key]["reason"] for r in rows if not r[key]["valid"])
        paths = Counter(o["search"] for o in ok)
        cpu = np.median([r[ms] for r in rows])
        print(f"{key:11s} valid {len(ok)}/{len(rows)} {dict(fails)} by {dict(paths)}, "
              f"position median {1e3 * np.median(err) if err else math.nan:.2f} mm, worst "
              f"{1e3 * worst:.1f} mm {worst_deg:.2f} deg; thread CPU median {cpu:.2f} ms "
              f"({cpu / orb:.2f} x ORB)")
    print(f"cv2.ORB(1000) detectAndCompute on the frame: median {orb:.2f} ms")
    print(f"the map: {res['map_features']} features over {res['map_m2']:.0f} m^2 from "
          f"{res['map_frames']} frames, built in {res['build_ms'] / 1e3:.1f} s; tiled to "
          f"the --big-m2 area: {res['big_features']} features")


if __name__ == "__main__":
    main()
