"""The covariances a fix carries follow its own residuals (issue 36's NEES): the
corridor's per-segment and per-line shares (:func:`.refine.segment_cov`, compiled, and
its numpy reading kept here as the reference) and the fusion's floors (a floor, not an
addition)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor import refine
from ceilkit.runtime.estimators.corridor.refine import (
    MIN_SHARE_LINES,
    MIN_SIGMA2_PX2,
    RowRates,
    residual_cov,
    segment_cov,
)
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.fusion import FusionOptions, measurement
from ceilkit.runtime.geometry.fits import student
from ceilkit.runtime.sim.render import SimOptions, render_frame

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _share(parts: list, s2: float, nu: float, M: np.ndarray, Hi: np.ndarray,
           floor: bool = True) -> None:
    """Append a share ``(v M, t, nu)`` (a segment share or single variance below the
    floor: the floor, no dof)."""
    if floor and s2 < MIN_SIGMA2_PX2:
        s2, nu = MIN_SIGMA2_PX2, math.inf
    parts.append((s2 * M, s2 * float(np.trace(Hi @ M)), nu))


def segment_cov_numpy(J, r, n_a, line_of):
    """:func:`.refine.segment_cov` in numpy (the reference of the compiled loops)."""
    H = J.T @ J
    if not abs(np.linalg.det(H)) > 1e-300:
        return None
    Hi = np.linalg.inv(H)
    parts: list = []
    raw = np.where(r ** 2 > refine.HUBER_PX ** 2, r ** 2 / refine.HUBER_PX, np.abs(r))
    cut = max(refine.HUBER_PX, refine.OUTLIER_SIGMAS * 1.4826 * float(np.median(raw)))
    own = raw > cut if r.size else np.zeros(0, bool)   # clipped outliers: own terms
    seg = own[:n_a:2] | own[1:n_a:2]
    own[:n_a] = np.repeat(seg, 2)
    g = np.r_[(J[:n_a] * r[:n_a, None]).reshape(-1, 2, 2).sum(axis=1)[seg],
              (J[n_a:] * r[n_a:, None])[own[n_a:]]]
    for gi in g:                                     # a clipped segment's pull, both ends
        _share(parts, 1.0, math.inf, np.outer(gi, gi), Hi, floor=False)
    J, r, line_of, n_a = J[~own], r[~own], np.asarray(line_of)[~seg], n_a - int(own[:n_a].sum())
    if own.any() and abs(np.linalg.det(J.T @ J)) > 1e-300:   # about the kept rows' own fit
        r = r - J @ np.linalg.solve(J.T @ J, J.T @ r)
    _, line = np.unique(line_of, return_inverse=True)
    if line.size == 0 or line.max() + 1 < MIN_SHARE_LINES:
        nu = max(r.size - 2.0, 1.0)
        _share(parts, float(r @ r) / nu, nu, J.T @ J, Hi)
    else:
        a, q = J[:n_a].reshape(-1, 2, 2), r[:n_a].reshape(-1, 2)
        for sign in (1.0, -1.0):
            Jg = (a[:, 0] + sign * a[:, 1]) * math.sqrt(0.5)
            rg = (q[:, 0] + sign * q[:, 1]) * math.sqrt(0.5)
            k, n_l = rg.size, np.bincount(line)
            nu_b = max(n_l.size - float(np.einsum("ij,jk,ik->", Jg, Hi, Jg)), 1.0)
            mean = np.bincount(line, rg) / n_l
            nu_w = float(max(k - n_l.size, 1))
            sw2 = float(np.sum((rg - mean[line]) ** 2)) / nu_w
            tau2 = max(0.0, float(n_l @ mean ** 2) / nu_b - sw2) / (k / n_l.size)
            G = np.stack([np.bincount(line, Jg[:, 0]), np.bincount(line, Jg[:, 1])], axis=1)
            _share(parts, sw2, nu_w, Jg.T @ Jg, Hi)
            _share(parts, tau2, nu_b, G.T @ G, Hi, floor=False)
        if r.size > n_a:
            Jb, rb = J[n_a:], r[n_a:]
            nu = max(rb.size - float(np.einsum("ij,jk,ik->", Jb, Hi, Jb)), 1.0)
            _share(parts, float(rb @ rb) / nu, nu, Jb.T @ Jb, Hi)
    M = sum(p[0] for p in parts)
    t = sum(p[1] for p in parts)
    d = sum(p[1] ** 2 / p[2] for p in parts if math.isfinite(p[2]))
    C = (student(t * t / d) if d > 0.0 else 1.0) * (Hi @ M @ Hi)
    C = 0.5 * (C + C.T)
    return C if np.all(np.isfinite(C)) else None


def residual_cov_numpy(psi, cy, gd, setup, rates=None):
    """:func:`.refine.residual_cov` in numpy: the rows of :func:`.refine.residuals`."""
    A = refine.residuals(psi, cy, gd, setup)
    J, r = A[:, :2], A[:, 2]
    if rates is not None:
        tau = np.concatenate([gd.tau, gd.tau_b])
        r = r + (J * tau[:, None]) @ np.array([rates.w_rps, rates.v_mps])
    sw = np.sqrt(np.minimum(1.0, 1.0 / np.maximum(np.abs(r), 1e-9)))
    return segment_cov_numpy(J * sw[:, None], r * sw, gd.e0.size, gd.y[:gd.e0.size:2])


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
    NEES of 2 dof about 2.9-3.9), the shares cover (below the 95% band's top for 1500
    independent frames, 2.15, and not 1.4x wide: each share at its own Student factor
    gave 1.54 and 1.63)."""
    new, pooled = _mean_nees(lines, per, line_px=0.025)
    assert pooled > 2.2
    assert 1.75 < new < 2.15


