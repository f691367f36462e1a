"""The ``texture`` method under a rolling shutter: each feature's place on the ceiling
plane put back to the frame's stamp (docs/methods/texture.md, "Rolling shutter").

A rolling-shutter camera exposes row ``v`` at ``tau(v)`` after the stamp
(:func:`~ceilkit.runtime.geometry.shutter.row_times_s`). A feature the rectified patch
places at ``q`` (m, in V) was seen from the vehicle's pose at ``t + tau``; at constant
velocity ``(vx, vy, w)`` (W) that pose is the stamp's moved by ``(vx tau, vy tau, w tau)``,
so the same ceiling point in the stamp's V is

    q' = R(w tau) q + R(-yaw) (vx, vy) tau

(``yaw`` the vehicle's heading in W). The velocity is the prior's
(:func:`~ceilkit.runtime.estimators.rows.row_motion`), the fit's covariance grown by
what one sigma of each velocity component moves the pose (:func:`widened`), as in the
other methods.

Without a velocity the frame carries its own: its features, spread over the rows, see
the ceiling at different times, and in W the model reads

    p = R(yaw + w tau) q + (x + vx tau, y + vy tau)

six unknowns, the pose at the stamp and the velocity (:func:`joint_fit`: Gauss-Newton
on the inliers, collected again about each new fit). It is taken where the frame
determines the velocity (the normal matrix, scaled to a unit diagonal, conditioned
better than :data:`JOINT_MAX_COND`, and each velocity component's sigma from the fit
below the ``unknown_*`` one); its pose's covariance is then the joint fit's marginal.
Elsewhere the features are taken as seen at the stamp (velocity zero) with the
``unknown_*`` sigmas' growth (:func:`refit`).

Example::

    ro = Readout.of(rig, 2.7, options, prior)          # None for a global shutter
    tau = ro.times(q_v)                                # (N,) s, each feature's row time
    q_v = ro.unrolled(q_v, tau, yaw)                   # in the stamp's V
    fit = refit(ro, q_v, tau, p_w, qi, pose, 0.006, 0.001)   # MapFit | None
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.rows import ShutterOptions, row_motion
from ceilkit.runtime.estimators.texture.match import MapFit, _one_per_query, refine
from ceilkit.runtime.geometry.ceiling import on_ceiling, project_px
from ceilkit.runtime.geometry.shutter import row_times_s
from ceilkit.runtime.jit import arr, njit, warmer

JOINT_ROUNDS = 3          # the joint fit's inliers collected this many times ...
JOINT_ITERATIONS = 3      # ... each followed by this many Gauss-Newton steps
JOINT_MAX_COND = 1e6      # the scaled normal matrix's condition a joint fit may have


@dataclass(frozen=True, eq=False)
class Readout:
    """One frame's row model: where the rig images a ceiling point of V, the readout
    time and the motion the rows are corrected with.

    Attributes:
        rig: the rig (``camera``, ``mount``); ``ceiling_m``: the ceiling's height, m.
        readout_s: top row to bottom row, s (> 0).
        velocity: ``(vx m/s, vy m/s, yaw rate rad/s)`` in W (zero when unknown).
        sigma: their 1-sigma (the ``unknown_*`` options' when unknown).
        known: whether the prior gave the velocity (False: the frame's own is fitted
            where it determines it, :func:`refit`).
    """

    rig: Any
    ceiling_m: float
    readout_s: float
    velocity: tuple[float, float, float]
    sigma: tuple[float, float, float]
    known: bool = True

    @classmethod
    def of(cls, rig: Any, ceiling_m: float, options: ShutterOptions,
           prior: PoseEstimate | None) -> Readout | None:
        """The model for a frame with this prior, or None for a global shutter
        (``readout_ms`` 0)."""
        motion = row_motion(options, prior)
        if motion is None:
            return None
        return cls(rig, float(ceiling_m), options.readout_ms / 1e3, *motion,
                   known=prior is not None and prior.velocity is not None)

    def times(self, q_v: np.ndarray) -> np.ndarray:
        """``(N,)`` the row time of features at ceiling points ``q_v`` ``(N, 2)`` of V
        (as the rectified patch placed them), s after the stamp; 0 for a point the
        lens does not image (none the patch holds)."""
        if len(q_v) == 0:
            return np.zeros(0)
        cam, mount = self.rig.camera, self.rig.mount
        px = project_px(cam, np.asarray(mount.R_vehicle_cam, float),
                        np.asarray(mount.t_vehicle_cam, float),
                        on_ceiling(np.asarray(q_v, float), self.ceiling_m), np.zeros((1, 3)))[0]
        tau = row_times_s(px[:, 1], cam.height, self.readout_s)
        return np.where(np.isfinite(tau), tau, 0.0)

    def unrolled(self, q_v: np.ndarray, tau: np.ndarray, yaw: float | None,
                 velocity: tuple[float, float, float] | None = None) -> np.ndarray:
        """``(N, 2)`` features ``q_v`` seen at row times ``tau`` put in the stamp's V
        (the module's ``q'``) at ``velocity`` (default this frame's). ``yaw`` None:
        the turn only (the translation needs the heading; its share, ``|v| tau``, is
        6 mm at 0.5 m/s and a 25 ms readout)."""
        vx, vy, w = self.velocity if velocity is None else velocity
        a = w * tau
        c, s = np.cos(a), np.sin(a)
        q = np.asarray(q_v, float)
        out = np.column_stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]])
        if yaw is not None and (vx or vy):
            cy, sy = math.cos(yaw), math.sin(yaw)
            out[:, 0] += (cy * vx + sy * vy) * tau
            out[:, 1] += (-sy * vx + cy * vy) * tau
        return out


def widened(fit: MapFit, ro: Readout, q_raw: np.ndarray, tau: np.ndarray) -> MapFit:
    """``fit`` (on the pairs ``used`` of features ``q_raw`` as observed, ``tau`` their
    row times) with its covariance grown by the velocity's uncertainty: for each
    component moved by its sigma, the move of the rigid least squares' pose (to first
    order: ``d = (JᵀJ)⁻¹ Jᵀ e``, ``e`` the inliers' moves in W: ``(σ tau, 0)``,
    ``(0, σ tau)`` and ``σ tau perp(R q)``), its outer product added."""
    used = fit.used
    if len(used) < 3:
        return fit
    t = tau[used]
    yaw = fit.pose[2]
    q = ro.unrolled(q_raw[used], t, yaw)
    c, s = math.cos(yaw), math.sin(yaw)
    rx, ry = c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]
    n = float(len(used))
    jtj = np.array([[n, 0.0, -ry.sum()], [0.0, n, rx.sum()],
                    [-ry.sum(), rx.sum(), float(np.sum(rx * rx + ry * ry))]])
    sx, sy, sw = ro.sigma
    # Jᵀe for each component's moves e (columns): rows x, y, yaw (J_i = [I | perp(Rq_i)])
    jte = np.array([[sx * t.sum(), 0.0, -sw * np.sum(t * ry)],
                    [0.0, sy * t.sum(), sw * np.sum(t * rx)],
                    [-sx * np.sum(t * ry), sy * np.sum(t * rx),
                     sw * np.sum(t * (rx * rx + ry * ry))]])
    try:
        d = np.linalg.solve(jtj, jte)
    except np.linalg.LinAlgError:
        return fit
    return dataclasses.replace(fit, cov=np.array(fit.cov, float) + d @ d.T)


def refit(ro: Readout, q_raw: np.ndarray, tau: np.ndarray, p: np.ndarray, qi: np.ndarray,
          pose: tuple[float, float, float], tol_m: float, sigma_floor_m: float
          ) -> MapFit | None:
    """The least squares of a rolling-shutter frame's pose from a RANSAC ``pose``, on the
    pairs ``q_raw`` (V, as observed, row times ``tau``) ~ ``p`` (W) of query features
    ``qi``: without a known velocity, :func:`joint_fit` where the frame determines its
    velocity; otherwise :func:`~.match.refine` on the features put back to the stamp at
    ``pose``'s heading (:meth:`Readout.unrolled`), its covariance grown by the
    velocity's sigmas (:func:`widened`). None with fewer than three inliers."""
    if not ro.known:
        joint = joint_fit(q_raw, tau, p, qi, pose, tol_m, sigma_floor_m, ro.sigma)
        if joint is not None:
            return joint
    fit = refine(ro.unrolled(q_raw, tau, pose[2]), p, qi, pose, tol_m, sigma_floor_m)
    return None if fit is None else widened(fit, ro, q_raw, tau)


class RowPairs(NamedTuple):
    """Correspondences with their row times, as :func:`_joint` takes them: ``q (M, 2)``
    in V as observed ~ ``p (M, 2)`` in W (m), of query features ``qi (M,)``, seen
    ``tau (M,)`` s after the stamp."""

    q: np.ndarray
    p: np.ndarray
    qi: np.ndarray
    tau: np.ndarray


class JointFitting(NamedTuple):
    """:func:`joint_fit`'s settings: the inlier tolerance ``tol`` and the covariance's
    floor ``sigma_floor`` (m), the ``rounds`` of collecting the inliers, the Gauss-Newton
    ``iterations`` after each, the scaled normal matrix's largest condition
    ``max_cond``."""

    tol: float
    sigma_floor: float
    rounds: int
    iterations: int
    max_cond: float


def joint_fit(q_raw: np.ndarray, tau: np.ndarray, p: np.ndarray, qi: np.ndarray,
              pose: tuple[float, float, float], tol_m: float, sigma_floor_m: float,
              sigma: tuple[float, float, float]) -> MapFit | None:
    """The pose at the stamp and the velocity fitted together (the module's six-unknown
    model) from ``pose`` at rest, on the pairs within ``tol_m`` (one per query feature,
    the nearest), collected again :data:`JOINT_ROUNDS` times. Its ``cov`` is the pose's
    marginal of ``s² (JᵀJ)⁻¹`` (``s²`` the residuals' variance per axis, ``2n - 6``
    degrees of freedom, never below ``sigma_floor_m²``), its ``velocity`` and
    ``velocity_sigma`` the fit's (W; m/s, m/s, rad/s). None where the frame does not
    determine the velocity: fewer than six inliers, the normal matrix scaled to a unit
    diagonal conditioned worse than :data:`JOINT_MAX_COND`, or a component's sigma not
    below ``sigma``'s (the one assumed without a velocity). One compiled loop."""
    good, th, cov, used, rms = _joint(
        RowPairs(arr(q_raw, np.float64), arr(p, np.float64), arr(qi, np.int64),
                 arr(tau, np.float64)),
        (float(pose[0]), float(pose[1]), float(pose[2])),
        JointFitting(float(tol_m), float(sigma_floor_m), JOINT_ROUNDS, JOINT_ITERATIONS,
                     JOINT_MAX_COND))
    if not good:
        return None
    vs = np.sqrt(np.maximum(np.diag(cov)[3:], 0.0))
    if not np.all(vs < np.asarray(sigma, float)):
        return None
    return MapFit((float(th[0]), float(th[1]), float(th[2])), cov[:3, :3].copy(), used, rms,
                  (float(th[3]), float(th[4]), float(th[5])), tuple(float(v) for v in vs))


@njit
def _joint(pairs, pose, fitting):  # pragma: no cover - compiled
    """:func:`joint_fit`: ``(good, theta (6,): x, y, yaw, vx, vy, w, cov (6, 6), used
    (indices), rms_m)``."""
    th = np.array([pose[0], pose[1], pose[2], 0.0, 0.0, 0.0])
    used = np.zeros(0, np.int64)
    for _ in range(fitting.rounds):
        used = _one_per_query(_joint_residuals(pairs, th), pairs.qi, fitting.tol)
        if len(used) < 6:
            return False, th, np.zeros((6, 6)), used, 0.0
        for _ in range(fitting.iterations):
            n, g, _ss = _normal(pairs, th, used)
            if not _conditioned(n, fitting.max_cond):
                return False, th, np.zeros((6, 6)), used, 0.0
            th -= np.linalg.solve(n, g)
    n, g, ss = _normal(pairs, th, used)
    if not _conditioned(n, fitting.max_cond):
        return False, th, np.zeros((6, 6)), used, 0.0
    m = len(used)
    s2 = max(ss / max(2 * m - 6, 1), fitting.sigma_floor * fitting.sigma_floor)
    return True, th, s2 * np.linalg.inv(n), used, math.sqrt(ss / m)


@njit
def _joint_residuals(pairs, th):  # pragma: no cover - compiled
    """``(M,)`` distances ``|R(yaw + w tau) q + (x, y) + (vx, vy) tau - p|``, m."""
    q, p, tau = pairs.q, pairs.p, pairs.tau
    out = np.empty(len(q))
    for k in range(len(q)):
        a = th[2] + th[5] * tau[k]
        c, s = math.cos(a), math.sin(a)
        out[k] = math.hypot(c * q[k, 0] - s * q[k, 1] + th[0] + th[3] * tau[k] - p[k, 0],
                            s * q[k, 0] + c * q[k, 1] + th[1] + th[4] * tau[k] - p[k, 1])
    return out


@njit
def _normal(pairs, th, used):  # pragma: no cover - compiled
    """The Gauss-Newton system of the pairs ``used`` at ``theta``: ``(JᵀJ (6, 6), Jᵀe
    (6,), eᵀe)``, the row of a pair's x and y ``[I | perp(r) | tau I | tau perp(r)]``
    with ``r = R(yaw + w tau) q``."""
    q, p, tau = pairs.q, pairs.p, pairs.tau
    n = np.zeros((6, 6))
    g = np.zeros(6)
    ss = 0.0
    jx = np.zeros(6)
    jy = np.zeros(6)
    for k in used:
        t = tau[k]
        a = th[2] + th[5] * t
        c, s = math.cos(a), math.sin(a)
        rx, ry = c * q[k, 0] - s * q[k, 1], s * q[k, 0] + c * q[k, 1]
        ex = rx + th[0] + th[3] * t - p[k, 0]
        ey = ry + th[1] + th[4] * t - p[k, 1]
        jx[0], jx[1], jx[2], jx[3], jx[4], jx[5] = 1.0, 0.0, -ry, t, 0.0, -ry * t
        jy[0], jy[1], jy[2], jy[3], jy[4], jy[5] = 0.0, 1.0, rx, 0.0, t, rx * t
        for i in range(6):
            g[i] += jx[i] * ex + jy[i] * ey
            for j in range(6):
                n[i, j] += jx[i] * jx[j] + jy[i] * jy[j]
        ss += ex * ex + ey * ey
    return n, g, ss


@njit
def _conditioned(n, max_cond):  # pragma: no cover - compiled
    """Whether the normal matrix ``n``, scaled to a unit diagonal, has a condition
    number below ``max_cond`` (its column scales, metres against m/s over a few ms,
    differ by 100x)."""
    d = np.sqrt(np.diag(n))
    if not np.all(d > 0.0):
        return False
    w = np.linalg.eigvalsh(n / np.outer(d, d))
    return w[0] > 0.0 and w[-1] < max_cond * w[0]


@warmer
def _warm() -> None:
    a = np.linspace(-0.4, 0.4, 8)
    q = np.column_stack([a, a[::-1] ** 2])
    joint_fit(q, a * 0.03, q, np.arange(8), (0.0, 0.0, 0.0), 0.03, 0.001, (0.5, 0.5, 0.5))


__all__ = ["JOINT_MAX_COND", "Readout", "joint_fit", "refit", "widened"]
