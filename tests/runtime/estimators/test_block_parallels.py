"""Heading from ceiling parallels (Xu eq. 10): exact on noise-free lines, the branch by
a hint, fewer than two lines is no heading."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block.parallels import heading_from_parallels
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, project_norm
from ceilkit.runtime.geometry.camera import CameraModel


def geometry(tilt_deg: float, swing_deg: float) -> PlanarGeometry:
    cam = CameraModel.pinhole(640, 480, 450.0)
    m = Mount(math.radians(3.0), math.radians(tilt_deg), math.radians(swing_deg),
              0.3, 0.05, 0.8)
    rig = type("R", (), {"camera": cam, "mount": m})
    return PlanarGeometry.of(rig, Site(3.0))


def grid_lines(geo, pose):
    """Two points of ceiling lines along x (y = -0.6, 0, 0.6) and along y (x = ...)."""
    x0, y0 = pose[0], pose[1]
    p1, p2 = [], []
    for c in (-0.6, 0.0, 0.6):
        p1.append([x0 - 0.3, y0 + c])
        p2.append([x0 + 0.4, y0 + c])
        p1.append([x0 + c, y0 - 0.3])
        p2.append([x0 + c, y0 + 0.5])
    return project_norm(geo, pose, np.array(p1)), project_norm(geo, pose, np.array(p2))


@pytest.mark.parametrize("tilt, swing", [(90.0, 0.0), (70.0, 2.0), (55.0, -4.0)])
@pytest.mark.parametrize("yaw_deg", [0.0, 23.0, -71.0, 150.0])
def test_eq10_is_exact_without_noise(tilt, swing, yaw_deg):
    geo = geometry(tilt, swing)
    yaw = math.radians(yaw_deg)
    pose = np.array([1.0, 0.5, yaw])
    a, b = grid_lines(geo, pose)
    h = heading_from_parallels(a, b, geo.R_vehicle_cam, hint_yaw_rad=yaw + 0.3)
    assert h is not None and h.n_lines == 6
    assert abs(math.remainder(h.yaw_rad - yaw, 2 * math.pi)) < 1e-9
    # no hint: the heading modulo a quarter turn
    free = heading_from_parallels(a, b, geo.R_vehicle_cam)
    assert abs(math.remainder(free.yaw_rad - yaw, math.pi / 2)) < 1e-9


def test_noisy_lines_and_fewer_than_two():
    geo = geometry(70.0, 2.0)
    yaw = math.radians(12.0)
    a, b = grid_lines(geo, np.array([0.0, 0.0, yaw]))
    rng = np.random.default_rng(1)
    h = heading_from_parallels(a + rng.normal(0, 0.2 / 450, a.shape),
                               b + rng.normal(0, 0.2 / 450, b.shape),
                               geo.R_vehicle_cam, hint_yaw_rad=yaw)
    assert abs(math.degrees(h.yaw_rad - yaw)) < 0.1 and h.sigma_rad > 0
    assert heading_from_parallels(a[:1], b[:1], geo.R_vehicle_cam) is None
