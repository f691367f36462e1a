"""The pose from matched lights: Gauss-Newton over ``(x, y, yaw)`` on pixel residuals.

:func:`refine_pose_ceiling` (what the estimator runs) linearizes the pixel residual at
each observation through its pixel Jacobian, so a step costs a 3x3 solve
(:func:`_cholesky3`) and no projection, all in one compiled loop
(:func:`_gauss_newton`); :func:`refine_pose` reprojects the map lights through the lens
at every step and is kept as the reference it is tested against.
Both return the covariance ``s² (JᵀJ)⁻¹``, ``s`` the pixel residual (floored).
:func:`with_shifts` refits with shifts the frame's centroids share as more unknowns
(a thresholded frame's radial shift), their uncertainty in the pose's covariance.

Convention (SPEC §1): ``X_W = Rz(yaw) X_V + (x, y, 0)``; ceiling points in V, metres;
pixels distorted.

Example::

    x, y, yaw, cov, res_px = refine_pose_ceiling(q_v, jac_px, lights_w, x0, y0, yaw0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.lights.rays import project_poses
from ceilkit.runtime.geometry.fits import covering, student
from ceilkit.runtime.geometry.fits import scaled_inverse3 as _scaled_inverse
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

SIGMA_FLOOR_PX = 0.02
SHIFT_MIN_DOF = 2  # residual degrees of freedom :func:`with_shifts` leaves at least
"""Least pixel noise assumed in the covariance (px): a guard for a fit whose few
residuals happen to be tiny, not a noise model. The covariance is the residuals' own
``s² (JᵀJ)⁻¹`` (pooled over the run: :class:`NoisePool`): a real lens's unmodelled error
is in the residuals and so in ``s²``.
Measured (``benchmarks/bench_ambiguity.py``, noise 2, blur 0.8): the residuals give
a light-grid drive's mean NEES 2.11 (3 dof; band 2.41-3.65), 0.36 with the former
0.1 px floor; at noise 5, blur 1.2, 2.64, inside. With the shared radial shift counted
out (:func:`pattern_cover`, frames with more grey levels; 2026-12-07): 3.11 (band
2.38-3.69) and 3.39 (2.39-3.67)."""
POOL_MEMORY_DOF = 200.0
"""How many residual degrees of freedom a run's pixel-noise pool (:class:`NoisePool`)
remembers: past it the older sums are scaled down (a forgetting), so the pool follows
a change of the frames' noise. 200 because the variance of ``ν`` residuals is known to
``sqrt(2 / ν)`` = 10 % and its Student factor ``ν / (ν - 2)`` is 1.01 there: more
memory buys no accuracy the covariance could use. At 4 lights a fix (5 dof) it is 40
fixes, 1.3 s at 30 fps."""
JACKKNIFE_MAX_LEVERAGE = 0.99
"""A light whose own leverage in a fit (the largest eigenvalue of its 2x2 block of the
hat matrix) reaches this is left out of :func:`spot_jackknife`: its residual says
nothing about its error."""


@dataclass(frozen=True)
class NoisePool:
    """A run's pixel noise: the sum ``ssr_px2`` (px²) of the published fixes' squared
    pixel residuals and their residual degrees of freedom ``dof`` (a fit's own, as its
    covariance counts them: ``2K - 4`` with the shared radial pattern counted out,
    :func:`pattern_cover`; ``2K - 3`` where it cannot be, a fit of two lights). A fix's
    covariance takes ``s² = (ssr + its own SSR) / (dof + its ν)`` with the Student factor
    of that many degrees of freedom (:func:`pooled`, :func:`pattern_cover`): one frame's
    few residuals (a fit of two lights has one) estimate the variance no better than a
    chi-square of one degree of freedom, whose inverse has no mean (issue 36, held-out
    ``grid0`` of seed 7: every fix on two lights, ``s`` 0.001-0.02 px from its own
    residual against 0.026 px pooled). Held by the estimator between frames
    (``LightsEstimator.forget`` empties it); empty, a fix is its own residual's."""

    ssr_px2: float = 0.0
    dof: float = 0.0

    def added(self, own: np.ndarray) -> NoisePool:
        """The pool with a published fix's own ``[SSR px², ν]`` added (what
        :func:`pooled` or :func:`pattern_cover` wrote into ``noise[2:]``), at most
        :data:`POOL_MEMORY_DOF` degrees of freedom kept."""
        ssr, dof = self.ssr_px2 + float(own[0]), self.dof + float(own[1])
        if not (math.isfinite(ssr) and dof > 0):
            return self
        keep = min(1.0, POOL_MEMORY_DOF / dof)
        return NoisePool(ssr * keep, dof * keep)

    def array(self) -> np.ndarray:
        """``(4,)`` ``[ssr_px2, dof, nan, nan]``: the compiled calls read the pool and
        write the fix's own ``[SSR, ν]`` into the last two."""
        return np.array([self.ssr_px2, self.dof, math.nan, math.nan])


