"""Ceiling-plane odometry: the rigid fit exact on noise-free ceiling points, outliers
dropped; on rendered frames the motion between two frames to a fraction of a mm."""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.odometry import PlaneOdometry, plane_motion
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS


def test_plane_motion_is_exact_and_drops_outliers():
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, (40, 2))
    dyaw, t = 0.05, np.array([0.03, -0.01])
    c, s = math.cos(dyaw), math.sin(dyaw)
    q = p @ np.array([[c, s], [-s, c]]) + t
    q[:5] += 0.3                                     # five wrong tracks
    inc = plane_motion(q, p)
    assert inc is not None and inc.n == 35
    assert abs(inc.dx_m - 0.03) < 1e-9 and abs(inc.dy_m + 0.01) < 1e-9
    assert abs(inc.dyaw_rad - dyaw) < 1e-9
    assert plane_motion(q[:5], p[:5]) is None        # too few


def test_rendered_step_gives_the_motion():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    odo = PlaneOdometry(PlanarGeometry.of(rig, site))
    opts = SimOptions(noise_sigma=2.0, blur_px=1.0)
    x, y, yaw = 1.0, 0.1, 0.3
    assert odo.step(render_frame(rig, site, x, y, yaw, opts)) is None
    dx, dy, dth = 0.04, -0.01, math.radians(1.0)      # in V at the first frame
    c, s = math.cos(yaw), math.sin(yaw)
    inc = odo.step(render_frame(rig, site, x + c * dx - s * dy, y + s * dx + c * dy,
                                yaw + dth, opts))
    assert inc is not None
    assert math.hypot(inc.dx_m - dx, inc.dy_m - dy) < 0.001
    assert abs(math.degrees(inc.dyaw_rad) - 1.0) < 0.05
    assert np.all(np.linalg.eigvalsh(inc.cov) > 0)
