"""The block fix's covariance by parts (``pnp.residual_parts``, issue 36): a common
offset of the four sides is fitted apart (counted once, as its own effect on the pose),
so the white noise and the side offsets read the same with or without it."""

from __future__ import annotations

import numpy as np

from ceilkit.runtime.estimators.block.pnp import residual_parts


def _fit(seed: int, per_side: int = 12):
    """A square's edge points' Jacobian ``(M, 3)`` of a planar pose, each side's points
    along it, and ``A = (JᵀJ)⁻¹``: side k's normal rotates by 90 deg per side."""
    rng = np.random.default_rng(seed)
    rows, side = [], []
    for k in range(4):
        n = np.array([np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)])
        t = np.array([-n[1], n[0]])
        for s in np.linspace(-0.4, 0.4, per_side):
            p = 0.5 * n + s * t
            rows.append([n[0], n[1], n[0] * -p[1] + n[1] * p[0]])
            side.append(k)
    J = np.array(rows) * 40.0 + rng.normal(0.0, 0.5, (len(rows), 3))
    return J, np.array(side), np.linalg.inv(J.T @ J)


def test_a_common_offset_leaves_the_noise_and_side_terms_alone():
    J, side, A = _fit(1)
    r = np.random.default_rng(2).normal(0.0, 0.05, len(side))
    s2, vb, U, C = residual_parts(r, J, side, A)
    s2c, vbc, Uc, Cc = residual_parts(r + 0.4, J, side, A)
    assert np.isclose(s2c, s2, rtol=1e-9) and np.isclose(vbc, vb, rtol=1e-9, atol=1e-15)
    assert U is not None and np.allclose(Uc, U)
    # the offset's own effect on the pose is added instead, and grows with it
    assert np.trace(Cc) > np.trace(C)


def test_the_noise_term_is_inflated_for_few_points_and_floored():
    J, side, A = _fit(3, per_side=3)
    r = np.random.default_rng(4).normal(0.0, 0.1, len(side))
    s2 = residual_parts(r, J, side, A)[0]
    rc = r - r.mean()
    assert s2 > float(rc @ rc) / (len(r) - 4)          # the Student factor
    assert residual_parts(np.zeros(len(side)), J, side, A)[0] > 0.0   # the floor
