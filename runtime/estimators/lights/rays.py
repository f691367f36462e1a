"""Rays between the image and the ceiling plane, for the lights method (through
``geometry/ceiling.py``, the one implementation every method shares).

Convention (SPEC §1): ``X_V = R_vehicle_cam X_C + t_vehicle_cam``; every light centre
lies on the ceiling plane ``z = H`` (``ceiling_height_m``, W's z: the height above the
floor). A *ceiling point in V* is the ``(x, y)`` in the vehicle frame where a pixel's
ray from the optical centre meets that plane: known without the vehicle's pose (the
yaw only turns about the vertical), it is the map as seen from the vehicle.

Example::

    q_v, ok = ceiling_points(rig, 3.0, spots.centroids_px)       # (N, 2) m in V
    px = project_lights(rig, 3.0, site.lights_m, x_m, y_m, yaw_rad)   # (M, 2) px
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.geometry import ceiling
from ceilkit.runtime.geometry.camera import undistort_points
from ceilkit.runtime.jit import njit

RISE_SIN = 1e-6
"""A pixel's ray rises to the ceiling when its elevation's sine is above this."""


@functools.lru_cache(maxsize=64)
def mount_arrays(mount: Mount) -> tuple[np.ndarray, np.ndarray]:
    """``(R_vehicle_cam, t_vehicle_cam)`` of a mount, computed once (read-only)."""
    R, t = mount.R_vehicle_cam, mount.t_vehicle_cam
    R.setflags(write=False)
    t.setflags(write=False)
    return R, t


def ceiling_points(rig: Rig, ceiling_height_m: float, points_px: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Ceiling points in the vehicle frame of image points.

    Args:
        rig: camera and mount.
        ceiling_height_m: ``H``, the ceiling's height above the floor (W's z).
        points_px: ``(N, 2)`` distorted pixels.

    Returns:
        ``(q_V (N, 2), ok (N,))``: ``(x, y)`` in V (metres) of the ray's meeting with
        ``z = H``; ``ok`` is False where the ray does not rise (NaN there).
    """
    px = np.asarray(points_px, float).reshape(-1, 2)
    if px.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    R_vc, t_vc = mount_arrays(rig.mount)
    return ceiling.ceiling_points(rig.camera.unproject(px), R_vc, t_vc,
                                  ceiling_height_m - rig.mount.z_m, min_rz=0.0,
                                  min_sin=RISE_SIN)


_STENCIL = np.array([(i, j) for j in (-1, 0, 1) for i in (-1, 0, 1)], float)   # (9, 2)
_STENCIL_PX = 1.0   # the finite differences' step (the lens is smooth over a pixel)


