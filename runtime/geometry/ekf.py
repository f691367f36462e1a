"""Extended Kalman filter math over the vehicle's planar pose (pure functions).

The state (:data:`STATE`, shape ``(7,)``) is the vehicle pose in W, its velocity in W
and the wheel odometry's scale factor::

    s = (x_m, y_m, yaw_rad, vx_mps, vy_mps, vyaw_rps, odo_scale)

with its ``(7, 7)`` covariance ``P``. Every function takes arrays and returns new
arrays; nothing is kept between calls (the orchestration in ``runtime/fusion.py``
keeps the state, the time and the measurement buffer).

Convention: SPEC §1. Odometry increments are in V (the vehicle frame at the previous
row): ``(dx_m, dy_m)`` forward/left, ``dyaw_rad`` counter-clockwise.

Example::

    s, P = initial_state((1.0, 2.0, 0.1), np.diag([1e-4, 1e-4, 1e-4]))
    s, P = predict_cv(s, P, 0.033, MotionNoise())
    s, P, nis = update(s, P, np.array([1.01, 2.0, 0.1]), FULL_POSE, np.eye(3) * 1e-4)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ceilkit.runtime.geometry.rotations import wrap_pi

STATE = ("x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps", "vyaw_rps", "odo_scale")
N_STATE = len(STATE)
YAW = 2
SCALE = 6
FULL_POSE = (0, 1, 2)
"""Rows of a full-pose fix (lights, block)."""
Y_YAW = (1, 2)
"""Rows of a corridor fix (x unobserved)."""
YAW_ONLY = (2,)
"""Rows of a heading-only fix."""


@dataclass(frozen=True)
class MotionNoise:
    """Process noise.

    Attributes:
        accel_mps2: white-acceleration density of the constant-velocity model, m/s² /√Hz.
        turn_rps2: white angular acceleration density, rad/s² /√Hz.
        odo_rel: 1σ of an odometry increment's length, as a share of the length.
        odo_lateral_rel: 1σ sideways slip, as a share of the length.
        odo_yaw_rel: 1σ of an odometry turn, as a share of the turn.
        odo_yaw_per_m_rad: 1σ heading drift per metre driven, rad/√m.
        scale_walk: random walk of the odometry scale, 1/√s.
        hold_mps: position random walk while the odometry holds the pose between rows,
            m/√s.
        hold_rps: heading random walk while the odometry holds the pose, rad/√s.
    """

    accel_mps2: float = 0.8
    turn_rps2: float = math.radians(60.0)
    odo_rel: float = 0.01
    odo_lateral_rel: float = 0.01
    odo_yaw_rel: float = 0.02
    odo_yaw_per_m_rad: float = math.radians(0.5)
    scale_walk: float = 1e-4
    hold_mps: float = 0.002
    hold_rps: float = math.radians(0.01)


def initial_state(pose: tuple[float, float, float], pose_cov: np.ndarray,
                  speed_sigma_mps: float = 1.0, turn_sigma_rps: float = 1.0,
                  scale_sigma: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A state at ``pose`` (x, y, yaw) with ``pose_cov`` (3, 3), at rest, scale 1."""
    s = np.zeros(N_STATE)
    s[:3] = pose
    s[SCALE] = 1.0
    P = np.zeros((N_STATE, N_STATE))
    P[:3, :3] = pose_cov
    P[3, 3] = P[4, 4] = speed_sigma_mps ** 2
    P[5, 5] = turn_sigma_rps ** 2
    P[SCALE, SCALE] = scale_sigma ** 2
    return s, P


def predict_cv(s: np.ndarray, P: np.ndarray, dt_s: float,
               noise: MotionNoise) -> tuple[np.ndarray, np.ndarray]:
    """Constant velocity over ``dt_s`` (>= 0) with white-acceleration process noise."""
    if dt_s <= 0:
        return s, P
    F = np.eye(N_STATE)
    F[0, 3] = F[1, 4] = F[2, 5] = dt_s
    s2 = F @ s
    s2[YAW] = wrap_pi(s2[YAW])
    Q = np.zeros((N_STATE, N_STATE))
    for pos, vel, q in ((0, 3, noise.accel_mps2), (1, 4, noise.accel_mps2),
                        (2, 5, noise.turn_rps2)):
        Q[pos, pos], Q[pos, vel], Q[vel, vel] = cv_noise(q, dt_s)
        Q[vel, pos] = Q[pos, vel]
    Q[SCALE, SCALE] = noise.scale_walk ** 2 * dt_s
    return s2, F @ P @ F.T + Q


