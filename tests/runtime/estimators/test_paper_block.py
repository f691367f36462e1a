"""paper-block: eq. 3's linear PnP exact on noise-free corners; the estimator on a
rendered frame (heading from the detected parallels, eq. 10)."""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, project_norm
from ceilkit.runtime.estimators.paper_block import PaperBlockEstimator, linear_pnp
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

CORNERS = np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]])


def test_linear_pnp_is_exact_on_noise_free_corners():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    geo = PlanarGeometry.of(rig, site)
    for x, y, yaw in [(2.1, 0.1, 0.3), (2.5, -0.3, -2.0), (1.9, 0.2, 3.0)]:
        pose = np.array([x, y, yaw])
        got = linear_pnp(project_norm(geo, pose, CORNERS), CORNERS)
        assert got is not None
        R_cw, p = got
        R_wc = rot_z(yaw) @ geo.R_vehicle_cam
        c = rot_z(yaw) @ geo.t_vehicle_cam + np.array([x, y, 0.0])
        assert np.allclose(R_cw, R_wc.T, atol=1e-9)
        assert np.allclose(-R_cw.T @ p + [0, 0, geo.ceiling_m], c, atol=1e-9)


def test_paper_block_localizes_a_marker_frame_with_the_parallels_heading():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    est = make_estimator("paper-block", rig, site)
    assert isinstance(est, PaperBlockEstimator)
    x, y, yaw = 0.55, 0.4, math.radians(17.0)
    img = render_frame(rig, site, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=1.0))
    got = est.estimate(img, 0)
    assert got and got.method == "paper-block"
    assert math.hypot(got.x_m - x, got.y_m - y) < 0.05     # 6 DoF from 4 corners: cm
    assert got.diagnostics["parallels_mode"] == "detected"
    assert abs(math.degrees(got.yaw_rad - yaw)) < 0.1
