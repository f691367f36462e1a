"""A light constant-velocity tracker that gates outliers and never jumps silently.

Per frame the tracker predicts the pose at the frame's time (the estimators'
``prior``), then checks the estimator's measurement against the prediction:

* the prediction is the fusion's model of the vehicle (one model in the project):
  constant velocity with white acceleration (``options.noise``, a
  :class:`~ceilkit.runtime.geometry.ekf.MotionNoise`: 0.8 m/s^2 and 60 deg/s^2 per
  sqrt(Hz), as ``ekf.predict_cv``), Kalman-filtered per axis over the accepted poses
  with their own variances, so the velocity and its uncertainty are what the poses
  and the time between them say (not a smoothing that lags). A new track's velocity
  is unknown within the vehicle's stated limits (:func:`unknown_rates`); the fusion's
  ``noise`` is the tracker's too (``multi.make_localizer``). The prediction's
  covariance is the region in which the estimators' prior may choose among a frame's
  twins
  (:mod:`~.estimators.prior`): 0.1 s after a fix at 10 fps about 2 cm and 1.5 deg
  (1σ), where it was a 0.3 m/s, 15 deg/s velocity 1σ held over the time (4 cm and
  2.5 deg: a held-out tile kidnap's twin 0.16 m away lay inside it, issue 36);
* inside the gate: accepted; the published pose is the measurement itself (the
  estimators are more accurate than a motion model); a prediction carries the
  velocity once one was measured (two poses: ``PoseEstimate.velocity``, for a
  rolling shutter's rows);
* outside the gate (``gate_m`` + ``max_speed_mps`` x dt, as the heading): replaced by
  ``Failure(reason="gated")``, unless ``confirm`` consecutive measurements agree
  with each other away from the track: then the track is re-localized there and the
  result says so (``relocalized``), so the link can bump its reset counter;
* no accepted measurement for ``lost_after_s``: the track is dropped and the
  next measurement starts a new one (also a re-localization);
* ``confirm`` ambiguous frames in a row whose poses (``hypotheses``) all lie outside
  the prediction's region (:func:`~.estimators.prior.allows`, each with its own
  covariance): the frames contradict the track (a kidnap, a wrong start pose) and it
  is dropped, as the fusion drops one; kept, its region would widen frame by frame
  until it took in a twin of the vehicle's new pose, which the prior would then
  choose (issue 36's held-out lamps: 34 valid poses 3.5 m and 180 deg off after a
  kidnap); after such a frame, a pose the track's own prior chose among twins
  (``Provenance.PRIOR``) does not confirm the track but counts as one more such frame.

Coordinates the method does not observe (x for the corridor method) are neither
predicted nor gated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, Failure, PoseEstimate, Provenance
from ceilkit.runtime.estimators.prior import (
    DEFAULT_PRIOR_SIGMA,
    MAX_SPEED_MPS,
    MAX_TURN_RPS,
    PRIOR_P,
    allows,
)
from ceilkit.runtime.geometry.ekf import MotionNoise, chi2_quantile, cv_noise
from ceilkit.runtime.geometry.rotations import wrap_pi


@dataclass(frozen=True)
class TrackerOptions:
    gate_m: float = 0.25             # position gate at dt = 0
    gate_rad: float = math.radians(8.0)
    max_speed_mps: float = MAX_SPEED_MPS  # the gate grows by this times dt (prior.py)
    max_turn_rps: float = MAX_TURN_RPS
    confirm: int = 3                 # agreeing out-of-gate frames that re-localize
    lost_after_s: float = 1.0
    # the prediction (the region in which its prior may choose among a frame's twins,
    # estimators/prior.py): the fusion's constant-velocity model of the vehicle, white
    # acceleration (``MotionNoise.accel_mps2``, ``turn_rps2``; geometry/ekf.py),
    # filtered over the accepted poses with their own variances; a velocity not yet
    # measured: ``unknown_rates``, whose PRIOR_P region is the vehicle's stated limits
    noise: MotionNoise = field(default_factory=MotionNoise)
    # 1σ of an accepted pose that carries no covariance (every estimator's pose carries
    # one; a pose made by hand does not): the earlier tracker's 1σ of any accepted pose
    sigma_m: float = 0.01
    sigma_rad: float = math.radians(1.0)


class _Pose(NamedTuple):
    """A predicted pose as the gate reads it (:meth:`Tracker._predicted`)."""

    x_m: float | None
    y_m: float | None
    yaw_rad: float


@dataclass(frozen=True)
class TrackResult:
    estimate: Estimate
    relocalized: bool = False


class _Axis(NamedTuple):
    """One coordinate of the track (x, y or heading) under the constant-velocity model:
    its value and rate, and their covariance (``ppp``, ``ppv``, ``pvv``)."""

    p: float
    v: float
    ppp: float
    ppv: float
    pvv: float


@dataclass
class _State:
    """The track at ``t_ns``: x, y and heading (:class:`_Axis`; the model's axes are
    independent, a pose's cross-covariances left out: :func:`_absorbed`) over the
    coordinates the method gives (``has``: x, y; one it does not give is neither
    predicted nor gated)."""

    t_ns: int
    axes: tuple[_Axis, _Axis, _Axis]
    has: tuple[bool, bool]
    moving: bool = False  # a velocity measured (before: unknown, within the limits)
    fixed: bool = True    # the pose measured (not a start pose)


class Tracker:
    """See the module docstring. ``predict`` gives the prior, ``update`` the verdict."""

    def __init__(self, options: TrackerOptions | None = None,
                 start_pose: tuple[float, float, float] | None = None,
                 start_sigma: tuple[float, float] = DEFAULT_PRIOR_SIGMA):
        self.options = options or TrackerOptions()
        self._start_sd = (float(start_sigma[0]), float(start_sigma[1]))
        self._s: _State | None = None
        self._candidates: list[PoseEstimate] = []
        self.relocalizations = 0
        self.start_poses = 0
        self._pending: tuple[float, float, float] | None = start_pose
        self._jumped = False    # a start pose was taken: the next result is a reset
        self._disagree = 0      # frames in a row whose poses all lie outside the prior

    def set_start_pose(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float,
                       cov: object = None) -> None:
        """(Re)start the track at ``(x_m, y_m, yaw_rad)`` in W (a ``--start-pose`` or
        ROS ``/initialpose``): from the next frame the estimators get it as their prior,
        which chooses among the poses a frame supports alike (a symmetric corridor's
        half turn, a light grid's cells). Safe from any thread (it is taken at the next
        :meth:`predict`). ``t_ns`` is accepted for the fusion's interface; ``cov``'s
        diagonal, when given, is the start pose's region (the prior's, which chooses
        among twins: estimators/prior.py); else the tracker's ``start_sigma``."""
        if not all(math.isfinite(v) for v in (x_m, y_m, yaw_rad)):
            raise ValueError("set_start_pose: the pose must be finite")
        if cov is not None:
            d = np.sqrt(np.abs(np.diag(np.asarray(cov, float).reshape(3, 3))))
            if np.all(np.isfinite(d)) and np.all(d > 0):
                self._start_sd = (float(max(d[0], d[1])), float(d[2]))
        self._pending = (float(x_m), float(y_m), float(yaw_rad))

    @property
    def tracking(self) -> bool:
        return self._s is not None

    def reset(self) -> None:
        self._s = None
        self._candidates = []
        self._disagree = 0

    def predict(self, t_ns: int, method: str = "track") -> PoseEstimate | None:
        """The predicted vehicle pose at ``t_ns``, or ``None`` when not tracking."""
        at = self._predicted(t_ns)
        if at is None:
            return None
        s, dt, pose = at
        ax = _advanced(s, dt, self.options.noise)
        var = [a.ppp if k == 2 or s.has[k] else math.inf for k, a in enumerate(ax)]
        return PoseEstimate(
            t_ns=t_ns, method=method, x_m=pose.x_m, y_m=pose.y_m, yaw_rad=pose.yaw_rad,
            quality=0.0, cov=np.diag(var),
            velocity=(ax[0].v, ax[1].v, ax[2].v) if s.moving else None)

    def _predicted(self, t_ns: int) -> tuple[_State, float, _Pose] | None:
        """``(state, dt s, pose)``: :meth:`predict`'s pose at ``t_ns`` (a pending start
        pose taken first) without its covariance or object (the gate reads the pose
        only), or ``None`` when not tracking."""
        pending, self._pending = self._pending, None
        if pending is not None:
            sd_m, sd_r = self._start_sd
            self._s = _new_state(int(t_ns), pending, (sd_m * sd_m, sd_m * sd_m, sd_r * sd_r),
                                 self.options, fixed=False)
            self._candidates = []
            self.start_poses += 1
            self._jumped = True
        s = self._s
        if s is None:
            return None
        dt = (t_ns - s.t_ns) * 1e-9
        if dt > self.options.lost_after_s:
            return None
        x, y, yaw = s.axes
        return s, dt, _Pose(x.p + x.v * dt if s.has[0] else None,
                            y.p + y.v * dt if s.has[1] else None,
                            wrap_pi(yaw.p + yaw.v * dt))

    def _contradicts(self, est: Failure) -> bool:
        """Whether a failed frame lists poses (its ``hypotheses``: an ambiguous frame)
        and none lies inside the prediction's region (:func:`~.estimators.prior.allows`)."""
        if not est.hypotheses or self._s is None or self._pending is not None:
            return False
        pred = self.predict(est.t_ns)
        return pred is not None and not any(
            allows(pred, (h.x_m, h.y_m, h.yaw_rad, h.cov)) for h in est.hypotheses)

    def _inside(self, a: PoseEstimate, b: PoseEstimate | _Pose, dt_s: float) -> bool:
        o = self.options
        gate_m = o.gate_m + o.max_speed_mps * abs(dt_s)
        gate_r = o.gate_rad + o.max_turn_rps * abs(dt_s)
        if abs(wrap_pi(a.yaw_rad - b.yaw_rad)) > gate_r:
            return False
        for p, q in ((a.x_m, b.x_m), (a.y_m, b.y_m)):
            if p is not None and q is not None and abs(p - q) > gate_m:
                return False
        return True

    def _start(self, est: PoseEstimate) -> TrackResult:
        self._s = _new_state(est.t_ns, (est.x_m, est.y_m, est.yaw_rad),
                             _pose_var(est, self.options), self.options)
        self._candidates = []
        self.relocalizations += 1
        return TrackResult(est, relocalized=True)

    def update(self, est: Estimate) -> TrackResult:
        """Gate one measurement; returns what to publish (a reset, ``relocalized``, on
        the first frame after a start pose was taken)."""
        res = self._update(est)
        if self._jumped:
            self._jumped = False
            return TrackResult(res.estimate, True)
        return res

    def _update(self, est: Estimate) -> TrackResult:
        if not isinstance(est, PoseEstimate):
            if self._s is not None and (est.t_ns - self._s.t_ns) * 1e-9 > \
                    self.options.lost_after_s:
                self.reset()
            elif self._contradicts(est):
                # the frame supports poses, none of them the track's (a kidnap, a wrong
                # start pose): ``confirm`` such frames in a row drop the track, as the
                # fusion does; kept, its region would widen until it took in a twin of
                # wherever the vehicle now is, and the prior would choose that twin
                self._disagree += 1
                if self._disagree >= self.options.confirm:
                    self.reset()
            return TrackResult(est)
        if self._disagree and est.provenance is Provenance.PRIOR:
            # after a frame that contradicted the track, a pose its own prior chose among
            # twins does not confirm it: the region has widened since and may hold a twin
            # of wherever the vehicle now is (tiles2's kidnap: a quarter-turn twin, 28
            # poses 90 deg and 2.3 m off)
            self._disagree += 1
            if self._disagree >= self.options.confirm:
                self.reset()
            return TrackResult(Failure(est.t_ns, est.method, "gated", "a pose the "
                                       "track's prior chose after a frame contradicted "
                                       "the track", diagnostics={"rejected": est}))
        self._disagree = 0
        at = self._predicted(est.t_ns)
        if at is None:
            return self._start(est)
        pred = at[2]
        s = self._s
        dt = (est.t_ns - s.t_ns) * 1e-9
        if self._inside(est, pred, 0.0 if dt <= 0 else dt):
            self._candidates = []
            self._s = _absorbed(s, est, self.options)
            return TrackResult(est)
        # outside the gate: a glitch, or the vehicle really is elsewhere; only a pose the
        # frame alone singled out may move the track (one a prior chose among twins
        # proves nothing against the track)
        if self._jumped and abs(wrap_pi(est.yaw_rad - pred.yaw_rad)) <= \
                self.options.gate_rad + self.options.max_turn_rps * max(dt, 0.0):
            # the first frame after a start pose: its heading chose among the frame's
            # twins; where the vehicle is, the frame says (a start pose is rough)
            return self._start(est)
        if not est.singled_out:
            return TrackResult(Failure(
                est.t_ns, est.method, "gated",
                f"pose away from the track ({_describe_jump(est, pred)}) and not singled "
                "out by its frame", diagnostics={"rejected": est}))
        if self._candidates:
            last = self._candidates[-1]
            dtc = (est.t_ns - last.t_ns) * 1e-9
            if not self._inside(est, last, dtc):
                self._candidates = []
        self._candidates.append(est)
        if len(self._candidates) >= self.options.confirm:
            return self._start(est)
        return TrackResult(Failure(
            est.t_ns, est.method, "gated",
            f"pose jumped from the track ({_describe_jump(est, pred)}); "
            f"waiting for {self.options.confirm - len(self._candidates)} more to confirm",
            diagnostics={"rejected": est}))


