"""The window search against the global path on the same frames, paired (issues 18, 38).

Issue 38 turned each method's window search (``--option window_search=true``, formerly
``track``) on by default once a paired run on every bench case showed it no less
accurate than the global path. Every frame is estimated twice, with the same prior:

* **global**: the estimator with ``window_search=false`` (the default before issue 38:
  the lights' association about the prior, the corridor's and block's global search
  with the prior choosing among twins);
* **window**: the same estimator with ``window_search=true`` and no scheduled global
  search (``window_full_every=0``); where the window check or the prior's region
  refuses a fix, its global fallback decides the frame.

The prior is the true pose moved by a tracker's typical prediction error
(``--prior-sigma``: 1 cm and 0.1 deg by default), with that covariance, and no velocity
(``--velocity``: the truth's, as a track's prior carries it, which the rolling
shutter's rows use). Cases
(``--cases``):

* **clean**: ``bench_all.py``'s drives, read back as SPEC recordings (``--frames``,
  default 300);
* **realistic**: the same drives rendered with each site's ``realistic`` preset
  (``configs/*/presets.yaml``: clutter, people, flicker, motion blur, a 25 ms rolling
  shutter, auto-exposure, JPEG), the estimators told the readout time
  (``readout_ms``), ``--sim-frames`` frames (default 60);
* **rolling_shutter**: the preset's rolling shutter alone (25 ms), told as above
  (``--no-readout``: both realism cases with ``readout_ms`` left at 0, a global shutter
  assumed; the lights' window tracker, which does not model the readout, runs only
  then; the corridor's runs with the readout only when the prior carries a velocity,
  ``--velocity``: ``corridor.track.window_applies``, so without it those cases have no
  corridor window fix);
* **kidnap**: the clean frames with the prior of the frame half a drive away (the
  vehicle carried elsewhere, no odometry seeing it).

Accuracy is compared over the frames the window search itself fixed (lights and block
``mode`` ``window``, corridor ``hypothesis`` ``window``) where the global path gave a
pose: the medians and 95th percentiles of the yaw and position errors (corridor: the
lateral error) of each, their mean signed errors, and the median error's difference
and the p95's difference, each with a 95 % bootstrap interval (an interval that holds
0 is no measurable difference).
Over all frames: the poses each gave and the **wrong** ones (more than 10 cm or 2 deg
off); ``no_worse``: no difference of the medians or the p95s (window - global, yaw and
position) whose 95 % bootstrap interval lies above 0, and no more wrong poses.

Output: a table and ``benchmarks/out/bench_paired.csv`` with bench_all's provenance
header.

    .venv/bin/python benchmarks/bench_paired.py [--frames 300] [--sim-frames 60]
        [--methods lights,corridor,block] [--cases clean,realistic,rolling_shutter,kidnap]
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
from bench_realistic import DRIVES  # noqa: E402
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.config.rig import Rig  # noqa: E402
from ceilkit.runtime.config.site import Site  # noqa: E402
from ceilkit.runtime.estimators.base import PoseEstimate  # noqa: E402
from ceilkit.runtime.estimators.registry import make_estimator  # noqa: E402
from ceilkit.runtime.features.grey import to_grey  # noqa: E402
from ceilkit.runtime.sim.realism import load_preset  # noqa: E402
from ceilkit.runtime.sim.render import SimSource, straight_drive  # noqa: E402

CONFIGS = ROOT / "configs"
CASES = ("clean", "realistic", "rolling_shutter", "kidnap")
DRIVE = {**DRIVES, "block": dict(speed_mps=0.8, x0_m=0.3, y_m=0.0, weave_m=0.2)}
"""bench_all's drives (its ``make_recordings``), rendered again with realism."""
WINDOW = {"lights": ("mode", "window"), "block": ("mode", "window"),
          "corridor": ("hypothesis", "window")}
