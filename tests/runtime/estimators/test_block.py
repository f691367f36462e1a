"""The block method: planar PnP exactness, markers and plain blocks on rendered frames,
symmetric blocks, unknown markers, partial blocks, bad inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Block, MarkerPose, Markers, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.block.estimator import BlockEstimator, BlockOptions
from ceilkit.runtime.estimators.block.pnp import (
    PlanarGeometry,
    closed_form,
    magnification,
    project_norm,
    project_px,
    refine,
    six_dof_check,
)
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.marks import BLOCK_GREY
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

DICT = "DICT_APRILTAG_36h11"
RECT = np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]])
SQUARE = np.array([[2.0, -0.2], [2.4, -0.2], [2.4, 0.2], [2.0, 0.2]])
NOISY = SimOptions(noise_sigma=2.0, blur_px=1.0)


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.load(CONFIGS / "block" / "rig.yaml")


def tilted_rig() -> Rig:
    cam = CameraModel.pinhole(640, 480, 450.0, dist=[-0.1, 0.03, 0, 0, 0])
    return Rig(cam, Mount(math.radians(5.0), math.radians(70.0), math.radians(2.0),
                          0.3, 0.05, 0.8))


def marker_site(*ids_xy_yaw: tuple[int, float, float, float], size: float = 0.25) -> Site:
    poses = tuple(MarkerPose(i, x, y, math.radians(a), size) for i, x, y, a in ids_xy_yaw)
    return Site(3.0, markers=Markers(DICT, size, poses))


def prior_at(x: float, y: float, yaw: float) -> PoseEstimate:
    return PoseEstimate(0, "prior", x, y, yaw, 1.0)


# -- planar PnP: exact on noise-free data --------------------------------------------------
@pytest.mark.parametrize("make_rig", [lambda: Rig.load(CONFIGS / "block" / "rig.yaml"),
                                      tilted_rig])
def test_planar_pnp_is_exact_without_noise(make_rig):
    rig = make_rig()
    geo = PlanarGeometry.of(rig, Site(3.0))
    truth = np.array([1.7, 0.1, math.radians(23.0)])
    corners = project_norm(geo, truth, RECT)
    x, y, yaw, rms = closed_form(geo, corners, RECT)
    assert np.allclose([x, y, yaw], truth, atol=1e-10) and rms < 1e-10
    # edge points exactly on the sides, a start 2 cm and 1 degree off: back to the truth
    t = np.linspace(0.1, 0.9, 6)
    pts = np.concatenate([RECT[k] + t[:, None] * (RECT[(k + 1) % 4] - RECT[k])
                          for k in range(4)])
    side = np.repeat(np.arange(4), t.size)
    norm = project_norm(geo, truth, pts)
    ref = refine(geo, (x + 0.02, y - 0.01, yaw + math.radians(1.0)), RECT, norm, side,
                 magnification(rig.camera, norm))
    assert np.allclose(ref.pose, truth, atol=1e-9) and ref.rms_px < 1e-6
    assert np.all(np.isfinite(ref.cov)) and np.all(np.diag(ref.cov) > 0)
    check = six_dof_check(geo, corners, RECT, yaw)
    assert abs(check["pnp6_tilt_deg"]) < 1e-6 and abs(check["pnp6_height_m"]) < 1e-6


def square_edges(rig: Rig):
    """The 0.4 m SQUARE's edge points seen from a pose, 12 per side: ``(geo, truth,
    norm (M, 2), side (M,), scale (M,) px per unit, normal (M, 2) each side's normal)``."""
    geo = PlanarGeometry.of(rig, Site(3.0))
    truth = np.array([2.1, 0.05, math.radians(12.0)])
    t = np.linspace(0.15, 0.85, 12)
    pts = np.concatenate([SQUARE[k] + t[:, None] * (SQUARE[(k + 1) % 4] - SQUARE[k])
                          for k in range(4)])
    side = np.repeat(np.arange(4), t.size)
    norm = project_norm(geo, truth, pts)
    scale = magnification(rig.camera, norm)
    normal = np.zeros_like(norm)
    for k in range(4):
        d = norm[side == k][-1] - norm[side == k][0]
        normal[side == k] = np.array([-d[1], d[0]]) / np.hypot(*d)
    return geo, truth, norm, side, scale, normal


