"""Benchmark: `ceilcal intrinsics` on large frames (issue 16: the working resolution).

Renders ``--views`` views of a chessboard (and of a ChArUco board with ``--charuco``)
through a 12 Mpx lens (``--width`` x ``--height``, plumb_bob with barrel distortion),
writes them as PNG into a temporary folder and runs what ``ceilcal intrinsics`` runs
(:func:`detect_images` then :func:`calibrate_intrinsics`), timed per view:

* **decimated**: the boards' default working size (``WORKING_MPX``, found on the
  decimated image, refined at full resolution);
* **full**: ``working_mpx=0``, found at full resolution (the code before the working
  size), skipped with ``--no-full``;
* **downscale**: the same views box-averaged to about 1 Mpx
  (:func:`~ceilkit.calib.boards.decimate`) and calibrated there.

Each calibration is compared with the true lens at full resolution (the downscale's
model scaled up: ``f * k``, ``c * k + (k - 1) / 2``): focal and principal point errors
and the largest pixel difference of the true and the estimated model over the image
(a grid of pixels: true ray, estimated projection).

With ``--ceilrun`` it measures the runtime instead: the packaged ``lights`` and
``corridor`` examples' cameras scaled by ``--scale`` (6.25: 4000x3000 from 640x480),
one simulated frame each, and the estimator built and run on it with its working size
(``working_mpx`` 1, the default) and at full resolution (``working_mpx`` 0, the code
before): build and
estimate times (the estimate's median of ``--repeats`` after one warm-up run, on one
core), their peak traced memory (tracemalloc, a second pass), and the pose error.

Prints a table, saves it as JSON in ``--out``.

    .venv/bin/python benchmarks/bench_large.py [--views 8] [--width 4000 --height 3000]
        [--charuco] [--no-full] [--out benchmarks/out/large]
    .venv/bin/python benchmarks/bench_large.py --ceilrun [--scale 6.25] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.calib.boards import (
    WORKING_MPX,
    Board,
    CharucoBoard,
    ChessBoard,
    decimate,
    render_views,
    working_factor,
)
from ceilkit.calib.intrinsics import calibrate_intrinsics, detect_images
from ceilkit.runtime.geometry.camera import CameraModel


def true_camera(width: int, height: int) -> CameraModel:
    f = 0.85 * width
    K = np.array([[f, 0.0, (width - 1) / 2 + 7.0], [0.0, f, (height - 1) / 2 - 5.0],
                  [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.array([-0.12, 0.05, 0.0, 0.0, 0.0]))


def scaled_up(cam: CameraModel, k: int, size: tuple[int, int]) -> CameraModel:
    """A model of a ``k``-decimated image expressed at full resolution."""
    K = cam.K.copy()
    K[:2, :2] *= k
    K[:2, 2] = K[:2, 2] * k + (k - 1) / 2
    return CameraModel(size[0], size[1], K, cam.dist, cam.model)


def model_error(true: CameraModel, est: CameraModel) -> dict[str, float]:
    u, v = np.meshgrid(np.linspace(0, true.width - 1, 40), np.linspace(0, true.height - 1, 30))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    d = np.linalg.norm(est.distort(true.unproject(px)) - px, axis=1)
    return {"fx_rel": float(est.fx / true.fx - 1), "fy_rel": float(est.fy / true.fy - 1),
            "cx_px": float(est.K[0, 2] - true.K[0, 2]),
            "cy_px": float(est.K[1, 2] - true.K[1, 2]),
            "model_max_px": float(np.nanmax(d)), "model_rms_px": float(np.sqrt(np.nanmean(d ** 2)))}


def run(board: Board, folder: Path, names: list[Path], true: CameraModel, k: int) -> dict:
    t0 = time.perf_counter()
    dets = detect_images(names, board)
    t_det = time.perf_counter() - t0
    res = calibrate_intrinsics(dets)
    t_all = time.perf_counter() - t0
    cam = res.camera if k == 1 else scaled_up(res.camera, k, true.size)
    return {"views_found": len(dets), "s_per_view_detect": t_det / len(names),
            "s_per_view": t_all / len(names), "rms_px": res.report.rms_px,
            **model_error(true, cam)}


def bench(board: Board, n_views: int, width: int, height: int, full: bool) -> dict:
    true = true_camera(width, height)
    rng = np.random.default_rng(5)
    t0 = time.perf_counter()
    views = render_views(board, true, n_views, rng, blur_sigma_px=0.7 * width / 1280,
                         supersample=2)
    t_render = time.perf_counter() - t0
    k = working_factor((height, width), WORKING_MPX)
    out: dict = {"board": board.spec, "size": [width, height], "views": n_views,
                 "render_s": t_render, "factor": k}
    with tempfile.TemporaryDirectory() as tmp:
        big, small = Path(tmp, "big"), Path(tmp, "small")
        big.mkdir()
        small.mkdir()
        nb, ns = [], []
        for i, (img, _, _) in enumerate(views):
            nb.append(big / f"v{i:02d}.png")
            ns.append(small / f"v{i:02d}.png")
            cv2.imwrite(str(nb[-1]), img)
            cv2.imwrite(str(ns[-1]), decimate(img, k))
        out["decimated"] = run(board, big, nb, true, 1)
        out["downscale"] = run(board, small, ns, true, k)
        if full:
            whole = (ChessBoard(board.cols, board.rows, board.square_m, working_mpx=0.0)
                     if isinstance(board, ChessBoard) else
                     CharucoBoard(board.squares_x, board.squares_y, board.square_m,
                                  board.marker_m, board.dictionary, working_mpx=0.0))
            out["full"] = run(whole, big, nb, true, 1)
    return out


def scaled_rig(rig, k: float):
    """``rig`` with its camera's image ``k`` times larger (the same lens)."""
    import dataclasses

    cam = rig.camera
    K = cam.K.copy()
    K[:2, :2] *= k
    K[:2, 2] = K[:2, 2] * k + (k - 1) / 2
    big = dataclasses.replace(cam, width=int(round(cam.width * k)),
                              height=int(round(cam.height * k)), K=K, P=None)
    return dataclasses.replace(rig, camera=big)


