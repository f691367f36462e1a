"""The texture method under a rolling shutter (issue 39): a frame read out over 25 ms
while the vehicle turns fast, located with and without the readout model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.texture import TextureEstimator
from ceilkit.runtime.estimators.texture.match import refine
from ceilkit.runtime.estimators.texture.shutter import Readout, joint_fit, refit
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


def test_without_a_velocity_the_frame_gives_its_own(office):
    """No velocity known, turning at 57 deg/s: the frame's rows give the velocity
    (:func:`.shutter.joint_fit`), within 3 sigma of the truth; the pose at the stamp
    within 1.5 mm and 3 sigma of its covariance, where the frame taken as a global
    shutter's is off by over twice that."""
    pose = (2.5, 0.0, 0.3)
    img, v = _turning_frame(office, pose, 1.0)
    site = office.sites["scatter"]
    a = TextureEstimator(office.rig, site, {"plane_odometry": False}).estimate(img, 0)
    b = TextureEstimator(office.rig, site, {"plane_odometry": False,
                                            "readout_ms": READOUT_MS}).estimate(img, 0)
    assert isinstance(a, PoseEstimate) and isinstance(b, PoseEstimate)
    err = _error_mm(b, pose)
    assert err < 1.5 and _error_mm(a, pose) > 2.0 * err
    assert err < 3.0 * 1e3 * math.sqrt(b.cov[0, 0] + b.cov[1, 1])
    got, sigma = (np.array(b.diagnostics[k]) for k in ("velocity", "velocity_sigma"))
    assert np.all(np.abs(got - v) < 3.0 * sigma), (got, sigma, v)
    assert "velocity" not in a.diagnostics


def _synthetic(tau_of, velocity, n=60, seed=0, noise_m=5e-4):
    """Features over a 1.2 m square of V seen at row times ``tau_of(q)`` from a vehicle at
    ``POSE`` moving at ``velocity`` (W), their map points in W with ``noise_m``."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.6, 0.6, (n, 2))
    tau = tau_of(q)
    x, y, yaw = POSE
    a = yaw + velocity[2] * tau
    c, s = np.cos(a), np.sin(a)
    p = np.column_stack([c * q[:, 0] - s * q[:, 1] + x + velocity[0] * tau,
                         s * q[:, 0] + c * q[:, 1] + y + velocity[1] * tau])
    return q, tau, p + rng.normal(0.0, noise_m, p.shape)


POSE = (3.0, -1.0, 0.7)
ROWS = lambda q: q[:, 0] / 1.2 * 0.025       # noqa: E731  rows along V's x, 25 ms
UNKNOWN = (0.5, 0.5, math.radians(30.0))


@pytest.mark.parametrize("velocity", [(0.4, -0.3, 2.0), (0.0, 0.0, 0.0), (-0.5, 0.2, -1.2)])
def test_joint_fit_recovers_pose_and_velocity_within_their_sigma(velocity):
    q, tau, p = _synthetic(ROWS, velocity)
    start = (POSE[0] + 0.004, POSE[1] - 0.003, POSE[2] + 0.01)
    fit = joint_fit(q, tau, p, np.arange(len(q)), start, 0.03, 1e-4, UNKNOWN)
    assert fit is not None and len(fit.used) == len(q)
    err = np.array(fit.pose) - POSE
    assert abs(err[0]) < 3 * math.sqrt(fit.cov[0, 0]) and abs(err[1]) < 3 * math.sqrt(
        fit.cov[1, 1]) and abs(err[2]) < 3 * math.sqrt(fit.cov[2, 2]), (err, fit.cov)
    verr = np.array(fit.velocity) - velocity
    assert np.all(np.abs(verr) < 3.0 * np.array(fit.velocity_sigma)), (verr, fit.velocity_sigma)
    assert np.all(np.array(fit.velocity_sigma) < np.array(UNKNOWN))


@pytest.mark.parametrize("tau_of", [lambda q: np.zeros(len(q)),                  # global
                                    lambda q: 1e-4 * np.sign(q[:, 0])],          # 9 rows
                         ids=["global_shutter", "a_few_rows"])
def test_joint_fit_falls_back_where_the_rows_do_not_determine_the_velocity(tau_of):
    """A global shutter's frame (every row at the stamp: the velocity's columns are
    zero) or features on two rows 0.2 ms apart (9 rows of a 25 ms, 480-row readout; the
    velocity's sigma over 0.5 m/s): no joint fit; :func:`.shutter.refit` then takes the
    features as seen at the stamp, the covariance grown by what the ``unknown_*`` sigmas
    move them (nothing where every row is the stamp's)."""
    q, tau, p = _synthetic(tau_of, (0.4, -0.3, 2.0))
    qi = np.arange(len(q))
    assert joint_fit(q, tau, p, qi, POSE, 0.03, 1e-4, UNKNOWN) is None
    ro = Readout(None, 2.7, 0.025, (0.0, 0.0, 0.0), UNKNOWN, known=False)
    got = refit(ro, q, tau, p, qi, POSE, 0.03, 1e-4)
    plain = refine(q, p, qi, POSE, 0.03, 1e-4)
    assert got is not None and got.velocity is None
    assert got.pose == pytest.approx(plain.pose, abs=1e-12)
    grown = np.trace(got.cov) - np.trace(plain.cov)
    assert grown > 0 if np.any(tau) else grown == pytest.approx(0.0, abs=1e-15)


def test_tracked_path_models_the_readout(office):
    """The fast path (a tight prior 5 mm and 0.3 deg off) at 57 deg/s: without the
    readout model its pose is off by about 5 mm; with it, the prior carrying the
    velocity or not (the frame's own then fitted: :func:`.shutter.joint_fit`), within
    2 mm and under half that."""
    pose = (2.5, 0.0, 0.3)
    img, v = _turning_frame(office, pose, 1.0)
    site = office.sites["scatter"]
    errs = []
    for readout, velocity in ((0.0, v), (READOUT_MS, v), (READOUT_MS, None)):
        prior = PoseEstimate(0, "track", pose[0] + 0.005, pose[1], pose[2] + 0.005, 0.0,
                             cov=np.diag([1e-4, 1e-4, 1e-4]), velocity=velocity)
        e = TextureEstimator(office.rig, site, {"plane_odometry": False,
                                                "readout_ms": readout}).estimate(img, 0, prior)
        assert isinstance(e, PoseEstimate), e
        assert e.diagnostics["search"] == "tracked"
        assert ("velocity" in e.diagnostics) == (readout > 0 and velocity is None)
        errs.append(_error_mm(e, pose))
    assert all(err < 2.0 and err < 0.5 * errs[0] for err in errs[1:]), errs
