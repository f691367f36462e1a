"""Printed markers in a survey: each keyframe's markers (``cv2.aruco``, one dictionary)
placed on the ceiling plane with the solved poses, and the survey anchored by markers
of known pose (issue 39's "a marker of known pose").

Each keyframe's markers are measured on their edges as ``ceilcal blockmap`` and the
block method measure one (:func:`~ceilkit.calib.blockmap.frame_sightings`: lines fitted
to the four sides, corners where they meet), met with the ceiling plane ``z = H``
through the rig (metric) and moved into the survey's frame by the keyframe's solved
pose; a marker's views at its main place are fitted as blockmap fits them
(:func:`~ceilkit.calib.blockmap.fit_marker`: a square, weighted by each corner's
covariance), which gives each corner's covariance. A marker is *surveyed* only when
seen in :data:`MIN_VIEWS` keyframes or more; an id whose views fall at two places
farther apart than :data:`SAME_PLACE_M` (two prints of one id) is surveyed as
``places > 1``: which is the known one is not known, and it anchors nothing.

:func:`anchor_by_markers` moves the survey onto markers of known pose (``--site``'s
``markers``, or ``--anchor-marker``): the rigid motion of the plane that puts the
surveyed corners on the known ones (a decoded marker's id and corner order fix it: no
symmetric twin), accepted only when every known marker the drive saw is

* surveyed at one place, from :data:`MIN_VIEWS` views or more;
* of its known side within :data:`SIZE_TOL` (a marker of another size, or a wrong
  ceiling height, is refused, not scaled; a marker given with no side, NaN, is taken at
  its surveyed side, unchecked);
* within :data:`RESIDUAL_M` of its known corners after the common fit (several markers
  that disagree are refused: one of them is not where the site says).

Example::

    found = survey_markers(frames_and_poses, rig, 2.7, "DICT_APRILTAG_36h11")
    a = anchor_by_markers(found, site.markers.poses)
    if a.ok: poses_w = a.apply(poses)         # (N, 3) in the site's W
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import MARKER_CORNER_DIRECTIONS, MarkerPose
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.ceiling import PlanarGeometry
from ceilkit.runtime.geometry.fits import fit_rigid_2d

from .blockmap import Sighting, fit_marker, frame_sightings
from .survey_anchor import move_poses

MIN_VIEWS = 3
SAME_PLACE_M = 0.10
SIZE_TOL = 0.05
RESIDUAL_M = 0.02
CORNER_FLOOR_M = 0.001
"""A surveyed corner's 1σ per axis is at least this in the anchor's yaw 1σ. Set when the
corners were ``cornerSubPix``'s: one 0.2 m marker as the anchor then turned a 2 m drive
by 0.22 deg (4.3 mm at the other marker 1.1 m away), what 1 mm a corner gives. Measured
on their edges the same drive is turned by far less (the other marker 0.22 mm off;
corners 0.2-0.5 mm RMS from the placement from the true poses on
``bench_survey.py --against-known``): the floor now over-covers, kept until measured
on more drives."""


@dataclass(frozen=True, eq=False)
class SurveyedMarker:
    """One marker id as the survey placed it, in the survey's frame.

    Attributes:
        id: its id in the dictionary.
        corners_m: ``(4, 2)`` its corners (SPEC §2 order): the square fitted to its views
            at the main place (:func:`~ceilkit.calib.blockmap.fit_marker`).
        views: keyframes that saw it there; ``places``: places its views fall at (more
            than 1: two prints of one id).
        spread_m: RMS distance of the views' corners from ``corners_m``.
        fit_cov_m2: ``(4, 2, 2)`` each corner's covariance from the fit, m² (the views'
            scatter averaged down and an error every view shares, as blockmap states it).
        pose_sigma_m: the 1σ per axis of the poses that placed it (their errors are
            shared between neighbouring views: not averaged down).
    """

    id: int
    corners_m: np.ndarray
    views: int
    places: int
    spread_m: float
    fit_cov_m2: np.ndarray
    pose_sigma_m: float = 0.0

    @property
    def corner_cov(self) -> np.ndarray:
        """``(4, 2, 2)`` each corner's covariance, m²: the fit's and the poses'
        (``pose_sigma_m²`` per axis)."""
        return self.fit_cov_m2 + self.pose_sigma_m ** 2 * np.eye(2)

    @property
    def sigma_m(self) -> float:
        """A corner's 1σ per axis (RMS over the four corners and both axes), metres."""
        return math.sqrt(float(np.mean(np.trace(self.corner_cov, axis1=1, axis2=2))) / 2)

    @property
    def size_m(self) -> float:
        """Mean side length, m."""
        c = self.corners_m
        return float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))

    def pose(self) -> MarkerPose:
        """Centre, yaw and side as SPEC §2's marker pose (the corners' rigid fit)."""
        s = self.size_m
        yaw, t = fit_rigid_2d(0.5 * s * MARKER_CORNER_DIRECTIONS, self.corners_m)
        return MarkerPose(self.id, float(t[0]), float(t[1]), float(yaw), s)

    def moved(self, yaw_rad: float, t_m: np.ndarray) -> SurveyedMarker:
        """This marker in another frame, ``X' = Rz(yaw) X + t`` (an anchor's motion):
        its corners moved, their covariance turned with them."""
        p = move_poses(yaw_rad, np.asarray(t_m, float), np.c_[self.corners_m, np.zeros(4)])
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        R = np.array([[c, -s], [s, c]])
        return replace(self, corners_m=p[:, :2], fit_cov_m2=R @ self.fit_cov_m2 @ R.T)