WRONG = (0.10, 2.0)          # m, deg: a pose further off is wrong
COLUMNS = ["method", "case", "frames", "window_fixes", "paired", "path", "poses", "wrong",
           "yaw_err_med_deg", "yaw_err_p95_deg", "yaw_bias_deg", "pos_err_med_mm",
           "pos_err_p95_mm", "pos_bias_x_mm", "pos_bias_y_mm", "yaw_med_diff_deg",
           "yaw_med_diff_lo", "yaw_med_diff_hi", "pos_med_diff_mm", "pos_med_diff_lo",
           "pos_med_diff_hi", "yaw_p95_diff_deg", "yaw_p95_diff_lo", "yaw_p95_diff_hi",
           "pos_p95_diff_mm", "pos_p95_diff_lo", "pos_p95_diff_hi", "no_worse"]


def errors(est: PoseEstimate, truth: np.ndarray) -> tuple[float, float, float, float]:
    """``(signed yaw deg, position mm, signed x mm, signed y mm)`` of an estimate; a
    corridor estimate (no x) is its lateral error, x 0."""
    x, y, yaw = truth
    d_yaw = math.degrees(math.remainder(est.yaw_rad - yaw, 2 * math.pi))
    dx = 0.0 if est.x_m is None else 1e3 * (est.x_m - x)
    dy = 1e3 * (est.y_m - y)
    return d_yaw, math.hypot(dx, dy), dx, dy


def frames_of(method: str, case: str, folder: Path, frames: int, sim_frames: int,
              seed: int) -> tuple[Rig, Site, list, float]:
    """``(rig, site, [(grey, t_ns, truth (3,))], readout_ms)`` of one case."""
    if case in ("clean", "kidnap"):
        rec = next(r for r in make_recordings(folder, frames, False)
                   if r.name.startswith(method))
        data = load(rec)
        return data.rig, data.site, list(zip(data.grey, data.t_ns, data.truth,
                                             strict=True)), 0.0
    rig = Rig.load(CONFIGS / method / "rig.yaml")
    site = Site.load(CONFIGS / method / "site.yaml")
    real = load_preset(CONFIGS / method / "site.yaml", "realistic")
    if case != "realistic":
        real = real.only("rolling_shutter_ms")
    traj = straight_drive(sim_frames, 30.0, rng=np.random.default_rng(5), **DRIVE[method])
    src = SimSource(rig, site, traj, seed=seed, realism=real)
    out = []
    for k in range(sim_frames):
        f = src.render(k)
        out.append((np.ascontiguousarray(to_grey(f.image)), int(f.t_ns),
                    np.array(src.pose(k), float)))
    return rig, site, out, real.rolling_shutter_ms


def velocity(frames: list, k: int) -> tuple[float, float, float]:
    """The truth's velocity at frame ``k`` ``(vx m/s, vy m/s, yaw rate rad/s)`` in W, a
    central difference of the frames beside it (one-sided at the ends): what a track's
    prior carries (``--velocity``)."""
    a, b = frames[max(k - 1, 0)], frames[min(k + 1, len(frames) - 1)]
    dt = max((b[1] - a[1]) * 1e-9, 1e-9)
    d = np.asarray(b[2], float) - np.asarray(a[2], float)
    return float(d[0] / dt), float(d[1] / dt), float(math.remainder(d[2], 2 * math.pi) / dt)


