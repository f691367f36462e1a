import math

import numpy as np
import pytest

from ceilkit.runtime.geometry import ekf


def _state(pose=(1.0, 2.0, 0.0), var=1e-4):
    return ekf.initial_state(pose, np.eye(3) * var)


def test_chi2_quantiles_match_the_tables():
    assert ekf.chi2_quantile(0.95, 1) == pytest.approx(3.841, abs=1e-3)
    assert ekf.chi2_quantile(0.95, 2) == pytest.approx(5.991, abs=1e-3)
    assert ekf.chi2_quantile(0.95, 3) == pytest.approx(7.815, abs=1e-3)
    assert ekf.chi2_quantile(0.025, 2) == pytest.approx(0.0506, abs=1e-3)
    with pytest.raises(ValueError):
        ekf.chi2_cdf(1.0, 4)


def test_constant_velocity_moves_and_grows_the_covariance():
    s, P = _state()
    s[3], s[5] = 0.5, 0.1
    s2, P2 = ekf.predict_cv(s, P, 2.0, ekf.MotionNoise())
    assert s2[0] == pytest.approx(2.0) and s2[2] == pytest.approx(0.2)
    assert np.all(np.diag(P2)[:3] > np.diag(P)[:3])
    assert ekf.predict_cv(s, P, 0.0, ekf.MotionNoise())[0] is s


def test_odometry_is_rotated_into_w_and_scaled():
    s, P = _state(pose=(0.0, 0.0, math.pi / 2))
    s[ekf.SCALE] = 1.1
    s2, P2 = ekf.predict_odometry(s, P, (1.0, 0.0, 0.1), 0.5, ekf.MotionNoise())
    assert s2[:3] == pytest.approx([0.0, 1.1, math.pi / 2 + 0.1])
    assert s2[4] == pytest.approx(2.2)          # the velocity is the increment / dt
    assert P2[1, 1] > P[1, 1] + 0.05 ** 2 * 0.9  # the scale's 5% sigma shows in y


def test_update_pulls_to_the_measurement_and_reports_nis():
    s, P = _state(var=1e-2)
    z = np.array([1.1, 2.0, 0.0])
    s2, P2, nis = ekf.update(s, P, z, ekf.FULL_POSE, np.eye(3) * 1e-2)
    assert s2[0] == pytest.approx(1.05) and P2[0, 0] == pytest.approx(5e-3)
    assert nis == pytest.approx(0.01 / 0.02)


def test_partial_update_leaves_x_alone_and_wraps_yaw():
    s, P = _state(pose=(1.0, 2.0, math.pi - 0.01))
    z = np.array([2.0, -math.pi + 0.01])
    s2, P2, _ = ekf.update(s, P, z, ekf.Y_YAW, np.eye(2) * 1e-4)
    assert s2[0] == pytest.approx(1.0) and P2[0, 0] == pytest.approx(P[0, 0])
    assert abs(abs(s2[2]) - math.pi) < 0.01


def test_prob_within_radius():
    assert ekf.prob_within_radius(np.array([[1e-4]]), 0.01) == pytest.approx(
        math.erf(1 / math.sqrt(2)))
    iso = np.eye(2) * 1e-4
    assert ekf.prob_within_radius(iso, 0.02) == pytest.approx(1 - math.exp(-2))
    assert ekf.prob_within_radius(np.full((2, 2), np.inf), 0.02) == 0.0
