"""One vehicle pose from every cue: an EKF over (x, y, yaw) with relocalization.

:class:`Fusion` has the :class:`~ceilkit.runtime.tracking.Tracker` interface
(``predict(t_ns)`` gives the estimators' prior, ``update(estimate)`` the published
result), so the pipeline runs it in the tracker's place. Per frame it takes every
method's estimate (the ``cues`` of an :class:`~ceilkit.runtime.multi.AutoEstimator`
result, or the one estimate), and wheel odometry rows at any time
(:meth:`Fusion.add_odometry`). See docs/fusion.md.

* measurement models (rows of the state, :mod:`~ceilkit.runtime.geometry.ekf`): a
  full-pose fix (lights, block), the corridor method (y and yaw: x is never
  invented), a heading-only fix; each with the estimator's covariance, inflated and
  floored (:class:`FusionOptions`);
* motion: the odometry increments while they come, else constant velocity;
* time: measurements are applied at their capture time; a late one (an odometry row
  stamped before the last frame) re-filters the short buffer from its time;
* gating: a fix whose normalized innovation is beyond the chi-square gate is not
  applied; ``confirm`` agreeing, unambiguous (global) full fixes away from the track
  re-localize it there (``relocalized``: the link bumps its reset counter); while such
  fixes wait, a frame no other cue confirms is a ``gated`` Failure, and a confirmed
  one is published with quality 0: a kidnapped track never keeps a confident old pose;
* lost: no absolute fix for ``lost_after_s`` and no odometry: the next fix starts anew;
* ``quality`` = P(position error < ``quality_radius_m``) from the published
  covariance (:func:`~ceilkit.runtime.geometry.ekf.prob_within_radius`);
* ``method`` of a published pose: the method whose fix observed most in that frame
  (while coasting on the motion model, ``diagnostics["coasting"]``, the last such
  method: ``auto`` before any), ``diagnostics["applied"]`` every method applied.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import (
    Estimate,
    Failure,
    Hypothesis,
    PlaneIncrement,
    PoseEstimate,
    Provenance,
)
from ceilkit.runtime.estimators.prior import (
    DEFAULT_PRIOR_SIGMA,
    MAX_SPEED_MPS,
    MAX_TURN_RPS,
    PRIOR_P,
)
from ceilkit.runtime.geometry import ekf
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.tracking import TrackResult

NAME = "auto"
HOLD_MPS = 0.0005
"""Position random walk while odometry holds the pose between rows, m/√s: small, as
the next row's own noise covers the motion again (ekf's 0.002 over-covered x by ~11 mm
over 30 s of odometry alone: mean NEES 1.94 -> 2.82, bench_fusion)."""
UNKNOWN_X_VAR = 1e6      # m²: x of a track started by the corridor method alone


@dataclass(frozen=True)
class FusionOptions:
    """What a user may tune (docs/fusion.md).

    Attributes:
        noise: process noise (constant velocity, odometry); ``hold_mps`` is
            :data:`HOLD_MPS`.
        gate_p: chi-square probability of the innovation gate.
        confirm: agreeing unambiguous out-of-gate fixes that re-localize.
        lost_after_s: with no fix and no odometry for this long the track is dropped.
        window_s: how far back a late measurement is applied at its time.
        odometry_timeout_s: odometry older than this no longer carries the motion.
        quality_radius_m: the radius of ``quality`` = P(position error < radius).
        unobserved_sigma_m: a coordinate whose 1σ exceeds this is published empty (a
            corridor-only track's x, coasting from its start pose: 0.1 m, so that a
            published coordinate is within about 2σ = 0.2 m; the prior the estimators
            get uses ``prior_sigma_m`` instead).
        unobserved_sigma_rad: a heading whose 1σ exceeds this is not published (the
            frame is a ``coasting`` Failure): a track coasting on a turn rate it has not
            measured.
        prior_sigma_m: the estimators get the track's x and y as a prior only below this
            1σ (each alone: a corridor-only track's y and heading without its x).
        prior_sigma_rad: ... and its heading only below this 1σ (a prior chooses among
            a frame's twins: a half turn, a quarter turn).
        fix_inflation: factor on an estimator's covariance (1: measured consistent),
            for a method not in ``inflation``.
        inflation: the factor per method (docs/fusion.md): 1, the estimators'
            covariances being their residuals' (measured consistent, a little over);
            raise a method's where a real site's consistency line shows its NEES above
            the band (errors correlated from frame to frame, which a per-frame filter
            counts again and again).
        fix_floor_m, fix_floor_rad: 1σ floors of a fix (0.001 mm, 0.0001 deg: a guard
            against a degenerate fit's zero variance, below every estimator's measured
            1σ; docs/fusion.md): a variance below its floor is raised to it, one above
            it is left as it is.
        coast_hazard_per_s: the rate at which something no model of the filter holds
            (the vehicle carried while the camera is covered, wheels slipping) happens
            while no absolute cue confirms the track; ``quality`` is multiplied by
            ``exp(-rate * seconds since the last absolute fix)``.
        default_sigma_m, default_sigma_rad: 1σ of a fix that carries no covariance.
        cell_m: spacing of a regular layout: the cell probability is reported.
        max_speed_mps: the vehicle's stated maximum speed (m/s; the tracker's too,
            :data:`~ceilkit.runtime.estimators.prior.MAX_SPEED_MPS`): a new track's
            velocity is unknown but within it, so its 1σ per axis is
            :meth:`start_speed_sigma`, whose ``gate_p`` region is that speed: the gate
            of a track one frame old reaches no farther than the vehicle can move
            (a Gaussian of 1σ 2.5 m/s reached a 0.6 m tile's twin 0.1 s later).
        max_turn_rps: the vehicle's stated maximum turn rate (rad/s; the tracker's
            too): a new track's turn rate has the 1σ :meth:`start_turn_sigma`, whose
            ``gate_p`` region is that rate (a 1σ of 90 deg/s took a start pose's
            heading past ``prior_sigma_rad`` in 0.1 s with no fix: a two-light frame
            then got no prior).
        odo_scale_sigma: 1σ of the wheel odometry's scale factor when a track starts
            (a state of the filter: a scale error is a bias, not white noise).
        single_p, prune_p, max_modes: the modes an ambiguity leaves (:class:`ModeSet`):
            a track starts from one whose weight reaches ``single_p``; one below
            ``prune_p`` is dropped; at most ``max_modes`` are kept.
    """

    noise: ekf.MotionNoise = field(default_factory=lambda: ekf.MotionNoise(hold_mps=HOLD_MPS))
    gate_p: float = 0.9999
    confirm: int = 3
    lost_after_s: float = 1.0
    window_s: float = 0.5
    odometry_timeout_s: float = 0.5
    quality_radius_m: float = 0.02
    unobserved_sigma_m: float = 0.1
    unobserved_sigma_rad: float = math.radians(5.0)
    prior_sigma_m: float = 0.5
    prior_sigma_rad: float = math.radians(20.0)
    fix_inflation: float = 1.0
    inflation: Mapping[str, float] = field(
        default_factory=lambda: MappingProxyType({}))
    fix_floor_m: float = 0.000001
    fix_floor_rad: float = math.radians(0.0001)
    coast_hazard_per_s: float = 0.5
    default_sigma_m: float = 0.05
    default_sigma_rad: float = math.radians(2.0)
    cell_m: float | None = None
    max_speed_mps: float = MAX_SPEED_MPS
    max_turn_rps: float = MAX_TURN_RPS
    odo_scale_sigma: float = 0.05
    single_p: float = 0.999
    prune_p: float = 1e-4
    max_modes: int = 32

    def start_speed_sigma(self) -> float:
        """1σ (m/s, per axis) of a new track's velocity: the Gaussian whose ``gate_p``
        region (2 dof) is the disc of ``max_speed_mps``."""
        return self.max_speed_mps / math.sqrt(ekf.chi2_quantile(self.gate_p, 2))

    def start_turn_sigma(self) -> float:
        """1σ (rad/s) of a new track's turn rate: the Gaussian whose ``gate_p`` region
        (1 dof) is ``max_turn_rps``."""
        return self.max_turn_rps / math.sqrt(ekf.chi2_quantile(self.gate_p, 1))


@dataclass(frozen=True, eq=False)
class _Node:
    """The filter after an event: time, state, covariance, last odometry row's time."""

    t_ns: int
    s: np.ndarray
    P: np.ndarray
    t_odo_ns: int | None


@dataclass(frozen=True, eq=False)
class _Event:
    t_ns: int
    kind: str                  # "odo" | "fix"
    data: tuple

    @property
    def key(self) -> tuple[int, int]:
        return self.t_ns, 0 if self.kind == "odo" else 1


class FilterBuffer:
    """The EKF with a short time-ordered buffer of the events applied to it.

    ``add`` applies an event at its time: one older than the newest re-filters the
    events after it (:attr:`refiltered` counts them).
    """

    def __init__(self, start: _Node, options: FusionOptions):
        self.options = options
        self.base = start
        self.events: list[_Event] = []
        self.after: list[_Node] = []
        self.refiltered = 0

    @property
    def latest(self) -> _Node:
        return self.after[-1] if self.after else self.base

    def _propagate(self, n: _Node, t_ns: int) -> _Node:
        dt = (t_ns - n.t_ns) * 1e-9
        if dt <= 0:
            return n
        # constant velocity, also between odometry rows: a row is the motion over its
        # own interval (_apply), so a frame past the last row (the controller answers
        # each pose after it) is crossed on the velocity the rows set, not held still
        s, P = ekf.predict_cv(n.s, n.P, dt, self.options.noise)
        return _Node(t_ns, s, P, n.t_odo_ns)

    def _apply(self, n: _Node, ev: _Event) -> _Node:
        if ev.kind == "odo":
            d, cov, scaled, t0 = ev.data
            # an increment is the motion over [t0, t] (ceiling-plane odometry: t0 the
            # previous frame; a wheel row: the previous row, the first one the filter's
            # previous event): the motion model must not carry it as well
            if t0 is None:
                t0 = n.t_odo_ns if n.t_odo_ns is not None and n.t_odo_ns < ev.t_ns else n.t_ns
            n = self._propagate(n, min(t0, ev.t_ns))
            dt = (ev.t_ns - t0) * 1e-9
            if t0 < n.t_ns < ev.t_ns:
                # a fix inside [t0, t] was predicted to its time on the velocity: only
                # the increment's share after it is left (constant speed over the row)
                share = (ev.t_ns - n.t_ns) / (ev.t_ns - t0)
                d, dt = tuple(share * v for v in d), share * dt
                cov = None if cov is None else share * cov
            s, P = ekf.predict_odometry(n.s, n.P, d, dt, self.options.noise, cov, scaled)
            # a wheel row's stamp is where the next row's interval begins; a camera's
            # increment comes with its frame (it leaves the wheel rows' time alone)
            return _Node(max(n.t_ns, ev.t_ns), s, P, ev.t_ns if scaled else n.t_odo_ns)
        n = self._propagate(n, ev.t_ns)
        z, rows, R = ev.data
        s, P, _ = ekf.update(n.s, n.P, z, rows, R)
        return _Node(n.t_ns, s, P, n.t_odo_ns)

    def node_at(self, t_ns: int) -> _Node:
        """The filter predicted to ``t_ns`` from the last event at or before it."""
        i = bisect.bisect_right([e.t_ns for e in self.events], t_ns)
        n = self.after[i - 1] if i else self.base
        return self._propagate(n, t_ns)

    def add(self, ev: _Event) -> None:
        """Apply ``ev`` at its time (an odometry row before a fix of the same stamp)."""
        keys = [e.key for e in self.events]
        i = bisect.bisect_right(keys, ev.key)
        if ev.t_ns < self.base.t_ns:
            return  # older than the buffer: too late to matter
        self.refiltered += len(self.events) - i
        self.events.insert(i, ev)
        del self.after[i:]
        n = self.after[i - 1] if i else self.base
        for e in self.events[i:]:
            n = self._apply(n, e)
            self.after.append(n)
        horizon = self.events[-1].t_ns - int(self.options.window_s * 1e9)
        while len(self.events) > 1 and self.events[0].t_ns < horizon:
            self.base = self.after.pop(0)
            self.events.pop(0)


@dataclass(frozen=True, eq=False)
class _Fix:
    """One cue as a measurement: which rows, their values and covariance."""

    cue: PoseEstimate
    z: np.ndarray
    rows: tuple[int, ...]
    R: np.ndarray
    yaw_period: float | None = None

    @property
    def full(self) -> bool:
        return self.rows == ekf.FULL_POSE

    @property
    def unambiguous(self) -> bool:
        return self.full and self.cue.singled_out


def measurement(cue: PoseEstimate, options: FusionOptions) -> _Fix | None:
    """The measurement a cue makes: every coordinate it gives (x only with y)."""
    rows, z = [], []
    if cue.x_m is not None and cue.y_m is not None:
        rows.append(0)
        z.append(float(cue.x_m))
    if cue.y_m is not None:
        rows.append(1)
        z.append(float(cue.y_m))
    rows.append(ekf.YAW)
    z.append(float(cue.yaw_rad))
    floor = np.array([options.fix_floor_m, options.fix_floor_m, options.fix_floor_rad])[rows]
    default = np.array([options.default_sigma_m, options.default_sigma_m,
                        options.default_sigma_rad])[rows]
    cov = None if cue.cov is None else np.asarray(cue.cov, float)[np.ix_(rows, rows)]
    if cov is None or not np.all(np.isfinite(cov)):
        R = np.diag(default ** 2)
    else:
        R = options.inflation.get(cue.method, options.fix_inflation) * cov
    R = 0.5 * (R + R.T)
    # a floor, not an addition: a variance below it is raised to it, one above it is
    # left alone (added to every fix, 0.001 deg was 15 % of a corridor fix's yaw
    # variance and undid its y-yaw correlation, about 0.9: docs/fusion.md)
    R = R + np.diag(np.maximum(floor ** 2 - np.diag(R), 0.0))
    # a heading known modulo a period (the parallels'): its branches are its hypotheses
    branches = len(cue.hypotheses) if rows == [ekf.YAW] else 0
    period = 2 * math.pi / branches if branches > 1 else None
    return _Fix(cue, np.array(z), tuple(rows), R, None if period is None else float(period))


class PlaneChain:
    """Whether each ceiling-plane increment continues the vehicle's motion: its
    velocity (the increment over its interval, in V) against the last accepted one's,
    under the motion model's white acceleration (``noise``): the two intervals'
    averages of a velocity whose rate is white noise of density ``q`` differ by a
    variance ``q² (dt_a / 3 + gap + dt_b / 3)``, to which each increment's own
    covariance over its interval squared is added. A normalized difference beyond
    ``gate`` (the fusion's 3-dof gate) is a motion no vehicle made in that time: the
    frame-to-frame registration of a repeating ceiling locked onto a twin of the
    motion (one tile over, a quarter turn), or the vehicle was carried elsewhere.
    Body-frame velocities are compared: a vehicle turning steadily keeps its own.
    """

    def __init__(self, noise: ekf.MotionNoise, gate: float):
        self.q2 = np.array([noise.accel_mps2, noise.accel_mps2, noise.turn_rps2]) ** 2
        self.gate = gate
        self._last: tuple[int, float, np.ndarray, np.ndarray] | None = None
        self.refused = 0                       # increments refused, and the last one's
        self.refused_at: int | None = None     # frame time

    def event(self, t_ns: int, cues: tuple) -> _Event | None:
        """The filter's odometry event of the first cue's :class:`PlaneIncrement`
        (the motion over ``[t0_ns, t_ns]``, unscaled), None when no cue carries one or
        it is refused (:meth:`continues`: a frame motion no vehicle made, a kidnap or a
        registration locked onto a twin of the motion; the motion model carries the
        track over it)."""
        inc = next((c.increment for c in cues if isinstance(c.increment, PlaneIncrement)),
                   None)
        if inc is None:
            return None
        if not self.continues(t_ns, inc):
            self.refused, self.refused_at = self.refused + 1, t_ns
            return None
        return _Event(t_ns, "odo", ((inc.dx_m, inc.dy_m, inc.dyaw_rad),
                                    np.asarray(inc.cov, float), False, int(inc.t0_ns)))

    def continues(self, t_ns: int, inc: PlaneIncrement) -> bool:
        """Whether ``inc`` (ending at ``t_ns``) is accepted; an accepted one becomes the
        one the next is compared with (the first always is)."""
        dt = (t_ns - int(inc.t0_ns)) * 1e-9
        if dt <= 0:
            return True
        v = np.array([inc.dx_m, inc.dy_m, inc.dyaw_rad]) / dt
        cv = np.asarray(inc.cov, float) / (dt * dt)
        last = self._last
        if last is not None:
            t_end, dt_a, v_a, cv_a = last
            gap = max(0.0, (int(inc.t0_ns) - t_end) * 1e-9)
            S = cv + cv_a + np.diag(self.q2 * (dt_a / 3 + gap + dt / 3))
            if not np.all(np.isfinite(S)) or ekf.nis(v - v_a, S) > self.gate:
                return False
        self._last = (int(t_ns), dt, v, cv)
        return True


class Fusion:
    """See the module docstring. Counts: ``relocalizations``, ``contributions`` (fixes
    applied per method), ``gated`` (per method), ``odometry_rows``."""

    def __init__(self, options: FusionOptions | None = None,
                 start_pose: tuple[float, float, float] | None = None,
                 start_sigma: tuple[float, float] = DEFAULT_PRIOR_SIGMA):
        self.options = options or FusionOptions()
        self.gates = {k: ekf.chi2_quantile(self.options.gate_p, k) for k in (1, 2, 3)}
        self._f: FilterBuffer | None = None
        self._t_fix_ns = 0
        self._candidates: list[_Fix] = []
        self.relocalizations = 0
        self.contributions: Counter = Counter()
        self.gated: Counter = Counter()
        self.odometry_rows = 0
        self.odometry_refused = 0    # rows out of any vehicle's reach (1e308 from a peer)
        self._start_pose = start_pose
        self._method = NAME
        self._inbox: deque = deque()   # odometry rows, start poses: from any thread
        self._start_sigma = start_sigma
        self._t_wheel_ns: int | None = None   # the last wheel odometry row
        self._jumped = False         # a start pose was set: the next pose is a reset
        self.plane_increments = 0
        self._t_plane_ns: int | None = None   # the last ceiling-plane increment
        self.chain = PlaneChain(self.options.noise, self.gates[3])
        self.start_poses = 0
        self.modes = ModeSet(self.options, self.gates)   # the poses an ambiguity leaves
        self.tr = TrackFlags()

    @property
    def tracking(self) -> bool:
        return self._f is not None

    @property
    def refiltered(self) -> int:
        return 0 if self._f is None else self._f.refiltered

    def reset(self) -> None:
        self._f = None
        self._candidates = []
        self.modes.clear()
        self.tr = TrackFlags()

    # -- inputs ----------------------------------------------------------------------
    def start(self, t_ns: int, pose: tuple[float, float, float], cov: np.ndarray) -> None:
        """Start the track at ``pose`` (x, y, yaw) with covariance ``cov`` (3, 3)."""
        s, P = ekf.initial_state(pose, cov, self.options.start_speed_sigma(),
                                 self.options.start_turn_sigma(),
                                 self.options.odo_scale_sigma)
        t_odo = None if self._f is None else self._f.latest.t_odo_ns
        self._f = FilterBuffer(_Node(int(t_ns), s, P, t_odo), self.options)
        self._t_fix_ns = int(t_ns)
        self._candidates = []
        self.modes.clear()
        self.tr = TrackFlags()     # no frame has confirmed the track yet (a start pose)

    def add_odometry(self, t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float,
                     cov: np.ndarray | None = None) -> bool:
        """One wheel odometry row: the increment in V since the previous row, scaled by
        the filter's odometry scale; ``cov`` its ``(3, 3)`` covariance (dx, dy, dyaw),
        ``None`` for the wheel model of ``FusionOptions.noise``. Safe from any thread
        (the link's receive hook): rows are applied at the next frame, each over its
        interval (from the previous row's stamp to its own). False: refused."""
        c = None if cov is None else np.array(cov, float).reshape(3, 3)
        d = (float(dx_m), float(dy_m), float(dyaw_rad))
        if not plausible_increment(d, c):
            self.odometry_refused += 1      # bounded before any arithmetic: never raises
            return False
        self._inbox.append(("odo", int(t_ns), d, c))
        return True

    def set_start_pose(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float,
                       cov: np.ndarray | None = None) -> None:
        """(Re)start the track at ``(x_m, y_m, yaw_rad)`` in W as of capture time
        ``t_ns``, with ``cov`` its ``(3, 3)`` covariance (default: the constructor's
        ``start_sigma``): what a ``--start-pose`` or ROS ``/initialpose`` gives. Safe
        from any thread while the run goes on: it takes effect at the next frame (at
        ``t_ns``, or at that frame's time if later), that frame's pose is published as a
        reset (``relocalized``: the link bumps its reset counter), and pending
        relocalization candidates are dropped."""
        if cov is None:
            sp, sr = self._start_sigma
            cov = np.diag([sp * sp, sp * sp, sr * sr])
        c = np.array(cov, float).reshape(3, 3)
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite((x_m, y_m, yaw_rad)))):
            raise ValueError("set_start_pose: pose and covariance must be finite")
        self._inbox.append(("start", int(t_ns), (float(x_m), float(y_m), float(yaw_rad)), c))

    def _drain(self, t_now: int) -> None:
        while self._inbox:
            kind, t_ns, d, c = self._inbox.popleft()
            if kind == "start":
                self.start(max(t_ns, self._f.latest.t_ns if self._f else t_ns), d, c)
                self._jumped = True
                self.start_poses += 1
                continue
            self.odometry_rows += 1
            self._t_wheel_ns = t_ns if self._t_wheel_ns is None else max(t_ns, self._t_wheel_ns)
            if self._f is not None:
                self._f.add(_Event(t_ns, "odo", (d, c, True, None)))
            self.modes.add(_Event(t_ns, "odo", (d, c, True, None)))

    def _wheels(self, t_ns: int) -> bool:
        """Wheel odometry rows are coming (the last within ``odometry_timeout_s``)."""
        return self._t_wheel_ns is not None and \
            (t_ns - self._t_wheel_ns) * 1e-9 <= self.options.odometry_timeout_s

    def _plane_increments(self, t_ns: int, cues: tuple) -> None:
        """Ceiling-plane odometry (:meth:`PlaneChain.event`) while no wheel rows come
        (they would count the motion twice); a refused one leaves the track in doubt
        (``TrackFlags.split``: :meth:`TrackFlags.refuted`)."""
        if (self._f is None and not self.modes) or self._wheels(t_ns):
            return
        ev = self.chain.event(t_ns, cues)
        if ev is None:
            self.tr.split |= self.chain.refused_at == t_ns
            return
        if self._f is not None:
            self._f.add(ev)
        self.modes.add(ev)
        self.plane_increments += 1
        self._t_plane_ns = t_ns

    def feed(self, odometry: Any, first: int, t_ns: int) -> int:
        """Feed rows ``first..`` of an :class:`~ceilkit.runtime.io.recording.Odometry`
        stamped at or before ``t_ns``; returns the index of the next row."""
        k = first
        while k < len(odometry) and int(odometry.t_ns[k]) <= t_ns:
            self.add_odometry(int(odometry.t_ns[k]), float(odometry.dx_m[k]),
                              float(odometry.dy_m[k]), float(odometry.dyaw_rad[k]))
            k += 1
        return k

    # -- the per-frame interface of Tracker -------------------------------------------
    def _lost(self, t_ns: int) -> bool:
        f = self._f
        if f is None:
            return True
        n = f.latest
        stamps = [t for t in (n.t_odo_ns, self._t_plane_ns) if t is not None]
        odo = bool(stamps) and (t_ns - max(stamps)) * 1e-9 <= self.options.odometry_timeout_s
        return not odo and (t_ns - self._t_fix_ns) * 1e-9 > self.options.lost_after_s

    def predict(self, t_ns: int, method: str = NAME) -> PoseEstimate | None:
        """The prior for the estimators at ``t_ns``: ``None`` when not tracking or
        when the track is too uncertain to guide a local search."""
        if self._start_pose is not None and self._f is None:
            sp, sr = self._start_sigma
            self.start(t_ns, self._start_pose, np.diag([sp * sp, sp * sp, sr * sr]))
            self._start_pose = None
        self._drain(t_ns)
        if self._lost(t_ns):
            return None
        pose = publish(self._f.node_at(t_ns), method, {}, self.options, self._t_fix_ns,
                       bool(self._candidates), velocity=True, blank_above_m=math.inf)
        sd = np.sqrt(np.diag(np.asarray(pose.cov)))
        # a coordinate the track does not know (x of a corridor-only track) is left out
        # of the prior rather than dropping the prior: its heading and y still choose
        # between a frame's twins (a symmetric corridor's half turn)
        x, y = (v if v is not None and s <= self.options.prior_sigma_m else None
                for v, s in ((pose.x_m, sd[0]), (pose.y_m, sd[1])))
        if y is None or sd[2] > self.options.prior_sigma_rad:
            return None
        return dataclasses.replace(pose, x_m=x, y_m=y, provenance=Provenance.TRACK)

    def update(self, est: Estimate) -> TrackResult:
        """Fuse one frame's estimate(s); returns what to publish."""
        t = int(est.t_ns)
        self._drain(t)
        cues = est.cues or (est,)
        self._plane_increments(t, cues)
        fixes = [m for c in cues if isinstance(c, PoseEstimate)
                 if (m := measurement(c, self.options)) is not None]
        relocalized, started, contradicted, split = self._jumped, [], False, False
        self._jumped = False
        if self._lost(t):
            start = starting_fix(fixes, self.gates)
            if start is None:
                return self._ambiguity(t, est, cues)
            self._restart(t, start)
            relocalized, started = True, [start.cue.method]
            fixes = [f for f in fixes if f is not start]
        else:
            near, contradicted, split = twins_near(self._f, t, cues, self.options)
            fixes += near
        used = started + self._apply(t, fixes)
        if self._candidates and len(self._candidates) >= self.options.confirm:
            fix = self._candidates[-1]
            self._restart(t, fix)
            relocalized, used = True, [fix.cue.method]
        diag: dict[str, Any] = {"applied": tuple(used), "pending": len(self._candidates)}
        if used:
            self._method = used[0]
        diag["coasting"] = not used
        self.tr.carried = bool(used) or (self.tr.carried and (
            self._wheels(t) or self._t_plane_ns == t))
        if self._candidates:
            # a fix singled out by its frame put the vehicle elsewhere and no full fix
            # has agreed with the track since (it clears them): whatever else agrees
            # with the track (a heading whose branch the track chose: the block twin
            # start's 46 poses 180 deg off), nothing singles the track's pose out
            pend = self._candidates[-1].cue
            return TrackResult(Failure(
                t, pend.method, "gated", f"{pend.method} puts the vehicle away from the "
                f"track; {self.options.confirm - len(self._candidates)} more to confirm",
                diagnostics={"rejected": pend}), relocalized)
        if self.tr.refuted(bool(used), bool(fixes), contradicted, split):
            # ``confirm`` such frames in a row drop the track (the next frame starts
            # anew, from what singles a pose out)
            self.tr.disagree += 1
            if self.tr.disagree >= self.options.confirm:
                self._f, self.tr = None, TrackFlags()
            who = "/".join(sorted({f.cue.method for f in fixes})) or "ambiguous cues"
            return TrackResult(Failure(t, self._method, "gated", f"the frame's {who} "
                                       "disagree with the track"), relocalized)
        self.tr.disagree, self.tr.split = 0, False
        self.tr.confirmed |= bool(used)
        self.tr.x_seen |= self.tr.x_fixed
        if not self.tr.confirmed:
            # a start pose no frame has confirmed yet is what the user said, not what
            # the frames show: the frame's own answer goes out (the reset still does)
            return TrackResult(_failure(est, cues), relocalized)
        if not self.tr.carried:
            return TrackResult(Failure(t, self._method, "coasting", "no cue and no "
                                       "odometry has measured the motion since the "
                                       "last fix"), relocalized)
        pose = publish(self._f.node_at(t), self._method, diag, self.options,
                       self._t_fix_ns, bool(self._candidates), x_known=self.tr.x_seen)
        gone = unknown(pose, self.options, self.tr.lateral_only)
        if gone is not None:
            return TrackResult(gone)
        return TrackResult(pose, relocalized)

    # -- internals -------------------------------------------------------------------
    def _ambiguity(self, t_ns: int, est: Estimate, cues: tuple) -> TrackResult:
        """No track and no fix to start one: the ambiguous cues' hypotheses are carried
        as modes (:class:`ModeSet`); the track starts from one only when the drive's
        evidence singles it out (its weight at least ``single_p``)."""
        best = self.modes.step(t_ns, cues)
        if best is not None:
            self._f, self._t_fix_ns, self._candidates, self._method = best.f, t_ns, [], \
                best.method
            lateral = float(best.f.latest.P[0, 0]) >= 0.5 * UNKNOWN_X_VAR
            self.tr = TrackFlags(lateral, confirmed=True, x_seen=not lateral)
            self.relocalizations += 1
            diag = {"applied": (best.method,), "pending": 0, "coasting": False}
            return TrackResult(publish(self._f.node_at(t_ns), best.method, diag,
                                       self.options, t_ns, False), True)
        self._f, self._candidates = None, []
        return TrackResult(self.modes.failure(t_ns) if self.modes else _failure(est, cues))

    def _restart(self, t_ns: int, fix: _Fix) -> None:
        cov = np.diag([UNKNOWN_X_VAR, UNKNOWN_X_VAR, 1.0])
        z = np.zeros(3)
        cov[np.ix_(fix.rows, fix.rows)] = fix.R
        z[list(fix.rows)] = fix.z
        self.start(t_ns, (float(z[0]), float(z[1]), float(z[2])), cov)
        self.tr = TrackFlags(1 in fix.rows and 0 not in fix.rows, confirmed=True,
                             x_seen=0 in fix.rows)     # from a fix, not a start pose
        self.relocalizations += 1
        self.contributions[fix.cue.method] += 1

    def _apply(self, t_ns: int, fixes: list[_Fix]) -> list[str]:
        """Gate and apply each fix at ``t_ns``; keep disagreeing unambiguous ones as
        relocalization candidates. Returns the methods applied."""
        f = self._f
        used: list[str] = []
        self.tr.fresh = False
        for fix in sorted(fixes, key=lambda m: -len(m.rows)):
            n = f.node_at(t_ns)
            if fix.yaw_period:   # the branch of an ambiguous heading nearest the track
                p = fix.yaw_period
                z = float(n.s[ekf.YAW]) + math.remainder(float(fix.z[0]) - n.s[ekf.YAW], p)
                fix = _Fix(fix.cue, np.array([wrap_pi(z)]), fix.rows, fix.R, p)
            y, S = ekf.innovation(n.s, n.P, fix.z, fix.rows, fix.R)
            if ekf.nis(y, S) <= self.gates[len(fix.rows)]:
                if self.tr.confirmed:
                    f.add(_Event(t_ns, "fix", (fix.z, fix.rows, fix.R)))
                else:     # the start pose chose this fix: the track starts at it, no
                    # velocity inferred from the start pose's error (confirmed_start)
                    pending = self._candidates     # still against it (kept)
                    self.start(t_ns, *confirmed_start(f.node_at(t_ns), fix))
                    f, self.tr.confirmed, self._candidates = self._f, True, pending
                self.tr.lateral_only |= 1 in fix.rows and 0 not in fix.rows
                self.tr.x_fixed |= 0 in fix.rows
                # not a window about the prior, nor a heading's branch it chose
                self.tr.fresh |= fix.cue.provenance is Provenance.GLOBAL and fix.yaw_period is None
                used.append(fix.cue.method)
                self.contributions[fix.cue.method] += 1
                if fix.full or 1 in fix.rows:
                    self._t_fix_ns = t_ns
                if fix.full:
                    self._candidates = []
                continue
            self.gated[fix.cue.method] += 1
            if fix.unambiguous:
                self._candidates = chain_candidates(self._candidates, fix)
        return used