def survey_markers(frames: Iterable[tuple[np.ndarray, np.ndarray]], rig: Rig,
                   height_m: float, dictionary: str, pose_sigma_m: float = 0.0
                   ) -> list[SurveyedMarker]:
    """Every marker id the frames ``(grey, solved pose (3,))`` read, each placed
    (module docstring), ordered by id; ids seen fewer than :data:`MIN_VIEWS` times are
    left out. ``pose_sigma_m``: the poses' 1σ per axis (m)."""
    geo = PlanarGeometry(rig.camera, rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam,
                         float(height_m))
    views: dict[int, list[Sighting]] = {}
    for k, (grey, pose) in enumerate(frames):
        for mid, sg in frame_sightings(grey, k, pose, geo, dictionary):
            views.setdefault(mid, []).append(sg)
    found = (_placed(mid, views[mid], pose_sigma_m) for mid in sorted(views))
    return [m for m in found if m is not None]


def _placed(mid: int, sightings: list[Sighting], pose_sigma_m: float
            ) -> SurveyedMarker | None:
    """One id's views fitted at its main place (the views within :data:`SAME_PLACE_M`
    of their median centre), or None when fewer than :data:`MIN_VIEWS` are there."""
    centre = np.array([sg.corners_m.mean(axis=0) for sg in sightings])
    main = np.linalg.norm(centre - np.median(centre, axis=0), axis=1) <= SAME_PLACE_M
    if np.count_nonzero(main) < MIN_VIEWS:
        return None
    at = [sg for sg, ok in zip(sightings, main, strict=True) if ok]
    fit = fit_marker(mid, at)
    c = fit.corners_m
    spread = math.sqrt(float(np.mean([np.sum((sg.corners_m - c) ** 2, axis=1)
                                      for sg in at])))
    places = 1 + int(len(sightings) - len(at) >= MIN_VIEWS)
    return SurveyedMarker(mid, c, len(at), places, spread, fit.corner_cov, pose_sigma_m)


@dataclass(frozen=True, eq=False)
class MarkerAnchor:
    """The motion ``X_W = Rz(yaw) X + t`` from the survey's frame onto the known markers,
    or why none (``reason``; falsy). ``ids``: the markers it used; ``residual_m``:
    ``(K,)`` each one's RMS corner distance from its known corners after the fit;
    ``size_m``: ``(K,)`` each one's surveyed side; ``sigma_yaw_rad``: the motion's yaw
    1σ, the corners' 1σ (the largest of the fit's RMS residual, the markers' own
    ``sigma_m`` and :data:`CORNER_FLOOR_M`) over the corners' spread about their centre
    (one 0.2 m marker: 1 mm a corner is 0.2 deg, 3.5 mm at 1 m)."""

    ok: bool
    reason: str
    yaw_rad: float = 0.0
    t_m: np.ndarray | None = None
    ids: tuple[int, ...] = ()
    residual_m: np.ndarray | None = None
    size_m: np.ndarray | None = None
    sigma_yaw_rad: float = math.nan

    def __bool__(self) -> bool:
        return self.ok

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """Poses ``(N, 3)`` (x, y, yaw) of the survey's frame in the site's W."""
        return move_poses(self.yaw_rad, self.t_m, poses)

    def apply_xy(self, xy: np.ndarray) -> np.ndarray:
        p = np.asarray(xy, float).reshape(-1, 2)
        return self.apply(np.c_[p, np.zeros(len(p))])[:, :2]


