"""A surveyed light map's own error in the lights fix's covariance (issue 36; SPEC §2
extension ``light_sigma``): :func:`~ceilkit.runtime.estimators.lights.refine.map_cov` is
what moving the lights does to the fit, and the estimator adds it to the fix of the
lights it matched (the pose itself unchanged)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ceilkit.runtime.estimators.lights import LightsEstimator, refine_pose_ceiling
from ceilkit.runtime.estimators.lights.refine import map_cov
from ceilkit.runtime.sim.render import SimOptions, render_frame

JAC = 300.0     # px per m, the same for every light (a camera looking straight up)
LIGHTS = np.array([[0.5, 0.2], [-0.6, 0.4], [0.3, -0.7], [1.1, 0.9], [-0.8, -0.5]])
POSE = (0.2, -0.1, 0.3)


def test_map_cov_of_a_square():
    """Four lights at (+-1, +-1) about the pose: the translation takes sigma² / 4 per
    axis, the turn sigma² / sum |L - t|² = sigma² / 8."""
    lights = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    cov = map_cov(lights, 0.0, 0.0, np.full(4, 0.002))
    np.testing.assert_allclose(cov, np.diag([1e-6, 1e-6, 5e-7]), atol=1e-15)


def test_map_cov_is_what_moving_the_lights_does_to_the_fit():
    """Each light moved along each axis in turn, the fit (the estimator's own, the same
    pixel Jacobian for every light) refitted: the moves' outer products, weighted by
    each light's variance, are map_cov."""
    c, s = math.cos(POSE[2]), math.sin(POSE[2])
    q = (LIGHTS - np.array(POSE[:2])) @ np.array([[c, -s], [s, c]])   # in V
    jac = np.tile(np.eye(2) * JAC, (len(LIGHTS), 1, 1))
    sigma = np.linspace(0.001, 0.004, len(LIGHTS))
    base = np.array(refine_pose_ceiling(q, jac, LIGHTS, *POSE)[:3])
    want = np.zeros((3, 3))
    step = 1e-4
    for i in range(len(LIGHTS)):
        for axis in (0, 1):
            moved = LIGHTS.copy()
            moved[i, axis] += step
            d = (np.array(refine_pose_ceiling(q, jac, moved, *POSE)[:3]) - base) / step
            want += sigma[i] ** 2 * np.outer(d, d)
    got = map_cov(LIGHTS, POSE[0], POSE[1], sigma)
    # to the finite step (1e-4 m on lights 1 m away): 0.1 % of the largest entry
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())


def test_the_estimator_adds_the_matched_lights_map_error(lights_rig, lights_site):
    """The same frame on the site with and without ``light_sigma``: the same pose, the
    covariance larger by map_cov of the lights matched, nothing else."""
    x, y, yaw = 6.0, 0.5, 0.7
    grey = render_frame(lights_rig, lights_site, x, y, yaw, options=SimOptions(
        noise_sigma=2.0, blur_px=0.8, light_radius_m=0.08), rng=np.random.default_rng(4))
    sigma = np.linspace(0.001, 0.003, len(lights_site.lights_m))
    surveyed = dataclasses.replace(lights_site, light_sigma_m=sigma)
    a = LightsEstimator(lights_rig, lights_site).estimate(grey, 0)
    b = LightsEstimator(lights_rig, surveyed).estimate(grey, 0)
    assert a and b, (a, b)
    assert (a.x_m, a.y_m, a.yaw_rad) == (b.x_m, b.y_m, b.yaw_rad)
    ids = np.asarray(b.diagnostics["matched_lights"], int)
    assert len(ids) >= 3
    extra = map_cov(lights_site.lights_m[ids], b.x_m, b.y_m, sigma[ids])
    np.testing.assert_allclose(b.cov, a.cov + extra, rtol=1e-12, atol=1e-18)
    # a millimetre-scale map error dominates a sub-millimetre fit
    assert np.trace(extra[:2, :2]) > np.trace(a.cov[:2, :2])
