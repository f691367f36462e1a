"""Tests of runtime/estimators/lights/track.py: the windowed fast path with a prior, its
check and fallback to the global path, and its schedule."""

from __future__ import annotations

import math
import warnings

import lights_track_reference as reference
import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators import base
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.lights import LightsEstimator, LightsOptions
from ceilkit.runtime.estimators.lights.track import WindowTracker
from ceilkit.runtime.sim.render import SimOptions, render_frame

POSES = [(6.0, 0.5, 0.5), (12.0, 2.0, 2.8), (3.5, -2.0, -1.2), (9.0, -3.5, 1.9)]


def frame(rig, site, x, y, yaw, seed):
    return render_frame(rig, site, x, y, yaw, rng=np.random.default_rng(seed),
                        options=SimOptions(noise_sigma=2.0, blur_px=0.8))


def prior(x, y, yaw):
    return PoseEstimate(0, "track", x, y, yaw, 0.0)


def errors(est, x, y, yaw):
    return (math.hypot(est.x_m - x, est.y_m - y),
            abs(math.degrees(math.remainder(est.yaw_rad - yaw, 2 * math.pi))))


@pytest.fixture
def tracked(lights_rig, lights_site):
    return LightsEstimator(lights_rig, lights_site,
                           {"window_search": True, "window_full_every": 0})


def test_window_fix_agrees_with_global_path(lights_rig, lights_site, tracked):
    glob = LightsEstimator(lights_rig, lights_site)
    for k, (x, y, yaw) in enumerate(POSES):
        img = frame(lights_rig, lights_site, x, y, yaw, k)
        g = glob.estimate(img, 0)
        t = tracked.estimate(img, 0, prior(x + 0.03, y - 0.02, yaw + 0.01))
        assert g and t
        assert t.diagnostics["mode"] == "window"
        # the same frame: the two readings of the same lights agree to a few tenths of a mm
        assert math.hypot(t.x_m - g.x_m, t.y_m - g.y_m) < 1e-3
        assert abs(math.degrees(t.yaw_rad - g.yaw_rad)) < 0.02
        dp, dyaw = errors(t, x, y, yaw)
        assert dp < 0.005 and dyaw < 0.05
        assert t.diagnostics["inliers"] >= 3 and np.all(np.isfinite(t.cov))
        # the covariance is the refinement's: positive definite, sub-millimetre here
        assert np.all(np.linalg.eigvalsh(t.cov) > 0) and t.cov[0, 0] < 1e-5
        assert 0 < t.quality <= 1


def test_far_prior_falls_back_to_the_global_path(lights_rig, lights_site, tracked):
    x, y, yaw = POSES[1]
    img = frame(lights_rig, lights_site, x, y, yaw, 3)
    for p in (prior(x + 0.9, y - 0.8, yaw + 0.4), prior(5.0, 1.3, -1.3)):
        out = tracked.estimate(img, 0, p)
        assert out and out.diagnostics["mode"] != "window"
        dp, dyaw = errors(out, x, y, yaw)
        assert dp < 0.02 and dyaw < 0.3


def test_missing_lights_fail_the_window_check(lights_rig, lights_site):
    x, y, yaw = POSES[0]
    img = frame(lights_rig, lights_site, x, y, yaw, 4)
    est = LightsEstimator(lights_rig, lights_site, {"window_search": True})
    w: WindowTracker = est.windows
    assert w.observe(img, x, y, yaw) is not None
    # the lights switched off (the image flattened): the windows find nothing
    flat = np.full_like(img, int(np.median(img)))
    assert w.observe(flat, x, y, yaw) is None
    out = est.estimate(flat, 0, prior(x, y, yaw))
    assert not out


def test_a_light_cut_by_its_window_border_is_not_found(lights_rig, lights_site):
    # the window check's border contact: a light whose bright part reaches its window's
    # border (cut off, or a neighbour's) does not count, one wholly inside does
    x, y, yaw = POSES[0]
    img = frame(lights_rig, lights_site, x, y, yaw, 5)
    w: WindowTracker = LightsEstimator(lights_rig, lights_site,
                                       {"window_search": True}).windows
    idx, px, m, corner, half = w._predict(x, y, yaw)
    _, good, _ = w._measure(img, corner, half, m)
    assert good.all()
    shifted = corner.copy()
    shifted[0] += half          # the first window's corner moved onto its light's centre
    _, good2, _ = w._measure(img, shifted, half, m)
    assert not good2[0] and good2[1:].all()


def test_prediction_table_agrees_with_projection(lights_rig, lights_site):
    """The windows' places from the prediction table (a lookup) are the projected
    lights' pixels to a few hundredths of a pixel, for the lights the visibility
    table reports."""
    from ceilkit.runtime.estimators.lights.rays import project_lights

    est = LightsEstimator(lights_rig, lights_site, {"window_search": True})
    w: WindowTracker = est.windows
    rng = np.random.default_rng(7)
    worst, n = 0.0, 0
    for _ in range(30):
        x, y, yaw = rng.uniform(1, 17), rng.uniform(-4, 4), rng.uniform(-3, 3)
        pred = w._predict(x, y, yaw)
        if pred is None:
            continue
        idx, px, m, corner, half = pred
        assert np.array_equal(idx, np.flatnonzero(est.visibility(x, y, yaw)))
        exact = project_lights(lights_rig, 3.0, est.lights_w[idx], x, y, yaw)
        worst = max(worst, float(np.abs(px - exact).max()))
        n += idx.size
        assert np.all(corner >= 0) and np.all(corner + 2 * half < (640, 480))
    assert n > 100 and worst < 0.1, (n, worst)


