import math

import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.fusion import Fusion
from ceilkit.runtime.multi import AutoEstimator, make_localizer, parse_start_pose
from ceilkit.runtime.tracking import Tracker


def test_start_pose_parses_degrees():
    assert parse_start_pose("1,2,90") == pytest.approx((1.0, 2.0, math.pi / 2))
    for bad in ("1,2", "a,b,c", "1,2,inf"):
        with pytest.raises(ConfigError, match="start_pose"):
            parse_start_pose(bad)


def test_auto_on_a_one_method_site_is_that_method(lights_rig, lights_site):
    est, tracker = make_localizer("auto", lights_rig, lights_site)
    assert est.name == "lights" and isinstance(tracker, Tracker)
    est, tracker = make_localizer("auto", lights_rig, lights_site, start_pose=(0, 0, 0))
    assert isinstance(est, AutoEstimator) and isinstance(tracker, Fusion)
    with pytest.raises(ConfigError, match="start_pose"):
        make_localizer("lights", lights_rig, lights_site, start_pose=(0, 0, 0))
    with pytest.raises(ConfigError, match="options.nope"):
        AutoEstimator(lights_rig, lights_site, {"nope": 1})