@pytest.mark.parametrize("cam", [
    CameraModel.pinhole(640, 480, 450.0, dist=[-0.1, 0.03, 0.001, -0.002, 0.01]),
    CameraModel.pinhole(640, 480, 450.0, dist=[0.1, -0.05, 0.001, -0.002, 0.01, 0.02, -0.01,
                                               0.003], model="rational_polynomial"),
    CameraModel.pinhole(640, 480, 450.0, dist=[0.05, -0.01, 0.002, 0.0], model="equidistant"),
], ids=lambda c: c.model)
def test_the_lens_magnification_is_the_distortions_jacobian(cam):
    """sqrt |det d(pixel)/d(normalized point)|: OpenCV's Jacobian for the polynomial
    lenses, finite differences otherwise; both against central differences."""
    p = np.random.default_rng(2).uniform(-0.6, 0.6, (30, 2))
    e = 1e-6
    du = (cam.distort(p + [e, 0]) - cam.distort(p - [e, 0])) / (2 * e)
    dv = (cam.distort(p + [0, e]) - cam.distort(p - [0, e])) / (2 * e)
    want = np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))
    np.testing.assert_allclose(magnification(cam, p), want, rtol=1e-3)
    assert magnification(cam, np.zeros((0, 2))).shape == (0,)


def test_an_offset_shared_by_a_sides_points_is_in_the_covariance(rig):
    """A whole side moved (a seam flush with the block's edge moves every station the
    same way): the fit's white covariance does not average it out; the side-offset
    term, measured by the block's known size, covers the pose error it makes."""
    geo, truth, norm, side, scale, normal = square_edges(rig)
    rng = np.random.default_rng(0)
    white = norm + rng.normal(0.0, 0.05, norm.shape) / scale[:, None]      # 0.05 px
    clean = refine(geo, truth, SQUARE, white, side, scale)
    # side 1 moved 0.3 px along its normal (towards the block's inside)
    moved = white.copy()
    moved[side == 1] += 0.3 * normal[side == 1] / scale[side == 1, None]
    got = refine(geo, truth, SQUARE, moved, side, scale)
    e = got.pose - truth
    assert math.hypot(e[0], e[1]) > 5 * math.sqrt(clean.cov[0, 0])   # a real bias
    assert float(e @ np.linalg.solve(got.cov, e)) < 7.81             # covered (95 %, 3 dof)
    # the white covariance of the same geometry (the clean fit's) would not cover it
    assert float(e @ np.linalg.solve(clean.cov, e)) > 30.0
    # and on clean sides the term stays small: the clean pose's sigma is the noise's
    ec = clean.pose - truth
    assert float(ec @ np.linalg.solve(clean.cov, ec)) < 11.3
    assert math.sqrt(clean.cov[0, 0]) < 0.3 * math.sqrt(got.cov[0, 0])


def test_side_offsets_pooled_over_frames_cover_the_pose_error(rig):
    """Random per-side offsets (0.2 px) and 0.05 px noise, 400 frames of one target:
    one frame's size check has 2 degrees of freedom and often under-states the
    offsets; pooled per target over frames, the 95 % ellipse holds about 95 %."""
    from ceilkit.runtime.estimators.block.pnp import PooledSideOffsets
    geo, truth, norm, side, scale, normal = square_edges(rig)
    rng = np.random.default_rng(1)
    pool = PooledSideOffsets()
    inside = {"frame": 0, "pooled": 0}
    for _ in range(400):
        off = rng.normal(0.0, 0.05, len(norm)) + rng.normal(0.0, 0.2, 4)[side]
        got = refine(geo, truth, SQUARE, norm + (off / scale)[:, None] * normal, side, scale)
        for key, ref in (("frame", got), ("pooled", pool("block:X", got))):
            e = ref.pose - truth
            inside[key] += float(e @ np.linalg.solve(ref.cov, e)) < 7.81
    assert inside["frame"] < 0.88 * 400                 # one frame: too often too small
    assert inside["pooled"] > 0.92 * 400                # pooled: about 95 %


