"""The texture method under a rolling shutter (issue 39): a frame read out over 25 ms
while the vehicle turns fast, located with and without the readout model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.texture import TextureEstimator
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.sim.realism import Realism, render_real
from ceilkit.runtime.sim.render import Trajectory

READOUT_MS = 25.0
FREE = np.diag([np.inf, np.inf, 1e4])   # a prior on the motion only: no position


def _turning_frame(office, pose, rate_rps):
    """The frame stamped 0 at ``pose``, the vehicle moving 0.5 m/s ahead and turning at
    ``rate_rps``, read out top to bottom over :data:`READOUT_MS`; and the velocity."""
    x0, y0, a0 = pose
    v = (0.5 * math.cos(a0), 0.5 * math.sin(a0), rate_rps)
    t = np.array([-10 ** 8, 0, 10 ** 8], np.int64)
    traj = Trajectory(t, x0 + v[0] * t / 1e9, y0 + v[1] * t / 1e9, a0 + v[2] * t / 1e9)
    img = render_real(office.rig, office.sites["scatter"], traj.pose_at, 0, office.opts,
                      Realism(rolling_shutter_ms=READOUT_MS, time_samples=16),
                      np.random.default_rng(3))
    return img, v


def _error_mm(e, pose):
    return 1e3 * math.hypot(e.x_m - pose[0], e.y_m - pose[1])


@pytest.mark.parametrize("pose", [(2.5, 0.0, 0.3), (3.2, -0.4, 2.0)])
def test_readout_model_takes_a_fast_turn_back(office, pose):
    """At 143 deg/s (3.6 deg across the readout) the frame fitted as a global shutter's is
    off by several mm or a misfit; with ``readout_ms`` and the prior's velocity its
    pose is the stamp's within 2 mm, inside 3 sigma of its covariance."""
    img, v = _turning_frame(office, pose, 2.5)
    site = office.sites["scatter"]
    prior = PoseEstimate(0, "track", None, None, 0.0, 0.0, cov=FREE, velocity=v)
    plain = TextureEstimator(office.rig, site, {"plane_odometry": False}).estimate(img, 0)
    est = TextureEstimator(office.rig, site, {"plane_odometry": False,
                                              "readout_ms": READOUT_MS})
    e = est.estimate(img, 0, prior)
    assert isinstance(e, PoseEstimate), e
    assert not plain or _error_mm(plain, pose) > 5.0
    err = _error_mm(e, pose)
    assert err < 2.0
    assert err < 3.0 * 1e3 * math.sqrt(e.cov[0, 0] + e.cov[1, 1])
    assert abs(math.degrees(wrap_pi(e.yaw_rad - pose[2]))) < 0.1


def test_without_a_velocity_the_pose_is_as_fitted_and_its_covariance_grows(office):
    """No velocity known: the features are taken as seen at the stamp (the same pose as
    with a global shutter assumed) and the covariance grows by the ``unknown_*``
    sigmas' effect."""
    pose = (2.5, 0.0, 0.3)
    img, _ = _turning_frame(office, pose, 1.0)
    site = office.sites["scatter"]
    a = TextureEstimator(office.rig, site, {"plane_odometry": False}).estimate(img, 0)
    b = TextureEstimator(office.rig, site, {"plane_odometry": False,
                                            "readout_ms": READOUT_MS}).estimate(img, 0)
    assert isinstance(a, PoseEstimate) and isinstance(b, PoseEstimate)
    assert (a.x_m, a.y_m, a.yaw_rad) == pytest.approx((b.x_m, b.y_m, b.yaw_rad), abs=1e-9)
    assert np.trace(b.cov[:2, :2]) > 1.5 * np.trace(a.cov[:2, :2])


def test_tracked_path_models_the_readout(office):
    """The fast path (a tight prior 5 mm and 0.3 deg off, carrying the velocity) at
    57 deg/s: without the readout model its pose is off by about 5 mm, with it within
    2 mm and under half that."""
    pose = (2.5, 0.0, 0.3)
    img, v = _turning_frame(office, pose, 1.0)
    site = office.sites["scatter"]
    prior = PoseEstimate(0, "track", pose[0] + 0.005, pose[1], pose[2] + 0.005, 0.0,
                         cov=np.diag([1e-4, 1e-4, 1e-4]), velocity=v)
    errs = []
    for readout in (0.0, READOUT_MS):
        e = TextureEstimator(office.rig, site, {"plane_odometry": False,
                                                "readout_ms": readout}).estimate(img, 0, prior)
        assert isinstance(e, PoseEstimate), e
        assert e.diagnostics["search"] == "tracked"
        errs.append(_error_mm(e, pose))
    assert errs[1] < 2.0 and errs[1] < 0.5 * errs[0]
