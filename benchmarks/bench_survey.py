"""Benchmark: ``ceilcal survey`` on a ~60 m office drive with no external poses
(issue 39, item 1): how far the map's features and the poses land from the truth with
the chain alone and after loop closure, time and memory.

The drive (rendered once into ``--rec`` when that folder does not hold it): the packaged
office (configs/office, its scatter scene), a 12.8 x 2.4 m rounded loop centred on
x = 6 m driven 2.05 laps (60.2 m) at 0.5 m/s, a frame every 5 cm (10 fps), noise 2 and
blur 0.8 grey levels / px, supersample 3, seed 1. It is surveyed anchored by the truth
of its first frame (the start pose a user would measure).

Figures:

* **features**: every keyframe's ceiling features (its ORB keypoints on the ceiling
  plane, :func:`~ceilkit.calib.survey_places.place_of`) placed by the surveyed pose
  against by the true pose: RMS and max of the distance, for the chain (the poses
  before the solve) and the solved graph;
* **map**: the ceiling map built from the surveyed poses against one built from the
  true poses (the same keyframes): features matched within 2 cm and 40 bits, RMS;
* **poses**: position RMS, max and at the end; heading max;
* the time of each stage (process CPU and wall), the graph's solve by Gauss-Newton and
  by ``scipy.optimize.least_squares`` on the same graph, the peak RSS after the survey
  and after building the two maps (``build_map``'s feature merge dominates it).

    .venv/bin/python benchmarks/bench_survey.py [--rec benchmarks/out/survey_office60]
        [--out benchmarks/out/bench_survey.json]

Measured (2026-12-06 18:55 UTC, git 1b28e0d, load 4-6): features 2.80 mm RMS with the
chain alone, 1.07 mm (max 2.4) after loop closure (issue 39: ≤ 1 cm); poses 0.95 mm
RMS; the map 1955 of 2335 features matched, 1.59 mm RMS; 277 keyframes, 288 closures;
17.2 s CPU; peak RSS 334 MB (docs/survey.md, "Figures"). The survey's drive has noise
and blur only; under the ``realistic`` preset, told its readout (``--preset realistic``,
2026-12-06 21:56 UTC): features 18.6 mm chain, 1.49 mm (max 4.7) after closure, poses
1.44 mm RMS; not told 26.4 mm.

``--preset NAME`` renders the same drive (path and seed) under configs/office's
simulator preset into ``benchmarks/out/survey_office60_<NAME>`` (``--seed N`` past 1:
``..._s<N>``, the noise and the preset's layout drawn from it) and tells the survey the
preset's rolling shutter as ``readout_ms`` (``--no-readout``: not told). The features'
truth is then each point's ceiling point seen from the true pose at its row's time
(:func:`feature_errors`; with no rolling shutter, the frame's stamp as before).

    .venv/bin/python benchmarks/bench_survey.py --preset realistic [--no-readout]
        [--seed N]

``--second-drive`` measures instead a second drive on that map (issue 39: "a second
drive on another path then localizes from single frames on ≥ 95 % of frames, position
median ≤ 1 cm, and no valid pose wrong by more than 10 cm or 2°"): the 60 m drive
surveyed as above, its map (``survey_map``) the site's; 200 frames of another path
(from x = 11 m heading -x, weaving ±1.0 m across the loop's two rows with a 4 m period,
the heading wobbling ±0.5 rad on top, 0.5 m/s at 10 fps, noise 2, blur 0.8, supersample
2, seed 5; rendered once into ``--second-rec``) with configs/office's ``--preset`` (none:
noise and blur only); each frame estimated alone by ``texture`` (no odometry, the
preset's rolling shutter as ``readout_ms``; with ``--velocity`` a prior holding the
truth's velocity and no position, what a track or wheel odometry and a gyro carry).
Prints each refused frame's reason, the valid share, the position error's median, 95th
percentile and max, the worst heading, the valid poses wrong by > 10 cm or 2°, the
position NEES (2 dof: the law's median 1.39, 95th percentile 5.99) and on how many
valid frames the texture method fitted the frame's own velocity (no ``--velocity``).

    .venv/bin/python benchmarks/bench_survey.py --second-drive [--preset realistic]
        [--velocity] [--second-rec benchmarks/out/survey_second_<preset>]
        [--survey-preset realistic [--no-readout]]
        [--out benchmarks/out/bench_survey_second_<preset>[_velocity].json]

Measured (2026-12-06 19:43 UTC, load 4-6; 21 s wall a run once the drive is rendered,
5 min with ``realistic``'s rendering): noise and blur 199 / 200 valid (1 ``ambiguous``),
median 1.14 mm, p95 2.7, max 4.4, 0 wrong; ``--preset realistic`` 184 / 200, median
3.19 mm, 0 wrong; ``--preset realistic --velocity`` 189 / 200 (94.5 %: 9 frames a person
under the camera, 2 ``ambiguous``), median 1.16 mm, p95 2.5, max 4.0, heading 0.26° at
most, 0 wrong. After a pose with few distinctive matches lists and judges its twins
(19:50 UTC): noise and blur 200 / 200, ``--preset realistic --velocity`` 191 / 200
(95.5 %: the 9 person frames), median 1.15 mm, 0 wrong (docs/survey.md, "A second
drive"). After the texture method fits a frame's own velocity from its rows when the
prior gives none (2026-12-06 21:00 UTC): ``--preset realistic`` 191 / 200 (95.5 %:
the 9 person frames), median 1.17 mm, p95 2.83, max 5.13, NEES median 1.37, 0 wrong;
with ``--velocity`` and noise and blur unchanged (191 and 200 / 200, NEES medians 1.80
and 1.85).

``--against-known`` measures instead the survey's sections against the known-pose tools
(issue 39: "the survey's lights agree with ``ceilcal lightmap`` from known poses within
their σ; on a marker site, with ``ceilcal blockmap``"): a 12.6 m loop (3.6 x 2.4 m,
1.15 laps, a frame every 0.1 m, noise 2, blur 0.8, supersample 1, seed 1) under the
office scatter with eight spot lights (0.12 m) and four AprilTag markers (0.2 m) added,
surveyed from its true start pose. Its lights (``survey_files._lights``: the lit spots
placed with the solved poses, the clusters that stay put) against
:func:`~ceilkit.calib.lightmap.survey_lights` with the true poses (what ``ceilcal
lightmap`` does), the same clusters kept; its markers
(:func:`~ceilkit.calib.survey_markers.survey_markers` with the solved poses) against the
same placement with the true poses (the edges measured and fitted as ``ceilcal
blockmap`` does: what its known-pose marker map holds; ``bench_blockmap.py`` compares
with blockmap itself) and against the site's markers.

    .venv/bin/python benchmarks/bench_survey.py --against-known
        [--rec benchmarks/out/survey_known] [--out benchmarks/out/bench_survey_known.json]

Measured (2026-12-06 18:57 UTC, git 1b28e0d): 19 lights written (the 8 lamps and 11
round spots that are not lamps), 0.53 mm median and 1.0 mm max from the known-pose
placement, distance over the combined 1σ median 0.30, 95th percentile 1.70, max 2.39;
markers 0.22-0.52 mm RMS from the known-pose placement.

``--against-known --seeds N`` measures instead whether the stated 1σ covers the error
(:func:`honesty`) on N renderings of that loop (seed s moved by (0.05, 0.03) m per seed
and its noise drawn from seed s; rendered into ``survey_known_s<s>`` beside ``--rec``):
each keyframe's position error against the truth over its 1σ and each marker corner's
(docs/survey.md, "Limits"; measured 2026-12-06, ``--seeds 5``: the worst seed's 95th
percentile 2.07 for the keyframes; the corners' against the site 0.63-0.96, and
against the known-pose placement over the poses' part of their 1σ alone 0.95-1.58, the
2-D law's 2.45).

    .venv/bin/python benchmarks/bench_survey.py --against-known --seeds 5
        [--out benchmarks/out/bench_survey_honesty.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import resource
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import ceilkit.calib.survey as survey_mod
import ceilkit.calib.survey_files as survey_files
from ceilkit.calib.lightmap import survey_lights
from ceilkit.calib.simulate import simulate_recording
from ceilkit.calib.survey import SurveyOptions, result_frames, survey_drives, survey_map
from ceilkit.calib.survey_graph import solve_graph
from ceilkit.calib.survey_loop import loop_trajectory
from ceilkit.calib.survey_markers import survey_markers
from ceilkit.calib.survey_places import place_of
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import MarkerPose, Markers, Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.texture import TextureEstimator
from ceilkit.runtime.estimators.texture.ceilmap import build_map
from ceilkit.runtime.estimators.texture.match import places
from ceilkit.runtime.estimators.texture.shutter import Readout
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry.ceiling import vehicle_to_world
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.realism import load_preset
from ceilkit.runtime.sim.render import SimOptions, straight_drive
from ceilkit.runtime.sim.scatter_file import scene_beside

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_paired import velocity  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "configs" / "office"


def render(folder: Path, preset: str | None = None, seed: int = 1) -> None:
    """The survey drive (docstring) into ``folder``, with configs/office's ``preset``
    (None: noise and blur only); ``seed`` draws the noise, and past 1 the preset's
    layout too (``layout_seed`` ``seed - 1``: the people elsewhere); the same path."""
    rig = Rig.load(OFFICE / "rig.yaml")
    site = Site.load(OFFICE / "site.yaml")
    traj = loop_trajectory(12.8, 2.4, laps=2.05, fps=10.0, speed_mps=0.5,
                           centre_m=(6.0, 0.0))
    real = load_preset(OFFICE / "site.yaml", preset) if preset else None
    if real is not None and seed > 1:
        real = dataclasses.replace(real, layout_seed=seed - 1)
    simulate_recording(rig, site, traj, folder, SimOptions(
        noise_sigma=2.0, blur_px=0.8, supersample=3, scatter=scene_beside(site)),
        seed=seed, realism=real)


def truth_at(rec: Recording, t_ns: np.ndarray) -> np.ndarray:
    """``(N, 3)`` the true pose at stamps ``t_ns`` (linear between truth.csv's rows, the
    heading unwrapped)."""
    tt = rec.truth.t_ns.astype(float)
    yaw = np.unwrap(rec.truth.yaw_rad)
    return np.column_stack([np.interp(t_ns, tt, v) for v in (rec.truth.x_m, rec.truth.y_m,
                                                            yaw)])


def feature_errors(rec: Recording, res, poses: np.ndarray, readout_ms: float
                   ) -> list[np.ndarray]:
    """Every keyframe's ORB points of the frame as recorded: where the survey puts each
    (the keyframe's surveyed pose, the point put back to the stamp with the survey's
    velocity when it was told a readout, as its resampling does) against the ceiling
    point it truly is (seen from the true pose at its row's time, ``readout_ms`` the
    camera's true readout), m: one array per keyframe."""
    out = []
    for n in res.keys:
        k = int(res.frame[n])
        q = place_of(to_grey(rec.frame(k).image), rec.rig, res.ceiling_height_m).points_v
        ro = Readout(rec.rig, res.ceiling_height_m, max(readout_ms, 1e-9) / 1e3,
                     (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        tau = ro.times(q) if readout_ms > 0 else np.zeros(len(q))
        t = truth_at(rec, rec.t_ns[k] + 1e9 * tau)          # each point's row's pose
        c, s = np.cos(t[:, 2]), np.sin(t[:, 2])
        true_w = np.column_stack([t[:, 0] + c * q[:, 0] - s * q[:, 1],
                                  t[:, 1] + s * q[:, 0] + c * q[:, 1]])
        if res.velocity is not None and res.readout_ms > 0 and readout_ms > 0:
            q = dataclasses.replace(ro, velocity=tuple(res.velocity[n])).unrolled(
                q, tau * res.readout_ms / readout_ms, 0.0)
        out.append(np.hypot(*(vehicle_to_world(q, *poses[n]) - true_w).T))
    return out


def map_errors(rec: Recording, res, truth: np.ndarray) -> dict:
    """The map from the surveyed poses against one from the true poses, the same
    keyframes read the same way (with the survey's resampling when it had one)."""
    cmap = survey_map(res, [rec], rec.rig)
    read = result_frames(res, [rec], rec.rig)
    frames = (read.grey(0, int(res.frame[n])) for n in res.keys)
    ref = build_map(frames, [tuple(truth[int(res.frame[n])]) for n in res.keys], rec.rig,
                    res.ceiling_height_m)
    # a feature's first row (its medoid descriptor) stands for it, on both maps
    a, b = (np.unique(places(m.points_xy)[0]) for m in (cmap, ref))
    d, j = cKDTree(ref.points_xy[b]).query(cmap.points_xy[a], distance_upper_bound=0.02)
    ok = np.isfinite(d)
    bits = np.unpackbits(cmap.descriptors[a][ok] ^ ref.descriptors[b][j[ok]], axis=1).sum(1)
    good = d[ok][bits <= 40]
    return {"features": int(len(a)), "matched": int(len(good)),
            "rms_mm": 1e3 * float(np.sqrt(np.mean(good ** 2))) if len(good) else None,
            "sigma_median_mm": 1e3 * float(np.median(cmap.sigma_m[a]))}


def _stats(err: np.ndarray) -> dict:
    return {"rms_mm": 1e3 * float(np.sqrt(np.mean(err ** 2))),
            "max_mm": 1e3 * float(err.max())}


def _solvers(captured: dict, t_true: np.ndarray) -> dict:
    """Both solvers on the survey's graph: CPU, iterations, position RMS vs truth."""
    out = {}
    for solver in ("gauss-newton", "least_squares"):
        t0 = time.process_time()
        sol = solve_graph(captured["poses0"], captured["edges"], solver=solver,
                          sigma_nodes=[])
        err = np.hypot(*(sol.poses[:, :2] - t_true[:, :2]).T)
        out[solver] = {"cpu_s": time.process_time() - t0, "iterations": sol.iterations,
                       "rms_mm": 1e3 * float(np.sqrt(np.mean(err ** 2)))}
    return out


KNOWN_LIGHTS = np.array([[2.3, -1.5], [3.1, 1.4], [4.4, -1.3], [5.0, 1.6], [5.9, -0.6],
                         [2.1, 0.5], [4.0, 0.1], [6.1, 1.0]])
KNOWN_MARKERS = Markers("DICT_APRILTAG_36h11", 0.2, (
    MarkerPose(1, 2.4, -0.9, 0.3, 0.2), MarkerPose(2, 4.7, 1.0, -1.2, 0.2),
    MarkerPose(4, 5.6, -1.0, 2.0, 0.2), MarkerPose(6, 3.2, 0.9, 0.0, 0.2)))


def _pcts(z: np.ndarray) -> dict:
    return {"median": float(np.median(z)), "p95": float(np.percentile(z, 95)),
            "max": float(np.max(z))}


def known_recording(folder: Path, seed: int = 1) -> Recording:
    """The ``--against-known`` loop rendered into ``folder`` (when it does not hold it):
    seed 1 centred on (4.0, 0.0) m; seed s moved by (0.05, 0.03) m per seed after the
    first and its noise drawn from seed s."""
    office = Site.load(OFFICE / "site.yaml")
    site = dataclasses.replace(office, lights_m=KNOWN_LIGHTS, light_diameter_m=0.12,
                               markers=KNOWN_MARKERS)
    if not (folder / "frames.csv").exists():
        traj = loop_trajectory(3.6, 2.4, laps=1.15, fps=5.0, speed_mps=0.5,
                               centre_m=(4.0 + 0.05 * (seed - 1), 0.03 * (seed - 1)))
        simulate_recording(Rig.load(OFFICE / "rig.yaml"), site, traj, folder, SimOptions(
            noise_sigma=2.0, blur_px=0.8, supersample=1, scatter=scene_beside(office)),
            seed=seed)
    return Recording(folder)


def _marker_views(rec: Recording, res, poses: np.ndarray, sigma_m: float = 0.0):
    frames = ((to_grey(rec.frame(int(res.frame[n])).image), poses[n]) for n in res.keys)
    return {m.id: m for m in survey_markers(frames, rec.rig, res.ceiling_height_m,
                                            KNOWN_MARKERS.dictionary, sigma_m)}


def honesty(rec: Recording) -> dict:
    """Whether the survey's stated 1σ covers its error on one ``--against-known`` loop:
    each keyframe's position error against the truth over its 1σ (``hypot(ex / σx,
    ey / σy)``, the 2-D law's median 1.18, 95th percentile 2.45), its heading's
    (1-D: 0.67, 1.96), and each marker corner's distance from the same placement with
    the true poses and from the site's corners over the marker's ``sigma_m`` (marker 2,
    read off under a light panel even from the true poses, left out of the latter), and
    from the same placement with the true poses over the poses' part of it alone
    (``pose_sigma_m``: the two placements share every edge measurement, so only the
    poses' error parts them)."""
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    res = survey_drives([rec], rec.rig, rec.site.ceiling_height_m, tuple(truth[0]))
    keys = res.keys[res.keys != 0]                       # the anchor is exact
    t = truth[res.frame[keys]]
    e, s = res.poses[keys] - t, res.sigma[keys]
    e[:, 2] = (e[:, 2] + math.pi) % (2 * math.pi) - math.pi
    sig = float(np.nanmedian(np.hypot(*res.sigma[res.keys, :2].T))) / math.sqrt(2)
    ms, mt = _marker_views(rec, res, res.poses, sig), _marker_views(rec, res, truth[res.frame])
    known, site, poses_only = [], [], []
    for m in ms.values():
        if m.id in mt:
            d = np.linalg.norm(m.corners_m - mt[m.id].corners_m, axis=1)
            known += list(d / m.sigma_m)
            poses_only += list(d / m.pose_sigma_m)
        if m.id != 2:
            site += list(np.linalg.norm(m.corners_m - KNOWN_MARKERS.pose(m.id).corners_m(),
                                        axis=1) / m.sigma_m)
    return {"keyframes": int(len(keys)),
            "position_error_mm": _pcts(1e3 * np.hypot(*e[:, :2].T)),
            "position_sigma_mm_median": 1e3 * float(np.median(s[:, :2])),
            "position_error_over_sigma": _pcts(np.hypot(*(e[:, :2] / s[:, :2]).T)),
            "yaw_error_over_sigma": _pcts(np.abs(e[:, 2]) / s[:, 2]),
            "marker_sigma_mm": [1e3 * m.sigma_m for m in ms.values()],
            "corner_vs_known_pose_over_sigma": _pcts(np.array(known)),
            "corner_vs_known_pose_over_pose_sigma": _pcts(np.array(poses_only)),
            "corner_vs_site_over_sigma": _pcts(np.array(site))}


def against_known(folder: Path) -> dict:
    """The survey's lights and markers against the known-pose placements (docstring)."""
    rec = known_recording(folder)
    site = rec.site
    rig = rec.rig
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    res = survey_drives([rec], rig, site.ceiling_height_m, tuple(truth[0]))
    lm, note = survey_files._lights([rec], res)
    known = survey_lights(rec, ceiling_height_m=site.ceiling_height_m)
    keep = known.spread_m <= survey_files.LIGHT_SPREAD_M
    d, j = cKDTree(known.lights_m[keep]).query(lm.lights_m)
    z = d / np.hypot(lm.sigma_m, known.sigma_m[keep][j])
    to_true = cKDTree(KNOWN_LIGHTS).query(lm.lights_m)[0]
    out = {"lights": {"surveyed": len(lm.lights_m), "note": note,
                      "known_pose_kept": int(keep.sum()), "distance_mm": _pcts(1e3 * d),
                      "distance_over_sigma": _pcts(z),
                      "sigma_mm_median": 1e3 * float(np.median(lm.sigma_m)),
                      "true_lights_surveyed": int(np.count_nonzero(to_true < 0.02)),
                      "other_stable_spots": int(np.count_nonzero(to_true >= 0.02))}}
    frames = lambda P: ((to_grey(rec.frame(int(res.frame[n])).image), P[n])  # noqa: E731
                        for n in res.keys)
    sig = float(np.nanmedian(np.hypot(*res.sigma[res.keys, :2].T))) / math.sqrt(2)
    ms = survey_markers(frames(res.poses), rig, site.ceiling_height_m,
                        KNOWN_MARKERS.dictionary, sig)
    mt = {m.id: m for m in survey_markers(frames(truth[res.frame]), rig,
                                          site.ceiling_height_m, KNOWN_MARKERS.dictionary)}
    rms = lambda a, b: float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))  # noqa: E731
    out["markers"] = [{"id": m.id, "views": m.views, "sigma_mm": 1e3 * m.sigma_m,
                       "vs_known_pose_rms_mm": 1e3 * rms(m.corners_m, mt[m.id].corners_m),
                       "known_pose_sigma_mm": 1e3 * mt[m.id].sigma_m,
                       "vs_site_rms_mm": 1e3 * rms(m.corners_m,
                                                  KNOWN_MARKERS.pose(m.id).corners_m()),
                       "known_pose_vs_site_rms_mm": 1e3 * rms(
                           mt[m.id].corners_m, KNOWN_MARKERS.pose(m.id).corners_m())}
                      for m in ms if m.id in mt]
    return out


def _honesty_report(runs: list[dict], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"seeds": runs}, indent=1) + "\n")
    for k, r in enumerate(runs, 1):
        print(f"seed {k}: keyframes' position error / σ median "
              f"{r['position_error_over_sigma']['median']:.2f} p95 "
              f"{r['position_error_over_sigma']['p95']:.2f}, yaw p95 "
              f"{r['yaw_error_over_sigma']['p95']:.2f}; corners / σ against the known-pose "
              f"placement p95 {r['corner_vs_known_pose_over_sigma']['p95']:.2f}, against "
              f"the site p95 {r['corner_vs_site_over_sigma']['p95']:.2f}; position error "
              f"median {r['position_error_mm']['median']:.2f} mm, 1σ per axis median "
              f"{r['position_sigma_mm_median']:.2f} mm")
    for key in ("position_error_over_sigma", "corner_vs_known_pose_over_sigma",
                "corner_vs_known_pose_over_pose_sigma", "corner_vs_site_over_sigma"):
        print(f"{key}: median {min(r[key]['median'] for r in runs):.2f}-"
              f"{max(r[key]['median'] for r in runs):.2f}, p95 "
              f"{min(r[key]['p95'] for r in runs):.2f}-{max(r[key]['p95'] for r in runs):.2f}")


