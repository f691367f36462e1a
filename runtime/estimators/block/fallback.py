"""Markers for the block method: read on a dark quad of the decimated search
(:meth:`MarkerReader.quad_fix`), and the full-resolution fallback (issue 36, option
``marker_fallback``: :meth:`MarkerReader.aruco_fixes`).

The quad search runs on the frame decimated by 2 and opened (:func:`.detect.find_quads`):
a marker of about 3 px per cell (a 16 cm AprilTag 36h11 1.9 m away at f = 310 px) has a
one-cell black border there of 1.6 px, which the opening breaks, so no quad. Where the
decimated search gave no marker fix, ``cv2.aruco``'s default detector reads the full
frame (:func:`.detect.aruco_markers`, the site's dictionary), or, when the dark search
flagged the spots of a marker's size on its mask before the opening
(:attr:`MarkerReader.spot_side_px`, :class:`.detect.SpotSearch`), on crops about those
spots only (:func:`.detect.marker_crops`: no marker aruco reads on the whole frame lies
outside them, and their perimeter limits are the whole frame's). Each marker it reads is
measured on its edges about aruco's corners (two passes, the edges searched dark inside
only: a cell away the first inner cells' edges and the quiet ring's are of the other
polarity), read again by :func:`.detect.read_marker` as a check, and solved as any
marker (the block method's solve stage, :class:`.pnp.PlanarSolver`). aruco's corner k
is SPEC §2's corner k.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.block.detect import (
    Sides,
    SpotSearch,
    aruco_markers,
    marker_crops,
    measure_sides,
    read_marker,
)
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, PlanarSolver, TargetFix
from ceilkit.runtime.features.quads import MarkerCodes, Quad, signed_area
from ceilkit.runtime.geometry.ceiling import ceiling_points_vehicle

SPOT_GRID = (33, 25)
"""Pixels across and down the frame where :func:`marker_side_range_px` samples the
ceiling's scale."""

SPOT_MARGIN = 1.5
"""The largest spot searched is this many times the largest marker's diagonal at the
frame's largest scale (the scale between the grid's samples, and blur)."""

