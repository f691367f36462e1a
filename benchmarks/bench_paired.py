"""The tracked path against the global path on the same frames, paired (issue 18).

Issue 18 asks that each method's tracked path (``--option track=true``) be no less
accurate than its global path on the same frames. ``bench_all.py`` compares the two as
``ceilrun`` runs them (the tracked entry's own track, a scheduled global search every
``track_full_every`` frames); here every frame is measured both ways:

* **global**: the estimator with no prior (every frame on its own);
* **tracked**: the same estimator with ``track=true`` and no scheduled global search,
  given the true pose moved by a tracker's typical prediction error (``--prior-sigma``:
  1 cm and 0.1 deg by default) as its prior; a frame counts only when the tracked path
  itself made the fix (lights and block ``mode`` ``window``, corridor ``hypothesis``
  ``window``), not its global fallback.

Per method: the frames both paths localized, the medians and 95th percentiles of the
yaw and position errors (corridor: the lateral error) of each, their mean signed errors
(a bias both share is the scene's, not the path's), and the median error's difference
with a 95 % bootstrap interval: an interval that holds 0 is no measurable difference.

The recordings are ``bench_all.py``'s drives (``--frames``, default 300: a longer drive
than bench_all's timing run, so that a few hundredths of a millimetre can be told from
noise). Output: a table and ``benchmarks/out/bench_paired.csv`` with bench_all's
provenance header.

    .venv/bin/python benchmarks/bench_paired.py [--frames 300] [--methods lights,corridor,block]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_all import OUT, load, make_recordings, provenance  # noqa: E402
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.estimators.base import PoseEstimate  # noqa: E402
from ceilkit.runtime.estimators.registry import make_estimator  # noqa: E402

TRACKED = {"lights": ("mode", "window"), "block": ("mode", "window"),
           "corridor": ("hypothesis", "window")}
COLUMNS = ["method", "frames", "paired", "path", "yaw_err_med_deg", "yaw_err_p95_deg",
           "yaw_bias_deg", "pos_err_med_mm", "pos_err_p95_mm", "pos_bias_x_mm",
           "pos_bias_y_mm", "yaw_med_diff_deg", "yaw_med_diff_lo", "yaw_med_diff_hi",
           "pos_med_diff_mm", "pos_med_diff_lo", "pos_med_diff_hi"]


def errors(est: PoseEstimate, truth: np.ndarray) -> tuple[float, float, float, float]:
    """``(signed yaw deg, position mm, signed x mm, signed y mm)`` of an estimate; a
    corridor estimate (no x) is its lateral error, x 0."""
    x, y, yaw = truth
    d_yaw = math.degrees(math.remainder(est.yaw_rad - yaw, 2 * math.pi))
    dx = 0.0 if est.x_m is None else 1e3 * (est.x_m - x)
    dy = 1e3 * (est.y_m - y)
    return d_yaw, math.hypot(dx, dy), dx, dy


def paired(method: str, folder: Path, frames: int, sigma: tuple[float, float],
           seed: int) -> tuple[int, np.ndarray, np.ndarray]:
    """``(frames, global errors (K, 4), tracked errors (K, 4))`` over the frames both
    paths localized with the tracked path's own fix."""
    rec = next(r for r in make_recordings(folder, frames, False) if r.name.startswith(method))
    data = load(rec)
    glob = make_estimator(method, data.rig, data.site, stated(method, {}))
    tracked = make_estimator(method, data.rig, data.site,
                             stated(method, {"track": True, "track_full_every": 0}))
    key, value = TRACKED[method]
    rng = np.random.default_rng(seed)
    eg, et = [], []
    for grey, t_ns, truth in zip(data.grey, data.t_ns, data.truth, strict=True):
        x, y, yaw = truth
        prior = PoseEstimate(t_ns, "prior", x + rng.normal(0, sigma[0]),
                             y + rng.normal(0, sigma[0]), yaw + rng.normal(0, sigma[1]), 1.0)
        g = glob.estimate(grey, t_ns, None)
        t = tracked.estimate(grey, t_ns, prior)
        if not g or not t or t.diagnostics.get(key) != value or g.y_m is None:
            continue
        eg.append(errors(g, truth))
        et.append(errors(t, truth))
    return len(data.grey), np.array(eg).reshape(-1, 4), np.array(et).reshape(-1, 4)


