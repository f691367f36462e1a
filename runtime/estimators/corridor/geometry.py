"""The corridor method's formulas: level normals, vanishing points, pan, offsets.

Convention (SPEC §1): ``R_world_cam = Rz(psi) @ R_level_cam`` with ``psi = yaw + pan``
(the camera's pan in W). A segment's homogeneous line ``l`` (undistorted normalized
coordinates, ``hypot(l_x, l_y) = 1``) seen in the level frame is ``q = R_level_cam l``;
the along family's vanishing direction is ``R_level_cam^T (cos psi, -sin psi, 0)``, so
its lines satisfy ``q_x cos psi - q_y sin psi = 0``; the across family's satisfy
``q_x sin psi + q_y cos psi = 0``. The plane through the optical centre and an along
line at ``y = y_j`` has the world normal ``n = Rz(psi) q`` and meets the ceiling, ``h``
above the camera, at ``y_j = c_y - n_z h / n_y``.

These are the functions the estimator calls (arrays in, arrays out); the tests test
them against independent forms.

Example::

    q = level_normals(lines, R_level_cam)                 # (N, 3)
    va, vb = vanishing_directions(psi, R_level_cam)       # along, across (camera frame)
    offsets, n_y = along_offsets(q, psi, ceiling_above_cam_m)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.jit import arr, njit, warmer

Rows = Sequence[Sequence[float]]
"""A 3x3 matrix as rows: an ``(3, 3)`` array or nested float tuples (faster scalar math)."""


def level_normals(lines: np.ndarray, R_level_cam: np.ndarray) -> np.ndarray:
    """``q = R_level_cam l`` for lines ``(N, 3)`` (camera normalized coordinates):
    their interpretation planes' normals in the level frame, ``(N, 3)``."""
    R_T = np.ascontiguousarray(np.asarray(R_level_cam, dtype=np.float64).T)
    return np.asarray(lines, dtype=np.float64).reshape(-1, 3) @ R_T