class MarkerReader:
    """The site's markers read and solved for the block method (see module).

    Args:
        geo: the rig and ceiling.
        markers: the site's ``markers`` section.
        codes: its dictionary's codes (the check read).
        edge_points: edge stations per side (the block method's option).
        solve: the block method's solve stage (:class:`.pnp.PlanarSolver`, or a
            subclass: a marker's measured sides and corners in W, its fix or None).
    """

    def __init__(self, geo: PlanarGeometry, markers: Any, codes: MarkerCodes,
                 edge_points: int, solve: PlanarSolver) -> None:
        self.geo, self.markers, self.codes = geo, markers, codes
        self.edge_points, self.solve = int(edge_points), solve
        self.spot_side_px = marker_side_range_px(geo, [p.size_m for p in markers.poses])
        self._corners: dict[int, np.ndarray] = {}     # id -> corners (4, 2) in W, SPEC §2
        for p in markers.poses:                       # (an id's first pose, as Markers.pose)
            self._corners.setdefault(int(p.id), _read_only(p.corners_m()))

    def spots(self) -> SpotSearch:
        """A fresh :class:`.detect.SpotSearch` of this site's marker sizes, for the dark
        :func:`.detect.find_quads` of one frame."""
        return SpotSearch(self.spot_side_px, [])

    def quad_fix(self, grey: np.ndarray, quad: Quad) -> TargetFix | int | None:
        """A fix from a marker-sized dark quad of the decimated search, the id read when
        the site does not hold it, or None (not a marker, or not measured)."""
        sides = measure_sides(grey, quad.corners_px, self.geo, self.edge_points, passes=1,
                              cells=self.codes.cells)
        if sides is None:
            return None
        read = read_marker(grey, sides.corners_norm, self.geo, self.codes)
        if read is None:
            return None
        marker_id, s, _ = read
        corners_w = self._corners.get(marker_id)
        if corners_w is None:
            return marker_id
        # corner s of the quad is the printed top-left: aruco's corner 0 (SPEC §2)
        sides = Sides(sides.corners_norm[(np.arange(4) + s) % 4], sides.edge_norm,
                      (sides.side - s) % 4, sides.stations)
        return self.solve(sides, corners_w, f"marker:{marker_id}", "id")

    def aruco_fixes(self, grey: np.ndarray, fixes: list[TargetFix], unknown: list[int],
                    max_fixes: int, spots: SpotSearch | None = None) -> int:
        """The fallback: the markers ``cv2.aruco`` reads on the full frame (or, with the
        frame's ``spots`` from the dark search, on crops about them only), the largest
        first (of equal areas the nearest the principal point), measured and solved
        into ``fixes`` (up to ``max_fixes``; a source already there is skipped), the ids
        not in the site into ``unknown``. Returns how many markers aruco read."""
        h, w = grey.shape
        boxes = None if spots is None else spots.boxes()
        crops = None if boxes is None else marker_crops(boxes, w, h)
        found = aruco_markers(grey, self.markers.dictionary, crops)
        # the largest first; of equal areas (aruco's corners are whole pixels) the one
        # nearer the principal point (the least distorted), then by id: an order of the
        # markers, not of how aruco or the crops met them
        centre = np.array([self.geo.camera.cx, self.geo.camera.cy])
        found.sort(key=lambda m: (-abs(signed_area(m[1])),
                                  float(np.hypot(*(m[1].mean(axis=0) - centre))), m[0]))
        have = {f.source for f in fixes}
        for marker_id, corners in found:
            if len(fixes) >= max_fixes:
                break
            if f"marker:{marker_id}" in have:
                continue
            got = self.aruco_fix(grey, marker_id, corners)
            if isinstance(got, int):
                if got not in unknown:
                    unknown.append(got)
            elif got is not None:
                fixes.append(got)
        return len(found)

    def aruco_fix(self, grey: np.ndarray, marker_id: int, corners_px: np.ndarray
                  ) -> TargetFix | int | None:
        """The fix of one marker aruco read (its id, its corners ``(4, 2)`` px in aruco's
        order), the id when the site does not hold it, or None: the sides not measured,
        or :func:`.detect.read_marker` of the measured outline names another id or
        corner order (at the size aruco still reads, ours may read nothing: that is no
        conflict)."""
        corners_w = self._corners.get(marker_id)
        if corners_w is None:
            return marker_id
        # aruco's corners are coarse (up to a pixel or two off), clockwise as displayed
        sign = -1 if signed_area(corners_px) > 0 else 1
        sides = measure_sides(grey, corners_px, self.geo, self.edge_points, passes=2,
                              sign=sign, cells=self.codes.cells)
        if sides is None:
            return None
        read = read_marker(grey, sides.corners_norm, self.geo, self.codes)
        if read is not None and (read[0], read[1]) != (marker_id, 0):
            return None
        return self.solve(sides, corners_w, f"marker:{marker_id}", "id")


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a`` made read-only (shared by every fix of its marker)."""
    a.setflags(write=False)
    return a


def marker_side_range_px(geo: PlanarGeometry, sizes_m: list[float]) -> tuple[float, float]:
    """``(least, most)`` px: the larger side of the box a marker of ``sizes_m`` (m) covers
    anywhere in the frame, as the fallback's spots are searched. ``least``:
    ``cv2.aruco``'s own limit (its default least perimeter, 3 % of the frame's larger
    side, over 4), less the decimated search's 2 px rounding. ``most``: the largest
    marker's diagonal at the ceiling's largest scale in px per metre over a
    :data:`SPOT_GRID` of the frame (the larger singular value of the pixel's
    derivative by the ceiling point), times :data:`SPOT_MARGIN`; infinite when no
    sampled pixel sees the ceiling."""
    cam = geo.camera
    least = max(2.0, 0.03 * max(cam.width, cam.height) / 4.0 - 2.0)
    if not sizes_m:
        return least, least
    gu, gv = SPOT_GRID
    step = min((cam.width - 1) / gu, (cam.height - 1) / gv)
    u, v = np.meshgrid(np.linspace(0, cam.width - 1 - step, gu),
                       np.linspace(0, cam.height - 1 - step, gv))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    q = [ceiling_points_vehicle(geo, cam.unproject_fast(px + d))
         for d in ((0.0, 0.0), (step, 0.0), (0.0, step))]
    A = np.stack([(q[1] - q[0]) / step, (q[2] - q[0]) / step], axis=2)   # m per px
    ok = np.isfinite(A).all(axis=(1, 2))
    if not ok.any():
        return least, float("inf")
    s_min = np.linalg.svd(A[ok], compute_uv=False)[:, -1]                # m per px
    scale = float(1.0 / max(s_min.min(), 1e-12))                          # px per m
    return least, SPOT_MARGIN * math.sqrt(2.0) * max(sizes_m) * scale
