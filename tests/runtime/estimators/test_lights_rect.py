"""The lights method under rectangular lamps in a regular grid (SPEC §2 ``light_size``,
``light_yaw``): the simulator draws them, the observer checks a spot against the lamp's
projected rectangle (a 170° fisheye tilted 22° from vertical, frames thresholded to
0/255), a prior holds the track through the grid without slipping a cell, and with no
prior no valid pose is wrong (a grid's cells and half turns are ``ambiguous``)."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import Node
from ceilkit.runtime.estimators.base import AMBIGUOUS, PoseEstimate, Provenance
from ceilkit.runtime.estimators.lights import LightsEstimator, project_lights
from ceilkit.runtime.estimators.lights import observe as observe_module
from ceilkit.runtime.estimators.lights.observe import two_level
from ceilkit.runtime.estimators.lights.refine import refine_pose_ceiling, with_shifts
from ceilkit.runtime.features.spots import SpotParams, detect_spots
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.tracking import Tracker

PITCH = (3.05, 3.66)       # the grid's cells, m
LAMP = (1.2, 0.47)         # length, width, m
GRID = (6, 5)              # lamps along x, y
OFF = ((2, 1), (4, 3))     # lamps of the map that are off in the frames
CLUTTER = ((1.5, 1.8), (7.6, 9.1), (12.0, 4.0))   # lamps not in the map
THRESHOLD = 200            # the frames are stored thresholded to 0/255 at this grey
FPS = 30.0
STEP = 5                   # every 5th frame of a 30 fps drive
N_FRAMES = 24


def fisheye_rig() -> Rig:
    """640x480, a 170° equidistant fisheye tilted 22° from vertical (mount tilt 68°),
    the lamps 2.5 m above the lens."""
    cam = CameraModel.pinhole(640, 480, 205.0, dist=[0.02, -0.005, 0.0, 0.0],
                              model="equidistant")
    return Rig(cam, Mount(tilt_rad=math.radians(68.0), x_m=0.1, z_m=0.3))


def grid_site(missing=(), extra=(), light_yaw_deg: float = 90.0) -> Site:
    pts = [[i * PITCH[0], j * PITCH[1]] for i in range(GRID[0]) for j in range(GRID[1])
           if (i, j) not in missing] + [list(p) for p in extra]
    return Site.from_node(Node({"ceiling_height": 2.8, "lights": pts,
                                "light_size": list(LAMP), "light_yaw": light_yaw_deg},
                               None, ""))


def thresholded(rig: Rig, site: Site, x: float, y: float, yaw: float, seed: int) -> np.ndarray:
    img = render_frame(rig, site, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=0.8),
                       np.random.default_rng(seed))
    return np.where(img > THRESHOLD, 255, 0).astype(np.uint8)


def drive_poses() -> list[tuple[float, float, float, float]]:
    """``(t_s, x, y, yaw)`` of every STEP-th frame of a 30 fps drive at 0.8 m/s turning
    at 0.35 rad/s: 3.2 m across a cell boundary of the grid."""
    out, x, y, yaw = [], 2.0, 4.0, 0.3
    for k in range(N_FRAMES * STEP):
        if k % STEP == 0:
            out.append((k / FPS, x, y, yaw))
        yaw += 0.35 / FPS
        x += 0.8 / FPS * math.cos(yaw)
        y += 0.8 / FPS * math.sin(yaw)
    return out


def errors(est: PoseEstimate, x: float, y: float, yaw: float) -> tuple[float, float]:
    return (math.hypot(est.x_m - x, est.y_m - y),
            abs(math.degrees(math.remainder(est.yaw_rad - yaw, 2 * math.pi))))


@pytest.fixture(scope="module")
def scene():
    rig = fisheye_rig()
    shown = grid_site(missing=OFF, extra=CLUTTER)
    poses = drive_poses()
    frames = [thresholded(rig, shown, x, y, yaw, 10 + k)
              for k, (_, x, y, yaw) in enumerate(poses)]
    est = LightsEstimator(rig, grid_site())
    return rig, est, poses, frames


def check_tracked(results, poses):
    posed = [(e, p) for e, p in zip(results, poses, strict=True) if isinstance(e, PoseEstimate)]
    assert len(posed) >= math.ceil(0.95 * len(poses)), [getattr(e, "reason", "") for e in results]
    errs = np.array([errors(e, *p[1:]) for e, p in posed])
    assert np.median(errs[:, 0]) <= 0.05
    assert errs[:, 0].max() <= 0.10 and errs[:, 1].max() <= 2.0, errs.max(axis=0)
    for e, _ in posed:
        assert e.provenance is Provenance.PRIOR
        if e.hypotheses:   # the twins the prior ruled out, after the published pose
            assert (e.hypotheses[0].x_m, e.hypotheses[0].y_m) == (e.x_m, e.y_m)
            assert sum(h.weight for h in e.hypotheses) == pytest.approx(1.0)
            assert all(math.hypot(h.x_m - e.x_m, h.y_m - e.y_m) > 1.0
                       or abs(math.remainder(h.yaw_rad - e.yaw_rad, 2 * math.pi)) > 0.5
                       for h in e.hypotheses[1:])
    return errs


def test_simulator_draws_a_lit_rectangle():
    """Straight up, pinhole: the lit area is the lamp's projected rectangle, its long
    side along light_yaw."""
    cam = CameraModel.pinhole(320, 240, 200.0)
    rig = Rig(cam, Mount(tilt_rad=math.pi / 2, z_m=0.5))
    site = Site.from_node(Node({"ceiling_height": 3.0, "lights": [[0.0, 0.0]],
                                "light_size": [1.0, 0.4], "light_yaw": 30.0}, None, ""))
    img = render_frame(rig, site, 0.0, 0.0, 0.0,
                       SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, halo=0.0))
    lit = img > 200
    corners = project_lights(rig, 3.0, site.light_rectangles()[0], 0.0, 0.0, 0.0)
    assert lit.sum() == pytest.approx(cv2.contourArea(corners.astype(np.float32)), rel=0.05)
    m = cv2.moments(lit.astype(np.uint8), True)
    angle = 0.5 * math.degrees(math.atan2(2 * m["mu11"], m["mu20"] - m["mu02"]))
    long_px = corners[1] - corners[0]
    want = math.degrees(math.atan2(long_px[1], long_px[0]))
    assert abs(math.remainder(angle - want, 180.0)) < 1.0
    # the halo (the disc's logic about the long axis) brightens the ceiling beside it
    glow = render_frame(rig, site, 0.0, 0.0, 0.0,
                        SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0))
    assert glow[~lit].max() > img[~lit].max() + 10


def test_a_binary_frame_gives_whole_regions():
    """A lamp larger than the Niblack window in a 0/255 frame is one region, not a
    ring of fragments (the threshold never exceeds 254)."""
    img = np.zeros((240, 320), np.uint8)
    img[100:140, 100:200] = 255
    spots = detect_spots(img, SpotParams(min_axis_ratio=0.0))
    assert len(spots) == 1
    assert spots.areas_px[0] == 4000
    np.testing.assert_allclose(spots.centroids_px[0], [149.5, 119.5], atol=1e-9)


def test_observer_finds_the_lamps_centres(scene):
    """Each kept spot's ceiling point is a lamp's centre (of the map, or one of the
    extra lamps) seen from the true pose: the projected rectangle's centroid offset
    taken off, lamps cut by the frame's or the lens's edge left out."""
    rig, est, poses, frames = scene
    for k in (0, 12):
        _, x, y, yaw = poses[k]
        obs = est.observer.observe(frames[k])
        assert len(obs.spots) >= 6
        c, s = math.cos(yaw), math.sin(yaw)
        world = np.array([x, y]) + obs.q_v @ np.array([[c, s], [-s, c]])
        lamps = np.vstack([est.lights_w, np.array(CLUTTER)])
        d = np.linalg.norm(world[:, None] - lamps[None], axis=2).min(axis=1)
        assert d.max() < 0.03, d
        assert obs.weak is not None and obs.weak.shape == (len(obs.spots),)
        assert obs.axis_v is not None


def test_tracked_from_the_previous_pose_perturbed(scene):
    """A prior 2 cm / 1° off the previous frame's true pose: every frame tracked."""
    rig, est, poses, frames = scene
    rng = np.random.default_rng(7)
    results = []
    for k, img in enumerate(frames):
        _, x, y, yaw = poses[max(k - 1, 0)]
        prior = PoseEstimate(0, "truth", x + rng.normal(0, 0.02), y + rng.normal(0, 0.02),
                             yaw + math.radians(rng.normal(0, 1.0)), 1.0)
        results.append(est.estimate(img, int(poses[k][0] * 1e9), prior))
    check_tracked(results, poses)