def test_a_block_side_on_a_seam_is_left_out_and_the_pose_is_unbiased(rig):
    """configs/block's bright tile B ends on the tile seam at x = 5.4 m: the half seam
    left outside it, narrower than the blur, pulled that edge ~0.3 px in (1.2-1.5 mm
    of x error with a 0.19 mm 1-sigma). That side is left out of the refinement (its
    opposite is on no line): the pose comes from the three clean sides."""
    from ceilkit.runtime.estimators.block.parallels import sides_on_lines
    site = Site.load(CONFIGS / "block" / "site.yaml")
    b = next(blk for blk in site.blocks if blk.id == "B")
    assert sides_on_lines(site.corridor, b.corners_m).tolist() == [False, True, False, False]
    a = next(blk for blk in site.blocks if blk.id == "A")       # lines cross it: not on
    assert not sides_on_lines(site.corridor, a.corners_m).any()
    est = BlockEstimator(rig, site, {"plane_odometry": False})
    rng = np.random.default_rng(4)
    for x, y, yaw in [(5.2, -0.3, 0.1), (5.4, -0.1, 0.25), (5.25, 0.0, 0.0)]:
        img = render_frame(rig, site, x, y, yaw, NOISY, rng)
        got = est.estimate(img, 0, prior_at(x, y, yaw))
        assert got and got.diagnostics["source"] == "block:B"
        e = np.array([got.x_m - x, got.y_m - y])
        assert np.hypot(*e) < 0.0005                                # was 1.2-1.5 mm
        assert float(e @ np.linalg.solve(np.asarray(got.cov)[:2, :2], e)) < 9.21  # 99 %


# -- markers -------------------------------------------------------------------------------
@pytest.mark.parametrize("x, y, yaw_deg", [(0.2, 0.1, 0.0), (-0.3, 0.35, 71.0),
                                           (0.1, -0.2, -160.0)])
def test_marker_pose_on_noisy_frames(rig, x, y, yaw_deg):
    site = marker_site((7, 0.4, 0.3, 30.0))
    yaw = math.radians(yaw_deg)
    img = render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(3))
    est = BlockEstimator(rig, site).estimate(img, 5)
    assert est, est
    assert est.diagnostics["source"] == "marker:7"
    assert math.hypot(est.x_m - x, est.y_m - y) < 0.01
    assert abs(math.degrees(est.yaw_rad - yaw)) < 0.5
    assert est.cov.shape == (3, 3) and est.quality > 0.5


def test_marker_at_the_image_edge_through_strong_distortion():
    cam = CameraModel.pinhole(640, 480, 330.0, dist=[-0.32, 0.11, 0.0, 0.0, -0.015])
    rig = Rig(cam, Mount(0.0, math.radians(90.0), 0.0, 0.1, 0.0, 0.6))
    site = marker_site((3, 1.8, 2.5, 15.0), size=0.55)
    img = render_frame(rig, site, 0.0, 0.0, 0.0, NOISY, np.random.default_rng(4))
    px = project_px(PlanarGeometry.of(rig, site), np.zeros(3),
                    site.markers.poses[0].corners_m())
    assert px[:, 0].min() < 70 and px[:, 1].max() > 410        # in the image's corner
    est = BlockEstimator(rig, site).estimate(img, 0)
    assert est, est
    assert math.hypot(est.x_m, est.y_m) < 0.02 and abs(math.degrees(est.yaw_rad)) < 0.5


def test_a_marker_not_in_the_site_is_ignored(rig):
    seen = marker_site((9, 0.4, 0.2, 0.0))
    img = render_frame(rig, seen, 0.0, 0.0, 0.0, NOISY)
    est = BlockEstimator(rig, marker_site((7, 3.0, 0.0, 0.0)),
                         {"heading_cue": False}).estimate(img, 0)
    assert not est and est.reason == "unknown_marker"
    assert est.diagnostics["unknown_marker_ids"] == (9,)


