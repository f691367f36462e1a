"""Benchmark of the ambiguity issue (issue 36): no valid pose wrong where the ceiling
repeats, on simulated drives written as SPEC recordings and run through ``replay`` (the
library function of ``ceilrun replay``), as data from outside would be.

Cases (by default noise 2 grey levels, blur 0.8 px, ``supersample=1`` to keep it short):

* **corridor-reverse** / **corridor-forward**: the packaged corridor (lines and lamp row
  symmetric about its centre line) driven towards -x (heading about 180 deg) and +x,
  weaving: ``corridor`` without a start pose, with the right one, with one turned
  180 deg (a wrong prior: the twin is all the data can say), ``auto`` with the right
  one;
* **tiles**: a plain 0.6 m drop-tile grid given as ``corridor`` lines along and across,
  an upward wide-angle camera (configs/block's rig) driven round a loop: ``corridor``
  without and with a start pose;
* **tiles-markers**: configs/block (tiles, a hatch, a bright block, AprilTags):
  ``auto`` without a start pose;
* **tiles-small-markers**: the issue's tiles with a hatch and five 16 cm AprilTags at
  about 3.2 px per cell (``bench_tiles_markers.py``'s rig and site) on a loop:
  ``auto`` and ``block`` without a start pose;
* **light-grid**: a regular 1.5 m grid of spot lights (configs/lights' rig) on a loop:
  ``lights`` and ``auto`` without and with a start pose;
* **...-wrong-prior**: the corridor, the tiles and the light grid from a start pose off
  by a distance and an angle that make it no twin of the truth (the run's name says
  how far): no valid pose may be wrong;
* **...-kidnap**: the light grid, the corridor and the small markers with the vehicle
  carried elsewhere between frames 29 and 30 (:func:`kidnap`; no odometry sees it).

For every run: frames, valid poses, **wrong valid poses** (more than 10 cm or 2 deg
off, over the coordinates published), median position error, and the mean NEES of
the published poses (each with its full covariance, taken from a pose sink:
``poses.csv`` has sigmas only) against its 95% band. The
band is that of the poses' effective number of independent samples
(:func:`~ceilkit.runtime.fusion.effective_count`, from the NEES series'
autocorrelation; ``n_eff``), not of their count: a track's errors correlate from frame
to frame (a light grid's loop: about 46 of 60). Saved to
``benchmarks/out/bench_ambiguity.csv``. ``--noise`` and ``--blur`` set the simulated
camera (default 2 grey levels, 0.8 px; a cheap camera: 5 and 1.2), ``--supersample``
its samples per pixel side (default 1: each pixel the scene at its centre, which a
sensor integrating over its pixel does not do; the edges' staircase is then a locator
error of about 0.03 px that the residuals hold and that moves the pose less than
independent errors of its size would: the corridor's drives at noise 2 read about 1.3
of 2 with 1 sample, 1.8-2.0 with 3, docs/methods/honesty.md).

    .venv/bin/python benchmarks/bench_ambiguity.py [--frames 60] [--only tiles ...]
        [--noise 2] [--blur 0.8] [--supersample 1]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.fusion import effective_count, nees
from ceilkit.runtime.geometry.ekf import chi2_quantile, mean_nees_band
from ceilkit.runtime.replay import replay
from ceilkit.runtime.sim.render import SimOptions, Trajectory, straight_drive

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
OUT = Path(__file__).resolve().parent / "out"
SIM = SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=1)


def drive(n: int, fps: float, x0: float, y0: float, heading_deg: float, speed: float,
          weave: float = 0.15) -> Trajectory:
    """A drive weaving about a straight line along ``heading_deg`` (a 6 m period)."""
    return straight_drive(n, fps, speed, x0, y0, math.radians(heading_deg), weave)


def loop(n: int, fps: float, cx: float, cy: float, r: float, speed: float) -> Trajectory:
    """A circle of radius ``r`` about ``(cx, cy)``, counter-clockwise."""
    t = np.arange(n) / fps
    a = speed * t / r
    return Trajectory((t * 1e9).astype(np.int64), cx + r * np.cos(a), cy + r * np.sin(a),
                      a + math.pi / 2)


class Published:
    """A pose sink keeping every published pose (with its full covariance, which
    ``poses.csv`` does not carry)."""

    def __init__(self) -> None:
        self.poses: dict[int, PoseEstimate] = {}

    def send(self, est, relocalized: bool, capture_ns: int) -> None:
        if isinstance(est, PoseEstimate):
            self.poses[int(est.t_ns)] = est


def score(folder: Path, out: Path, published: dict[int, PoseEstimate]) -> dict[str, float]:
    """Counts and errors from ``poses.csv``; the NEES of each published pose with its
    full covariance over the coordinates it gives (:func:`~ceilkit.runtime.fusion.nees`:
    the corridor's y and heading are strongly correlated, which a NEES from the sigmas
    alone ignores)."""
    truth = {int(r["t_ns"]): r for r in csv.DictReader(open(folder / "truth.csv"))}
    rows = list(csv.DictReader(open(out / "poses.csv")))
    valid = wrong = 0
    errs, nees_v, dofs = [], [], []
    for r in rows:
        if r["yaw_deg"] == "":
            continue
        valid += 1
        t = truth[int(r["t_ns"])]
        dyaw = math.remainder(math.radians(float(r["yaw_deg"]) - float(t["yaw_deg"])),
                              2 * math.pi)
        e = [float(r[k]) - float(t[k]) for k in ("x", "y") if r[k] != ""]
        d = math.hypot(*e) if e else 0.0
        errs.append(d)
        wrong += d > 0.10 or abs(dyaw) > math.radians(2.0)
        est = published.get(int(r["t_ns"]))
        got = None if est is None else nees(est, (float(t["x"]), float(t["y"]),
                                                  math.radians(float(t["yaw_deg"]))))
        if got is not None and math.isfinite(got[0]):
            nees_v.append(got[0])
            dofs.append(got[1])
    out_d = {"frames": len(rows), "valid": valid, "wrong": wrong,
             "median_m": float(np.median(errs)) if errs else math.nan}
    if nees_v:
        dof = round(float(np.mean(dofs)))
        n_eff = effective_count(nees_v)          # the track's errors correlate in time
        lo, hi = mean_nees_band(max(1, round(n_eff)), dof)
        out_d.update(nees=float(np.mean(nees_v)), nees_lo=lo, nees_hi=hi, nees_n_eff=n_eff,
                     inside95=float(np.mean([v <= chi2_quantile(0.95, d)
                                             for v, d in zip(nees_v, dofs, strict=True)])))
    return out_d


def run(folder: Path, tag: str, method: str, start=None) -> dict[str, float]:
    out = folder.parent / f"{folder.name}-{tag}"
    t0 = time.perf_counter()
    published = Published()
    replay(folder, out, method=method, start_pose=start, sinks=[published])
    res = score(folder, out, published.poses)
    res["s"] = time.perf_counter() - t0
    return res


def kidnap(a: Trajectory, b: Trajectory, k: int) -> Trajectory:
    """``a``'s first ``k`` poses, then ``b``'s from its ``k``-th: the vehicle carried
    elsewhere between two frames (no odometry sees it)."""
    return Trajectory(a.t_ns, np.r_[a.x_m[:k], b.x_m[k:]], np.r_[a.y_m[:k], b.y_m[k:]],
                      np.r_[a.yaw_rad[:k], b.yaw_rad[k:]])


def tiles_site(tmp: Path) -> Path:
    d = {"ceiling_height": 3.0,
         "corridor": {"lines_along": [round(-3.0 + 0.6 * i, 2) for i in range(11)],
                      "lines_across": {"first": 0.0, "spacing": 0.6}}}
    p = tmp / "tiles.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def grid_site(tmp: Path) -> Path:
    g = np.arange(-3.0, 4.51, 1.5)
    p = tmp / "grid.yaml"
    p.write_text("ceiling_height: 3.0\nlights:\n" + "".join(
        f"  - [{a:.3f}, {b:.3f}]\n" for a in g for b in g))
    return p


def small_markers(n: int) -> tuple[Rig, Site, Trajectory]:
    """The issue's tiles with a hatch and five 16 cm AprilTags at about 3.2 px per cell
    (the rig, site and loop of ``bench_tiles_markers.py``), driven at 10 fps."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_tiles_markers as tm

    poses = np.array(tm.loop(n))
    t = (np.arange(n) * 1e8).astype(np.int64)
    return tm.rig(), tm.site(), Trajectory(t, poses[:, 0], poses[:, 1], np.unwrap(poses[:, 2]))


