"""Tests of runtime/estimators/corridor/: the formulas (geometry) on exactly projected
lines, the association, the stages against independent forms, noise sweeps, simulated
frames, failures and the prior."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Corridor, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import AMBIGUOUS, PoseEstimate, Provenance
from ceilkit.runtime.estimators.corridor import (
    CorridorEstimator,
    CorridorOptions,
    match_offsets,
    visible_along_lines,
)
from ceilkit.runtime.estimators.corridor.association import AMBIGUITY_RATIO, gauss
from ceilkit.runtime.estimators.corridor.estimator import _median_finite
from ceilkit.runtime.estimators.corridor.frame import frame_lines
from ceilkit.runtime.estimators.corridor.geometry import (
    along_offsets,
    fit_pan,
    level_normals,
    mount_from_vanishing_line,
    vanishing_angles,
    vanishing_directions,
)
from ceilkit.runtime.estimators.corridor.hypotheses import families
from ceilkit.runtime.estimators.corridor.refine import gn_inputs, residuals
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.features.lines import fit_line, segment_lines
from ceilkit.runtime.geometry.rotations import R_level_cam, rot_z, wrap_pi
from ceilkit.runtime.sim import render as sim

HEADING = {"assume_heading_deg": 0.0}
"""The packaged corridor is symmetric about its centre line: a frame alone cannot tell
its heading from the half turn. The accuracy tests state the heading, as a user may."""

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "corridor"


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.load(CONFIGS / "rig.yaml")


@pytest.fixture(scope="module")
def site() -> Site:
    return Site.load(CONFIGS / "site.yaml")


def ceiling_segments_w(site: Site, x: float) -> list[tuple[tuple[float, float], ...]]:
    """World segments ((x, y), (x, y)) of the example site around ``x``."""
    out = []
    for yj in site.corridor.lines_along_m:
        if abs(yj) < 0.2:   # lamp long edges
            out += [((-0.6 + 2.4 * k, yj), (0.6 + 2.4 * k, yj)) for k in range(-8, 10)]
        else:               # seams
            out.append(((x - 20.0, yj), (x + 20.0, yj)))
    out += [((-0.6 + 1.2 * k, -0.15), (-0.6 + 1.2 * k, 0.15)) for k in range(-16, 20)]
    return out


def exact_segments(rig: Rig, site: Site, x: float, y: float, yaw: float,
                   edge_sigma_px: float = 0.0, rng: np.random.Generator | None = None
                   ) -> np.ndarray:
    """Pixel segments ``(N, 4)`` of the ceiling lines, projected exactly; with
    ``edge_sigma_px`` the edge points (every 2 px) are perturbed and refitted by
    least squares, as in the paper's simulations."""
    cam, m = rig.camera, rig.mount
    R_wc, C = m.R_world_cam(yaw), m.camera_position(x, y, yaw)
    out = []
    for a, b in ceiling_segments_w(site, x):
        t = np.linspace(0.0, 1.0, 1500)[:, None]
        P = np.hstack([np.array(a) + t * (np.array(b) - np.array(a)),
                       np.full((t.size, 1), site.ceiling_height_m)])
        px = cam.project((P - C) @ R_wc)
        ok = np.isfinite(px[:, 0]) & cam.in_image(px, 2.0)
        if np.count_nonzero(ok) < 2:
            continue
        i = np.flatnonzero(ok)
        p1, p2 = px[i[0]], px[i[-1]]
        length = float(np.hypot(*(p2 - p1)))
        if length < 30:
            continue
        if edge_sigma_px > 0:
            xy = cam.unproject(np.array([p1, p2]))
            s = np.linspace(0, 1, int(length / 2))[:, None]
            pts = cam.distort(xy[0] + s * (xy[1] - xy[0]))
            pts = pts + rng.normal(0.0, edge_sigma_px, pts.shape)
            line = fit_line(pts)
            p1 = p1 - (p1 @ line[:2] + line[2]) * line[:2]
            p2 = p2 - (p2 @ line[:2] + line[2]) * line[:2]
        out.append(np.r_[p1, p2])
    return np.array(out)


# -- pure geometry ---------------------------------------------------------------------