def second_drive(rec: Recording, folder: Path, preset: str | None, with_velocity: bool,
                 n: int = 200, survey_readout_ms: float = 0.0) -> dict:
    """``--second-drive``: ``rec`` surveyed from its first frame's true pose, its map
    (:func:`~ceilkit.calib.survey.survey_map`) the site's; the second path (docstring)
    rendered into ``folder`` when it does not hold it, with ``preset`` (None: noise and
    blur only); each of its frames estimated alone by ``texture`` (no odometry),
    ``readout_ms`` the preset's rolling shutter, the prior (with ``with_velocity``) the
    truth's velocity and no position. The summary and every frame's outcome.
    ``survey_readout_ms``: the survey drive's readout told to the survey."""
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    res = survey_drives([rec], rec.rig, rec.site.ceiling_height_m, tuple(truth[0]),
                        SurveyOptions(readout_ms=survey_readout_ms))
    smap = survey_map(res, [rec], rec.rig)
    real = load_preset(OFFICE / "site.yaml", preset) if preset else None
    rig, site = Rig.load(OFFICE / "rig.yaml"), Site.load(OFFICE / "site.yaml")
    if not (folder / "frames.csv").exists():
        traj = straight_drive(n, fps=10.0, speed_mps=0.5, x0_m=11.0, y_m=0.0,
                              yaw_rad=math.pi, weave_m=1.0, weave_period_m=4.0,
                              yaw_wobble_rad=0.5)
        simulate_recording(rig, site, traj, folder, SimOptions(
            noise_sigma=2.0, blur_px=0.8, supersample=2, scatter=scene_beside(site)),
            seed=5, realism=real)
    second = Recording(folder)
    with tempfile.TemporaryDirectory() as tmp:
        smap.save(Path(tmp) / "survey.npz")
        est = TextureEstimator(rig, dataclasses.replace(
            site, ceiling_map=str(Path(tmp) / "survey.npz")), {
            "plane_odometry": False,
            "readout_ms": real.rolling_shutter_ms if real is not None else 0.0})
    stamps = [(None, int(second.frame(k).t_ns), (second.truth.x_m[k], second.truth.y_m[k],
                                                 second.truth.yaw_rad[k]))
              for k in range(len(second))]
    free = np.diag([np.inf, np.inf, 1e4])        # the motion only: no position, any heading
    rows = []
    for k, (_, t_ns, t) in enumerate(stamps):
        prior = PoseEstimate(t_ns, "track", None, None, 0.0, 0.0, cov=free,
                             velocity=velocity(stamps, k)) if with_velocity else None
        e = est.estimate(second.frame(k).image, t_ns, prior)
        row = {"frame": k, "valid": bool(e), **{key: e.diagnostics.get(key) for key in (
            "features", "matches", "inliers", "unique", "runner_up", "ncc", "runner_up_ncc",
            "differ_ncc", "runner_up_differ_ncc")}}
        if e:
            d = np.array([e.x_m - t[0], e.y_m - t[1]])
            row.update(err_mm=1e3 * math.hypot(*d),
                       err_deg=abs(math.degrees(math.remainder(e.yaw_rad - t[2], 2 * math.pi))),
                       nees=float(d @ np.linalg.solve(np.asarray(e.cov, float)[:2, :2], d)),
                       velocity=e.diagnostics.get("velocity"),
                       velocity_sigma=e.diagnostics.get("velocity_sigma"))
        else:
            row.update(reason=e.reason, detail=e.detail)
        rows.append(row)
    ok = [r for r in rows if r["valid"]]
    err = np.array([r["err_mm"] for r in ok]) if ok else np.full(1, np.nan)
    return {"preset": preset, "velocity": with_velocity, "map_rows": int(len(smap.points_xy)),
            "frames": len(rows), "valid": len(ok), "valid_pct": 100.0 * len(ok) / len(rows),
            "median_mm": float(np.median(err)), "p95_mm": float(np.percentile(err, 95)),
            "max_mm": float(np.max(err)),
            "max_deg": max((r["err_deg"] for r in ok), default=math.nan),
            "wrong": sum(r["err_mm"] > 100.0 or r["err_deg"] > 2.0 for r in ok),
            "nees_median": float(np.median([r["nees"] for r in ok])) if ok else math.nan,
            "nees_p95": float(np.percentile([r["nees"] for r in ok], 95)) if ok else math.nan,
            "own_velocity": sum(r["velocity"] is not None for r in ok),
            "reasons": dict(Counter(r["reason"] for r in rows if not r["valid"])),
            "per_frame": rows}


