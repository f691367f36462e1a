"""Tests of runtime/estimators/paper_corridor.py: the paper's closed forms on exact data,
and frames."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.corridor.geometry import vanishing_directions
from ceilkit.runtime.estimators.paper_corridor import (
    PaperCorridorEstimator,
    PaperCorridorOptions,
    lateral_from_line,
    mean_intersection,
    pan_from_vanishing_line,
)
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.geometry.rotations import R_level_cam, rot_z
from ceilkit.runtime.sim.render import render_frame

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "corridor"


@pytest.mark.parametrize("swing_deg", [0.0, 1.0, -6.0])
@pytest.mark.parametrize("psi", [-0.6, -0.1, 0.02, 0.3, 0.7])
def test_pan_closed_form_is_exact_with_a_complementary_twin(psi, swing_deg):
    M = R_level_cam(math.radians(45), math.radians(swing_deg))
    va, vb = map(np.array, vanishing_directions(psi, M))
    D = va[:2] / va[2] - vb[:2] / vb[2]
    p1, p2 = pan_from_vanishing_line(D, M)
    assert min(abs(p1 - psi), abs(p2 - psi)) < 1e-9
    # the twin also explains D (the paper's 45 deg ambiguity)
    other = p2 if abs(p1 - psi) < 1e-9 else p1
    va2, vb2 = map(np.array, vanishing_directions(other, M))
    assert np.allclose(va2[:2] / va2[2] - vb2[:2] / vb2[2], D, rtol=1e-9)


def test_lateral_from_line_is_exact():
    M = R_level_cam(math.radians(45), math.radians(1))
    psi, h, dy = 0.25, 2.0, -0.37
    R_cw = (rot_z(psi) @ M).T
    n_w = np.array([0.0, h, -dy])        # plane of the line y = c_y + dy, z = h
    line = R_cw @ n_w
    line /= np.hypot(line[0], line[1])
    assert lateral_from_line(line, psi, M, h) == pytest.approx(dy, abs=1e-12)


def test_mean_intersection():
    lines = np.array([[1.0, 0, -1], [0, 1.0, -2], [1.0, 1.0, -3]])
    assert np.allclose(mean_intersection(lines), [1.0, 2.0])
    assert mean_intersection(np.array([[1.0, 0, 0], [1.0, 0, -1]])) is None


def test_paper_estimator_frames():
    rig, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    est = make_estimator("paper-corridor", rig, site)
    assert est.name == "paper-corridor"
    h, w = rig.camera.height, rig.camera.width
    assert est.estimate(np.zeros((h, w), np.uint8), 3).reason == "blank_frame"
    assert est.estimate(np.full((h, w), 255, np.uint8), 3).reason == "saturated_frame"
    with pytest.raises(ConfigError):
        PaperCorridorEstimator(rig, site, {"nope": 1})
    assert est.estimate(np.zeros((10, 10), np.uint8), 3).reason == "bad_frame"
    yaw = math.radians(12.0)
    img = render_frame(rig, site, 0.3, 0.1, yaw, rng=np.random.default_rng(2))
    r = est.estimate(img, 5)
    assert r and r.x_m is None and r.t_ns == 5
    assert abs(math.degrees(r.yaw_rad - yaw)) < 10.0       # the paper reports ~1-5 deg
    assert np.isinf(r.cov[0, 0]) and 0.0 <= r.quality <= 1.0


def test_paper_options():
    """Defaults as the paper's procedure had them; strings from a CLI are coerced."""
    rig, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    est = PaperCorridorEstimator(rig, site)
    assert est.canny == (40.0, 100.0) and est.options.hough_threshold == 30
    assert est.min_length_px == pytest.approx(0.04 * rig.camera.width)
    assert est.match_tol_m == pytest.approx(0.075)
    est = PaperCorridorEstimator(rig, site, {"canny_low": "30", "hough_threshold": "25",
                                             "min_length_px": "20"})
    assert est.options == PaperCorridorOptions(canny_low=30.0, hough_threshold=25,
                                               min_length_px=20.0)
    assert est.canny == (30.0, 100.0) and est.min_length_px == 20.0
    with pytest.raises(ConfigError, match=r"options\.hough_threshold"):
        PaperCorridorEstimator(rig, site, {"hough_threshold": "lots"})
    with pytest.raises(ConfigError, match="ceiling"):   # the camera above the ceiling
        PaperCorridorEstimator(rig, Site(0.5, site.corridor))
