"""The block method's compiled loops against their array readings
(tests/block_reference.py): the edge measurement, the contrast check, the planar
solve, the predicted ceiling chords and the predicted outlines must give the same
numbers (to float rounding) and the same decisions as the code they replaced."""

from __future__ import annotations

import dataclasses
import math

import block_reference as ref
import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block import detect, parallels, pnp
from ceilkit.runtime.estimators.block.estimator import BlockEstimator
from ceilkit.runtime.estimators.block.parallels import LinedSides
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, project_px
from ceilkit.runtime.estimators.block.window import WINDOW
from ceilkit.runtime.features.quads import MarkerCodes, marker_dictionary
from ceilkit.runtime.geometry.camera import CameraModel, magnification_points
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

NOISY = SimOptions(noise_sigma=2.0, blur_px=0.8)


@pytest.fixture(scope="module")
def scene():
    """configs/block: the rig, the site, its geometry and 12 frames along the blocks
    and markers, with the truth."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    rng = np.random.default_rng(3)
    poses = [np.array([0.3 + 0.45 * k, rng.normal(0, 0.15), rng.normal(0, 0.3)])
             for k in range(12)]
    frames = [render_frame(rig, site, *p, NOISY, np.random.default_rng(k))
              for k, p in enumerate(poses)]
    return rig, site, PlanarGeometry.of(rig, site), poses, frames


def _outlines(scene):
    """``(frame, target, px)`` of every target fully in view, from the truth."""
    rig, site, geo, poses, frames = scene
    est = BlockEstimator(rig, site, {"window_search": True})
    for pose, grey in zip(poses, frames, strict=True):
        for tgt, px in est.windows.predicted(pose):
            yield grey, tgt, px


def test_measure_sides_equals_the_array_reading(scene):
    geo = scene[2]
    rng = np.random.default_rng(0)
    n = 0
    for grey, _, px in _outlines(scene):
        start = px + rng.normal(0, 1.5, px.shape)          # a prior a pixel or two off
        for passes, search in ((1, 3.0), (2, 4.0), (2, 6.0), (3, 4.0)):
            want = ref.measure_sides(grey, start, geo, 12, passes, search)
            got = detect.measure_sides(grey, start, geo, 12, passes, search)
            assert (want is None) == (got is None)
            if want is None:
                continue
            n += 1
            np.testing.assert_array_equal(got.side, want.side)
            np.testing.assert_allclose(got.edge_norm, want.edge_norm, rtol=0, atol=1e-11)
            np.testing.assert_allclose(got.corners_norm, want.corners_norm, rtol=0,
                                       atol=1e-10)
            assert got.stations == want.stations
    assert n > 40
    assert detect.measure_sides(scene[4][0], np.full((4, 2), np.nan), geo, 12) is None


def test_step_contrast_reads_as_opencvs_remap(scene):
    n = 0
    for grey, tgt, px in _outlines(scene):
        got, want = detect.step_contrast(grey, px), ref.step_contrast(grey, px)
        assert abs(got - want) < 0.03 * want        # (remap rounds to uint8)
        assert (got < 0.62) == tgt.dark
        n += 1
    assert n > 10
    black = np.zeros((40, 40), np.uint8)
    assert math.isnan(detect.step_contrast(black, np.array([[10.0, 10], [30, 10], [30, 30],
                                                               [10, 30]])))


def test_planar_solve_equals_closed_form_then_refine(scene):
    """pnp.solve (one compiled call) against closed_form + refine + side_offset_cov,
    with and without sides left out, on measured sides of every target in view."""
    rig, site, geo = scene[:3]
    lined = LinedSides(site.corridor)
    n = 0
    for grey, tgt, px in _outlines(scene):
        sides = detect.measure_sides(grey, px, geo, 12)
        if sides is None:
            continue
        for drop in (lined(tgt.corners_w), np.array([False, True, False, False]),
                     np.zeros(4, bool)):
            s_want, want = ref.solve(geo, sides.corners_norm, tgt.corners_w,
                                     sides.edge_norm, sides.side, drop)
            s_got, got = pnp.solve(geo, sides.corners_norm, tgt.corners_w,
                                   sides.edge_norm, sides.side, drop)
            assert s_got == pytest.approx(s_want, rel=1e-9, abs=1e-15)
            np.testing.assert_allclose(got.pose, want.pose, rtol=0, atol=1e-10)
            np.testing.assert_allclose(got.cov, want.cov, rtol=1e-4, atol=1e-16)
            assert got.rms_px == pytest.approx(want.rms_px, rel=1e-6)
            assert got.n == want.n
            assert got.side_var_px2 == pytest.approx(want.side_var_px2, rel=1e-4, abs=1e-12)
            assert (got.side_unit is None) == (want.side_unit is None)
            n += 1
    assert n > 30
    # a corner with no ray (a lens that has no inverse there): no closed form
    lost = sides.corners_norm.copy()
    lost[2] = np.nan
    assert pnp.solve(geo, lost, tgt.corners_w, sides.edge_norm, sides.side,
                     np.zeros(4, bool)) is None


@pytest.mark.parametrize("sides", [(0, 1, 2, 3), (0, 1, 3), (1, 2), (2,)])
def test_side_offset_cov_equals_the_array_reading(sides):
    rng = np.random.default_rng(len(sides))
    side = np.repeat(np.array(sides), 9)
    r, J = rng.normal(0, 0.3, side.size), rng.normal(0, 50.0, (side.size, 3))
    r[side == sides[0]] += 0.4                    # one side offset as a whole
    A = np.linalg.inv(J.T @ J)
    want = ref.side_offset_cov(r, J, side, A)
    got = pnp.side_offset_cov(r, J, side, A)
    assert got[0] == pytest.approx(want[0], rel=1e-9, abs=1e-15)
    assert (got[1] is None) == (want[1] is None) == (len(sides) < 3)
    if want[1] is not None:
        assert want[0] > 0
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9, atol=1e-20)


@pytest.mark.parametrize("model,dist,skew", [
    ("plumb_bob", [-0.3, 0.1, 0.001, -0.002, 0.0], 0.0),
    ("rational_polynomial", [-0.3, 0.1, 0.001, -0.002, 0.01, 0.05, 0.01, 0.002], 0.0),
    ("plumb_bob", [-0.2, 0.05, 0.0, 0.0, 0.0], 3.0),
    ("equidistant", [0.05, -0.01, 0.002, -0.0005], 0.0),
    ("plumb_bob", [0.0, 0.0, 0.0, 0.0, 0.0], 0.0),
])
def test_magnification_points_is_the_lens_jacobians_determinant(model, dist, skew):
    K = np.array([[400.0, skew, 320.0], [0.0, 410.0, 240.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(640, 480, K, np.array(dist), model)
    xy = np.random.default_rng(1).uniform(-0.6, 0.6, (50, 2))
    J = cam.distort_jacobian(xy)
    want = np.sqrt(np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]))
    got = np.empty(len(xy))
    magnification_points(xy, *cam.lens, got)
    # (the camera's reading is forward differences of 1e-4 for a fisheye or a skewed K)
    fd = model == "equidistant" or skew
    np.testing.assert_allclose(got, want, rtol=1e-4 if fd else 1e-9)


def test_predicted_chords_equal_the_array_reading(scene):
    rig, site, geo = scene[:3]
    rng = np.random.default_rng(2)
    ignore = dataclasses.replace(site, ignore_m=(np.array([[2.0, -0.5], [3.0, -0.5],
                                                           [3.0, 0.7], [2.0, 0.7]]),))
    no_across = dataclasses.replace(site.corridor, lines_across=None)
    n = 0
    for pose in scene[3]:
        for _ in range(3):
            p = pose + rng.normal(0, [0.3, 0.3, 0.4])
            for cor, s, most in ((site.corridor, site, 12), (site.corridor, site, 1000),
                                 (site.corridor, ignore, 20), (no_across, site, 20),
                                 (site.corridor, None, 0), (site.corridor, None, 1)):
                want = ref.predicted_chords(geo, cor, p, most, s)
                got = parallels.predicted_chords(geo, cor, p, most, s)
                assert got.shape == want.shape
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
                n += len(got)
    assert n > 500
    # looking at the sky: the camera's axis never meets the ceiling
    up = PlanarGeometry(geo.camera, np.diag([1.0, -1.0, -1.0]), geo.t_vehicle_cam, 3.0)
    assert parallels.predicted_chords(up, site.corridor, (0.0, 0.0, 0.0)).shape == (0, 4)


def test_predicted_outlines_equal_the_array_reading(scene):
    rig, site, geo, poses, _ = scene
    est = BlockEstimator(rig, site, {"window_search": True})
    w = est.windows
    margin = 2.0 + est.options.window_px + 1.0
    rng = np.random.default_rng(4)
    seen = 0
    for pose in poses:
        p = pose + rng.normal(0, [0.2, 0.2, 0.3])
        want = ref.predicted(geo, w.targets, p, margin)
        got = w.predicted(p)
        assert [w.targets.index(t) for t, _ in got] == [k for k, _ in want]
        for (_, a), (_, b) in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
        seen += len(got)
    assert seen > 10


def test_the_window_check_refuses_the_wrong_polarity_and_a_far_outline(scene):
    """The compiled window fix passes the truth's outline and refuses: a dark target
    read as bright, an outline displaced beyond window_px, a frame with no
    block where the prior puts one."""
    rig, site, geo, poses, frames = scene
    est = BlockEstimator(rig, site, {"window_search": True})
    w = est.windows
    fixed = 0
    for pose, grey in zip(poses, frames, strict=True):
        for tgt, px in w.predicted(pose):
            got = w.fix(grey, tgt, px)
            if got is None:
                continue
            fixed += 1
            assert np.hypot(*(got.refined.pose[:2] - pose[:2])) < 0.01
            flipped = dataclasses.replace(tgt, dark=not tgt.dark)
            w.targets[w.targets.index(tgt)] = flipped
            try:
                assert w.fix(grey, flipped, px) is None
            finally:
                w.targets[w.targets.index(flipped)] = tgt
            assert w.fix(grey, tgt, px + 7.0) is None
            assert w.fix(np.full_like(grey, 180), tgt, px) is None
    assert fixed > 10
    # the estimator's tracked frame: a window fix, its source and mode
    pose = poses[4]
    from ceilkit.runtime.estimators.base import PoseEstimate
    prior = PoseEstimate(0, "prior", pose[0] + 0.003, pose[1] - 0.002, pose[2], 1.0)
    out = est.estimate(frames[4], 0, prior)
    assert out and out.diagnostics["mode"] == WINDOW
    assert math.hypot(out.x_m - pose[0], out.y_m - pose[1]) < 0.005
    assert project_px(geo, pose, site.blocks[0].corners_m).shape == (4, 2)


def _remap_in_float() -> bool:
    """OpenCV's ``remap`` interpolates in float (5.x; older releases round the sample's
    place to 1/32 px): 0.49 px between 0 and 255 reads 125 in float, 128 in fixed point."""
    grey = np.array([[0, 255]], np.uint8)
    at = cv2.remap(grey, np.full((1, 1), 0.49, np.float32), np.zeros((1, 1), np.float32),
                   cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return int(at[0, 0]) == 125


@pytest.mark.skipif(not _remap_in_float(), reason="this OpenCV's remap rounds to 1/32 px")
@pytest.mark.parametrize("dictionary", ["DICT_4X4_50", "DICT_APRILTAG_36h11"])
def test_read_marker_equals_the_opencv_reading(dictionary):
    """The compiled read (``detect.read_core``) names the same code with the same
    errors, or refuses, as OpenCV's homography, ``remap`` and array code did, on
    printed markers under blur, noise, grey backgrounds and outlines up to 5 % of a
    side off, through a pinhole and a distorting lens: reads, misreads and refusals."""
    codes = MarkerCodes(dictionary)
    d = marker_dictionary(dictionary)
    n = codes.cells
    src = np.array([[10, 10], [10 + 10 * n, 10], [10 + 10 * n, 10 + 10 * n], [10, 10 + 10 * n]],
                   np.float32)
    rng = np.random.default_rng(1)
    outcomes = {"read": 0, "errors": 0, "refused": 0}
    for lens in ([0.0] * 5, [-0.05, 0.01, 0.001, 0.0, 0.0]):
        geo = PlanarGeometry(CameraModel.pinhole(640, 480, 400.0, dist=lens), np.eye(3),
                             np.zeros(3), 3.0)
        for _ in range(60):
            printed = cv2.copyMakeBorder(cv2.aruco.generateImageMarker(
                d, int(rng.integers(0, 50)), 10 * n), 10, 10, 10, 10, cv2.BORDER_CONSTANT,
                value=255)
            a, s = rng.uniform(0, 2 * math.pi), rng.uniform(0.03, 0.3)
            turn = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            corners = rng.uniform(-0.6, 0.6, 2) + s * (np.array(
                [[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) @ turn.T)
            H = cv2.getPerspectiveTransform(src, (corners * 400 + [320, 240]).astype(np.float32))
            grey = cv2.warpPerspective(printed, H, (640, 480),
                                       borderValue=int(rng.integers(100, 256)))
            grey = np.clip(cv2.GaussianBlur(grey, (0, 0), rng.uniform(0.3, 2.5))
                           + rng.normal(0, rng.uniform(0, 20), grey.shape), 0, 255)
            outline = corners + rng.normal(0, rng.uniform(0, 0.05) * s, (4, 2))
            want = ref.read_marker(grey.astype(np.uint8), outline, geo, codes)
            assert detect.read_marker(grey.astype(np.uint8), outline, geo, codes) == want
            outcomes["refused" if want is None else "errors" if want[2] else "read"] += 1
    assert min(outcomes.values()) >= 5, outcomes      # every kind of outcome was met
