"""`ceilcal survey`'s library: a simulated office loop surveyed with no external poses
lands within its target after loop closure; the closure is what gets it there."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ceilkit.calib.simulate import simulate_recording
from ceilkit.calib.survey import SurveyOptions, survey_drives, survey_map
from ceilkit.calib.survey_loop import loop_trajectory
from ceilkit.calib.survey_places import place_of
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry.ceiling import vehicle_to_world
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions
from ceilkit.runtime.sim.scatter_file import scene_beside
from helpers import CONFIGS


@pytest.fixture(scope="module")
def office_loop(tmp_path_factory):
    """A 12.6 m loop under the office scatter (3.6 x 2.4 m, 1.15 laps, a frame every
    0.1 m; noise 2, blur 0.8; supersample 1 to keep it fast) and its survey."""
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    site = Site.load(CONFIGS / "office" / "site.yaml")
    traj = loop_trajectory(3.6, 2.4, laps=1.15, fps=5.0, speed_mps=0.5, centre_m=(4.0, 0.0))
    out = tmp_path_factory.mktemp("survey") / "loop"
    simulate_recording(rig, site, traj, out, SimOptions(noise_sigma=2.0, blur_px=0.8,
                                                        supersample=1,
                                                        scatter=scene_beside(site)), seed=1)
    rec = Recording(out)
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    res = survey_drives([rec], rec.rig, site.ceiling_height_m, tuple(truth[0]))
    return rec, truth, res


def feature_errors(rec: Recording, res, truth: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Every keyframe's ceiling features placed by ``poses`` against by the truth, m."""
    out = []
    for n in res.keys:
        k = int(res.frame[n])
        q = place_of(to_grey(rec.frame(k).image), rec.rig, res.ceiling_height_m).points_v
        a = vehicle_to_world(q, *poses[n])
        b = vehicle_to_world(q, *truth[k])
        out.append(np.hypot(*(a - b).T))
    return np.concatenate(out)


def test_office_loop_features_within_target(office_loop):
    rec, truth, res = office_loop
    assert res.unplaced == 0 and len(res.poses) == len(rec)
    err = feature_errors(rec, res, truth, res.poses)
    rms = float(np.sqrt(np.mean(err ** 2)))
    # issue 39: 1 cm RMS on a 60 m drive; this loop is 12.6 m: 2.5 mm (measured 0.8)
    assert rms < 0.0025, rms
    pos = np.hypot(*(res.poses[:, :2] - truth[res.frame, :2]).T)
    assert float(np.sqrt(np.mean(pos ** 2))) < 0.0025
    yaw = np.abs((res.poses[:, 2] - truth[res.frame, 2] + math.pi) % (2 * math.pi) - math.pi)
    assert math.degrees(float(yaw.max())) < 0.2


def test_loop_closure_reduces_the_error(office_loop):
    rec, truth, res = office_loop
    assert sum(lk.kind == "loop" for lk in res.links) >= 5
    chain = np.hypot(*(res.chain[:, :2] - truth[res.frame, :2]).T)
    solved = np.hypot(*(res.poses[:, :2] - truth[res.frame, :2]).T)
    # the chain alone drifts: measured at most 2.72 mm, RMS 1.72 mm (its end 0.97 mm: a
    # drift can come back near the start, so the end alone says little; 24 mm at the end
    # before the odometry's turns were tracked on the frame turned back,
    # odometry.TURN_WARP_MIN_RAD); the closures take them to 0.86 and 0.48 mm (3.2x and
    # 3.6x: near the place matches' own error)
    assert chain.max() > 0.001
    assert solved.max() < chain.max() / 2
    assert np.sqrt(np.mean(solved ** 2)) < np.sqrt(np.mean(chain ** 2)) / 2


def test_sigmas_cover_the_errors(office_loop):
    rec, truth, res = office_loop
    k = res.keys[1:]                                   # the anchor's sigma is 0
    err = res.poses[k, :2] - truth[res.frame[k], :2]
    z = np.abs(err) / res.sigma[k, :2]
    assert np.all(np.isfinite(res.sigma[k]))
    assert np.median(z) < 3.0, np.median(z)
    # the 2-D distance over its 1σ: the law's 95th percentile is 2.45. With the graph's
    # own 1σ this loop gave 3.58 (it set POSE_SIGMA_FACTOR, with bench_survey.py
    # --against-known --seeds' 2.0-3.3); with the factor, 2.4. Since the odometry's
    # VAR_FACTOR (1.0, 1.8, 3.5) (2026-12-07): 2.74 and 1.83, median 1.26 (the factor
    # re-measured on nine surveys: POSE_SIGMA_FACTOR's docstring, docs/survey.md)
    d = np.hypot(*z.T)
    print(f"keyframes' error / 1σ (2-D): median {np.median(d):.2f}, "
          f"95th percentile {np.percentile(d, 95):.2f}")
    assert np.percentile(d, 95) < 2.6, np.percentile(d, 95)


