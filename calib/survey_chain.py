"""The survey's frames chained by relative motions: ceiling-plane odometry between
consecutive frames, wheel odometry when the recording has it, a place match where both
fail; split into *segments* where nothing links two consecutive frames.

A segment's chain (:attr:`Segment.chain`) is its frames' poses composed from its first
frame at the origin of the segment's own frame: where the segment lies in W is what
the loop closures and the anchor decide (:mod:`ceilkit.calib.survey`).

Wheel odometry (SPEC §2 ``odometry.csv``: increments in V since the previous row) is
summed between two frames' stamps; its covariance is the tracker's wheel model
(:class:`~ceilkit.runtime.geometry.ekf.MotionNoise`: 1 % of the length along and
across, 2 % of the turn plus 0.5 deg per sqrt(m)), the same as ``ceilrun`` assumes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.odometry import PlaneOdometry
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry import ekf
from ceilkit.runtime.geometry.ceiling import PlanarGeometry
from ceilkit.runtime.geometry.ekf import MotionNoise
from ceilkit.runtime.io.recording import Odometry, Recording

from .survey_graph import Edge, chain_poses, compose
from .survey_places import Place, PlaceMatch, match_places, place_of


@dataclass(frozen=True, eq=False)
class Segment:
    """Consecutive frames of one drive linked by measured motions.

    Attributes:
        drive: the recording's number (the order given).
        frames: ``(n,)`` the frames' positions in the recording.
        steps: ``n - 1`` edges between consecutive frames (``i``, ``j`` are positions in
            ``frames``), each the odometry, the wheels or a place match.
        chain: ``(n, 3)`` the poses composed from the first at (0, 0, 0).
    """

    drive: int
    frames: np.ndarray
    steps: tuple[Edge, ...]
    chain: np.ndarray


@dataclass(eq=False)
class _Builder:
    drive: int
    frames: list[int] = field(default_factory=list)
    steps: list[Edge] = field(default_factory=list)

    def segment(self) -> Segment:
        z = [e.z for e in self.steps]
        return Segment(self.drive, np.array(self.frames, int), tuple(self.steps),
                       chain_poses(np.zeros(3), z))


def wheel_between(odo: Odometry, t0_ns: int, t1_ns: int,
                  noise: MotionNoise = MotionNoise()) -> tuple[np.ndarray, np.ndarray] | None:
    """The wheel odometry's motion from ``t0_ns`` to ``t1_ns`` in V at ``t0_ns`` (rows
    with ``t0 < t <= t1`` composed) and its ``(3, 3)`` covariance; None when no row
    falls in the interval."""
    rows = np.flatnonzero((odo.t_ns > t0_ns) & (odo.t_ns <= t1_ns))
    if rows.size == 0:
        return None
    pose = np.zeros(3)
    for k in rows:
        pose = compose(pose, np.array([odo.dx_m[k], odo.dy_m[k], odo.dyaw_rad[k]]))
    length = float(np.sum(np.hypot(odo.dx_m[rows], odo.dy_m[rows])))
    turn = float(np.sum(np.abs(odo.dyaw_rad[rows])))
    var_yaw = (noise.odo_yaw_rel * turn) ** 2 + noise.odo_yaw_per_m_rad ** 2 * length
    cov = np.diag([(noise.odo_rel * length) ** 2 + 1e-8,
                   (noise.odo_lateral_rel * length) ** 2 + 1e-8, var_yaw + 1e-10])
    return pose, cov


def chain_drive(rec: Recording, drive: int, rig: Rig, height_m: float,
                rng: np.random.Generator,
                prepare: Callable[[int, np.ndarray], np.ndarray] | None = None
                ) -> tuple[list[Segment], dict[int, Place]]:
    """The segments of one recording (module docstring) and the places computed to
    bridge odometry gaps (by frame position). ``prepare(k, grey)``: each frame's grey
    image as the survey reads it (the rolling shutter undone:
    :mod:`~ceilkit.calib.survey_shutter`); default as recorded."""
    geo = PlanarGeometry.of(rig, Site(height_m))
    odo = PlaneOdometry(geo)
    segments: list[Segment] = []
    places: dict[int, Place] = {}
    cur = _Builder(drive)
    prev_grey: np.ndarray | None = None
    for k in range(len(rec)):
        frame = rec.frame(k)
        if frame.damage:
            continue
        grey = to_grey(frame.image)
        if prepare is not None:
            grey = prepare(k, grey)
        t_ns = int(rec.t_ns[k])
        inc = odo.increment(grey, t_ns)
        edge = None
        if cur.frames:
            j = len(cur.frames)
            if inc is not None:
                edge = Edge(j - 1, j, np.array([inc.dx_m, inc.dy_m, inc.dyaw_rad]),
                            np.asarray(inc.cov, float), "odometry")
            else:
                edge = _bridge(rec, cur.frames[-1], k, prev_grey, grey, rig, height_m,
                               places, rng, j)
            if edge is None:
                segments.append(cur.segment())
                cur = _Builder(drive)
        if edge is not None:
            cur.steps.append(edge)
        cur.frames.append(k)
        prev_grey = grey
    if cur.frames:
        segments.append(cur.segment())
    return segments, places


def _bridge(rec: Recording, k0: int, k1: int, grey0: np.ndarray | None, grey1: np.ndarray,
            rig: Rig, height_m: float, places: dict[int, Place], rng: np.random.Generator,
            j: int) -> Edge | None:
    """The link between two consecutive frames the odometry could not measure: a place
    match, else the wheel odometry, else None (a new segment starts)."""
    if grey0 is not None:
        for k, g in ((k0, grey0), (k1, grey1)):
            if k not in places:
                places[k] = place_of(g, rig, height_m)
        m = match_places(places[k0], places[k1], rng, min_points=0)   # a step
        if m:
            return Edge(j - 1, j, m.z, m.cov, "place")
    if rec.odometry is not None:
        w = wheel_between(rec.odometry, int(rec.t_ns[k0]), int(rec.t_ns[k1]))
        if w is not None:
            return Edge(j - 1, j, w[0], w[1], "wheel")
    return None


GAP_REACH = 3
"""Frames either side of a break in the chain that :func:`gap_matches` pairs: places
up to ``GAP_REACH + 1`` frames apart (0.4 s at 10 fps)."""


def gap_matches(segments: list[Segment], place: Callable[[int, int], Place],
                rng: np.random.Generator
                ) -> tuple[list[tuple[int, int, int, int, PlaceMatch]], dict[str, int]]:
    """Where the chain broke (nothing linked frame ``k - 1`` to ``k``: a new segment
    started), the frames either side matched as places at longer baselines: for each
    segment and each later segment of its drive that starts within
    :data:`GAP_REACH` + 1 frames of its end, its last :data:`GAP_REACH` frames against
    the other's first, nearest in time first, until one match is accepted
    (:func:`~.survey_places.match_places` as a step: singled out, beyond chance). A sparse
    frame or a seam's standstill that broke one step often leaves the frames around
    it matchable. ``place(drive, k)``: a frame's place.

    Returns the accepted ``(segment, position, other segment, position, match)`` and
    the refused tries by reason (``gap: <reason>``)."""
    out, refused = [], {}
    for s, a in enumerate(segments):
        for t in range(s + 1, len(segments)):
            b = segments[t]
            if b.drive != a.drive or b.frames[0] - a.frames[-1] > GAP_REACH + 1:
                break
            tries = sorted(((int(b.frames[j] - a.frames[i]), i, j)
                            for i in range(max(0, len(a.frames) - GAP_REACH), len(a.frames))
                            for j in range(min(GAP_REACH, len(b.frames)))),
                           key=lambda x: x[0])
            for gap, i, j in tries:
                if gap > GAP_REACH + 1:
                    break
                m = match_places(place(a.drive, int(a.frames[i])),
                                 place(b.drive, int(b.frames[j])), rng, min_points=0)
                if m:
                    out.append((s, i, t, j, m))
                    break
                refused[f"gap: {m.reason}"] = refused.get(f"gap: {m.reason}", 0) + 1
    return out, refused


def wheel_edges(rec: Recording, seg: Segment, offset: int) -> list[Edge]:
    """The wheel odometry beside the camera's steps of a segment (graph nodes numbered
    from ``offset``): one edge per consecutive pair the odometry covers."""
    if rec.odometry is None:
        return []
    out = []
    for a in range(len(seg.frames) - 1):
        if seg.steps[a].kind == "wheel":
            continue
        w = wheel_between(rec.odometry, int(rec.t_ns[seg.frames[a]]),
                          int(rec.t_ns[seg.frames[a + 1]]))
        if w is not None:
            out.append(Edge(offset + a, offset + a + 1, w[0], w[1], "wheel"))
    return out


def keyframes(chain: np.ndarray, step_m: float, turn_rad: float) -> np.ndarray:
    """Positions in a segment of its keyframes: the first, then each frame
    ``step_m`` of travel or ``turn_rad`` of turn past the last keyframe, and the last."""
    keys = [0]
    for k in range(1, len(chain)):
        last = chain[keys[-1]]
        if math.hypot(*(chain[k, :2] - last[:2])) >= step_m or \
                abs(chain[k, 2] - last[2]) >= turn_rad:
            keys.append(k)
    if keys[-1] != len(chain) - 1:
        keys.append(len(chain) - 1)
    return np.array(keys, int)


def path_length(chain: np.ndarray) -> np.ndarray:
    """``(n,)`` the distance driven to each pose of a chain, m."""
    return np.r_[0.0, np.cumsum(np.hypot(*np.diff(chain[:, :2], axis=0).T))]


def chain_between(seg: Segment, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """The chain's motion from position ``i`` to ``j > i`` of a segment (pose ``j`` in
    the frame of pose ``i``) and its ``(3, 3)`` covariance: the steps applied as the
    tracker applies an odometry increment of its own scale
    (:func:`~ceilkit.runtime.geometry.ekf.predict_odometry`), their covariances
    propagated to first order."""
    s, P = np.zeros(ekf.N_STATE), np.zeros((ekf.N_STATE, ekf.N_STATE))
    s[ekf.SCALE] = 1.0
    for e in seg.steps[i:j]:
        s, P = ekf.predict_odometry(s, P, tuple(map(float, e.z)), 0.0, MotionNoise(),
                                    cov_v=e.cov, scaled=False)
    pose = np.ix_(ekf.FULL_POSE, ekf.FULL_POSE)
    return s[list(ekf.FULL_POSE)], P[pose]
