"""Rotations and frames of SPEC §1, as pure numpy functions.

Convention (SPEC §1):

* ``Rz(a) = [[c,-s,0],[s,c,0],[0,0,1]]``, ``Ry(a) = [[c,0,s],[0,1,0],[-s,0,c]]``.
* ``R0 = [[0,0,1],[-1,0,0],[0,-1,0]]`` maps a camera looking straight ahead into V.
* The mount: ``R_vehicle_cam = Rz(pan) @ Ry(-tilt) @ R0 @ Rz(swing)``;
  ``X_V = R_vehicle_cam @ X_C + t_vehicle_cam``.
* The vehicle pose: ``X_W = Rz(yaw) @ X_V + (x, y, 0)``.

Names follow ``R_A_B`` maps B coordinates to A. All angles here are radians.
"""

from __future__ import annotations

import math

import numpy as np

R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
R0.setflags(write=False)


def rot_z(a_rad: float) -> np.ndarray:
    """Rotation about z by ``a_rad`` (counter-clockwise seen from +z)."""
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a_rad: float) -> np.ndarray:
    """Rotation about y by ``a_rad``."""
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def R_vehicle_cam(pan_rad: float, tilt_rad: float, swing_rad: float) -> np.ndarray:
    """The mount rotation ``Rz(pan) Ry(-tilt) R0 Rz(swing)`` (camera to vehicle).

    Example: a camera looking straight up (tilt 90°) has its optical axis on V's z:

    >>> R = R_vehicle_cam(0.0, math.pi / 2, 0.0)
    >>> np.allclose(R @ [0, 0, 1], [0, 0, 1])
    True
    """
    return rot_z(pan_rad) @ rot_y(-tilt_rad) @ R0 @ rot_z(swing_rad)


def R_level_cam(tilt_rad: float, swing_rad: float) -> np.ndarray:
    """``Ry(-tilt) R0 Rz(swing)``: the camera in a level frame turned with its pan.

    ``R_world_cam = Rz(yaw + pan) @ R_level_cam(tilt, swing)``. Its third row, seen
    from the camera, is the ceiling's normal: the vanishing line of every horizontal
    plane depends on tilt and swing only.
    """
    return rot_y(-tilt_rad) @ R0 @ rot_z(swing_rad)


def mount_angles(R_vc: np.ndarray, eps: float = 1e-9) -> tuple[float, float, float]:
    """Decompose a camera-to-vehicle rotation into ``(pan, tilt, swing)`` radians.

    Inverse of :func:`R_vehicle_cam` for tilt in [-90°, 90°]. At tilt = 90° only
    ``pan + swing`` is observable; it is returned as pan with swing 0 (SPEC §1).
    """
    R = np.asarray(R_vc, dtype=float)
    axis = R[:, 2]  # optical axis in V: (cos t cos p, cos t sin p, sin t)
    tilt = math.asin(max(-1.0, min(1.0, axis[2])))
    if math.hypot(axis[0], axis[1]) < eps:
        x1 = R[:, 0]  # (sin(p+s), -cos(p+s), 0) when looking straight up
        pan = math.atan2(x1[0], -x1[1]) if tilt > 0 else math.atan2(-x1[0], x1[1])
        return wrap_pi(pan), tilt, 0.0
    pan = math.atan2(axis[1], axis[0])
    Rs = R0.T @ rot_y(tilt) @ rot_z(-pan) @ R
    swing = math.atan2(Rs[1, 0], Rs[0, 0])
    return pan, tilt, swing


def wrap_pi(a_rad: float) -> float:
    """Wrap an angle into [-pi, pi)."""
    return (a_rad + math.pi) % (2.0 * math.pi) - math.pi


def wrap_half_pi(a_rad: float) -> float:
    """Wrap an angle into [-pi/2, pi/2): a line's direction has no sign."""
    return (a_rad + math.pi / 2) % math.pi - math.pi / 2


def pose_matrix(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    """The 4x4 ``T_world_vehicle`` of a planar vehicle pose."""
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw_rad)
    T[0, 3], T[1, 3] = x_m, y_m
    return T
