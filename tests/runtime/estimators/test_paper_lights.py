"""Tests of runtime/estimators/paper_lights.py: the paper's pipeline as a baseline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.lights import project_lights
from ceilkit.runtime.estimators.paper_lights import PaperLightsEstimator, PaperLightsOptions
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.sim.render import SimOptions, render_frame


def test_localizes_a_small_map(lights_rig, lights_site):
    # the paper's setting: a handful of lights (its target model has at most 11)
    x, y, yaw = 5.0, 0.3, 1.1
    L = lights_site.lights_m
    near = L[np.linalg.norm(L - [x, y], axis=1) < 4.0]
    site = Site(3.0, lights_m=near)
    est = PaperLightsEstimator(lights_rig, site)
    img = render_frame(lights_rig, site, x, y, yaw, options=SimOptions(),
                       rng=np.random.default_rng(1))
    out = est.estimate(img, 3)
    assert out, (out.reason, out.detail)
    assert math.hypot(out.x_m - x, out.y_m - y) < 0.03
    assert abs(math.remainder(out.yaw_rad - yaw, 2 * math.pi)) < math.radians(0.5)
    assert out.method == "paper-lights" and 0 < out.quality <= 1
    assert abs(out.diagnostics["scale"] - 1.0) < 0.02


def test_observed_points_are_the_lights(lights_rig, lights_site):
    x, y, yaw = 9.0, -1.0, -0.4
    est = PaperLightsEstimator(lights_rig, lights_site)
    img = render_frame(lights_rig, lights_site, x, y, yaw, options=SimOptions(),
                       rng=np.random.default_rng(2))
    px, q = est.observed_points(img)
    truth = project_lights(lights_rig, 3.0, lights_site.lights_m, x, y, yaw)
    d = np.linalg.norm(px[:, None] - truth[None], axis=2)
    err = np.nanmin(d, axis=1)
    # binary centroids of tile-thresholded regions: good near the centre, off by
    # pixels at the rim of the wide-angle image
    assert 3 <= px.shape[0] <= 11 and np.sum(err < 1.0) >= 6 and err.max() < 5.0


def test_failures(lights_rig, lights_site):
    est = make_estimator("paper-lights", lights_rig, lights_site)
    out = est.estimate(np.full((480, 640), 50, np.uint8), 1)
    assert not out and out.reason == "no_lights"
    assert est.estimate(np.zeros((4, 4), np.uint8), 1).reason == "bad_frame"
    with pytest.raises(ConfigError, match="at least one light"):
        PaperLightsEstimator(lights_rig, Site(3.0))


def test_options_on_the_contract(lights_rig, lights_site):
    est = PaperLightsEstimator(lights_rig, lights_site, {"scale_min": "0.9", "k": 2.0})
    assert est.options == PaperLightsOptions(scale_min=0.9, k=2.0)
    assert est.options.min_contrast == 0.0          # a blank frame stays `no_lights`
    assert PaperLightsEstimator.site_sections == ("lights",)
    with pytest.raises(ConfigError, match="options.scale_range"):
        PaperLightsEstimator(lights_rig, lights_site, {"scale_range": (0.8, 1.2)})
    # a scale window that excludes 1 matches nothing
    x, y, yaw = 5.0, 0.3, 1.1
    near = lights_site.lights_m[np.linalg.norm(lights_site.lights_m - [x, y], axis=1) < 4.0]
    site = Site(3.0, lights_m=near)
    img = render_frame(lights_rig, site, x, y, yaw, options=SimOptions(),
                       rng=np.random.default_rng(1))
    off = PaperLightsEstimator(lights_rig, site, {"scale_min": 1.3, "scale_max": 1.5})
    assert off.estimate(img, 0).reason == "no_match"
