"""When a prior may choose among the poses a frame supports: the one rule (issue 36).

A frame of a repeating ceiling supports several poses alike (its ``hypotheses``). A
prior (the track's prediction, a ``--start-pose``, a stated heading) may choose one of
them only when it is the **only** one the prior allows: inside the prior's
``PRIOR_P`` region, with the prior's covariance and the pose's own added. None
inside: the frame contradicts the prior (a kidnap, a wrong start pose), and the
prior chooses nothing. Several inside: the prior is too vague to tell them. In both
cases the frame stays ``ambiguous``; a prior never picks "the nearest" twin.

A prior without a covariance (a start pose, the constant-velocity tracker's first
frames) is given :data:`DEFAULT_PRIOR_SIGMA`. A coordinate the prior does not give
(``None``, or an infinite variance: x of a corridor track) is not compared.

Example::

    k = prior_choice(prior, [(h.x_m, h.y_m, h.yaw_rad, h.cov) for h in hyps])
    if k is None:
        ...   # ambiguous: the prior does not single one out
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.geometry.ekf import chi2_quantile, chi2_table
from ceilkit.runtime.jit import arr, njit, warmer

PRIOR_P = 0.999
"""The probability of the region a prior allows (chi-square quantile of its
Mahalanobis distance)."""
DEFAULT_PRIOR_SIGMA = (0.1, math.radians(5.0))
"""1σ (m, rad) of a prior that carries no covariance: a start pose's default."""
MAX_SPEED_MPS = 2.5
"""The vehicle's stated maximum speed (m/s) over the floor: the farthest a track may have
moved since its last fix, for the tracker's gate and the fusion's new tracks
(``max_speed_mps`` of both options; docs/config.md, "The vehicle's limits"). A vehicle
cannot cross a 0.6 m tile in one 0.1 s frame, so a tile's twin is never within reach."""
MAX_TURN_RPS = math.radians(90.0)
"""The vehicle's stated maximum turn rate (rad/s), as :data:`MAX_SPEED_MPS`
(``max_turn_rps``)."""

Pose = tuple[float | None, float | None, float, "np.ndarray | None"]


def prior_cov(prior: PoseEstimate) -> np.ndarray:
    """The prior's ``(3, 3)`` covariance, :data:`DEFAULT_PRIOR_SIGMA` where it has none."""
    if prior.cov is not None:
        c = np.array(prior.cov, float)
        if c.shape == (3, 3):
            return c
    sp, sr = DEFAULT_PRIOR_SIGMA
    return np.diag([sp * sp, sp * sp, sr * sr])


def prior_distance(prior: PoseEstimate, pose: Pose) -> tuple[float, int]:
    """``(d2, dof)``: the squared Mahalanobis distance of ``pose`` ``(x, y, yaw, cov)``
    from ``prior`` over the coordinates both give (yaw always), with both covariances."""
    d2, dof = _distances(prior, prior_cov(prior), (pose,))
    return float(d2[0]), int(dof[0])


