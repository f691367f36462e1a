"""calib/poses.py: poses at their own stamps, interpolated at the frames' stamps."""

import math

import numpy as np
import pytest

from ceilkit.calib.poses import StampedPoses
from ceilkit.runtime.io.recording import Truth


def _table():
    t = np.array([0, 10, 20, 1000], np.int64)
    return StampedPoses(t, np.array([0.0, 1.0, 2.0, 3.0]), np.zeros(4),
                     np.radians([170.0, -170.0, -160.0, 0.0]))


def test_interpolates_position_and_heading_along_the_shorter_arc():
    p = _table().at(np.array([5, 15]))
    assert p[0, 0] == pytest.approx(0.5)
    assert math.degrees(p[0, 2]) % 360 == pytest.approx(180.0)   # not 0 (the long way)
    assert p[1, 0] == pytest.approx(1.5)
    assert math.degrees(p[1, 2]) == pytest.approx(-165.0)


def test_offset_and_no_extrapolation():
    tab = _table()
    assert tab.at(np.array([0]), offset_ns=10)[0, 0] == pytest.approx(1.0)
    assert np.isnan(tab.at(np.array([-1, 1001]))).all()


def test_no_pose_invented_across_a_gap():
    tab = _table()
    p = tab.at(np.array([15, 500, 1000]), max_gap_ns=100)
    assert np.isfinite(p[0]).all() and np.isnan(p[1]).all() and np.isfinite(p[2]).all()
    assert np.isfinite(tab.at(np.array([500]))).all()          # no limit: interpolated


def test_from_truth_and_exact():
    tr = Truth(np.array([5, 7], np.int64), np.array([1.0, 2.0]), np.zeros(2), np.zeros(2))
    tab = StampedPoses.from_truth(tr)
    assert tab.exact(np.array([5, 7])) and not tab.exact(np.array([6]))
    assert tab.at(np.array([6]))[0, 0] == pytest.approx(1.5)
