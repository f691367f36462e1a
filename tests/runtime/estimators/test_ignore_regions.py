"""SPEC §2 ``ignore``: regions of the ceiling no method uses. A light, block or marker
there is not in the map the method matches, expects or refines against; a ceiling line
there gives the block method's parallels no chord."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.block.estimator import BlockEstimator
from ceilkit.runtime.estimators.block.parallels import predicted_chords
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, ceiling_points_vehicle
from ceilkit.runtime.estimators.lights.rays import project_lights
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

NOISY = SimOptions(noise_sigma=2.0, blur_px=0.8)


def square(cx: float, cy: float, half: float) -> np.ndarray:
    return np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half],
                     [cx - half, cy + half]])


def test_a_moved_light_in_an_ignore_region_is_not_used():
    """A lamp moved 3 cm since the survey is within the outlier pass's reach: it is
    matched and pulls the pose 6 mm. Marked as an ignore region, it is not used: the
    pose comes from the others, and the diagnostics still name the site's indices."""
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    x, y, yaw = 4.6, 0.3, math.radians(20.0)
    lights = np.array(site.lights_m, float)
    k = int(np.argmin(np.hypot(lights[:, 0] - x, lights[:, 1] - y)))   # the one overhead
    moved = lights.copy()
    moved[k] += (0.03, 0.0)
    truth = dataclasses.replace(site, lights_m=moved)
    img = render_frame(rig, truth, x, y, yaw, NOISY, np.random.default_rng(2))
    plain = make_estimator("lights", rig, site, None).estimate(img, 0)
    marked = dataclasses.replace(site, ignore_m=(square(*lights[k], 0.3),))
    got = make_estimator("lights", rig, marked, None).estimate(img, 0)
    assert plain and got
    assert k in plain.diagnostics["matched_lights"]
    assert k not in got.diagnostics["matched_lights"]
    err_plain = math.hypot(plain.x_m - x, plain.y_m - y)
    err = math.hypot(got.x_m - x, got.y_m - y)
    assert err_plain > 0.004 and err < 0.001
    # the indices are the site's: each matched spot is where the site's light of that
    # index projects from the true pose
    pairs = np.asarray(got.diagnostics["pairs"], int)
    spots = np.asarray(got.diagnostics["spots_px"], float)[pairs[:, 0]]
    px = project_lights(rig, site.ceiling_height_m, lights[pairs[:, 1]], x, y, yaw)
    assert np.max(np.hypot(*(spots - px).T)) < 1.0


def test_a_marker_in_an_ignore_region_is_not_used():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    m1 = site.markers.pose(1)
    marked = dataclasses.replace(site, ignore_m=(square(m1.x_m, m1.y_m, 0.3),))
    used = marked.without_ignored()
    assert [m.id for m in used.markers.poses] == [0, 2, 3]
    assert [b.id for b in used.blocks] == ["A", "B"]
    x, y, yaw = m1.x_m, m1.y_m + 0.1, 0.2                      # marker 1 overhead, alone
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(5))
    prior = PoseEstimate(0, "prior", x, y, yaw, 1.0)
    opts = {"plane_odometry": False}
    seen = BlockEstimator(rig, site, opts).estimate(img, 0, prior)
    assert seen and seen.diagnostics["source"] == "marker:1"
    got = BlockEstimator(rig, marked, opts).estimate(img, 0, prior)
    assert not (got and got.x_m is not None and got.diagnostics.get("source") == "marker:1")


def test_parallels_take_no_chord_inside_an_ignore_region():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    geo = PlanarGeometry.of(rig, site)
    pose = np.array([3.0, 0.0, 0.1])
    every = predicted_chords(geo, site.corridor, pose, 40, site)
    marked = dataclasses.replace(site, ignore_m=(square(3.0, 0.0, 50.0),))   # all of it
    assert len(every) > 4 and len(predicted_chords(geo, site.corridor, pose, 40, marked)) == 0