def test_tracked_behind_the_tracker_from_the_first_pose(scene):
    rig, est, poses, frames = scene
    tracker = Tracker()
    tracker.set_start_pose(0, *poses[0][1:])
    results = []
    for k, ((t, *_), img) in enumerate(zip(poses, frames, strict=True)):
        t_ns = int(t * 1e9)
        e = est.estimate(img, t_ns, tracker.predict(t_ns))
        # the start pose is published as a reset on its first frame, then no slip
        assert tracker.update(e).relocalized == (k == 0)
        results.append(e)
    check_tracked(results, poses)


def test_no_prior_no_wrong_valid_pose(scene):
    """With no prior a grid frame is ambiguous (another cell, a half turn explains the
    spots as well); whatever is published is right, and an ambiguous failure carries
    its hypotheses (weights summing to 1)."""
    rig, est, poses, frames = scene
    ambiguous = 0
    for (t, x, y, yaw), img in zip(poses, frames, strict=True):
        e = est.estimate(img, int(t * 1e9), None)
        if isinstance(e, PoseEstimate):
            d, dyaw = errors(e, x, y, yaw)
            assert d <= 0.10 and dyaw <= 2.0, (d, dyaw)
            continue
        if e.reason == AMBIGUOUS:
            ambiguous += 1
            assert len(e.hypotheses) >= 2
            assert sum(h.weight for h in e.hypotheses) == pytest.approx(1.0)
            assert all(h.cov is None or h.cov.shape == (3, 3) for h in e.hypotheses)
    assert ambiguous >= len(poses) // 2


