"""Tests of runtime/estimators/honesty.py (the model checks) and of the corridor and
lights estimators refusing poses their model does not explain: the cases of issue #16
(a vent grille, a pose metres outside the site, a vanishing line 23.5 deg off), each
published before the checks (shown with the checks turned off) and refused now."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import FAILURE_REASONS, PoseEstimate
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.estimators.honesty import (
    MODEL_REASONS,
    SiteExtent,
    chi2_quantile,
    covariance_inflation,
    design_effect,
    misfit,
    outside_site,
)
from ceilkit.runtime.estimators.lights import LightsEstimator
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.io.link.nmea import encode_pose
from ceilkit.runtime.sim.render import SimOptions, render_frame

CONFIGS = Path(__file__).resolve().parents[3] / "configs"

# every model check of the corridor method turned off: what the estimator published
# before the checks existed
CORRIDOR_OFF = dict(noise_px=1e6, min_lines=0, min_spread=0.0, max_vp_elevation_deg=180.0,
                    max_vanishing_line_deg=180.0, max_heading_change_deg=180.0,
                    site_margin_m=1e9)
LIGHTS_OFF = dict(noise_px=1e6, site_margin_m=1e9)

HEADING = {"assume_heading_deg": 0.0}
"""The packaged corridor is symmetric about its centre line: its tests state the
heading, as a user may (a frame alone cannot tell it from the half turn)."""


@pytest.fixture(scope="module")
def crig() -> Rig:
    return Rig.load(CONFIGS / "corridor" / "rig.yaml")


@pytest.fixture(scope="module")
def csite() -> Site:
    return Site.load(CONFIGS / "corridor" / "site.yaml")


@pytest.fixture(scope="module")
def lrig() -> Rig:
    return Rig.load(CONFIGS / "lights" / "rig.yaml")


@pytest.fixture(scope="module")
def lsite() -> Site:
    return Site.load(CONFIGS / "lights" / "site.yaml")


def with_mount(rig: Rig, **changes) -> Rig:
    return dataclasses.replace(rig, mount=dataclasses.replace(rig.mount, **changes))


def project_segments(rig: Rig, height_m: float, segs_w, x: float, y: float, yaw: float,
                     edge_sigma_px: float = 0.0, rng=None) -> np.ndarray:
    """Pixel segments ``(N, 4)`` of ceiling segments ``((x, y), (x, y))`` in W seen from
    a vehicle pose, the visible part of each (at least 30 px); with ``edge_sigma_px``
    each endpoint is moved across the segment by that much noise."""
    cam, m = rig.camera, rig.mount
    R_wc, c = m.R_world_cam(yaw), m.camera_position(x, y, yaw)
    out = []
    for a, b in segs_w:
        t = np.linspace(0.0, 1.0, 600)[:, None]
        p = np.hstack([np.array(a) + t * (np.array(b) - np.array(a)),
                       np.full((t.size, 1), height_m)])
        px = cam.project((p - c) @ R_wc)
        ok = np.flatnonzero(np.isfinite(px[:, 0]) & cam.in_image(px, 2.0))
        if ok.size < 2:
            continue
        p1, p2 = px[ok[0]], px[ok[-1]]
        d = p2 - p1
        n = float(np.hypot(*d))
        if n < 30:
            continue
        if edge_sigma_px > 0:
            normal = np.array([-d[1], d[0]]) / n
            p1 = p1 + normal * rng.normal(0, edge_sigma_px)
            p2 = p2 + normal * rng.normal(0, edge_sigma_px)
        out.append(np.r_[p1, p2])
    return np.array(out)


def corridor_lines_w(x: float) -> list:
    """The example corridor's ceiling lines around ``x``: two seams, the lamps' long
    and short edges."""
    out = [((x - 20.0, yj), (x + 20.0, yj)) for yj in (-0.45, 0.45)]
    for yj in (-0.15, 0.15):
        out += [((-0.6 + 2.4 * k, yj), (0.6 + 2.4 * k, yj)) for k in range(-4, 8)]
    out += [((-0.6 + 1.2 * k, -0.15), (-0.6 + 1.2 * k, 0.15)) for k in range(-8, 16)]
    return out


# -- the statistics ------------------------------------------------------------------------


@pytest.mark.parametrize("p,dof,exact", [(0.999, 1, 10.828), (0.999, 3, 16.266),
                                         (0.999, 10, 29.588), (0.999, 50, 86.661),
                                         (0.95, 5, 11.070), (0.99, 100, 135.807)])
def test_chi2_quantile_against_tables(p, dof, exact):
    assert chi2_quantile(p, dof) == pytest.approx(exact, abs=1e-3)
    assert chi2_quantile(p, 0) == math.inf


def test_misfit_false_alarm_rate_on_pure_noise():
    rng = np.random.default_rng(3)
    trials, sigma = 4000, 0.7
    fails = 0
    for _ in range(trials):
        m = misfit(rng.normal(0, sigma, 24), sigma, 2)
        fails += not m.passed
        if m.reduced <= 1.0:
            assert m.inflation == 1.0
    # alpha = 1e-3: 4 expected; Wilson-Hilferty is within 1 % of the quantile
    assert fails <= 14
    m = misfit(rng.normal(0, 3 * sigma, 24), sigma, 2)
    assert not m.passed and m.reduced > 5
    assert "chi-square" in m.detail()


def test_misfit_degenerate_inputs():
    assert misfit(np.array([0.3, -0.2]), 1.0, 2).passed          # no dof: cannot test
    assert not misfit(np.array([0.1, np.nan, 0.2, 0.1]), 1.0, 2).passed
    # Huber: one gross outlier among good residuals costs linearly, not quadratically
    r = np.r_[np.zeros(40), 30.0]
    assert misfit(r, 1.0, 2, huber_px=1.0).chi2 == pytest.approx(59.0)
    assert misfit(r, 1.0, 2).chi2 == pytest.approx(900.0)


def test_design_effect_of_shared_offsets():
    rng = np.random.default_rng(5)
    groups = np.repeat(np.arange(4), 25)
    noise = rng.normal(0, 1, 100)
    assert design_effect(noise, groups) < 1.5                   # independent
    shared = np.repeat(rng.normal(0, 3, 4), 25) + 0.1 * noise
    assert design_effect(shared, groups) == pytest.approx(25.0, rel=0.05)
    assert design_effect(shared, None) == 1.0
    assert design_effect(noise, np.arange(100)) == 1.0


def test_covariance_inflation_is_one_below_and_continuous_above():
    r = np.repeat([2.0, -2.0, 1.5, -1.0], 10)
    groups = np.repeat(np.arange(4), 10)
    assert covariance_inflation(r, 1.0, 1.0, 1.0, groups) == 1.0
    assert covariance_inflation(r, 0.5, 1.0, 1.0, groups) == 1.0
    just = covariance_inflation(r, 1.0 + 1e-9, 1.0, 1.0, groups)
    assert just == pytest.approx(1.0, abs=1e-6)
    full = covariance_inflation(r, 3.0, 1.0, 1.0, groups)
    assert full > 10.0                              # Huber-hidden misfit x design effect


def test_site_extent(csite, lsite):
    ce = SiteExtent.from_site(csite)
    assert (ce.y_lo, ce.y_hi) == (-0.45, 0.45)
    assert ce.outside_m(None, 0.3) == 0.0 and ce.outside_m(None, 10.45) == pytest.approx(10.0)
    assert ce.outside_m(1e6, None) > 0            # the lamp rows bound x
    le = SiteExtent.from_site(lsite)
    assert le.x_lo == pytest.approx(-0.594) and le.y_hi == pytest.approx(5.387)
    assert outside_site(le, 5.0, 0.0, 1.5) is None
    detail = outside_site(le, 5.0, 16.4, 1.5)
    assert detail is not None and "11.01 m outside" in detail
    assert SiteExtent.from_site(Site(3.0)).outside_m(1e9, 1e9) == 0.0   # nothing bounds it


def test_model_reasons_are_failure_reasons():
    for reason in MODEL_REASONS:
        assert reason in FAILURE_REASONS


@pytest.mark.parametrize("name,value", [("noise_px", 0.0), ("misfit_alpha", 1.0),
                                        ("site_margin_m", -1.0), ("min_spread", math.nan)])
def test_bad_check_options(crig, csite, lrig, lsite, name, value):
    with pytest.raises(ConfigError, match=f"options.{name}"):
        CorridorEstimator(crig, csite, {**HEADING, name: value})
    if name in ("noise_px", "misfit_alpha", "site_margin_m"):
        with pytest.raises(ConfigError, match=f"options.{name}"):
            LightsEstimator(lrig, lsite, {name: value})


# -- the corridor method -----------------------------------------------------------------


def test_clean_corridor_fit_passes_with_its_covariance_unchanged(crig, csite):
    rng = np.random.default_rng(1)
    for pose in ((0.5, 0.1, 0.2), (1.3, -0.3, -0.5), (2.0, 0.4, 0.6)):
        segs = project_segments(crig, csite.ceiling_height_m, corridor_lines_w(pose[0]),
                                *pose, 0.3, rng)
        on = CorridorEstimator(crig, csite, HEADING).estimate_segments(segs, 0)
        off = CorridorEstimator(crig, csite, {**HEADING, **CORRIDOR_OFF}).estimate_segments(segs, 0)
        assert isinstance(on, PoseEstimate), on
        assert on.diagnostics["chi2_reduced"] <= 1.0
        assert on.diagnostics["cov_inflation"] == 1.0
        assert np.array_equal(on.cov, off.cov) and on.y_m == off.y_m
        assert abs(on.y_m - pose[1]) < 0.01


def test_vent_grille_frame_is_not_published(crig, csite):
    """One seam of the site and a grille of slats (nearly along the corridor) that the
    association takes for site lines: before the checks, a pose 0.25 m and 7 deg off
    with sigma_yaw 1.3 deg; now the slats are left out of the fit (they are not on the
    ceiling's lines: consensus.py) and the one seam is too little."""
    x, y, yaw = 0.0, -0.3, math.radians(-10)
    segs_w = [((x - 20, 0.45), (x + 20, 0.45))]
    segs_w += [((1.8, 0.9 + 0.035 * k), (2.6, 1.0 + 0.035 * k)) for k in range(8)]
    segs = project_segments(crig, csite.ceiling_height_m, segs_w, x, y, yaw)
    old = CorridorEstimator(crig, csite, {**HEADING, **CORRIDOR_OFF, "consensus": False}
                            ).estimate_segments(segs, 0)
    assert isinstance(old, PoseEstimate)
    assert old.diagnostics["n_lines_matched"] == 1 and old.diagnostics["rms_px"] > 3
    err_yaw = abs(math.degrees(wrap_pi(old.yaw_rad - yaw)))
    assert err_yaw > 2.0 and err_yaw > 3 * math.degrees(math.sqrt(old.cov[2, 2]))
    assert encode_pose(old, 0).split(b",")[3] == b"A"       # what the link used to send
    new = CorridorEstimator(crig, csite, HEADING).estimate_segments(segs, 0)
    assert not new and new.reason == "weak_geometry", new
    assert "off the site's ceiling lines" in new.detail
    assert encode_pose(new, 0).split(b",")[3] == b"V"
    # fitting every matched segment, the misfit test refuses it
    fitted = CorridorEstimator(crig, csite, {**HEADING, "consensus": False}
                               ).estimate_segments(segs, 0)
    assert not fitted and fitted.reason == "misfit", fitted
    # with the misfit test off as well, the one matched site line still refuses it
    weak = CorridorEstimator(crig, csite, {**HEADING, "noise_px": 1e6, "consensus": False}
                             ).estimate_segments(segs, 0)
    assert not weak and weak.reason == "weak_geometry", weak


def test_vanishing_line_off_the_calibrated_mount(crig, csite):
    """The camera's true tilt is 45 deg; the rig says 68.5: the vanishing line is
    23.5 deg off. Before the checks a pose was published."""
    bad = with_mount(crig, tilt_rad=math.radians(68.5))
    segs = project_segments(crig, csite.ceiling_height_m, corridor_lines_w(1.0), 1.0, 0.1,
                            0.2)
    old = CorridorEstimator(bad, csite, {**HEADING, **CORRIDOR_OFF}).estimate_segments(segs, 0)
    new = CorridorEstimator(bad, csite, HEADING).estimate_segments(segs, 0)
    assert not new, new
    if old:   # a pose was published: the vanishing line said it could not be right
        d = old.diagnostics
        off = [abs(d[k]) for k in ("vanishing_line_residual_deg", "vp_along_elevation_deg")
               if math.isfinite(d[k])]
        assert off and max(off) > 10.0, d          # one across segment: the forward VP
        only_vl = CorridorEstimator(bad, csite, {**HEADING, **CORRIDOR_OFF,
                                                 "max_vanishing_line_deg": 10.0,
                                                 "max_vp_elevation_deg": 5.0})
        r = only_vl.estimate_segments(segs, 0)
        assert not r and r.reason == "vanishing_line" and f"{max(off):.1f} deg" in r.detail
    # a smaller mount error (tilt 60 deg in the rig): published before, refused now
    bad15 = with_mount(crig, tilt_rad=math.radians(60))
    old = CorridorEstimator(bad15, csite, {**HEADING, **CORRIDOR_OFF}).estimate_segments(segs, 0)
    assert isinstance(old, PoseEstimate)
    assert old.diagnostics["vanishing_line_residual_deg"] == pytest.approx(15.0, abs=0.5)
    r = CorridorEstimator(bad15, csite, {**HEADING, "noise_px": 1e6}).estimate_segments(segs, 0)
    assert not r and r.reason == "vanishing_line", r
    assert not CorridorEstimator(bad15, csite, HEADING).estimate_segments(segs, 0)


def test_pose_outside_the_site(crig, csite):
    """The rig's lever arm typed in the wrong unit (mount y = 10 m): the lines fit, but
    the vehicle would be 10 m outside a 0.9 m wide band of ceiling lines."""
    bad = with_mount(crig, y_m=10.0)
    segs = project_segments(bad, csite.ceiling_height_m, corridor_lines_w(1.0), 1.0, -9.9,
                            0.0)
    old = CorridorEstimator(bad, csite, {**HEADING, **CORRIDOR_OFF}).estimate_segments(segs, 0)
    assert isinstance(old, PoseEstimate) and old.y_m == pytest.approx(-9.9, abs=1e-6)
    new = CorridorEstimator(bad, csite, HEADING).estimate_segments(segs, 0)
    assert not new and new.reason == "outside_site" and "9.45 m outside" in new.detail
    wide = CorridorEstimator(bad, csite, {**HEADING, "site_margin_m": 12.0}
                             ).estimate_segments(segs, 0)
    assert wide


def test_heading_check_compares_refined_and_vanishing_point_heading(crig, csite):
    rng = np.random.default_rng(2)
    segs = project_segments(crig, csite.ceiling_height_m, corridor_lines_w(1.0), 1.0, 0.1,
                            0.3, 1.0, rng)
    r = CorridorEstimator(crig, csite, HEADING).estimate_segments(segs, 0)
    assert r, r
    change = abs(r.diagnostics["heading_change_deg"])
    assert 0 < change < 2.0
    tight = CorridorEstimator(crig, csite, {**HEADING, "max_heading_change_deg": 0.5 * change})
    f = tight.estimate_segments(segs, 0)
    assert not f and f.reason == "heading_disagrees"


def test_corridor_sim_frames_pass_every_check(crig, csite):
    rng = np.random.default_rng(7)
    est = CorridorEstimator(crig, csite, HEADING)
    for x, y, yaw in ((3.0, 0.2, 0.3), (10.0, -0.5, -0.4)):
        r = est.estimate(render_frame(crig, csite, x, y, yaw, SimOptions(), rng), 0)
        assert isinstance(r, PoseEstimate), r
        assert r.diagnostics["cov_inflation"] == 1.0
        assert abs(r.y_m - y) < 0.005


# -- the lights method ---------------------------------------------------------------------


def test_lights_wrong_ceiling_height_is_a_misfit(lrig, lsite):
    """The ceiling is 3.6 m high, the site says 3.0: before the checks a pose 5 m off
    was published (quality ~0, but status A); now a misfit."""
    high = dataclasses.replace(lsite, ceiling_height_m=3.6)
    img = render_frame(lrig, high, 7.0, 0.5, 0.3, SimOptions(), np.random.default_rng(1))
    old = LightsEstimator(lrig, lsite, LIGHTS_OFF).estimate(img, 0)
    assert isinstance(old, PoseEstimate)
    assert math.hypot(old.x_m - 7.0, old.y_m - 0.5) > 1.0
    new = LightsEstimator(lrig, lsite).estimate(img, 0)
    assert not new and new.reason == "misfit", new


def test_lights_pose_outside_the_site(lrig, lsite):
    bad = with_mount(lrig, x_m=10.0)         # 10 m instead of 0.10
    img = render_frame(bad, lsite, -6.0, 0.5, 0.0, SimOptions(), np.random.default_rng(1))
    old = LightsEstimator(bad, lsite, LIGHTS_OFF).estimate(img, 0)
    assert isinstance(old, PoseEstimate) and old.x_m == pytest.approx(-6.0, abs=0.01)
    new = LightsEstimator(bad, lsite).estimate(img, 0)
    assert not new and new.reason == "outside_site"


def test_clean_lights_fit_keeps_its_covariance(lrig, lsite):
    img = render_frame(lrig, lsite, 7.0, 0.5, 0.3, SimOptions(), np.random.default_rng(4))
    on = LightsEstimator(lrig, lsite).estimate(img, 0)
    off = LightsEstimator(lrig, lsite, LIGHTS_OFF).estimate(img, 0)
    assert isinstance(on, PoseEstimate), on
    assert on.diagnostics["chi2_reduced"] <= 1.0
    assert np.array_equal(on.cov, off.cov)


def test_misfit_sum_is_the_least_squares_misfit():
    """The scalar test of summed least-squares residuals (the lights' fit) gives
    misfit's numbers: passing, failing, non-finite, no degrees of freedom."""
    from ceilkit.runtime.estimators.honesty import misfit, misfit_sum

    rng = np.random.default_rng(5)
    for n, scale in ((12, 0.5), (12, 3.0), (40, 1.0), (3, 1.0), (2, 1.0), (0, 1.0)):
        r = rng.normal(0.0, scale, n)
        a, b = misfit(r, 1.0, 3), misfit_sum(float(r @ r), n, 1.0, 3)
        assert (a.dof, a.passed, a.inflation) == (b.dof, b.passed, b.inflation)
        for name in ("chi2", "reduced", "limit", "rms_px"):
            x, y = getattr(a, name), getattr(b, name)
            assert (math.isnan(x) and math.isnan(y)) or x == pytest.approx(y, rel=1e-12)
    r = np.array([1.0, np.inf, 0.5, 0.2])
    a, b = misfit(r, 1.0, 3), misfit_sum(float(r @ r), 4, 1.0, 3)
    assert not a.passed and not b.passed and a.inflation == b.inflation == math.inf