def vanishing_directions(psi_rad: float, R_level_cam: Rows
                         ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Camera-frame directions of W's x (along) and y (across) for camera pan
    ``psi_rad`` in W: ``va = R^T (cos psi, -sin psi, 0)``, ``vb = R^T (sin psi, cos psi, 0)``
    (``R = R_level_cam``), as two 3-tuples (they lie on the ceiling's vanishing line
    ``R[2] . v = 0``)."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    m0, m1 = R_level_cam[0], R_level_cam[1]
    return (tuple(c * a - s * b for a, b in zip(m0, m1, strict=True)),
            tuple(s * a + c * b for a, b in zip(m0, m1, strict=True)))


def vanishing_angles(psi_rad: float, R_level_cam: Rows, lines_t: np.ndarray,
                     mx: np.ndarray, my: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each segment against the along (row 0) and across (row 1) vanishing points for
    camera pan ``psi_rad``.

    Args:
        lines_t: ``(3, N)`` the segments' lines (columns, ``hypot(a, b) = 1``).
        mx, my: ``(N,)`` their midpoints (normalized coordinates).

    Returns:
        ``(2, N)`` absolute angles (rad, small-angle) between each segment and the line
        joining its midpoint to the vanishing point ``v``: ``|l . v| / |v_xy - v_z m|``;
        and ``(2, N)`` the denominators ``|v_xy - v_z m|`` (at least 1e-12).
    """
    V = np.array(vanishing_directions(psi_rad, R_level_cam))          # rows: va, vb
    vz = V[:, 2:]
    den = np.maximum(np.hypot(V[:, :1] - vz * mx, V[:, 1:2] - vz * my), 1e-12)
    return np.abs(V @ lines_t) / den, den


def fit_pan(q: np.ndarray, w_along: np.ndarray, w_across: np.ndarray) -> float:
    """Closed-form ``psi`` minimising ``sum w_along (q_x c - q_y s)^2 +
    sum w_across (q_x s + q_y c)^2`` (``c, s = cos, sin psi``) over level normals
    ``q (N, 3)`` with weights ``(N,)`` (0 outside a family): the smallest eigenvector
    of a 2x2 matrix. Returns psi in [-pi, pi) (defined mod pi)."""
    q0, q1 = q[:, 0], q[:, 1]
    q00, q11, q01 = q0 * q0, q1 * q1, q0 * q1
    # along rows (q_x, -q_y), across rows (q_y, q_x)
    sxx = float(w_along @ q00 + w_across @ q11)
    syy = float(w_along @ q11 + w_across @ q00)
    sxy = float((w_across - w_along) @ q01)
    # the 2x2 matrix's major axis is at 0.5 atan2(2 sxy, sxx - syy); the minor is normal
    th = 0.5 * math.atan2(2.0 * sxy, sxx - syy) + 0.5 * math.pi
    return th if th < math.pi else th - 2 * math.pi


def along_offsets(q: np.ndarray, psi_rad: float, ceiling_above_cam_m: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``y_line - c_y`` (m) of along lines with level normals ``q (N, 3)``, for a camera
    ``ceiling_above_cam_m`` below the ceiling, and ``n_y = (Rz(psi) q)_y`` ``(N,)``
    (its sign orients a segment's edge polarity in W). Offsets are NaN where the plane
    is parallel to W's y-z (``|n_y| <= 1e-12``)."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    n_y = s * q[:, 0] + c * q[:, 1]
    offs = np.full(n_y.size, np.nan)
    np.divide(-q[:, 2] * ceiling_above_cam_m, n_y, out=offs, where=np.abs(n_y) > 1e-12)
    return offs, n_y


def across_offsets(q: np.ndarray, psi_rad: float, ceiling_above_cam_m: float) -> np.ndarray:
    """``x_line - c_x`` (m) of across lines (parallel to W's y) with level normals ``q``
    ``(N, 3)``; NaN where the plane is parallel to W's x-z."""
    n = q @ rot_z(psi_rad).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(n[:, 0]) > 1e-12, -n[:, 2] * ceiling_above_cam_m / n[:, 0],
                        np.nan)


def free_vanishing_points(lines: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The unit homogeneous points ``(F, 3)`` closest (algebraically, weighted) to the
    lines ``(N, 3)`` of each of F families: the smallest eigenvector of
    ``sum_n w_fn l_n l_n^T``, with ``weights (F, N)`` (0 outside family f)."""
    w = np.asarray(weights, dtype=float).reshape(-1, lines.shape[0])
    Wl = np.empty((lines.shape[0], 3 * w.shape[0]))
    for f in range(w.shape[0]):
        np.multiply(lines, w[f][:, None], out=Wl[:, 3 * f:3 * f + 3])
    lines_t = np.ascontiguousarray(lines.T)
    S = (lines_t @ Wl).reshape(3, -1, 3).transpose(1, 0, 2)        # (F, 3, 3)
    return np.linalg.eigh(S)[1][:, :, 0]


def mount_from_vanishing_line(n_cam: np.ndarray) -> tuple[float, float]:
    """``(tilt, swing)`` radians whose ceiling vanishing line is ``n_cam`` (3,):
    the level frame's z seen from the camera is ``(-sin s cos t, -cos s cos t, sin t)``."""
    n = np.asarray(n_cam, dtype=float) / np.linalg.norm(n_cam)
    if n[2] < 0:
        n = -n
    return math.asin(min(1.0, n[2])), math.atan2(-n[0], -n[1])


def vanishing_line_check(lines: np.ndarray, len_n: np.ndarray, along: np.ndarray,
                         across: np.ndarray, R_level_cam: np.ndarray) -> dict[str, float]:
    """The mount check: the free vanishing points of both families (weights length^2)
    against the calibrated tilt and swing. Keys ``vanishing_line_residual_deg``,
    ``vp_along_elevation_deg``, ``implied_tilt_deg``, ``implied_swing_deg`` (NaN where
    a family has fewer than two segments)."""
    lines_t = np.ascontiguousarray(np.asarray(lines, np.float64).reshape(-1, 3).T)
    return vanishing_line_dict(*_vanishing_line(
        arr(lines_t, np.float64), arr(len_n, np.float64), arr(along, np.bool_),
        arr(across, np.bool_), arr(R_level_cam, np.float64)))


def vanishing_line_dict(resid: float, elev: float, tilt: float, swing: float
                        ) -> dict[str, float]:
    """:func:`vanishing_line_check`'s dict of :func:`_vanishing_line`'s numbers."""
    return {"vanishing_line_residual_deg": resid, "vp_along_elevation_deg": elev,
            "implied_tilt_deg": tilt, "implied_swing_deg": swing}


@njit
def _vanishing_line(lines_t, len_n, along, across, R):  # pragma: no cover - compiled
    """:func:`vanishing_line_check`'s ``(residual deg, elevation deg, tilt deg, swing
    deg)`` from the lines ``(3, N)``: each family's free vanishing point
    (:func:`free_vanishing_points`, weights ``len²``), the unit vanishing line ``n``
    through both and the mount that has it (:func:`_mount_of`); NaN where a family has
    fewer than two segments."""
    nan = np.nan
    if np.count_nonzero(along) < 2:
        return nan, nan, nan, nan
    va = _family_point(lines_t, len_n, along)
    n_pred = R[2]
    elev = math.degrees(math.asin(min(1.0, abs(n_pred[0] * va[0] + n_pred[1] * va[1]
                                                + n_pred[2] * va[2]))))
    if np.count_nonzero(across) < 2:
        return nan, elev, nan, nan
    vb = _family_point(lines_t, len_n, across)
    n = np.array([va[1] * vb[2] - va[2] * vb[1], va[2] * vb[0] - va[0] * vb[2],
                  va[0] * vb[1] - va[1] * vb[0]])
    nn = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if not nn > 1e-12:
        return nan, elev, nan, nan
    n /= nn
    resid = math.degrees(math.acos(min(1.0, abs(n[0] * n_pred[0] + n[1] * n_pred[1]
                                                 + n[2] * n_pred[2]))))
    tilt, swing = _mount_of(n)
    return resid, elev, math.degrees(tilt), math.degrees(swing)


@njit
def _mount_of(n_cam):  # pragma: no cover - compiled
    """:func:`mount_from_vanishing_line` of a unit-ish ``n_cam`` (3,)."""
    n = n_cam / math.sqrt(n_cam[0] * n_cam[0] + n_cam[1] * n_cam[1] + n_cam[2] * n_cam[2])
    if n[2] < 0:
        n = -n
    return math.asin(min(1.0, n[2])), math.atan2(-n[0], -n[1])


@njit
def _family_point(lines_t, len_n, fam):  # pragma: no cover - compiled
    """The smallest eigenvector of ``sum w l lᵀ`` over the lines of one family
    (``w = len²``)."""
    S = np.zeros((3, 3))
    for k in range(len_n.size):
        if fam[k]:
            w = len_n[k] * len_n[k]
            for i in range(3):
                for j in range(3):
                    S[i, j] += lines_t[i, k] * (lines_t[j, k] * w)
    return np.linalg.eigh(S)[1][:, 0].copy()


@warmer
def _warm() -> None:
    f = np.float64
    lines_t = arr(np.array([[0.0, 0.1, 0.2], [1.0, 1.0, 1.0], [0.1, 0.2, 0.3]]), f)
    on = arr(np.ones(3, bool), np.bool_)
    _vanishing_line(lines_t, arr(np.ones(3), f), on, on, arr(np.eye(3), f))
