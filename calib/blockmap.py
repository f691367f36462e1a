"""Marker map from a drive of known poses: the ``markers`` section of a site (SPEC §2),
with each marker's covariance (``ceilcal blockmap``).

Every frame with a known vehicle pose is read by ``cv2.aruco`` (one dictionary; an id
read twice in a frame is left out, :func:`~ceilkit.runtime.estimators.block.detect.aruco_markers`),
each marker measured on its edges as the block method measures one (lines fitted to
its four sides, corners where they meet: :func:`frame_sightings`), met with the ceiling plane
``z = H`` through the rig and placed in W by the frame's pose (``X_W = Rz(yaw) X_V +
(x, y)``, SPEC §1). Each corner carries the 2x2 covariance in W of one pixel of error
(the ray's Jacobian on the ceiling: a corner seen far off-axis is weighted less).

A marker's pose is SPEC §2's centre ``(x, y)``, yaw ``a`` and side ``s``: corner k is
``(x, y) + Rz(a) (s/2) d_k``. With ``(p, q) = (s/2)(cos a, sin a)`` the corners are
linear in ``(x, y, p, q)``, so the weighted least squares over all its sightings'
corners is solved in closed form. Its covariance is ``s² N⁻¹`` (``N`` the normal
matrix, ``s²`` the residual's variance per pixel from the fit's ``8 V - 4`` degrees of
freedom: the views' independent errors, averaged down) plus ``σ_b² N₁⁻¹`` (``N₁``: one
view of the mean corner covariances; ``σ_b`` = the larger of :data:`SHARED_PX` and
``s``: an error every view shares), moved to ``(x, y, yaw, side)`` by the Jacobian. A
marker is *refused* (a
value with its reason, not written) when

* it is seen in fewer than :data:`MIN_VIEWS` frames;
* its sightings disagree: one lies more than :data:`DISAGREE_M` (RMS over its corners)
  from the fit of all (two prints of one id, or poses that are wrong);
* a side was given (``size_m``) and it measures more than :data:`SIZE_TOL` off it.

Example::

    rec = Recording("drive")                              # truth.csv: the known poses
    bm = map_markers(frames_with_poses(rec), rec.rig, 3.0, "DICT_APRILTAG_36h11")
    bm.placed[0].pose, bm.placed[0].cov                   # MarkerPose, (4, 4)
    [r.reason for r in bm.refused]
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import (
    MARKER_CORNER_DIRECTIONS,
    MarkerPose,
    Markers,
    Site,
    aruco_dictionary_size,
    check_rig_site,
)
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.estimators.block.detect import aruco_markers, measure_sides
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.quads import signed_area, square_cells
from ceilkit.runtime.geometry.ceiling import PlanarGeometry, ceiling_jacobian, ceiling_points
from ceilkit.runtime.io.outputs import claimed, recording_inputs
from ceilkit.runtime.io.recording import Recording

from .lightmap import load_pose_table
from .poses import StampedPoses
from .workflow import provenance_header

MIN_VIEWS = 3
"""Fewest frames a marker must be seen in to be placed."""
DISAGREE_M = 0.02
"""A sighting farther than this (RMS over its four corners) from the fit of all the
marker's sightings: the sightings disagree, the marker is refused (the survey's
corner tolerance, :data:`~ceilkit.calib.survey_markers.RESIDUAL_M`)."""
SIZE_TOL = 0.05
"""A marker whose side measures more than this share off the given side is refused
(another marker's size, or a wrong ceiling height)."""
DEFAULT_DICTIONARY = "DICT_APRILTAG_36h11"
MAX_GAP_S = 0.25
"""No pose is interpolated across a gap of the pose table longer than this (s)."""
SHARED_PX = 0.1
"""1σ per axis, pixels, of a corner's error shared by all its sightings (edges pulled
by the blur and the cells beside them, a lamp's edge across a side): not averaged
down over the views. Measured (``benchmarks/bench_blockmap.py``): 16 cm tags at 3.2 px
a cell came out 0.56-0.71 mm small (0.05 px a side) from 22-46 views whose scatter
alone gave a 0.03-0.08 mm corner 1σ. The larger of this and the fit's own residual
(a marker under a panel's edge: 0.49 px) is taken."""
EDGE_POINTS = 12
"""Edge stations a side (the block method's ``edge_points``)."""

_ROWS = np.stack([np.array([[1.0, 0.0, dx, -dy], [0.0, 1.0, dy, dx]])
                  for dx, dy in MARKER_CORNER_DIRECTIONS])       # (4, 2, 4)
"""Corner k = ``_ROWS[k] @ (x, y, p, q)``."""


@dataclass(frozen=True, eq=False)
class Sighting:
    """One frame's reading of one marker.

    Attributes:
        frame: the frame's index in the recording.
        corners_m: ``(4, 2)`` its corners in W (SPEC §2 order), metres.
        cov_m2: ``(4, 2, 2)`` each corner's covariance in W for one pixel of error
            (m² per px²).
    """

    frame: int
    corners_m: np.ndarray
    cov_m2: np.ndarray


@dataclass(frozen=True, eq=False)
class PlacedMarker:
    """A marker placed by least squares over its sightings.

    Attributes:
        pose: centre, yaw and side as measured (SPEC §2's marker pose).
        cov: ``(4, 4)`` covariance of ``(x m, y m, yaw rad, side m)``.
        corner_cov: ``(4, 2, 2)`` covariance of each corner in W, m².
        frames: the frames that saw it.
        rms_px: the fit's residual, pixels (RMS per axis, from its covariance weights).
        worst_m: the farthest sighting from the fit, RMS over its corners, metres.
    """

    pose: MarkerPose
    cov: np.ndarray
    corner_cov: np.ndarray
    frames: tuple[int, ...]
    rms_px: float
    worst_m: float

    @property
    def id(self) -> int:
        return self.pose.id

    @property
    def corners_m(self) -> np.ndarray:
        """``(4, 2)`` the fitted corners in W (SPEC §2 order)."""
        return self.pose.corners_m()

    @property
    def corner_sigma_m(self) -> float:
        """A corner's 1σ per axis (RMS over the four corners and both axes), metres."""
        return math.sqrt(float(np.mean(np.trace(self.corner_cov, axis1=1, axis2=2))) / 2)

    @property
    def sigmas(self) -> tuple[float, float, float, float]:
        """1σ of ``(x m, y m, yaw rad, side m)``."""
        return tuple(float(v) for v in np.sqrt(np.maximum(np.diag(self.cov), 0.0)))


@dataclass(frozen=True)
class RefusedMarker:
    """A marker seen in the drive but not placed, and why (``reason``: one line)."""

    id: int
    views: int
    reason: str


@dataclass(frozen=True, eq=False)
class BlockMap:
    """Every marker a drive saw: those placed (ordered by id) and those refused.

    ``frames_used``: frames with a known pose that were read; ``sightings``: marker
    readings in them (all ids)."""

    dictionary: str
    placed: tuple[PlacedMarker, ...]
    refused: tuple[RefusedMarker, ...]
    frames_used: int
    sightings: int


def corner_covariances(geo: PlanarGeometry, corners_norm: np.ndarray,
                       yaw_rad: float) -> np.ndarray:
    """``(N, 2, 2)`` covariance in W of the ceiling points of normalized image points
    ``(N, 2)`` for one pixel of error per axis, seen at vehicle heading ``yaw_rad``:
    ``G Gᵀ`` with ``G`` the ceiling point's Jacobian on the pixel (the ray's on the
    normalized point times the lens's inverse). NaN where a ray is level."""
    xy = np.asarray(corners_norm, float).reshape(-1, 2)
    G = ceiling_jacobian(xy, geo.R_vehicle_cam, geo.rise_m) \
        @ np.linalg.inv(geo.camera.distort_jacobian(xy))
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    G = np.array([[c, -s], [s, c]]) @ G
    return G @ np.transpose(G, (0, 2, 1))


def frame_sightings(grey: np.ndarray, frame: int, pose: np.ndarray, geo: PlanarGeometry,
                    dictionary: str) -> list[tuple[int, Sighting]]:
    """``(id, sighting)`` of every marker ``cv2.aruco`` reads in one frame seen from
    vehicle pose ``(x, y, yaw)`` (m, m, rad). Each is measured on its edges as the
    block method measures a marker (:func:`~ceilkit.runtime.estimators.block.detect.measure_sides`:
    lines fitted to :data:`EDGE_POINTS` edge points a side, dark inside, two passes
    about aruco's corners, each edge's level half a cell either side of it; corner k
    between sides k-1 and k); a marker whose sides are not measured, or with a corner
    whose ray does not rise to the ceiling, is left out."""
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    cells = square_cells(dictionary)
    out = []
    for mid, px in aruco_markers(grey, dictionary):
        sign = -1 if signed_area(px) > 0 else 1
        sides = measure_sides(grey, px, geo, EDGE_POINTS, passes=2, sign=sign, cells=cells)
        if sides is None:
            continue
        q, ok = ceiling_points(sides.corners_norm, geo.R_vehicle_cam, geo.t_vehicle_cam,
                               geo.rise_m)
        cov = corner_covariances(geo, sides.corners_norm, yaw)
        if not ok.all() or not np.all(np.isfinite(cov)):
            continue
        w = np.c_[c * q[:, 0] - s * q[:, 1] + x, s * q[:, 0] + c * q[:, 1] + y]
        out.append((int(mid), Sighting(frame, w, cov)))
    return out


def fit_marker(mid: int, sightings: Sequence[Sighting]) -> PlacedMarker:
    """The weighted least-squares pose of one marker over its sightings (module
    docstring), with its covariance; needs 2 sightings or more."""
    N = np.zeros((4, 4))
    rhs = np.zeros(4)
    weights = []
    for sg in sightings:
        W = np.linalg.inv(sg.cov_m2)                                 # (4, 2, 2) px²/m²
        weights.append(W)
        N += np.einsum("kia,kij,kjb->ab", _ROWS, W, _ROWS)
        rhs += np.einsum("kia,kij,kj->a", _ROWS, W, sg.corners_m)
    Ninv = np.linalg.inv(N)
    theta = Ninv @ rhs
    fit = _ROWS @ theta                                              # (4, 2)
    chi2, worst = 0.0, 0.0
    for sg, W in zip(sightings, weights, strict=True):
        e = sg.corners_m - fit
        chi2 += float(np.einsum("ki,kij,kj->", e, W, e))
        worst = max(worst, math.sqrt(float(np.mean(np.sum(e ** 2, axis=1)))))
    s2 = chi2 / (8 * len(sightings) - 4)
    shared = np.linalg.inv(np.mean([sg.cov_m2 for sg in sightings], axis=0))  # (4, 2, 2)
    N1 = np.einsum("kia,kij,kjb->ab", _ROWS, shared, _ROWS)
    cov_t = s2 * Ninv + max(SHARED_PX ** 2, s2) * np.linalg.inv(N1)
    x, y, p, q = theta
    r = math.hypot(p, q)
    J = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, -q / r ** 2, p / r ** 2], [0.0, 0.0, 2 * p / r, 2 * q / r]])
    pose = MarkerPose(mid, float(x), float(y), math.atan2(q, p), 2.0 * r)
    return PlacedMarker(pose, J @ cov_t @ J.T, _ROWS @ cov_t @ _ROWS.transpose(0, 2, 1),
                        tuple(sg.frame for sg in sightings), math.sqrt(s2), worst)