@dataclass
class TrackFlags:
    """What a fused track knows of itself beside its filter; new when it (re)starts.

    Attributes:
        lateral_only: a fix with y and no x was applied (the corridor's).
        confirmed: a frame has confirmed the track (not only a start pose).
        x_seen: a frame has measured x (else x is not published: a start pose's x,
            carried by odometry, is what the user stated); ``x_fixed``: this frame.
        disagree: frames in a row that did not confirm the track.
        fresh: this frame applied a fix found without the track's prior
            (``Provenance.GLOBAL``: not chosen among twins by it, nor searched for about
            it; not a heading whose branch it chose).
        carried: every frame since the last fix had odometry (wheel rows or its
            ceiling-plane increment): else the pose is the constant-velocity model's
            guess, which no frame checked, and is not published (a ``coasting``
            failure: a kidnap between frames without lights went out 3.7 m off).
        split: an ambiguous frame since the track was last confirmed listed every pose
            it supports and put none, or several, inside the track's gate.
    """

    lateral_only: bool = False
    confirmed: bool = False
    x_seen: bool = False
    x_fixed: bool = False
    disagree: int = 0
    fresh: bool = False
    carried: bool = True
    split: bool = False

    def refuted(self, used: bool, fixes: bool, contradicted: bool, split: bool) -> bool:
        """Whether this frame does not confirm the track: it explains a pose, not the
        track's (every fix gated, or a complete list with none in the gate: a glitch,
        a kidnap, a wrong start pose), several about it (``split``), or, after such a
        frame, only a pose the track's own prior chose (its region has widened since
        and may hold a twin of wherever the vehicle now is: a kidnap on tiles followed
        a twin 1.25 m off)."""
        doubted = self.split and used and not self.fresh
        self.split = (self.split or contradicted or split) and not (used and not doubted)
        return (not used and (fixes or contradicted or split)) or doubted


