"""The vehicle's stated limits (``--max-speed``) reach both trackers, and decide
whether a fast vehicle's frames are within reach (issue 36's bound on a new track)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.prior import MAX_SPEED_MPS, MAX_TURN_RPS
from ceilkit.runtime.fusion import Fusion
from ceilkit.runtime.multi import make_localizer, parse_limits
from ceilkit.runtime.tracking import Tracker
from helpers import CONFIGS


def _rig_site(name: str) -> tuple[Rig, Site]:
    return Rig.load(CONFIGS / name / "rig.yaml"), Site.load(CONFIGS / name / "site.yaml")


def test_parse_limits_takes_speed_and_an_optional_turn_rate():
    assert parse_limits("1.5") == (1.5, MAX_TURN_RPS)
    assert parse_limits("4,120") == pytest.approx((4.0, math.radians(120.0)))
    for bad in ("0", "-1", "inf", "nan", "101", "1,0", "1,4000", "", "1,2,3", "a"):
        with pytest.raises(ConfigError, match="max_speed"):
            parse_limits(bad)


@pytest.mark.parametrize("method", ["lights", "auto"])
def test_limits_reach_the_tracker_and_the_fusion(method):
    rig, site = _rig_site("lights")
    _, default = make_localizer(method, rig, site, start_pose=(1.0, 1.0, 0.0))
    _, fast = make_localizer(method, rig, site, start_pose=(1.0, 1.0, 0.0),
                             limits=(6.0, math.radians(200.0)))
    assert isinstance(default, Tracker | Fusion) and type(fast) is type(default)
    assert default.options.max_speed_mps == MAX_SPEED_MPS
    assert fast.options.max_speed_mps == 6.0
    assert fast.options.max_turn_rps == pytest.approx(math.radians(200.0))


def _fix(t_s: float, x: float) -> PoseEstimate:
    return PoseEstimate(int(t_s * 1e9), "lights", x, 0.5, 0.0, None, 1.0,
                        cov=np.diag([1e-6, 1e-6, 1e-6]))


def test_a_vehicle_faster_than_its_stated_limit_is_out_of_reach_and_within_a_higher_one():
    """Fixes 0.5 m apart every 1/30 s (15 m/s): beyond the default 2.5 m/s they are
    refused until the track restarts; with --max-speed 20 every one is accepted."""
    rig, site = _rig_site("lights")
    fixes = [_fix(k / 30.0, 6.0 + 0.5 * k) for k in range(6)]

    def accepted(limits):
        _, tracker = make_localizer("lights", rig, site, limits=limits)
        return [isinstance(tracker.update(f).estimate, PoseEstimate) for f in fixes]

    assert not all(accepted(None))
    assert all(accepted((20.0, MAX_TURN_RPS)))