# -- plain blocks --------------------------------------------------------------------------
def test_rectangle_is_ambiguous_without_a_prior_and_resolved_with_one(rig):
    site = Site(3.0, blocks=(Block("A", RECT, "dark"),))
    x, y, yaw = 2.2, 0.1, math.radians(12.0)
    img = render_frame(rig, site, x, y, yaw, NOISY)
    # the global path (the window path is test_block_track.py's)
    est = BlockEstimator(rig, site, {"heading_cue": False, "window_search": False})
    none = est.estimate(img, 0)
    assert not none and none.reason == "ambiguous"
    # with the heading cue (default) too: the frame is ambiguous and carries both poses
    # (a half turn apart, equally weighted, the truth among them), which say more than
    # the sides' heading alone
    cue = BlockEstimator(rig, site).estimate(img, 0)
    assert not cue and cue.reason == "ambiguous"
    assert len(cue.hypotheses) == 2 and [h.weight for h in cue.hypotheses] == [0.5, 0.5]
    near = min(cue.hypotheses, key=lambda h: math.hypot(h.x_m - x, h.y_m - y))
    assert math.hypot(near.x_m - x, near.y_m - y) < 0.005
    assert abs(math.remainder(near.yaw_rad - yaw, 2 * math.pi)) < math.radians(0.2)
    turn = cue.hypotheses[1].yaw_rad - cue.hypotheses[0].yaw_rad
    assert abs(math.remainder(turn - math.pi, 2 * math.pi)) < 1e-6
    got = est.estimate(img, 0, prior=prior_at(x + 0.1, y - 0.1, yaw + 0.2))
    assert got and got.diagnostics["resolved_by"] == "prior"
    assert got.provenance.value == "prior" and not got.singled_out
    assert len(got.hypotheses) == 2 and got.hypotheses[0].x_m == got.x_m
    assert got.hypotheses[1].label == "half_turn"
    assert math.hypot(got.x_m - x, got.y_m - y) < 0.005
    assert abs(math.degrees(got.yaw_rad - yaw)) < 0.2
    assert got.quality < 0.8
    # a prior half way between the two fits tells nothing: still ambiguous
    assert est.estimate(img, 0, prior=prior_at(x, y, yaw + math.pi / 2)).reason == "ambiguous"


@pytest.mark.parametrize("appearance", ["dark", "bright"])
def test_square_block_is_ambiguous_without_a_prior(rig, appearance):
    site = Site(3.0, blocks=(Block("S", SQUARE, appearance),))
    img = render_frame(rig, site, 2.1, 0.0, 0.3, NOISY)
    got = BlockEstimator(rig, site, {"heading_cue": False}).estimate(img, 0)
    assert not got and got.reason == "ambiguous"


def test_without_a_prior_a_symmetric_block_waits_for_the_marker_beside_it(rig, monkeypatch):
    """A symmetric block can only be ambiguous without a prior: with a marker in view
    the marker fixes the frame and the block is not measured; with the marker's id not
    in the site the block is measured last and the frame is still ``ambiguous``."""
    x, y, yaw = 2.2, 0.1, math.radians(12.0)
    seen = dataclasses.replace(marker_site((7, 2.3, 0.55, 10.0)),
                               blocks=(Block("A", RECT, "dark"),))
    img = render_frame(rig, seen, x, y, yaw, NOISY)
    calls = []
    orig = BlockEstimator._block_fix
    monkeypatch.setattr(BlockEstimator, "_block_fix",
                        lambda self, *a: calls.append(1) or orig(self, *a))
    got = BlockEstimator(rig, seen, {"heading_cue": False}).estimate(img, 0)
    assert got and got.diagnostics["source"] == "marker:7" and not calls
    assert math.hypot(got.x_m - x, got.y_m - y) < 0.005
    other = dataclasses.replace(marker_site((8, 2.3, 0.55, 10.0)),
                                blocks=(Block("A", RECT, "dark"),))
    got = BlockEstimator(rig, other, {"heading_cue": False}).estimate(img, 0)
    assert not got and got.reason == "ambiguous" and calls
    assert got.diagnostics["unknown_marker_ids"] == (7,)


def test_an_asymmetric_block_needs_no_prior(rig):
    kite = np.array([[2.0, -0.2], [2.7, -0.25], [2.55, 0.2], [2.05, 0.25]])
    site = Site(3.0, blocks=(Block("K", kite, "dark"),))
    x, y, yaw = 2.1, 0.0, math.radians(-40.0)
    got = BlockEstimator(rig, site).estimate(render_frame(rig, site, x, y, yaw, NOISY), 0)
    assert got and got.diagnostics["source"] == "block:K"
    assert math.hypot(got.x_m - x, got.y_m - y) < 0.005
    assert abs(math.degrees(got.yaw_rad - yaw)) < 0.1