def _kidnapped(rts: tuple[Rig, Site, Trajectory], n: int) -> tuple[Rig, Site, Trajectory]:
    """The small-marker loop, the second half carried a quarter of the loop ahead."""
    rig, site, tr = rts
    sh = np.roll(np.arange(n), -n // 4)
    other = Trajectory(tr.t_ns, tr.x_m[sh], tr.y_m[sh], tr.yaw_rad[sh])
    return rig, site, kidnap(tr, other, n // 2)


def cases(tmp: Path, n: int) -> dict[str, tuple]:
    crig, csite = Rig.load(CONFIGS / "corridor/rig.yaml"), Site.load(CONFIGS / "corridor/site.yaml")
    brig = Rig.load(CONFIGS / "block/rig.yaml")
    lrig = Rig.load(CONFIGS / "lights/rig.yaml")
    rev = drive(n, 10.0, 20.0, 0.1, 180.0, 0.5)
    fwd = drive(n, 10.0, 2.0, -0.1, 0.0, 0.5)

    def start(tr: Trajectory, turn_deg: float = 0.0, dx: float = 0.0, dy: float = 0.0):
        x, y, yaw = tr.pose(0)
        return (x + dx, y + dy, yaw + math.radians(turn_deg))

    grid_loop = loop(n, 10.0, 0.0, 0.0, 2.0, 0.5)
    grid_kidnap = kidnap(grid_loop, loop(n, 10.0, 0.6, -0.4, 1.5, -0.5), n // 2)
    tiles_loop = loop(n, 10.0, 1.0, 0.0, 1.5, 0.4)

    return {
        "corridor-reverse": (crig, csite, rev, [
            ("corridor", None), ("corridor", start(rev)), ("corridor", start(rev, 180.0)),
            ("auto", start(rev))]),
        "corridor-forward": (crig, csite, fwd, [
            ("corridor", None), ("corridor", start(fwd))]),
        "corridor-wrong-prior": (crig, csite, rev, [
            ("corridor", start(rev, 25.0, 0.0, 0.3)), ("auto", start(rev, -30.0, 0.5, 0.2))]),
        "tiles": (brig, Site.load(tiles_site(tmp)), tiles_loop, [
            ("corridor", None), ("corridor", start(tiles_loop))]),
        "tiles-wrong-prior": (brig, Site.load(tiles_site(tmp)), tiles_loop, [
            ("corridor", start(tiles_loop, 45.0, 0.3, 0.3)),
            ("corridor", start(tiles_loop, 10.0, 0.25, -0.2))]),
        "tiles-markers": (brig, Site.load(CONFIGS / "block/site.yaml"),
                          drive(n, 10.0, 0.0, 0.0, 0.0, 0.8, 0.3), [("auto", None)]),
        "tiles-small-markers": (*small_markers(n), [("auto", None), ("block", None)]),
        "light-grid": (lrig, Site.load(grid_site(tmp)), loop(n, 10.0, 0.0, 0.0, 2.0, 0.5), [
            ("lights", None), ("auto", None),
            ("lights", start(loop(n, 10.0, 0.0, 0.0, 2.0, 0.5))),
            ("auto", start(loop(n, 10.0, 0.0, 0.0, 2.0, 0.5)))]),
        "light-grid-wrong-prior": (lrig, Site.load(grid_site(tmp)), grid_loop, [
            ("lights", start(grid_loop, 20.0, 0.7, -0.6)), ("auto", start(grid_loop, -10.0, 0.8))]),
        "light-grid-kidnap": (lrig, Site.load(grid_site(tmp)), grid_kidnap, [
            ("lights", start(grid_kidnap)), ("auto", start(grid_kidnap))]),
        "corridor-kidnap": (crig, csite, kidnap(rev, drive(n, 10.0, 14.0, -0.3, 170.0, 0.5),
                                                n // 2), [
            ("corridor", start(rev)), ("auto", start(rev))]),
        "small-markers-kidnap": (*_kidnapped(small_markers(n), n), [("auto", None)]),
    }


def add_render_args(ap: argparse.ArgumentParser, sim: SimOptions) -> None:
    """``--noise``, ``--blur`` and ``--supersample``, their defaults ``sim``'s."""
    ap.add_argument("--noise", type=float, default=sim.noise_sigma,
                    help="the image noise's 1σ in grey levels (default %(default)s)")
    ap.add_argument("--blur", type=float, default=sim.blur_px,
                    help="the blur's 1σ in px (default %(default)s)")
    ap.add_argument("--supersample", type=int, default=sim.supersample,
                    help="samples per pixel side of the render (default %(default)s)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--keep", type=Path, help="write the recordings and runs here (kept)")
    add_render_args(ap, SIM)
    a = ap.parse_args(argv)
    sim = dataclasses.replace(SIM, noise_sigma=a.noise, blur_px=a.blur,
                              supersample=a.supersample)
    OUT.mkdir(exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = a.keep or Path(d)
        tmp.mkdir(parents=True, exist_ok=True)
        for name, (rig, site, traj, runs) in cases(tmp, a.frames).items():
            if a.only and name not in a.only:
                continue
            folder = simulate_recording(rig, site, traj, tmp / name, sim, seed=7)
            for method, start in runs:
                tag = f"{method}-{'start' if start else 'nostart'}"
                if start is not None:
                    x0, y0, yaw0 = traj.pose(0)
                    dyaw = abs(math.remainder(start[2] - yaw0, 2 * math.pi))
                    off = math.hypot(start[0] - x0, start[1] - y0)
                    tag += ("-turned" if dyaw > 3.0 else
                            f"-off{off:.2f}m{math.degrees(dyaw):.0f}deg"
                            if off > 0.1 or dyaw > math.radians(2.0) else "")
                res = run(folder, tag, method, start)
                rows.append({"case": name, "run": tag, **res})
                nees = (f"NEES {res['nees']:.2f} [{res['nees_lo']:.2f}, {res['nees_hi']:.2f}] "
                        f"n_eff {res['nees_n_eff']:.0f}" if "nees" in res else "")
                print(f"{name:22s} {tag:30s} valid {res['valid']:3d}/{res['frames']:3d} "
                      f"wrong {res['wrong']:3d}  median {1e3 * res['median_m']:7.2f} mm  "
                      f"{nees}  ({res['s']:.0f} s)", flush=True)
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k not in ("case", "run"), k))
    with open(OUT / "bench_ambiguity.csv", "w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {OUT / 'bench_ambiguity.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
