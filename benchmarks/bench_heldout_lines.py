"""Held-out benchmark of issue 36 for the corridor and block methods: scenes drawn from a
seed, beyond the cases ``bench_ambiguity.py`` and ``bench_tiles_markers.py`` were tuned on.

Each scene is written as a SPEC recording (``frames/``, ``frames.csv``, ``rig.yaml``,
``site.yaml``, ``truth.csv``) and replayed through :func:`ceilkit.runtime.replay.replay`
(the library function of ``ceilrun replay``), as a recording made outside the project
would be. Noise 2 grey levels, blur 0.8 px, ``supersample=1`` (``--noise``, ``--blur``,
``--supersample``). Classes:

* **corridor**: 2-6 lines mirror-symmetric about the centre line at irregular spacing,
  1.5-4 m wide (walls 0.75 m past the outermost line), a lamp row down the middle or
  none; driven towards -x, +x or diagonally weaving; a forward-tilted (30-60 deg) or
  upward camera, f 250-600 px, 640x480 or 800x600;
* **tiles**: a plain drop-tile grid (pitch 0.5, 0.6 or 0.625 m, or 0.6 x 1.2 m tiles)
  as ``corridor`` lines along and across; an upward wide-angle camera (f 220-320 px);
  a loop (turning 30-90 deg/s) or a straight weaving drive;
* **markers**: a tile grid with a dark hatch and 3-5 markers (AprilTag 36h11 or ArUco
  4x4, 12-20 cm, 3-5 px per cell) 4-6 m apart round a loop of radius 2.8 m (frames
  between markers see tiles and the hatch alone); an upward camera.

Runs per scene: no prior; the right start pose; a start pose on a twin of the truth
(``twin``: the corridor's half turn about its centre line, the tiles' quarter or half
turn or one period off: what the ceiling cannot tell from the truth); a start pose 30 cm
and 5 deg off (``off``); a kidnap (the vehicle carried elsewhere half-way, from the
right start pose). Methods: the class's own (``corridor`` or ``block``) and ``auto``.

A valid pose more than 10 cm or 2 deg off (over the coordinates published) is
``wrong``; on a ``twin`` run the wrong poses are the prior's (the ceiling cannot refute
it) and count only until evidence that breaks the twin (a marker, a lamp row's end)
is in view. Per run: frames, valid, wrong, median position error, mean NEES and its
95% band (``bench_ambiguity.score``). Saved to ``benchmarks/out/bench_heldout_lines.csv``.

    .venv/bin/python benchmarks/bench_heldout_lines.py [--scenes 3] [--frames 60]
        [--seed 36] [--only corridor tiles markers] [--runs TAG ...] [--keep DIR]
        [--option KEY=VALUE ...] [--noise 2] [--blur 0.8] [--supersample 1]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import (
    AcrossLines,
    Block,
    Corridor,
    LampRow,
    MarkerPose,
    Markers,
    Site,
)
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.replay import replay
from ceilkit.runtime.sim.render import SimOptions, Trajectory, straight_drive

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ambiguity import Published, add_render_args, kidnap, score  # noqa: E402

OUT = Path(__file__).resolve().parent / "out"
SIM = SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=1)
CELLS = {"DICT_APRILTAG_36h11": 8, "DICT_4X4_50": 6}   # cells across a marker, border in


@dataclass(frozen=True)
class Scene:
    """One drawn scene: its rig, site, drive, a kidnapped drive, and a twin of pose 0."""

    name: str
    rig: Rig
    site: Site
    traj: Trajectory
    kidnapped: Trajectory
    twin: tuple[float, float, float]
    twin_name: str
    methods: tuple[str, ...]


def _loop(n: int, fps: float, cx: float, cy: float, r: float, rate: float,
          phase: float = 0.0) -> Trajectory:
    """A circle of radius ``r`` (m) about ``(cx, cy)`` at ``rate`` rad/s (sign: sense)."""
    t = np.arange(n) / fps
    a = phase + rate * t
    return Trajectory((t * 1e9).astype(np.int64), cx + r * np.cos(a), cy + r * np.sin(a),
                      a + math.copysign(math.pi / 2, rate))


def _camera(rng: np.random.Generator, f_lo: float, f_hi: float) -> CameraModel:
    w, h = (640, 480) if rng.random() < 0.5 else (800, 600)
    return CameraModel.pinhole(w, h, float(rng.uniform(f_lo, f_hi)) * w / 640)


def _half_turn(x: float, y: float, yaw: float, across: AcrossLines | None
               ) -> tuple[float, float, float]:
    """The pose a half turn about the centre line (y = 0) takes ``(x, y, yaw)`` to, about
    the nearest point the across lines are symmetric about (none: the same x)."""
    c = x if across is None else round((x - across.first_m - across.spacing_m / 2)
                                       / across.spacing_m) * across.spacing_m \
        + across.first_m + across.spacing_m / 2
    return 2 * c - x, -y, yaw + math.pi


def corridor_scene(rng: np.random.Generator, n: int, k: int) -> Scene:
    """A mirror-symmetric corridor with irregular line spacing (see the module doc)."""
    half = float(rng.uniform(0.75, 2.0)) - 0.75            # walls 0.75 m past the lines
    lamp = rng.random() < 0.5
    npairs = int(rng.integers(1, 4))
    ys = np.sort(rng.uniform(0.2, 1.0, npairs)) * max(half, 0.35)
    ys = ys[np.r_[True, np.diff(ys) > 0.12]]
    along = sorted({round(float(s * y), 3) for y in ys for s in (-1, 1)})
    lamps: tuple[LampRow, ...] = ()
    across = None
    if lamp:
        lw, ll = float(rng.choice([0.2, 0.3, 0.6])), float(rng.choice([0.6, 1.2]))
        pitch = 2 * ll
        along = sorted(set(along) | {-lw / 2, lw / 2})
        along = [a for a in along if abs(abs(a) - lw / 2) < 1e-9 or abs(a) > lw / 2 + 0.08]
        lamps = (LampRow(0.0, 0.0, ll, lw, pitch, 40),)
        across = AcrossLines(-ll / 2, ll)
    site = Site(2.6 + float(rng.uniform(0.0, 0.8)),
                corridor=Corridor(tuple(along), across), lamps=lamps)
    up = rng.random() < 0.35
    tilt = 90.0 if up else float(rng.uniform(30.0, 60.0))
    cam = _camera(rng, 250.0, 600.0) if not up else _camera(rng, 250.0, 400.0)
    rig = Rig(cam, Mount(math.radians(rng.uniform(-3, 3)), math.radians(tilt),
                         math.radians(rng.uniform(-2, 2)), 0.3, 0.0, 0.8))
    kind = ("reverse", "forward", "diagonal")[k % 3]
    x_end = 80.0 * lamps[0].length_m - 10.0 if lamp else 60.0
    speed = float(rng.uniform(0.4, 1.0))
    y0 = float(rng.uniform(-0.3, 0.3)) * min(1.0, max(half, 0.35))
    if kind == "reverse":
        tr = straight_drive(n, 10.0, speed, x_end - 2.0, y0, math.pi, 0.15)
    elif kind == "forward":
        tr = straight_drive(n, 10.0, speed, 4.0, y0, 0.0, 0.15)
    else:
        tr = straight_drive(n, 10.0, speed, 4.0, y0, 0.0, 0.3, weave_period_m=3.0,
                            yaw_wobble_rad=math.radians(15.0), rng=rng)
    other = straight_drive(n, 10.0, speed, tr.x_m[0] + 6.0 * math.cos(tr.yaw_rad[0]), -y0,
                           tr.yaw_rad[0] + 0.05, 0.1)     # 6 m on, across the centre line
    return Scene(f"corridor{k}-{kind}{'-lamps' if lamp else ''}-{'up' if up else 'tilt'}"
                 f"{cam.fx:.0f}", rig, site, tr, kidnap(tr, other, n // 2),
                 _half_turn(*tr.pose(0), across), "halfturn", ("corridor", "auto"))


def _tile_lines(pitch_x: float, pitch_y: float, half_y: float) -> Corridor:
    m = int(half_y / pitch_y)
    along = tuple(round(pitch_y * i, 6) for i in range(-m, m + 1))
    return Corridor(along, AcrossLines(0.0, pitch_x))


def tiles_scene(rng: np.random.Generator, n: int, k: int, markers: bool = False) -> Scene:
    """A tile grid (with a hatch and markers when ``markers``); see the module doc."""
    kind = int(rng.integers(4))
    px, py = ((0.5, 0.5), (0.6, 0.6), (0.625, 0.625), (1.2, 0.6))[kind]
    if rng.random() < 0.5 and kind == 3:
        px, py = 0.6, 1.2
    height = 2.8 + float(rng.uniform(0.0, 0.6))
    cam_z = 0.6
    corridor = _tile_lines(px, py, 4.0)
    blocks: tuple[Block, ...] = ()
    mk = None
    desc = f"{px}x{py}"
    if markers:
        d = str(rng.choice(list(CELLS)))
        tag = float(rng.uniform(0.12, 0.20))
        ppc = float(rng.uniform(3.0, 5.0))
        f = ppc * CELLS[d] * (height - cam_z) / tag
        cam = CameraModel.pinhole(640, 480, f)
        hx, hy = px * 2, 0.0
        blocks = (Block("H", np.array([[hx, hy], [hx + px, hy], [hx + px, hy + py],
                                       [hx, hy + py]]), "dark"),)
        nm = int(rng.integers(3, 6))
        ids = rng.choice(40, nm, replace=False)
        poses = []
        for j in range(nm):
            a = 2 * math.pi * j / nm + 0.3
            poses.append(MarkerPose(int(ids[j]), round(1.5 + 3.4 * math.cos(a), 3),
                                    round(2.4 * math.sin(a), 3),
                                    math.radians(float(rng.choice([0, 90, 180, -90, 30]))),
                                    tag))
        mk = Markers(d, tag, tuple(poses))
        desc += f"-{'april' if 'APRIL' in d else 'aruco4'}{100 * tag:.0f}cm{ppc:.1f}px"
        tr = _loop(n, 10.0, 1.5, 0.0, 2.8, float(rng.choice([-1, 1]) * rng.uniform(0.2, 0.5)))
        methods = ("block", "auto")
    else:
        cam = _camera(rng, 220.0, 320.0)
        if rng.random() < 0.6:
            rate = math.radians(float(rng.uniform(30.0, 90.0)))
            r = float(rng.uniform(0.6, 1.5))
            tr = _loop(n, 10.0, 0.3, 0.1, r, float(rng.choice([-1, 1])) * rate)
            desc += f"-loop{math.degrees(rate):.0f}dps"
        else:
            tr = straight_drive(n, 10.0, float(rng.uniform(0.5, 1.2)), -2.0, 0.13,
                                float(rng.uniform(-math.pi, math.pi)), 0.2, rng=rng)
            desc += "-straight"
        methods = ("corridor", "auto")
    site = Site(height, corridor=corridor, blocks=blocks, markers=mk)
    rig = Rig(cam, Mount(0.0, math.radians(90.0), 0.0, 0.1, 0.0, cam_z))
    x, y, yaw = tr.pose(0)
    twins = [("quarter", (x, y, yaw + math.pi / 2)) if px == py else
             ("half", (x, y, yaw + math.pi)),
             ("pitch", (x + px, y, yaw)), ("half", (x, y, yaw + math.pi))]
    tname, twin = twins[(k + int(rng.integers(3))) % len(twins)]
    if tname == "quarter":      # a quarter turn about the nearest tile corner
        cx, cy = round(x / px) * px, round(y / py) * py
        twin = (cx - (y - cy), cy + (x - cx), yaw + math.pi / 2)
    elif tname == "half":
        cx, cy = round(x / px) * px, round(y / py) * py
        twin = (2 * cx - x, 2 * cy - y, yaw + math.pi)
    other = _loop(n, 10.0, -0.8, 0.9, 1.0, 0.5, phase=1.0)
    return Scene(f"{'markers' if markers else 'tiles'}{k}-{desc}-f{cam.fx:.0f}", rig, site,
                 tr, kidnap(tr, other, n // 2), twin, tname, methods)


def run(folder: Path, tag: str, method: str, start, options: dict[str, str]
        ) -> dict[str, float]:
    """``bench_ambiguity.run`` with the estimator's ``options`` (``--option``)."""
    out = folder.parent / f"{folder.name}-{tag}"
    published = Published()
    replay(folder, out, method=method, start_pose=start, sinks=[published],
           options=options or None)
    return score(folder, out, published.poses)