def publish(n: _Node, method: str, diag: dict[str, Any], o: FusionOptions,
            t_fix_ns: int, pending: bool, velocity: bool = False,
            blank_above_m: float | None = None, x_known: bool = True) -> PoseEstimate:
    """The pose of node ``n``; with ``velocity``, the state's velocity too (a
    prior's, for the estimators' rolling-shutter rows); a coordinate whose 1σ
    exceeds ``blank_above_m`` (default ``unobserved_sigma_m``) is left empty, and x
    when not ``x_known`` (no frame measured it);
    ``quality`` 0 while relocalization candidates are ``pending``, decaying since the
    last absolute fix at ``t_fix_ns`` otherwise."""
    blank = o.unobserved_sigma_m if blank_above_m is None else blank_above_m
    cov = np.array(n.P[:3, :3])
    sd = np.sqrt(np.diag(cov))
    observed = [bool(sd[0] <= blank) and x_known, bool(sd[1] <= blank)]
    for i in (0, 1):
        if not observed[i]:
            cov[i, :] = cov[:, i] = np.inf
    keep = [i for i in (0, 1) if observed[i]]
    quality = 0.0 if not keep or pending else \
        ekf.prob_within_radius(cov[np.ix_(keep, keep)], o.quality_radius_m) * \
        math.exp(-o.coast_hazard_per_s * max(0.0, (n.t_ns - t_fix_ns) * 1e-9))
    if o.cell_m is not None and all(observed):
        half = 0.5 * o.cell_m
        diag["cell_p"] = math.erf(half / (sd[0] * math.sqrt(2))) * \
            math.erf(half / (sd[1] * math.sqrt(2)))
    return PoseEstimate(int(n.t_ns), method,
                        float(n.s[0]) if observed[0] else None,
                        float(n.s[1]) if observed[1] else None,
                        float(n.s[2]), float(quality), None, cov,
                        MappingProxyType(diag),
                        tuple(float(v) for v in n.s[3:6])
                        if velocity and velocity_known(n, o) else None,
                        provenance=Provenance.TRACK)