def test_map_from_the_survey(office_loop):
    rec, truth, res = office_loop
    cmap = survey_map(res, [rec], rec.rig)
    assert len(cmap.points_xy) > 200 and cmap.anchor == "start pose"
    x0, y0, x1, y1 = cmap.extent_xy
    assert x0 < truth[:, 0].min() and x1 > truth[:, 0].max()
    # the keyframes' 1σ go with the map: a pose on it carries the error they share
    assert np.array_equal(cmap.keyframe_sigma, res.sigma[res.keys])
    assert np.all(cmap.keyframe_sigma[1:, :2] > 0)


def test_no_recording_is_refused():
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    with pytest.raises(ConfigError, match="at least one recording"):
        survey_drives([], rig, 2.7)


def test_options_are_frozen():
    with pytest.raises(AttributeError):
        SurveyOptions().key_step_m = 1.0       # type: ignore[misc]


def test_two_drives_merge_into_one_map(office_loop, tmp_path):
    """A second drive (straight along the loop's first side, y = -1.2, 2 m) shares no
    chain with the loop: it is placed by the places the two drives share."""
    rec, truth, _ = office_loop
    site = Site.load(CONFIGS / "office" / "site.yaml")
    from ceilkit.runtime.sim.render import straight_drive
    traj = straight_drive(20, fps=5.0, speed_mps=0.5, x0_m=3.3, y_m=-1.1)
    out = tmp_path / "second"
    simulate_recording(rec.rig, site, traj, out, SimOptions(noise_sigma=2.0, blur_px=0.8,
                                                           supersample=1,
                                                           scatter=scene_beside(site)), seed=2)
    second = Recording(out)
    res = survey_drives([rec, second], rec.rig, site.ceiling_height_m, tuple(truth[0]))
    assert res.unplaced == 0 and sum(lk.kind == "drives" for lk in res.links) >= 3
    two = res.drive == 1
    t2 = np.c_[second.truth.x_m, second.truth.y_m][res.frame[two]]
    err = np.hypot(*(res.poses[two, :2] - t2).T)
    assert err.max() < 0.003, err.max()
    # one map: the merged survey's features where the loop alone mapped them, within
    # their 1σ (both maps' per axis, combined)
    # (a feature's first row, its medoid descriptor, stands for it: build_map)
    one, both = (_first_rows(survey_map(r, recs, rec.rig))
                 for r, recs in ((office_loop[2], [rec]), (res, [rec, second])))
    d, j = cKDTree(one.points_xy).query(both.points_xy, distance_upper_bound=0.02)
    ok = np.isfinite(d)
    bits = np.unpackbits(both.descriptors[ok] ^ one.descriptors[j[ok]], axis=1).sum(1)
    same = np.flatnonzero(ok)[bits <= 40]
    assert len(same) > 0.8 * len(one.points_xy), (len(same), len(one.points_xy))
    z = d[same] / np.hypot(both.sigma_m[same], one.sigma_m[j[same]])
    print(f"merged map: {len(same)} of {len(one.points_xy)} features matched; "
          f"|d|/sigma median {np.median(z):.2f}, 95th pct {np.percentile(z, 95):.2f}")
    # measured: 672 of 744 matched, median 0.06, 95th percentile 0.24
    assert np.median(z) < 0.5 and np.percentile(z, 95) < 1.0, np.percentile(z, 95)


def _first_rows(cmap):
    """The map with one row a feature (its first: the medoid descriptor)."""
    import dataclasses

    from ceilkit.runtime.estimators.texture.match import places
    a = np.unique(places(cmap.points_xy)[0])
    return dataclasses.replace(cmap, points_xy=cmap.points_xy[a],
                               descriptors=cmap.descriptors[a], sigma_m=cmap.sigma_m[a])