def test_a_small_region_between_a_chords_samples_drops_that_chord_only():
    """The lines are sampled every 0.5 m for the frame test, but a chord is tested
    against the regions every 0.1 m: a 0.1 m region on a seam a quarter of the way
    along one chord (between its samples) drops that chord and no other."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    geo = PlanarGeometry.of(rig, site)
    pose = np.array([3.0, 0.0, 0.1])
    every = predicted_chords(geo, site.corridor, pose, 1000, site)
    # a chord along x at y = 0.6 m, its start on the ceiling (W)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    q = ceiling_points_vehicle(geo, rig.camera.unproject(every[:, :2]))
    start = pose[:2] + q @ np.array([[c, s], [-s, c]])
    along = np.flatnonzero(np.abs(start[:, 1] - 0.6) < 1e-6)
    assert len(along) >= 1
    k = along[0]
    quarter = start[k] + np.array([0.25, 0.0])
    assert abs(math.remainder(quarter[0], 0.6)) > 0.1       # no across seam in the region
    marked = dataclasses.replace(site, ignore_m=(square(quarter[0], quarter[1], 0.05),))
    left = predicted_chords(geo, site.corridor, pose, 1000, marked)
    assert len(left) == len(every) - 1
    assert not np.any(np.all(np.abs(left - every[k]) < 1e-9, axis=1))


def test_everything_ignored_is_a_one_line_error():
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    marked = dataclasses.replace(site, ignore_m=(square(0.0, 0.0, 100.0),))
    for method in ("lights", "paper-lights"):
        with pytest.raises(ConfigError) as e:
            make_estimator(method, rig, marked, None)
        assert "ignore" in str(e.value) and "\n" not in str(e.value)
    brig = Rig.load(CONFIGS / "block" / "rig.yaml")
    bsite = Site.load(CONFIGS / "block" / "site.yaml")
    with pytest.raises(ConfigError) as e:
        BlockEstimator(brig, dataclasses.replace(bsite, ignore_m=(square(0.0, 0.0, 100.0),)))
    assert "ignore" in str(e.value) and "\n" not in str(e.value)


def test_spots_inside_an_ignore_region_are_dropped_with_a_prior():
    """With a prior placing the frame on the ceiling, a spot inside an ignore region (a
    reflection, a skylight) is not used; without one nothing can be placed."""
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    x, y, yaw = 4.6, 0.3, math.radians(20.0)
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(2))
    est = make_estimator("lights", rig, site, None)
    obs = est.observer.observe(img)
    lights = np.array(site.lights_m, float)
    k = int(np.argmin(np.hypot(lights[:, 0] - x, lights[:, 1] - y)))
    marked = dataclasses.replace(site, ignore_m=(square(*lights[k], 0.3),))
    prior = PoseEstimate(0, "prior", x, y, yaw, 1.0)
    out = obs.outside(marked, prior)
    assert len(out.spots) == len(obs.spots) - 1
    assert sorted(out.order.tolist()) == list(range(len(out.spots)))
    # the dropped one is the spot nearest that light's pixel
    px = project_lights(rig, site.ceiling_height_m, lights[k:k + 1], x, y, yaw)[0]
    d = np.hypot(*(obs.spots.centroids_px - px).T)
    assert not np.any(np.all(np.isclose(out.spots.centroids_px, obs.spots.centroids_px[
        np.argmin(d)]), axis=1))
    assert obs.outside(marked, None) is obs and obs.outside(site, prior) is obs


@pytest.mark.parametrize("track", [False, True])
def test_corridor_lines_inside_an_ignore_region_are_not_used(track):
    """With a prior placing the frame (x known: a fused track, a start pose), segments
    and chords inside an ignore region are not used; a region elsewhere changes
    nothing; a prior without x places nothing."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    x, y, yaw = 6.0, 0.05, math.radians(3.0)
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(3))
    opts = {"window_search": track}
    prior = PoseEstimate(0, "prior", x, y, yaw, 1.0)
    plain = make_estimator("corridor", rig, site, opts).estimate(img, 0, prior)
    assert plain and abs(plain.y_m - y) < 0.002

    def run(region, p):
        s = dataclasses.replace(site, ignore_m=(region,))
        return make_estimator("corridor", rig, s, opts).estimate(img, 0, p)

    far = run(square(x + 200.0, 0.0, 1.0), prior)
    assert far and far.y_m == plain.y_m and far.yaw_rad == plain.yaw_rad
    everywhere = run(square(x, y, 100.0), prior)
    assert not everywhere                                       # nothing left to use
    no_x = PoseEstimate(0, "prior", None, y, yaw, 1.0)
    assert run(square(x, y, 100.0), no_x)                      # nothing placed


def test_corridor_keeps_the_lines_outside_a_partial_ignore_region():
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    x, y, yaw = 6.0, 0.05, math.radians(3.0)
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(3))
    prior = PoseEstimate(0, "prior", x, y, yaw, 1.0)
    left = np.array([[-50.0, 0.3], [50.0, 0.3], [50.0, 5.0], [-50.0, 5.0]])  # y > 0.3
    s = dataclasses.replace(site, ignore_m=(left,))
    got = make_estimator("corridor", rig, s, None).estimate(img, 0, prior)
    plain = make_estimator("corridor", rig, site, None).estimate(img, 0, prior)
    assert got and abs(got.y_m - y) < 0.001 and abs(math.degrees(got.yaw_rad - yaw)) < 0.01
    assert got.diagnostics["n_segments"] < plain.diagnostics["n_segments"]


def test_the_block_parallels_take_no_detected_segment_inside_a_region():
    """With a pose, the parallels' chords inside a region are not predicted; when none
    is left the frame's detected segments stand in, and those inside the region are
    dropped too (a region over the whole view: no heading from it)."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    x, y, yaw = 3.0, 0.0, 0.1
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(1))
    pose = np.array([x, y, yaw])
    plain = BlockEstimator(rig, site, {"plane_odometry": False})
    assert plain._heading(img, yaw, pose) is not None
    marked = dataclasses.replace(site, ignore_m=(square(x, y, 30.0),), blocks=(), markers=None)
    with pytest.raises(ConfigError):          # nothing left for the block method at all
        BlockEstimator(rig, marked)
    over_view = dataclasses.replace(site, ignore_m=(square(x, y, 4.0),))   # marker 3 left
    est = BlockEstimator(rig, over_view, {"plane_odometry": False})
    assert est._heading(img, yaw, pose) is None
    assert est._heading(img, yaw, None) is not None          # no pose: nothing placed


def test_a_site_with_two_lights_and_no_region_still_builds_paper_lights():
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    two = dataclasses.replace(site, lights_m=np.asarray(site.lights_m)[:2])
    est = make_estimator("paper-lights", rig, two, None)
    assert est.name == "paper-lights"
    np.testing.assert_array_equal(est.lights_w, two.lights_m)   # both used: no region
    assert est.pair_i.tolist() == [0] and est.pair_j.tolist() == [1]
