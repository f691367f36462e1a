"""The survey's 2-D pose graph: frame poses in W tied by relative motions, solved by
scipy's sparse least squares.

A node is a vehicle pose ``(x, y, yaw)`` in W (SPEC §1). An :class:`Edge` from node i to
node j measures j's pose in i's vehicle frame V_i: ``z = (dx, dy, dyaw)`` with

    dx, dy = Rz(-yaw_i) (p_j - p_i)        dyaw = yaw_j - yaw_i   (wrapped to (-pi, pi])

(the ceiling-plane odometry's :class:`~ceilkit.runtime.estimators.base.PlaneIncrement`
between consecutive frames, wheel odometry, or a place match between any two frames),
with its ``(3, 3)`` covariance. The residual of an edge is ``L (h(x_i, x_j) - z)``,
``L`` the Cholesky factor of the inverse covariance (whitened: 1 = one sigma).
The anchor node is held at its given pose (the gauge: a pose graph fixes motions, not
where the drive is in W).

:func:`solve_graph` minimises the sum of a robust loss of the whitened residuals
(``scipy.optimize.least_squares``, trust-region reflective, the Jacobian sparse and
analytic: 6 non-zeros per residual row, so a graph of a few thousand nodes solves in
well under a second and needs no GTSAM or Ceres: docs/survey.md). The loss is
Cauchy's at :data:`LOSS_SCALE` sigma: an edge within a few sigma counts as in a
plain least-squares fit, a wrong closure that slipped past the place matcher costs
only the logarithm of its residual, so the drive is not bent to meet it (``soft_l1``,
whose cost grows linearly, bent a 60-node loop by 0.3 m towards a closure a tile off:
``tests/calib/test_survey_graph.py``).

Example::

    poses = chain_poses(np.zeros(3), increments)               # (N, 3)
    sol = solve_graph(poses, edges, anchor=0)
    sol.poses, sol.sigma, sol.whitened                         # (N, 3), (N, 3), per edge
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.sparse.linalg import splu

LOSS_SCALE = 3.0
"""Whitened residual (sigmas) where the robust loss turns from quadratic to linear."""


@dataclass(frozen=True, eq=False)
class Edge:
    """A measured motion from node ``i`` to node ``j`` in V_i (m, m, rad) with its
    ``(3, 3)`` covariance; ``kind``: ``odometry``, ``wheel`` or ``closure``."""

    i: int
    j: int
    z: np.ndarray
    cov: np.ndarray
    kind: str = "odometry"


@dataclass(frozen=True, eq=False)
class GraphSolution:
    """The solved graph.

    Attributes:
        poses: ``(N, 3)`` x, y (m) and yaw (rad) of every node in W.
        sigma: ``(N, 3)`` their 1-sigma (m, m, rad) from the solution's Jacobian,
            scaled by ``sqrt(variance_factor)`` (0 at the anchor, which is held; NaN
            where not computed).
        whitened: ``(E,)`` each edge's residual norm in sigmas, in ``edges``' order.
        cost: the final robust cost; ``iterations``: function evaluations.
        variance_factor: the a-posteriori variance factor, at least 1: the robustly
            weighted sum of squared whitened residuals over the degrees of freedom.
            Above 1 the edges' stated covariances were too small for the scatter the
            solution leaves, and every sigma grows by its square root.
    """

    poses: np.ndarray
    sigma: np.ndarray
    whitened: np.ndarray
    cost: float
    iterations: int
    variance_factor: float = 1.0


def wrap(a: np.ndarray | float) -> np.ndarray | float:
    """An angle (rad) wrapped to ``[-pi, pi)``."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def compose(pose: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The pose reached from ``pose`` (x, y, yaw in W) by the motion ``z`` in its V."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * z[0] - s * z[1], pose[1] + s * z[0] + c * z[1],
                     pose[2] + z[2]])


def relative(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """``pose_j`` in the frame V of ``pose_i``: ``(dx, dy, dyaw)`` (the inverse of
    :func:`compose`, dyaw wrapped)."""
    c, s = math.cos(pose_i[2]), math.sin(pose_i[2])
    d = pose_j[:2] - pose_i[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1],
                     float(wrap(pose_j[2] - pose_i[2]))])


def chain_poses(start: np.ndarray, steps: Sequence[np.ndarray]) -> np.ndarray:
    """``(len(steps) + 1, 3)``: ``start``, then each step composed onto the last."""
    out = [np.asarray(start, float)]
    for z in steps:
        out.append(compose(out[-1], np.asarray(z, float)))
    return np.array(out)


