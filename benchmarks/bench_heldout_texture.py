"""Held-out benchmark of issue 39 for ``ceilcal survey`` and the ``texture`` method:
scenes drawn from a seed, beyond configs/office's one scene that ``bench_survey.py`` and
``bench_texture.py`` measured, each drive written as a SPEC recording by hand
(``frames/``, ``frames.csv``, ``rig.yaml`` with its camera inline, ``site.yaml``,
``truth.csv``) and used as a recording made outside the project would be.

Scenes (``--scenes`` of the first class, then one of each control):

* **scatter**: a drop-tile grid (pitch 0.5, 0.6 or 0.625 m, or 0.6 x 1.2 m tiles) with an
  irregular scatter (``runtime/sim/scatter.py``'s generator with its densities scaled
  0.4-1.5 times the office preset's, light panels every 3-6 x 2-5 tiles, 10-40 % of
  them left out; stains and discs (sprinklers, detectors) scaled 0.6-1.6 times in size;
  the grey of patches and stains 0.5-1.5 times), the simulator's ceiling texture
  (3 grey levels);
* **plain** (control): the tile grid alone, no texture: no pose can be singled out;
* **repeated** (control): one tile's scatter (a sprinkler, a detector, two stains)
  copied onto every tile, no texture: every pose has a twin a tile away.

Cameras looking up (swing within 2 deg): a pinhole of 60-90 deg across (scatter0, 2,
..., and the repeated control) or an equidistant fisheye of f 190-260 px at 640 px
across (scatter1, 3, ..., and the plain control); 640x480, scatter1 800x600; the
ceiling 2.4-3.4 m above the floor, the camera 0.3-0.8 m above it.
Noise 2, blur 0.8 px, supersample 2 (``--noise``, ``--blur``, ``--supersample``).

Per scene:

1. **survey**: a rounded-rectangle loop (5-9 x 1.8-3.0 m, 30-45 m driven: over the
   start again at the end), a frame every ``--survey-step`` (0.1 m: docs/survey.md asks
   5-10 cm a frame), written as a recording whose ``site.yaml`` holds the ceiling height
   alone, surveyed by :func:`~ceilkit.calib.survey_files.survey_site` (what
   ``ceilcal survey RIG REC --out DIR --start-pose`` calls) anchored by its first
   frame's true pose. Figures: the closures and the gaps of the chain matched across,
   the frames (and pieces of the drive) not placed; the surveyed frames' positions
   against the truth (RMS, max), the worst heading, every keyframe's ORB points on the
   ceiling placed by the
   surveyed pose against by the true pose (``bench_survey.feature_errors``: RMS), each
   keyframe's position error over its stated 1σ (``hypot(ex / σx, ey / σy)``: the 2-D
   law's median 1.18, 95th percentile 2.45) and the map features' stated 1σ (median);
2. **second drive**: ``--frames`` frames (80) of another path through the loop
   (weaving across it, the heading wobbling), and the same drive carried elsewhere at
   half-way (kidnap), written with the survey's ``site.yaml`` and ``ceiling_map.npz`` as
   the recording's site (``--preset realistic``: configs/office's realism preset on
   these drives only), replayed through :func:`ceilkit.runtime.replay.replay` (what
   ``ceilrun replay`` calls) with ``texture`` and ``auto``: no start pose, the right one,
   and the kidnapped drive from the right one.

Per run (``bench_ambiguity.score``): frames, valid, **wrong** (a valid pose > 10 cm or
2 deg off), median position error, mean NEES over the coordinates published with its
95 % band for the series' effective count; on a kidnap, ``reloc``: frames from the
carry to the first right pose (-1: none). Rows to
``benchmarks/out/bench_heldout_texture.csv`` after ``bench_all.py``'s provenance header.

    .venv/bin/python benchmarks/bench_heldout_texture.py [--scenes 2] [--frames 80]
        [--seed 1] [--only scatter plain repeated] [--pick scatter1] [--runs texture-none]
        [--survey-step 0.1] [--preset realistic] [--keep DIR]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ceilkit.calib.survey import CLOSURE_KINDS
from ceilkit.calib.survey_files import Anchors, survey_site
from ceilkit.calib.survey_loop import loop_trajectory
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import AcrossLines, Corridor, Site
from ceilkit.runtime.errors import CeilkitError
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.replay import replay
from ceilkit.runtime.sim.realism import Realism, load_preset, render_real
from ceilkit.runtime.sim.render import SimOptions, Trajectory, render_frame, straight_drive
from ceilkit.runtime.sim.scatter import PRESETS, Scatter, ScatterItem, generate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_all import provenance  # noqa: E402
from bench_ambiguity import Published, kidnap, score  # noqa: E402
from bench_heldout_lights import camera_yaml  # noqa: E402
from bench_survey import feature_errors  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
OFFICE_SITE = ROOT / "configs" / "office" / "site.yaml"
WRONG = (0.10, 2.0)          # m, deg: a valid pose further off is wrong
PITCHES = ((0.5, 0.5), (0.6, 0.6), (0.625, 0.625), (0.6, 1.2), (1.2, 0.6))


@dataclass(frozen=True)
class Scene:
    """One drawn scene: the files' contents, what is rendered, and the three drives."""

    name: str
    rig: dict                     # rig.yaml, the camera inline
    height_m: float
    pitch: tuple[float, float]
    scatter: Scatter | None
    texture: float                # the simulator's ceiling texture, grey levels
    survey: Trajectory
    second: Trajectory
    kidnapped: Trajectory
    note: str

    def shown(self) -> Site:
        """The ceiling as rendered: the tile grid's seams (the scatter rides in the
        render options)."""
        m = int(12.0 / self.pitch[1])
        along = tuple(round(self.pitch[1] * i, 6) for i in range(-m, m + 1))
        return Site(self.height_m, corridor=Corridor(along, AcrossLines(0.0, self.pitch[0])))