def _new_state(t_ns: int, pose: tuple[float | None, float | None, float],
               var: tuple[float, float, float], o: TrackerOptions,
               fixed: bool = True) -> _State:
    """A track at ``pose`` (x or y None: not given) of variances ``var`` (x, y, heading),
    its velocity unknown (:func:`unknown_rates`); ``fixed``: the pose was measured (not
    a start pose)."""
    sv, sw = unknown_rates(o)
    axes = tuple(_Axis(0.0 if p is None else float(p), 0.0, float(v), 0.0, r * r)
                 for p, v, r in zip((pose[0], pose[1], wrap_pi(pose[2])), var, (sv, sv, sw),
                                    strict=True))
    return _State(int(t_ns), axes, (pose[0] is not None, pose[1] is not None),  # type: ignore[arg-type]
                  fixed=fixed)


def _advanced(st: _State, dt_s: float, noise: MotionNoise) -> tuple[_Axis, _Axis, _Axis]:
    """The track's axes ``dt_s`` later: the fusion's constant-velocity model with white
    acceleration (:func:`~ceilkit.runtime.geometry.ekf.predict_cv`, per axis: its axes
    are independent)."""
    dt = max(dt_s, 0.0)
    out = []
    for a, q in zip(st.axes, (noise.accel_mps2, noise.accel_mps2, noise.turn_rps2),
                    strict=True):
        qpp, qpv, qvv = cv_noise(q, dt)
        out.append(_Axis(a.p + a.v * dt, a.v, a.ppp + dt * (2.0 * a.ppv + dt * a.pvv) + qpp,
                         a.ppv + dt * a.pvv + qpv, a.pvv + qvv))
    return out[0], out[1], out[2]


