"""A corridor fix's covariance where the Huber weights clip a few rows (issue 36: the
tiles-with-markers drive over-covered): a clipped row enters by its own term, not pooled
into every row's variance (:func:`.refine.segment_cov`)."""

from __future__ import annotations

import numpy as np
import pytest

from ceilkit.runtime.estimators.corridor.refine import HUBER_PX, segment_cov
from tests.runtime.test_fix_covariance import segment_cov_numpy


def _huber_frame(rng, lines: int = 6, per: int = 8, outliers: int = 1):
    """A linear fit of ``(psi, c_y)`` from ``lines x per`` segments (two endpoints each,
    offset 0.02 px and turn 0.035 px 1σ, a line's shared offset 0.01 px) and two across
    rows, with ``outliers`` segments off by 1.2-2.5 px at both ends (a seam's piece
    drawn over a block's edge), solved with the fit's Huber weights (k = 1 px): the
    weighted Jacobian and residuals at the solution, the segments' lines, the error."""
    k = lines * per
    line = np.repeat(np.arange(lines), per)
    x0 = rng.uniform(-1.0, 1.0, k)
    ends = np.stack([x0, x0 + rng.uniform(0.2, 0.6, k)], axis=1)
    A = np.concatenate([np.stack([100.0 * ends.ravel(), np.full(2 * k, 300.0)], axis=1),
                        np.c_[rng.normal(0.0, 50.0, 2), np.zeros(2)]])
    off = rng.normal(0.0, 0.02, k) + rng.normal(0.0, 0.01, lines)[line]
    turn = rng.normal(0.0, 0.035, k)
    bad = rng.choice(k, outliers, replace=False)
    off[bad] += rng.choice([-1.0, 1.0], outliers) * rng.uniform(1.2, 2.5, outliers)
    eps = np.concatenate([np.stack([off + turn, off - turn], axis=1).ravel(),
                          rng.normal(0.0, 0.03, 2)])
    x = np.zeros(2)
    for _ in range(30):                                  # IRLS, Huber k = HUBER_PX
        r = eps - A @ x
        sw = np.sqrt(np.minimum(1.0, HUBER_PX / np.maximum(np.abs(r), 1e-9)))
        x = np.linalg.lstsq(A * sw[:, None], eps * sw, rcond=None)[0]
    r = eps - A @ x
    sw = np.sqrt(np.minimum(1.0, HUBER_PX / np.maximum(np.abs(r), 1e-9)))
    return A * sw[:, None], r * sw, 0.6 * line, x


@pytest.mark.parametrize("outliers", [1, 2])
def test_clipped_segments_do_not_widen_every_row(outliers):
    """Frames with one or two segments off by 1.2-2.5 px among 48: the covariance
    covers the Huber fit's error at about its 2 dof (2.08 and 2.10). Pooled into the
    segments' shares (the rule before), a clipped row's ``|r|`` px² was every row's
    and the pulled fit's pattern the kept rows' scatter: 1.01 and 1.05, 2x wide."""
    rng = np.random.default_rng(36)
    got = []
    for _ in range(800):
        J, r, line_of, err = _huber_frame(rng, outliers=outliers)
        assert np.sum(r ** 2 > HUBER_PX ** 2) >= 1       # the outliers are clipped
        C = segment_cov(J, r, J.shape[0] - 2, line_of)
        got.append(err @ np.linalg.solve(C, err))
    assert 1.6 < float(np.mean(got)) < 2.3


def test_clean_frames_are_unchanged_and_the_reference_agrees():
    """The compiled covariance equals its numpy reading to 1e-12 with and without
    clipped rows (without: the shares as before, ``test_fix_covariance.py``)."""
    rng = np.random.default_rng(7)
    for outliers in (0, 1, 3):
        for _ in range(10):
            J, r, line_of, _ = _huber_frame(rng, outliers=max(outliers, 1))
            if outliers == 0:
                keep = r ** 2 <= HUBER_PX ** 2
                seg = keep[0:-2:2] & keep[1:-2:2]
                rows = np.r_[np.repeat(seg, 2), True, True]
                J, r, line_of = J[rows], r[rows], line_of[seg]
            n_a = J.shape[0] - 2
            np.testing.assert_allclose(segment_cov(J, r, n_a, line_of),
                                       segment_cov_numpy(J, r, n_a, line_of),
                                       rtol=1e-12, atol=0.0)
