"""Accuracy and speed of `lights` beside `paper-lights` on the same simulated frames.

Frames: ``runtime/sim.render_frame`` of ``configs/lights`` (640x480 equidistant
wide-angle lens looking up, 40 irregular lights on a 3.0 m ceiling) at uniformly
random vehicle poses over the hall, with noise and blur. Each method sees every
frame once, without a prior, on one core (``cv2.setNumThreads(1)``), one method
after the other (as a vehicle runs one).

The same frames are then written as a SPEC recording (``RecordingWriter``: PNG frames,
``frames.csv``, ``rig.yaml``, ``site.yaml``, ``truth.csv``), opened again with
``Recording`` (its own rig and site files, as data made outside the project is read)
and run through both methods a second time.

Printed per method and pass: position error median / p95 (cm), yaw error median / p95
(deg) over correct fixes, the share of frames with >= 4 lit lights in view (within 75
deg of the vertical; and anywhere in the frame) that were localized correctly, wrong
fixes (error > 20 cm or 2 deg) and how many of those had quality > 0.5, failure
reasons, and ms per frame (median, p95; the decoding of a PNG is not counted).

Usage::

    .venv/bin/python benchmarks/bench_lights.py [--frames 300] [--seed 1] [--noise 2.0]
        [--margin 2.0] [--off 0.0] [--exposure 1.0] [--keep DIR]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.lights import LightsEstimator, project_lights
from ceilkit.runtime.estimators.paper_lights import PaperLightsEstimator
from ceilkit.runtime.io.recording import Recording, RecordingWriter
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.sim.render import SimOptions, render_frame

VIEW_DEG = 75.0   # beyond this a 8 cm light is a few pixels of streak (1 px ~ 16 cm)
CONFIG = Path(__file__).resolve().parent.parent / "configs" / "lights"


def visible(rig: Rig, site: Site, x: float, y: float, yaw: float, margin_px: float = 8.0,
            max_angle_deg: float = 90.0) -> int:
    """Lights whose centre projects inside the frame, within ``max_angle_deg`` of the
    vertical as seen from the camera."""
    px = project_lights(rig, site.ceiling_height_m, site.lights_m, x, y, yaw)
    ok = np.isfinite(px[:, 0])
    ok[ok] = rig.camera.in_image(px[ok], margin_px)
    c = rig.mount.camera_position(x, y, yaw)
    d = np.hypot(site.lights_m[:, 0] - c[0], site.lights_m[:, 1] - c[1])
    ang = np.degrees(np.arctan2(d, site.ceiling_height_m - c[2]))
    return int((ok & (ang <= max_angle_deg)).sum())


def evaluate(methods: list, images: list[np.ndarray], poses: list[tuple[float, float, float]],
             nvis: np.ndarray, nraw: np.ndarray, title: str) -> None:
    """Run every method on every frame and print its figures."""
    for est in methods:
        for img in images[:3]:
            est.estimate(img, 0)  # warm-up
    stats = {est.name: {"pe": [], "ye": [], "ms": [], "qw": [], "qok": [],
                        "reasons": Counter(), "ok4": 0, "ok4raw": 0} for est in methods}
    for est in methods:
        st = stats[est.name]
        for k, (img, (x, y, yaw)) in enumerate(zip(images, poses, strict=True)):
            t0 = time.perf_counter()
            out = est.estimate(img, k)
            st["ms"].append(1e3 * (time.perf_counter() - t0))
            if not out:
                st["reasons"][out.reason] += 1
                continue
            dp = math.hypot(out.x_m - x, out.y_m - y)
            dy = abs(math.degrees(math.remainder(out.yaw_rad - yaw, 2 * math.pi)))
            if dp > 0.2 or dy > 2.0:
                st["qw"].append(out.quality)
                continue
            st["pe"].append(dp)
            st["ye"].append(dy)
            st["qok"].append(out.quality)
            st["ok4"] += int(nvis[k] >= 4)
            st["ok4raw"] += int(nraw[k] >= 4)
    n4 = max(1, int((nvis >= 4).sum()))
    n4raw = max(1, int((nraw >= 4).sum()))
    print(f"\n=== {title}")
    for est in methods:
        st = stats[est.name]
        pe_a, ye_a, ms_a = np.array(st["pe"]), np.array(st["ye"]), np.array(st["ms"])
        qw = np.array(st["qw"])
        print(f"[{est.name}]")
        if pe_a.size:
            print(f"  position error  median {100 * np.median(pe_a):.2f} cm   "
                  f"p95 {100 * np.percentile(pe_a, 95):.2f} cm")
            print(f"  yaw error       median {np.median(ye_a):.3f} deg  "
                  f"p95 {np.percentile(ye_a, 95):.3f} deg")
        print(f"  localized, >= 4 lights within {VIEW_DEG:.0f} deg: {st['ok4']}/{n4} = "
              f"{100 * st['ok4'] / n4:.1f} %;  >= 4 anywhere in the frame: "
              f"{st['ok4raw']}/{n4raw} = {100 * st['ok4raw'] / n4raw:.1f} %")
        print(f"  wrong fixes: {qw.size} (quality > 0.5: {int((qw > 0.5).sum())}, "
              f"max quality {qw.max() if qw.size else 0:.2f})")
        if st["qok"]:
            print(f"  quality of correct fixes: median {np.median(st['qok']):.2f}, "
                  f"share > 0.5: {100 * np.mean(np.array(st['qok']) > 0.5):.0f} %")
        print(f"  failures: {dict(st['reasons'])}")
        print(f"  time per frame (one core): median {np.median(ms_a):.2f} ms   "
              f"p95 {np.percentile(ms_a, 95):.2f} ms")


def run(frames: int, seed: int, noise: float, blur: float, margin: float, off: float,
        exposure: float, keep: Path | None = None) -> None:
    cv2.setNumThreads(1)
    rig = Rig.load(CONFIG / "rig.yaml")
    site = Site.load(CONFIG / "site.yaml")
    rng = np.random.default_rng(seed)
    lo, hi = site.lights_m.min(0) - margin, site.lights_m.max(0) + margin
    opts = SimOptions(noise_sigma=noise, blur_px=blur, light_radius_m=0.08,
                      exposure=exposure)
    poses, images, nvis, nraw = [], [], [], []
    for _ in range(frames):
        x, y = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        yaw = rng.uniform(-math.pi, math.pi)
        poses.append((x, y, yaw))
        # some lights switched off in this frame (the map still holds them)
        lit = site.lights_m[rng.uniform(size=site.lights_m.shape[0]) >= off]
        shown = Site(site.ceiling_height_m, lights_m=lit)
        images.append(render_frame(rig, shown, x, y, yaw, options=opts, rng=rng))
        nvis.append(visible(rig, shown, x, y, yaw, max_angle_deg=VIEW_DEG))
        nraw.append(visible(rig, shown, x, y, yaw))
    nvis_a, nraw_a = np.array(nvis), np.array(nraw)
    print(f"{frames} frames, seed {seed}, noise {noise} grey levels, blur {blur} px, "
          f"exposure {exposure}, poses up to {margin} m beyond the lights, "
          f"{100 * off:.0f} % of lights off; cv2 threads: {cv2.getNumThreads()}")
    print(f"lights in view (within {VIEW_DEG:.0f} deg of the vertical): median "
          f"{np.median(nvis_a):.0f}, frames with >= 4: {int((nvis_a >= 4).sum())}; "
          f"anywhere in the frame (up to the horizon): frames with >= 4: "
          f"{int((nraw_a >= 4).sum())}")
    evaluate([LightsEstimator(rig, site), PaperLightsEstimator(rig, site)], images, poses,
             nvis_a, nraw_a, "simulated frames in memory")

    # the same frames through a SPEC recording on disk, read back as outside data
    with tempfile.TemporaryDirectory() as tmp:
        folder = (keep if keep is not None else Path(tmp)) / "bench_lights_rec"
        with RecordingWriter(folder, rig, site, truth=True,
                             header="# benchmarks/bench_lights.py\n") as w:
            for k, (img, (x, y, yaw)) in enumerate(zip(images, poses, strict=True)):
                t_ns = 1_000_000_000 + k * 100_000_000
                w.write(Frame(img, t_ns, k))
                w.write_truth(t_ns, x, y, yaw)
        rec = Recording(folder)
        rimgs = [rec.frame(k).image for k in range(len(rec))]
        tr = rec.truth
        rposes = [(float(tr.x_m[k]), float(tr.y_m[k]), float(tr.yaw_rad[k]))
                  for k in range(len(rec))]
        evaluate([LightsEstimator(rec.rig, rec.site), PaperLightsEstimator(rec.rig, rec.site)],
                 rimgs, rposes, nvis_a, nraw_a, f"SPEC recording read back from {folder}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--blur", type=float, default=0.8)
    ap.add_argument("--margin", type=float, default=2.0,
                    help="poses range this far beyond the light layout, m")
    ap.add_argument("--off", type=float, default=0.0, help="share of lights switched off")
    ap.add_argument("--exposure", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, default=None,
                    help="write the recording under this folder and keep it")
    a = ap.parse_args()
    run(a.frames, a.seed, a.noise, a.blur, a.margin, a.off, a.exposure, a.keep)


if __name__ == "__main__":
    main()