def _sqrt_info(cov: np.ndarray) -> np.ndarray:
    """``L`` with ``Lᵀ L = cov⁻¹`` (a covariance floored at 1e-12 on its diagonal)."""
    c = np.asarray(cov, float) + np.eye(3) * 1e-12
    return np.linalg.cholesky(np.linalg.inv(c)).T


class _Problem:
    """The residuals and the sparse Jacobian of a graph with one node held."""

    def __init__(self, n: int, edges: Sequence[Edge], anchor: int, held: np.ndarray):
        self.n, self.anchor, self.held = n, anchor, np.asarray(held, float)
        self.i = np.array([e.i for e in edges], int)
        self.j = np.array([e.j for e in edges], int)
        self.z = np.array([e.z for e in edges], float).reshape(-1, 3)
        self.L = np.array([_sqrt_info(e.cov) for e in edges]).reshape(-1, 3, 3)
        free = np.ones(n, bool)
        free[anchor] = False
        self.col = np.full(n, -1)
        self.col[free] = np.arange(np.count_nonzero(free))

    def full(self, v: np.ndarray) -> np.ndarray:
        poses = np.empty((self.n, 3))
        poses[self.col >= 0] = v.reshape(-1, 3)
        poses[self.anchor] = self.held
        return poses

    def raw(self, poses: np.ndarray) -> np.ndarray:
        """``(E, 3)`` predicted minus measured motions (unwhitened)."""
        pi, pj = poses[self.i], poses[self.j]
        c, s = np.cos(pi[:, 2]), np.sin(pi[:, 2])
        d = pj[:, :2] - pi[:, :2]
        h = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1],
                      pj[:, 2] - pi[:, 2]], axis=1)
        r = h - self.z
        r[:, 2] = wrap(r[:, 2])
        return r

    def residuals(self, v: np.ndarray) -> np.ndarray:
        return np.einsum("eab,eb->ea", self.L, self.raw(self.full(v))).ravel()

    def jacobian(self, v: np.ndarray) -> sp.csr_matrix:
        poses = self.full(v)
        pi, pj = poses[self.i], poses[self.j]
        c, s = np.cos(pi[:, 2]), np.sin(pi[:, 2])
        d = pj[:, :2] - pi[:, :2]
        e = len(self.i)
        Ji = np.zeros((e, 3, 3))
        Ji[:, 0, 0], Ji[:, 0, 1] = -c, -s
        Ji[:, 1, 0], Ji[:, 1, 1] = s, -c
        Ji[:, 0, 2] = -s * d[:, 0] + c * d[:, 1]
        Ji[:, 1, 2] = -c * d[:, 0] - s * d[:, 1]
        Ji[:, 2, 2] = -1.0
        Jj = np.zeros((e, 3, 3))
        Jj[:, 0, 0], Jj[:, 0, 1] = c, s
        Jj[:, 1, 0], Jj[:, 1, 1] = -s, c
        Jj[:, 2, 2] = 1.0
        rows, cols, vals = [], [], []
        for node, J in ((self.i, Ji), (self.j, Jj)):
            WJ = np.einsum("eab,ebc->eac", self.L, J)
            ok = self.col[node] >= 0
            r = (3 * np.arange(e)[:, None, None] + np.arange(3)[None, :, None]
                 + np.zeros((1, 1, 3), int))
            cc = 3 * self.col[node][:, None, None] + np.arange(3)[None, None, :] \
                + np.zeros((1, 3, 1), int)
            rows.append(r[ok].ravel())
            cols.append(cc[ok].ravel())
            vals.append(WJ[ok].ravel())
        m = 3 * int(np.count_nonzero(self.col >= 0))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                    np.concatenate(cols))), shape=(3 * e, m))


def _sigmas(J: sp.csr_matrix, cols: np.ndarray) -> np.ndarray:
    """``(len(cols), 3)`` the square roots of the diagonal of ``(JᵀJ)⁻¹`` for the nodes
    at parameter columns ``3 cols .. 3 cols + 2``: one sparse LU, then one solve per
    column wanted (never the dense inverse)."""
    A = (J.T @ J).tocsc() + sp.identity(J.shape[1], format="csc") * 1e-12
    lu = splu(A)
    out = np.empty((len(cols), 3))
    e = np.zeros(J.shape[1])
    for k, c in enumerate(cols):
        for a in range(3):
            e[3 * c + a] = 1.0
            out[k, a] = lu.solve(e)[3 * c + a]
            e[3 * c + a] = 0.0
    return np.sqrt(np.maximum(out, 0.0))


