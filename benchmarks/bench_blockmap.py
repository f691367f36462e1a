"""Benchmark: ``ceilcal blockmap`` (markers placed from known poses) against the truth
and against ``ceilcal survey``'s markers on the same drive (issue 39: "on a marker
site, [the survey's markers agree] with ``ceilcal blockmap``").

Drives (each rendered once into ``--out-dir`` when not there):

* **office** (the drive of ``bench_survey.py --against-known``, the same recording
  folder by default): a 12.6 m loop under the office scatter with eight spot lights
  and four 0.2 m AprilTag 36h11 markers, noise 2, blur 0.8, supersample 1, seed 1.
  :func:`~ceilkit.calib.blockmap.map_markers` with the true poses, and the survey's
  markers (:func:`~ceilkit.calib.survey.survey_drives` from the true start pose, then
  :func:`~ceilkit.calib.survey_markers.survey_markers` with the solved poses and the
  keyframes' median pose 1σ, as ``bench_survey.py --against-known`` places them).
* **tiles** (``bench_tiles_markers.py``'s site: 0.6 m tiles, a hatch, five 16 cm tags
  at about 3.2 px a cell): an ellipse of ``--tiles-frames`` poses; blockmap with the
  true poses and the survey's markers from the true start pose, as for the office.

Both measure a marker on its edges
(:func:`~ceilkit.calib.blockmap.frame_sightings`) and fit its views as one square
(:func:`~ceilkit.calib.blockmap.fit_marker`); they differ only in the poses (known, or
the survey's solved keyframes, whose 1σ the survey's corners add).

Figures, per drive and marker: each corner's distance (blockmap to truth, survey to
blockmap, survey to truth) and the distance over the 1σ per axis the two sides claim,
``d / hypot(σ_a, σ_b)`` (σ of the truth: 0): for honest σ a 2-D distance over its
per-axis σ has the Rayleigh law, median 1.18, 95th percentile 2.45.

    .venv/bin/python benchmarks/bench_blockmap.py [--out benchmarks/out/bench_blockmap.json]
        [--office-rec benchmarks/out/survey_known] [--tiles-rec benchmarks/out/blockmap_tiles]

Measured (2026-12-06 18:58 UTC, git 1b28e0d): survey vs blockmap, per corner, office
0.40 / 0.53 / 0.57 mm (median / p95 / max), over the combined 1σ 0.51 / 0.83 / 0.83;
tiles 0.50 / 0.78 / 0.79 mm, 0.54 / 0.84 / 0.85: every corner within one combined 1σ
(docs/survey.md, "Against ceilcal blockmap").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
from bench_survey import KNOWN_LIGHTS, KNOWN_MARKERS, OFFICE
from bench_tiles_markers import OPTIONS as TILES_OPTIONS
from bench_tiles_markers import loop as tiles_loop
from bench_tiles_markers import rig as tiles_rig
from bench_tiles_markers import site as tiles_site

from ceilkit.calib.blockmap import frames_with_poses, map_markers
from ceilkit.calib.poses import StampedPoses
from ceilkit.calib.simulate import simulate_recording
from ceilkit.calib.survey import survey_drives
from ceilkit.calib.survey_loop import loop_trajectory
from ceilkit.calib.survey_markers import survey_markers
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from ceilkit.runtime.sim.scatter_file import scene_beside

ROOT = Path(__file__).resolve().parents[1]
RAYLEIGH = {"median": 1.177, "p95": 2.448}


def render_office(folder: Path) -> None:
    """``bench_survey.py --against-known``'s drive (the same arguments)."""
    office = Site.load(OFFICE / "site.yaml")
    site = dataclasses.replace(office, lights_m=KNOWN_LIGHTS, light_diameter_m=0.12,
                               markers=KNOWN_MARKERS)
    traj = loop_trajectory(3.6, 2.4, laps=1.15, fps=5.0, speed_mps=0.5, centre_m=(4.0, 0.0))
    simulate_recording(Rig.load(OFFICE / "rig.yaml"), site, traj, folder, SimOptions(
        noise_sigma=2.0, blur_px=0.8, supersample=1, scatter=scene_beside(office)), seed=1)


def render_tiles(folder: Path, n: int) -> None:
    poses = np.array(tiles_loop(n))
    traj = Trajectory(np.arange(n, dtype=np.int64) * 100_000_000, poses[:, 0],
                      poses[:, 1], poses[:, 2])
    simulate_recording(tiles_rig(), tiles_site(), traj, folder, TILES_OPTIONS, seed=1)


def _pcts(z: list[float]) -> dict:
    a = np.asarray(z, float)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(np.max(a)), "n": int(a.size)}


def _compare(a: np.ndarray, sa: float, b: np.ndarray, sb: float) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """Corner distances ``(4,)`` m and over ``hypot(sa, sb)``."""
    d = np.linalg.norm(a - b, axis=1)
    return d, d / math.hypot(sa, sb)