def _second_report(args: argparse.Namespace) -> None:
    # --survey-preset: the map surveyed from the survey drive rendered under that preset
    # (survey_office60_<name>, told its readout unless --no-readout)
    sp = args.survey_preset
    rec = Recording(args.rec or ROOT / ("benchmarks/out/survey_office60" +
                                        (f"_{sp}" if sp else "")))
    told = 0.0 if not sp or args.no_readout else \
        load_preset(OFFICE / "site.yaml", sp).rolling_shutter_ms
    name = args.preset or "noise_blur"
    out = second_drive(rec, args.second_rec or ROOT / f"benchmarks/out/survey_second_{name}",
                       args.preset, args.velocity, survey_readout_ms=told)
    out.update(survey_recording=str(rec.folder), survey_readout_ms=told)
    path = args.out or ROOT / (f"benchmarks/out/bench_survey_second_{name}"
                               f"{'_velocity' if args.velocity else ''}"
                               f"{f'_on_{sp}' if sp else ''}"
                               f"{'_no_readout' if sp and args.no_readout else ''}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    for r in out["per_frame"]:
        if not r["valid"]:
            print(f"frame {r['frame']}: {r['reason']}: {r['detail']}")
    print(f"second drive ({name}{', the truth velocity' if args.velocity else ''}): valid "
          f"{out['valid']} / {out['frames']} ({out['valid_pct']:.1f} %), position median "
          f"{out['median_mm']:.2f} p95 {out['p95_mm']:.2f} max {out['max_mm']:.2f} mm, "
          f"heading max {out['max_deg']:.2f} deg, wrong {out['wrong']}; position NEES (2 dof) "
          f"median {out['nees_median']:.2f} p95 {out['nees_p95']:.2f}; the frame's own "
          f"velocity fitted on {out['own_velocity']}; refused {out['reasons']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rec", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--against-known", action="store_true")
    ap.add_argument("--seeds", type=int, default=0,
                    help="with --against-known: the σ's honesty on this many renderings")
    ap.add_argument("--second-drive", action="store_true",
                    help="localize a second drive's single frames on the surveyed map")
    ap.add_argument("--preset", default=None,
                    help="configs/office's simulator preset of the survey drive (or, with "
                    "--second-drive, of the second drive)")
    ap.add_argument("--survey-preset", default=None,
                    help="with --second-drive: the map surveyed from the survey drive "
                    "rendered under this preset")
    ap.add_argument("--seed", type=int, default=1,
                    help="the survey drive's seed (past 1 also the preset's layout)")
    ap.add_argument("--no-readout", action="store_true",
                    help="do not tell the survey the preset's rolling shutter")
    ap.add_argument("--velocity", action="store_true",
                    help="with --second-drive: each frame's prior the truth's velocity")
    ap.add_argument("--second-rec", type=Path, default=None,
                    help="with --second-drive: the second drive's folder (rendered once)")
    args = ap.parse_args()
    if args.second_drive:
        _second_report(args)
        return
    if args.against_known and args.seeds:
        base = args.rec or ROOT / "benchmarks/out/survey_known"
        _honesty_report([honesty(known_recording(
            base if s == 1 else base.with_name(f"{base.name}_s{s}"), s))
            for s in range(1, args.seeds + 1)],
            args.out or ROOT / "benchmarks/out/bench_survey_honesty.json")
        return
    if args.against_known:
        out = against_known(args.rec or ROOT / "benchmarks/out/survey_known")
        path = args.out or ROOT / "benchmarks/out/bench_survey_known.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1) + "\n")
        print(json.dumps(out, indent=1))
        return
    _survey_report(args)


def _survey_report(args: argparse.Namespace) -> None:
    """The survey part (docstring): the drive rendered into ``--rec`` when it does not
    hold it (``--preset``, ``--seed``), surveyed (told the preset's readout unless
    ``--no-readout``), its figures printed and written to ``--out``."""
    name = "survey_office60" + (f"_{args.preset}" if args.preset else "") + \
        (f"_s{args.seed}" if args.seed > 1 else "")
    args.rec = args.rec or ROOT / "benchmarks/out" / name
    args.out = args.out or ROOT / "benchmarks/out" / (
        name.replace("survey_office60", "bench_survey") +
        ("_no_readout" if args.no_readout else "") + ".json")
    if not (args.rec / "frames.csv").exists():
        render(args.rec, args.preset, args.seed)
    real = load_preset(OFFICE / "site.yaml", args.preset) if args.preset else None
    readout = real.rolling_shutter_ms if real is not None else 0.0
    told = 0.0 if args.no_readout else readout
    rec = Recording(args.rec)
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    captured: dict = {}
    real_solve = survey_mod.solve_graph

    def spy(poses0, edges, **kw):
        captured.update(poses0=poses0, edges=edges)
        return real_solve(poses0, edges, **kw)

    survey_mod.solve_graph = spy
    t0, w0 = time.process_time(), time.perf_counter()
    res = survey_drives([rec], rec.rig, rec.site.ceiling_height_m, tuple(truth[0]),
                        SurveyOptions(readout_ms=told))
    cpu, wall = time.process_time() - t0, time.perf_counter() - w0
    survey_mod.solve_graph = real_solve
    rss_survey = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t_true = truth[res.frame]
    yaw = lambda p: math.degrees(float(np.max(np.abs(  # noqa: E731
        (p[:, 2] - t_true[:, 2] + math.pi) % (2 * math.pi) - math.pi))))
    out = {"recording": str(args.rec), "preset": args.preset, "readout_ms": readout,
           "readout_told_ms": told, "frames": len(rec), "driven_m": float(np.sum(np.hypot(
               np.diff(truth[:, 0]), np.diff(truth[:, 1])))), "keyframes": int(len(res.keys)),
           "closures": sum(lk.kind == "loop" for lk in res.links),
           "links": sum(lk.kind == "link" for lk in res.links), "refused": res.refused,
           "unplaced": res.unplaced, "survey_cpu_s": cpu, "survey_wall_s": wall,
           "solve_wall_s": res.solve_s, "solve_iterations": res.iterations,
           "solvers": _solvers(captured, t_true)}
    for key, P in (("chain", res.chain), ("solved", res.poses)):
        pos = np.hypot(*(P[:, :2] - t_true[:, :2]).T)
        per_key = feature_errors(rec, res, P, readout)
        out[key] = {"features": _stats(np.concatenate(per_key)),
                    "poses": {**_stats(pos), "end_mm": 1e3 * float(pos[-1]),
                              "yaw_max_deg": yaw(P)},
                    "per_keyframe": [
                        [int(res.frame[n]), len(e), 1e3 * float(np.sqrt(np.mean(e ** 2)))
                         if len(e) else None]
                        for n, e in zip(res.keys, per_key, strict=True)]}
    t0 = time.process_time()
    out["map"] = map_errors(rec, res, truth)
    out["map"]["cpu_s_both_maps"] = time.process_time() - t0
    out["peak_rss_mb_after_survey"] = rss_survey
    out["peak_rss_mb_after_maps"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))

if __name__ == "__main__":
    main()