def cv_noise(q: float, dt_s: float) -> tuple[float, float, float]:
    """The process noise ``(pp, pv, vv)`` of one axis (a position and its rate) over
    ``dt_s`` under white acceleration of density ``q`` (per sqrt(Hz)): what
    :func:`predict_cv` adds to each of its axes, and the single-method tracker to its
    own (``tracking._advanced``)."""
    q2 = q * q
    return q2 * dt_s ** 3 / 3, q2 * dt_s ** 2 / 2, q2 * dt_s


def predict_hold(s: np.ndarray, P: np.ndarray, dt_s: float,
                 noise: MotionNoise) -> tuple[np.ndarray, np.ndarray]:
    """The pose held between odometry rows (the rows carry the motion)."""
    if dt_s <= 0:
        return s, P
    P2 = P.copy()
    h = noise.hold_mps ** 2 * dt_s
    P2[0, 0] += h
    P2[1, 1] += h
    P2[YAW, YAW] += noise.hold_rps ** 2 * dt_s
    P2[SCALE, SCALE] += noise.scale_walk ** 2 * dt_s
    return s, P2


def predict_odometry(s: np.ndarray, P: np.ndarray, d_v: tuple[float, float, float],
                     dt_s: float, noise: MotionNoise, cov_v: np.ndarray | None = None,
                     scaled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Apply one odometry increment ``(dx_m, dy_m, dyaw_rad)`` in V; the velocity
    becomes the increment over ``dt_s``.

    ``scaled``: the increment is multiplied by the state's odometry scale (wheel
    odometry); ``False`` for an increment whose scale is its own (the ceiling-plane
    odometry of a camera). ``cov_v``: the increment's ``(3, 3)`` covariance in V
    (dx, dy, dyaw); ``None``: the wheel model of ``noise`` (a share of the length and
    of the turn, a heading drift per metre)."""
    dx, dy, dyaw = d_v
    yaw, k = s[YAW], (s[SCALE] if scaled else 1.0)
    c, sn = math.cos(yaw), math.sin(yaw)
    step = np.array([c * dx - sn * dy, sn * dx + c * dy])
    s2 = s.copy()
    s2[0:2] = s[0:2] + k * step
    s2[YAW] = wrap_pi(yaw + dyaw)
    if dt_s > 0:
        s2[3:5] = k * step / dt_s
        s2[5] = dyaw / dt_s
    F = np.eye(N_STATE)
    F[0, YAW] = k * (-sn * dx - c * dy)
    F[1, YAW] = k * (c * dx - sn * dy)
    if scaled:
        F[0:2, SCALE] = step
    length = math.hypot(dx, dy)
    R_wv = np.array([[c, -sn], [sn, c]])
    Q = np.zeros((N_STATE, N_STATE))
    if cov_v is None:
        Q_v = np.diag([(noise.odo_rel * length) ** 2, (noise.odo_lateral_rel * length) ** 2])
        Q[0:2, 0:2] = R_wv @ Q_v @ R_wv.T
        Q[YAW, YAW] = (noise.odo_yaw_rel * dyaw) ** 2 + noise.odo_yaw_per_m_rad ** 2 * length
    else:
        C = np.asarray(cov_v, float)
        G = np.zeros((3, 3))
        G[0:2, 0:2] = k * R_wv
        G[2, 2] = 1.0
        Q[np.ix_(FULL_POSE, FULL_POSE)] = G @ (0.5 * (C + C.T)) @ G.T
    Q[SCALE, SCALE] = noise.scale_walk ** 2 * max(dt_s, 0.0)
    return s2, F @ P @ F.T + Q


def innovation(s: np.ndarray, P: np.ndarray, z: np.ndarray, rows: tuple[int, ...],
               R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(y, S)``: the residual of measurement ``z`` of state ``rows`` (yaw wrapped),
    and its covariance ``H P H^T + R``."""
    idx = list(rows)
    y = np.asarray(z, float) - s[idx]
    for i, r in enumerate(rows):
        if r == YAW:
            y[i] = wrap_pi(y[i])
    S = P[np.ix_(idx, idx)] + R
    return y, S


def nis(y: np.ndarray, S: np.ndarray) -> float:
    """The normalized innovation squared ``y^T S^-1 y`` (chi-square, ``len(y)`` dof)."""
    return float(y @ np.linalg.solve(S, y))