def pooled(fit: tuple[float, float, float, np.ndarray, np.ndarray], noise: np.ndarray
           ) -> tuple[float, float, float, np.ndarray, np.ndarray]:
    """``fit`` (:func:`refine_pose_ceiling`'s, covariance ``max(SSR / ν, floor²) N⁻¹``,
    ``ν = 2K - 3``) with the covariance ``max((pool SSR + SSR) / (pool dof + ν), floor²)
    student(pool dof + ν) N⁻¹``, the pool ``noise[:2]`` (:meth:`NoisePool.array`; the
    fit's own ``[SSR, ν]`` written into ``noise[2:]``); the pose kept."""
    res = np.asarray(fit[4], float)
    ssr, nu = float(res @ res), 2.0 * res.size - 3.0
    if nu <= 0 or not np.all(np.isfinite(fit[3])):
        return fit
    noise[2], noise[3] = ssr, nu
    own = max(ssr / nu, SIGMA_FLOOR_PX ** 2)
    dof = noise[1] + nu
    s2 = max((noise[0] + ssr) / dof, SIGMA_FLOOR_PX ** 2) * student(dof)
    return (*fit[:3], np.asarray(fit[3], float) * (s2 / own), fit[4])


class RefinedPose(NamedTuple):
    """A candidate's refined pose (:func:`~.estimator.refine_candidate`): its inlier
    ``pairs (K, 2)`` (spot index, light index in the map), the pose ``x_m, y_m,
    yaw_rad`` (m, rad; W), its ``cov (3, 3)`` and the residual norms ``res_px (K,)``
    (px)."""

    pairs: np.ndarray
    x_m: float
    y_m: float
    yaw_rad: float
    cov: np.ndarray
    res_px: np.ndarray


