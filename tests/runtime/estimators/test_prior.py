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