def test_vanishing_directions_lie_on_the_ceiling_vanishing_line():
    M = R_level_cam(math.radians(45), math.radians(3))
    for psi in (-1.0, 0.0, 0.4):
        va, vb = vanishing_directions(psi, M)
        assert abs(M[2] @ va) < 1e-12 and abs(M[2] @ vb) < 1e-12
        assert abs(np.dot(va, vb)) < 1e-12
        c, s = math.cos(psi), math.sin(psi)         # R^T (c, -s, 0), R^T (s, c, 0)
        assert np.allclose(va, M.T @ [c, -s, 0.0], atol=1e-15)
        assert np.allclose(vb, M.T @ [s, c, 0.0], atol=1e-15)


def test_fit_pan_exact_on_lines_through_the_vanishing_points():
    M = R_level_cam(math.radians(50), math.radians(-2))
    rng = np.random.default_rng(0)
    psi = 0.3
    va, vb = vanishing_directions(psi, M)
    la = np.cross(rng.normal(size=(5, 3)), va)
    lb = np.cross(rng.normal(size=(4, 3)), vb)
    q = np.vstack([level_normals(la, M), level_normals(lb, M)])
    got = fit_pan(q, np.r_[np.ones(5), np.zeros(4)], np.r_[np.zeros(5), np.ones(4)])
    assert abs(math.remainder(got - psi, math.pi)) < 1e-12
    assert -math.pi <= got < math.pi


def test_mount_from_vanishing_line_round_trip():
    for tilt, swing in ((45.0, 1.0), (80.0, -7.0), (30.0, 0.0)):
        M = R_level_cam(math.radians(tilt), math.radians(swing))
        t, s = mount_from_vanishing_line(-M[2])
        assert math.degrees(t) == pytest.approx(tilt, abs=1e-9)
        assert math.degrees(s) == pytest.approx(swing, abs=1e-9)


def test_along_offsets_match_the_world(rig, site):
    x, y, yaw = 0.4, 0.12, 0.2
    segs = exact_segments(rig, site, x, y, yaw)
    lines = segment_lines(np.hstack([rig.camera.unproject(segs[:, :2]),
                                     rig.camera.unproject(segs[:, 2:])]))
    psi = yaw + rig.mount.pan_rad
    cy = rig.mount.camera_position(x, y, yaw)[1]
    q = level_normals(lines, rig.mount.R_level_cam)
    assert np.allclose(q, lines @ rig.mount.R_level_cam.T, atol=1e-15)
    h = site.ceiling_height_m - rig.mount.z_m
    offs, n_y = along_offsets(q, psi, h)
    n = q @ rot_z(psi).T                                       # the world normals
    assert np.allclose(n_y, n[:, 1], atol=1e-15)
    fin = np.abs(n[:, 1]) > 1e-12
    assert np.allclose(offs[fin], -n[fin, 2] * h / n[fin, 1], rtol=1e-12)
    near = [min(abs(o + cy - yj) for yj in site.corridor.lines_along_m) for o in offs]
    assert sum(d < 1e-9 for d in near) >= 4


def test_match_offsets_tolerates_missing_extra_and_shift():
    ys = np.array([-0.45, -0.15, 0.15, 0.45])
    c = 0.37
    # lines 0, 2 and 3 (1 missing: the gaps 0.6, 0.3 fit one shift only) and an extra
    obs = np.array([-0.45, 0.15, 0.45, 1.2]) - c + np.array([0.003, -0.002, 0.001, 0.0])
    m = match_offsets(obs, np.ones(4), ys, 0.07)
    assert m.shift_m == pytest.approx(c, abs=0.003)
    assert m.assign.tolist() == [0, 2, 3, -1]
    assert m.n_lines == 3
    assert m.runner_up is None or m.runner_up[0] < AMBIGUITY_RATIO * m.score
    # three lines evenly spaced like the site's fit two shifts equally: a tie, reported
    obs = np.array([-0.15, 0.15, 0.45]) - c
    m = match_offsets(obs, np.ones(3), ys, 0.07)
    assert m.runner_up is not None and m.runner_up[0] == pytest.approx(m.score)
    assert {round(m.shift_m, 6), round(m.runner_up[2], 6)} == {0.07, 0.37}