def test_a_prior_one_cell_off_decides_only_as_a_prior(scene):
    """A prior exactly one cell off puts every spot on a lamp too. Where the frame
    prefers the true cell (lights the shifted pose should see are not there) the prior
    is contradicted and not followed; where the frame cannot tell, the prior decides,
    and says so: ``PRIOR`` provenance, the true pose among the twins it ruled out
    (what a multi-hypothesis fusion needs to recover)."""
    rig, est, poses, frames = scene
    for k in (0, 8, 16):
        t, x, y, yaw = poses[k]
        for dx, dy in ((PITCH[0], 0.0), (0.0, -PITCH[1])):
            e = est.estimate(frames[k], int(t * 1e9),
                             PoseEstimate(0, "wrong", x + dx, y + dy, yaw, 1.0))
            if not isinstance(e, PoseEstimate):
                continue
            d, dyaw = errors(e, x, y, yaw)
            if d <= 0.10 and dyaw <= 2.0:
                continue
            assert e.provenance is Provenance.PRIOR and not e.singled_out
            assert min(math.hypot(h.x_m - x, h.y_m - y) for h in e.hypotheses[1:]) < 0.10


def test_edge_lamps_alone_are_no_fix(scene):
    """Only lamps near the lens's edge in view (the others off): no valid pose
    without a prior, however they match."""
    rig, est, poses, frames = scene
    _, x, y, yaw = poses[6]
    site = grid_site()
    px = project_lights(rig, site.ceiling_height_m, site.lights_m, x, y, yaw)
    cam = rig.camera
    r = np.hypot(px[:, 0] - cam.cx, px[:, 1] - cam.cy)
    far = np.isfinite(r) & (r > 200)
    assert far.sum() >= 3
    edge = dataclasses.replace(site, lights_m=site.lights_m[far])
    img = thresholded(rig, edge, x, y, yaw, 99)
    e = est.estimate(img, 0, None)
    if isinstance(e, PoseEstimate):
        d, dyaw = errors(e, x, y, yaw)
        assert d <= 0.10 and dyaw <= 2.0


def centre_errors_px(obs, rig: Rig, lamps_w: np.ndarray, x: float, y: float, yaw: float
                     ) -> np.ndarray:
    """Each kept spot's centre error (px): its ceiling point against the nearest lamp's
    true place in V, through the spot's pixel Jacobian."""
    c, s = math.cos(yaw), math.sin(yaw)
    d = lamps_w - np.array([x, y])
    lv = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    near = np.linalg.norm(obs.q_v[:, None] - lv[None], axis=2).argmin(axis=1)
    e = np.einsum("kab,kb->ka", obs.jac_px, obs.q_v - lv[near])
    return np.hypot(e[:, 0], e[:, 1])


def test_two_level_frames_are_told_apart(scene):
    """A 0/255 frame is two-level (its observation carries the principal point); the
    same frame before thresholding is not."""
    rig, est, poses, frames = scene
    _, x, y, yaw = poses[0]
    raw = render_frame(rig, grid_site(OFF, CLUTTER), x, y, yaw,
                       SimOptions(noise_sigma=2.0, blur_px=0.8), np.random.default_rng(10))
    assert two_level(frames[0]) and not two_level(raw)
    np.testing.assert_allclose(est.observer.observe(frames[0]).centre_px,
                               [rig.camera.cx, rig.camera.cy])
    assert est.observer.observe(raw).centre_px is None


def test_the_thresholds_shift_across_the_frame_is_taken_off(scene, monkeypatch):
    """Under the lens's fall-off a fixed threshold trims a lamp's outer edge more than
    its inner one: taking the fitted shift off (``edge_shift_px``) brings the lamps'
    centre errors down; with no fall-off there is nothing to take off."""
    rig, est, poses, frames = scene
    lamps = np.vstack([est.lights_w, np.array(CLUTTER)])
    shown = grid_site(OFF, CLUTTER)
    for vignetting, fewer in ((0.3, True), (0.0, False)):
        with_shift, without = [], []
        for k in range(0, N_FRAMES, 3):
            _, x, y, yaw = poses[k]
            img = render_frame(rig, shown, x, y, yaw,
                               SimOptions(noise_sigma=2.0, blur_px=0.8, vignetting=vignetting),
                               np.random.default_rng(10 + k))
            img = np.where(img > THRESHOLD, 255, 0).astype(np.uint8)
            with_shift.append(centre_errors_px(est.observer.observe(img), rig, lamps, x, y, yaw))
            with monkeypatch.context() as m:
                m.setattr(observe_module, "edge_shift_px", lambda p, *a: np.zeros((len(p), 2)))
                without.append(centre_errors_px(est.observer.observe(img), rig, lamps, x, y, yaw))
        a, b = np.median(np.concatenate(with_shift)), np.median(np.concatenate(without))
        if fewer:
            assert a < 0.8 * b, (a, b)
        else:
            assert a == pytest.approx(b, rel=0.1), (a, b)