def test_a_partly_occluded_block_is_a_partial_block(rig):
    site = Site(3.0, blocks=(Block("A", RECT, "dark"),))
    x, y, yaw = 2.2, 0.0, 0.0
    img = render_frame(rig, site, x, y, yaw, NOISY)
    dark = img < (BLOCK_GREY + 150) / 2
    v, u = np.nonzero(dark)
    img[v.min():(v.min() + v.max()) // 2, u.min():(u.min() + u.max()) // 2] = 150
    got = BlockEstimator(rig, site, {"heading_cue": False}).estimate(
        img, 0, prior=prior_at(x, y, yaw))
    assert not got and got.reason == "partial_block"


def test_nothing_in_view_is_no_block(rig):
    site = Site(3.0, blocks=(Block("A", RECT + 20.0, "dark"),))
    img = render_frame(rig, site, 0.0, 0.0, 0.0, NOISY)
    got = BlockEstimator(rig, site).estimate(img, 0)
    assert not got and got.reason == "no_block"    # no block, no parallels in view


def test_packaged_site_localizes_and_is_registered(rig):
    site = Site.load(CONFIGS / "block" / "site.yaml")
    est = make_estimator("block", rig, site)
    assert isinstance(est, BlockEstimator)
    p = site.markers.poses[1]
    img = render_frame(rig, site, p.x_m - 0.1, p.y_m, 0.4, NOISY)
    got = est.estimate(img, 0)
    assert got and math.hypot(got.x_m - p.x_m + 0.1, got.y_m - p.y_m) < 0.01


# -- bad inputs ----------------------------------------------------------------------------
def test_bad_inputs_are_one_line_errors(rig):
    bad_size = marker_site((1, 0.0, 0.0, 0.0), size=0.2)
    zero = dataclasses.replace(bad_size.markers, poses=(MarkerPose(1, 0, 0, 0, 0.0),))
    with pytest.raises(ConfigError, match=r"markers.poses\[0\].size.*> 0"):
        BlockEstimator(rig, dataclasses.replace(bad_size, markers=zero))
    unknown = dataclasses.replace(bad_size.markers, dictionary="DICT_NOPE")
    with pytest.raises(ConfigError, match="unknown aruco dictionary"):
        BlockEstimator(rig, dataclasses.replace(bad_size, markers=unknown))
    with pytest.raises(ConfigError, match="blocks"):
        BlockEstimator(rig, Site(3.0))
    with pytest.raises(ConfigError, match="options.shape_tol"):
        BlockEstimator(rig, bad_size, BlockOptions(shape_tol=0.0))
    with pytest.raises(ConfigError, match="not convex|convex"):
        Site.from_node(_node("ceiling_height: 3\nblocks: [{id: A, corners: "
                             "[[0, 0], [1, 0], [0.2, 0.2], [0, 1]]}]\n"))


def _node(text: str):
    import tempfile
    from pathlib import Path

    from ceilkit.runtime.config.yaml import load_yaml

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "site.yaml"
        p.write_text(text)
        return load_yaml(p)


# -- heading from the ceiling's parallels ------------------------------------------------
def test_parallels_heading_is_fused_with_the_block_and_given_alone_between_blocks(rig):
    site = Site.load(CONFIGS / "block" / "site.yaml")
    est = BlockEstimator(rig, site)
    x, y, yaw = 0.55, 0.4, math.radians(17.0)            # marker 0 and the tile seams
    got = est.estimate(render_frame(rig, site, x, y, yaw, NOISY), 0)
    assert got and got.x_m is not None and got.diagnostics["parallels_fused"]
    assert got.diagnostics["parallels_n"] >= 2
    assert abs(math.degrees(got.yaw_rad - yaw)) < 0.05
    assert got.cov[2, 2] < got.diagnostics["parallels_sigma_rad"] ** 2 + 1e-18
    # between blocks: a heading-only cue, modulo a quarter turn
    x, y, yaw = -2.0, 0.0, math.radians(-33.0)
    alone = est.estimate(render_frame(rig, site, x, y, yaw, NOISY), 0)
    assert alone and alone.x_m is None and alone.diagnostics["no_fix"] == "no_block"
    assert abs(math.degrees(math.remainder(alone.yaw_rad - yaw, math.pi / 2))) < 0.05
    off = BlockEstimator(rig, site, {"parallels": False})
    assert not off.estimate(render_frame(rig, site, x, y, yaw, NOISY), 0)


def test_a_side_lost_on_the_last_edge_pass_keeps_the_previous_pass(rig):
    """Review finding (83434b6): when the window path's last edge pass finds too few
    points on a side (its narrower search about corners a pass moved), the quad is
    measured by the pass before it, as it was before 83434b6, not dropped. The
    compiled measurement (detect.measure_core) is given a last pass whose search
    cannot find any step (two samples across each side): it keeps the first pass's
    points, through the lens, which is the one-pass measurement exactly."""
    from ceilkit.runtime.estimators.block import detect
    from ceilkit.runtime.features.quads import EDGE_STEP_PX, edge_stations, sharpen_quad

    kite = np.array([[2.0, -0.2], [2.7, -0.25], [2.55, 0.2], [2.05, 0.25]])
    site = Site(3.0, blocks=(Block("K", kite, "dark"),))
    est = BlockEstimator(rig, site)
    grey = render_frame(rig, site, 2.1, 0.0, math.radians(-40.0), NOISY)
    quads = detect.find_quads(grey, True, 0.5)
    assert quads
    corners = sharpen_quad(quads[0]).corners_px
    n = est.options.edge_points
    one = detect.measure_sides(grey, corners, est.geo, n, passes=1, search_px=4.0)
    assert one is not None
    first, t = edge_stations(n, 4.0)
    blind = np.array([-0.5, 0.5])                    # no interval inside: no edge found
    out = detect.SidesOut.empty(n)
    search = detect.EdgeSearch(first, blind, t, EDGE_STEP_PX, 0)
    got = detect.measure_core(grey, corners, 2, search, *rig.camera.lens, out)
    assert got == len(one.side)
    np.testing.assert_array_equal(out.corners, one.corners_norm)
    np.testing.assert_array_equal(out.side[:got], one.side)
    # with nothing before it to fall back on, a blind pass measures nothing
    assert detect.measure_core(grey, corners, 1, search._replace(first=blind),
                               *rig.camera.lens, out) == -1


def test_a_block_cut_by_the_frame_gives_no_fix_and_the_marker_beside_it_does(rig):
    """Found on bench_all's block drive (frame 32, a scheduled global search with a
    prior): block A runs off the frame's edge, its quad still fits A's shape within
    shape_tol, and being the largest dark quad it was solved first, at an edge RMS of
    1.8 px: published with quality 0, 22 mm and 1.1 deg off (4 sigma in yaw). A fix
    whose edge RMS exceeds RMS_BAD_PX is now no fix: the marker beside it is taken."""
    from ceilkit.runtime.estimators.block.estimator import RMS_BAD_PX

    site = Site.load(CONFIGS / "block" / "site.yaml")
    x, y, yaw = 1.153333, -0.06511, 0.19550080468740974
    grey = render_frame(rig, site, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=0.8),
                        np.random.default_rng(32))
    est = BlockEstimator(rig, site, {"plane_odometry": False, "window_search": False})
    out = est.estimate(grey, 0, PoseEstimate(0, "prior", x + 4e-4, y + 3e-4, yaw + 1e-3, 1.0))
    assert out and out.diagnostics["quads"] >= 2            # block A's quad was found
    assert out.diagnostics["source"] == "marker:0"
    assert out.diagnostics["rms_px"] < RMS_BAD_PX and out.quality > 0.8
    assert math.hypot(out.x_m - x, out.y_m - y) < 0.002
    assert abs(math.degrees(math.remainder(out.yaw_rad - yaw, 2 * math.pi))) < 0.05