def blockmap_vs_truth(rec: Recording, site: Site) -> tuple[dict, dict]:
    """Blockmap of ``rec`` from its truth, each marker against the site's."""
    t0 = time.process_time()
    bm = map_markers(frames_with_poses(rec, StampedPoses.from_truth(rec.truth)), rec.rig,
                     site.ceiling_height_m, site.markers.dictionary)
    cpu = time.process_time() - t0
    rows, ds, zs = [], [], []
    for m in bm.placed:
        d, z = _compare(m.corners_m, m.corner_sigma_m, site.markers.pose(m.id).corners_m(),
                        0.0)
        ds += list(1e3 * d)
        zs += list(z)
        rows.append({"id": m.id, "views": len(m.frames),
                     "corner_sigma_mm": 1e3 * m.corner_sigma_m,
                     "vs_truth_mm": [round(1e3 * v, 4) for v in d],
                     "side_mm_err": 1e3 * (m.pose.size_m - site.markers.pose(m.id).size_m),
                     "rms_px": m.rms_px, "worst_sighting_mm": 1e3 * m.worst_m})
    out = {"frames": bm.frames_used, "sightings": bm.sightings, "cpu_s": cpu,
           "placed": len(bm.placed), "refused": [dataclasses.asdict(r) for r in bm.refused],
           "markers": rows, "vs_truth_mm": _pcts(ds), "vs_truth_over_sigma": _pcts(zs)}
    return out, {m.id: m for m in bm.placed}


def survey_vs_blockmap(rec: Recording, site: Site, placed: dict) -> dict:
    """The survey's markers (``bench_survey.py --against-known``) against blockmap's and
    the truth."""
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    t0 = time.process_time()
    res = survey_drives([rec], rec.rig, site.ceiling_height_m, tuple(truth[0]))
    sig = float(np.nanmedian(np.hypot(*res.sigma[res.keys, :2].T))) / math.sqrt(2)
    frames = ((to_grey(rec.frame(int(res.frame[n])).image), res.poses[n]) for n in res.keys)
    ms = survey_markers(frames, rec.rig, site.ceiling_height_m, site.markers.dictionary, sig)
    cpu = time.process_time() - t0
    rows, acc = [], {"d": [], "z": [], "dt": [], "zt": []}
    for s in ms:
        if s.id not in placed:
            continue
        b = placed[s.id]
        d, z = _compare(s.corners_m, s.sigma_m, b.corners_m, b.corner_sigma_m)
        dt, zt = _compare(s.corners_m, s.sigma_m, site.markers.pose(s.id).corners_m(), 0.0)
        for k, v in (("d", 1e3 * d), ("z", z), ("dt", 1e3 * dt), ("zt", zt)):
            acc[k] += list(v)
        side = site.markers.pose(s.id).size_m
        rows.append({"id": s.id, "survey_views": s.views, "survey_sigma_mm": 1e3 * s.sigma_m,
                     "blockmap_sigma_mm": 1e3 * b.corner_sigma_m,
                     "vs_blockmap_mm": [round(1e3 * v, 3) for v in d],
                     "vs_blockmap_over_sigma": [round(v, 3) for v in z],
                     "survey_side_mm_err": 1e3 * (s.size_m - side),
                     "blockmap_side_mm_err": 1e3 * (b.pose.size_m - side)})
    return {"keyframes": int(len(res.keys)), "cpu_s_survey_and_markers": cpu,
            "pose_sigma_mm": 1e3 * sig, "markers": rows,
            "vs_blockmap_mm": _pcts(acc["d"]), "vs_blockmap_over_sigma": _pcts(acc["z"]),
            "survey_vs_truth_mm": _pcts(acc["dt"]),
            "survey_vs_truth_over_sigma": _pcts(acc["zt"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--office-rec", type=Path, default=ROOT / "benchmarks/out/survey_known")
    ap.add_argument("--tiles-rec", type=Path, default=ROOT / "benchmarks/out/blockmap_tiles")
    ap.add_argument("--tiles-frames", type=int, default=120)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/out/bench_blockmap.json")
    args = ap.parse_args()
    if not (args.office_rec / "frames.csv").exists():
        render_office(args.office_rec)
    if not (args.tiles_rec / "frames.csv").exists():
        render_tiles(args.tiles_rec, args.tiles_frames)
    out = {"rayleigh_honest": RAYLEIGH}
    rec = Recording(args.office_rec)
    site = dataclasses.replace(rec.site, markers=KNOWN_MARKERS)
    out["office"], placed = blockmap_vs_truth(rec, site)
    out["office"]["survey"] = survey_vs_blockmap(rec, site, placed)
    rec = Recording(args.tiles_rec)
    out["tiles"], placed = blockmap_vs_truth(rec, tiles_site())
    out["tiles"]["survey"] = survey_vs_blockmap(rec, tiles_site(), placed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
