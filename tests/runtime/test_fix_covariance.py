"""The covariances a fix carries follow its own residuals (issue 36's NEES): the
corridor's per-segment and per-line shares (:func:`.refine.segment_cov`) and the
fusion's floors (a floor, not an addition)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor.refine import (
    MIN_SHARE_LINES,
    MIN_SIGMA2_PX2,
    segment_cov,
)
from ceilkit.runtime.fusion import FusionOptions, measurement
from ceilkit.runtime.geometry.fits import student


def _frame(rng, lines: int, per: int, line_px: float, offset_px: float = 0.03,
           turn_px: float = 0.05):
    """A linear fit of ``(psi, c_y)`` from ``lines x per`` segments (two endpoints each)
    and two across rows: the weighted Jacobian, residuals, the per-segment line ids and
    the fit's error. Each segment's offset and turn errors are independent; the
    segments of one line share an offset error of 1σ ``line_px``."""
    k = lines * per
    line = np.repeat(np.arange(lines), per)
    x0 = rng.uniform(-1.0, 1.0, k)
    ends = np.stack([x0, x0 + rng.uniform(0.2, 0.6, k)], axis=1)
    gain = rng.uniform(0.5, 1.5, lines)[line] * (1.0 + 0.3 * (line - lines / 2))
    J = np.concatenate([np.stack([100.0 * ends.ravel(), 300.0 * np.repeat(gain, 2)], axis=1),
                        np.c_[rng.normal(0.0, 50.0, 2), np.zeros(2)]])
    off = rng.normal(0.0, offset_px, k) + rng.normal(0.0, line_px, lines)[line]
    turn = rng.normal(0.0, turn_px, k)
    eps = np.concatenate([np.stack([off + turn, off - turn], axis=1).ravel(),
                          rng.normal(0.0, 0.05, 2)])
    err = np.linalg.solve(J.T @ J, J.T @ eps)
    return J, eps - J @ err, 0.3 * line, err


def _mean_nees(lines: int, per: int, line_px: float, trials: int = 1500):
    """Mean NEES of the fit's error with :func:`segment_cov` and with one pooled
    variance (the rule before)."""
    rng = np.random.default_rng(36)
    new, pooled = [], []
    for _ in range(trials):
        J, r, line_of, err = _frame(rng, lines, per, line_px)
        C = segment_cov(J, r, 2 * lines * per, line_of)
        s2 = float(r @ r) / (r.size - 2)
        new.append(err @ np.linalg.solve(C, err))
        pooled.append(err @ np.linalg.solve(s2 * np.linalg.inv(J.T @ J), err))
    return float(np.mean(new)), float(np.mean(pooled))


@pytest.mark.parametrize("lines, per", [(4, 4), (7, 8)])
def test_segments_sharing_their_lines_error_are_covered(lines, per):
    """Segments of one line sharing its error: the pooled variance under-covers (mean
    NEES of 2 dof about 2.3-3.4), the shares cover (below the 95% band's top for 1500
    independent frames, 2.15, and not 3x wide)."""
    new, pooled = _mean_nees(lines, per, line_px=0.025)
    assert pooled > 2.2
    assert 0.67 < new < 2.15


@pytest.mark.parametrize("lines, per", [(4, 4), (7, 8)])
def test_independent_segments_are_covered_with_room(lines, per):
    """No shared error: the shares still cover (the line share is estimated from few
    lines, at least 0, and taken at its Student-t variance)."""
    new, _ = _mean_nees(lines, per, line_px=0.0)
    assert 0.67 < new < 2.15


def test_few_lines_take_one_variance():
    """On fewer than MIN_SHARE_LINES lines no line's share shows: ``s^2 H^-1`` times the
    Student-t factor of its ``n - 2`` dof."""
    rng = np.random.default_rng(7)
    J, r, line_of, _ = _frame(rng, MIN_SHARE_LINES - 1, 3, 0.02)
    n = r.size
    want = float(r @ r) / (n - 2) * student(n - 2.0) * np.linalg.inv(J.T @ J)
    assert segment_cov(J, r, r.size - 2, line_of) == pytest.approx(want, rel=1e-9)


def test_equal_shares_and_a_singular_fit():
    """A singular normal matrix has no covariance; tiny residuals meet the floor."""
    J = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [4.0, 0.0]])
    assert segment_cov(J, np.zeros(4), 4, np.zeros(2)) is None
    J = np.array([[1.0, 1.0], [2.0, 1.0], [1.0, 3.0], [2.0, 3.0], [5.0, 0.0]])
    C = segment_cov(J, np.zeros(5), 4, np.array([0.0, 1.0]))
    assert np.all(np.linalg.eigvalsh(C) >= 0.0)
    Hi = np.linalg.inv(J.T @ J)
    assert np.all(np.linalg.eigvalsh(C - MIN_SIGMA2_PX2 * Hi) >= -1e-15)   # at least the floor
    assert student(14.0) == pytest.approx(14.0 / 12.0) and student(2.0) == 3.0


def test_fusion_floor_raises_a_small_variance_and_leaves_a_larger_one():
    """A corridor fix's y-yaw covariance (correlation -0.9) above the floors goes in as
    it is (the floors added to it were 15 % of a clean fix's yaw variance); one below a
    floor is raised to it."""
    opt = FusionOptions()
    sy, syaw = 1e-4, math.radians(0.003)
    cov = np.full((3, 3), np.nan)
    cov[0, 0] = np.inf
    cov[1:, 1:] = [[sy * sy, -0.9 * sy * syaw], [-0.9 * sy * syaw, syaw * syaw]]
    fix = PoseEstimate(0, "corridor", None, 0.1, 0.2, 1.0, None, cov)
    assert measurement(fix, opt).R == pytest.approx(cov[1:, 1:], rel=1e-12, abs=0.0)
    tiny = cov.copy()
    tiny[1:, 1:] = np.diag([1e-14, 1e-14])
    R = measurement(PoseEstimate(0, "corridor", None, 0.1, 0.2, 1.0, None, tiny), opt).R
    assert R == pytest.approx(np.diag([opt.fix_floor_m ** 2, opt.fix_floor_rad ** 2]))
