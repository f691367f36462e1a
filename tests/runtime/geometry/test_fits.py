"""Tests of runtime/geometry/fits.py: closed-form 2-D rigid and similarity fits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.geometry.fits import fit_rigid_2d, fit_rigid_2d_complex, fit_similarity_2d


def _rot(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def test_fit_rigid_2d_recovers_transform():
    rng = np.random.default_rng(3)
    q = rng.uniform(-3, 3, (6, 2))
    yaw, t = 2.5, np.array([4.0, -1.0])
    p = q @ _rot(yaw).T + t
    yaw_hat, t_hat = fit_rigid_2d(q, p)
    assert abs(math.remainder(yaw_hat - yaw, 2 * math.pi)) < 1e-12
    np.testing.assert_allclose(t_hat, t, atol=1e-12)


def test_fit_rigid_2d_weights_and_two_points():
    q = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]])
    p = q @ _rot(0.3).T + (1.0, 2.0)
    p[2] += (3.0, -2.0)                           # an outlier
    yaw_w, t_w = fit_rigid_2d(q, p, np.array([1.0, 1.0, 0.0]))
    assert yaw_w == pytest.approx(0.3, abs=1e-12)
    np.testing.assert_allclose(t_w, (1.0, 2.0), atol=1e-12)
    yaw_u, _ = fit_rigid_2d(q, p)
    assert abs(yaw_u - 0.3) > 1e-3                 # unweighted, the outlier pulls


def test_fit_rigid_2d_complex_agrees_with_real_form():
    rng = np.random.default_rng(5)
    for _ in range(10):
        q = rng.uniform(-3, 3, (7, 2))
        p = q @ _rot(rng.uniform(-3, 3)).T + rng.uniform(-5, 5, 2) + rng.normal(0, 0.01, (7, 2))
        yaw, t = fit_rigid_2d(q, p)
        rot, tc = fit_rigid_2d_complex(q[:, 0] + 1j * q[:, 1], p[:, 0] + 1j * p[:, 1])
        assert abs(rot) == pytest.approx(1.0)
        assert math.atan2(rot.imag, rot.real) == pytest.approx(yaw, abs=1e-12)
        np.testing.assert_allclose((tc.real, tc.imag), t, atol=1e-12)
    # coincident points give no direction: the identity rotation
    rot, tc = fit_rigid_2d_complex(np.zeros(2, complex), np.ones(2, complex))
    assert rot == 1.0 and tc == 1.0


def test_fit_similarity_recovers_scale_rotation_translation():
    rng = np.random.default_rng(0)
    q = rng.uniform(-2, 2, (5, 2))
    s, th, t = 1.07, -0.8, np.array([3.0, 2.0])
    p = s * q @ _rot(th).T + t
    s2, th2, t2 = fit_similarity_2d(q, p)
    assert s2 == pytest.approx(s) and th2 == pytest.approx(th)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_similarity_with_unit_scale_is_the_rigid_fit():
    rng = np.random.default_rng(1)
    q = rng.uniform(-2, 2, (6, 2))
    p = q @ _rot(1.9).T + (0.5, -0.7)
    s, th, t = fit_similarity_2d(q, p)
    yaw, t_r = fit_rigid_2d(q, p)
    assert s == pytest.approx(1.0) and th == pytest.approx(yaw, abs=1e-12)
    np.testing.assert_allclose(t, t_r, atol=1e-12)
    # round trip: the fit's inverse maps p back onto q
    s_i, th_i, t_i = fit_similarity_2d(p, q)
    np.testing.assert_allclose(s_i * p @ _rot(th_i).T + t_i, q, atol=1e-12)
