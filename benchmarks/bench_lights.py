"""Accuracy and speed of `lights` beside `paper-lights` on the same simulated frames.

Frames: ``runtime/sim.render_frame`` of ``configs/lights`` (640x480 equidistant
wide-angle lens looking up, 40 irregular lights on a 3.0 m ceiling) at uniformly
random vehicle poses over the hall, with noise and blur. Each method sees every
frame once, without a prior, on one core (``cv2.setNumThreads(1)``).

Printed per method: position error median / p95 (cm), yaw error median / p95 (deg)
over correct fixes, the share of frames with >= 4 lights in view that were localized
correctly, wrong fixes (error > 20 cm or 2 deg) and how many of those had quality
> 0.5, failure reasons, and ms per frame (median, p95).

Usage::

    .venv/bin/python benchmarks/bench_lights.py [--frames 300] [--seed 1] [--noise 2.0]
"""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.lights import LightsEstimator, project_lights
from ceilkit.runtime.paper_lights import PaperLightsEstimator
from ceilkit.runtime.rig import Rig
from ceilkit.runtime.sim import SimOptions, render_frame
from ceilkit.runtime.site import Site

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "lights"


def visible(rig: Rig, site: Site, x: float, y: float, yaw: float, margin_px: float = 8.0
            ) -> int:
    px = project_lights(rig, site.ceiling_height_m, site.lights_m, x, y, yaw)
    ok = np.isfinite(px[:, 0])
    ok[ok] = rig.camera.in_image(px[ok], margin_px)
    return int(ok.sum())


def run(frames: int, seed: int, noise: float, blur: float) -> None:
    cv2.setNumThreads(1)
    rig = Rig.load(CONFIG / "rig.yaml")
    site = Site.load(CONFIG / "site.yaml")
    rng = np.random.default_rng(seed)
    lo, hi = site.lights_m.min(0) - 0.5, site.lights_m.max(0) + 0.5
    opts = SimOptions(noise_sigma=noise, blur_px=blur, light_radius_m=0.08)
    poses, images, nvis = [], [], []
    for _ in range(frames):
        x, y = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        yaw = rng.uniform(-math.pi, math.pi)
        poses.append((x, y, yaw))
        images.append(render_frame(rig, site, x, y, yaw, options=opts, rng=rng))
        nvis.append(visible(rig, site, x, y, yaw))
    nvis_a = np.array(nvis)
    print(f"{frames} frames, seed {seed}, noise {noise} grey levels, blur {blur} px; "
          f"lights in view: median {np.median(nvis_a):.0f}, "
          f"frames with >= 4: {int((nvis_a >= 4).sum())}")
    methods = [LightsEstimator(rig, site), PaperLightsEstimator(rig, site)]
    for est in methods:
        for img in images[:3]:
            est.estimate(img, 0)  # warm-up
        pe, ye, ms, quality_wrong = [], [], [], []
        reasons: Counter[str] = Counter()
        ok4 = 0
        for k, (img, (x, y, yaw)) in enumerate(zip(images, poses, strict=True)):
            t0 = time.perf_counter()
            out = est.estimate(img, k)
            ms.append(1e3 * (time.perf_counter() - t0))
            if not out:
                reasons[out.reason] += 1
                continue
            dp = math.hypot(out.x_m - x, out.y_m - y)
            dy = abs(math.degrees(math.remainder(out.yaw_rad - yaw, 2 * math.pi)))
            if dp > 0.2 or dy > 2.0:
                quality_wrong.append(out.quality)
                continue
            pe.append(dp)
            ye.append(dy)
            ok4 += int(nvis[k] >= 4)
        pe_a, ye_a, ms_a = np.array(pe), np.array(ye), np.array(ms)
        qw = np.array(quality_wrong)
        n4 = max(1, int((nvis_a >= 4).sum()))
        print(f"\n[{est.name}]")
        if pe_a.size:
            print(f"  position error  median {100 * np.median(pe_a):.2f} cm   "
                  f"p95 {100 * np.percentile(pe_a, 95):.2f} cm")
            print(f"  yaw error       median {np.median(ye_a):.3f} deg  "
                  f"p95 {np.percentile(ye_a, 95):.3f} deg")
        print(f"  localized (>= 4 in view): {ok4}/{n4} = {100 * ok4 / n4:.1f} %")
        print(f"  wrong fixes: {qw.size} (quality > 0.5: {int((qw > 0.5).sum())}, "
              f"max quality {qw.max() if qw.size else 0:.2f})")
        print(f"  failures: {dict(reasons)}")
        print(f"  time per frame: median {np.median(ms_a):.2f} ms   "
              f"p95 {np.percentile(ms_a, 95):.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--blur", type=float, default=0.8)
    a = ap.parse_args()
    run(a.frames, a.seed, a.noise, a.blur)


if __name__ == "__main__":
    main()
