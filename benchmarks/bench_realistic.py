"""Realistic ceilings (issue 16): simulated drives with the site's ``realistic`` preset
and with each of its knobs alone (at the preset's strength), for ``corridor`` and
``lights``. Per case:

* ``est_pct``: frames with a PoseEstimate (not a Failure), of all frames;
* ``yaw_med_deg``: median |heading error| of the estimates;
* ``pos_med_mm``: median lateral |y error| (corridor) or |xy error| (lights);
* ``bad_valid``: published valid poses (quality >= 0.5) wrong by > 10 cm or > 2 deg
  (target: none);
* ``cov_small_pct``: estimates whose covariance is smaller than their error: the NEES
  over the observed coordinates above its chi-square 99 % quantile (a consistent
  covariance gives ~1 %; target <= 1 %).

The estimator runs as on the vehicle: each frame's prior is the tracker's prediction
(:class:`~ceilkit.runtime.tracking.Tracker`, fed every estimate; it carries the track's
velocity), and the estimator is told the camera's readout time (``readout_ms``, the
case's ``rolling_shutter_ms``; ``--no-readout``: left at 0, a global shutter assumed).
Prints the table and saves it as CSV in ``--out``.

    .venv/bin/python benchmarks/bench_realistic.py [--frames 20] [--out benchmarks/out/realistic]
        [--methods lights] [--option spot_stage=windowed]
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.sim.realism import Realism, load_preset
from ceilkit.runtime.sim.render import SimSource, straight_drive
from ceilkit.runtime.tracking import Tracker

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DRIVES = {
    # a weaving drive down the corridor, 0.8 m/s, heading wobble 4 deg
    "corridor": dict(speed_mps=0.8, x0_m=0.0, y_m=0.1, weave_m=0.25,
                     yaw_wobble_rad=math.radians(4.0)),
    # a drive across the hall at 30 deg, 0.8 m/s
    "lights": dict(speed_mps=0.8, x0_m=2.0, y_m=-2.5, yaw_rad=math.radians(30.0),
                   weave_m=0.3),
}
FIELDS = ["method", "case", "frames", "est_pct", "yaw_med_deg", "pos_med_mm", "bad_valid",
          "cov_small_pct", "reasons", "s_per_frame"]


def _median(a: list[float]) -> float:
    return float(np.nanmedian(a)) if a else math.nan


def run_case(method: str, realism: Realism | None, frames: int, seed: int,
             readout: bool = True, options: dict[str, str] | None = None) -> dict:
    rig = Rig.load(CONFIGS / method / "rig.yaml")
    site = Site.load(CONFIGS / method / "site.yaml")
    ro = realism.rolling_shutter_ms if realism is not None and readout else 0.0
    est = make_estimator(method, rig, site,
                         stated(method, {"readout_ms": ro, **(options or {})}))
    traj = straight_drive(frames, 30.0, rng=np.random.default_rng(seed), **DRIVES[method])
    src = SimSource(rig, site, traj, seed=seed, realism=realism)
    tracker = Tracker()
    yaw_err, pos_err, bad, small, n_est = [], [], 0, 0, 0
    reasons: dict[str, int] = {}
    t0 = time.perf_counter()
    for k in range(frames):
        f = src.render(k)
        e = est.estimate(f.image, f.t_ns, tracker.predict(f.t_ns))
        tracker.update(e)
        if not isinstance(e, PoseEstimate):
            reasons[e.reason] = reasons.get(e.reason, 0) + 1
            continue
        n_est += 1
        x, y, yaw = src.pose(k)
        d_yaw = float(wrap_pi(e.yaw_rad - yaw))
        err, idx = [], []
        if e.x_m is not None:
            err.append(e.x_m - x)
            idx.append(0)
        if e.y_m is not None:
            err.append(e.y_m - y)
            idx.append(1)
        err.append(d_yaw)
        idx.append(2)
        pos = math.hypot(*err[:-1]) if len(err) > 1 else math.nan
        yaw_err.append(abs(math.degrees(d_yaw)))
        pos_err.append(pos)
        if e.quality >= 0.5 and (pos > 0.10 or abs(math.degrees(d_yaw)) > 2.0):
            bad += 1
        c = np.asarray(e.cov, float)[np.ix_(idx, idx)]
        ev = np.asarray(err)
        try:
            nees = float(ev @ np.linalg.solve(c, ev))
        except np.linalg.LinAlgError:
            nees = math.inf
        small += not (nees <= chi2.ppf(0.99, len(idx)))
    s = (time.perf_counter() - t0) / frames
    return {"frames": frames, "est_pct": 100.0 * n_est / frames,
            "yaw_med_deg": _median(yaw_err), "pos_med_mm": 1e3 * _median(pos_err),
            "bad_valid": bad, "cov_small_pct": 100.0 * small / n_est if n_est else math.nan,
            "reasons": ";".join(f"{r}={n}" for r, n in sorted(reasons.items())),
            "s_per_frame": s}


def cases(method: str, only: list[str] | None) -> list[tuple[str, Realism | None]]:
    real = load_preset(CONFIGS / method / "site.yaml", "realistic")
    out = [("clean", None), ("realistic", real)] + [(k, real.only(k)) for k in real.on]
    return [c for c in out if not only or c[0] in only]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--methods", default="corridor,lights")
    ap.add_argument("--cases", default="", help="comma-separated case names (all if empty)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/realistic"))
    ap.add_argument("--no-readout", action="store_true",
                    help="leave the estimators' readout_ms at 0 (a global shutter assumed)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="an estimator option for every method run (as ceilrun --option)")
    a = ap.parse_args()
    bad = [o for o in a.option if "=" not in o]
    if bad:
        ap.error(f"--option {bad[0]!r}: expected KEY=VALUE")
    options = dict(o.split("=", 1) for o in a.option)
    a.out.mkdir(parents=True, exist_ok=True)
    only = [c for c in a.cases.split(",") if c] or None
    rows = []
    print(" | ".join(FIELDS))
    for method in a.methods.split(","):
        for name, real in cases(method, only):
            r = {"method": method, "case": name,
                 **run_case(method, real, a.frames, a.seed, not a.no_readout, options)}
            rows.append(r)
            print(" | ".join(f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k])
                             for k in FIELDS), flush=True)
    path = a.out / "realistic.csv"
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, FIELDS)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