def unknown(pose: PoseEstimate, o: FusionOptions, lateral_only: bool) -> Failure | None:
    """The ``coasting`` Failure a track's pose is published as when it no longer knows
    what it would publish: a heading whose 1σ exceeds ``unobserved_sigma_rad``; a y
    without x on a track of full fixes (``lateral_only`` False: it would read as a
    corridor's lateral, which this track never measured). None: publish it."""
    if pose.cov[2, 2] > o.unobserved_sigma_rad ** 2:
        return Failure(pose.t_ns, pose.method, "coasting", "the heading is no longer "
                       f"known to {math.degrees(o.unobserved_sigma_rad):g} deg")
    if pose.x_m is None and pose.y_m is not None and not lateral_only:
        return Failure(pose.t_ns, pose.method, "coasting", "the position is no longer "
                       f"known to {o.unobserved_sigma_m:g} m")
    return None


def confirmed_start(n: _Node, fix: _Fix) -> tuple[tuple[float, float, float], np.ndarray]:
    """The pose and covariance a track starts from at the first fix a start pose chose
    (the start pose's node ``n``): what the fix observes from it, the rest (a corridor
    track's x) from the start pose."""
    z, cov, r = np.array(n.s[:3]), np.array(n.P[:3, :3]), list(fix.rows)
    cov[r, :] = 0.0
    cov[:, r] = 0.0
    cov[np.ix_(r, r)] = fix.R
    z[r] = fix.z
    return (float(z[0]), float(z[1]), float(z[2])), cov