def test_a_radial_shift_of_every_centroid_is_fitted_and_in_the_covariance():
    """A linear camera (300 px/m about the principal point) whose centroids all moved
    outwards by 1 %: the three-unknown fit is pulled off, the fit with the radial shift
    finds the pose and a wider covariance than the three-unknown fit of exact points."""
    centre = np.array([320.0, 240.0])
    lights = np.array([[0.5, 0.2], [-0.6, 0.4], [0.3, -0.7], [1.1, 0.9], [-0.8, -0.5]])
    x, y, yaw = 0.2, -0.1, 0.3
    c, s = math.cos(yaw), math.sin(yaw)
    d = lights - np.array([x, y])
    q_true = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    q_obs = 1.01 * q_true
    jac = np.tile(300.0 * np.eye(2), (5, 1, 1))
    px = centre + 300.0 * q_obs
    fit3 = refine_pose_ceiling(q_obs, jac, lights, x + 0.05, y, yaw)
    assert math.hypot(fit3[0] - x, fit3[1] - y) > 1e-3
    fit4 = with_shifts(q_obs, jac, lights, (px - centre)[:, None], fit3)
    assert math.hypot(fit4[0] - x, fit4[1] - y) < 1e-6 and abs(fit4[2] - yaw) < 1e-6
    exact = refine_pose_ceiling(q_true + 1e-4, jac, lights, x, y, yaw)
    widened = with_shifts(q_true + 1e-4, jac, lights, 300.0 * (q_true + 1e-4)[:, None], exact)
    assert np.all(np.diag(widened[3]) >= np.diag(exact[3]) * (1 - 1e-9))
    assert with_shifts(q_obs[:2], jac[:2], lights[:2], (px - centre)[:2, None], fit3) is fit3


def test_a_lamp_larger_than_the_glare_bound_is_kept_whole():
    """A saturated lamp whose own image is over the detector's glare bound
    (``max_area_px``, 6000 px: a 0.93 x 0.46 m lamp 2.5 m above a 334 px pinhole is
    about 7,500 px) went through the glare split and its core was dropped as too large:
    ``no_lights`` on every frame (held-out ``lamps0-2`` of seed 7). The estimator now
    keeps a core up to the lamp's largest image in the view; the halo stays out (the
    region is still split) and each kept spot's ceiling point is a lamp's centre."""
    cam = CameraModel.pinhole(640, 480, 334.0)
    rig = Rig(cam, Mount(tilt_rad=math.pi / 2, x_m=0.1, z_m=0.54))
    lamps = [[i * 1.81, j * 2.45] for i in range(-3, 4) for j in range(-3, 4)]
    site = Site.from_node(Node({"ceiling_height": 3.05, "lights": lamps,
                                "light_size": [0.93, 0.46], "light_yaw": 0.0}, None, ""))
    x, y, yaw = 0.4, 0.3, 0.5
    img = render_frame(rig, site, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=0.8,
                                                        exposure=1.3),
                       np.random.default_rng(3))
    est = LightsEstimator(rig, site)
    params = est.observer.spot_params
    assert params.max_light_px > params.max_area_px
    old = detect_spots(img, dataclasses.replace(params, max_light_px=0))   # the lamps dropped
    assert old.rejected["large"] >= 2 and not np.any(old.areas_px > 1000), old.areas_px
    obs = est.observer.observe(img)
    assert len(obs.spots) >= 2 and obs.spots.areas_px.max() > params.max_area_px
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.array([x, y]) + obs.q_v @ np.array([[c, s], [-s, c]])
    d = np.linalg.norm(world[:, None] - est.lights_w[None], axis=2).min(axis=1)
    assert d.max() < 0.03, d


def thresholded_drive(rig, site, poses, sim, level):
    """``(estimator, poses, frames)``: ``poses`` ``(x, y, yaw_deg)`` rendered under ``sim``
    and stored 0/255 at ``level`` (a camera that thresholds its frames)."""
    frames = []
    for k, (x, y, yaw_deg) in enumerate(poses):
        img = render_frame(rig, site, x, y, math.radians(yaw_deg), sim,
                           np.random.default_rng(k))
        frames.append(np.where(img > level, 255, 0).astype(np.uint8))
    return LightsEstimator(rig, site), poses, frames


