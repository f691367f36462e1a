"""The fast path's start prediction and its tables looked up once (track.py, ceilmap.py)."""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.prior import _quadratic
from ceilkit.runtime.estimators.texture.ceilmap import Rectifier, rectify
from ceilkit.runtime.estimators.texture.track import _add_shift, _predicted
from helpers import CONFIGS


def test_the_prediction_is_the_affine_fit_of_the_features_followed():
    # a prior 0.5 deg and (0.4, -0.3) px off: the displacement is affine in the place
    rng = np.random.default_rng(0)
    th = math.radians(0.5)
    A = np.array([[math.cos(th) - 1, -math.sin(th)], [math.sin(th), math.cos(th) - 1]])
    acc = np.zeros(12)
    for u, v in rng.uniform(-80, 80, (8, 2)):
        dx, dy = A @ (u, v) + (0.4, -0.3)
        _add_shift(acc, u, v, dx, dy)
    for u, v in rng.uniform(-80, 80, (5, 2)):
        want = A @ (u, v) + (0.4, -0.3)
        assert np.allclose(_predicted(acc, u, v), want, atol=1e-9)


def test_no_prediction_from_features_on_a_line():
    acc = np.zeros(12)
    for t in range(8):
        _add_shift(acc, 10.0 * t, 5.0 * t, 0.3, 0.1)      # collinear: no turn to fit
    assert _predicted(acc, 3.0, 40.0) == (0.0, 0.0)


def test_the_rectifier_is_rectify_with_its_tables_looked_up_once():
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    grey = np.random.default_rng(1).integers(0, 255, (rig.camera.height, rig.camera.width),
                                             dtype=np.uint8)
    for res in (0.01, 0.02):                              # pyramid levels 1 and 2
        r = Rectifier.of(rig, 2.7, res, 1.0)
        patch, valid = r(grey)
        want, want_valid = rectify(grey, rig, 2.7, res, 1.0)
        assert np.array_equal(patch, want) and np.array_equal(valid, want_valid)


def test_the_priors_quadratic_form_is_numpys():
    def quadratic(S, e):
        n = len(e)
        a = np.zeros((3, 4))
        a[:n, :n], a[:n, n] = S, e
        return _quadratic(a, np.asarray(e, float), n)

    rng = np.random.default_rng(2)
    for n in (1, 2, 3):
        for _ in range(50):
            a = rng.normal(size=(n, n))
            S = a @ a.T + 1e-3 * np.eye(n)
            e = rng.normal(size=n)
            assert math.isclose(quadratic(S, e), float(e @ np.linalg.solve(S, e)),
                                rel_tol=1e-9)
    assert quadratic([[1.0, 1.0], [1.0, 1.0]], [1.0, 0.0]) == math.inf