def test_match_offsets_edge_kinds_break_the_spacing_tie():
    ys = np.array([-0.45, -0.15, 0.15, 0.45])
    site_kind = np.array([0.0, 1.0, -1.0, 0.0])     # seam, lamp edges (lamp between), seam
    obs = np.array([-0.15, 0.15]) - 0.1              # two lines 0.3 apart: three fits
    m = match_offsets(obs, np.ones(2), ys, 0.07)
    assert m.runner_up is not None and m.runner_up[0] >= AMBIGUITY_RATIO * m.score  # a tie
    # the two lamp edges: steps, the lamp (bright) between them
    pol = np.array([1.0, -1.0])
    compat = (pol[:, None] == site_kind[None, :]).astype(float)
    m = match_offsets(obs, np.ones(2), ys, 0.07, compat=compat)
    assert m.shift_m == pytest.approx(0.1, abs=1e-9) and m.assign.tolist() == [1, 2]
    assert m.runner_up is None or m.runner_up[0] < 0.5 * m.score
    # a seam (thin line) and the lamp edge next to it
    compat = np.array([[1.0, 0, 0, 1.0], [0, 1.0, 0, 0]])
    m = match_offsets(np.array([-0.45, -0.15]) + 0.2, np.ones(2), ys, 0.07, compat=compat)
    assert m.shift_m == pytest.approx(-0.2, abs=1e-9) and m.assign.tolist() == [0, 1]
    assert match_offsets(obs, np.ones(2), ys, 0.07, compat=np.zeros((2, 4))) is None


def test_visible_along_lines(rig, site):
    # straight down the middle: all four lines; far to the side looking at the wall: fewer
    assert visible_along_lines(rig, site, 1.0, 0.0, 0.0, 25.6).tolist() == [True] * 4
    side = visible_along_lines(rig, site, 1.0, 0.75, math.radians(40), 25.6)
    assert not side[0] and side[3]
    # a lamp edge is seen only where its lamps are: none at x far past the last lamp
    far = visible_along_lines(rig, site, 500.0, 0.0, 0.0, 25.6)
    assert far.tolist() == [True, False, False, True]


def test_match_offsets_prior_breaks_a_tie():
    ys = np.array([-0.45, -0.15, 0.15, 0.45])
    obs = np.array([-0.15, 0.15]) - 0.1          # fits c = 0.1, 0.4 and -0.2 equally
    for prior in (0.1, 0.4, -0.2):
        m = match_offsets(obs, np.ones(2), ys, 0.07, prior_shift_m=prior)
        assert m.shift_m == pytest.approx(prior, abs=1e-9)


def test_median_finite_matches_numpy():
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 8, 17):
        a = rng.normal(size=n)
        assert _median_finite(a) == float(np.median(a))
        b = np.concatenate([a, [np.nan, np.inf]])
        assert _median_finite(b) == float(np.median(a))
    assert math.isnan(_median_finite(np.array([np.nan, np.inf])))
    assert math.isnan(_median_finite(np.zeros(0)))


def test_gauss_is_exp_above_its_floor():
    z = np.linspace(-37.0, 37.0, 2001)
    assert np.array_equal(gauss(z), np.exp(-0.5 * z ** 2))
    far = np.array([38.0, -60.0, 1e6, np.inf])
    g = gauss(far)
    assert np.all(g > 0) and np.all(g <= np.exp(-700.0)) and 1.0 + g[0] == 1.0


