"""The mount as integrators paste it (URDF joint, ROS 2 static transform, ArduPilot
VISO_POS_*): the numbers against the rig, by transforming points both ways."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from ceilkit.calib.export import (
    export_paths,
    static_transform_args,
    urdf_joint,
    viso_pos,
    write_exports,
)
from ceilkit.runtime.config.rig import Mount

MOUNTS = [Mount(0.1, math.radians(40), 0.02, 0.3, -0.05, 0.8),
          Mount(math.radians(-170), math.radians(90), 0.0, -0.12, 0.2, 0.45),
          Mount(math.radians(30), math.radians(89.2), math.radians(-1.5), 0.0, 0.0, 1.1)]
POINTS_C = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 2.0], [-1.0, 0.5, 0.1]])


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF: fixed-axis roll (x), pitch (y), yaw (z): Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                              math.cos(y), math.sin(y))
    return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
            @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
            @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` rotated by the unit quaternion ``(qx, qy, qz, qw)``: q v q*."""
    u, w = q[:3], q[3]
    return v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))


def _mount_map(m: Mount, p_c: np.ndarray) -> np.ndarray:
    """SPEC §1: X_V = R_VC X_C + (mx, my, mz)."""
    return m.R_vehicle_cam @ p_c + m.t_vehicle_cam


@pytest.mark.parametrize("m", MOUNTS)
def test_urdf_joint_maps_the_optical_frame_into_base_link(m):
    text = urdf_joint(m)
    assert '<parent link="base_link"/>' in text
    assert '<child link="camera_optical_frame"/>' in text
    xyz, rpy = (np.array(g.split(), float) for g in
                re.search(r'xyz="([^"]+)" rpy="([^"]+)"', text).groups())
    R = _rpy_matrix(*rpy)
    for p_c in POINTS_C:
        p_v = R @ p_c + xyz
        np.testing.assert_allclose(p_v, _mount_map(m, p_c), atol=1e-5)
        np.testing.assert_allclose(R.T @ (p_v - xyz), p_c, atol=1e-9)  # and back


@pytest.mark.parametrize("m", MOUNTS)
def test_static_transform_maps_the_optical_frame_into_base_link(m):
    args = static_transform_args(m)
    kv = dict(zip(args[::2], args[1::2], strict=True))
    assert kv["--frame-id"] == "base_link"
    assert kv["--child-frame-id"] == "camera_optical_frame"
    t = np.array([float(kv[k]) for k in ("--x", "--y", "--z")])
    q = np.array([float(kv[k]) for k in ("--qx", "--qy", "--qz", "--qw")])
    assert abs(np.linalg.norm(q) - 1) < 1e-5
    for p_c in POINTS_C:
        np.testing.assert_allclose(_quat_rotate(q, p_c) + t, _mount_map(m, p_c), atol=1e-5)
    # the optical axis (C's z) of an upward camera points up in base_link (z)
    if math.isclose(m.tilt_rad, math.pi / 2):
        np.testing.assert_allclose(_quat_rotate(q, np.array([0, 0, 1.0])), [0, 0, 1],
                                   atol=1e-6)


@pytest.mark.parametrize("m", MOUNTS)
def test_viso_pos_is_the_optical_centre_in_frd(m):
    x, y, z = viso_pos(m)
    # FRD = V with y and z flipped: the camera centre back in V
    np.testing.assert_allclose([x, -y, -z], m.t_vehicle_cam, atol=1e-4)
    ax, ay, az = viso_pos(m, (0.1, 0.2, 0.3))
    np.testing.assert_allclose([ax, -ay, -az], m.t_vehicle_cam - [0.1, 0.2, 0.3], atol=1e-4)


def test_write_exports_beside_the_rig_with_its_header(tmp_path):
    m = MOUNTS[0]
    rig = tmp_path / "rig.yaml"
    header = "# rig.yaml written by ceilcal mount\n# command: ceilcal mount --fix h=0.8\n"
    paths = write_exports(m, rig, header)
    assert paths == export_paths(rig)
    assert {p.name for p in paths.paths()} == {"rig.urdf.xml", "rig.static_tf.sh",
                                                "rig.viso.param"}
    urdf = paths.urdf.read_text()
    assert urdf.startswith("<!--") and "rig.yaml written by ceilcal mount" in urdf
    assert "--fix" not in urdf.split("-->")[0][4:]   # no "--" inside an XML comment
    assert urdf_joint(m) in urdf
    tf = paths.static_tf.read_text()
    assert header in tf
    assert "ros2 run tf2_ros static_transform_publisher " + " ".join(
        static_transform_args(m)) in tf
    param = paths.ardupilot.read_text()
    assert param.startswith(header)
    values = dict(line.split(",") for line in param.splitlines() if not line.startswith("#"))
    np.testing.assert_allclose([float(values[f"VISO_POS_{a}"]) for a in "XYZ"],
                               viso_pos(m), atol=1e-6)