def update(s: np.ndarray, P: np.ndarray, z: np.ndarray, rows: tuple[int, ...],
           R: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The Kalman update with a direct measurement of state ``rows`` (Joseph form):
    ``(s, P, nis)``."""
    y, S = innovation(s, P, z, rows, R)
    idx = list(rows)
    PHt = P[:, idx]
    K = np.linalg.solve(S, PHt.T).T
    s2 = s + K @ y
    s2[YAW] = wrap_pi(s2[YAW])
    H = np.zeros((len(idx), N_STATE))
    H[np.arange(len(idx)), idx] = 1.0
    A = np.eye(N_STATE) - K @ H
    P2 = A @ P @ A.T + K @ R @ K.T
    return s2, 0.5 * (P2 + P2.T), nis(y, S)


def chi2_cdf(x: float, dof: int) -> float:
    """The chi-square CDF for 1, 2 or 3 degrees of freedom (closed forms)."""
    if x <= 0:
        return 0.0
    h = x / 2.0
    if dof == 1:
        return math.erf(math.sqrt(h))
    if dof == 2:
        return 1.0 - math.exp(-h)
    if dof == 3:
        return math.erf(math.sqrt(h)) - math.sqrt(2.0 * x / math.pi) * math.exp(-h)
    raise ValueError(f"dof must be 1, 2 or 3, found {dof}")


CHI2_TABLE_DOF = 1024
"""Degrees of freedom ``1..CHI2_TABLE_DOF`` of a probability's chi-square quantiles are
made in one call (:func:`chi2_table`): a model check's degrees of freedom change from
frame to frame (a corridor drive's 2..70, a block's 78..155), so that a quantile per
new value, 0.07-0.2 ms each, was made on frames (frame 0's among them)."""


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile (0 < p < 1) of the chi-square law with ``dof`` degrees of
    freedom (exact: ``scipy.stats.chi2.ppf``; inf for ``dof < 1``), looked up in
    :func:`chi2_table` up to :data:`CHI2_TABLE_DOF`. The one implementation: the
    fusion's gates and the estimators' model checks
    (:mod:`~ceilkit.runtime.estimators.honesty`) both call it.

    ``scipy.stats`` takes seconds to import on a slow machine; it is imported on the
    first call, which the callers make before the first frame (the fusion's gates at
    construction, honesty's warmer at :func:`~ceilkit.runtime.jit.warm_up`: the table
    of the model checks' and the priors' probability, 0.999, whole).

    >>> round(chi2_quantile(0.999, 3), 3)
    16.266
    """
    if dof < 1:
        return math.inf
    if dof <= CHI2_TABLE_DOF:
        return float(chi2_table(p)[int(dof) - 1])
    return _chi2_ppf(p, int(dof))


@lru_cache(maxsize=16)
def chi2_table(p: float) -> np.ndarray:
    """``(CHI2_TABLE_DOF,)`` read-only: the ``p`` quantiles of chi-square with 1, 2, ...
    degrees of freedom, in one vectorized ``scipy.stats.chi2.ppf`` call (about 1 ms;
    the same numbers as one call per value)."""
    from scipy.stats import chi2

    table = np.asarray(chi2.ppf(p, np.arange(1, CHI2_TABLE_DOF + 1)), float)
    table.flags.writeable = False
    return table


@lru_cache(maxsize=256)
def _chi2_ppf(p: float, dof: int) -> float:
    """:func:`chi2_quantile` beyond the table, one value (cached)."""
    from scipy.stats import chi2

    return float(chi2.ppf(p, dof))


def mean_nees_band(n: int, dof: int, p: float = 0.95) -> tuple[float, float]:
    """The two-sided ``p`` band of the mean of ``n`` independent chi-square(``dof``)
    values (Wilson-Hilferty for chi-square(n dof), divided by n)."""
    k = n * dof
    z = math.sqrt(2.0) * _erfinv(p)
    c = 2.0 / (9.0 * k)
    return (k * (1 - c - z * math.sqrt(c)) ** 3 / n, k * (1 - c + z * math.sqrt(c)) ** 3 / n)


def _erfinv(p: float) -> float:
    lo, hi = 0.0, 6.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if math.erf(mid) < p else (lo, mid)
    return 0.5 * (lo + hi)


def prob_within_radius(cov_xy: np.ndarray, radius_m: float) -> float:
    """A lower bound of P(‖e‖ < radius) for a zero-mean Gaussian error of covariance
    ``cov_xy`` (1x1 or 2x2): ``1 - exp(-r² / (2 λ_max))`` in 2-D, ``erf(r / (σ √2))``
    in 1-D; 0 when a variance is not finite."""
    C = np.atleast_2d(np.asarray(cov_xy, float))
    if not np.all(np.isfinite(C)):
        return 0.0
    if C.shape == (1, 1):
        sd = math.sqrt(max(float(C[0, 0]), 1e-30))
        return math.erf(radius_m / (sd * math.sqrt(2.0)))
    lam = max(float(np.linalg.eigvalsh(C)[-1]), 1e-30)
    return 1.0 - math.exp(-radius_m ** 2 / (2.0 * lam))


__all__ = ["STATE", "N_STATE", "FULL_POSE", "Y_YAW", "YAW_ONLY", "MotionNoise",
           "initial_state", "predict_cv", "predict_hold", "predict_odometry", "innovation",
           "nis", "update", "chi2_cdf", "chi2_quantile", "chi2_table", "mean_nees_band",
           "prob_within_radius"]