def test_estimator_stages_agree_with_independent_forms(rig, site):
    """The frame stage's lines and normals, the vanishing angles and the family gate
    agree with independent forms, and the Gauss-Newton Jacobian with finite
    differences."""
    est = CorridorEstimator(rig, site, HEADING)
    setup = est.setup
    M = setup.R_level_cam
    x, y, yaw = 0.7, 0.2, 0.3
    segs_px = exact_segments(rig, site, x, y, yaw)
    segs = est.rig.camera.unproject(segs_px.reshape(-1, 2)).reshape(-1, 4)
    fr = frame_lines(segs, np.full(segs.shape[0], np.nan), setup, est.angle_tol_rad, 2.5)
    assert np.allclose(fr.lines, segment_lines(segs), atol=1e-15)
    assert np.allclose(fr.q, fr.lines @ M.T, atol=1e-15)
    mids = 0.5 * (segs[:, :2] + segs[:, 2:])
    for psi in (-0.4, 0.3, 2.0):
        va, vb = vanishing_directions(psi, M)
        assert vanishing_directions(psi, setup.R_rows) == (va, vb)
        ang, den = vanishing_angles(psi, setup.R_rows, fr.lines_t, fr.mx, fr.my)
        for row, v in enumerate((np.array(va), np.array(vb))):
            # angle between each segment and the line from its midpoint to v
            ref_den = np.hypot(v[0] - v[2] * mids[:, 0], v[1] - v[2] * mids[:, 1])
            ref = np.abs(fr.lines @ v) / np.maximum(ref_den, 1e-12)
            assert np.allclose(ang[row], ref, atol=1e-15)
        assert np.all(den > 0)
    psi = wrap_pi(yaw + rig.mount.pan_rad)
    ang = vanishing_angles(psi, setup.R_rows, fr.lines_t, fr.mx, fr.my)[0]
    along, across = families(ang, est.angle_tol_rad)
    assert np.count_nonzero(along) >= 3 and np.count_nonzero(across) >= 2
    assert not np.any(along & across)
    # every along segment on its site line (the nearest to its true offset)
    offs = along_offsets(fr.q[along], psi, setup.ceiling_above_cam_m)[0]
    cy = y + float((rot_z(yaw) @ rig.mount.t_vehicle_cam)[1])
    assign = np.full(segs.shape[0], -1)
    assign[along] = np.argmin(np.abs(offs[:, None] + cy - setup.site_y[None, :]), axis=1)
    gd = gn_inputs(fr, along, across, assign, setup)
    A = residuals(psi, cy, gd, setup)
    assert A.shape == (2 * np.count_nonzero(along) + np.count_nonzero(across), 3)
    assert np.max(np.abs(A[:, 2])) < 1e-6                       # exact lines: px
    for k, (dp, dc) in enumerate(((1e-6, 0.0), (0.0, 1e-6))):
        num = (residuals(psi + dp, cy + dc, gd, setup)[:, 2]
               - residuals(psi - dp, cy - dc, gd, setup)[:, 2]) / 2e-6
        assert np.allclose(A[:, k], num, rtol=1e-5, atol=1e-3)


# -- the estimator on exact and noisy lines ------------------------------------------------


@pytest.mark.parametrize("pose", [(0.3, 0.1, 0.2), (1.0, -0.3, -0.5), (2.0, 0.0, 0.0),
                                  (0.7, 0.25, math.radians(40)), (1.7, -0.2, math.radians(-40))])
def test_noise_free_exactness(rig, site, pose):
    x, y, yaw = pose
    est = CorridorEstimator(rig, site, HEADING)
    r = est.estimate_segments(exact_segments(rig, site, x, y, yaw), 7)
    assert isinstance(r, PoseEstimate) and r.x_m is None and r.t_ns == 7
    assert abs(wrap_pi(r.yaw_rad - yaw)) < 1e-6
    assert abs(r.y_m - y) < 1e-6
    assert r.lateral_m == pytest.approx(r.y_m - site.corridor.axis_y_m)
    assert r.diagnostics["vp_along_elevation_deg"] < 1e-6
    if r.diagnostics["n_across"] >= 2:
        assert r.diagnostics["vanishing_line_residual_deg"] < 1e-6
        assert r.diagnostics["implied_tilt_deg"] == pytest.approx(45.0, abs=1e-6)
    assert np.isinf(r.cov[0, 0]) and r.cov[1, 1] >= 0 and r.cov[2, 2] >= 0
    assert 0.0 <= r.quality <= 1.0


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_edge_point_noise_sweep(rig, site, sigma):
    rng = np.random.default_rng(int(sigma * 10))
    est = CorridorEstimator(rig, site, HEADING)
    dyaw, dy, n_along, zs = [], [], [], []
    for yaw in np.radians([-40, -20, 0, 20, 40]):
        for y in (-0.4, 0.0, 0.4):
            r = est.estimate_segments(
                exact_segments(rig, site, 1.0, y, yaw, sigma, rng), 0)
            if not r:   # too few lines in view to tell the lateral shift
                assert r.reason in ("ambiguous", "too_few_lines"), r
                continue
            dyaw.append(abs(math.degrees(wrap_pi(r.yaw_rad - yaw))))
            dy.append(abs(r.y_m - y))
            n_along.append(r.diagnostics["n_along"])
            zs += [abs(wrap_pi(r.yaw_rad - yaw)) / math.sqrt(r.cov[2, 2]),
                   abs(r.y_m - y) / math.sqrt(r.cov[1, 1])]
    assert len(dy) >= 12
    # accuracy degrades with the noise but stays far inside the paper's figures
    assert np.median(dyaw) < 0.05 * sigma and np.median(dy) < 0.005 * sigma
    assert max(dy) < 0.03 * sigma
    # frames with many lines are tight; sparse ones (2 forward segments) are within
    # their reported covariance
    assert max(e for e, n in zip(dyaw, n_along, strict=True) if n >= 4) < 0.25 * sigma
    assert max(zs) < 5.0


