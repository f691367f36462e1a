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
area, each copy's descriptors dealt to its points in another order with 8 % of their
bits flipped (a site that size holds as many features, its descriptors alike but not
equal, in another layout; the accuracy there is not what is measured, the time is.
Until 2026-12-07 the copies kept the first's layout: a repeated ceiling, which the
texture method now refuses, 0 of 60 valid).

Then the kidnap run (:func:`kidnaps`): ``--method texture`` and ``auto``, each with
its tracker as ``ceilrun`` makes them, driven, the camera covered, the vehicle carried
elsewhere, uncovered: the frames to the first right pose, and the wrong poses published.

Prints the figures and writes them (JSON) to ``--out``.

    .venv/bin/python benchmarks/bench_texture.py [--frames 60] [--length 8]
        [--supersample 2] [--big-m2 1000] [--kidnaps 8]
        [--out benchmarks/out/bench_texture.json]

Measured (2026-12-06 18:57 and 19:01 UTC, git 1b28e0d, the shared 2-core machine at
load 5.6-6.7, ``--frames 60 --length 8 --supersample 2``, a map of 1,143 features in
2,532 descriptor rows over 71 m²): global 60/60 valid, position median 1.17 mm, worst
3.6 mm and 0.12°, thread CPU 4.41 and 3.39 ms (0.70 and 0.72 x ``cv2.ORB(1000)``'s
6.32 and 4.70 ms on the same frames); tracked 60/60 (all by the fast path), 0.43 mm,
worst 1.4 mm, 1.30 and 1.04 ms (0.21, 0.22 x); against 16,837 features in 37,980 rows
(1,000 m²) 60/60, 5.39 and 4.30 ms (0.85, 0.91 x) and 1.27 and 1.01 ms (0.20, 0.21 x).
Kidnap: right again on the 3rd uncovered frame after a 0.5 s cover, on the 1st after
1.5 s, for both methods in all 8 trials; no wrong pose published.
After the global search kept its list by place (``match._lsh_knn``; the estimates
unchanged, frame by frame): 1,000 m² 2.67 against 3.05 ms before (0.74 against 0.85 x
ORB), interleaved in one process; two runs of this benchmark (the first beside
another): 3.00 and 3.75 ms (0.86, 0.71 x ORB at 3.50 and 5.30 ms), 71 m² 2.55 and
3.53 ms (0.73, 0.67), the errors and kidnaps as above.
docs/methods/texture.md, "Figures", has the tables.
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
from ceilkit.runtime.multi import make_localizer
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.sim.scatter_file import scene_beside

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "configs" / "office"


def timed(fn, *args, **kw):
    t = time.thread_time()
    out = fn(*args, **kw)
    return out, 1e3 * (time.thread_time() - t)