@pytest.fixture(scope="module")
def bloomed():
    """Held-out ``lamps1`` of seed 7, rebuilt: a 183 deg fisheye tilted 23 deg under a
    7 x 7 grid of 1.04 x 0.39 m lamps at exposure 1.5 with a 100-level halo, frames
    thresholded at 246: the lamps near the axis bloom into ovals no rectangle fits and
    only slivers at the rim are kept."""
    cam = CameraModel.pinhole(640, 480, 188.28, dist=[0.02, -0.005, 0.0, 0.0],
                              model="equidistant")
    rig = Rig(cam, Mount(tilt_rad=math.radians(66.956), x_m=0.1, z_m=0.247))
    lamps = [[i * 3.97, j * 3.47] for i in range(-3, 4) for j in range(-3, 4)]
    site = Site.from_node(Node({"ceiling_height": 3.646, "lights": lamps,
                                "light_size": [1.037, 0.387], "light_yaw": 54.06}, None, ""))
    poses = [(-1.197, -0.115, -203.15), (-1.32, -0.057, -206.6), (-0.6, -0.23, -176.0)]
    return thresholded_drive(rig, site, poses, SimOptions(exposure=1.5, halo=100.0), 246)


def test_bloomed_lamps_are_there_not_missing(bloomed):
    """A map light a pose shows where the frame has a region the observer did not keep
    (a bloomed lamp) is not missing (``TwinJudge.present``). Counted missing, every pose
    inside the grid lost a dozen lights and one at the map's edge three cells away lost
    few: the true pose was never listed (``outside_site`` on two of these frames; in the
    held-out drive a complete list of four poses 12-15 m off, which ``auto`` published).
    Now the truth is among the hypotheses of every frame and no pose is singled out.
    Nor is a pose published from a prior at the truth: it shows more lights that are
    there unmeasured than it measures, and the few slivers it measures carry the same
    bloom (``misfit``; in the held-out drive they carried a prior 10-14 cm off)."""
    est, poses, frames = bloomed
    for (x, y, yaw_deg), img in zip(poses, frames, strict=True):
        e = est.estimate(img, 0, None)
        assert e.reason == AMBIGUOUS, getattr(e, "detail", e)
        near = min(math.hypot(h.x_m - x, h.y_m - y) + abs(math.remainder(
            h.yaw_rad - math.radians(yaw_deg), 2 * math.pi)) for h in e.hypotheses)
        assert near < 0.05, near
        prior = PoseEstimate(0, "truth", x, y, math.radians(yaw_deg), 1.0)
        got = est.estimate(img, 0, prior)
        assert not isinstance(got, PoseEstimate) or errors(
            got, x, y, math.radians(yaw_deg))[0] < 0.1, got


@pytest.fixture(scope="module")
def rim_lamps():
    """Held-out ``lamps1`` of seed 13, rebuilt: a 155 deg fisheye tilted 24 deg under a
    3.19 x 3.16 m grid of 0.61 x 0.37 m lamps at exposure 1.42 with a 60-level halo,
    frames thresholded at 228: a dozen lamps kept a frame, and half a dozen at the rim
    the checks do not keep (cut, or imaged too small for their place)."""
    cam = CameraModel.pinhole(640, 480, 222.2526, dist=[0.02, -0.005, 0.0, 0.0],
                              model="equidistant")
    rig = Rig(cam, Mount(tilt_rad=math.radians(65.697), x_m=0.1, z_m=0.455))
    lamps = [[-2.6308 + i * 3.18523, -1.4169 + j * 3.16183]
             for i in range(-4, 5) for j in range(-4, 5)]
    site = Site.from_node(Node({"ceiling_height": 3.705, "lights": lamps,
                                "light_size": [0.613, 0.371], "light_yaw": 90.0}, None, ""))
    poses = [(-0.746, -0.9013, -128.12), (-0.9513, -1.1652, -127.545),
             (-1.053, -1.2978, -127.324)]
    return thresholded_drive(rig, site, poses, SimOptions(exposure=1.422, halo=59.58), 228)


def test_a_prior_is_not_refused_for_lamps_the_checks_did_not_keep(rim_lamps):
    """The association about a prior is trusted when it measures most spots and the
    lights it shows where the frame is dark are few; lamps it shows where the frame has
    a region the checks did not keep are there, not missing, as its twins are scored
    (``TwinJudge.present``), so long as it measures at least as many (``unmeasured``'s
    rule). Counted missing (12 of 12 spots matched, 6-7 rim lamps unkept: 7-8 "missing"
    against a bound of 6), the prior was refused on every frame of the held-out drive, and
    the track was lost to the global search's twins after 15 frames (15 of 100 poses)."""
    est, poses, frames = rim_lamps
    for (x, y, yaw_deg), img in zip(poses, frames, strict=True):
        prior = PoseEstimate(0, "truth", x, y, math.radians(yaw_deg), 1.0,
                             cov=np.diag([1e-4, 1e-4, math.radians(0.5) ** 2]))
        got = est.estimate(img, 0, prior)
        assert isinstance(got, PoseEstimate), getattr(got, "detail", got)
        assert got.diagnostics["mode"] == "about_prior", got.diagnostics["mode"]
        assert errors(got, x, y, math.radians(yaw_deg))[0] < 0.02, got


