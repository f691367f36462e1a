"""The ceiling plane seen through the rig: rays to it, points on it, their Jacobians.

The one implementation the corridor, lights and block methods, the ``ignore`` regions,
the overlays and calib's self-calibration use, in numpy and (for the per-frame loops)
compiled.

Convention (SPEC §1): ``X_V = R_vehicle_cam X_C + t_vehicle_cam``,
``X_W = Rz(yaw) X_V + (x, y, 0)``; the ceiling is the plane ``z = H`` of W (and of V:
the floor is level), ``rise = H - t_z`` above the camera. A normalized image point
``(x, y)`` (lens undistorted, ``z_C = 1``) has the ray ``r = R (x, y, 1)`` (R: the
camera's rotation into V, or into any frame whose z is up, such as the level frame of
the corridor method or W); the ray meets the ceiling at ``s = rise / r_z`` (the
point's depth ``z_C``), ``s (r_x, r_y)`` from the optical centre: a *ceiling point in
V* is ``t_xy + s (r_x, r_y)``. A ray *rises* when ``r_z > min_rz + min_sin |r|``
(the methods differ: ``min_rz`` alone, or ``min_sin`` per length; NaN where it
does not). Back, a ceiling point ``p`` of W seen from the pose is
``X_C = Rᵀ (Rz(-yaw) (p - (x, y)) - t)`` (z: ``H - t_z``).

Example::

    q_v, ok = ceiling_points(cam.unproject(px), R_vc, t_vc, H - t_vc[2])   # (N, 2) in V
    px = project_px(cam, R_vc, t_vc, on_ceiling(q_w, H), poses)           # (P, N, 2)
    J = pixel_jacobian(cam, R_vc, t_vc, H, q_v)           # (N, 2, 2) d(px)/d(q_V)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.jit import arr, njit, warmer

MIN_RZ = 1e-9
"""The default rising test: ``r_z > MIN_RZ`` (``r = R (x, y, 1)``)."""


class KernelMount(NamedTuple):
    """The rig as the compiled loops take it: ``R (3, 3)``, ``t (3,)`` the camera in
    the vehicle frame (read-only float64), the ceiling's height ``ceiling_m`` above the
    floor (z of V and W; above the camera: ``ceiling_m - t[2]``), and the lens ``code``,
    ``lens (13,)``
    (:attr:`~ceilkit.runtime.geometry.camera.CameraModel.lens`)."""

    R: np.ndarray
    t: np.ndarray
    ceiling_m: float
    code: int
    lens: np.ndarray


@dataclass(frozen=True, eq=False)
class PlanarGeometry:
    """What the rig and the site fix: the lens, the mount, the ceiling's height.

    Attributes:
        camera: the lens model.
        R_vehicle_cam, t_vehicle_cam: the mount (``X_V = R X_C + t``).
        ceiling_m: the ceiling's height above the floor (W's z of the ceiling plane).
    """

    camera: CameraModel
    R_vehicle_cam: np.ndarray
    t_vehicle_cam: np.ndarray
    ceiling_m: float

    @classmethod
    def of(cls, rig: Any, site: Any) -> PlanarGeometry:
        return cls(rig.camera, rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam,
                   float(site.ceiling_height_m))

    @property
    def rise_m(self) -> float:
        """The ceiling's height above the camera."""
        return self.ceiling_m - float(self.t_vehicle_cam[2])


# -- rays to the ceiling (numpy) -------------------------------------------------------
def kernel_mount(geo: PlanarGeometry) -> KernelMount:
    """``geo`` as the compiled loops take it (:class:`KernelMount`)."""
    code, lens = geo.camera.lens
    return KernelMount(arr(geo.R_vehicle_cam, np.float64), arr(geo.t_vehicle_cam, np.float64),
                       float(geo.ceiling_m), code, lens)


