"""Review of stop 51's twin test (brief R): a rival set aside only because its overlap
is too small to beat chance has not been ruled out by the pair."""

import math

import numpy as np
import pytest

from ceilkit.calib.survey_places import Place, match_places


def _view(pts: np.ndarray, d: np.ndarray, z: np.ndarray, rng: np.random.Generator
          ) -> Place:
    """What a place at ``z`` (in the points' frame) sees: its 2.4 x 1.8 m, 1 mm noise
    (``q_a = R p_b + t`` between two views)."""
    c, s = math.cos(z[2]), math.sin(z[2])
    v = (pts - z[:2]) @ np.array([[c, -s], [s, c]])
    see = np.all(np.abs(v) < [1.2, 0.9], axis=1)
    return Place(v[see] + rng.normal(0, 0.001, (see.sum(), 2)), d[see])


def _two_copies(rng: np.random.Generator, per_m2: float = 16.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """A 3 x 8 m scatter (own descriptors) repeated with a 3 m period along x: a view
    (2.4 x 1.8 m) never holds two copies, so a's own repeats show no period."""
    n = int(3.0 * 8.0 * per_m2)
    tile = np.c_[rng.uniform(0, 3.0, n), rng.uniform(-4, 4, n)]
    d = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return (np.concatenate([tile + [k * 3.0, 0.0] for k in range(-3, 4)]),
            np.tile(d, (7, 1)))


@pytest.mark.xfail(strict=True, reason="open (issue 36/39, stop 51 review): a rival too "
                   "small to beat chance over its overlap is set aside, not refused; a "
                   "scatter repeating beyond one view can be matched a period off")
def test_a_twin_of_larger_overlap_is_not_accepted_over_a_small_overlap_truth():
    """Frames 2.0-2.1 m apart along the period: the truth overlaps a by 0.3-0.4 m, the
    copy 3 m back (-0.9 to -1.0 m) by 1.4-1.5 m and wins the RANSAC. The truth explains
    every feature it brings over a's (3 of 3, 6 of 8: Fisher's p 0.03-1 against the
    winner), but too few to beat chance over so small an overlap, so ``_twin`` sets it
    aside as not credible, and the pair is accepted 3 m off (here 2 of 20 pairs; 5 of
    100 over seeds 0-4 with view-dependent descriptors, every one at dx >= 2.0:
    /tmp/R/two_copies.py of stop 51). A rival the evidence does not rule out must leave
    the pair refused (or the match at the truth)."""
    rng = np.random.default_rng(4)
    pts, d = _two_copies(rng)
    bad = []
    for _ in range(20):
        dz = np.array([rng.uniform(1.4, 2.1), rng.uniform(-0.2, 0.2),
                       rng.uniform(-0.05, 0.05)])
        z0 = np.r_[rng.uniform(-1.5, 1.5), rng.uniform(-1, 1), 0.0]
        a, b = _view(pts, d, z0, rng), _view(pts, d, z0 + dz, rng)
        m = match_places(a, b, np.random.default_rng(0), min_points=0)
        if m and np.hypot(*(m.z[:2] - dz[:2])) > 0.1:
            bad.append((np.round(dz, 2), np.round(m.z, 2), m.inliers))
    assert not bad, bad