def test_a_bloom_outline_covers_steiner_s_area():
    """A ``L x W`` rectangle dilated by ``s`` covers ``LW + 2 (L + W) s + pi s²``: the
    outline's rounded corners sampled, within their chords' shortfall."""
    from ceilkit.runtime.estimators.lights.observe import bloom_outline, polygon_moments

    base, out = bloom_outline(1.2, 0.4)
    for s in (0.0, 0.1, 0.5):
        area = polygon_moments((base + s * out)[None])[0][0]
        steiner = 1.2 * 0.4 + 2 * 1.6 * s + math.pi * s * s
        assert area == pytest.approx(steiner, rel=0.01), s
        assert area <= steiner + 1e-12


@pytest.fixture(scope="module")
def bloomed_fisheye():
    """Held-out ``lamps0`` of seed 13, rebuilt: a 171 deg fisheye tilted 11 deg under a
    3.33 x 2.47 m grid of 1.11 x 0.31 m lamps at exposure 1.4 with a 100-level halo,
    frames thresholded at 226: every lamp blooms into a region two to four times its
    rectangle (a dozen whole in view), which no rectangle fits."""
    cam = CameraModel.pinhole(640, 480, 201.4673, dist=[0.02, -0.005, 0.0, 0.0],
                              model="equidistant")
    rig = Rig(cam, Mount(tilt_rad=math.radians(78.85), x_m=0.1, z_m=0.246))
    lamps = [[-11.0399 + i * 3.33466, -8.8812 + j * 2.46797]
             for i in range(7) for j in range(9)]
    site = Site.from_node(Node({"ceiling_height": 3.657, "lights": lamps,
                                "light_size": [1.112, 0.311], "light_yaw": 0.0}, None, ""))
    poses = [(0.0, 0.0, -144.91), (-0.6546, -0.6121, -128.51), (-1.1223, -1.3775, -114.57)]
    sim = SimOptions(exposure=1.4, halo=100.0, noise_sigma=2.0, blur_px=0.8)
    return thresholded_drive(rig, site, poses, sim, 226)


def test_bloomed_lamps_are_measured_as_their_rectangles_dilated(bloomed_fisheye):
    """Issue 36 (a fisheye drive under rectangular lamps, thresholded frames): each
    bloomed region is its lamp's rectangle dilated on the ceiling (``_bloomed``), its
    centre where the lamp's is, and the drive is tracked from a prior at the truth to
    a centimetre. Without the dilated family (``bloom_max_m`` 0) a few rim slivers are
    kept and no frame gives a pose (the held-out drive: 0 of 100 from its start pose)."""
    est, poses, frames = bloomed_fisheye
    obs_ = est.observer
    assert obs_.bloom_max_m > 0.3
    for (x, y, yaw_deg), img in zip(poses, frames, strict=True):
        yaw = math.radians(yaw_deg)
        obs = obs_.observe(img)
        assert len(obs.spots) >= 8 and np.median(obs.excess_px) > 3.0
        c, s = math.cos(yaw), math.sin(yaw)
        q_w = np.column_stack([x + c * obs.q_v[:, 0] - s * obs.q_v[:, 1],
                               y + s * obs.q_v[:, 0] + c * obs.q_v[:, 1]])
        lamps = np.asarray(est.lights_w)
        err = np.linalg.norm(q_w[:, None] - lamps[None], axis=2).min(axis=1)
        assert np.median(err) < 0.012 and err.max() < 0.05, err
        prior = PoseEstimate(0, "truth", x, y, yaw, 1.0,
                             cov=np.diag([1e-4, 1e-4, math.radians(0.5) ** 2]))
        got = est.estimate(img, 0, prior)
        assert isinstance(got, PoseEstimate), getattr(got, "detail", got)
        assert errors(got, x, y, yaw)[0] < 0.01, got
    reach, obs_.bloom_max_m = obs_.bloom_max_m, 0.0
    try:
        for (x, y, yaw_deg), img in zip(poses, frames, strict=True):
            prior = PoseEstimate(0, "truth", x, y, math.radians(yaw_deg), 1.0,
                                 cov=np.diag([1e-4, 1e-4, math.radians(0.5) ** 2]))
            assert not isinstance(est.estimate(img, 0, prior), PoseEstimate)
    finally:
        obs_.bloom_max_m = reach


def test_a_quarter_turn_of_a_square_grid_of_oblong_lamps_is_no_twin():
    """A grid pitched alike both ways looks the same under a quarter turn by its lamps'
    centres, never by the lamps: a spot that shows its lamp's long side refutes a pose
    that puts the lamp across it (``TwinJudge.aligned``). Without a prior, the frame's
    hypotheses are its cells, every one at the true heading or its half turn."""
    rig = fisheye_rig()
    lamps = [[i * 3.0, j * 3.0] for i in range(-3, 4) for j in range(-3, 4)]
    site = Site.from_node(Node({"ceiling_height": 3.0, "lights": lamps,
                                "light_size": [1.2, 0.4], "light_yaw": 30.0}, None, ""))
    est = LightsEstimator(rig, site)
    yaw = math.radians(17.0)
    img = render_frame(rig, site, 0.4, -0.3, yaw, SimOptions(), np.random.default_rng(1))
    e = est.estimate(img, 0, None)
    assert e.hypotheses, getattr(e, "detail", e)
    turns = [abs(math.remainder(h.yaw_rad - yaw, math.pi)) for h in e.hypotheses]
    assert max(turns) < math.radians(2.0), np.degrees(turns)
    assert any(math.hypot(h.x_m - 0.4, h.y_m + 0.3) < 0.02 for h in e.hypotheses)


