"""Benchmark of the whole calibration on simulated data: `ceilcal calibrate`, then
`ceilrun replay` of a held-back drive with the calibrated rig (nothing typed in).

For each seed: rendered chessboard views through configs/corridor's lens (step 1),
five measured placements rendered with noise 2 grey levels and blur 0.8 px (step 2),
then a weaving drive replayed with the calibrated rig and, for reference, with the
true rig. Prints the mount errors with their 1 sigma, and heading / lateral median
and p95 against truth (the foundation issue's targets: heading median <= 0.05 deg,
p95 <= 0.15 deg; lateral median <= 5 mm, p95 <= 15 mm).

    .venv/bin/python benchmarks/bench_mount.py [--seeds 3] [--frames 300]
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import cv2
import numpy as np
from typer.testing import CliRunner

from ceilkit.calib.boards import parse_board, render_views
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app as ceilcal
from ceilkit.cli.ceilrun import app as ceilrun
from ceilkit.runtime.recording import Recording, load_poses
from ceilkit.runtime.rig import Rig
from ceilkit.runtime.sim import SimOptions, Trajectory, straight_drive
from ceilkit.runtime.site import Site

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "corridor"
PLACES = [(0.0, 0.0), (0.3, 0.0), (-0.3, 0.0), (0.1, 10.0), (-0.1, -12.0)]


def accuracy(rec_dir: Path, poses: Path) -> dict[str, float]:
    """Heading (deg) and lateral (mm) median / p95 of a poses.csv against truth.csv."""
    truth = Recording(rec_dir).truth
    got = load_poses(poses)
    dh, dy, n = [], [], 0
    for t, y, yaw in zip(got.t_ns, got.y_m, got.yaw_rad, strict=True):
        row = truth.lookup(int(t))
        if row is None:
            continue
        n += 1
        if math.isfinite(yaw):
            dh.append(abs(math.degrees(math.remainder(yaw - row[2], 2 * math.pi))))
        if math.isfinite(y):
            dy.append(abs(y - row[1]) * 1000)
    return {"h50": float(np.median(dh)), "h95": float(np.percentile(dh, 95)),
            "y50": float(np.median(dy)), "y95": float(np.percentile(dy, 95)),
            "est": len(dh), "n": n}


def one(seed: int, frames: int, work: Path) -> dict:
    rig, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    rng = np.random.default_rng(seed)
    boards = work / "boards"
    boards.mkdir()
    for k, (img, _, _) in enumerate(render_views(parse_board("chess:9x6", 0.04), rig.camera,
                                                 20, rng)):
        cv2.imwrite(str(boards / f"b{k:02d}.png"), img)
    xs = rng.uniform(0.0, 50.0, len(PLACES))
    traj = Trajectory(np.arange(len(PLACES), dtype=np.int64) * 10**8, xs,
                      np.array([p[0] for p in PLACES]), np.radians([p[1] for p in PLACES]))
    opts = SimOptions(noise_sigma=2.0, blur_px=0.8)
    simulate_recording(rig, site, traj, work / "pl", opts, seed=seed)
    drive = straight_drive(frames, fps=30.0, speed_mps=0.8, x0_m=60.0, y_m=0.05, weave_m=0.2,
                           yaw_wobble_rad=math.radians(4.0), rng=rng)
    simulate_recording(rig, site, drive, work / "check", opts, seed=seed + 100)
    r = CliRunner().invoke(ceilcal, ["calibrate", "--boards", str(boards), "--board",
                                     "chess:9x6", "--square", "0.04", "--placements",
                                     str(work / "pl"), "--site", str(CONFIGS / "site.yaml"),
                                     "--out", str(work / "cal")])
    if r.exit_code:
        raise SystemExit(r.output)
    got = Rig.load(work / "cal" / "rig.yaml")
    out = {"fx": got.camera.fx - rig.camera.fx, "cx": got.camera.cx - rig.camera.cx,
           "cy": got.camera.cy - rig.camera.cy}
    for name in ("tilt_rad", "swing_rad", "pan_rad"):
        out[name[:-4]] = math.degrees(getattr(got.mount, name) - getattr(rig.mount, name))
    out["y_mm"] = 1000 * (got.mount.y_m - rig.mount.y_m)
    out["x_mm"] = 1000 * (got.mount.x_m - rig.mount.x_m)
    out["z_mm"] = 1000 * (got.mount.z_m - rig.mount.z_m)
    for tag, rig_path in (("calibrated", work / "cal" / "rig.yaml"),
                          ("true", work / "check" / "rig.yaml")):
        dst = work / f"replay_{tag}"
        r = CliRunner().invoke(ceilrun, ["replay", str(work / "check"), "--out", str(dst),
                                         "--rig", str(rig_path)])
        if r.exit_code:
            raise SystemExit(r.output)
        out[tag] = accuracy(work / "check", dst / "poses.csv")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    for seed in range(args.seeds):
        with tempfile.TemporaryDirectory() as tmp:
            o = one(seed, args.frames, Path(tmp))
        print(f"seed {seed}: fx {o['fx']:+.2f} px  cx {o['cx']:+.2f}  cy {o['cy']:+.2f}  "
              f"tilt {o['tilt']:+.4f} deg  swing {o['swing']:+.4f}  pan {o['pan']:+.4f}  "
              f"y {o['y_mm']:+.2f} mm  x {o['x_mm']:+.1f}  z {o['z_mm']:+.1f}")
        for tag in ("calibrated", "true"):
            a = o[tag]
            print(f"   replay, {tag:10s} rig: heading median {a['h50']:.3f} p95 "
                  f"{a['h95']:.3f} deg; lateral median {a['y50']:.1f} p95 {a['y95']:.1f} mm; "
                  f"{a['est']}/{a['n']} estimated")


if __name__ == "__main__":
    main()
