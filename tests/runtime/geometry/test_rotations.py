import math

import numpy as np
import pytest

from ceilkit.runtime.geometry.rotations import (
    R0,
    R_level_cam,
    R_vehicle_cam,
    mount_angles,
    pose_matrix,
    rot_y,
    rot_z,
    wrap_half_pi,
    wrap_pi,
)


def test_spec_matrices():
    assert np.allclose(rot_z(math.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(rot_y(math.pi / 2) @ [0, 0, 1], [1, 0, 0])
    # a camera looking straight ahead: optical axis on V's x, image right on -y, down on -z
    assert np.allclose(R0 @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R0 @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(R0 @ [0, 1, 0], [0, 0, -1])


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, 45.0, 89.0])
def test_tilt_elevates_optical_axis(tilt_deg):
    t = math.radians(tilt_deg)
    axis = R_vehicle_cam(0.0, t, 0.0) @ [0, 0, 1]
    assert np.allclose(axis, [math.cos(t), 0, math.sin(t)])


def test_pan_turns_about_vertical():
    axis = R_vehicle_cam(math.radians(90), math.radians(30), 0.0) @ [0, 0, 1]
    assert np.allclose(axis, [0, math.cos(math.radians(30)), 0.5])


def test_level_cam_is_mount_without_pan():
    assert np.allclose(rot_z(0.3) @ R_level_cam(0.7, 0.1), R_vehicle_cam(0.3, 0.7, 0.1))


def test_mount_angles_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(200):
        p, t, s = rng.uniform(-3, 3), rng.uniform(0, math.pi / 2 - 1e-3), rng.uniform(-3, 3)
        p2, t2, s2 = mount_angles(R_vehicle_cam(p, t, s))
        assert np.allclose(R_vehicle_cam(p2, t2, s2), R_vehicle_cam(p, t, s), atol=1e-9)
        assert abs(wrap_pi(p2 - p)) < 1e-8 and abs(t2 - t) < 1e-8 and abs(wrap_pi(s2 - s)) < 1e-8


def test_mount_angles_straight_up_reports_pan_plus_swing():
    R = R_vehicle_cam(0.4, math.pi / 2, 0.25)
    p, t, s = mount_angles(R)
    assert s == 0.0 and math.isclose(t, math.pi / 2)
    assert math.isclose(p, 0.65, abs_tol=1e-9)
    assert np.allclose(R_vehicle_cam(p, t, s), R)


def test_wraps_and_pose():
    assert math.isclose(wrap_pi(3 * math.pi / 2), -math.pi / 2)
    assert math.isclose(wrap_half_pi(math.pi * 0.75), -math.pi / 4)
    T = pose_matrix(1.0, 2.0, math.pi / 2)
    assert np.allclose(T @ [1, 0, 0, 1], [1, 3, 0, 1])