def paired(method: str, case: str, folder: Path, a: argparse.Namespace
           ) -> dict[str, object]:
    """Both paths on every frame of a case (see the module docstring): the frames, the
    window fixes, the errors of both over the frames the window search fixed, and each
    path's poses and wrong poses over all frames."""
    rig, site, frames, readout_ms = frames_of(method, case, folder, a.frames, a.sim_frames,
                                             a.seed)
    base = {"readout_ms": 0.0 if a.no_readout else readout_ms} if method != "block" else {}
    glob = make_estimator(method, rig, site, stated(method, {**base, "window_search": False}))
    win = make_estimator(method, rig, site, stated(method, {**base, "window_search": True,
                                                            "window_full_every": 0}))
    sp, sr = a.prior_sigma[0], math.radians(a.prior_sigma[1])
    cov = np.diag([sp * sp, sp * sp, sr * sr])
    key, value = WINDOW[method]
    rng = np.random.default_rng(a.seed)
    eg, ew, fixes = [], [], 0
    poses, wrong = {"global": 0, "window": 0}, {"global": 0, "window": 0}
    n = len(frames)
    for k, (grey, t_ns, truth) in enumerate(frames):
        x, y, yaw = frames[(k + n // 2) % n][2] if case == "kidnap" else truth
        prior = PoseEstimate(t_ns, "prior", x + rng.normal(0, sp), y + rng.normal(0, sp),
                             yaw + rng.normal(0, sr), 1.0, None, cov,
                             velocity=velocity(frames, k) if a.velocity else None)
        got = {"global": glob.estimate(grey, t_ns, prior),
               "window": win.estimate(grey, t_ns, prior)}
        for path, e in got.items():
            if e and e.y_m is not None:
                poses[path] += 1
                d_yaw, d_pos = errors(e, truth)[:2]
                wrong[path] += d_pos > 1e3 * WRONG[0] or abs(d_yaw) > WRONG[1]
        g, w = got["global"], got["window"]
        fixes += bool(w) and w.diagnostics.get(key) == value
        if not g or not w or w.diagnostics.get(key) != value or g.y_m is None:
            continue
        eg.append(errors(g, truth))
        ew.append(errors(w, truth))
    return {"frames": n, "window_fixes": fixes, "poses": poses, "wrong": wrong,
            "global": np.array(eg).reshape(-1, 4), "window": np.array(ew).reshape(-1, 4)}


def stat_diff(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, q: float = 50.0,
              n: int = 2000) -> tuple[float, float, float]:
    """``percentile(a, q) - percentile(b, q)`` and its 95 % interval, the pairs
    resampled together."""
    k = a.size
    idx = rng.integers(0, k, (n, k))
    boot = np.percentile(a[idx], q, axis=1) - np.percentile(b[idx], q, axis=1)
    return (float(np.percentile(a, q) - np.percentile(b, q)),
            float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5)))


def summary(e: np.ndarray) -> dict[str, float]:
    """The medians, p95s and mean signed errors of ``errors`` rows ``(K, 4)``."""
    return {"yaw_err_med_deg": float(np.median(np.abs(e[:, 0]))),
            "yaw_err_p95_deg": float(np.percentile(np.abs(e[:, 0]), 95)),
            "yaw_bias_deg": float(e[:, 0].mean()),
            "pos_err_med_mm": float(np.median(e[:, 1])),
            "pos_err_p95_mm": float(np.percentile(e[:, 1], 95)),
            "pos_bias_x_mm": float(e[:, 2].mean()), "pos_bias_y_mm": float(e[:, 3].mean())}


def no_worse(diffs: list[tuple[float, float, float]], wrong: dict[str, int]) -> bool:
    """No difference (window - global: the yaw and position medians and p95s) whose
    95 % interval lies above 0, and no more wrong poses."""
    return all(lo <= 0.0 for _, lo, _ in diffs) and wrong["window"] <= wrong["global"]