def test_schedule_runs_a_global_search(lights_rig, lights_site):
    est = LightsEstimator(lights_rig, lights_site,
                          {"window_search": True, "window_full_every": 2})
    x, y, yaw = POSES[2]
    img = frame(lights_rig, lights_site, x, y, yaw, 5)
    modes = [est.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] for _ in range(6)]
    assert modes == ["window", "window", "about_prior", "window", "window", "about_prior"]


def test_on_by_default_and_not_without_prior(lights_rig, lights_site, tracked):
    x, y, yaw = POSES[3]
    img = frame(lights_rig, lights_site, x, y, yaw, 6)
    default = LightsEstimator(lights_rig, lights_site)   # issue 38: the window search on
    assert default.windows is not None and default.options.window_full_every == 30
    assert default.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] == "window"
    plain = LightsEstimator(lights_rig, lights_site, {"window_search": False})
    assert plain.windows is None
    assert plain.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] == "about_prior"
    assert tracked.estimate(img, 0).diagnostics["mode"] == "global"
    # a prior without x (a corridor's) is not a full prior: the global path runs
    out = tracked.estimate(img, 0, PoseEstimate(0, "track", None, y, yaw, 0.0))
    assert out.diagnostics["mode"] != "window"


def test_window_options_from_cli_strings(lights_rig, lights_site):
    est = LightsEstimator(lights_rig, lights_site,
                          {"window_search": "true", "window_px": "6", "window_full_every": "10"})
    assert est.options.window_search and est.options.window_px == 6.0
    assert est.options.window_full_every == 10
    assert est.windows is not None and est.windows.window_px == 6.0


def test_the_old_track_names_are_deprecated_aliases(lights_rig, lights_site, monkeypatch):
    """``track``, ``track_window_px``, ``track_full_every`` (issue 35: "track" also names
    the tracker) are read as the window-search options, each noted once per run with
    its new key; an option given by both names is an error naming the new one."""
    monkeypatch.setattr(base, "_NOTED", set())
    old = {"track": "false", "track_window_px": "6", "track_full_every": "10"}
    with pytest.warns(FutureWarning) as notes:
        est = LightsEstimator(lights_rig, lights_site, old)
    assert sorted(str(n.message) for n in notes) == [
        "option 'track' is deprecated: use 'window_search'",
        "option 'track_full_every' is deprecated: use 'window_full_every'",
        "option 'track_window_px' is deprecated: use 'window_px'"]
    assert est.options == LightsOptions.from_mapping(
        {"window_search": "false", "window_px": "6", "window_full_every": "10"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")       # once per run: not noted again
        assert LightsEstimator(lights_rig, lights_site, old).options == est.options
    with pytest.raises(ConfigError, match="options.window_search"):
        LightsOptions.from_mapping({"track": "true", "window_search": "false"})


def test_compiled_window_fix_equals_the_array_reading(lights_rig, lights_site):
    """The compiled fix (one call from the prior to the refined pose) decides as the
    array functions it stands for (tests/lights_track_reference.py)
    and gives their numbers: priors near and far, lights cut by the frame's border,
    a window moved off its light."""
    est = LightsEstimator(lights_rig, lights_site, {"window_search": True})
    w: WindowTracker = est.windows
    rng = np.random.default_rng(11)
    fixes = refused = 0
    for k in range(12):
        x, y, yaw = rng.uniform(1, 17), rng.uniform(-4, 4), rng.uniform(-3, 3)
        img = frame(lights_rig, lights_site, x, y, yaw, 20 + k)
        for err in (0.0, 0.03, 0.3):
            px, py, pyaw = x + rng.normal(0, err), y + rng.normal(0, err), yaw + rng.normal(0, err)
            a = w.observe(img, px, py, pyaw)
            b = reference.observe(w, img, px, py, pyaw)
            assert (a is None) == (b is None), (k, err)
            if a is None:
                refused += 1
                continue
            fixes += 1
            x_b, y_b, yaw_b, cov_b, res_b, cen_b, pairs_b, m_b, found_b, pred_b = b
            # the same pose to float rounding carried through three Gauss-Newton steps
            assert abs(a.x_m - x_b) < 1e-6 and abs(a.y_m - y_b) < 1e-6
            assert abs(a.yaw_rad - yaw_b) < 1e-7
            np.testing.assert_allclose(a.cov, cov_b, rtol=1e-4)
            np.testing.assert_allclose(a.res_px, res_b, atol=1e-4)
            np.testing.assert_allclose(a.centroids_px, cen_b, atol=1e-9)
            np.testing.assert_allclose(a.predicted_px, pred_b, atol=1e-9)
            assert np.array_equal(a.pairs, pairs_b)
            assert (a.predicted, a.found) == (m_b, found_b)
    assert fixes >= 20 and refused >= 3, (fixes, refused)