def refine_pose(rig: Rig, ceiling_height_m: float, points_px: np.ndarray,
                lights_w: np.ndarray, x_m: float, y_m: float, yaw_rad: float,
                iterations: int = 3, sigma_floor_px: float = SIGMA_FLOOR_PX) -> tuple[
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
                        sigma_floor_px: float = SIGMA_FLOOR_PX) -> tuple[
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
    q = arr(q_v, np.float64).reshape(-1, 2)
    J = arr(jac_px, np.float64).reshape(-1, 2, 2)
    L = arr(lights_w, np.float64).reshape(-1, 2)
    return _refine(q, J, L, float(x_m), float(y_m), float(yaw_rad), int(iterations),
                   float(sigma_floor_px))


@njit
def _refine(q, J, L, x, y, yaw, iterations, sigma_floor):  # pragma: no cover - compiled
    """:func:`refine_pose_ceiling` (also called by the lights' compiled window fix):
    ``(x, y, yaw in [-pi, pi), cov, residual norms)``. The covariance is ``s² N⁻¹`` by
    cofactors, inf where ``N`` is singular or not finite or a residual is NaN."""
    k = q.shape[0]
    pose = np.array([x, y, yaw])
    N = np.empty((3, 3))
    norms = np.empty(k)
    ssr = _gauss_newton(q, J, L, pose, iterations, N, norms)
    dof = 2 * k - 3
    s2 = max(ssr / dof if dof > 0 else 0.0, sigma_floor * sigma_floor)
    cov = np.full((3, 3), np.inf)
    if math.isfinite(ssr):
        _scaled_inverse(N, s2, cov)
    return pose[0], pose[1], (pose[2] + math.pi) % (2.0 * math.pi) - math.pi, cov, norms


def with_shifts(q_v: np.ndarray, jac_px: np.ndarray, lights_w: np.ndarray,
                shifts_px: np.ndarray,
                fit: tuple[float, float, float, np.ndarray, np.ndarray],
                sigma_floor_px: float = SIGMA_FLOOR_PX) -> tuple[
                    float, float, float, np.ndarray, np.ndarray]:
    """``fit`` (:func:`refine_pose_ceiling` of the same lights) refitted with ``m`` more
    unknowns ``e_j``: every observed centroid ``i`` moved by ``sum_j e_j S_ij``, a
    pattern shared by the frame's lights whose size the frame cannot tell from a pose
    move alone (a threshold's radial shift under the lens's fall-off, ``S_i = p_i - c``;
    a lamp's image larger or smaller than its map size, ``S_i`` its centroid offset:
    :class:`~.observe.Observation`). One Gauss-Newton step over the pose and ``e`` from
    ``fit`` (the model is linear in ``e``); the covariance is the pose block of
    ``s² (AᵀA)⁻¹``, ``s² = max(SSR / (2K - 3 - m), floor²)``: what the patterns can
    move is in it; widened (:func:`covering`) to cover what leaving any one light out
    moves the pose by (:func:`spot_jackknife`): a two-level frame's centroid errors are
    each lamp's own trim (its halo, its place under the fall-off, a fixture beside it),
    of very different sizes, and one lamp's bias pulls the pose by its leverage, which
    the pooled ``s²`` does not see. ``fit`` itself when fewer than
    :data:`SHIFT_MIN_DOF` residual degrees of freedom are left or the unknowns are not
    separable.

    Args:
        q_v, jac_px, lights_w: as :func:`refine_pose_ceiling` (``K`` lights).
        shifts_px: ``(K, m, 2)`` each light's centroid motion per unit of each ``e_j``
            (distorted pixels).
    """
    q = np.asarray(q_v, float).reshape(-1, 2)
    k = q.shape[0]
    S = np.asarray(shifts_px, float).reshape(k, -1, 2)
    m = S.shape[1]
    if m == 0 or 2 * k - 3 - m < SHIFT_MIN_DOF:
        return fit
    J = np.asarray(jac_px, float).reshape(-1, 2, 2)
    L = np.asarray(lights_w, float).reshape(-1, 2)
    x, y, yaw = fit[:3]
    c, s = math.cos(yaw), math.sin(yaw)
    d = L - np.array([x, y])
    qh = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    r = np.einsum("kab,kb->ka", J, qh - q).ravel()
    A = np.empty((2 * k, 3 + m))
    A[:, 0] = np.einsum("kab,b->ka", J, np.array([-c, s])).ravel()
    A[:, 1] = np.einsum("kab,b->ka", J, np.array([-s, -c])).ravel()
    A[:, 2] = np.einsum("kab,kb->ka", J, np.stack([qh[:, 1], -qh[:, 0]], axis=1)).ravel()
    A[:, 3:] = -S.transpose(0, 2, 1).reshape(2 * k, m)   # residual = predicted - observed
    scale = np.linalg.norm(A, axis=0)
    if not np.all(np.isfinite(A)) or not np.all(scale > 1e-12):
        return fit
    An = A / scale
    N = An.T @ An
    if np.linalg.cond(N) > 1e10:
        return fit
    Ni = np.linalg.inv(N) / np.outer(scale, scale)
    step = -Ni @ (A.T @ r)
    r_new = r + A @ step
    s2 = max(float(r_new @ r_new) / (2 * k - 3 - m), sigma_floor_px ** 2)
    norms = np.linalg.norm(r_new.reshape(-1, 2), axis=1)
    cov = covering(s2 * Ni[:3, :3], spot_jackknife(A, Ni, r_new)[:3, :3])
    return (float(x + step[0]), float(y + step[1]), float(wrap_pi(yaw + step[2])),
            cov, norms)


def pattern_cover(q_v: np.ndarray, jac_px: np.ndarray, lights_w: np.ndarray,
                  shifts_px: np.ndarray,
                  fit: tuple[float, float, float, np.ndarray, np.ndarray],
                  noise: np.ndarray | None = None) -> tuple[
                      float, float, float, np.ndarray, np.ndarray]:
    """``fit`` (:func:`refine_pose_ceiling` of the same lights) with the covariance of
    :func:`_pattern_cover`: the pose kept, ``s²`` counted without a centroid shift
    ``e S_i`` the frame's lights share (``shifts_px (K, 2)``: the radial ``p_i - c``)
    and pooled with the run's pixel noise ``noise[:2]`` (:meth:`NoisePool.array`, an
    empty pool when None; the fit's own ``[SSR, ν]`` written into ``noise[2:]``), and
    what the fitted ``e`` moves the pose by added. ``fit`` with the pooled noise
    (:func:`pooled`) when fewer than :data:`SHIFT_MIN_DOF` residual degrees of freedom
    are left or the pattern is not separable from a pose move."""
    noise = NoisePool().array() if noise is None else noise
    k = np.asarray(q_v).reshape(-1, 2).shape[0]
    if 2 * k - 4 < SHIFT_MIN_DOF or not np.all(np.isfinite(fit[3])):
        return pooled(fit, noise)
    cov = np.empty((3, 3))
    ok = _pattern_cover(arr(q_v, np.float64).reshape(-1, 2),
                        arr(jac_px, np.float64).reshape(-1, 2, 2),
                        arr(lights_w, np.float64).reshape(-1, 2),
                        np.array(fit[:3], float), arr(shifts_px, np.float64).reshape(-1, 2),
                        cov, noise)
    return (*fit[:3], cov, fit[4]) if ok else pooled(fit, noise)


@njit
def _pattern_cover(q, J, L, pose, S, cov, noise):  # pragma: no cover - compiled
    """The covariance (into ``cov``; False when it cannot be had) of the
    three-unknown fit at ``pose`` whose lights' centroid errors hold a shift ``e S_i``
    they share (``S (K, 2)`` px per unit ``e``) besides errors of their own, the run's
    pixel noise ``noise[:2]`` ``[SSR px², dof]`` so far (:class:`NoisePool`; the fit's
    own ``[SSR, ν]`` written into ``noise[2:]``).

    With ``A`` the residuals' pose Jacobian, ``N = AᵀA``, ``r`` the residuals at the
    fit, ``g = N⁻¹ AᵀS`` (what a unit ``e`` moves the pose by) and ``m = SᵀS - Sᵀ A g``
    (the part of the pattern no pose move takes): ``ê = Sᵀr / m``, and the covariance
    is ``s² student(ν) N⁻¹ + max(ê² - s² / m, 0) g gᵀ``, ``s² = max((pool SSR + rᵀr -
    (Sᵀr)² / m) / ν, floor²)``, ``ν = pool dof + 2K - 4`` (a variance estimated from
    ``ν`` residuals, the run's and the frame's:
    :func:`~ceilkit.runtime.geometry.fits.student`; ``ê²`` less its own variance). A
    frame's fall-off and halo move every intensity-weighted centroid towards the
    principal point by a place-dependent
    0.02-0.05 px (docs/methods/lights.md §4): in the residuals, where it was a third of
    ``s²``, but not in the pose of a centred upward camera (``g`` small), so the pooled
    ``s² N⁻¹`` over-covered (the spot grid's mean NEES 2.16 below 2.33-3.75; now 3.11
    in 2.38-3.69)."""
    k = q.shape[0]
    B = _basis(q, J, L)
    r = np.empty(2 * k)
    At = np.empty((3, 2 * k))
    ssr = _residuals(B, pose[0], pose[1], pose[2], r, At)
    N = np.empty((3, 3))
    h = np.empty(3)
    _normal(At, r, N, h)
    Ni = np.empty((3, 3))
    if not (math.isfinite(ssr) and _scaled_inverse(N, 1.0, Ni)):
        return False
    a_s = np.zeros(3)
    ss = sr = 0.0
    for j in range(2 * k):
        sj = S[j // 2, j % 2]
        ss += sj * sj
        sr += sj * r[j]
        for a in range(3):
            a_s[a] += At[a, j] * sj
    g = np.zeros(3)
    m = ss
    for a in range(3):
        for b in range(3):
            g[a] += Ni[a, b] * a_s[b]
    for a in range(3):
        m -= a_s[a] * g[a]
    if not (math.isfinite(m) and m > 1e-9 * max(ss, 1e-300)):
        return False
    e = sr / m
    noise[2], noise[3] = ssr - sr * e, 2.0 * k - 4.0
    nu = noise[1] + noise[3]
    s2 = max((noise[0] + noise[2]) / nu, SIGMA_FLOOR_PX * SIGMA_FLOOR_PX)
    e2 = max(e * e - s2 / m, 0.0)                 # ê² less its own variance s² / m
    s2 *= student(nu)
    for a in range(3):
        for b in range(3):
            cov[a, b] = s2 * Ni[a, b] + e2 * g[a] * g[b]
    return True


def spot_jackknife(A: np.ndarray, Ni: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``Σ_i δ_i δ_iᵀ``: what leaving each light out does to the unknowns of a linear
    least-squares fit (the leave-one-out jackknife; HC3 by pairs of rows).

    ``A (2K, n)`` the residuals' Jacobian (two rows per light), ``Ni = (AᵀA)⁻¹``,
    ``r (2K,)`` the residuals at the fit. Light ``i``'s rows ``A_i`` have the leverage
    ``H_i = A_i Ni A_iᵀ`` (2x2) and move the unknowns by ``δ_i = Ni A_iᵀ (I - H_i)⁻¹
    r_i`` when left out. A light whose leverage reaches :data:`JACKKNIFE_MAX_LEVERAGE`
    (the fit cannot see its own residual: no other light checks it) adds nothing; the
    pooled ``s² Ni`` covers it (:func:`covering`). Units those of the unknowns²."""
    k = A.shape[0] // 2
    P = (Ni @ A.T).T.reshape(k, 2, -1)                 # (k, 2, n): A_i Ni, rows of P_iᵀ
    Ak = A.reshape(k, 2, -1)
    G = np.eye(2) - np.einsum("kan,kbn->kab", Ak, P)   # I - H_i
    G = 0.5 * (G + np.swapaxes(G, 1, 2))
    det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
    tr = G[:, 0, 0] + G[:, 1, 1]
    low = 0.5 * (tr - np.sqrt(np.maximum(tr * tr - 4.0 * det, 0.0)))   # least eigenvalue
    use = low >= 1.0 - JACKKNIFE_MAX_LEVERAGE
    rk = r.reshape(k, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        u0 = (G[:, 1, 1] * rk[:, 0] - G[:, 0, 1] * rk[:, 1]) / det   # (I - H_i)⁻¹ r_i
        u1 = (G[:, 0, 0] * rk[:, 1] - G[:, 0, 1] * rk[:, 0]) / det
    d = P[:, 0, :] * u0[:, None] + P[:, 1, :] * u1[:, None]          # (k, n)
    d = d[use]
    return d.T @ d


def _inv3(N: np.ndarray) -> np.ndarray | None:
    """The inverse of a symmetric ``(3, 3)`` matrix by cofactors, or ``None`` when it is
    singular or not finite (:func:`_scaled_inverse`)."""
    out = np.empty((3, 3))
    return out if _scaled_inverse(arr(N, np.float64), 1.0, out) else None


@njit
def _gauss_newton(q, J, L, pose, iterations, N, norms):  # pragma: no cover - compiled
    """The Gauss-Newton of :func:`refine_pose_ceiling` from ``pose`` (moved in place):
    the sum of squared residuals at the end; ``N`` = JᵀJ there and ``norms`` each
    light's residual norm (px).

    With ``Rz(-yaw) = [[c, s], [-s, c]]`` and ``(u, v) = Rz(-yaw) t``, light i's
    residual is ``c J L + s J L_perp - u J e_x - v J e_y - J q`` (``L_perp = (L_y,
    -L_x)``): a fixed basis ``B (5, 2k)`` weighted by the pose. A step is kept only if
    it lowers the sum (a ridge of 1e-9 on the normal equations, a Cholesky solve);
    steps end below 1e-5 m and 1e-6 rad."""
    k = q.shape[0]
    B = _basis(q, J, L)
    r = np.empty(2 * k)
    At = np.empty((3, 2 * k))
    r_new = np.empty(2 * k)
    At_new = np.empty((3, 2 * k))
    g = np.empty(3)
    ssr = _residuals(B, pose[0], pose[1], pose[2], r, At)
    for _ in range(iterations):
        _normal(At, r, N, g)
        if not (math.isfinite(ssr) and math.isfinite(N[0, 0] + N[1, 1] + N[2, 2])):
            break
        ok, s0, s1, s2 = _cholesky3(N, g, 1e-9)
        if not ok:
            break
        x, y, yaw = pose[0] - s0, pose[1] - s1, pose[2] - s2
        ssr_new = _residuals(B, x, y, yaw, r_new, At_new)
        if not math.isfinite(ssr_new) or ssr_new > ssr:
            break
        pose[0], pose[1], pose[2] = x, y, yaw
        r, r_new = r_new, r                       # the new residuals kept, no copy
        At, At_new = At_new, At
        ssr = ssr_new
        if max(abs(s0), abs(s1)) < 1e-5 and abs(s2) < 1e-6:
            break
    _normal(At, r, N, g)
    for i in range(k):
        norms[i] = math.sqrt(r[2 * i] ** 2 + r[2 * i + 1] ** 2)
    return ssr


@njit
def _basis(q, J, L):  # pragma: no cover - compiled
    """The fixed basis ``B (5, 2k)`` of :func:`_gauss_newton`'s residuals."""
    k = q.shape[0]
    B = np.empty((5, 2 * k))
    for i in range(k):
        for a in range(2):
            j0, j1 = J[i, a, 0], J[i, a, 1]
            B[0, 2 * i + a] = j0 * L[i, 0] + j1 * L[i, 1]
            B[1, 2 * i + a] = j0 * L[i, 1] - j1 * L[i, 0]
            B[2, 2 * i + a] = j0
            B[3, 2 * i + a] = j1
            B[4, 2 * i + a] = j0 * q[i, 0] + j1 * q[i, 1]
    return B


@njit
def _residuals(B, x, y, yaw, r, At):  # pragma: no cover - compiled
    """Residuals ``r (2k,)`` and their Jacobian transposed ``At (3, 2k)`` at a pose (see
    :func:`_gauss_newton`); returns the sum of squares."""
    c, s = math.cos(yaw), math.sin(yaw)
    u, v = c * x + s * y, c * y - s * x
    ssr = 0.0
    for j in range(B.shape[1]):
        b0, b1, b2, b3, b4 = B[0, j], B[1, j], B[2, j], B[3, j], B[4, j]
        r[j] = c * b0 + s * b1 - u * b2 - v * b3 - b4
        At[0, j] = -c * b2 + s * b3
        At[1, j] = -s * b2 - c * b3
        At[2, j] = -s * b0 + c * b1 - v * b2 + u * b3
        ssr += r[j] * r[j]
    return ssr


@njit
def _normal(At, r, N, g):  # pragma: no cover - compiled
    """``N = At Atᵀ`` and ``g = At r``."""
    for a in range(3):
        g[a] = 0.0
        for b in range(3):
            N[a, b] = 0.0
    for j in range(At.shape[1]):
        for a in range(3):
            g[a] += At[a, j] * r[j]
            for b in range(3):
                N[a, b] += At[a, j] * At[b, j]


@njit
def _cholesky3(N, g, ridge):  # pragma: no cover - compiled
    """``(ok, x)``: ``x = (N + ridge I)⁻¹ g`` for a symmetric ``(3, 3)`` ``N`` by
    Cholesky, as ``(ok, x0, x1, x2)``; ``ok`` False if the matrix is not positive
    definite."""
    a, b, c = N[0, 0] + ridge, N[0, 1], N[0, 2]
    d, e, f = N[1, 1] + ridge, N[1, 2], N[2, 2] + ridge
    if not a > 0:
        return False, 0.0, 0.0, 0.0
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    t = d - l10 * l10
    if not t > 0:
        return False, 0.0, 0.0, 0.0
    l11 = math.sqrt(t)
    l21 = (e - l20 * l10) / l11
    t = f - l20 * l20 - l21 * l21
    if not t > 0:
        return False, 0.0, 0.0, 0.0
    l22 = math.sqrt(t)
    z0 = g[0] / l00
    z1 = (g[1] - l10 * z0) / l11
    z2 = (g[2] - l20 * z0 - l21 * z1) / l22
    x2 = z2 / l22
    x1 = (z1 - l21 * x2) / l11
    x0 = (z0 - l10 * x1 - l20 * x2) / l00
    return True, x0, x1, x2


def map_cov(lights_w: np.ndarray, x_m: float, y_m: float, sigma_m: np.ndarray
            ) -> np.ndarray:
    """``(3, 3)``: what the map's own error does to a pose fitted on ``lights_w``
    ``(K, 2)`` (W) from ``(x_m, y_m)``, each light's position off by an independent
    error of 1σ ``sigma_m (K,)`` per axis (a surveyed map's: SPEC §2 extension
    ``light_sigma``). A light moved by ``d`` moves the least-squares rigid fit of the
    plane by ``A⁺ d``, ``A`` the fit's design (a unit translation, and the turn about the
    pose: ``perp(L - t)``); so the pose takes ``A⁺ diag(σ²) A⁺ᵀ``. The fit's own
    weights (the pixel Jacobians) are left out: the same weight for every light (what a
    camera looking straight up gives). Issue 36: the surveyed lights of
    ``bench_heldout_texture.py --seed 3`` scatter1 are 0.3-4.7 mm off, against fixes of
    0.35 mm 1σ (docs/methods/lights.md, "A surveyed map's own error")."""
    L = np.asarray(lights_w, float).reshape(-1, 2)
    d = L - np.array([x_m, y_m])
    A = np.zeros((2 * L.shape[0], 3))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2] = -d[:, 1]
    A[1::2, 2] = d[:, 0]
    Ap = np.linalg.pinv(A)
    var = np.repeat(np.asarray(sigma_m, float).reshape(-1) ** 2, 2)
    return (Ap * var) @ Ap.T


@warmer
def _warm() -> None:
    q = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    refine_pose_ceiling(q, np.tile(np.eye(2) * 300.0, (3, 1, 1)), q, 0.0, 0.0, 0.0)
    _inv3(np.eye(3))
    pattern_cover(q, np.tile(np.eye(2) * 300.0, (3, 1, 1)), q, q[:, ::-1],
                  (0.0, 0.0, 0.0, np.eye(3), np.zeros(3)), NoisePool().array())


__all__ = ["NoisePool", "map_cov", "pattern_cover", "pooled", "refine_pose",
           "refine_pose_ceiling", "spot_jackknife", "with_shifts"]
