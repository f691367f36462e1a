"""Measures the ceiling-plane odometry's noise factor (``odometry.VAR_FACTOR``): the
measured scatter of the increments against the truth over the scatter the fit reports.

    python benchmarks/calib_odometry_noise.py [--drives 4] [--frames 120] [--seed 0]
    python benchmarks/calib_odometry_noise.py --heldout 1 36 2 [--noise 2] [--stretch 15]

Drives through configs/block (0.03 m steps, weaving in y and yaw as bench_block's fused
drives), rendered with noise and blur, frames 0-3 of every 30 with the site's blocks and
markers and the rest with them painted over (so increments beside markers, across their
vanishing and on the bare tile ceiling are all measured). Each increment of
:class:`~ceilkit.runtime.estimators.odometry.PlaneOdometry` is compared with the
true motion in the earlier frame's V. Printed per kind of step (``blocks>bare``: from a
frame with blocks to one without) and for all:

* the error over the fit's own sigma (``VAR_FACTOR`` taken out), RMS per axis: its
  square is the factor a single step needs;
* the same for sums over non-overlapping stretches of ``--stretch`` steps (50: the
  legs between fixes of bench_block's fused drives; the errors' sum against the sum
  of the covariances, as a chain of white increments would carry them): a factor
  above the per-step one means errors correlated from step to step, and a white
  chain scaled by it is honest at that horizon (over-covers shorter legs, under-covers
  longer ones);
* NEES with the published covariance (``VAR_FACTOR`` in): 3 on average when honest;
* the suggested factor: the larger of the per-step and the stretch squares.

``--heldout SEED ...``: instead, the held-out marker drives of
``bench_heldout_lines.py`` (``markers`` class, 2 scenes a seed, 60 frames, noise
``--noise``, blur 0.8 at noise 2 and 1.2 above: another camera, texture and speed than
configs/block), steps grouped by scene and by whether their fit used corners detected
afresh on that step (``fresh``: a stream's first step), corners carried from the step
before while fresh ones were detected beside them (``redetect``), or carried ones
alone (``carried``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.estimators.odometry import VAR_FACTOR, PlaneOdometry
from ceilkit.runtime.sim.render import SimOptions, render_frame

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "block"
OPTIONS = SimOptions(noise_sigma=2.0, blur_px=1.0)
STRETCH = 50   # the sums' length: bench_block's fused drives cross 50 frames between fixes


def drive_steps(rig, site, rng, frames: int, step_m: float = 0.03) -> list[tuple]:
    """``(kind, error (3,), published cov (3, 3))`` of every increment of one drive."""
    bare = dataclasses.replace(site, blocks=(), markers=None)
    odo = PlaneOdometry(PlanarGeometry.of(rig, site))
    phase, amp = rng.uniform(0, 2 * math.pi), rng.uniform(0.15, 0.35)
    out, prev = [], None
    for i in range(frames):
        x = 0.3 + i * step_m
        y = amp * math.sin(x * 0.9 + phase)
        yaw = 0.3 * math.sin(x * 0.6 + phase)
        kind = "blocks" if i % 30 < 4 else "bare"
        inc = odo.step(render_frame(rig, site if kind == "blocks" else bare, x, y, yaw,
                                    OPTIONS, rng))
        if inc is not None and prev is not None:
            px, py, pyaw, pkind = prev
            c, s = math.cos(pyaw), math.sin(pyaw)
            truth = np.array([c * (x - px) + s * (y - py), -s * (x - px) + c * (y - py),
                              math.remainder(yaw - pyaw, 2 * math.pi)])
            e = np.array([inc.dx_m, inc.dy_m, inc.dyaw_rad]) - truth
            out.append((f"{pkind}>{kind}", e, np.asarray(inc.cov, float), i))
        elif inc is None and prev is not None:
            out.append((f"{prev[3]}>{kind} (none)", None, None, i))
        prev = (x, y, yaw, kind)
    return out


def heldout_steps(seed: int, noise: float) -> list[tuple]:
    """``(scene, error (3,), published cov (3, 3), frame, fresh|carried)`` of every
    increment of the held-out marker drives of ``seed`` (see the module)."""
    import bench_heldout_lines as held

    sim = dataclasses.replace(held.SIM, noise_sigma=noise, blur_px=0.8 if noise <= 2 else 1.2)
    out = []
    for n, sc in enumerate(held.scenes(seed, 2, 60, ["markers"])):
        odo = PlaneOdometry(PlanarGeometry.of(sc.rig, sc.site))
        prev = None
        for i in range(60):
            x, y, yaw = sc.traj.pose(i)
            grey = render_frame(sc.rig, sc.site, x, y, yaw, sim, np.random.default_rng([seed, i]))
            inc = odo.step(grey)
            if inc is not None and prev is not None:
                c, s = math.cos(prev[2]), math.sin(prev[2])
                dx, dy = x - prev[0], y - prev[1]
                truth = np.array([c * dx + s * dy, -s * dx + c * dy,
                                  math.remainder(yaw - prev[2], 2 * math.pi)])
                # fitted from corners detected on this step; detected on it but fitted
                # from the carried ones; carried
                kind = "fresh" if getattr(odo, "fresh_fit", odo._age == 1) else \
                    "redetect" if odo._age == 1 else "carried"
                e = np.array([inc.dx_m, inc.dy_m, inc.dyaw_rad]) - truth
                out.append((f"s{seed} {sc.name[:8]}", e, np.asarray(inc.cov, float),
                            1000 * n + i, kind))
            prev = (x, y, yaw)
    return out


def report(name: str, steps: list[tuple], stretch: int) -> np.ndarray:
    f = np.sqrt(VAR_FACTOR)
    e = np.array([s[1] for s in steps])
    cov = np.array([s[2] for s in steps])
    raw = cov / np.outer(f, f)
    sig = np.sqrt(np.diagonal(raw, axis1=1, axis2=2))
    per = np.sqrt(np.mean((e / sig) ** 2, axis=0))
    nees = np.array([x @ np.linalg.solve(c, x) for x, c in zip(e, cov, strict=True)])
    line = (f"{name:22s} n={len(e):4d}  error/fit sigma RMS (dx, dy, dyaw) "
            f"{per[0]:.2f} {per[1]:.2f} {per[2]:.2f}")
    fac = per ** 2
    # consecutive runs of stretch increments (same drive, no gap)
    idx = np.array([s[3] for s in steps])
    sums = []
    k = 0
    while k + stretch <= len(steps):
        if idx[k + stretch - 1] - idx[k] == stretch - 1:
            sums.append((e[k:k + stretch].sum(0), raw[k:k + stretch].sum(0)))
            k += stretch
        else:
            k += 1
    if len(sums) >= 5:
        se = np.array([a for a, _ in sums])
        ss = np.sqrt(np.array([np.diag(b) for _, b in sums]))
        st = np.sqrt(np.mean((se / ss) ** 2, axis=0))
        line += f"; {stretch}-step sums {st[0]:.2f} {st[1]:.2f} {st[2]:.2f} ({len(sums)})"
        fac = np.maximum(fac, st ** 2)
    print(line + f"; NEES (published) mean {nees.mean():.2f} median {np.median(nees):.2f}"
          " (honest: 3, 2.37)")
    return fac


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=4)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stretch", type=int, default=STRETCH, help="steps per summed stretch")
    ap.add_argument("--heldout", type=int, nargs="*",
                    help="seeds of bench_heldout_lines' marker drives to measure instead")
    ap.add_argument("--noise", type=float, default=2.0, help="with --heldout: grey levels")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.heldout:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        steps = [s for seed in args.heldout for s in heldout_steps(seed, args.noise)]
        print(f"VAR_FACTOR now {VAR_FACTOR.tolist()}; held-out marker drives, seeds "
              f"{args.heldout}, noise {args.noise}")
        for kind in ("fresh", "redetect", "carried"):
            if sum(s[4] == kind for s in steps) >= 3:
                report(kind, [s for s in steps if s[4] == kind], args.stretch)
    else:
        rig, site = Rig.load(CONFIG / "rig.yaml"), Site.load(CONFIG / "site.yaml")
        rng = np.random.default_rng(args.seed)
        steps = [s for _ in range(args.drives) for s in drive_steps(rig, site, rng, args.frames)]
        print(f"VAR_FACTOR now {VAR_FACTOR.tolist()}; {args.drives} drives x {args.frames} "
              f"frames, seed {args.seed}")
    by = collections.defaultdict(list)
    for s in steps:
        by[s[0]].append(s)
    for kind in sorted(by):
        if by[kind][0][1] is None:
            print(f"{kind:22s} n={len(by[kind]):4d}  (no increment)")
        elif len(by[kind]) >= 3:
            report(kind, by[kind], args.stretch)
    fac = report("all", [s for s in steps if s[1] is not None], args.stretch)
    print(f"suggested VAR_FACTOR (larger of per step and {args.stretch}-step sums): "
          + " ".join(f"{v:.2f}" for v in fac))


if __name__ == "__main__":
    main()