def _robust(white2: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-edge IRLS weights and the cost of the Cauchy loss at :data:`LOSS_SCALE`
    (``f² log(1 + r² / f²)``) of squared whitened edge norms ``r²``."""
    z = white2 / LOSS_SCALE ** 2
    return 1.0 / (1.0 + z), float(np.sum(LOSS_SCALE ** 2 * np.log1p(z)))


def _gauss_newton(prob: _Problem, v: np.ndarray, max_iter: int) -> tuple[np.ndarray, float, int]:
    """Iteratively reweighted Gauss-Newton with Levenberg damping: each step one sparse
    factorisation (``splu``) of ``Jᵀ W J + lambda D``; ``(x, cost, iterations)``."""
    lam, it = 1e-6, 0
    r = prob.residuals(v)
    w, cost = _robust(np.sum(r.reshape(-1, 3) ** 2, 1))
    while it < max_iter:
        it += 1
        J = prob.jacobian(v)
        W = sp.diags(np.repeat(w, 3))
        A = (J.T @ W @ J).tocsc()
        g = J.T @ (W @ r)
        D = sp.diags(A.diagonal() + 1e-12)
        while True:
            dx = -splu((A + lam * D).tocsc()).solve(g)
            r2 = prob.residuals(v + dx)
            w2, cost2 = _robust(np.sum(r2.reshape(-1, 3) ** 2, 1))
            if cost2 <= cost or lam > 1e6:
                break
            lam *= 10.0
        if cost2 > cost:
            break
        done = cost - cost2 <= 1e-7 * max(cost, 1.0) or np.max(np.abs(dx)) < 1e-6
        v, r, w, cost, lam = v + dx, r2, w2, cost2, max(lam / 10.0, 1e-9)
        if done:
            break
    return v, cost, it


def solve_graph(poses0: np.ndarray, edges: Sequence[Edge], anchor: int = 0,
                solver: str = "gauss-newton", max_iter: int = 50,
                sigma_nodes: Sequence[int] | None = None) -> GraphSolution:
    """The poses that best explain ``edges``, from the start ``poses0`` ``(N, 3)``, with
    node ``anchor`` held at ``poses0[anchor]``, under the Cauchy loss.

    ``solver``: ``gauss-newton`` (iteratively reweighted, one sparse LU a step; the
    default) or ``least_squares`` (``scipy.optimize.least_squares``, trust-region
    reflective with LSMR on the sparse Jacobian and the loss per residual: on the 60 m
    benchmark drive 12 times the CPU, and it stayed at the drifted chain, where every
    closure lies on the Cauchy cost's flat tail; kept to compare: docs/survey.md).

    ``sigma_nodes``: the nodes whose 1-sigma is computed (None: all; each costs three
    sparse solves); the others' is NaN.

    Returns:
        :class:`GraphSolution`: poses, their 1-sigma (the Gauss-Newton covariance at the
        solution, without the robust loss's down-weighting, times the a-posteriori
        variance factor when above 1), each edge's whitened residual norm.
    """
    poses0 = np.asarray(poses0, float).reshape(-1, 3)
    prob = _Problem(len(poses0), edges, anchor, poses0[anchor])
    v0 = poses0[prob.col >= 0].ravel()
    if solver == "least_squares":
        res = least_squares(prob.residuals, v0, jac=prob.jacobian, method="trf",
                            tr_solver="lsmr", loss="cauchy", f_scale=LOSS_SCALE,
                            max_nfev=20 * max_iter)
        v, cost, iterations = res.x, 2.0 * float(res.cost), int(res.nfev)
    elif solver == "gauss-newton":
        v, cost, iterations = _gauss_newton(prob, v0, max_iter)
    else:
        raise ValueError(f"unknown solver {solver!r}")
    poses = prob.full(v)
    sigma = np.full_like(poses, np.nan)
    sigma[anchor] = 0.0
    want = np.arange(len(poses)) if sigma_nodes is None else np.asarray(sigma_nodes, int)
    want = want[prob.col[want] >= 0]
    r = prob.residuals(v)
    white2 = np.sum(r.reshape(-1, 3) ** 2, 1)
    w, _ = _robust(white2)
    dof = r.size - v.size
    factor = max(1.0, float(w @ white2) / dof) if dof > 0 else 1.0
    if v.size and want.size:
        sigma[want] = _sigmas(prob.jacobian(v), prob.col[want]) * math.sqrt(factor)
    return GraphSolution(poses, sigma, np.sqrt(white2), cost, iterations, factor)
