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
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import warmer

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
    return _distance(prior, prior_cov(prior).tolist(), pose)


def _distance(prior: PoseEstimate, P: list[list[float]], pose: Pose) -> tuple[float, int]:
    """:func:`prior_distance` with the prior's covariance ``P`` given (:func:`prior_cov`
    as nested lists of floats: made once for all the poses of :func:`prior_choice`)."""
    x, y, yaw, cov = pose
    rows, e = [], []
    for i, (a, b) in enumerate(((x, prior.x_m), (y, prior.y_m))):
        if a is not None and b is not None and math.isfinite(P[i][i]):
            rows.append(i)
            e.append(float(a) - float(b))
    rows.append(2)
    e.append(wrap_pi(float(yaw) - float(prior.yaw_rad)))
    S = [[P[i][j] for j in rows] for i in rows]
    if cov is not None:
        C = np.asarray(cov, float)
        add = [[float(C[i, j]) for j in rows] for i in rows]
        if all(math.isfinite(c) for r in add for c in r):
            S = [[a + b for a, b in zip(r, q, strict=True)] for r, q in zip(S, add, strict=True)]
    return _quadratic(S, e), len(rows)


def _quadratic(S: list[list[float]], e: list[float]) -> float:
    """``eᵀ S⁻¹ e`` for a symmetric ``S`` of 1-3 rows, by Gaussian elimination in
    floats (a tracked frame calls it once: numpy's small-array calls cost ten times
    the arithmetic); inf when ``S`` is singular."""
    a = [list(r) + [v] for r, v in zip(S, e, strict=True)]
    n = len(a)
    for k in range(n):
        piv = max(range(k, n), key=lambda i: abs(a[i][k]))
        if a[piv][k] == 0.0 or not math.isfinite(a[piv][k]):
            return math.inf
        a[k], a[piv] = a[piv], a[k]
        for i in range(k + 1, n):
            f = a[i][k] / a[k][k]
            a[i] = [x - f * y for x, y in zip(a[i], a[k], strict=True)]
    x = [0.0] * n
    for k in range(n - 1, -1, -1):
        x[k] = (a[k][n] - sum(a[k][j] * x[j] for j in range(k + 1, n))) / a[k][k]
    return float(sum(v * w for v, w in zip(e, x, strict=True)))


def allows(prior: PoseEstimate, pose: Pose, p: float = PRIOR_P) -> bool:
    """Whether ``pose`` lies inside the prior's ``p`` region."""
    d2, dof = prior_distance(prior, pose)
    return d2 <= chi2_quantile(p, dof)


def _allows_all(prior: PoseEstimate, poses: Sequence[Pose], p: float) -> list[int]:
    """The indices of ``poses`` the prior allows (:func:`allows`), its covariance and
    the quantiles taken once (a tile grid's window fix checks 15 poses a frame)."""
    P = prior_cov(prior).tolist()
    q: dict[int, float] = {}
    inside = []
    for k, pose in enumerate(poses):
        d2, dof = _distance(prior, P, pose)
        if dof not in q:
            q[dof] = chi2_quantile(p, dof)
        if d2 <= q[dof]:
            inside.append(k)
    return inside


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