def _absorbed(st: _State, est: PoseEstimate, o: TrackerOptions) -> _State:
    """The track after an accepted pose: predicted to its time and updated with it (a
    Kalman update per axis with the pose's own variance, :func:`_pose_var`; its
    cross-covariances, a corridor fix's y with its heading, are left out: the pose's
    1σ is 0.01-1 mm where the model's region 0.1 s on is 2 cm); a coordinate the track
    did not give is taken from the pose (its velocity unknown), one the pose does not
    give is dropped."""
    dt = (est.t_ns - st.t_ns) * 1e-9
    ax = _advanced(st, dt, o.noise)
    var = _pose_var(est, o)
    sv = unknown_rates(o)[0]
    out = []
    for k, z in enumerate((est.x_m, est.y_m, est.yaw_rad)):
        a = ax[k]
        if z is None:
            out.append(a)
        elif k < 2 and not st.has[k]:
            out.append(_Axis(float(z), 0.0, var[k], 0.0, sv * sv))
        else:
            e = float(z) - a.p if k < 2 else wrap_pi(float(z) - a.p)
            s = a.ppp + var[k]
            kp, kv = a.ppp / s, a.ppv / s
            out.append(_Axis(a.p + kp * e if k < 2 else wrap_pi(a.p + kp * e), a.v + kv * e,
                             (1.0 - kp) * a.ppp, (1.0 - kp) * a.ppv, a.pvv - kv * a.ppv))
    given = (est.x_m is not None, est.y_m is not None)
    return _State(est.t_ns, (out[0], out[1], out[2]), given,
                  moving=st.moving or (st.fixed and dt > 1e-6))