def tiled(cmap: CeilingMap, area_m2: float, seed: int = 0) -> CeilingMap:
    """The map's features spread over ``area_m2``: shifted copies, each but the first
    with its descriptors dealt to its points in another order and 8 % of their bits
    flipped (a site that size: as many features, alike descriptors, another layout;
    copies of one layout would be a repeated ceiling, on which no pose is singled
    out), same mosaic."""
    x0, y0, x1, y1 = cmap.extent_xy
    w, h = x1 - x0, y1 - y0
    copies = max(1, int(math.ceil(area_m2 / (w * h))))
    shifts = np.array([[w * (k % 40), h * (k // 40)] for k in range(copies)])
    pts = (cmap.points_xy[None] + shifts[:, None]).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    n = len(cmap.descriptors)
    desc = np.concatenate([cmap.descriptors if k == 0 else cmap.descriptors[rng.permutation(n)]
                           for k in range(copies)])
    flips = rng.random((*desc.shape, 8)) < 0.08
    flips[:n] = False                                    # the first copy: the map itself
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
    ap.add_argument("--kidnaps", type=int, default=8, help="kidnap trials per cover length")
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
    map_site = dataclasses.replace(site, ceiling_map=str(tmp / "map.npz"))
    res = {"map_frames": len(map_poses), "map_rows": int(len(cmap.points_xy)),
           "map_features": int(len(np.unique(cmap.points_xy, axis=0))),
           "map_m2": float(np.prod(np.subtract(cmap.extent_xy[2:], cmap.extent_xy[:2]))),
           "big_rows": int(len(big.map.points_xy)),
           "big_features": int(len(np.unique(big.map.points_xy, axis=0))),
           "build_ms": build_ms, "rows": rows,
           "kidnaps": kidnaps(rig, map_site, opts, args.length, args.kidnaps)}
    _report(res)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


KIDNAP_BEFORE, KIDNAP_AFTER = 6, 6     # frames driven before the cover and after it
COVERS = (5, 15)       # frames the camera is covered (10 fps: 0.5 s, and 1.5 s: the
#                        fusion's track is lost after 1 s without a fix)


def kidnaps(rig, site, opts, length: float, trials: int) -> list[dict]:
    """The kidnap run: ``--method texture`` and ``auto`` (beside ``corridor``, the tile
    grid's lines), each with its tracker, on drives at 0.5 m/s (10 fps): driven
    :data:`KIDNAP_BEFORE` frames, the camera covered (a blank frame) for each of
    :data:`COVERS`, the vehicle carried elsewhere on the map (a place and heading drawn
    per trial, at least 1.5 m away), then :data:`KIDNAP_AFTER` frames. Per trial and
    method: the frames from the uncovering to the first published pose within 10 cm
    and 2 deg of the truth (1: the first uncovered frame), and the published poses
    wrong by more than that."""
    rng = np.random.default_rng(7)
    out = []
    for k in range(trials):
        a = (rng.uniform(1.8, length - 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-math.pi, math.pi))
        while True:
            b = (rng.uniform(1.8, length - 1.0), rng.uniform(-1.0, 1.0),
                 rng.uniform(-math.pi, math.pi))
            if math.hypot(b[0] - a[0], b[1] - a[1]) >= 1.5:
                break
        poses = [_ahead(a, 0.05 * i) for i in range(KIDNAP_BEFORE)] + \
            [_ahead(b, 0.05 * i) for i in range(KIDNAP_AFTER)]
        imgs = [render_frame(rig, site, *p, opts, np.random.default_rng([3, k, i]))
                for i, p in enumerate(poses)]
        for cover in COVERS:
            seq = imgs[:KIDNAP_BEFORE] + [np.full_like(imgs[0], 3)] * cover + \
                imgs[KIDNAP_BEFORE:]
            truth = poses[:KIDNAP_BEFORE] + [None] * cover + poses[KIDNAP_BEFORE:]
            for method in ("texture", "auto"):
                out.append({"trial": k, "cover": cover, "method": method,
                            **_kidnap_run(rig, site, method, seq, truth,
                                          KIDNAP_BEFORE + cover)})
    return out


def _ahead(pose, d: float) -> tuple[float, float, float]:
    return pose[0] + d * math.cos(pose[2]), pose[1] + d * math.sin(pose[2]), pose[2]


def _kidnap_run(rig, site, method: str, seq, truth, uncover: int) -> dict:
    est, tracker = make_localizer(method, rig, site)
    first, wrong, before = None, 0, 0
    for k, img in enumerate(seq):
        t = k * 100_000_000
        got = tracker.update(est.estimate(img, t, tracker.predict(t))).estimate
        if not isinstance(got, PoseEstimate) or truth[k] is None:
            continue
        r = _row(got, truth[k])
        good = r["error_m"] <= 0.10 and r["error_deg"] <= 2.0
        wrong += not good
        before += k < uncover and good
        if k >= uncover and good and first is None:
            first = k - uncover + 1
    return {"frames_to_relocalize": first, "wrong": wrong, "valid_before": before}


def _row(est, truth) -> dict:
    if not est:
        return {"valid": False, "reason": est.reason}
    e = np.array([est.x_m - truth[0], est.y_m - truth[1]])
    a = abs(math.degrees((est.yaw_rad - truth[2] + math.pi) % (2 * math.pi) - math.pi))
    cov = None if est.cov is None else np.asarray(est.cov, float)[:2, :2]
    nees = float(e @ np.linalg.solve(cov, e)) if cov is not None else math.nan
    return {"valid": True, "error_m": float(np.hypot(*e)), "error_deg": a, "nees": nees,
            "provenance": est.provenance.value, "search": est.diagnostics.get("search")}


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
        nees = np.median([o["nees"] for o in ok]) if ok else math.nan
        print(f"{key:11s} valid {len(ok)}/{len(rows)} {dict(fails)} by {dict(paths)}, "
              f"position median {1e3 * np.median(err) if err else math.nan:.2f} mm, worst "
              f"{1e3 * worst:.1f} mm {worst_deg:.2f} deg; position NEES median {nees:.2f} "
              f"(2 dof: 1.39); thread CPU median {cpu:.2f} ms ({cpu / orb:.3f} x ORB)")
    print(f"cv2.ORB(1000) detectAndCompute on the frame: median {orb:.2f} ms")
    for cover in COVERS:
        for method in ("texture", "auto"):
            runs = [r for r in res["kidnaps"] if r["cover"] == cover and r["method"] == method]
            n = [r["frames_to_relocalize"] for r in runs]
            print(f"kidnap, camera covered {cover} frames, {method:7s}: frames from the "
                  f"uncovering to the first right pose {n} (worst "
                  f"{max((v for v in n if v is not None), default=None)}, never: "
                  f"{sum(v is None for v in n)}), wrong poses published "
                  f"{sum(r['wrong'] for r in runs)}, right before the cover "
                  f"{sum(r['valid_before'] for r in runs)}/{len(runs) * KIDNAP_BEFORE}")
    print(f"the map: {res['map_features']} features ({res['map_rows']} descriptor rows) "
          f"over {res['map_m2']:.0f} m^2 from {res['map_frames']} frames, built in "
          f"{res['build_ms'] / 1e3:.1f} s; tiled to the --big-m2 area: "
          f"{res['big_features']} features ({res['big_rows']} rows)")


if __name__ == "__main__":
    main()