def place_marker(mid: int, sightings: Sequence[Sighting], size_m: float | None = None
                 ) -> PlacedMarker | RefusedMarker:
    """One marker placed from its sightings, or refused with its reason (module
    docstring). ``size_m``: the printed side, checked within :data:`SIZE_TOL`."""
    n = len(sightings)
    frames = ", ".join(str(sg.frame) for sg in sightings[:6]) + (", ..." if n > 6 else "")
    if n < MIN_VIEWS:
        return RefusedMarker(mid, n, f"seen in {n} frame{'s' * (n != 1)} ({frames}), "
                                     f"fewer than {MIN_VIEWS}: drive under it again")
    m = fit_marker(mid, sightings)
    if m.worst_m > DISAGREE_M:
        err = [math.sqrt(float(np.mean(np.sum((sg.corners_m - m.corners_m) ** 2, 1))))
               for sg in sightings]
        k = int(np.argmax(err))
        return RefusedMarker(mid, n, f"its {n} sightings disagree: frame "
                             f"{sightings[k].frame} lies {1e3 * err[k]:.0f} mm from the "
                             f"fit of all (RMS over its corners; over "
                             f"{1e3 * DISAGREE_M:.0f} mm; the sightings' centres span "
                             f"{1e3 * _span(sightings):.0f} mm): two prints of one id, "
                             "or poses that are wrong")
    side = m.pose.size_m
    if size_m is not None and abs(side - size_m) > SIZE_TOL * size_m:
        return RefusedMarker(mid, n, f"measures {side:.4f} m on the ceiling, the given "
                             f"side is {size_m:.4f} m (more than {100 * SIZE_TOL:.0f}% "
                             "off: another marker's size, or a wrong ceiling height)")
    return m