def camera(rng: np.random.Generator, fisheye: bool, size: tuple[int, int]
           ) -> tuple[dict, str]:
    """A camera.yaml mapping (ROS ``camera_info`` layout) and a note."""
    w, h = size
    if fisheye:
        f = float(rng.uniform(190.0, 260.0)) * w / 640
        model, dist = "equidistant", [0.02, -0.005, 0.0, 0.0]
        note = f"fisheye f{f:.0f}"
    else:
        fov = float(rng.uniform(60.0, 90.0))
        f = (w / 2) / math.tan(math.radians(fov / 2))
        model, dist = "plumb_bob", [float(rng.uniform(-0.08, 0.03)), 0.0, 0.0, 0.0, 0.0]
        note = f"pinhole {fov:.0f}deg f{f:.0f}"
    return camera_yaml(w, h, f, model, dist), f"{w}x{h} {note}"


def drives(rng: np.random.Generator, n: int, step_m: float
           ) -> tuple[Trajectory, Trajectory, Trajectory, str]:
    """The survey loop, the second drive of ``n`` frames through it, and that drive
    carried elsewhere at half-way (the kidnap)."""
    length, width = float(rng.uniform(5.0, 9.0)), float(rng.uniform(1.8, 3.0))
    cx, cy = float(rng.uniform(0.0, 1.0)), float(rng.uniform(0.0, 1.0))
    driven = float(rng.uniform(30.0, 45.0))
    lap = 2 * (length + width) - (8 - 2 * math.pi) * 0.6
    survey = loop_trajectory(length, width, laps=max(1.25, driven / lap), fps=10.0,
                             speed_mps=10.0 * step_m, centre_m=(cx, cy))
    speed = 0.7 * length / (n / 10.0)
    sense = float(rng.choice([-1.0, 1.0]))
    x0 = cx - sense * 0.35 * length
    second = straight_drive(n, 10.0, speed, x0, cy, 0.0 if sense > 0 else math.pi,
                            0.35 * width, yaw_wobble_rad=float(rng.uniform(0.2, 0.5)),
                            rng=rng, weave_period_m=float(rng.uniform(2.5, 4.0)))
    other = straight_drive(n, 10.0, speed, cx + sense * 0.3 * length, cy - 0.2 * width,
                           math.pi / 2 + float(rng.uniform(-0.5, 0.5)), 0.2 * width,
                           rng=rng, length_m=0.8 * width)
    note = (f"loop {length:.1f}x{width:.1f} m {len(survey)} frames "
            f"({len(survey) * step_m:.0f} m)")
    return survey, second, kidnap(second, other, n // 2), note


def scatter_of(rng: np.random.Generator, site: Site, x: tuple[float, float],
               y: tuple[float, float]) -> tuple[Scatter, str]:
    """An irregular scatter on ``site``'s tile grid: the office preset's densities
    scaled, its blobs resized and its greys rescaled (module docstring)."""
    dens = float(rng.uniform(0.4, 1.5))
    size = float(rng.uniform(0.6, 1.6))
    contrast = float(rng.uniform(0.5, 1.5))
    o = PRESETS["office"]
    p = dataclasses.replace(
        o, name="heldout", panel_pitch_tiles=(int(rng.integers(3, 7)), int(rng.integers(2, 6))),
        panel_missing=float(rng.uniform(0.1, 0.4)), vents_per_m2=o.vents_per_m2 * dens,
        hatches_per_m2=o.hatches_per_m2 * dens, patch_share=o.patch_share * dens,
        stains_per_m2=o.stains_per_m2 * dens, sprinklers_per_m2=o.sprinklers_per_m2 * dens,
        detectors_per_m2=o.detectors_per_m2 * dens, cables_per_m2=o.cables_per_m2 * dens)
    base = generate(p, site, int(rng.integers(1 << 30)), x, y)
    items = []
    for it in base.items:
        if it.kind in ("stain", "sprinkler", "detector"):
            it = dataclasses.replace(it, length_m=round(it.length_m * size, 4),
                                     width_m=round(it.width_m * size, 4))
        if it.kind in ("stain", "patch"):
            it = dataclasses.replace(it, grey=round(it.grey * contrast, 1))
        items.append(it)
    sc = Scatter(tuple(items), f"{base.origin}, sizes x{size:.2f}, greys x{contrast:.2f}")
    return sc, f"density x{dens:.2f} blobs x{size:.2f} contrast x{contrast:.2f} " \
               f"({len(items)} items)"


def repeated_scatter(pitch: tuple[float, float], x: tuple[float, float],
                     y: tuple[float, float]) -> Scatter:
    """One tile's items (a sprinkler, a detector, two stains) on every tile of the grid
    over the ranges: the scatter repeats with the tile period."""
    px, py = pitch
    one = [("sprinkler", 0.3, 0.25, 0.05, 0.05, 0.0, 0.0),
           ("detector", 0.7, 0.65, 0.12, 0.12, 0.0, 0.0),
           ("stain", 0.25, 0.7, 0.16, 0.09, 35.0, 22.0),
           ("stain", 0.75, 0.3, 0.10, 0.07, 120.0, 16.0)]
    items = []
    for i in range(math.floor(x[0] / px), math.ceil(x[1] / px)):
        for j in range(math.floor(y[0] / py), math.ceil(y[1] / py)):
            for kind, u, v, ln, wd, yaw, grey in one:
                items.append(ScatterItem(kind, round((i + u) * px, 4), round((j + v) * py, 4),
                                         ln, wd, yaw, grey))
    return Scatter(tuple(items), "one tile's scatter on every tile")


def draw(cls: str, rng: np.random.Generator, n: int, k: int, step_m: float) -> Scene:
    """One scene of class ``cls`` (``scatter``, ``plain``, ``repeated``), index ``k``."""
    fisheye = k % 2 == 1 if cls == "scatter" else cls == "plain"
    size = (800, 600) if cls == "scatter" and k == 1 else (640, 480)
    cam, cnote = camera(rng, fisheye, size)
    cam_z = float(rng.uniform(0.3, 0.8))
    height = round(float(rng.uniform(2.4, 3.4)), 3)
    rig = {"camera": cam, "mount": {"pan": 0.0, "tilt": 90.0,
                                    "swing": round(float(rng.uniform(-2.0, 2.0)), 3),
                                    "x": 0.1, "y": 0.0, "z": round(cam_z, 3)}}
    pitch = PITCHES[int(rng.integers(len(PITCHES)))]
    survey, second, kid, dnote = drives(rng, n, step_m)
    xs = np.r_[survey.x_m, second.x_m, kid.x_m]
    ys = np.r_[survey.y_m, second.y_m, kid.y_m]
    xr = (float(xs.min()) - 5.0, float(xs.max()) + 5.0)
    yr = (float(ys.min()) - 5.0, float(ys.max()) + 5.0)
    probe = Scene("", rig, height, pitch, None, 0.0, survey, second, kid, "")
    if cls == "scatter":
        sc, snote = scatter_of(rng, probe.shown(), xr, yr)
        texture = SimOptions().texture
    else:
        sc = repeated_scatter(pitch, xr, yr) if cls == "repeated" else None
        snote, texture = ("tile-period scatter" if sc else "no scatter"), 0.0
    note = (f"{cnote}, ceiling {height:.2f} m camera {cam_z:.2f} m, tiles "
            f"{pitch[0]}x{pitch[1]}, {snote}, {dnote}")
    return dataclasses.replace(probe, name=f"{cls}{k}", scatter=sc, texture=texture,
                               note=note)


def write(scene: Scene, traj: Trajectory, folder: Path, site_yaml: str, seed: int,
          sim: SimOptions, real: Realism | None = None, beside: tuple[Path, ...] = ()
          ) -> Path:
    """The recording of ``traj`` under ``scene`` in the SPEC layout, written by hand,
    ``site_yaml`` its ``site.yaml`` (and ``beside`` copied next to it: the ceiling map);
    frame k's noise from ``default_rng([seed, k])``. A folder that already holds a whole
    recording (``truth.csv``: ``--keep`` of an earlier run) keeps its frames, but takes
    this ``site_yaml`` and ``beside`` (the survey just run: its map, not the last one's)."""
    whole = (folder / "truth.csv").exists()
    if not whole:
        shutil.rmtree(folder, ignore_errors=True)
        (folder / "frames").mkdir(parents=True)
        (folder / "rig.yaml").write_text(yaml.safe_dump(scene.rig, sort_keys=False))
    (folder / "site.yaml").write_text(site_yaml)
    for p in beside:
        shutil.copy(p, folder / p.name)
    if whole:
        return folder
    rig, shown = Rig.load(folder / "rig.yaml"), scene.shown()
    opts = dataclasses.replace(sim, scatter=scene.scatter, texture=scene.texture)
    part = folder / "truth.csv.part"          # truth.csv last: a whole recording has it
    with open(folder / "frames.csv", "w") as fc, open(part, "w") as ft:
        fc.write("index,t_ns\n")
        ft.write("t_ns,x,y,yaw_deg\n")
        for k in range(len(traj)):
            x, y, yaw = traj.pose(k)
            rng = np.random.default_rng([seed, k])
            img = (render_frame(rig, shown, x, y, yaw, opts, rng) if real is None else
                   render_real(rig, shown, traj.pose_at, int(traj.t_ns[k]), opts, real, rng))
            cv2.imwrite(str(folder / "frames" / f"{k:06d}.png"), img)
            fc.write(f"{k},{int(traj.t_ns[k])}\n")
            ft.write(f"{int(traj.t_ns[k])},{x:.6f},{y:.6f},{math.degrees(yaw):.6f}\n")
    part.rename(folder / "truth.csv")
    return folder


def surveyed(folder: Path, out: Path) -> tuple[dict, Path | None]:
    """``folder`` surveyed as ``ceilcal survey`` does, anchored by its first frame's
    true pose, into ``out``: the figures, and ``out`` (None: the survey refused)."""
    rec = Recording(folder)
    t0 = (float(rec.truth.x_m[0]), float(rec.truth.y_m[0]), float(rec.truth.yaw_rad[0]))
    shutil.rmtree(out, ignore_errors=True)
    c0 = time.process_time()
    try:
        run = survey_site(folder / "rig.yaml", [folder], out, anchors=Anchors(start_pose=t0))
    except CeilkitError as e:
        return {"survey": f"refused: {e}"[:160], "survey_cpu_s": time.process_time() - c0}, None
    cpu = time.process_time() - c0
    res = run.result
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, np.unwrap(rec.truth.yaw_rad)]
    t = truth[res.frame]
    pos = np.hypot(*(res.poses[:, :2] - t[:, :2]).T)
    dyaw = np.degrees(np.abs(np.remainder(res.poses[:, 2] - t[:, 2] + math.pi, 2 * math.pi)
                             - math.pi))
    feat = np.concatenate(feature_errors(rec, res, res.poses, 0.0))   # per keyframe
    keys = res.keys[res.keys != 0]                       # the anchor is exact
    z = np.hypot(*((res.poses[keys, :2] - truth[res.frame[keys], :2])
                   / res.sigma[keys, :2]).T)
    return {"survey": "ok", "survey_cpu_s": cpu, "keyframes": int(len(res.keys)),
            "closures": sum(lk.kind in CLOSURE_KINDS for lk in res.links),
            "gaps": sum(lk.kind == "gap" for lk in res.links),
            "piece_joins": sum(lk.kind == "piece" for lk in res.links), "unplaced": res.unplaced,
            "pieces_unplaced": res.unplaced_pieces,
            "map_features": run.cmap.feature_count,
            "poses_rms_mm": 1e3 * float(np.sqrt(np.mean(pos ** 2))),
            "poses_max_mm": 1e3 * float(pos.max()), "yaw_max_deg": float(dyaw.max()),
            "features_rms_mm": 1e3 * float(np.sqrt(np.mean(feat ** 2))),
            "keyframe_z_median": float(np.median(z)), "keyframe_z_p95":
                float(np.percentile(z, 95)),
            "map_sigma_mm_median": 1e3 * float(np.median(run.cmap.sigma_m))}, out