MAX_ODOMETRY_STEP_M = 10.0
"""An odometry row moving the vehicle farther than this (m) between two rows is refused:
no vehicle does, and a peer's 1e308 must not reach the filter's arithmetic."""


def plausible_increment(d: tuple[float, float, float], cov: np.ndarray | None) -> bool:
    """Whether an odometry increment ``(dx_m, dy_m, dyaw_rad)`` (and its covariance)
    is finite and within a vehicle's reach between two rows."""
    dx, dy, dyaw = d
    ok = all(math.isfinite(v) for v in d) and abs(dx) <= MAX_ODOMETRY_STEP_M \
        and abs(dy) <= MAX_ODOMETRY_STEP_M and abs(dyaw) <= 2 * math.pi
    return ok and (cov is None or bool(np.all(np.isfinite(cov)) and np.all(np.abs(cov) < 1e6)))


def chain_candidates(candidates: list[_Fix], fix: _Fix) -> list[_Fix]:
    """The relocalization candidates after ``fix``: appended when it agrees with the
    last (moved no farther than a vehicle could since), else starting anew."""
    if candidates:
        last = candidates[-1]
        dt = (fix.cue.t_ns - last.cue.t_ns) * 1e-9
        d = float(np.hypot(*(fix.z[:2] - last.z[:2])))
        dyaw = abs(wrap_pi(float(fix.z[2] - last.z[2])))
        if d > 0.25 + 2.5 * dt or dyaw > math.radians(10.0) + math.radians(90.0) * dt:
            candidates = []
    return candidates + [fix]