def _distances(prior: PoseEstimate, P: np.ndarray, poses: Sequence[Pose]
               ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`prior_distance` of each of ``poses`` in one compiled call
    (:func:`_distances_core`) with the prior's covariance ``P`` ``(3, 3)`` given
    (:func:`prior_cov`, made once for all the poses of :func:`prior_choice`; a tile
    grid's window fix checks 15 poses a frame): ``(d2 (K,), dof (K,))``."""
    gx, gy = prior.x_m is not None, prior.y_m is not None
    flat: list[float] = []      # one flat list: numpy reads it without finding a shape
    for x, y, yaw, _ in poses:
        flat += (0.0 if x is None else x, 0.0 if y is None else y, yaw,
                 1.0 if gx and x is not None else 0.0, 1.0 if gy and y is not None else 0.0)
    rows = np.array(flat, float).reshape(-1, 5)
    covs = _NO_COVS
    if any(pose[3] is not None for pose in poses):
        covs = np.full((len(poses), 3, 3), np.nan)     # NaN: none (not finite: not added)
        for k, pose in enumerate(poses):
            if pose[3] is not None:
                covs[k] = np.asarray(pose[3], float)
    ref = (0.0 if prior.x_m is None else prior.x_m, 0.0 if prior.y_m is None else prior.y_m,
           prior.yaw_rad)
    f = np.float64
    return _distances_core(arr(ref, f), arr(P, f), arr(rows, f), arr(covs, f))


_NO_COVS = arr(np.empty((0, 3, 3)), np.float64)
""":func:`_distances`' ``covs`` when no pose carries a covariance."""


@njit
def _distances_core(ref, P, poses, covs):  # pragma: no cover - compiled
    """:func:`_distances`: the prior's ``ref (3,)`` ``(x, y, yaw)`` and ``P (3, 3)``;
    per pose ``poses (K, 5)``: its x, y, yaw and whether its x and y are compared
    (1: the pose and the prior both give it; and ``P``'s variance is finite), and its
    covariance ``covs (K, 3, 3)`` (added where finite over the rows compared; none
    when ``covs`` is empty): ``(d2, dof)``, the yaw's error wrapped into [-pi, pi)
    (:func:`~..geometry.rotations.wrap_pi`)."""
    n_k = poses.shape[0]
    d2 = np.empty(n_k)
    dof = np.empty(n_k, np.int64)
    rows = np.empty(3, np.int64)
    e = np.empty(3)
    a = np.empty((3, 4))
    for k in range(n_k):
        n = 0
        for i in range(2):
            if poses[k, 3 + i] != 0.0 and math.isfinite(P[i, i]):
                rows[n], e[n] = i, poses[k, i] - ref[i]
                n += 1
        rows[n], e[n] = 2, (poses[k, 2] - ref[2] + math.pi) % (2.0 * math.pi) - math.pi
        n += 1
        add = covs.shape[0] > 0
        for i in range(n):
            for j in range(n):
                add = add and math.isfinite(covs[k, rows[i], rows[j]])
        for i in range(n):
            for j in range(n):
                s = P[rows[i], rows[j]]
                a[i, j] = s + covs[k, rows[i], rows[j]] if add else s
            a[i, n] = e[i]
        d2[k], dof[k] = _quadratic(a, e, n), n
    return d2, dof


@njit
def _quadratic(a, e, n):  # pragma: no cover - compiled
    """``eᵀ S⁻¹ e`` for ``a = [S | e]`` (its first ``n`` rows and ``n + 1`` columns;
    overwritten) of a symmetric ``S`` of 1-3 rows, by Gaussian elimination with
    partial pivoting (the first largest pivot); inf when ``S`` is singular."""
    for k in range(n):
        piv = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[piv, k]):
                piv = i
        if a[piv, k] == 0.0 or not math.isfinite(a[piv, k]):
            return math.inf
        for j in range(n + 1):
            a[k, j], a[piv, j] = a[piv, j], a[k, j]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(n + 1):
                a[i, j] = a[i, j] - f * a[k, j]
    x = np.zeros(3)
    for k in range(n - 1, -1, -1):
        s = 0.0
        for j in range(k + 1, n):
            s += a[k, j] * x[j]
        x[k] = (a[k, n] - s) / a[k, k]
    out = 0.0
    for i in range(n):
        out += e[i] * x[i]
    return out


def allows(prior: PoseEstimate, pose: Pose, p: float = PRIOR_P) -> bool:
    """Whether ``pose`` lies inside the prior's ``p`` region."""
    d2, dof = prior_distance(prior, pose)
    return d2 <= chi2_quantile(p, dof)


def _allows_all(prior: PoseEstimate, poses: Sequence[Pose], p: float) -> list[int]:
    """The indices of ``poses`` the prior allows (:func:`allows`), its covariance and
    the quantiles taken once, the distances in one compiled call (:func:`_distances`)."""
    if not poses:
        return []
    d2, dof = _distances(prior, prior_cov(prior), poses)
    q = chi2_table(p)[:3].tolist()   # chi2_quantile's table (dof 1-3 here)
    return [k for k, (d, n) in enumerate(zip(d2.tolist(), dof.tolist(), strict=True))
            if d <= q[n - 1]]


TWIN_ANGLE_RAD = math.pi / 3
"""The smallest turn a map's twins are assumed apart by (a hexagonal layout's; a grid's
are a quarter turn) in :func:`narrower_than`."""


def narrower_than(prior: PoseEstimate, distance_m: float,
                  angle_rad: float = TWIN_ANGLE_RAD, p: float = PRIOR_P) -> bool:
    """Whether the prior's region is too narrow to hold a pose ``distance_m`` away in any
    direction or ``angle_rad`` turned: then a search about the prior alone (a window
    search, which enumerates no twins) cannot take a twin for the pose it finds."""
    P = prior_cov(prior)
    q = chi2_quantile(p, 3)
    a, b, c = float(P[0, 0]), float(P[0, 1]), float(P[1, 1])
    # the larger eigenvalue of the position block, in closed form
    pos = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b) \
        if all(map(math.isfinite, (a, b, c, float(P[1, 0])))) else math.inf
    return distance_m * distance_m > q * pos and angle_rad * angle_rad > q * P[2, 2]


def prior_choice(prior: PoseEstimate | None, poses: Sequence[Pose],
                 p: float = PRIOR_P) -> int | None:
    """The index of the only one of ``poses`` the prior allows (:func:`allows`), or
    None: no prior, none allowed (the frame contradicts it) or several (it cannot
    tell them apart)."""
    if prior is None:
        return None
    inside = _allows_all(prior, poses, p)
    return inside[0] if len(inside) == 1 else None


@warmer
def _warm() -> None:
    chi2_table(PRIOR_P)   # the regions' quantiles before the first frame (issue 37)
    f = np.float64
    _distances_core(arr(np.zeros(3), f), arr(np.eye(3), f), arr(np.zeros((1, 5)), f), _NO_COVS)