def test_the_quad_search_decimates_as_the_working_resolution_does():
    """One ``decimate`` (issue 35: block/detect.py had its own): the quad search's frame
    is :func:`~ceilkit.runtime.features.working.decimate`'s. On an even frame that is
    cv2's area resize of the whole frame, what the block method's own did (no change);
    on an odd one it averages whole 2x2 boxes (the last row and column dropped), so the
    factor back to full resolution is exactly 2 on both axes, where the former resize
    of 641x481 to 320x240 scaled u by 2.003 and v by 2.004 and mapped both by u's."""
    import cv2

    from ceilkit.runtime.estimators.block import detect
    from ceilkit.runtime.features.working import decimate

    even = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
    np.testing.assert_array_equal(decimate(even, detect.DECIMATE),
                                  cv2.resize(even, (320, 240), interpolation=cv2.INTER_AREA))
    odd = np.full((481, 641), 200, np.uint8)
    odd[101:241, 301:461] = 40     # a dark block: pixel edges at u 300.5, 460.5, v 100.5, 240.5
    small = decimate(odd, detect.DECIMATE)
    boxes = odd[:480, :640].reshape(240, 2, 320, 2).astype(float).mean(axis=(1, 3))
    assert small.shape == (240, 320) and np.abs(small - boxes).max() <= 0.5
    quads = detect.find_quads(odd, True, 0.5)
    assert len(quads) == 1
    got = np.sort(quads[0].corners_px, axis=0)
    want = np.array([[300.5, 100.5], [300.5, 100.5], [460.5, 240.5], [460.5, 240.5]])
    assert np.abs(got - want).max() <= 2.0     # approxPolyDP's coarse vertices