def ambiguous_cues(cues: tuple) -> list[Failure]:
    """The cues that are ``ambiguous`` failures carrying their hypotheses."""
    return [c for c in cues
            if isinstance(c, Failure) and c.reason == "ambiguous" and c.hypotheses]


def prior_regions() -> dict[int, float]:
    """The squared-distance bounds (by dof, 1-3) of the region in which a track may
    choose among a frame's twins (:func:`twins_near`): the prior's, ``PRIOR_P``
    (estimators/prior.py: the one rule every prior chooses by), not the fixes'
    innovation gate (``gate_p``: wider; a kidnap on tiles put a quarter-turn twin of
    the new pose at NIS 15.7, under the gate's 18.4 and over the region's 13.8, and
    the track followed it: held-out lines seed 17's ``tiles0``, 30 wrong of 60). Three
    look-ups in the quantile table warmed before the first frame, made only on frames
    with an ambiguous cue (a cache of its own would be filled on frame 0)."""
    return {k: ekf.chi2_quantile(PRIOR_P, k) for k in (1, 2, 3)}


def twins_near(f: FilterBuffer, t_ns: int, cues: tuple, options: FusionOptions
               ) -> tuple[list[_Fix], bool, bool]:
    """The track (its filter ``f`` at ``t_ns``) decides the frame's ambiguous cues
    (:func:`ambiguous_cues`): of each one's hypotheses, the one inside the track's
    region (:func:`prior_regions`) when it is the only one there and the
    list is complete (``hypotheses_complete``: a pose left out of an incomplete list
    may be the one inside), as a fix. Also whether a complete list puts several poses
    inside the region
    (``split``: the frame does not single the track's pose out, so the track's pose
    is not published on it), and whether a cue contradicts the
    track: none of its poses is inside (a method given the track's prior lists the
    poses near it first, and finds the one there when the prior singles it out; a cue
    that is ambiguous about a track's prior and lists no pose near it shows the vehicle
    elsewhere). A frame with no ambiguous cue costs no prediction."""
    ambiguous = ambiguous_cues(cues)
    region = prior_regions() if ambiguous else {}
    n = f.node_at(t_ns) if ambiguous else None
    out, contradicted, split = [], False, False
    for c in ambiguous:
        inside = []
        for h in c.hypotheses:
            m = measurement(hypothesis_cue(n.t_ns, c.method, h), options)
            y, S = ekf.innovation(n.s, n.P, m.z, m.rows, m.R)
            if ekf.nis(y, S) <= region[len(m.rows)]:
                inside.append(m)
        if len(inside) == 1 and c.hypotheses_complete:
            out.append(inside[0])
        elif len(inside) > 1 and c.hypotheses_complete:
            split = True
        contradicted |= not inside
    return out, contradicted, split