def test_prior_resolves_the_half_turn(rig, site):
    """The packaged corridor is symmetric about its centre line: without a prior the
    frame is ambiguous, carrying both poses; a prior (or the stated heading) chooses,
    and the pose says so (Provenance.PRIOR, with the twin it ruled out)."""
    x, y, yaw = 0.5, 0.1, math.radians(170)
    segs = exact_segments(rig, site, x, y, yaw)
    est = CorridorEstimator(rig, site)
    prior = PoseEstimate(0, "tracker", x, y + 0.05, math.radians(165), 1.0)
    r = est.estimate_segments(segs, 0, prior=prior)
    assert abs(wrap_pi(r.yaw_rad - yaw)) < 1e-6 and abs(r.y_m - y) < 1e-6
    assert r.provenance is Provenance.PRIOR and not r.singled_out
    assert [h.label for h in r.hypotheses] == ["chosen", "half_turn"]
    r0 = est.estimate_segments(segs, 0)           # no prior: both, never one assumed
    assert not r0 and r0.reason == AMBIGUOUS
    got = sorted((round(math.degrees(h.yaw_rad)), round(h.y_m, 6)) for h in r0.hypotheses)
    twin_y = -y          # the camera mirrored about the centre line, turned a half turn
    assert got == sorted([(170, round(y, 6)), (-10, round(twin_y, 6))])
    assert sum(h.weight for h in r0.hypotheses) == pytest.approx(1.0)
    stated = CorridorEstimator(rig, site, {**HEADING, "assume_heading_deg": 180.0})
    r1 = stated.estimate_segments(segs, 0)
    assert r1 and abs(wrap_pi(r1.yaw_rad - yaw)) < 1e-6
    assert r1.provenance is Provenance.PRIOR    # chosen by the statement, not the frame


def test_family_choice_beyond_45_degrees(rig, site):
    # the paper's |pan| <= 45 deg rule would pick the across lines here
    x, y, yaw = 0.9, -0.4, math.radians(55)
    segs = exact_segments(rig, site, x, y, yaw)
    r = CorridorEstimator(rig, site, HEADING).estimate_segments(segs, 0)
    assert r and abs(wrap_pi(r.yaw_rad - yaw)) < 1e-6


# -- frames ----------------------------------------------------------------------------------


def test_blank_saturated_featureless_and_bad_frames(rig, site):
    est = CorridorEstimator(rig, site, HEADING)
    h, w = rig.camera.height, rig.camera.width
    rng = np.random.default_rng(3)
    assert est.estimate(np.zeros((h, w), np.uint8), 1).reason == "blank_frame"
    assert est.estimate(np.full((h, w), 255, np.uint8), 1).reason == "saturated_frame"
    flat = np.clip(128 + rng.normal(0, 2.0, (h, w)), 0, 255).astype(np.uint8)
    r = est.estimate(flat, 1)
    assert not r and r.reason in ("blank_frame", "too_few_lines", "no_ceiling_lines")
    blobs = np.clip(128 + 40 * np.sin(np.arange(w) / 9.0)[None, :] * np.sin(
        np.arange(h) / 7.0)[:, None] + rng.normal(0, 2, (h, w)), 0, 255).astype(np.uint8)
    assert not est.estimate(blobs, 1)
    assert est.estimate(np.zeros((10, 10), np.uint8), 1).reason == "bad_frame"


@pytest.mark.parametrize("name", ["corridor", "paper-corridor"])
def test_both_corridor_methods_check_options_and_site(rig, site, name):
    own = {"corridor": "detector", "paper-corridor": "hough_threshold"}[name]
    with pytest.raises(ConfigError, match=r"options\.bogus: unknown option .*" + own):
        make_estimator(name, rig, site, {"bogus": 1})
    with pytest.raises(ConfigError, match="needs a `corridor` section"):
        make_estimator(name, rig, Site(2.8, lights_m=np.array([[0.0, 0.0], [1.0, 0.0]])))


