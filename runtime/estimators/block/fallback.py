"""Markers for the block method: read on a dark quad of the decimated search
(:meth:`MarkerReader.quad_fix`), and the full-resolution fallback (issue 36, option
``marker_fallback``: :meth:`MarkerReader.aruco_fixes`).

The quad search runs on the frame decimated by 2 and opened (:func:`.detect.find_quads`):
a marker of about 3 px per cell (a 16 cm AprilTag 36h11 1.9 m away at f = 310 px) has a
one-cell black border there of 1.6 px, which the opening breaks, so no quad. Where the
decimated search gave no marker fix, ``cv2.aruco``'s default detector reads the full
frame (:func:`.detect.aruco_markers`, the site's dictionary); each marker it reads is
measured on its edges about aruco's corners (two passes, the edges searched dark inside
only: a cell away the first inner cells' edges and the quiet ring's are of the other
polarity), read again by :func:`.detect.read_marker` as a check, and solved as any
marker (the caller's ``solve``). aruco's corner k is SPEC §2's corner k.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.block.detect import (
    Sides,
    aruco_markers,
    measure_sides,
    read_marker,
)
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.features.quads import MarkerCodes, Quad, signed_area

Solve = Callable[[Sides, np.ndarray, str, str], Any]
"""``solve(sides, corners_w, source, resolved_by)``: the caller's fix, or None."""


class MarkerReader:
    """The site's markers read and solved for the block method (see module).

    Args:
        geo: the rig and ceiling.
        markers: the site's ``markers`` section.
        codes: its dictionary's codes (the check read).
        edge_points: edge stations per side (the block method's option).
        solve: the block method's solve of measured sides.
    """

    def __init__(self, geo: PlanarGeometry, markers: Any, codes: MarkerCodes,
                 edge_points: int, solve: Solve) -> None:
        self.geo, self.markers, self.codes = geo, markers, codes
        self.edge_points, self.solve = int(edge_points), solve

    def quad_fix(self, grey: np.ndarray, quad: Quad) -> Any:
        """A fix from a marker-sized dark quad of the decimated search, the id read when
        the site does not hold it, or None (not a marker, or not measured)."""
        sides = measure_sides(grey, quad.corners_px, self.geo, self.edge_points, passes=1)
        if sides is None:
            return None
        read = read_marker(grey, sides.corners_norm, self.geo, self.codes)
        if read is None:
            return None
        marker_id, s, _ = read
        pose = self.markers.pose(marker_id)
        if pose is None:
            return marker_id
        # corner s of the quad is the printed top-left: aruco's corner 0 (SPEC §2)
        sides = Sides(sides.corners_norm[(np.arange(4) + s) % 4], sides.edge_norm,
                      (sides.side - s) % 4, sides.stations)
        return self.solve(sides, pose.corners_m(), f"marker:{marker_id}", "id")

    def aruco_fixes(self, grey: np.ndarray, fixes: list[Any], unknown: list[int],
                    max_fixes: int) -> int:
        """The fallback: the markers ``cv2.aruco`` reads on the full frame, the largest
        first, measured and solved into ``fixes`` (up to ``max_fixes``; a source already
        there is skipped), the ids not in the site into ``unknown``. Returns how many
        markers aruco read."""
        found = aruco_markers(grey, self.markers.dictionary)
        found.sort(key=lambda m: -abs(signed_area(m[1])))
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

    def aruco_fix(self, grey: np.ndarray, marker_id: int, corners_px: np.ndarray) -> Any:
        """The fix of one marker aruco read (its id, its corners ``(4, 2)`` px in aruco's
        order), the id when the site does not hold it, or None: the sides not measured,
        or :func:`.detect.read_marker` of the measured outline names another id or
        corner order (at the size aruco still reads, ours may read nothing: that is no
        conflict)."""
        pose = self.markers.pose(marker_id)
        if pose is None:
            return marker_id
        # aruco's corners are coarse (up to a pixel or two off), clockwise as displayed
        sign = -1 if signed_area(corners_px) > 0 else 1
        sides = measure_sides(grey, corners_px, self.geo, self.edge_points, passes=2,
                              sign=sign)
        if sides is None:
            return None
        read = read_marker(grey, sides.corners_norm, self.geo, self.codes)
        if read is not None and (read[0], read[1]) != (marker_id, 0):
            return None
        return self.solve(sides, pose.corners_m(), f"marker:{marker_id}", "id")