def _span(sightings: Sequence[Sighting]) -> float:
    """Largest distance between two sightings' centres, metres."""
    c = np.array([sg.corners_m.mean(axis=0) for sg in sightings])
    return float(np.max(np.linalg.norm(c[:, None] - c[None], axis=2)))


def map_markers(frames: Iterable[tuple[int, np.ndarray, np.ndarray]], rig: Rig,
                height_m: float, dictionary: str, size_m: float | None = None
                ) -> BlockMap:
    """Every marker the frames ``(index, image, vehicle pose (3,))`` read, placed or
    refused (module docstring); ``height_m``: the ceiling's height (m)."""
    seen: dict[int, list[Sighting]] = {}
    used = 0
    geo = PlanarGeometry(rig.camera, rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam,
                         float(height_m))
    for k, image, pose in frames:
        used += 1
        for mid, sg in frame_sightings(to_grey(image), k, pose, geo, dictionary):
            seen.setdefault(mid, []).append(sg)
    out = [place_marker(mid, seen[mid], size_m) for mid in sorted(seen)]
    return BlockMap(dictionary, tuple(m for m in out if isinstance(m, PlacedMarker)),
                    tuple(m for m in out if isinstance(m, RefusedMarker)), used,
                    sum(len(v) for v in seen.values()))