def _usable(found: dict[int, SurveyedMarker], known: Sequence[MarkerPose]
            ) -> tuple[list[tuple[SurveyedMarker, MarkerPose]], str]:
    """The known markers the survey placed, paired, or why they cannot anchor it."""
    seen = [(found[k.id], k) for k in known if k.id in found]
    if not seen:
        ids = ", ".join(str(k.id) for k in known)
        got = ", ".join(str(i) for i in sorted(found)) or "none"
        return [], (f"marker(s) {ids} not seen in {MIN_VIEWS} keyframes or more "
                    f"(markers the drive surveyed: {got})")
    seen = [(s, k if math.isfinite(k.size_m) else replace(k, size_m=s.size_m))
            for s, k in seen]
    for s, k in seen:
        if s.places > 1:
            return [], (f"ambiguous: marker {k.id} is seen at {s.places} places more than "
                        f"{SAME_PLACE_M:.2f} m apart (two prints of one id)")
        if abs(s.size_m - k.size_m) > SIZE_TOL * k.size_m:
            return [], (f"marker {k.id} measures {s.size_m:.3f} m on the ceiling, its known "
                        f"side is {k.size_m:.3f} m (more than {100 * SIZE_TOL:.0f}% off: "
                        "another marker's size, or a wrong ceiling height)")
    return seen, ""


def anchor_by_markers(surveyed: Sequence[SurveyedMarker], known: Sequence[MarkerPose]
                      ) -> MarkerAnchor:
    """The motion from the survey's frame onto the known markers (module docstring)."""
    if not known:
        return MarkerAnchor(False, "no marker of known pose given")
    seen, why = _usable({s.id: s for s in surveyed}, known)
    if not seen:
        return MarkerAnchor(False, why)
    q = np.concatenate([s.corners_m for s, _ in seen])
    p = np.concatenate([k.corners_m() for _, k in seen])
    yaw, t = fit_rigid_2d(q, p)
    moved = move_poses(yaw, np.asarray(t), np.c_[q, np.zeros(len(q))])[:, :2]
    res = np.sqrt(np.mean(np.sum((moved - p) ** 2, axis=1).reshape(-1, 4), axis=1))
    ids = tuple(k.id for _, k in seen)
    sizes = np.array([s.size_m for s, _ in seen])
    worst = int(np.argmax(res))
    if res[worst] > RESIDUAL_M:
        return MarkerAnchor(False, f"the markers disagree: marker {ids[worst]} is "
                            f"{1e3 * res[worst]:.0f} mm from its known corners after the "
                            f"common fit (over {1e3 * RESIDUAL_M:.0f} mm): one of "
                            f"{', '.join(map(str, ids))} is not where it is said to be",
                            ids=ids, residual_m=res, size_m=sizes)
    sigma_c = max(float(np.sqrt(np.mean(res ** 2))), max(s.sigma_m for s, _ in seen),
                  CORNER_FLOOR_M)
    lever = math.sqrt(float(np.sum((q - q.mean(axis=0)) ** 2)))
    return MarkerAnchor(True, "", float(yaw), np.asarray(t, float), ids, res, sizes,
                        sigma_c / lever)


def parse_anchor_marker(text: str, sizes: dict[int, float] | None = None,
                        default_size_m: float = math.nan) -> MarkerPose:
    """``"ID,X,Y,YAW[,SIZE]"`` (id, m, m, degrees, m) as a marker pose; without SIZE, the
    side ``sizes`` gives that id, else ``default_size_m`` (NaN: unchecked).

    Raises:
        ConfigError: keyed ``--anchor-marker``, for anything else.
    """
    parts = text.replace(" ", "").split(",")
    try:
        mid = int(parts[0])
        x, y, yaw, *size = (float(v) for v in parts[1:])
    except (ValueError, IndexError):
        mid, size = -1, [0.0, 0.0]
    if mid < 0 or len(size) > 1 or not all(map(math.isfinite, (x, y, yaw, *size))) \
            or (size and size[0] <= 0):
        raise ConfigError(None, "--anchor-marker", f"expected ID,X,Y,YAW[,SIZE] (id >= 0, "
                          f"m, m, degrees, side > 0 m), found {text!r}")
    side = size[0] if size else (sizes or {}).get(mid, default_size_m)
    return MarkerPose(mid, x, y, math.radians(yaw), side)