def median_diff(a: np.ndarray, b: np.ndarray, rng: np.random.Generator,
                n: int = 2000) -> tuple[float, float, float]:
    """``median(a) - median(b)`` and its 95 % interval, the pairs resampled together."""
    k = a.size
    idx = rng.integers(0, k, (n, k))
    boot = np.median(a[idx], axis=1) - np.median(b[idx], axis=1)
    return (float(np.median(a) - np.median(b)), float(np.percentile(boot, 2.5)),
            float(np.percentile(boot, 97.5)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--methods", default="lights,corridor,block")
    ap.add_argument("--prior-sigma", type=float, nargs=2, default=(0.01, 0.1),
                    metavar=("M", "DEG"), help="the prior's error: position (m), yaw (deg)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT / "bench_paired.csv")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    folder = OUT / "recordings"
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    rows = []
    print(f"{'method':9s} {'path':8s} {'paired':>7s}  yaw med/p95 (bias) deg"
          f"        pos med/p95 mm (bias x, y)")
    for method in a.methods.split(","):
        n, eg, et = paired(method, folder, a.frames,
                           (a.prior_sigma[0], math.radians(a.prior_sigma[1])), a.seed)
        if eg.shape[0] < 2:
            print(f"{method:9s} fewer than 2 frames both paths localized")
            continue
        yaw_d = median_diff(np.abs(et[:, 0]), np.abs(eg[:, 0]), rng)
        pos_d = median_diff(et[:, 1], eg[:, 1], rng)
        for path, e in (("global", eg), ("tracked", et)):
            row = {"method": method, "frames": n, "paired": e.shape[0], "path": path,
                   "yaw_err_med_deg": float(np.median(np.abs(e[:, 0]))),
                   "yaw_err_p95_deg": float(np.percentile(np.abs(e[:, 0]), 95)),
                   "yaw_bias_deg": float(e[:, 0].mean()),
                   "pos_err_med_mm": float(np.median(e[:, 1])),
                   "pos_err_p95_mm": float(np.percentile(e[:, 1], 95)),
                   "pos_bias_x_mm": float(e[:, 2].mean()), "pos_bias_y_mm": float(e[:, 3].mean())}
            if path == "tracked":
                row.update(zip(COLUMNS[11:14], yaw_d, strict=True))
                row.update(zip(COLUMNS[14:17], pos_d, strict=True))
            rows.append(row)
            print(f"{method:9s} {path:8s} {e.shape[0]:4d}/{n:<4d} "
                  f"{row['yaw_err_med_deg']:.4f}/{row['yaw_err_p95_deg']:.4f} "
                  f"({row['yaw_bias_deg']:+.4f})   {row['pos_err_med_mm']:.3f}/"
                  f"{row['pos_err_p95_mm']:.3f} ({row['pos_bias_x_mm']:+.3f}, "
                  f"{row['pos_bias_y_mm']:+.3f})")
        print(f"{'':9s} tracked - global, median: yaw {yaw_d[0]:+.5f} deg "
              f"[{yaw_d[1]:+.5f}, {yaw_d[2]:+.5f}], position {pos_d[0]:+.4f} mm "
              f"[{pos_d[1]:+.4f}, {pos_d[2]:+.4f}] (95 % bootstrap)")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w", newline="") as f:
        for line in provenance("bench_paired.py", load_before, os.getloadavg(),
                               [f"# prior error sigma {a.prior_sigma[0]} m, "
                                f"{a.prior_sigma[1]} deg; seed {a.seed}"]):
            f.write(line + "\n")
        w = csv.DictWriter(f, COLUMNS)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