def test_options_and_site_are_checked(rig, site):
    with pytest.raises(ConfigError):
        CorridorEstimator(rig, site, {**HEADING, "bogus": 1})
    with pytest.raises(ConfigError):
        CorridorEstimator(rig, Site(2.8))
    with pytest.raises(ConfigError):
        CorridorEstimator(rig, site, {**HEADING, "detector": "nope"})
    with pytest.raises(ConfigError):   # ceiling below the camera
        CorridorEstimator(rig, Site(0.5, Corridor((-0.15, 0.15))))
    assert make_estimator("corridor", rig, site).name == "corridor"
    with pytest.raises(ConfigError, match=r"options\.max_segments"):
        CorridorEstimator(rig, site, {**HEADING, "max_segments": "many"})
    with pytest.raises(ConfigError, match="takes CorridorOptions"):
        CorridorEstimator(rig, site, object())


def test_options_defaults_and_strings(rig, site):
    """``None`` defaults resolve as documented; CLI strings are coerced."""
    est = CorridorEstimator(rig, site)
    assert est.detector.min_length_px == pytest.approx(0.04 * rig.camera.width)
    assert est.match_tol_m == pytest.approx(0.075)      # a quarter of the 0.3 m spacing
    est = CorridorEstimator(rig, site, {"min_length_px": "40", "match_tol_m": "0.05",
                                        "edge_fit": "false", "detector": "lsd"})
    assert est.options == CorridorOptions(min_length_px=40.0, match_tol_m=0.05,
                                          edge_fit=False, detector="lsd")
    assert est.detector.min_length_px == 40.0 and est.match_tol_m == 0.05
    assert est.estimate(np.zeros((10, 10), np.uint8), 1).reason == "bad_frame"


def test_simulated_frames(rig, site):
    """Small frames from the simulator: accuracy well inside the issue's targets (which
    are for 640x480: a 320x240 frame has half the resolution)."""
    small = rig.__class__(rig.camera.scaled(320, 240), rig.mount)
    est = CorridorEstimator(small, site, HEADING)
    rng = np.random.default_rng(11)
    dyaw, dy = [], []
    for x, y, yaw in ((0.2, 0.05, 0.1), (1.1, -0.25, -0.45), (2.0, 0.3, 0.5), (0.7, -0.1, -0.1)):
        img = sim.render_frame(small, site, x, y, yaw, rng=rng)
        r = est.estimate(img, 0)
        assert r, r
        dyaw.append(abs(math.degrees(wrap_pi(r.yaw_rad - yaw))))
        dy.append(abs(r.y_m - y))
    assert max(dyaw) < 0.3 and max(dy) < 0.02


def test_blurred_frames_keep_their_accuracy(rig, site):
    """A softer lens (blur 1.5 px instead of 0.8): the seams' edges are taken for their
    middles (refine_undistorted's second look), so heading and lateral stay within
    a fifth of the issue's targets."""
    est = CorridorEstimator(rig, site, HEADING)
    rng = np.random.default_rng(1)
    dyaw, dy = [], []
    for _ in range(8):
        x, y, yaw = rng.uniform(0, 3), rng.uniform(-0.8, 0.8), math.radians(rng.uniform(-40, 40))
        img = sim.render_frame(rig, site, x, y, yaw,
                               options=sim.SimOptions(noise_sigma=2.0, blur_px=1.5), rng=rng)
        r = est.estimate(img, 0)
        assert r, r
        dyaw.append(abs(math.degrees(wrap_pi(r.yaw_rad - yaw))))
        dy.append(abs(r.y_m - y))
    assert np.median(dyaw) < 0.01 and max(dyaw) < 0.03
    assert np.median(dy) < 1e-3 and max(dy) < 3e-3