def ceiling_rays(points_norm: np.ndarray, R: np.ndarray, rise_m: float, *,
                 min_rz: float = MIN_RZ, min_sin: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays of normalized image points meet the ceiling.

    Args:
        points_norm: ``(N, 2)`` undistorted normalized points.
        R: ``(3, 3)`` the camera's rotation into a frame whose z is up (V, level, W).
        rise_m: the ceiling's height above the camera.
        min_rz, min_sin: a ray rises when ``r_z > min_rz + min_sin |r|``.

    Returns:
        ``(offsets (N, 2), depth (N,), ok (N,))``: the ceiling point minus the optical
        centre (in R's frame, metres), ``s = rise / r_z`` (its ``z_C``), and whether the
        ray rises (NaN where not).
    """
    xy = np.asarray(points_norm, float).reshape(-1, 2)
    r = xy @ R[:, :2].T + R[:, 2]                       # R (x, y, 1), row-wise
    rz = r[:, 2]
    limit = min_rz + min_sin * np.sqrt(np.einsum("ij,ij->i", r, r)) if min_sin else min_rz
    ok = rz > limit
    s = np.divide(rise_m, rz, out=np.full(rz.shape, np.nan), where=ok)
    return s[:, None] * r[:, :2], s, ok


def ceiling_points(points_norm: np.ndarray, R_vehicle_cam: np.ndarray,
                   t_vehicle_cam: np.ndarray, rise_m: float, *, min_rz: float = MIN_RZ,
                   min_sin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(q_V (N, 2), ok (N,))``: the ceiling points in V ``(x, y)`` of normalized
    image points ``(N, 2)`` (:func:`ceiling_rays`; NaN where the ray does not rise)."""
    off, _, ok = ceiling_rays(points_norm, R_vehicle_cam, rise_m, min_rz=min_rz,
                              min_sin=min_sin)
    return t_vehicle_cam[:2] + off, ok


def ceiling_points_vehicle(geo: PlanarGeometry, points_norm: np.ndarray) -> np.ndarray:
    """``(N, 2)`` points of the ceiling in V (x, y) seen at normalized image points
    ``(N, 2)``; NaN for rays that do not rise to the ceiling (:data:`MIN_RZ`)."""
    return ceiling_points(points_norm, geo.R_vehicle_cam, geo.t_vehicle_cam, geo.rise_m)[0]


def ceiling_jacobian(points_norm: np.ndarray, R: np.ndarray, rise_m: float) -> np.ndarray:
    """``(N, 2, 2)`` d(ceiling point)/d(normalized point) of :func:`ceiling_rays`:
    ``rise (R_ij r_z - r_i R_2j) / r_z²`` (i, j in x, y); NaN where the ray is level.
    Its inverse is the normalized point's derivative by the ceiling point."""
    xy = np.asarray(points_norm, float).reshape(-1, 2)
    r = xy @ R[:, :2].T + R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = rise_m / (r[:, 2] * r[:, 2])
    return g[:, None, None] * (R[None, :2, :2] * r[:, 2, None, None]
                               - r[:, :2, None] * R[None, 2:3, :2])


# -- points on the ceiling: W <-> V <-> C (numpy) --------------------------------------
def on_ceiling(points_xy: np.ndarray, ceiling_m: float) -> np.ndarray:
    """``(N, 3)`` points of W on the ceiling plane from their ``(x, y)`` ``(N, 2)``."""
    p = np.asarray(points_xy, float).reshape(-1, 2)
    return np.column_stack([p, np.full(p.shape[0], float(ceiling_m))])


def vehicle_to_world(points_v: np.ndarray, x_m: float, y_m: float, yaw_rad: float
                     ) -> np.ndarray:
    """``(N, 2)`` ceiling points in W of ceiling points ``(N, 2)`` in V at the pose:
    ``Rz(yaw) q + (x, y)``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.asarray(points_v, float).reshape(-1, 2) @ np.array([[c, s], [-s, c]]) + (x_m, y_m)


def seen_from(points_w: np.ndarray, poses: np.ndarray, t_vehicle_cam: np.ndarray
              ) -> np.ndarray:
    """``(P, N, 3)`` points of W ``(N, 3)`` from the optical centre of each vehicle pose
    ``(P, 3)`` ``(x, y, yaw)``, in V's axes: ``Rz(-yaw) (p - (x, y, 0)) - t``
    (``... @ R_vehicle_cam`` is then the point in C)."""
    p = np.asarray(points_w, float).reshape(-1, 3)
    poses = np.asarray(poses, float).reshape(-1, 3)
    c, s = np.cos(poses[:, 2, None]), np.sin(poses[:, 2, None])
    dx = p[None, :, 0] - poses[:, None, 0]
    dy = p[None, :, 1] - poses[:, None, 1]
    out = np.empty((poses.shape[0], p.shape[0], 3))
    out[..., 0] = c * dx + s * dy - t_vehicle_cam[0]
    out[..., 1] = -s * dx + c * dy - t_vehicle_cam[1]
    out[..., 2] = p[None, :, 2] - t_vehicle_cam[2]
    return out


def project_px(camera: CameraModel, R_vehicle_cam: np.ndarray, t_vehicle_cam: np.ndarray,
               points_w: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``(P, N, 2)`` pixels of points of W ``(N, 3)`` (:func:`on_ceiling` for the
    ceiling's) from vehicle poses ``(P, 3)``; NaN where a point is behind the camera."""
    P_v = seen_from(points_w, poses, t_vehicle_cam)
    n_poses, n = P_v.shape[:2]
    return camera.project(P_v.reshape(-1, 3) @ R_vehicle_cam).reshape(n_poses, n, 2)


def pixel_jacobian(camera: CameraModel, R_vehicle_cam: np.ndarray,
                   t_vehicle_cam: np.ndarray, ceiling_m: float, q_v: np.ndarray,
                   eps_m: float = 1e-3) -> np.ndarray:
    """``(N, 2, 2)`` d(pixel)/d(ceiling point in V, metres) at ceiling points ``q_v``
    ``(N, 2)`` (forward differences of ``eps_m``, through the lens; the analytic
    geometry is :func:`ceiling_jacobian`'s inverse)."""
    q = np.asarray(q_v, float).reshape(-1, 2)
    n = q.shape[0]
    if n == 0:
        return np.zeros((0, 2, 2))
    pts = on_ceiling(np.concatenate([q, q + [eps_m, 0.0], q + [0.0, eps_m]]), ceiling_m)
    px = project_px(camera, R_vehicle_cam, t_vehicle_cam, pts, np.zeros((1, 3)))[0]
    return np.stack([(px[n:2 * n] - px[:n]) / eps_m, (px[2 * n:] - px[:n]) / eps_m], axis=2)


# -- compiled: one point at a time -----------------------------------------------------
@njit
def ray(R, x, y):  # pragma: no cover - compiled
    """``R (x, y, 1)`` of a normalized point ``(x, y)``: ``(r_x, r_y, r_z)``."""
    return (R[0, 0] * x + R[0, 1] * y + R[0, 2], R[1, 0] * x + R[1, 1] * y + R[1, 2],
            R[2, 0] * x + R[2, 1] * y + R[2, 2])


@njit
def meet_ceiling(R, x, y, rise, min_rz, min_sin):  # pragma: no cover - compiled
    """:func:`ceiling_rays` of one point: ``(ok, offset x, offset y)`` (NaN when the
    ray does not rise: ``r_z > min_rz + min_sin |r|`` fails)."""
    rx, ry, rz = ray(R, x, y)
    limit = min_rz + min_sin * math.sqrt(rx * rx + ry * ry + rz * rz) if min_sin else min_rz
    if not rz > limit:
        return False, np.nan, np.nan
    s = rise / rz
    return True, s * rx, s * ry


@njit
def level_offset(x, y, c, s, wx, wy):  # pragma: no cover - compiled
    """``Rz(-yaw) ((wx, wy) - (x, y))`` with ``c, s = cos, sin yaw``: a point of W from
    the vehicle's origin, in V's axes."""
    dx, dy = wx - x, wy - y
    return dx * c + dy * s, dy * c - dx * s


@njit
def to_camera(R, q0, q1, q2):  # pragma: no cover - compiled
    """``Rᵀ q``: a vector in V (``R = R_vehicle_cam``) in C."""
    return (q0 * R[0, 0] + q1 * R[1, 0] + q2 * R[2, 0],
            q0 * R[0, 1] + q1 * R[1, 1] + q2 * R[2, 1],
            q0 * R[0, 2] + q1 * R[1, 2] + q2 * R[2, 2])


@njit
def ceiling_norm(R, t, ceiling_m, x, y, yaw, points_w, min_z):  # pragma: no cover - compiled
    """Normalized image points ``(N, 2)`` of ceiling points ``points_w (N, 2)`` in W
    (at height ``ceiling_m``) from the vehicle pose ``(x, y, yaw)`` and the mount ``(R,
    t)`` (``X_V = R X_C + t``); NaN where a point is not in front of the camera
    (``z_C <= min_z``). The camera coordinates are ``Rᵀ (Rz(-yaw) (p - (x, y)) - t)``."""
    cz, sz = math.cos(yaw), math.sin(yaw)
    out = np.empty((points_w.shape[0], 2))
    for i in range(points_w.shape[0]):
        vx, vy = level_offset(x, y, cz, sz, points_w[i, 0], points_w[i, 1])
        p0, p1, p2 = to_camera(R, vx - t[0], vy - t[1], ceiling_m - t[2])
        if p2 > min_z:
            out[i, 0] = p0 / p2
            out[i, 1] = p1 / p2
        else:
            out[i, 0] = out[i, 1] = np.nan
    return out


@warmer
def _warm() -> None:
    R = arr(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T, np.float64)
    t = arr(np.zeros(3), np.float64)
    ceiling_norm(R, t, 3.0, 0.0, 0.0, 0.0, arr(np.zeros((1, 2)), np.float64), 1e-9)
    meet_ceiling(R, 0.0, 0.0, 3.0, MIN_RZ, 0.0)


__all__ = ["MIN_RZ", "PlanarGeometry", "ceiling_jacobian", "ceiling_norm", "ceiling_points",
           "ceiling_points_vehicle", "ceiling_rays", "level_offset", "meet_ceiling",
           "on_ceiling", "pixel_jacobian", "project_px", "ray", "seen_from", "to_camera",
           "vehicle_to_world"]