def test_the_association_about_a_prior_is_judged_at_its_own_pairs_fit(bloomed_fisheye):
    """The matcher's pose is fitted before its last re-association; the prior's region
    judges the rigid fit of the pairs it kept (``TwinJudge.refitted``). On held-out
    ``lamps2`` of seed 19 the two lay 3.7 cm apart (the refit 0.2 cm from the truth), a
    fused prior of 1.75 cm 1σ refused the association and ``auto`` lost its track on the
    second frame (2 of 100 poses; 100 of 100 since)."""
    est, poses, frames = bloomed_fisheye
    x, y, yaw_deg = poses[1]
    obs = est.observer.observe(frames[1])
    c = est.matcher.verify(obs.q_v, math.radians(yaw_deg), np.array([x, y]), 1.0)
    stale = dataclasses.replace(c, x_m=c.x_m + 0.05, y_m=c.y_m - 0.04)
    got = est.judge.refitted(obs, stale)
    assert math.hypot(got.x_m - x, got.y_m - y) < 0.01
    assert abs(math.remainder(got.yaw_rad - math.radians(yaw_deg), 2 * math.pi)) < 0.005
    assert got.inliers == c.inliers and got.rms_m < 0.02


def pinhole_lamps(f_px: float, k1: float, z_m: float, ceiling_m: float,
                  origin: tuple[float, float], pitch: tuple[float, float],
                  counts: tuple[int, int], size: list[float], yaw_deg: float
                  ) -> tuple[Rig, Site]:
    """A 640x480 pinhole looking up (``f_px``, radial ``k1``) ``z_m`` above the floor,
    under a ``counts`` grid of ``size`` lamps from ``origin`` at ``pitch``."""
    cam = CameraModel.pinhole(640, 480, f_px, dist=[k1, 0.0, 0.0, 0.0, 0.0])
    rig = Rig(cam, Mount(tilt_rad=math.pi / 2, x_m=0.1, z_m=z_m))
    lamps = [[origin[0] + i * pitch[0], origin[1] + j * pitch[1]]
             for i in range(counts[0]) for j in range(counts[1])]
    site = Site.from_node(Node({"ceiling_height": ceiling_m, "lights": lamps,
                                "light_size": size, "light_yaw": yaw_deg}, None, ""))
    return rig, site


@pytest.fixture(scope="module")
def bloomed_pinhole():
    """Held-out ``lamps0`` of seed 7, rebuilt: a 334 px pinhole 2.5 m under a 1.81 x
    2.45 m grid of 0.93 x 0.46 m lamps at exposure 1.31 with a 51-level halo, frames
    thresholded at 210: two or three lamps in view, each bloomed to about twice its
    rectangle, the halo cut nearer the lamp on its side away from the image centre;
    every 2nd frame of the drive's first 0.8 s."""
    rig, site = pinhole_lamps(333.578, -0.0716, 0.538, 3.052, (-10.8347, -11.3468),
                              (1.81275, 2.4507), (11, 9), [0.926, 0.456], 0.0)
    poses = [(0.0, 0.0, -62.693), (0.0653, -0.1215, -58.967), (0.1382, -0.2385, -55.419),
             (0.2181, -0.3509, -52.087), (0.3044, -0.4585, -49.008),
             (0.3961, -0.5614, -46.216), (0.4926, -0.6599, -43.743)]
    sim = SimOptions(exposure=1.309, halo=50.7, noise_sigma=2.0, blur_px=0.8)
    return thresholded_drive(rig, site, poses, sim, 210)


