"""Tests of the block method's window path (option ``track``): a fix measured on the
outline the prior predicts, its check and fallback to the global path, its schedule."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Block, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.block.estimator import WINDOW, BlockEstimator
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

NOISY = SimOptions(noise_sigma=2.0, blur_px=1.0)
# poses of configs/block with a marker (0, 2) or a block (A: the hatch) fully in view
POSES = [(0.6, 0.3, 0.4), (6.7, 0.2, -2.0), (2.25, 0.05, 0.2), (3.9, -0.3, 1.2)]


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.load(CONFIGS / "block" / "rig.yaml")


@pytest.fixture(scope="module")
def site() -> Site:
    return Site.load(CONFIGS / "block" / "site.yaml")


def frame(rig, site, x, y, yaw, seed):
    return render_frame(rig, site, x, y, yaw, NOISY, np.random.default_rng(seed))


def prior(x, y, yaw):
    return PoseEstimate(0, "track", x, y, yaw, 0.0)


def tracked(rig, site, **kw):
    return BlockEstimator(rig, site, {"window_search": True, "window_full_every": 0,
                                      "plane_odometry": False, **kw})


def errors(est, x, y, yaw):
    return (math.hypot(est.x_m - x, est.y_m - y),
            abs(math.degrees(math.remainder(est.yaw_rad - yaw, 2 * math.pi))))


def test_window_fix_agrees_with_the_global_path(rig, site):
    glob = BlockEstimator(rig, site, {"plane_odometry": False, "window_search": False})
    est = tracked(rig, site)
    for k, (x, y, yaw) in enumerate(POSES):
        img = frame(rig, site, x, y, yaw, k)
        p = prior(x + 0.004, y - 0.003, yaw + 0.003)
        g, t = glob.estimate(img, 0, p), est.estimate(img, 0, p)
        assert g and t and g.x_m is not None and t.x_m is not None
        assert t.diagnostics["mode"] == WINDOW and g.diagnostics["mode"] == "global"
        assert t.diagnostics["source"] == g.diagnostics["source"]
        # two readings of the same outline: they agree to a fraction of a millimetre
        assert math.hypot(t.x_m - g.x_m, t.y_m - g.y_m) < 1e-3
        # (yaw: within 0.02 deg, or within 2 of the two readings' combined sigma)
        assert abs(t.yaw_rad - g.yaw_rad) < max(math.radians(0.02), 2 * math.sqrt(
            t.cov[2, 2] + g.cov[2, 2]))
        dp, dyaw = errors(t, x, y, yaw)
        assert dp < 0.003 and dyaw < 0.03
        assert np.all(np.linalg.eigvalsh(t.cov) > 0) and t.cov[0, 0] < 1e-5
        assert "pnp6_tilt_deg" not in t.diagnostics       # the mount check: global only


def test_a_far_prior_falls_back_to_the_global_path(rig, site):
    x, y, yaw = POSES[0]
    img = frame(rig, site, x, y, yaw, 7)
    est = tracked(rig, site)
    for p in (prior(x + 0.04, y, yaw), prior(x, y - 0.05, yaw + 0.03)):
        out = est.estimate(img, 0, p)
        assert out and out.diagnostics["mode"] == "global"
        dp, dyaw = errors(out, x, y, yaw)
        assert dp < 0.003 and dyaw < 0.03


def test_a_block_gone_from_its_place_fails_the_window_check(rig, site):
    """The blocks and markers painted over (a covered lens, a removed hatch): no window
    fix, and the global path decides the frame (here a heading-only cue)."""
    x, y, yaw = POSES[2]
    bare = dataclasses.replace(site, blocks=(), markers=None)
    img = frame(rig, bare, x, y, yaw, 3)
    out = tracked(rig, site).estimate(img, 0, prior(x, y, yaw))
    assert out.x_m is None and out.diagnostics.get("mode") != WINDOW


def test_the_wrong_contrast_fails_the_window_check(rig):
    """A bright tile where the site has a dark hatch of the same outline: its edges,
    shape and residuals fit the prediction; only the contrast across the outline tells
    it is not the hatch (the test fails if that check is dropped)."""
    rect = np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]])
    dark = Site(3.0, blocks=(Block("A", rect, "dark"),))
    bright = Site(3.0, blocks=(Block("A", rect, "bright"),))
    x, y, yaw = 2.25, 0.05, 0.2
    est = tracked(rig, dark, heading_cue=False)
    ok = est.estimate(frame(rig, dark, x, y, yaw, 1), 0, prior(x, y, yaw))
    assert ok and ok.diagnostics["mode"] == WINDOW
    assert ok.diagnostics["resolved_by"] == "prior"         # a rectangle: 2-fold
    assert ok.quality <= 0.7
    out = est.estimate(frame(rig, bright, x, y, yaw, 1), 0, prior(x, y, yaw))
    assert not out


def test_a_global_search_runs_on_schedule(rig, site):
    x, y, yaw = POSES[1]
    img = frame(rig, site, x, y, yaw, 5)
    est = tracked(rig, site, window_full_every=2)
    modes = [est.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] for _ in range(6)]
    assert modes == [WINDOW, WINDOW, "global", WINDOW, WINDOW, "global"]
    # no prior: the global path
    assert tracked(rig, site).estimate(img, 0, None).diagnostics["mode"] == "global"


def test_bad_track_options_are_one_line_errors(rig, site):
    # each names the key that is wrong (not the other one)
    for bad in ({"window_px": 0.0}, {"window_px": float("nan")},
                {"window_full_every": -1}):
        (key, value), = bad.items()
        with pytest.raises(ConfigError, match=f"options.{key}") as err:
            BlockEstimator(rig, site, {"window_search": True, **bad})
        assert "\n" not in str(err.value) and repr(value) in str(err.value)


def test_the_window_path_is_on_by_default(rig, site):
    """Issue 38 turned the block method's window path on by default (docs/methods/
    block.md): with a prior the window path runs unless ``window_search=false``."""
    x, y, yaw = POSES[1]
    img = frame(rig, site, x, y, yaw, 5)
    est = BlockEstimator(rig, site, {"plane_odometry": False})
    assert est.options.window_search and est.options.window_full_every == 30
    assert est.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] == WINDOW
    off = BlockEstimator(rig, site, {"window_search": False, "plane_odometry": False})
    assert off.estimate(img, 0, prior(x, y, yaw)).diagnostics["mode"] == "global"


@pytest.mark.parametrize("hint", [None, 0.3])
def test_the_stage_heading_is_the_array_reading(hint):
    """The parallels stage's one compiled call (weights, gate, sigma and its few-lines
    factor) gives what robust_heading, line_weights and few_lines_factor give on the
    same lines, a line marked bad left out (to rounding: the weights are summed in
    another order)."""
    from block_reference import few_lines_factor, line_weights

    from ceilkit.runtime.estimators.block import parallels as P
    from ceilkit.runtime.jit import arr
    rng = np.random.default_rng(3)
    ang = rng.choice([0.0, math.pi / 2], 12) + rng.normal(0, 0.004, 12) + 0.3
    p1 = rng.uniform(-0.5, 0.5, (12, 2))
    p2 = p1 + 0.2 * np.column_stack([np.cos(ang), np.sin(ang)])
    px = np.hstack([p1, p2]) * 400.0 + 300.0
    good = np.ones(12, bool)
    good[[2, 7]] = False
    p1[1] += [0.05, 0.0]                 # a line off the axes: the gate drops it
    R = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    length = np.hypot(px[:, 2] - px[:, 0], px[:, 3] - px[:, 1])
    gate = math.radians(1.0)
    want, kept = P.robust_heading(p1[good], p2[good], R, hint, gate, length[good])
    w = line_weights(p1[good], p2[good], R, length[good])
    how = P.HeadingGate(0.0 if hint is None else hint, hint is not None, gate,
                        P.PERIOD_RAD, P.MIN_LINES, P.SIGMA_FLOOR_RAD)
    found, yaw, sigma, n = P._stage_heading(arr(np.hstack([p1, p2]), np.float64),
                                            arr(px, np.float64), arr(good, np.bool_),
                                            arr(R, np.float64), how)
    assert found and n == want.n_lines == kept.sum() < 10
    assert P._near_hint(P.ParallelsHeading(yaw, sigma, P.PERIOD_RAD, n), hint).yaw_rad \
        == pytest.approx(want.yaw_rad, abs=1e-12)
    assert sigma == pytest.approx(want.sigma_rad * few_lines_factor(w[kept]), rel=1e-12)
    assert few_lines_factor(w[kept]) > 1.0


def test_the_mean_side_is_numpys():
    """A marker's cell size in the image (the window search's reach) from the compiled
    mean side length: numpy's to the bit."""
    from ceilkit.runtime.estimators.block.window import mean_side_px
    rng = np.random.default_rng(4)
    for _ in range(50):
        px = rng.uniform(0, 640, (4, 2))
        want = float(np.mean(np.hypot(*(np.roll(px, -1, axis=0) - px).T)))
        assert mean_side_px(px) == want