def ceiling_centroids(rig: Rig, ceiling_height_m: float, centroids_px: np.ndarray,
                      cov_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ceiling points in V of spots given by their image moments: the centroid of each
    spot's lit face *on the ceiling plane*, to second order in its image moments.

    A spot's weights are the ceiling's radiance seen through the lens, so its image
    centroid ``c`` is the mean of the pixels; :func:`ceiling_points` of ``c`` is not the
    mean of their ceiling points, and a lens that compresses the far side of a disc
    (a fisheye seen off-axis, a tilted pinhole) moves it towards the camera. With ``f``
    the map from pixels to the ceiling (V), ``a = |det Df|`` the ceiling area of a pixel
    and ``Σ`` the spot's second central moments (px²), the face's centroid is

        q = f(c) + Df Σ ∇log a + ½ Σ_jk ∂²f/∂p_j∂p_k Σ_jk  (+ third order)

    with ``∂_k log a = tr(Df⁻¹ ∂²f/∂p ∂p_k)``; ``Df`` and the second derivatives by
    differences over a 3 x 3 pixel stencil about ``c`` (one :func:`ceiling_points` call).
    On the optical axis of a camera looking straight up both terms vanish (``f`` is
    then linear and ``a`` flat at ``c``): the point is ``f(c)``.

    Args:
        rig: camera and mount.
        ceiling_height_m: ``H``, the ceiling's height above the floor (W's z).
        centroids_px: ``(N, 2)`` spot centroids, distorted pixels.
        cov_px: ``(N, 2, 2)`` their second central moments, px² (``Spots.cov_px``).

    Returns:
        ``(q_V (N, 2), ok (N,))`` as :func:`ceiling_points`; where a stencil pixel's ray
        does not rise (a spot at the horizon) the point is ``f(c)``, uncorrected.

    Example::

        q_v, ok = ceiling_centroids(rig, 3.0, spots.centroids_px, spots.cov_px)
    """
    c = np.asarray(centroids_px, float).reshape(-1, 2)
    n = c.shape[0]
    S = np.asarray(cov_px, float).reshape(n, 2, 2)
    pts = c[:, None, :] + _STENCIL_PX * _STENCIL[None]                   # (N, 9, 2)
    q, ok = ceiling_points(rig, ceiling_height_m, pts.reshape(-1, 2))
    q, ok = q.reshape(n, 3, 3, 2), ok.reshape(n, 9)                      # [n, v, u]
    f0 = q[:, 1, 1]
    h = _STENCIL_PX
    Df = np.stack([(q[:, 1, 2] - q[:, 1, 0]) / (2 * h),
                   (q[:, 2, 1] - q[:, 0, 1]) / (2 * h)], axis=2)          # (N, 2, 2)
    H = np.empty((n, 2, 2, 2))                                           # [n, i, j, k]
    H[:, :, 0, 0] = (q[:, 1, 2] - 2 * f0 + q[:, 1, 0]) / h ** 2
    H[:, :, 1, 1] = (q[:, 2, 1] - 2 * f0 + q[:, 0, 1]) / h ** 2
    H[:, :, 0, 1] = H[:, :, 1, 0] = (q[:, 2, 2] - q[:, 2, 0] - q[:, 0, 2]
                                     + q[:, 0, 0]) / (4 * h * h)
    good = ok.all(axis=1) & (np.abs(np.linalg.det(np.where(
        ok.all(axis=1)[:, None, None], Df, 1.0))) > 0)
    out = f0.copy()
    if np.any(good):
        Dg, Hg, Sg = Df[good], H[good], S[good]
        Dinv = np.linalg.inv(Dg)
        grad_log_a = np.einsum("nji,nijk->nk", Dinv, Hg)
        out[good] = (f0[good] + np.einsum("nij,njk,nk->ni", Dg, Sg, grad_log_a)
                     + 0.5 * np.einsum("nijk,njk->ni", Hg, Sg))
    return out, ok[:, 4]


def project_lights(rig: Rig, ceiling_height_m: float, lights_w: np.ndarray, x_m: float,
                   y_m: float, yaw_rad: float) -> np.ndarray:
    """Pixels ``(N, 2)`` of ceiling lights ``(N, 2)`` (W) seen from a vehicle pose.

    NaN where a light is behind the camera.
    """
    L = np.asarray(lights_w, float).reshape(-1, 2)
    return project_poses(rig, ceiling_height_m, L, np.array([[x_m, y_m, yaw_rad]]))[0]


def project_poses(rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                  poses: np.ndarray) -> np.ndarray:
    """``(P, N, 2)`` pixels of ``N`` lights from ``P`` poses ``(x, y, yaw)``, one call."""
    R_vc, t_vc = mount_arrays(rig.mount)
    return ceiling.project_px(rig.camera, R_vc, t_vc,
                              ceiling.on_ceiling(lights_w, ceiling_height_m), poses)


def pixel_scale(rig: Rig, ceiling_height_m: float, q_v: np.ndarray) -> np.ndarray:
    """``(N, 2, 2)`` Jacobians d(pixel)/d(ceiling point in V, metres) at points ``q_v``
    (:func:`~ceilkit.runtime.geometry.ceiling.pixel_jacobian`)."""
    R_vc, t_vc = mount_arrays(rig.mount)
    return ceiling.pixel_jacobian(rig.camera, R_vc, t_vc, ceiling_height_m, q_v)


def jacobian_grid(rig: Rig, ceiling_height_m: float, step_px: int = 16) -> np.ndarray:
    """``(GH, GW, 2, 2)`` d(pixel)/d(ceiling point in V) on the pixel grid
    ``u = i step_px``, ``v = j step_px`` (the last node past the image edge); NaN where a
    pixel's ray does not rise. Read with :func:`interp_grid`."""
    cam = rig.camera
    us = np.arange(0, cam.width - 1 + step_px, step_px, dtype=float)
    vs = np.arange(0, cam.height - 1 + step_px, step_px, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    q, ok = ceiling_points(rig, ceiling_height_m, np.stack([uu.ravel(), vv.ravel()], 1))
    J = np.full((q.shape[0], 2, 2), np.nan)
    if np.any(ok):
        J[ok] = pixel_scale(rig, ceiling_height_m, q[ok])
    return J.reshape(vs.size, us.size, 2, 2)


def interp_grid(grid: np.ndarray, step_px: int, points_px: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a per-node table ``(GH, GW, ...)`` (nodes every
    ``step_px`` pixels from pixel 0) at pixels ``(N, 2)``; returns ``(N, ...)``."""
    px = np.asarray(points_px, float).reshape(-1, 2)
    gh, gw = grid.shape[:2]
    f = np.minimum(np.maximum(px / step_px, 0.0), (gw - 1.0, gh - 1.0))   # (u, v) in nodes
    i = np.minimum(f.astype(np.intp), (gw - 2, gh - 2))
    ab = f - i
    extra = (slice(None),) + (None,) * (grid.ndim - 2)
    a, b = ab[:, 0][extra], ab[:, 1][extra]
    # the four corners of each point's cell in one gather: (N, 4, ...)
    node = i[:, 1] * gw + i[:, 0]
    c = grid.reshape((gh * gw,) + grid.shape[2:])[node[:, None] + (0, 1, gw, gw + 1)]
    ua = 1 - a
    return (1 - b) * (ua * c[:, 0] + a * c[:, 1]) + b * (ua * c[:, 2] + a * c[:, 3])


class GridTable:
    """:func:`interp_grid` of one table, its cells' bilinear coefficients computed once
    (``v00, v01 - v00, v10 - v00, v11 - v10 - v01 + v00``): a reading is one gather and
    one product (the same numbers to ~1e-15 relative, in about half the time).

    Args:
        grid: ``(GH, GW, ...)`` per-node table (nodes every ``step_px`` px from pixel 0).

    Attributes:
        coef: ``((GH - 1) (GW - 1), 4, C)`` the cells' coefficients (read-only).
        limits: ``(1 / step_px, GW - 1, GH - 1, GW - 2, GH - 2, GW - 1)``: the scale,
            the clamps of a node coordinate and of a cell index, the cells per row (for
            a compiled reading: :func:`grid_row`).
    """

    def __init__(self, grid: np.ndarray, step_px: int) -> None:
        gh, gw = grid.shape[:2]
        self.tail = grid.shape[2:]
        g = np.asarray(grid, float).reshape(gh, gw, -1)
        v00, v01, v10, v11 = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
        coef = np.stack([v00, v01 - v00, v10 - v00, v11 - v10 - v01 + v00], axis=2)
        self.coef = np.ascontiguousarray(coef.reshape((gh - 1) * (gw - 1), 4, -1))
        self.coef.setflags(write=False)
        self._scale = 1.0 / step_px
        self._hi = np.array([gw - 1.0, gh - 1.0])
        self._cell_hi = np.array([gw - 2, gh - 2])
        self._cells_w = gw - 1
        self.limits = np.array([self._scale, gw - 1.0, gh - 1.0, gw - 2, gh - 2, gw - 1.0])
        self.limits.setflags(write=False)

    def __call__(self, points_px: np.ndarray) -> np.ndarray:
        """``(N, ...)`` the table at pixels ``(N, 2)`` (clamped to the grid)."""
        f = np.asarray(points_px, float).reshape(-1, 2) * self._scale
        np.maximum(f, 0.0, out=f)
        np.minimum(f, self._hi, out=f)
        i = np.minimum(f.astype(np.intp), self._cell_hi)
        f -= i                                                # (a, b) within the cell
        c = self.coef[i[:, 1] * self._cells_w + i[:, 0]]      # (N, 4, C)
        w = np.empty((f.shape[0], 1, 4))
        w[:, 0, 0] = 1.0
        w[:, 0, 1:3] = f
        w[:, 0, 3] = f[:, 0] * f[:, 1]
        return (w @ c).reshape((f.shape[0],) + self.tail)


@njit
def grid_row(coef, limits, u, v, out):  # pragma: no cover - compiled
    """Into ``out (C,)``: :class:`GridTable`'s reading at pixel ``(u, v)`` (``coef``,
    ``limits``: its :attr:`~GridTable.coef` and :attr:`~GridTable.limits`)."""
    scale, hi_u, hi_v, cell_hi_u, cell_hi_v, cells_w = (limits[0], limits[1], limits[2],
                                                        limits[3], limits[4], limits[5])
    fu = min(max(u * scale, 0.0), hi_u)
    fv = min(max(v * scale, 0.0), hi_v)
    iu = min(np.int64(fu), np.int64(cell_hi_u))
    iv = min(np.int64(fv), np.int64(cell_hi_v))
    a, b = fu - iu, fv - iv
    ab = a * b
    c = coef[iv * np.int64(cells_w) + iu]
    for j in range(out.size):
        out[j] = c[0, j] + a * c[1, j] + b * c[2, j] + ab * c[3, j]


@njit
def ceiling_points_core(px, lens_code, lens, R, t, dz, q):  # pragma: no cover - compiled
    """Into ``q (N, 2)``: :func:`ceiling_points` of pixels ``px (N, 2)`` in a compiled
    loop (``lens_code, lens``: :attr:`~ceilkit.runtime.geometry.camera.CameraModel.lens`;
    ``R, t``: :func:`mount_arrays`; ``dz``: the ceiling's height above the camera).
    Returns ``ok (N,)``: False where the ray does not rise (NaN there)."""
    n = px.shape[0]
    xy = np.empty_like(px)
    undistort_points(px, lens_code, lens, xy)
    ok = np.zeros(n, np.bool_)
    for i in range(n):
        ok[i], ox, oy = ceiling.meet_ceiling(R, xy[i, 0], xy[i, 1], dz, 0.0, RISE_SIN)
        q[i, 0] = t[0] + ox
        q[i, 1] = t[1] + oy
    return ok


def view_mask(rig: Rig, max_angle_rad: float) -> np.ndarray:
    """``(H, W)`` uint8: 255 where a pixel's ray rises within ``max_angle_rad`` of the
    vertical (computed on a 4x coarser grid, then enlarged)."""
    cam = rig.camera
    step = 4
    us = np.arange(0, cam.width, step) + (step - 1) / 2
    vs = np.arange(0, cam.height, step) + (step - 1) / 2
    uu, vv = np.meshgrid(us, vs)
    rays = np.hstack([cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1)),
                      np.ones((uu.size, 1))]) @ rig.mount.R_vehicle_cam.T
    cos_up = rays[:, 2] / np.linalg.norm(rays, axis=1)
    ok = np.isfinite(cos_up) & (cos_up > math.cos(max_angle_rad))
    small = np.where(ok, 255, 0).astype(np.uint8).reshape(uu.shape)
    big = cv2.resize(small, (us.size * step, vs.size * step), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(big[:cam.height, :cam.width])


def nadir_px(rig: Rig) -> tuple[float, float]:
    """The pixel that sees straight up (the principal point if the vertical is not in
    front of the camera)."""
    R_vc, _ = mount_arrays(rig.mount)
    up = R_vc.T @ np.array([0.0, 0.0, 1.0])   # the vertical seen from the camera
    nadir = rig.camera.project(up[None]) if up[2] > 1e-6 else np.full((1, 2), np.nan)
    if np.all(np.isfinite(nadir)):
        return float(nadir[0, 0]), float(nadir[0, 1])
    return rig.camera.cx, rig.camera.cy


def max_pair_m(rig: Rig, ceiling_height_m: float, gate_m: float) -> float:
    """The longest distance between two ceiling points one frame can see (from the
    image border, plus ``2 gate_m``); unbounded (1e9) when the view reaches the horizon."""
    cam = rig.camera
    w, h = cam.width, cam.height
    t = np.linspace(0, 1, 24)
    border = np.concatenate([np.stack([t * (w - 1), np.zeros_like(t)], 1),
                             np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
                             np.stack([np.zeros_like(t), t * (h - 1)], 1),
                             np.stack([np.full_like(t, w - 1), t * (h - 1)], 1)])
    q, ok = ceiling_points(rig, ceiling_height_m, border)
    if not np.all(ok):
        return 1e9
    return float(np.linalg.norm(q[:, None] - q[None], axis=2).max()) + 2 * gate_m


__all__ = ["GridTable", "ceiling_centroids", "ceiling_points", "ceiling_points_core",
           "grid_row", "interp_grid", "jacobian_grid", "max_pair_m", "mount_arrays",
           "nadir_px", "pixel_scale", "project_lights", "project_poses", "view_mask"]