def report(method: str, case: str, r: dict[str, object], rng: np.random.Generator
           ) -> list[dict[str, object]]:
    """The two rows (global, window) of one method and case, printed."""
    eg, ew = r["global"], r["window"]
    common = {"method": method, "case": case, "frames": r["frames"],
              "window_fixes": r["window_fixes"], "paired": eg.shape[0]}
    if eg.shape[0] < 2:
        rows = [{**common, "path": p, "poses": r["poses"][p], "wrong": r["wrong"][p],
                 "no_worse": r["wrong"]["window"] <= r["wrong"]["global"] if p == "window"
                 else ""} for p in ("global", "window")]
        for row in rows:
            print(f"{method:9s} {case:16s} {row['path']:7s} window fixes {r['window_fixes']:4d}"
                  f"/{r['frames']:<4d} poses {row['poses']:4d} wrong {row['wrong']:3d}"
                  f"  (fewer than 2 paired frames)")
        return rows
    yaw_d = stat_diff(np.abs(ew[:, 0]), np.abs(eg[:, 0]), rng)
    pos_d = stat_diff(ew[:, 1], eg[:, 1], rng)
    yaw_p = stat_diff(np.abs(ew[:, 0]), np.abs(eg[:, 0]), rng, 95.0)
    pos_p = stat_diff(ew[:, 1], eg[:, 1], rng, 95.0)
    sg, sw = summary(eg), summary(ew)
    rows = []
    for path, sm in (("global", sg), ("window", sw)):
        row = {**common, "path": path, "poses": r["poses"][path], "wrong": r["wrong"][path],
               **sm}
        if path == "window":
            for at, d in zip((15, 18, 21, 24), (yaw_d, pos_d, yaw_p, pos_p), strict=True):
                row.update(zip(COLUMNS[at:at + 3], d, strict=True))
            row["no_worse"] = no_worse([yaw_d, pos_d, yaw_p, pos_p], r["wrong"])
        rows.append(row)
        print(f"{method:9s} {case:16s} {path:7s} {eg.shape[0]:4d}/{r['frames']:<4d} "
              f"poses {row['poses']:4d} wrong {row['wrong']:3d}  "
              f"{sm['yaw_err_med_deg']:.4f}/{sm['yaw_err_p95_deg']:.4f} "
              f"({sm['yaw_bias_deg']:+.4f})   {sm['pos_err_med_mm']:.3f}/"
              f"{sm['pos_err_p95_mm']:.3f} ({sm['pos_bias_x_mm']:+.3f}, "
              f"{sm['pos_bias_y_mm']:+.3f})")
    print(f"{'':26s} window - global, median: yaw {yaw_d[0]:+.5f} deg "
          f"[{yaw_d[1]:+.5f}, {yaw_d[2]:+.5f}], position {pos_d[0]:+.4f} mm "
          f"[{pos_d[1]:+.4f}, {pos_d[2]:+.4f}]; p95: yaw {yaw_p[0]:+.5f} deg "
          f"[{yaw_p[1]:+.5f}, {yaw_p[2]:+.5f}], position {pos_p[0]:+.4f} mm "
          f"[{pos_p[1]:+.4f}, {pos_p[2]:+.4f}] (95 % bootstrap); no worse: "
          f"{rows[1]['no_worse']}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--sim-frames", type=int, default=60)
    ap.add_argument("--methods", default="lights,corridor,block")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--prior-sigma", type=float, nargs=2, default=(0.01, 0.1),
                    metavar=("M", "DEG"), help="the prior's error: position (m), yaw (deg)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-readout", action="store_true",
                    help="leave readout_ms at 0 in the realism cases (a global shutter assumed)")
    ap.add_argument("--velocity", action="store_true",
                    help="the prior carries the truth's velocity, as a track's does")
    ap.add_argument("--out", type=Path, default=OUT / "bench_paired.csv")
    a = ap.parse_args()
    bad = sorted(set(a.cases.split(",")) - set(CASES))
    if bad:
        ap.error(f"unknown case {bad[0]!r} (choose from {', '.join(CASES)})")
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    folder = OUT / "recordings"
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    rows = []
    print(f"{'method':9s} {'case':16s} {'path':7s} {'paired':>9s} poses wrong  "
          f"yaw med/p95 (bias) deg        pos med/p95 mm (bias x, y)")
    for method in a.methods.split(","):
        for case in a.cases.split(","):
            rows += report(method, case, paired(method, case, folder, a), rng)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w", newline="") as f:
        for line in provenance("bench_paired.py", load_before, os.getloadavg(),
                               [f"# prior error sigma {a.prior_sigma[0]} m, "
                                f"{a.prior_sigma[1]} deg; seed {a.seed}; readout "
                                f"{'not told' if a.no_readout else 'told'}"]):
            f.write(line + "\n")
        w = csv.DictWriter(f, COLUMNS)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