def frames_with_poses(recording: Recording, table: StampedPoses,
                      offset_ns: float = 0.0) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(index, image, pose)`` of the recording's frames whose pose the table gives
    (interpolated at the frame's stamp + ``offset_ns``, never across a gap over
    :data:`MAX_GAP_S`); damaged frames are skipped."""
    poses = table.at(recording.t_ns, offset_ns, MAX_GAP_S * 1e9)
    for k in np.flatnonzero(np.all(np.isfinite(poses), axis=1)):
        frame = recording.frame(int(k))
        if not frame.damage:
            yield int(k), frame.image, poses[k]


def marker_section(bm: BlockMap, size_m: float | None) -> Markers:
    """The placed markers as SPEC §2's ``markers`` section: centres to 0.01 mm, yaw to
    1e-4 degree; every side ``size_m`` when given (the printed side, checked), else
    each marker's measured side (the section's default: their median)."""
    poses = []
    for m in bm.placed:
        p = m.pose
        poses.append(MarkerPose(p.id, round(p.x_m, 5), round(p.y_m, 5),
                                math.radians(round(math.degrees(p.yaw_rad), 4)),
                                size_m if size_m is not None else round(p.size_m, 5)))
    default = size_m if size_m is not None else float(np.median([p.size_m for p in poses]))
    return Markers(bm.dictionary, default, tuple(poses))


def header_lines(bm: BlockMap, where: str) -> list[str]:
    """Report lines for the site file's header: the map, each marker's uncertainty
    (SPEC's ``markers`` has no key for it) and the markers refused."""
    lines = [f"marker map: {len(bm.placed)} markers placed from {bm.sightings} sightings "
             f"in {bm.frames_used} frames with a known pose ({len(bm.refused)} refused); "
             f"dictionary {bm.dictionary}",
             "per marker (same order as `markers.poses`): sx_mm, sy_mm = centre 1-sigma, "
             "syaw_deg, side_m measured +- sside_mm, corner_mm = a corner's 1-sigma per "
             "axis, rms_px = fit residual, worst_mm = farthest sighting, views"]
    for i, m in enumerate(bm.placed):
        sx, sy, syaw, ss = m.sigmas
        lines.append(f"  poses[{i}] id {m.id}: sx_mm {1e3 * sx:.3f}  sy_mm {1e3 * sy:.3f}  "
                     f"syaw_deg {math.degrees(syaw):.4f}  side_m {m.pose.size_m:.5f} +- "
                     f"{1e3 * ss:.3f} mm  corner_mm {1e3 * m.corner_sigma_m:.3f}  rms_px "
                     f"{m.rms_px:.3f}  worst_mm {1e3 * m.worst_m:.2f}  views {len(m.frames)}")
    lines += [f"refused: {where}: marker {r.id}: {r.reason}" for r in bm.refused]
    return lines


@dataclass(frozen=True, eq=False)
class BlockmapRun:
    """A written site map with the markers of a drive."""

    blockmap: BlockMap
    site_path: Path
    where: str

    def lines(self) -> list[str]:
        bm = self.blockmap
        ids = ", ".join(str(m.id) for m in bm.placed)
        sig = float(np.median([m.corner_sigma_m for m in bm.placed]))
        return [f"{self.site_path}: {len(bm.placed)} markers ({ids}) from "
                f"{bm.frames_used} frames; median corner 1-sigma {1e3 * sig:.2f} mm"]

    def refusals(self) -> list[str]:
        """One line per marker refused (``REC: marker ID: why``)."""
        return [f"{self.where}: marker {r.id}: {r.reason}" for r in self.blockmap.refused]


def _check_options(dictionary: str, size_m: float | None) -> None:
    if aruco_dictionary_size(dictionary) is None:
        raise ConfigError(None, "dictionary", f"expected an OpenCV aruco dictionary "
                          f"(DICT_4X4_50, DICT_APRILTAG_36h11, ...), found {dictionary!r}")
    if size_m is not None and not (math.isfinite(size_m) and size_m > 0):
        raise ConfigError(None, "size_m", f"expected a side > 0 m, found {size_m!r}")


def blockmap(recording: Path, out: Path, *, rig: Path | None = None,
             poses: Path | None = None, pose_offset_ms: float | None = None,
             dictionary: str | None = None, size_m: float | None = None,
             ceiling_height_m: float | None = None, force: bool = False) -> BlockmapRun:
    """Map the markers of ``recording`` from its known poses and write them as the
    ``markers`` of ``out`` (site.yaml; its other sections kept when it exists, else the
    recording's). Poses: ``poses`` (truth.csv or poses.csv layout) or the recording's
    truth.csv, interpolated at each frame's stamp + ``pose_offset_ms``. ``dictionary``:
    default the base site's markers' (else :data:`DEFAULT_DICTIONARY`); ``size_m``: the
    printed side (checked, written); ``force``: write into an existing ``out``.

    Raises:
        ConfigError: bad inputs or options; no poses; ``out`` exists (without
            ``force``), is an input or lies in the recording.
        CalibrationError: no marker could be placed (nothing written).
    """
    with claimed({"out": [Path(out)]}, force=force,
                 inputs=[*recording_inputs(recording), *(p for p in (rig, poses) if p)]):
        rec = Recording(recording, rig=rig)
        base = Site.load(out) if Path(out).exists() else rec.site
        if ceiling_height_m is not None:
            base = replace(base, ceiling_height_m=ceiling_height_m)
        check_rig_site(rec.rig, base)
        if dictionary is None:
            dictionary = base.markers.dictionary if base.markers else DEFAULT_DICTIONARY
        _check_options(dictionary, size_m)
        table = _pose_table(rec, poses)
        offset_ns = 0.0 if pose_offset_ms is None else pose_offset_ms * 1e6
        bm = map_markers(frames_with_poses(rec, table, offset_ns), rec.rig,
                         base.ceiling_height_m, dictionary, size_m)
        where = str(recording)
        if bm.frames_used == 0:
            raise ConfigError(poses or rec.folder / "truth.csv", "t_ns", "no pose covers a "
                              "frame stamp (frames.csv t_ns): the poses cover none of the "
                              "frames")
        if not bm.placed:
            why = "; ".join(f"marker {r.id}: {r.reason}" for r in bm.refused)
            raise CalibrationError(f"{where}: no marker placed ({bm.frames_used} frames "
                                   f"with a pose read with {dictionary}"
                                   + (f"; {why}" if why else ": none seen") + "); nothing written")
        site = replace(base, markers=marker_section(bm, size_m), source=str(out))
        site.save(out, provenance_header("ceilcal blockmap: site map with surveyed markers",
                                         header_lines(bm, where)))
        Site.load(out)          # read back: the file is valid by the same rules as any other
        return BlockmapRun(bm, Path(out), where)


def _pose_table(rec: Recording, poses: Path | None) -> StampedPoses:
    if poses is not None:
        return StampedPoses.from_truth(load_pose_table(poses))
    if rec.truth is None:
        raise ConfigError(rec.folder, "truth.csv", "no known poses: the recording has no "
                          "truth.csv; give them with --poses")
    return StampedPoses.from_truth(rec.truth)


__all__ = ["BlockMap", "BlockmapRun", "PlacedMarker", "RefusedMarker", "Sighting",
           "blockmap", "corner_covariances", "fit_marker", "frame_sightings",
           "frames_with_poses", "header_lines", "map_markers", "marker_section",
           "place_marker"]