def runs_for(sc: Scene) -> list[tuple[str, str, tuple | None, bool]]:
    """``(tag, method, start, kidnapped)`` of every run of a scene."""
    x, y, yaw = sc.traj.pose(0)
    off = (x + 0.3 * math.cos(yaw + 1.0), y + 0.3 * math.sin(yaw + 1.0),
           yaw + math.radians(5.0))
    out = []
    for m in sc.methods:
        out += [(f"{m}-none", m, None, False), (f"{m}-right", m, (x, y, yaw), False),
                (f"{m}-off30cm5deg", m, off, False)]
    m = sc.methods[0]
    out += [(f"{m}-twin-{sc.twin_name}", m, sc.twin, False),
            (f"{m}-kidnap", m, (x, y, yaw), True), ("auto-kidnap", "auto", (x, y, yaw), True)]
    return out


def scenes(seed: int, n_per: int, frames: int, only: list[str] | None) -> list[Scene]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_per):
        for cls in ("corridor", "tiles", "markers"):
            sc = (corridor_scene(rng, frames, k) if cls == "corridor" else
                  tiles_scene(rng, frames, k, markers=cls == "markers"))
            if not only or cls in only:
                out.append(sc)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3, help="scenes per class")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=36)
    ap.add_argument("--only", nargs="*", help="classes: corridor tiles markers")
    ap.add_argument("--runs", nargs="*", help="only runs whose tag contains one of these")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="an estimator option of every run (repeatable), e.g. "
                         "window_search=true")
    ap.add_argument("--keep", type=Path, help="write the recordings and runs here (kept)")
    ap.add_argument("--out", type=Path, default=OUT / "bench_heldout_lines.csv")
    add_render_args(ap, SIM)
    a = ap.parse_args(argv)
    options = dict(o.split("=", 1) for o in a.option)
    sim = dataclasses.replace(SIM, noise_sigma=a.noise, blur_px=a.blur,
                              supersample=a.supersample)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = a.keep or Path(d)
        tmp.mkdir(parents=True, exist_ok=True)
        for sc in scenes(a.seed, a.scenes, a.frames, a.only):
            rec: dict[bool, Path] = {}
            for tag, method, start, kid in runs_for(sc):
                if a.runs and not any(r in tag for r in a.runs):
                    continue
                if kid not in rec:
                    name = sc.name + ("-kidnapped" if kid else "")
                    rec[kid] = simulate_recording(sc.rig, sc.site,
                                                  sc.kidnapped if kid else sc.traj,
                                                  tmp / name, sim, seed=a.seed)
                t0 = time.perf_counter()
                res = run(rec[kid], tag, method, start, options)
                res["s"] = time.perf_counter() - t0
                rows.append({"scene": sc.name, "run": tag, **res})
                nees = (f"NEES {res['nees']:.2f} [{res['nees_lo']:.2f}, {res['nees_hi']:.2f}]"
                        if "nees" in res else "")
                print(f"{sc.name:44s} {tag:22s} valid {res['valid']:3d}/{res['frames']:3d} "
                      f"wrong {res['wrong']:3d}  median {1e3 * res['median_m']:8.2f} mm  "
                      f"{nees}  ({res['s']:.0f} s)", flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k not in ("scene", "run"), k))
    with open(a.out, "w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