def starting_fix(fixes: list[_Fix], gates: Mapping[int, float]) -> _Fix | None:
    """The fix a track starts from: a full fix that every other cue of the frame
    agrees with, else a fix with y (the corridor's: x stays unknown)."""
    for f in fixes:
        if f.full and all(agree(f, g, gates) for g in fixes if g is not f):
            return f
    return next((f for f in fixes if 1 in f.rows and not f.full), None)


def agree(a: _Fix, b: _Fix, gates: Mapping[int, float]) -> bool:
    """Whether two fixes of one frame agree on the coordinates they share."""
    shared = [r for r in b.rows if r in a.rows]
    ia, ib = [a.rows.index(r) for r in shared], [b.rows.index(r) for r in shared]
    y = a.z[ia] - b.z[ib]
    if shared[-1] == ekf.YAW:
        y[-1] = wrap_pi(float(y[-1]))
    S = a.R[np.ix_(ia, ia)] + b.R[np.ix_(ib, ib)]
    return ekf.nis(y, S) <= gates[len(shared)]


def velocity_known(n: _Node, o: FusionOptions) -> bool:
    """Whether the filter has measured its velocity: its speed's 1σ under three
    quarters of the start's (a new track's velocity is its start guess, 0, not a
    measurement; as with the light tracker, the estimators then assume it unknown; a
    second fix 0.1 s later halves it) and its turn rate's under half the vehicle's
    ``max_turn_rps`` (the turn rate's process noise keeps its 1σ near the start's)."""
    sd = np.sqrt(np.maximum(np.diag(n.P)[3:6], 0.0))
    v = 0.75 * o.start_speed_sigma()
    return bool(sd[0] < v and sd[1] < v and sd[2] < 0.5 * o.max_turn_rps)


def hypothesis_cue(t_ns: int, method: str, h: Hypothesis) -> PoseEstimate:
    """One hypothesis of an ambiguous cue as a pose (a measurement's input)."""
    return PoseEstimate(int(t_ns), method, h.x_m, h.y_m, h.yaw_rad, 0.0, None, h.cov,
                        provenance=Provenance.PRIOR)


@dataclass(eq=False)
class Mode:
    """One pose the drive still supports: its filter, weight and the method that gave it."""

    f: FilterBuffer
    weight: float
    method: str
    label: str = ""


class ModeSet:
    """A Gaussian sum over the poses an ambiguity leaves: one EKF (:class:`FilterBuffer`)
    per mode, born from an ambiguous frame's ``hypotheses``, each moved by the same
    odometry and updated by the hypothesis of every later ambiguous cue that falls in
    its gate. Weights follow Bayes' rule only from lists the method says are complete
    (``hypotheses_complete``: every pose the frame supports is listed, so a mode none
    of them is near is ruled out); an incomplete list updates the modes' filters but
    moves no weight (a mode it leaves out may still be the truth). Modes that merge
    (within a gate of each other) are kept once; a mode below ``prune_p`` is dropped.
    :meth:`singled_out` is the mode whose weight reaches ``single_p`` after at least
    two frames: only then does a track start from an ambiguity."""

    def __init__(self, options: FusionOptions, gates: Mapping[int, float]):
        self.options, self.gates = options, gates
        self.modes: list[Mode] = []
        self.frames = 0
        self.resolved = 0
        self.weighed = False      # a complete list has moved the weights since birth

    def __bool__(self) -> bool:
        return bool(self.modes)

    def __len__(self) -> int:
        return len(self.modes)

    def clear(self) -> None:
        self.modes, self.frames, self.weighed = [], 0, False

    def add(self, ev: _Event) -> None:
        """An odometry event, applied to every mode."""
        for m in self.modes:
            m.f.add(ev)

    def _birth(self, t_ns: int, method: str, hyps: tuple[Hypothesis, ...],
               complete: bool) -> None:
        """Modes from ``hyps``, weighted as the method weighted them when the list is
        complete, alike otherwise (a truncated list's weights single out nothing)."""
        o = self.options
        for h in hyps[: o.max_modes]:
            cov = np.diag([UNKNOWN_X_VAR, UNKNOWN_X_VAR, 1.0])
            fix = measurement(hypothesis_cue(t_ns, method, h), o)
            z = np.zeros(3)
            cov[np.ix_(fix.rows, fix.rows)] = fix.R
            z[list(fix.rows)] = fix.z
            s, P = ekf.initial_state(tuple(float(v) for v in z), cov, o.start_speed_sigma(),
                                     o.start_turn_sigma(), o.odo_scale_sigma)
            self.modes.append(Mode(FilterBuffer(_Node(int(t_ns), s, P, None), o),
                                   float(h.weight) if complete else 1.0, method, h.label))
        self._normalize()
        self.frames, self.weighed = 1, complete

    def update(self, t_ns: int, sets: list[tuple[str, tuple[Hypothesis, ...], bool]]) -> None:
        """One frame's ambiguous cues ``(method, hypotheses, complete)``."""
        if not sets:
            return
        if not self.modes:
            self._birth(t_ns, *sets[0])
            return
        self.frames += 1
        for method, hyps, complete in sets:
            fixes = [measurement(hypothesis_cue(t_ns, method, h), self.options) for h in hyps]
            for m in self.modes:
                n = m.f.node_at(t_ns)
                best, like = None, 0.0
                for h, fx in zip(hyps, fixes, strict=True):
                    y, S = ekf.innovation(n.s, n.P, fx.z, fx.rows, fx.R)
                    d2 = ekf.nis(y, S)
                    if d2 <= self.gates[len(fx.rows)]:
                        p = h.weight * math.exp(-0.5 * d2) / math.sqrt(
                            max(float(np.linalg.det(2 * math.pi * S)), 1e-300))
                        if p > like or best is None:
                            best, like = fx, p
                if best is not None:
                    m.f.add(_Event(t_ns, "fix", (best.z, best.rows, best.R)))
                if complete:
                    m.weight *= like
                    self.weighed = True
        if sum(m.weight for m in self.modes) <= 0.0:
            self.clear()          # the drive contradicts every mode: start again
            self._birth(t_ns, *sets[0])
            return
        self._normalize()
        self._merge(t_ns)

    def _normalize(self) -> None:
        total = sum(m.weight for m in self.modes)
        if total <= 0:
            return
        for m in self.modes:
            m.weight /= total
        self.modes = sorted((m for m in self.modes if m.weight >= self.options.prune_p),
                            key=lambda m: -m.weight)[: self.options.max_modes]
        total = sum(m.weight for m in self.modes)
        for m in self.modes:
            m.weight /= total

    def _merge(self, t_ns: int) -> None:
        kept: list[Mode] = []
        for m in self.modes:
            n = m.f.node_at(t_ns)
            for k in kept:
                nk = k.f.node_at(t_ns)
                y = n.s[:3] - nk.s[:3]
                y[2] = wrap_pi(float(y[2]))
                if ekf.nis(y, n.P[:3, :3] + nk.P[:3, :3]) <= self.gates[3]:
                    k.weight += m.weight
                    break
            else:
                kept.append(m)
        self.modes = kept

    def step(self, t_ns: int, cues: tuple) -> Mode | None:
        """One frame's cues with no track: their ambiguous hypotheses update the modes;
        the mode singled out (cleared from the set), or None."""
        self.update(t_ns, [(c.method, c.hypotheses, c.hypotheses_complete)
                           for c in ambiguous_cues(cues)])
        best = self.singled_out()
        if best is not None:
            self.clear()
        return best

    def singled_out(self) -> Mode | None:
        """The mode the drive has singled out, or None."""
        if (self.frames >= 2 and self.weighed and self.modes
                and self.modes[0].weight >= self.options.single_p):
            self.resolved += 1
            return self.modes[0]
        return None

    def failure(self, t_ns: int) -> Failure:
        """What to publish while several modes remain: ``ambiguous``, with them."""
        hyps = []
        for m in self.modes:
            n = m.f.node_at(t_ns)
            hyps.append(Hypothesis(float(n.s[0]), float(n.s[1]), float(n.s[2]),
                                   np.array(n.P[:3, :3]), m.weight, m.label))
        top = ", ".join(f"({h.x_m:.2f}, {h.y_m:.2f}, {h.yaw_deg:.0f} deg) {h.weight:.2f}"
                        for h in hyps[:3])
        return Failure(int(t_ns), self.modes[0].method, "ambiguous",
                       f"{len(hyps)} poses fit the drive so far: {top}",
                       hypotheses=tuple(hyps), hypotheses_complete=False)


