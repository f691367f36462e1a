"""The one rule by which a prior chooses among a frame's twins (estimators/prior.py)."""

import math

import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.prior import (
    DEFAULT_PRIOR_SIGMA,
    allows,
    prior_choice,
    prior_distance,
)


def _prior(x=1.0, y=2.0, yaw=0.0, cov=None):
    return PoseEstimate(0, "track", x, y, yaw, 0.0, None, cov)


def test_the_prior_chooses_the_only_twin_inside_its_region():
    grid = [(1.0 + 1.5 * i, 2.0, 0.0, None) for i in range(-2, 3)]   # a 1.5 m grid's cells
    assert prior_choice(_prior(1.05), grid) == 2


def test_a_prior_no_twin_lies_near_chooses_nothing():
    """A kidnap or a wrong start pose: the nearest twin is not chosen because it is the
    nearest; it must lie inside the prior's region."""
    grid = [(1.0 + 1.5 * i, 2.0, 0.0, None) for i in range(-2, 3)]
    assert prior_choice(_prior(1.75), grid) is None          # half a cell off
    quarter = [(1.0, 2.0, k * math.pi / 2, None) for k in range(4)]
    assert prior_choice(_prior(yaw=math.radians(45.0)), quarter) is None


def test_a_prior_as_wide_as_the_pitch_cannot_tell_the_cells():
    cells = [(1.0 + 0.6 * i, 2.0, 0.0, None) for i in range(-2, 3)]   # 0.6 m tiles
    wide = np.diag([0.5 ** 2, 0.5 ** 2, 0.01])
    assert prior_choice(_prior(1.0, cov=wide), cells) is None
    assert prior_choice(_prior(1.0), cells) == 2            # the default start σ tells them


def test_a_prior_without_covariance_has_the_default_region():
    sp, sr = DEFAULT_PRIOR_SIGMA
    d2, dof = prior_distance(_prior(), (1.0 + sp, 2.0, sr, None))
    assert dof == 3 and math.isclose(d2, 2.0)


def test_a_coordinate_the_prior_does_not_know_is_not_compared():
    corridor_track = _prior(None, 0.1, math.pi, np.diag([np.inf, 1e-4, 1e-4]))
    assert prior_distance(corridor_track, (7.0, 0.1, math.pi, None))[1] == 2
    assert allows(corridor_track, (99.0, 0.1, math.pi, None))
    assert not allows(corridor_track, (0.0, 0.1, 0.0, None))     # the half turn


def test_a_search_about_the_prior_alone_needs_a_prior_narrower_than_the_twins():
    """The window search finds no twins: it may run only when the prior's region cannot
    hold another cell's pose (1.5 m away) or a turn of 60 deg."""
    from ceilkit.runtime.estimators.prior import narrower_than

    assert narrower_than(_prior(), 1.5)                        # the default 0.1 m, 5 deg
    assert not narrower_than(_prior(cov=np.diag([0.5 ** 2, 0.01, 1e-4])), 1.5)  # wide in x
    assert not narrower_than(_prior(cov=np.diag([1e-4, 1e-4, 0.3 ** 2])), 1.5)  # in yaw


def _reference_distance(prior, pose):
    """eᵀ S⁻¹ e by numpy over the coordinates both give (the rule's reading)."""
    P = np.diag([0.1 ** 2, 0.1 ** 2, math.radians(5.0) ** 2]) if prior.cov is None \
        else np.array(prior.cov, float)
    x, y, yaw, cov = pose
    rows = [i for i, (a, b) in enumerate(((x, prior.x_m), (y, prior.y_m)))
            if a is not None and b is not None and math.isfinite(P[i, i])] + [2]
    e = np.array([(x - prior.x_m) if i == 0 else (y - prior.y_m) if i == 1
                  else (yaw - prior.yaw_rad + math.pi) % (2 * math.pi) - math.pi for i in rows])
    S = P[np.ix_(rows, rows)]
    if cov is not None and np.isfinite(np.asarray(cov)[np.ix_(rows, rows)]).all():
        S = S + np.asarray(cov)[np.ix_(rows, rows)]
    return float(e @ np.linalg.solve(S, e)), len(rows)


def test_the_distances_of_many_poses_are_each_pose_own():
    """prior_choice takes every pose's distance in one compiled call: each the same as
    the pose's alone and as numpy's solve, with coordinates and covariances missing,
    not finite or given (a corridor hypothesis: x unknown, its variance infinite)."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        A = rng.normal(size=(3, 3)) * 0.2
        cov = A @ A.T + 1e-3 * np.eye(3)
        prior = _prior(*(None if rng.random() < 0.3 else float(v) for v in rng.normal(size=2)),
                       float(rng.uniform(-4, 4)), None if rng.random() < 0.3 else cov)
        poses = []
        for _ in range(rng.integers(1, 16)):
            c = None if rng.random() < 0.5 else cov * rng.uniform(0.1, 2.0)
            if c is not None and rng.random() < 0.3:
                c = c.copy()
                c[0, :] = c[:, 0] = np.inf
            poses.append((None if rng.random() < 0.3 else float(rng.normal()),
                          None if rng.random() < 0.3 else float(rng.normal()),
                          float(rng.uniform(-4, 4)), c))
        inside = [k for k, p in enumerate(poses) if allows(prior, p)]
        assert prior_choice(prior, poses) == (inside[0] if len(inside) == 1 else None)
        for pose in poses:
            d2, dof = prior_distance(prior, pose)
            want, want_dof = _reference_distance(prior, pose)
            assert dof == want_dof and math.isclose(d2, want, rel_tol=1e-9, abs_tol=1e-12)