def _pose_var(est: PoseEstimate, o: TrackerOptions) -> tuple[float, float, float]:
    """The pose's own variances (x, y, heading; those it does not give unread), or
    ``sigma_m``, ``sigma_rad`` where it carries none (or a degenerate one)."""
    out = [o.sigma_m ** 2, o.sigma_m ** 2, o.sigma_rad ** 2]
    c = est.cov
    if c is not None and np.shape(c) == (3, 3):
        for k in range(3):
            v = float(c[k][k])
            if math.isfinite(v) and v > 0:
                out[k] = v
    return out[0], out[1], out[2]


def unknown_rates(o: TrackerOptions) -> tuple[float, float]:
    """1σ (m/s per axis, rad/s) of a velocity not yet measured: the Gaussian whose
    ``PRIOR_P`` region over the fewest coordinates a prior is read on (1: the heading
    alone, a corridor frame's turn, ``corridor/hypotheses.py``) reaches
    ``max_speed_mps`` and ``max_turn_rps``, the vehicle's stated limits (over y and
    heading, 13 % farther; over all three, 22 %): a twin beyond the vehicle's reach is
    outside it. With the 2-dof region's 1σ (before, 2026-12-07 stop 54) a heading-only
    check 0.1 s after a first fix reached 88 % of the stated turn rate (the old
    tracker's 1 deg added to it hid that: ``bench_heldout_lines.py --seed 41``'s
    corridor2 turns 92 deg/s on its first frame, which was then refused); half the
    limits (before, 2026-12-07) reached 1.86 times them: 0.1 s
    after a start pose a corridor track's region held the twins a 0.5 m tile away, and
    its prior chose on no later frame of a tile grid (tiles0: 1 of 60 valid)."""
    k = math.sqrt(chi2_quantile(PRIOR_P, 1))
    return o.max_speed_mps / k, o.max_turn_rps / k


def _describe_jump(est: PoseEstimate, pred: PoseEstimate | _Pose) -> str:
    parts = [f"yaw {math.degrees(wrap_pi(est.yaw_rad - pred.yaw_rad)):+.1f} deg"]
    if est.y_m is not None and pred.y_m is not None:
        parts.append(f"y {est.y_m - pred.y_m:+.2f} m")
    if est.x_m is not None and pred.x_m is not None:
        parts.append(f"x {est.x_m - pred.x_m:+.2f} m")
    return ", ".join(parts)