def reloc(folder: Path, out: Path, k: int) -> int:
    """Frames from the carry (frame ``k``) to the first right valid pose; -1: none."""
    truth = {int(r["t_ns"]): r for r in csv.DictReader(open(folder / "truth.csv"))}
    order = {t: i for i, t in enumerate(truth)}
    for r in csv.DictReader(open(out / "poses.csv")):
        i = order[int(r["t_ns"])]
        if i < k or "" in (r["x"], r["y"], r["yaw_deg"]):
            continue
        t = truth[int(r["t_ns"])]
        d = math.hypot(float(r["x"]) - float(t["x"]), float(r["y"]) - float(t["y"]))
        dyaw = math.remainder(math.radians(float(r["yaw_deg"]) - float(t["yaw_deg"])),
                              2 * math.pi)
        if d <= WRONG[0] and abs(dyaw) <= math.radians(WRONG[1]):
            return i - k
    return -1


def run_scene(scene: Scene, tmp: Path, seed: int, sim: SimOptions, real: Realism | None,
              only_runs: list[str] | None) -> list[dict]:
    """The scene's survey, its second drives written on the surveyed map, every run
    replayed and scored."""
    c0 = time.perf_counter()
    sfold = write(scene, scene.survey, tmp / f"{scene.name}-survey",
                  yaml.safe_dump({"ceiling_height": scene.height_m}), seed, sim)
    info, sdir = surveyed(sfold, tmp / f"{scene.name}-site")
    info["survey_s"] = round(time.perf_counter() - c0, 1)
    print(f"{scene.name}: survey {info}", flush=True)
    base = {"scene": scene.name, **info, "note": scene.note}
    if sdir is None:
        return [{**base, "run": "-"}]
    site_yaml = (sdir / "site.yaml").read_text()
    beside = (sdir / "ceiling_map.npz",)
    rows = []
    for suffix, traj in (("second", scene.second), ("kidnap", scene.kidnapped)):
        start = traj.pose(0)
        runs = [(f"{m}-{tag}", m, st) for m in ("texture", "auto")
                for tag, st in ((("none", None), ("right", start)) if suffix == "second"
                                else (("kidnap", start),))]
        runs = [r for r in runs if not only_runs or r[0] in only_runs]
        if not runs:
            continue
        folder = write(scene, traj, tmp / f"{scene.name}-{suffix}", site_yaml, seed + 1,
                       sim, real, beside)
        for tag, method, st in runs:
            out = tmp / f"{scene.name}-{suffix}-{tag}"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            published = Published()
            res = replay(folder, out, method=method, start_pose=st, sinks=[published])
            row = {**base, "run": tag, **score(folder, out, published.poses),
                   "failures": " ".join(f"{k}:{v}" for k, v in
                                        Counter(res.telemetry.failures).most_common(3)),
                   "s": round(time.perf_counter() - t0, 1)}
            if suffix == "kidnap":
                row["reloc"] = reloc(folder, out, len(traj) // 2)
            rows.append(row)
            print(f"{scene.name:10s} {tag:15s} valid {row['valid']:3d}/{row['frames']:3d} "
                  f"wrong {row['wrong']:3d}  median {1e3 * row['median_m']:7.2f} mm  NEES "
                  f"{row.get('nees', math.nan):.2f} [{row.get('nees_lo', math.nan):.2f}, "
                  f"{row.get('nees_hi', math.nan):.2f}]  reloc {row.get('reloc', '')}  "
                  f"{row['failures']}  ({row['s']:.0f} s)", flush=True)
    return rows


def scenes(seed: int, n_scatter: int, frames: int, step_m: float) -> list[Scene]:
    """``n_scatter`` scatter scenes, then the two controls, drawn from ``seed``."""
    out = []
    for ci, (cls, count) in enumerate((("scatter", n_scatter), ("plain", 1),
                                       ("repeated", 1))):
        rng = np.random.default_rng([seed, ci])
        out += [draw(cls, rng, frames, k, step_m) for k in range(count)]
    return out


def save(rows: list[dict], path: Path, load_before: tuple[float, float, float],
         sim: SimOptions, preset: str | None) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    header = provenance("bench_heldout_texture.py", load_before, os.getloadavg(), [
        f"# noise {sim.noise_sigma} blur {sim.blur_px} supersample {sim.supersample}; "
        f"second drives' preset {preset or 'none'}; wrong: > {100 * WRONG[0]:.0f} cm or "
        f"{WRONG[1]:.0f} deg"])
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        f.write("\n".join(header) + "\n")
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2, help="scatter scenes (then 2 controls)")
    ap.add_argument("--frames", type=int, default=80, help="frames of each second drive")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", nargs="*", default=["scatter", "plain", "repeated"])
    ap.add_argument("--pick", nargs="*", help="only these scenes (e.g. scatter1 plain0)")
    ap.add_argument("--runs", nargs="*", help="only these runs (e.g. texture-none)")
    ap.add_argument("--survey-step", type=float, default=0.1,
                    help="m driven between the survey drive's frames (default %(default)s)")
    ap.add_argument("--preset", default=None,
                    help="configs/office's simulator preset on the second drives")
    ap.add_argument("--keep", type=Path, help="write the recordings and runs here (kept)")
    ap.add_argument("--out", type=Path, default=OUT / "bench_heldout_texture.csv")
    ap.add_argument("--noise", type=float, default=2.0)
    ap.add_argument("--blur", type=float, default=0.8)
    ap.add_argument("--supersample", type=int, default=2)
    a = ap.parse_args(argv)
    load_before = os.getloadavg()
    sim = SimOptions(noise_sigma=a.noise, blur_px=a.blur, supersample=a.supersample)
    real = load_preset(OFFICE_SITE, a.preset) if a.preset else None
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = a.keep or Path(d)
        tmp.mkdir(parents=True, exist_ok=True)
        for i, scene in enumerate(scenes(a.seed, a.scenes, a.frames, a.survey_step)):
            if scene.name.rstrip("0123456789") not in a.only or \
                    (a.pick and scene.name not in a.pick):
                continue
            print(f"{scene.name}: {scene.note}", flush=True)
            rows += run_scene(scene, tmp, 1000 * a.seed + 10 * i, sim, real, a.runs)
    save(rows, a.out, load_before, sim, a.preset)
    return 0


if __name__ == "__main__":
    sys.exit(main())