def test_plain_tiles_are_refused(tmp_path):
    """A plain tile grid (1.2 x 0.6 m tiles, no scatter, no texture; 15 frames 0.1 m
    apart): no two keyframes single out a place, so nothing checks the chain (on a
    40 m loop of such tiles the chain ended 1.9 m and 47.5 deg off under a stated 1σ of
    0.26 m, issue 39) and the survey refuses in one line rather than write its map."""
    from ceilkit.runtime.config.site import AcrossLines, Corridor
    from ceilkit.runtime.errors import CalibrationError
    from ceilkit.runtime.sim.render import straight_drive
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    site = Site(2.7, corridor=Corridor(tuple(round(1.2 * i, 3) for i in range(-5, 6)),
                                       AcrossLines(0.0, 0.6)))
    traj = straight_drive(15, fps=5.0, speed_mps=0.5, x0_m=0.1, y_m=0.2)
    out = simulate_recording(rig, site, traj, tmp_path / "plain", SimOptions(
        noise_sigma=2.0, blur_px=0.8, supersample=1, texture=0.0), seed=1)
    rec = Recording(out)
    with pytest.raises(CalibrationError, match="no two keyframes matched as places") as e:
        survey_drives([rec], rig, 2.7, (0.1, 0.2, 0.0))
    assert "\n" not in str(e.value) and str(out) in str(e.value)


def test_a_survey_with_no_loop_says_its_sigma_is_unverified(office_loop):
    """With a loop closed the survey says nothing more; with its links alone (the
    closures taken out) it says in one line that its 1σ is unchecked."""
    import dataclasses
    res = office_loop[2]
    assert res.unchecked == ""
    links = tuple(lk for lk in res.links if lk.kind == "link")
    open_ = dataclasses.replace(res, links=links)
    assert open_.unchecked.startswith("no loop closed") and "\n" not in open_.unchecked



def test_a_rival_a_step_away_makes_the_match_ambiguous():
    """40 points that stay put (a seam along the travel: a standstill) and 30 that
    moved 4 cm (the true step): the rival is 4 cm from the winner, a distinct motion
    (past twice the inlier radius), so the pair is ambiguous. With rivals counted only
    5 cm away the standstill was accepted (issue 39: a survey bridge 50 mm off)."""
    from ceilkit.calib.survey_places import Place, match_places
    rng = np.random.default_rng(3)
    still, moved = rng.uniform(-0.5, 0.5, (40, 2)), rng.uniform(-0.5, 0.5, (30, 2))
    d_still = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    d_moved = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    a = Place(np.r_[still, moved], np.r_[d_still, d_moved])
    b = Place(np.r_[still, moved - [0.04, 0.0]], np.r_[d_still, d_moved])
    m = match_places(a, b, np.random.default_rng(0))
    assert not m and m.reason == "ambiguous" and (m.inliers, m.runner_up) == (40, 30)
    # the true step alone is accepted
    m = match_places(Place(moved, d_moved), Place(moved - [0.04, 0.0], d_moved),
                     np.random.default_rng(0))
    assert m and abs(m.z[0] - 0.04) < 1e-6


def test_lights_that_repeat_are_not_written_from_a_drive_not_all_placed():
    """A lattice of lights (a detector on every 0.6 m tile) surveyed from part of a drive
    (frames left unplaced): a pose matched to them has twins a period on, where the
    lights were not placed, so they are left out with the reason; from a drive placed
    whole, or where the lights do not repeat, they are written."""
    from ceilkit.calib.survey_files import _repeated_beyond

    gx, gy = np.meshgrid(np.arange(5) * 0.6, np.arange(4) * 0.6)
    lattice = np.c_[gx.ravel(), gy.ravel()] + 0.3
    why = _repeated_beyond(lattice, unplaced=120)
    assert "20 lights left out" in why and "120 frames" in why, why
    assert _repeated_beyond(lattice, unplaced=0) == ""
    scatter = np.random.default_rng(3).uniform(0, 3.0, (12, 2))
    assert _repeated_beyond(scatter, unplaced=120) == ""


def test_a_lattice_of_more_lights_than_the_runtime_searches_is_also_left_out():
    """The rule searches every light, also past the runtime's SYMMETRY_MAX_LIGHTS (a
    20 x 20 lattice, 400 lights: written before, seed 4's repeated control held 364)."""
    from ceilkit.calib.survey_files import _repeated_beyond
    from ceilkit.runtime.estimators.lights.matching import SYMMETRY_MAX_LIGHTS

    gx, gy = np.meshgrid(np.arange(20) * 0.6, np.arange(20) * 0.6)
    lattice = np.c_[gx.ravel(), gy.ravel()] + 0.3
    assert len(lattice) > SYMMETRY_MAX_LIGHTS
    assert "400 lights left out" in _repeated_beyond(lattice, unplaced=5)
    scatter = np.random.default_rng(4).uniform(0, 12.0, (400, 2))
    assert _repeated_beyond(scatter, unplaced=5) == ""
