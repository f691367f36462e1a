"""Upward (lights) rig mount calibration on simulated 60 s drives (issue 13).

For each seed: a random true mount (pan within +-10 deg, tilt 90, lever arm within
+-0.3 / +-0.2 m, height 0.4-0.7 m) on configs/lights' wide-angle camera, a 60 s weaving
drive under configs/lights' 40 spot lights, rendered at 1.5 fps (90 frames), spots
detected, the mount fitted from the nominal start (pan 0, x = y = 0, z 0.5) with the
truth poses at the frame stamps. Then the same frames with "motion capture" poses: 120 Hz
rows at their own stamps, 7 ms ahead of the frame clock, interpolated and the offset
estimated. Prints each seed's errors and 1 sigma and writes
benchmarks/out/bench_mount_upward.json.

Targets: pan within 0.1 deg, lever arm within 5 mm, height within 5 mm, each inside 3
reported sigma; offset within 1 ms; mocap mount unchanged from the exact one within sigma.

    python benchmarks/bench_mount_upward.py [--seeds 10] [--frames 90]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from ceilkit.calib.mount_upward import StampedPoses, calibrate_mount_upward, observe
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.sim.render import SimOptions, render_frame, straight_drive

ROOT = Path(__file__).resolve().parents[1]
DENSE_HZ = 6000          # the continuous drive, sampled finely
MOCAP_EVERY = 50         # 120 Hz
OFFSET_SAMPLES = 42      # 7 ms


def run_seed(seed: int, frames: int, site: Site, base: Rig) -> dict:
    rng = np.random.default_rng(1000 + seed)
    true = Mount(math.radians(rng.uniform(-10, 10)), math.pi / 2, 0.0,
                 float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.2, 0.2)),
                 float(rng.uniform(0.4, 0.7)))
    rig = base.with_mount(true)
    n_dense = 60 * DENSE_HZ
    dense = straight_drive(n_dense, fps=DENSE_HZ, speed_mps=0.18, x0_m=0.5, y_m=0.0,
                           weave_m=2.5, weave_period_m=5.0,
                           yaw_wobble_rad=math.radians(20), rng=np.random.default_rng(seed))
    step = n_dense // frames
    ks = np.arange(OFFSET_SAMPLES + 17, n_dense - OFFSET_SAMPLES, step)[:frames]
    lf = []
    for i, k in enumerate(ks):
        x, y, yaw = dense.pose(int(k))
        img = render_frame(rig, site, x, y, yaw, SimOptions(), np.random.default_rng([seed, i]))
        lf.append(observe(rig, img, int(dense.t_ns[k]), f"frame {i}"))
    start = base.with_mount(Mount(0.0, math.pi / 2, 0.0, 0.0, 0.0, 0.5))
    exact = StampedPoses(dense.t_ns[ks], dense.x_m[ks], dense.y_m[ks], dense.yaw_rad[ks])
    t0 = time.perf_counter()
    res = calibrate_mount_upward(start, site, lf, exact)
    fit_s = time.perf_counter() - t0
    # mocap: row j stamped j/120 s on the mocap clock, which runs 7 ms ahead
    js = np.arange(OFFSET_SAMPLES, n_dense, MOCAP_EVERY)
    src = js - OFFSET_SAMPLES
    mocap = StampedPoses(dense.t_ns[js], dense.x_m[src], dense.y_m[src], dense.yaw_rad[src])
    mres = calibrate_mount_upward(start, site, lf, mocap, estimate_offset=True)

    def errs(r) -> dict:
        m = r.mount
        return {"pan_deg": math.degrees(math.remainder(r.heading_rad - true.pan_rad,
                                                       2 * math.pi)),
                "mx_mm": 1000 * (m.x_m - true.x_m), "my_mm": 1000 * (m.y_m - true.y_m),
                "z_mm": 1000 * (m.z_m - true.z_m)}

    def sig(r) -> dict:
        return {"pan_deg": math.degrees(r.sigma["pan"]), "mx_mm": 1000 * r.sigma["mx"],
                "my_mm": 1000 * r.sigma["my"], "z_mm": 1000 * r.sigma["mz"]}

    return {"seed": seed, "frames": len(lf), "sightings": res.matches,
            "rms_px": res.rms_px, "fit_s": fit_s, "err": errs(res), "sigma": sig(res),
            "tilt_deg": math.degrees(res.mount.tilt_rad),
            "mocap_err": errs(mres), "mocap_sigma": sig(mres),
            "offset_ms": 1000 * mres.offset_s, "offset_sigma_ms": 1000 * mres.sigma["offset"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--frames", type=int, default=90)
    a = ap.parse_args()
    site = Site.load(ROOT / "configs/lights/site.yaml")
    base = Rig.load(ROOT / "configs/lights/rig.yaml")
    rows = []
    limits = {"pan_deg": 0.1, "mx_mm": 5.0, "my_mm": 5.0, "z_mm": 5.0}
    for seed in range(a.seeds):
        r = run_seed(seed, a.frames, site, base)
        rows.append(r)
        e, s, me = r["err"], r["sigma"], r["mocap_err"]
        print(f"seed {seed}: " + ", ".join(
            f"{k} {e[k]:+.4f} (sigma {s[k]:.4f}, {abs(e[k]) / s[k]:.1f} s)" for k in e)
            + f"; rms {r['rms_px']:.3f} px, fit {r['fit_s']:.1f} s; mocap offset "
            f"{r['offset_ms']:+.3f} ms (true +7, sigma {r['offset_sigma_ms']:.3f}), mocap - "
            "exact: " + ", ".join(f"{k} {me[k] - e[k]:+.4f}" for k in e), flush=True)
    summary = {}
    for k, lim in limits.items():
        ab = np.array([abs(r["err"][k]) for r in rows])
        ns = np.array([abs(r["err"][k]) / r["sigma"][k] for r in rows])
        dm = np.array([abs(r["mocap_err"][k] - r["err"][k]) / r["sigma"][k] for r in rows])
        summary[k] = {"max_abs": float(ab.max()), "limit": lim, "max_sigmas": float(ns.max()),
                      "within_limit": bool((ab <= lim).all()), "within_3_sigma":
                      bool((ns <= 3).all()), "mocap_minus_exact_max_sigmas": float(dm.max())}
        print(f"{k}: max |err| {ab.max():.4f} (limit {lim}), max {ns.max():.2f} sigma, "
              f"mocap - exact at most {dm.max():.2f} sigma")
    off = np.array([r["offset_ms"] - 7.0 for r in rows])
    summary["offset_ms"] = {"max_abs_err": float(np.abs(off).max()), "limit": 1.0}
    print(f"offset: max |err| {np.abs(off).max():.3f} ms (limit 1 ms)")
    out = ROOT / "benchmarks/out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_mount_upward.json").write_text(json.dumps(
        {"seeds": a.seeds, "frames": a.frames, "rows": rows, "summary": summary}, indent=1))
    print(f"wrote {out / 'bench_mount_upward.json'}")


if __name__ == "__main__":
    main()
