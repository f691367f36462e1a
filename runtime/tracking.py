"""A light constant-velocity tracker that gates outliers and never jumps silently.

Per frame the tracker predicts the pose at the frame's time (the estimators'
``prior``), then checks the estimator's measurement against the prediction:

* inside the gate: accepted; the published pose is the measurement itself (the
  estimators are more accurate than a motion model), the velocity is smoothed (the
  track's first sample taken whole); a prediction carries the velocity once one was
  measured (``PoseEstimate.velocity``, for a rolling shutter's rows);
* outside the gate: replaced by ``Failure(reason="gated")``, unless
  ``confirm`` consecutive measurements agree with each other away from the
  track: then the track is re-localized there and the result says so
  (``relocalized``), so the link can bump its reset counter;
* no accepted measurement for ``lost_after_s``: the track is dropped and the
  next measurement starts a new one (also a re-localization);
* ``confirm`` ambiguous frames in a row whose poses (``hypotheses``) all lie outside
  the prediction's region (:func:`~.estimators.prior.allows`): the frames contradict
  the track (a kidnap, a wrong start pose) and it is dropped, as the fusion drops
  one; kept, its region would widen frame by frame until it took in a twin of the
  vehicle's new pose, which the prior would then choose (issue 36's held-out lamps:
  34 valid poses 3.5 m and 180 deg off after a kidnap); after such a frame, a pose the
  track's own prior chose among twins (``Provenance.PRIOR``) does not confirm the
  track but counts as one more such frame.

Coordinates the method does not observe (x for the corridor method) are neither
predicted nor gated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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
from ceilkit.runtime.geometry.ekf import chi2_quantile
from ceilkit.runtime.geometry.rotations import wrap_pi


@dataclass(frozen=True)
class TrackerOptions:
    gate_m: float = 0.25             # position gate at dt = 0
    gate_rad: float = math.radians(8.0)
    max_speed_mps: float = MAX_SPEED_MPS  # the gate grows by this times dt (prior.py)
    max_turn_rps: float = MAX_TURN_RPS
    velocity_smoothing: float = 0.3  # 0..1: weight of a new velocity sample
    confirm: int = 3                 # agreeing out-of-gate frames that re-localize
    lost_after_s: float = 1.0
    # the prediction's 1σ (the region in which its prior may choose among a frame's
    # twins, estimators/prior.py): an accepted pose's, growing with the velocity's
    # 1σ (a measured velocity; an unknown one: ``unknown_rates``, whose PRIOR_P
    # region is the vehicle's stated limits)
    sigma_m: float = 0.01
    sigma_rad: float = math.radians(1.0)
    speed_sigma_mps: float = 0.3
    turn_sigma_rps: float = math.radians(15.0)


class _Pose(NamedTuple):
    """A predicted pose as the gate reads it (:meth:`Tracker._predicted`)."""

    x_m: float | None
    y_m: float | None
    yaw_rad: float


@dataclass(frozen=True)
class TrackResult:
    estimate: Estimate
    relocalized: bool = False


@dataclass
class _State:
    t_ns: int
    x: float | None
    y: float | None
    yaw: float
    vx: float = 0.0
    vy: float = 0.0
    vyaw: float = 0.0
    moving: bool = False  # a velocity measured (before: at rest, assumed, not known)
    sd: tuple[float, float] = (0.0, 0.0)  # 1σ (m, rad) of the pose at t_ns


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
        return PoseEstimate(
            t_ns=t_ns, method=method, x_m=pose.x_m, y_m=pose.y_m, yaw_rad=pose.yaw_rad,
            quality=0.0, cov=self._cov(s, max(dt, 0.0)),
            velocity=(s.vx, s.vy, s.vyaw) if s.moving else None)

    def _predicted(self, t_ns: int) -> tuple[_State, float, _Pose] | None:
        """``(state, dt s, pose)``: :meth:`predict`'s pose at ``t_ns`` (a pending start
        pose taken first) without its covariance or object (the gate reads the pose
        only), or ``None`` when not tracking."""
        pending, self._pending = self._pending, None
        if pending is not None:
            x, y, yaw = pending
            self._s = _State(int(t_ns), x, y, wrap_pi(yaw), sd=self._start_sd)
            self._candidates = []
            self.start_poses += 1
            self._jumped = True
        s = self._s
        if s is None:
            return None
        dt = (t_ns - s.t_ns) * 1e-9
        if dt > self.options.lost_after_s:
            return None
        return s, dt, _Pose(None if s.x is None else s.x + s.vx * dt,
                            None if s.y is None else s.y + s.vy * dt,
                            wrap_pi(s.yaw + s.vyaw * dt))

    def _cov(self, s: _State, dt: float) -> np.ndarray:
        """The prediction's covariance ``dt`` after the state (diagonal; x unknown: inf)."""
        o = self.options
        sv, sw = ((o.speed_sigma_mps, o.turn_sigma_rps) if s.moving
                  else unknown_rates(o))
        sp, sr = s.sd[0] + sv * dt, s.sd[1] + sw * dt
        return np.diag([sp * sp if s.x is not None else math.inf,
                        sp * sp if s.y is not None else math.inf, sr * sr])

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
        self._s = _State(est.t_ns, est.x_m, est.y_m, est.yaw_rad,
                         sd=(self.options.sigma_m, self.options.sigma_rad))
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
            # the first velocity sample of a track is taken whole (before it the
            # velocity is not known, not zero), later ones smoothed
            a = self.options.velocity_smoothing if s.moving else 1.0
            if dt > 1e-6:
                s.moving = True
                if est.x_m is not None and s.x is not None:
                    s.vx = (1 - a) * s.vx + a * (est.x_m - s.x) / dt
                if est.y_m is not None and s.y is not None:
                    s.vy = (1 - a) * s.vy + a * (est.y_m - s.y) / dt
                s.vyaw = (1 - a) * s.vyaw + a * wrap_pi(est.yaw_rad - s.yaw) / dt
            s.t_ns, s.yaw = est.t_ns, est.yaw_rad
            s.sd = (self.options.sigma_m, self.options.sigma_rad)
            s.x = est.x_m if est.x_m is not None else None
            s.y = est.y_m if est.y_m is not None else None
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


def unknown_rates(o: TrackerOptions) -> tuple[float, float]:
    """1σ (m/s per axis, rad/s) of a velocity not yet measured: the Gaussian whose
    ``PRIOR_P`` region over the prior's fewest coordinates (2: a corridor track's y and
    heading) reaches ``max_speed_mps`` and ``max_turn_rps``, the vehicle's stated limits
    (over all three, 8 % farther): a twin beyond the vehicle's reach is outside it.
    Half the limits (before, 2026-12-07) reached 1.86 times them: 0.1 s after a start
    pose a corridor track's region held the twins a 0.5 m tile away, and its prior
    chose on no later frame of a tile grid (``bench_heldout_lines.py``'s tiles0: 1 of
    60 valid)."""
    k = math.sqrt(chi2_quantile(PRIOR_P, 2))
    return o.max_speed_mps / k, o.max_turn_rps / k


def _describe_jump(est: PoseEstimate, pred: PoseEstimate | _Pose) -> str:
    parts = [f"yaw {math.degrees(wrap_pi(est.yaw_rad - pred.yaw_rad)):+.1f} deg"]
    if est.y_m is not None and pred.y_m is not None:
        parts.append(f"y {est.y_m - pred.y_m:+.2f} m")
    if est.x_m is not None and pred.x_m is not None:
        parts.append(f"x {est.x_m - pred.x_m:+.2f} m")
    return ", ".join(parts)