@pytest.mark.parametrize("seed", [1, 4])
def test_random_poses_without_prior_meet_the_targets(rig, site, seed):
    """640x480 frames, noise 2, blur 0.8 (the issue's conditions), heading +-40 deg across
    the lateral range, no prior: every frame with two or more forward lines in view is
    estimated (no "ambiguous" on the packaged site) and the errors are inside the
    issue's targets with room (median heading <= 0.05 deg, lateral <= 5 mm)."""
    rng = np.random.default_rng(seed)
    n = 20
    poses = np.stack([rng.uniform(0, 3, n), rng.uniform(-0.8, 0.8, n),
                      np.radians(rng.uniform(-40, 40, n))], axis=1)
    est = CorridorEstimator(rig, site, HEADING)
    dyaw, dy, signed = [], [], []
    for x, y, yaw in poses:
        img = sim.render_frame(rig, site, x, y, yaw, sim.SimOptions(noise_sigma=2.0,
                                                                      blur_px=0.8), rng)
        in_view = visible_along_lines(rig, site, x, y, yaw, est.detector.min_length_px)
        r = est.estimate(img, 0)
        if np.count_nonzero(in_view) >= 2:
            assert r, (x, y, yaw, r)
        if r:
            e = math.degrees(wrap_pi(r.yaw_rad - yaw))
            dyaw.append(abs(e))
            signed.append(e)
            dy.append(abs(r.y_m - y) * 1e3)
    assert len(dyaw) == n
    assert max(dyaw) < 0.05 and np.median(dyaw) < 0.02 and abs(np.mean(signed)) < 0.01
    assert max(dy) < 5.0 and np.median(dy) < 2.0


def test_clutter_frames(rig, site):
    """Wall edges, door frames and pipes along the ceiling's edges: near the walls, the
    pipes must not be taken for lamp edges or seams."""
    rng = np.random.default_rng(6)
    est = CorridorEstimator(rig, site, HEADING)
    opts = sim.SimOptions(clutter=True)
    for x, y, yaw in ((0.465, 0.731, 0.68), (2.188, -0.719, -0.639), (0.9, 0.676, 0.617),
                      (1.5, 0.0, 0.3)):
        r = est.estimate(sim.render_frame(rig, site, x, y, yaw, opts, rng), 0)
        assert r, r
        assert abs(math.degrees(wrap_pi(r.yaw_rad - yaw))) < 0.1 and abs(r.y_m - y) < 0.01


def test_coarse_search_falls_back_to_full_resolution(rig, site):
    """The coarse search (segments found on the frame decimated by 2, refitted on the
    full frame) and its fallback to the full frame. Clutter frames beside the wall: on
    the first the coarse search fails and the full search's right pose stands (the
    ``fallback``); on the others the coarse search's pose is published. Two more
    frames beside the wall where the coarse search's pose has a quality below 0.5:
    0.9 m off (the full search then fails its model check: nothing is published), and
    right (the full search publishes it at a quality of 0.5 or more)."""
    import time

    from ceilkit.runtime.estimators.corridor.estimator import COARSE_MIN_QUALITY

    rng = np.random.default_rng(6)
    est = CorridorEstimator(rig, site, HEADING)
    assert est.coarse_detector is not None and est.coarse_detector.factor == 2
    searches = []
    for x, y, yaw in ((0.465, 0.731, 0.68), (2.188, -0.719, -0.639), (0.9, 0.676, 0.617),
                      (1.5, 0.0, 0.3)):
        img = sim.render_frame(rig, site, x, y, yaw, sim.SimOptions(clutter=True), rng)
        r = est.estimate(img, 0)
        assert r and abs(r.y_m - y) < 0.01, r
        searches.append(r.diagnostics["search"])
    assert searches == ["fallback", "coarse", "coarse", "coarse"]
    opts = sim.SimOptions(clutter=True, noise_sigma=2.0, blur_px=0.8)
    for seed, (x, y, yaw), wrong in ((3, (1.292, 0.748, 0.687), True),
                                     (57, (1.307, 0.656, 0.668), False)):
        img = sim.render_frame(rig, site, x, y, yaw, opts, np.random.default_rng(seed))
        coarse = est._global(img, 0, None, time.perf_counter(), "coarse")
        assert coarse and coarse.quality < COARSE_MIN_QUALITY
        assert (abs(coarse.y_m - y) > 0.5) == wrong
        r = est.estimate(img, 0)
        assert r.diagnostics["search"] == "fallback"
        if wrong:
            assert not r, r                     # not the coarse search's wrong pose
        else:
            assert r and r.quality >= COARSE_MIN_QUALITY and abs(r.y_m - y) < 0.002


