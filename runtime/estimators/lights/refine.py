"""The pose from matched lights: Gauss-Newton over ``(x, y, yaw)`` on pixel residuals.

:func:`refine_pose_ceiling` (what the estimator runs) linearizes the pixel residual at
each observation through its pixel Jacobian, so a step costs a 3x3 solve
(:func:`_solve3`) and no projection; :func:`refine_pose` reprojects the map lights
through the lens at every step and is kept as the reference it is tested against.
Both return the covariance ``s² (JᵀJ)⁻¹``, ``s`` the pixel residual (floored).

Convention (SPEC §1): ``X_W = Rz(yaw) X_V + (x, y, 0)``; ceiling points in V, metres;
pixels distorted.

Example::

    x, y, yaw, cov, res_px = refine_pose_ceiling(q_v, jac_px, lights_w, x0, y0, yaw0)
"""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.lights.rays import project_poses
from ceilkit.runtime.geometry.rotations import wrap_pi


def refine_pose(rig: Rig, ceiling_height_m: float, points_px: np.ndarray,
                lights_w: np.ndarray, x_m: float, y_m: float, yaw_rad: float,
                iterations: int = 3, sigma_floor_px: float = 0.1) -> tuple[
                    float, float, float, np.ndarray, np.ndarray]:
    """Minimize the reprojection error of matched lights over ``(x, y, yaw)``.

    Args:
        points_px: ``(K, 2)`` observed centroids (distorted pixels).
        lights_w: ``(K, 2)`` their map lights in W.
        x_m, y_m, yaw_rad: the starting pose.
        sigma_floor_px: least pixel noise assumed in the covariance.

    Returns:
        ``(x, y, yaw, cov (3, 3), residual norms (K,) px)``. The covariance is
        ``s² (JᵀJ)⁻¹``, ``s² = max(SSR / (2K - 3), sigma_floor²)``.
    """
    p = np.array([x_m, y_m, yaw_rad], float)
    obs = np.asarray(points_px, float).reshape(-1, 2)
    L = np.asarray(lights_w, float).reshape(-1, 2)
    k = obs.shape[0]
    eps = np.array([1e-5, 1e-5, 1e-6])

    def jac(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals at q and their forward-difference Jacobian, in one projection."""
        poses = np.repeat(q[None, :], 4, axis=0)
        poses[1:] += np.diag(eps)
        px = project_poses(rig, ceiling_height_m, L, poses)
        r0 = (px[0] - obs).ravel()
        Jq = np.stack([((px[a + 1] - obs).ravel() - r0) / eps[a] for a in range(3)], axis=1)
        return r0, Jq

    r, J = jac(p)
    for _ in range(iterations):
        if not np.all(np.isfinite(J)) or not np.all(np.isfinite(r)):
            break
        try:
            step = -np.linalg.solve(J.T @ J + 1e-9 * np.eye(3), J.T @ r)
        except np.linalg.LinAlgError:
            break
        r_new, J_new = jac(p + step)
        if not np.all(np.isfinite(r_new)) or r_new @ r_new > r @ r:
            break
        p, r, J = p + step, r_new, J_new
        if np.abs(step[:2]).max() < 1e-5 and abs(step[2]) < 1e-6:
            break
    dof = 2 * k - 3
    s2 = max(float(r @ r) / dof if dof > 0 else 0.0, sigma_floor_px ** 2)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    norms = np.linalg.norm(r.reshape(-1, 2), axis=1)
    return float(p[0]), float(p[1]), float(wrap_pi(p[2])), cov, norms


def refine_pose_ceiling(q_v: np.ndarray, jac_px: np.ndarray, lights_w: np.ndarray,
                        x_m: float, y_m: float, yaw_rad: float, iterations: int = 3,
                        sigma_floor_px: float = 0.1) -> tuple[
                            float, float, float, np.ndarray, np.ndarray]:
    """:func:`refine_pose` linearized at the observations: no projection per step.

    The pixel residual of light ``i`` is ``J_i (q̂_i - q_i)``, with ``q_i`` the observed
    ceiling point in V, ``q̂_i = Rz(-yaw) (L_i - t)`` the map light seen from the pose and
    ``J_i`` d(pixel)/d(ceiling point) at the observation (:func:`pixel_scale`). It differs
    from the reprojection error only at second order in the residual (sub-millimetre
    here), so both give the same pose; this one costs a few 3x3 solves.

    Args:
        q_v: ``(K, 2)`` observed ceiling points in V (metres).
        jac_px: ``(K, 2, 2)`` pixel Jacobians at those points (px per metre).
        lights_w: ``(K, 2)`` their map lights in W.
        x_m, y_m, yaw_rad: the starting pose.

    Returns:
        As :func:`refine_pose`: ``(x, y, yaw, cov (3, 3), residual norms (K,) px)``.
    """
    q = np.asarray(q_v, float).reshape(-1, 2)
    J = np.asarray(jac_px, float).reshape(-1, 2, 2)
    L = np.asarray(lights_w, float).reshape(-1, 2)
    k = q.shape[0]
    # With Rz(-yaw) = [[c, s], [-s, c]] and (u, v) = Rz(-yaw) t, the residuals are
    # r = c J L + s J L_perp - u J e_x - v J e_y - J q (L_perp = (L_y, -L_x)): a fixed
    # basis B (5, 2k) and pose-dependent weights, so the residuals and their Jacobian
    # at a pose are one (4, 5) @ (5, 2k) product
    B = np.empty((5, k, 2))
    np.matmul(J, L[:, :, None], out=B[0, :, :, None])
    np.matmul(J, (L[:, ::-1] * (1.0, -1.0))[:, :, None], out=B[1, :, :, None])
    B[2] = J[:, :, 0]
    B[3] = J[:, :, 1]
    np.matmul(J, q[:, :, None], out=B[4, :, :, None])
    B = B.reshape(5, -1)

    def resid(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(2k,)`` px (light by light, u then v) and their Jacobian
        transposed ``(3, 2k)`` (d/dx, d/dy, d/dyaw) at a pose."""
        c, s = math.cos(yaw), math.sin(yaw)
        u, v = c * x + s * y, c * y - s * x
        out = np.array([[c, s, -u, -v, -1.0],
                        [0.0, 0.0, -c, s, 0.0],
                        [0.0, 0.0, -s, -c, 0.0],
                        [-s, c, -v, u, 0.0]]) @ B
        return out[0], out[1:]

    p = (float(x_m), float(y_m), float(yaw_rad))
    r, At = resid(*p)
    ssr = float(r @ r)
    for _ in range(iterations):
        N = At @ At.T
        if not (math.isfinite(ssr) and math.isfinite(N[0, 0] + N[1, 1] + N[2, 2])):
            break
        step = _solve3(N, At @ r, 1e-9)
        if step is None:
            break
        p_new = (p[0] - step[0], p[1] - step[1], p[2] - step[2])
        r_new, At_new = resid(*p_new)
        ssr_new = float(r_new @ r_new)
        if not math.isfinite(ssr_new) or ssr_new > ssr:
            break
        p, r, At, ssr = p_new, r_new, At_new, ssr_new
        if max(abs(step[0]), abs(step[1])) < 1e-5 and abs(step[2]) < 1e-6:
            break
    dof = 2 * k - 3
    s2 = max(ssr / dof if dof > 0 else 0.0, sigma_floor_px ** 2)
    inv = _inv3(At @ At.T)
    cov = np.full((3, 3), np.inf) if inv is None else s2 * inv
    rr = r.reshape(-1, 2)
    norms = np.sqrt(rr[:, 0] ** 2 + rr[:, 1] ** 2)
    return p[0], p[1], float(wrap_pi(p[2])), cov, norms


def _inv3(N: np.ndarray) -> np.ndarray | None:
    """The inverse of a symmetric ``(3, 3)`` matrix by cofactors in plain floats (a
    tenth of ``np.linalg.inv``'s call), or ``None`` when it is singular or not finite."""
    (a, b, c), (_, d, e), (_, _, f) = N.tolist()
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    if not (math.isfinite(det) and abs(det) > 1e-300):
        return None
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    return np.array([[A, B, C], [B, D, E], [C, E, F]]) * (1.0 / det)


def _solve3(N: np.ndarray, g: np.ndarray, ridge: float) -> tuple[float, float, float] | None:
    """``(N + ridge I)⁻¹ g`` for a symmetric ``(3, 3)`` ``N`` and ``g`` ``(3,)`` by Cholesky,
    in plain floats (a 3x3 system costs less than the call to a general solver);
    ``None`` if the matrix is not positive definite."""
    (a, b, c), (_, d, e), (_, _, f) = N.tolist()
    a, d, f = a + ridge, d + ridge, f + ridge
    g0, g1, g2 = g.tolist()
    if not a > 0:
        return None
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    t = d - l10 * l10
    if not t > 0:
        return None
    l11 = math.sqrt(t)
    l21 = (e - l20 * l10) / l11
    t = f - l20 * l20 - l21 * l21
    if not t > 0:
        return None
    l22 = math.sqrt(t)
    z0 = g0 / l00
    z1 = (g1 - l10 * z0) / l11
    z2 = (g2 - l20 * z0 - l21 * z1) / l22
    x2 = z2 / l22
    x1 = (z1 - l21 * x2) / l11
    x0 = (z0 - l10 * x1 - l20 * x2) / l00
    return x0, x1, x2


__all__ = ["refine_pose", "refine_pose_ceiling"]