def lamp_errors(obs, lamps_w: np.ndarray, x: float, y: float, yaw_deg: float) -> np.ndarray:
    """``(N,)`` each kept spot's ceiling point's distance from the nearest lamp (m)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    q_w = np.column_stack([x + c * obs.q_v[:, 0] - s * obs.q_v[:, 1],
                           y + s * obs.q_v[:, 0] + c * obs.q_v[:, 1]])
    return np.linalg.norm(q_w[:, None] - lamps_w[None], axis=2).min(axis=1)


def test_a_bloom_is_not_dropped_as_a_glare_halo(bloomed_pinhole):
    """The detector drops a region larger than a light's largest image (times the size
    check's bound) as a glare halo; a lamp bloomed to twice its rectangle and more (a
    pinhole's lamps near the nadir, held-out ``lamps0`` of seed 7) was dropped before
    the bloom family could measure it, and no more than two lamps were in any frame's
    regions (``too_few_lights`` on 75 of 100 frames). The bound now covers a lamp
    bloomed its farthest (half the narrowest gap between two lamps)."""
    est, poses, frames = bloomed_pinhole
    observer = est.observer
    params = observer.spot_params
    budget = observe_module.MAX_BUDGET_FACTOR * observer.max_spots
    new = observer._examine(frames[6], budget)[0]
    area = 0.926 * 0.456 * (333.578 / 2.514) ** 2          # the lamp's image at the nadir
    assert params.max_light_px > 4 * area
    assert new.areas_px.max() > 2.2 * area, new.areas_px
    observer.spot_params = dataclasses.replace(
        params, max_light_px=int(2.2 * area * 1.1))
    try:
        old = observer._examine(frames[6], budget)[0]
    finally:
        observer.spot_params = params
    assert not np.any(old.areas_px > 2.2 * area * 1.1), old.areas_px


def test_a_lone_bloom_is_judged_with_the_run_s(bloomed_pinhole):
    """Under a pinhole one or two lamps are in view and a frame's blooms are too few
    to judge one by (at least three: two lamps merged reach twice as far). The run's
    recent blooms (``BloomPool``) are judged with them, and their slope across the view
    places each bloom's centre. Measured as rectangles (the frame alone), the blooms
    a size check passes were 5-10 cm off; judged with the run's, each lamp's centre is
    within 2.5 cm."""
    est, poses, frames = bloomed_pinhole
    lamps = np.asarray(est.lights_w)
    alone = est.observer.observe(frames[6])
    assert not np.any(alone.bloom_m > 0)
    assert lamp_errors(alone, lamps, *poses[6]).max() > 0.04
    pool = observe_module.BloomPool()
    for img in frames:
        obs = est.observer.observe(img, pool)
        pool = pool.added(obs.blooms_seen)
        assert len(obs.spots) >= 1
    assert pool.s.size >= 3
    assert np.any(obs.bloom_m > 0)
    err = lamp_errors(obs, lamps, *poses[-1])
    assert err.max() < 0.025, err


def test_a_run_s_blooms_are_forgotten(bloomed_pinhole):
    """The estimator carries the pool between frames; ``forget`` empties it (a
    ``--no-track`` row does not depend on the frames before it)."""
    est, poses, frames = bloomed_pinhole
    for img in frames[:3]:
        est.estimate(img, 0, None)
    assert est._blooms.s.size >= 3
    est.forget()
    assert est._blooms.s.size == 0


def test_a_lamp_s_fragment_is_not_the_lamp():
    """Held-out ``lamps1`` of seed 31, rebuilt: a 358 px pinhole 3.4 m under 1.28 x
    0.43 m lamps at exposure 1.1, raw: a lamp clipped at one end and not at the other
    (the vignetting) keeps its clipped part whole and its unclipped part is hollowed by
    the Niblack window: a region 70 % of its rectangle, centred 10-12 cm off, which
    the size check (0.4-2.2) passed; two such turned a pose 2.8 deg. A region short of
    its rectangle by more than ``RECT_SHORT_PX`` (1.5 px) is not kept (issue 36)."""
    rig, site = pinhole_lamps(357.89, -0.0173, 0.589, 3.977, (-6.6977, -9.8408),
                              (2.47045, 2.25081), (6, 8), [1.281, 0.425], 90.0)
    pose = (-0.0163, -0.0095, -150.174)
    img = render_frame(rig, site, pose[0], pose[1], math.radians(pose[2]),
                       SimOptions(noise_sigma=2.0, blur_px=0.8, exposure=1.1),
                       np.random.default_rng(1))
    est = LightsEstimator(rig, site)
    lamps = np.asarray(est.lights_w)
    assert lamp_errors(est.observer.observe(img), lamps, *pose).max() < 0.03
    short = observe_module.RECT_SHORT_PX
    observe_module.RECT_SHORT_PX = math.inf
    try:
        assert lamp_errors(est.observer.observe(img), lamps, *pose).max() > 0.08
    finally:
        observe_module.RECT_SHORT_PX = short


def test_blooms_are_judged_with_the_run_s_median():
    """``judged_blooms``: a frame's blooms against the median of theirs and the run's
    pool (at least three), the merged one (twice as wide) left out, and the median
    returned: a bloom cut short by the fall-off carries the typical bloom's centre
    error (``Observation.bloom_m``; the quiet blooms at a pinhole's edge, held-out
    ``lamps2`` of seed 11, were 2 cm off at s 0.03-0.08 m: NEES 35 -> 15)."""
    judged = observe_module.judged_blooms
    pool = observe_module.BloomPool(np.array([0.1, 0.2]), np.array([0.18, 0.20]))
    u, s = np.array([0.15, 0.5]), np.array([0.19, 0.40])
    good, b, median = judged(u, s, np.ones(2, bool), pool)
    assert good.tolist() == [True, False]
    assert median == pytest.approx(0.195)
    good, b, median = judged(u[:1], s[:1], np.ones(1, bool), observe_module.BloomPool())
    assert not good.any() and b == 0.0 and median == 0.0