def test_coarse_search_only_where_it_applies(rig, site):
    """Off by option, without the edge fit (nothing would refit the coarse segments),
    with ``working_mpx=0``, on frames below 0.25 Mpx and where the working resolution is
    already decimated; the full-resolution search then labels its poses ``full``."""
    off = {**HEADING, "coarse_search": "false"}
    assert CorridorEstimator(rig, site, off).coarse_detector is None
    assert CorridorEstimator(rig, site, {**HEADING, "edge_fit": False}).coarse_detector is None
    assert CorridorEstimator(rig, site, {**HEADING, "working_mpx": 0}).coarse_detector is None
    small = rig.__class__(rig.camera.scaled(320, 240), rig.mount)
    assert CorridorEstimator(small, site, HEADING).coarse_detector is None
    big = rig.__class__(rig.camera.scaled(1920, 1440), rig.mount)
    est = CorridorEstimator(big, site, HEADING)
    assert est.detector.factor == 2 and est.coarse_detector is None
    x, y, yaw = 1.0, 0.1, 0.2
    img = sim.render_frame(rig, site, x, y, yaw, rng=np.random.default_rng(1))
    r = CorridorEstimator(rig, site, {**HEADING, "coarse_search": False}).estimate(img, 0)
    assert r and r.diagnostics["search"] == "full"
    r2 = CorridorEstimator(rig, site, HEADING).estimate(img, 0)
    assert r2 and r2.diagnostics["search"] == "coarse"
    assert abs(r2.y_m - y) < 1e-3 and abs(r.y_m - y) < 1e-3


def test_a_prior_the_frames_missing_lines_contradict_gives_ambiguous(rig, site):
    """Beside the wall, with its clutter, on a 960x720 frame: a prior 1 cm off picks
    the true lateral shift (two seams matched), the runner-up three seams over pairs
    clutter with seams (three matched) and the absence test prefers it. Before, the
    estimate flipped to it: 0.90 m off at a sigma below a millimetre. Now the prior and
    the frame disagree, and the frame is ambiguous."""
    import dataclasses

    big = dataclasses.replace(rig, camera=rig.camera.scaled(960, 720))
    x, y, yaw = 0.465, 0.731, 0.68
    img = sim.render_frame(big, site, x, y, yaw, sim.SimOptions(clutter=True),
                           np.random.default_rng(0))
    est = CorridorEstimator(big, site, HEADING)
    r = est.estimate(img, 0, PoseEstimate(0, "prior", x, y + 0.01, yaw + 0.005, 1.0))
    if r:                                       # a pose, if any, must be the right one
        assert abs(r.y_m - y) < max(5 * math.sqrt(r.cov[1, 1]), 0.01), r.y_m - y
    else:
        assert r.reason == "ambiguous" and "disagree" in r.detail, r


def test_polarity_needs_the_right_kind(rig, site):
    """Exact segments with their edge kinds: a step on a seam's line or a thin line on a
    lamp edge's is not associated."""
    x, y, yaw = 0.3, 0.1, 0.2
    segs = exact_segments(rig, site, x, y, yaw)
    est = CorridorEstimator(rig, site, HEADING)
    r = est.estimate_segments(segs, 0, polarity=np.zeros(segs.shape[0]))   # all thin
    assert r and r.diagnostics["n_lines_matched"] == 2      # only the two seams
    assert abs(r.y_m - y) < 1e-6
    assert est.estimate_segments(segs, 0, polarity=np.full(segs.shape[0], np.nan))


def test_spec_recording_from_outside():
    """The fixture recording (SPEC layout, PNG frames, its own rig.yaml / site.yaml and
    truth.csv, written by `ceilcal simulate`): every frame estimated, within targets."""
    from ceilkit.runtime.io.recording import Recording
    from helpers import FIXTURES

    rec = Recording(FIXTURES / "corridor_rec")
    est = CorridorEstimator(rec.rig, rec.site, HEADING)
    dyaw, dy = [], []
    for k in range(len(rec)):
        frame = rec.frame(k)
        x, y, yaw = rec.truth.lookup(frame.t_ns)
        r = est.estimate(frame.image, frame.t_ns)
        assert r, r
        dyaw.append(abs(math.degrees(wrap_pi(r.yaw_rad - yaw))))
        dy.append(abs(r.y_m - y) * 1e3)
    assert len(dy) == len(rec) >= 8
    assert np.median(dyaw) < 0.05 and max(dyaw) < 0.15
    assert np.median(dy) < 5.0 and max(dy) < 15.0