@pytest.mark.parametrize("lines, per", [(4, 4), (7, 8)])
def test_independent_segments_are_covered_with_room(lines, per):
    """No shared error: the shares still cover (the line share is estimated from few
    lines, at least 0, and the sum taken at the Student-t variance of its effective
    degrees of freedom)."""
    new, _ = _mean_nees(lines, per, line_px=0.0)
    assert 1.5 < new < 2.15             # each share at its own factor: 1.37 (4 x 4)


def test_few_lines_take_one_variance():
    """On fewer than MIN_SHARE_LINES lines no line's share shows: ``s^2 H^-1`` times the
    Student-t factor of its ``n - 2`` dof."""
    rng = np.random.default_rng(7)
    J, r, line_of, _ = _frame(rng, MIN_SHARE_LINES - 1, 3, 0.02)
    n = r.size
    want = float(r @ r) / (n - 2) * student(n - 2.0) * np.linalg.inv(J.T @ J)
    assert float(r @ r) / (n - 2) > MIN_SIGMA2_PX2
    assert segment_cov(J, r, r.size - 2, line_of) == pytest.approx(want, rel=1e-9)
    # below the floor: the floor, a stated value, at no Student factor
    want = MIN_SIGMA2_PX2 * np.linalg.inv(J.T @ J)
    assert segment_cov(J, 1e-3 * r, r.size - 2, line_of) == pytest.approx(want, rel=1e-9)


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


@pytest.mark.parametrize("lines, per, line_px", [(4, 4, 0.025), (7, 8, 0.0), (2, 3, 0.02),
                                                 (5, 1, 0.01), (6, 3, 0.0)])
def test_compiled_shares_equal_the_numpy_reading(lines, per, line_px):
    """:func:`segment_cov` (compiled) against its numpy reading to 1e-12: shares from
    frames of 2-7 lines, with and without a line's shared error, with residuals scaled
    down to meet the floor, with no across rows."""
    rng = np.random.default_rng(lines * 10 + per)
    for scale in (1.0, 0.1, 1e-3):
        for _ in range(20):
            J, r, line_of, _ = _frame(rng, lines, per, line_px)
            n_a = 2 * lines * per
            for JJ, rr in ((J, scale * r), (J[:n_a], scale * r[:n_a])):
                np.testing.assert_allclose(segment_cov(JJ, rr, n_a, line_of),
                                           segment_cov_numpy(JJ, rr, n_a, line_of),
                                           rtol=1e-12, atol=0.0)
    J = np.c_[rng.normal(0.0, 50.0, 5), rng.normal(0.0, 50.0, 5)]      # across rows only
    r = rng.normal(0.0, 0.1, 5)
    np.testing.assert_allclose(segment_cov(J, r, 0, np.zeros(0)),
                               segment_cov_numpy(J, r, 0, np.zeros(0)), rtol=1e-12)


def test_compiled_residual_cov_equals_the_numpy_reading(monkeypatch):
    """:func:`residual_cov` (one compiled call) against the numpy rows of
    :func:`.refine.residuals` and :func:`segment_cov_numpy` to 1e-12, on the packaged
    corridor's rendered frames, as a global shutter and with made-up row times and
    rates (a rolling shutter's shift)."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    est = make_estimator("corridor", rig, site, {"assume_heading_deg": 0.0})
    seen = []
    real = refine.residual_cov

    def spy(psi, cy, gd, setup, rates=None):
        seen.append((psi, cy, gd, setup))
        return real(psi, cy, gd, setup, rates)

    monkeypatch.setattr(refine, "residual_cov", spy)
    for k, pose in enumerate([(3.0, 0.1, 0.02), (6.0, -0.2, -0.05), (9.0, 0.3, 0.1)]):
        img = render_frame(rig, site, *pose, rng=np.random.default_rng(k),
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8))
        est.estimate(img, k, None)
    monkeypatch.undo()
    assert len(seen) >= 3
    rng = np.random.default_rng(3)
    rates = RowRates(0.3, -0.2, 0.1, 0.05)
    for psi, cy, gd, setup in seen:
        np.testing.assert_allclose(residual_cov(psi, cy, gd, setup),
                                   residual_cov_numpy(psi, cy, gd, setup), rtol=1e-12)
        rows = dataclasses.replace(gd, tau=rng.uniform(0.0, 0.03, gd.e0.size),
                                   tau_b=rng.uniform(0.0, 0.03, gd.p0.size))
        np.testing.assert_allclose(residual_cov(psi, cy, rows, setup, rates),
                                   residual_cov_numpy(psi, cy, rows, setup, rates), rtol=1e-12)
