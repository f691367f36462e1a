"""Benchmark of the block method: single-frame pose on simulated 640x480 frames with
noise and blur, a block or marker of configs/block fully in view, one core.

    python benchmarks/bench_block.py [--frames N] [--out results/bench_block.csv]

Prints the figures of issue 11 (position and yaw medians, share localized, wrong poses
with quality >= 0.8, ms per frame) and saves one row per frame as CSV.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.estimator import BlockEstimator
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, project_px
from ceilkit.runtime.sim.render import SimOptions, render_frame

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "block"
OPTIONS = SimOptions(noise_sigma=2.0, blur_px=1.0)


def targets(site: Site) -> list[tuple[str, np.ndarray]]:
    out = [(f"block:{b.id}", b.corners_m) for b in site.blocks]
    return out + [(f"marker:{p.id}", p.corners_m()) for p in site.markers.poses]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--out", default="results/bench_block.csv")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rig, site = Rig.load(CONFIG / "rig.yaml"), Site.load(CONFIG / "site.yaml")
    geo = PlanarGeometry.of(rig, site)
    est = BlockEstimator(rig, site)
    rng = np.random.default_rng(args.seed)
    rows = []
    tg = targets(site)
    while len(rows) < args.frames:
        name, corners = tg[len(rows) % len(tg)]
        c = corners.mean(axis=0)
        x, y = c + rng.uniform(-0.7, 0.7, 2)
        yaw = rng.uniform(-math.pi, math.pi)
        if not rig.camera.in_image(project_px(geo, np.array([x, y, yaw]), corners), 3).all():
            continue
        img = render_frame(rig, site, x, y, yaw, OPTIONS, rng)
        prior = None
        t0 = time.perf_counter()
        got = est.estimate(img, len(rows), prior)
        ms = 1e3 * (time.perf_counter() - t0)
        row = {"target": name, "x": x, "y": y, "yaw_deg": math.degrees(yaw), "ms": ms,
               "ok": int(bool(got)), "reason": "" if got else got.reason}
        if got:
            row.update(err_pos_mm=1e3 * math.hypot(got.x_m - x, got.y_m - y),
                       err_yaw_deg=abs(math.degrees(math.remainder(got.yaw_rad - yaw,
                                                                   2 * math.pi))),
                       quality=got.quality, source=got.diagnostics["source"])
        rows.append(row)
    ok = [r for r in rows if r["ok"]]
    pos = np.array([r["err_pos_mm"] for r in ok]) if ok else np.array([np.nan])
    yaw = np.array([r["err_yaw_deg"] for r in ok]) if ok else np.array([np.nan])
    bad = sum(1 for r in ok if r["quality"] >= 0.8
              and (r["err_pos_mm"] > 50 or r["err_yaw_deg"] > 1.0))
    ms = np.array([r["ms"] for r in rows])
    reasons = sorted({r["reason"] for r in rows if not r["ok"]})
    print(f"block: {len(rows)} frames, localized {100 * len(ok) / len(rows):.1f}% "
          f"(failures: {', '.join(reasons) or 'none'})")
    print(f"  position median {np.median(pos):.2f} mm, p95 {np.percentile(pos, 95):.2f} mm")
    print(f"  yaw median {np.median(yaw):.4f} deg, p95 {np.percentile(yaw, 95):.4f} deg")
    print(f"  wrong with quality >= 0.8: {bad}")
    print(f"  ms per frame: median {np.median(ms):.2f}, p95 {np.percentile(ms, 95):.2f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    keys = ["target", "x", "y", "yaw_deg", "ok", "reason", "source", "err_pos_mm",
            "err_yaw_deg", "quality", "ms"]
    with out.open("w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"  saved {out}")


if __name__ == "__main__":
    main()