def nees(est: PoseEstimate, truth: tuple[float, float, float]) -> tuple[float, int] | None:
    """The normalized estimation error squared of a published pose against the truth
    ``(x, y, yaw)`` over the coordinates it gives: ``(nees, dof)``, or None."""
    rows = [i for i, v in ((0, est.x_m), (1, est.y_m)) if v is not None] + [ekf.YAW]
    if est.cov is None:
        return None
    C = np.asarray(est.cov, float)[np.ix_(rows, rows)]
    if not np.all(np.isfinite(C)):
        return None
    got = np.array([est.x_m if est.x_m is not None else 0.0,
                    est.y_m if est.y_m is not None else 0.0, est.yaw_rad])[rows]
    e = got - np.asarray(truth, float)[rows]
    e[-1] = wrap_pi(float(e[-1]))
    return ekf.nis(e, C), len(rows)


def effective_count(values: Sequence[float]) -> float:
    """How many independent samples the mean of ``values`` (a series in time order,
    e.g. each published pose's NEES) is worth: ``n / (1 + 2 Σ_k (1 - k/n) ρ_k)``, the
    sum over the lags ``k`` from 1 while the sample autocorrelation ``ρ_k`` stays
    positive (at most ``n / 3`` lags), at most ``n``. A track's errors are correlated
    in time (the same lights seen from nearly the same place, a filter's memory): the
    95% band of a mean NEES is that of this many frames, not of ``n``
    (:func:`~ceilkit.runtime.geometry.ekf.mean_nees_band`)."""
    x = np.asarray(values, float)
    n = x.size
    if n < 8:
        return float(n)
    d = x - x.mean()
    v = float(d @ d)
    if v <= 0.0:
        return float(n)
    s = 0.0
    for k in range(1, n // 3):
        rho = float(d[:-k] @ d[k:]) / v
        if rho <= 0.0:
            break
        s += (1.0 - k / n) * rho
    return float(n) / (1.0 + 2.0 * s)


class FusionReport:
    """The summary of a fused run: per-cue contributions and, against a truth, the
    consistency of the published covariance (NEES)."""

    def __init__(self, fusion: Fusion, truth: Any = None):
        self.fusion, self.truth = fusion, truth
        self.values: list[tuple[float, int]] = []
        self.confident_wrong = 0   # quality >= 0.8 and more than 5 cm off

    def add(self, est: Estimate) -> None:
        if self.truth is None or not isinstance(est, PoseEstimate):
            return
        t = self.truth.lookup(est.t_ns)
        if t is None:
            return
        v = nees(est, t)
        if v is not None:
            self.values.append(v)
        err = [abs(a - b) for a, b in ((est.x_m, t[0]), (est.y_m, t[1])) if a is not None]
        if est.quality >= 0.8 and err and math.hypot(*err) > 0.05:
            self.confident_wrong += 1

    def lines(self) -> list[str]:
        fu = self.fusion
        cues = ", ".join(f"{m} {n}" for m, n in fu.contributions.most_common()) or "none"
        gated = ", ".join(f"{m} {n}" for m, n in fu.gated.most_common()) or "none"
        out = [f"fusion: fixes applied {cues}; gated {gated}; resets "
               f"{fu.relocalizations + fu.start_poses} ({fu.relocalizations} "
               f"relocalizations, {fu.start_poses} start poses); odometry rows "
               f"{fu.odometry_rows}"
               + (f" ({fu.odometry_refused} refused: out of reach)" if fu.odometry_refused
                  else "")
               + f", ceiling-plane increments {fu.plane_increments}"
               + (f" ({fu.chain.refused} refused: a motion no vehicle made)"
                  if fu.chain.refused else "") + "; "
               f"late rows re-filtered {fu.refiltered}"]
        if self.values:
            inside = [v <= ekf.chi2_quantile(0.95, d) for v, d in self.values]
            dof = round(float(np.mean([d for _, d in self.values])))
            n_eff = effective_count([v for v, _ in self.values])
            lo, hi = ekf.mean_nees_band(max(1, round(n_eff)), dof)
            mean = float(np.mean([v for v, _ in self.values]))
            out.append(f"consistency: mean NEES {mean:.2f} ({dof} dof, 95% band "
                       f"{lo:.2f}-{hi:.2f} for {n_eff:.0f} independent of "
                       f"{len(self.values)} poses), {100 * np.mean(inside):.1f}% of poses inside "
                       f"their 95% ellipsoid; quality >= 0.8 but > 5 cm off: "
                       f"{self.confident_wrong}")
            if not lo <= mean <= hi:
                out.append(_NEES_BELOW if mean < lo else _NEES_ABOVE)
        return out


_NEES_BELOW = ("consistency: below the band: the published covariances are wider than the "
               "errors made (conservative: a gate or a fusion downstream trusts these poses "
               "less than it could); nothing to do on the vehicle")
_NEES_ABOVE = ("consistency: ABOVE the band: the errors are larger than the published "
               "covariances claim; do not fuse these poses with a tight gate, and report "
               "the recording (docs/methods/honesty.md)")


def _failure(est: Estimate, cues: tuple) -> Failure:
    """What to publish with no track and no fix: the first cue's failure."""
    first = next((c for c in cues if isinstance(c, Failure)), None)
    if first is None:
        return Failure(int(est.t_ns), NAME, "no_match", "no cue gives a position")
    return first


__all__ = ["Fusion", "FusionOptions", "FusionReport", "FilterBuffer",
           "effective_count", "measurement", "nees", "NAME"]