def bench_ceilrun(method: str, scale: float, repeats: int) -> dict:
    """One simulated frame of the packaged ``method`` example at ``scale``: the estimator
    built and run with its working size and at full resolution."""
    import math
    import tracemalloc

    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site
    from ceilkit.runtime.devices import packaged_config
    from ceilkit.runtime.estimators.registry import make_estimator
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    cfg = packaged_config(method)
    site = Site.load(cfg / "site.yaml")
    rig = scaled_rig(Rig.load(cfg / "rig.yaml"), scale)
    x, y, yaw = (1.0, 0.5, 0.3) if method == "lights" else (2.0, 0.1, 0.05)
    t0 = time.perf_counter()
    img = render_frame(rig, site, x, y, yaw, SimOptions(supersample=1),
                       rng=np.random.default_rng(0))
    out: dict = {"method": method, "size": [rig.camera.width, rig.camera.height],
                 "render_s": time.perf_counter() - t0}
    for label, mpx in (("working", 1.0), ("full", 0.0)):
        t0 = time.perf_counter()
        est = make_estimator(method, rig, site, stated(method, {"working_mpx": mpx}))
        build_ms = 1e3 * (time.perf_counter() - t0)
        est.estimate(img, 0)                                   # warm-up (imports, caches)
        times = []
        for i in range(repeats):
            t0 = time.perf_counter()
            res = est.estimate(img, i + 1)
            times.append(1e3 * (time.perf_counter() - t0))
        tracemalloc.start()
        make_estimator(method, rig, site, stated(method, {"working_mpx": mpx}))
        build_peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.reset_peak()
        est.estimate(img, 99)
        est_peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        factor = (est.observer.factor if method == "lights" else est.detector.factor)
        row = {"factor": factor, "build_ms": build_ms,
               "estimate_ms": float(np.median(times)), "build_peak_mb": build_peak,
               "estimate_peak_mb": est_peak, "ok": bool(res)}
        if res:
            row["quality"] = res.quality
            row["pos_err_mm"] = 1e3 * (math.hypot(res.x_m - x, res.y_m - y)
                                       if res.x_m is not None else abs(res.y_m - y))
            row["yaw_err_deg"] = abs(math.degrees(math.remainder(res.yaw_rad - yaw,
                                                                 2 * math.pi)))
        else:
            row["reason"] = f"{res.reason}: {res.detail}"
        out[label] = row
    return out


def main_ceilrun(a: argparse.Namespace) -> None:
    results = [bench_ceilrun(m, a.scale, a.repeats) for m in ("lights", "corridor")]
    for r in results:
        print(f"{r['method']} estimator on a {r['size'][0]}x{r['size'][1]} simulated frame "
              f"(render {r['render_s']:.1f} s)")
        for label in ("working", "full"):
            m = r[label]
            what = "position" if r["method"] == "lights" else "lateral"
            res = (f"{what} error {m['pos_err_mm']:.2f} mm, yaw {m['yaw_err_deg']:.4f} deg, "
                   f"quality {m['quality']:.2f}" if m["ok"] else m["reason"])
            print(f"  {label:<8} factor {m['factor']}: build {m['build_ms']:.0f} ms "
                  f"(peak {m['build_peak_mb']:.0f} MB), estimate {m['estimate_ms']:.1f} ms "
                  f"(peak {m['estimate_peak_mb']:.0f} MB); {res}")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "ceilrun.json").write_text(json.dumps(results, indent=1))
    print(f"saved {a.out / 'ceilrun.json'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=3000)
    ap.add_argument("--charuco", action="store_true", help="also a ChArUco board")
    ap.add_argument("--no-full", action="store_true", help="skip the full-resolution run")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/large"))
    ap.add_argument("--ceilrun", action="store_true",
                    help="the lights estimator on a large frame instead")
    ap.add_argument("--scale", type=float, default=6.25)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    cv2.setNumThreads(1)
    if a.ceilrun:
        main_ceilrun(a)
        return
    boards: list[Board] = [ChessBoard(9, 6, 0.03)]
    if a.charuco:
        boards.append(CharucoBoard(7, 5, 0.04, 0.03))
    results = [bench(b, a.views, a.width, a.height, not a.no_full) for b in boards]
    print(f"{'board':<22} {'run':<10} {'found':>5} {'s/view':>7} {'RMS px':>7} "
          f"{'fx rel':>9} {'cx px':>7} {'cy px':>7} {'model max px':>12}")
    for r in results:
        for run_name in ("decimated", "full", "downscale"):
            if run_name not in r:
                continue
            m = r[run_name]
            print(f"{r['board']:<22} {run_name:<10} {m['views_found']:>5} "
                  f"{m['s_per_view']:>7.2f} {m['rms_px']:>7.3f} {m['fx_rel']:>9.2e} "
                  f"{m['cx_px']:>7.2f} {m['cy_px']:>7.2f} {m['model_max_px']:>12.3f}")
        print(f"  ({r['size'][0]}x{r['size'][1]}, decimation {r['factor']}, "
              f"render {r['render_s']:.1f} s for {r['views']} views)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MB")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "large.json").write_text(json.dumps({"results": results, "peak_rss_mb": peak},
                                                 indent=1))
    print(f"saved {a.out / 'large.json'}")


if __name__ == "__main__":
    main()
