"""Detection stages of the block method: what on the frame is a marker or a block.

* :func:`find_quads`: dark (and, if the site has bright blocks, bright) convex quads;
  a pixel belongs to a block when it is darker (brighter) than a fixed ratio of the
  ceiling's grey around it (:func:`background`), so vignetting does not matter; a 3x3
  opening removes seams before the contours are taken.
* :func:`read_markers`: each dark quad of about a marker's size on the ceiling is read by
  ``cv2.aruco`` on a crop around it (a small image: fast), corners sub-pixel.
* :func:`measure_sides`: points on the four sides' edges, undistorted, a line fitted to
  each side and the corners as the lines' intersections (normalized coordinates).

Everything returns arrays or frozen dataclasses; nothing raises per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, ceiling_points_vehicle
from ceilkit.runtime.features.lines import fit_line
from ceilkit.runtime.features.quads import MarkerDetector, Quad, detect_quads, edge_points

BG_SHRINK = 16             # background(): the frame shrunk by this factor
BG_WINDOW = 9              # background(): local max/min over this many shrunk cells
CROP_MARGIN = 0.6          # a marker's crop: its bounding box grown by this fraction
MIN_SIDE_POINTS = 4        # measure_sides: edge points each side needs
_OPEN = np.ones((3, 3), np.uint8)


def background(grey: np.ndarray, dark: bool) -> np.ndarray:
    """The ceiling's grey around each pixel ``(H, W)`` float32: the frame shrunk by
    :data:`BG_SHRINK`, its local maximum (``dark``: blocks darker than the ceiling drop
    out) or minimum taken over :data:`BG_WINDOW` cells, and grown back. Vignetting and
    exposure scale it as they scale the block, so a ratio to it is a fixed threshold."""
    h, w = grey.shape
    small = cv2.resize(grey, (max(1, w // BG_SHRINK), max(1, h // BG_SHRINK)),
                       interpolation=cv2.INTER_AREA)
    k = np.ones((BG_WINDOW, BG_WINDOW), np.uint8)
    small = cv2.dilate(small, k) if dark else cv2.erode(small, k)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)


def find_quads(grey: np.ndarray, dark: bool, ratio: float,
               others: list[np.ndarray] | None = None) -> list[Quad]:
    """Convex quads darker than ``ratio`` times the ceiling around them (``dark``) or
    brighter than ``ratio`` times it; ``others`` receives the large regions of that
    polarity that are not convex quads (a block partly occluded, a lamp of another shape).
    A 3x3 opening removes thin seams before the contours are taken."""
    bg = background(grey, dark)
    g = grey.astype(np.float32)
    mask = ((g < ratio * bg) if dark else (g > ratio * bg)).astype(np.uint8) * 255
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _OPEN)
    return detect_quads(mask, dark=False, regions=others)


def side_lengths_m(points_v: np.ndarray) -> np.ndarray:
    """``(4,)`` side lengths of a quad ``(4, 2)`` on the ceiling (side k: corner k to k+1)."""
    return np.linalg.norm(np.roll(points_v, -1, axis=0) - points_v, axis=1)


def read_markers(grey: np.ndarray, quads: list[Quad], geo: PlanarGeometry,
                 detector: MarkerDetector, sizes_m: np.ndarray, tol: float
                 ) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Markers in the crops around the dark quads whose sides on the ceiling are within
    ``tol`` (relative) of one of ``sizes_m``.

    Returns ids ``(N,)``, corners ``(N, 4, 2)`` px (aruco's order) and the indices of
    the quads read as markers."""
    h, w = grey.shape
    ids, corners, used = [], [], []
    for k, q in enumerate(quads):
        pv = ceiling_points_vehicle(geo, geo.camera.unproject(q.corners_px))
        if not np.all(np.isfinite(pv)):
            continue
        side = float(np.mean(side_lengths_m(pv)))
        if not np.any(np.abs(side / sizes_m - 1.0) < tol):
            continue
        lo, hi = q.corners_px.min(axis=0), q.corners_px.max(axis=0)
        grow = CROP_MARGIN * (hi - lo) + 4
        u0, v0 = (int(max(0, np.floor(v))) for v in lo - grow)
        u1, v1 = int(min(w, np.ceil(hi[0] + grow[0]))), int(min(h, np.ceil(hi[1] + grow[1])))
        found_ids, found = detector.detect(np.ascontiguousarray(grey[v0:v1, u0:u1]))
        for mid, c in zip(found_ids, found, strict=True):
            ids.append(int(mid))
            corners.append(c + [u0, v0])
            used.append(k)
    if not ids:
        return np.zeros(0, np.int64), np.zeros((0, 4, 2)), []
    return np.array(ids, np.int64), np.array(corners), used


@dataclass(frozen=True, eq=False)
class Sides:
    """A quad measured on its edges (normalized coordinates, distortion removed).

    Attributes:
        corners_norm: ``(4, 2)`` the side lines' intersections (corner k between side
            k-1 and side k).
        edge_norm: ``(M, 2)`` the edge points; ``side`` ``(M,)`` which side each is on.
        stations: how many stations were searched (for the share found).
    """

    corners_norm: np.ndarray
    edge_norm: np.ndarray
    side: np.ndarray
    stations: int


def _sides_once(grey: np.ndarray, corners_px: np.ndarray, geo: PlanarGeometry,
                per_side: int) -> Sides | None:
    pts, side = edge_points(grey, corners_px, per_side)
    counts = np.bincount(side, minlength=4)
    if np.any(counts < MIN_SIDE_POINTS):
        return None
    norm = geo.camera.unproject(pts)
    lines = np.array([fit_line(norm[side == k]) for k in range(4)])
    corners = np.cross(np.roll(lines, 1, axis=0), lines)       # side k-1 meets side k
    if np.any(np.abs(corners[:, 2]) < 1e-12):
        return None
    return Sides(corners[:, :2] / corners[:, 2:3], norm, side, 4 * per_side)


def measure_sides(grey: np.ndarray, corners_px: np.ndarray, geo: PlanarGeometry,
                  per_side: int) -> Sides | None:
    """The quad's sides measured on the frame (see the module docstring), twice: the
    second time about the corners the first found (a coarse contour's corners may be a
    few pixels off); None when a side has fewer than :data:`MIN_SIDE_POINTS` points."""
    first = _sides_once(grey, corners_px, geo, per_side)
    if first is None:
        return None
    again = geo.camera.distort(first.corners_norm)
    if not np.all(np.isfinite(again)):
        return first
    return _sides_once(grey, again, geo, per_side) or first
