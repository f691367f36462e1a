"""Detection stages of the block method: what on the frame is a marker or a block.

* :func:`find_quads`: dark (and, if the site has bright blocks, bright) convex quads;
  a pixel belongs to a block when it is darker (brighter) than a fixed ratio of the
  ceiling's grey around it (:func:`background`), so vignetting does not matter; a 3x3
  opening removes seams before the contours are taken.
* :func:`read_marker`: a dark quad of about a marker's size on the ceiling, once measured
  on its edges, is read from its cells (:class:`~ceilkit.runtime.features.quads.MarkerCodes`,
  the ``cv2.aruco`` dictionary's codes): no search of the frame, a fraction of
  ``cv2.aruco``'s time; corners sub-pixel from the sides' edges.
* :func:`measure_sides`: points on the four sides' edges, undistorted, a line fitted to
  each side and the corners as the lines' intersections (normalized coordinates).
* :func:`aruco_markers`: the full-resolution fallback where the decimated search finds
  no marker (markers down to ``cv2.aruco``'s own limit, about 3 px per cell, whose
  one-cell black border a decimated, opened mask breaks): ``cv2.aruco``'s default
  detector, with the site's dictionary, on the whole frame (about 2-3 ms at 640x480)
  or only on crops about the marker-sized dark spots :func:`find_quads` flagged on the
  decimated mask before its opening (:func:`marker_crops`; the same markers, a tenth
  of the time on a tiled ceiling).

Everything returns arrays or frozen dataclasses; nothing raises per frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.features.bits import popcount
from ceilkit.runtime.features.edges import remap_linear
from ceilkit.runtime.features.quads import (
    EDGE_SEARCH_PX,
    EDGE_STEP_PX,
    MIN_QUAD_AREA_PX,
    QUIET_CELLS,
    MarkerCodes,
    Quad,
    bilinear,
    edge_offsets,
    edge_points,
    edge_points_core,
    edge_stations,
    line_corners,
    marker_dictionary,
    quads_of_mask,
)
from ceilkit.runtime.features.working import decimate
from ceilkit.runtime.geometry.camera import CameraModel, distort_points, undistort_points
from ceilkit.runtime.geometry.ceiling import PlanarGeometry
from ceilkit.runtime.geometry.fits import median_of
from ceilkit.runtime.jit import arr, njit, warmer

BG_SHRINK = 16             # background(): the frame shrunk by this factor
BG_WINDOW = 9              # background(): local max/min over this many shrunk cells
MIN_MARKER_CONTRAST = 25.0  # read_marker: grey levels between the quiet ring and the border
BORDER_ERRORS = 3          # read_marker: white cells the black border may show (noise, blur)
_CELL_SUB = np.array([-0.22, 0.22])   # read_marker: samples per cell, in cells from its centre
MIN_SIDE_POINTS = 4        # measure_sides: edge points each side needs
DECIMATE = 2               # find_quads: the search runs on the frame shrunk this much
_OPEN = np.ones((3, 3), np.uint8)
_OPEN_SMALL = np.ones((2, 2), np.uint8)


_BG_KERNEL = np.ones((BG_WINDOW, BG_WINDOW), np.uint8)


def background(grey: np.ndarray, dark: bool, shrink: int = BG_SHRINK,
               scale: float = 1.0) -> np.ndarray:
    """The ceiling's grey around each pixel ``(H, W)`` float32 times ``scale``: the
    frame shrunk by ``shrink``, its local maximum (``dark``: blocks darker than the
    ceiling drop out) or minimum taken over :data:`BG_WINDOW` cells, and grown back.
    Vignetting and exposure scale it as they scale the block, so a ratio to it is a
    fixed threshold (``scale``: that ratio, applied on the shrunk frame)."""
    h, w = grey.shape
    small = cv2.resize(grey, (max(1, w // shrink), max(1, h // shrink)),
                       interpolation=cv2.INTER_AREA)
    small = cv2.dilate(small, _BG_KERNEL) if dark else cv2.erode(small, _BG_KERNEL)
    return cv2.resize(small.astype(np.float32) * np.float32(scale), (w, h),
                      interpolation=cv2.INTER_LINEAR)


def find_quads(grey: np.ndarray, dark: bool, ratio: float,
               others: list[np.ndarray] | None = None,
               small: np.ndarray | None = None,
               spots: SpotSearch | None = None) -> list[Quad]:
    """Convex quads darker than ``ratio`` times the ceiling around them (``dark``) or
    brighter than ``ratio`` times it; ``others`` receives the large regions of that
    polarity that are not convex quads (a block partly occluded, a lamp of another shape);
    ``spots`` (a :class:`SpotSearch`) receives the mask *before* the opening, whose
    marker-sized parts (:meth:`SpotSearch.boxes`) are where the fallback's ``cv2.aruco``
    may read a marker the opening broke.

    The search runs on the frame decimated by :data:`DECIMATE` (``small``, from
    :func:`~ceilkit.runtime.features.working.decimate`: whole boxes, so that the
    factor is exact on both axes of an odd-sized frame; may be passed to share it
    between polarities); the corners come back in full-resolution pixels, coarse
    (``approxPolyDP``'s vertices: pixels off;
    :func:`~ceilkit.runtime.features.quads.sharpen_quad` puts them within a pixel,
    :func:`measure_sides` refines them on the full frame). A 3x3 opening (full
    resolution; a 2x2 one when decimated) removes thin seams before the contours are taken."""
    if small is None:
        small = decimate(grey, DECIMATE)
    f = float(grey.shape[1] // small.shape[1])
    bg = background(small, dark, max(1, int(round(BG_SHRINK / f))), ratio)
    mask = cv2.compare(small.astype(np.float32), bg, cv2.CMP_LT if dark else cv2.CMP_GT)
    if spots is not None:       # kept unopened; its spots are taken only if needed
        spots.masks.append((mask, f))
    if f < 1.5:
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, _OPEN)
    else:      # an even kernel: erode and dilate about opposite anchors (no shift)
        mask = cv2.dilate(cv2.erode(mask, _OPEN_SMALL, anchor=(0, 0)), _OPEN_SMALL,
                          anchor=(1, 1))
    found: list[np.ndarray] = []
    quads = quads_of_mask(mask, min_area_px=MIN_QUAD_AREA_PX / (f * f), regions=found,
                          sharpen=False)
    if others is not None:
        others.extend((c * f).astype(np.float32) for c in found)
    if f == 1:
        return quads
    # pixel centres: full-resolution u = f * u_small + (f - 1) / 2
    o = 0.5 * (f - 1)
    return [Quad(q.corners_px * f + o, q.area_px * f * f, q.at_border,
                 q.contour_px * f + o, f) for q in quads]


@functools.lru_cache(maxsize=8)
def _aruco_detector(dictionary: str, crops: bool = False) -> cv2.aruco.ArucoDetector:
    """``cv2.aruco``'s detector for ``dictionary`` with its default parameters (its
    thresholds at several scales: what it reads, the fallback reads); with ``crops`` a
    second one, whose parameters :func:`aruco_markers` sets per crop."""
    return cv2.aruco.ArucoDetector(marker_dictionary(dictionary),
                                   cv2.aruco.DetectorParameters())


class SpotSearch(NamedTuple):
    """What :func:`find_quads` flags for the marker fallback: ``masks`` receives its
    unopened masks with their decimation factors; :meth:`boxes` are the spots of a
    marker's size on them, ``side_px = (least, most)`` px."""

    side_px: tuple[float, float]
    masks: list[tuple[np.ndarray, float]]

    def boxes(self) -> list[tuple[int, int, int, int]] | None:
        """``(x0, y0, x1, y1)`` full-resolution pixel boxes (end exclusive) of the masks'
        connected parts whose larger side lies in ``side_px`` (:func:`_spot_boxes`);
        None when a mask has more than :data:`MAX_SPOT_CONTOURS` parts (read the whole
        frame: crops would cover most of it)."""
        out: list[tuple[int, int, int, int]] = []
        for mask, f in self.masks:
            got = _spot_boxes(mask, f, self.side_px)
            if got is None:
                return None
            out.extend(got)
        return out


MAX_SPOT_CONTOURS = 256
"""A mask of more parts than this is not searched for spots (:meth:`SpotSearch.boxes`):
on configs/block at 1280x720 about 450 (speckle), and their crops covered 90 % of
the frame."""


def _spot_boxes(mask: np.ndarray, f: float, side_px: tuple[float, float]
                ) -> list[tuple[int, int, int, int]] | None:
    """The full-resolution boxes of ``mask``'s 8-connected parts (a frame decimated by
    ``f``) whose larger side, times ``f``, lies within ``side_px``: the bounding boxes
    of every contour, outer and inner (a part inside another's hole too; a third of
    ``connectedComponentsWithStats``' time); None over :data:`MAX_SPOT_CONTOURS`."""
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    if len(contours) > MAX_SPOT_CONTOURS:
        return None
    k, out = int(f), []
    one = f < side_px[0]        # a contour of one point (one pixel) is then too small
    for c in contours:
        if one and len(c) == 1:
            continue
        x, y, w, h = cv2.boundingRect(c)
        if side_px[0] <= max(w, h) * f <= side_px[1]:
            out.append((x * k, y * k, (x + w) * k, (y + h) * k))
    return out


CROP_MARGIN_PX = 16
"""A fallback crop reaches this far beyond its spot's box (px, plus a quarter of the
box's larger side): past ``cv2.aruco``'s largest adaptive-threshold window (23 px, so
every pixel of the marker is thresholded as on the whole frame) and its 3 px border
rule."""


CROP_MAX_SHARE = 0.5
"""Crops covering more of the frame than this are read as the whole frame (one pass
costs no more: a mask of many marker-sized parts)."""


def marker_crops(boxes: list[tuple[int, int, int, int]], width: int, height: int
                 ) -> list[tuple[int, int, int, int]] | None:
    """``boxes`` grown by :data:`CROP_MARGIN_PX` and a quarter of their larger side,
    clipped to the ``width`` x ``height`` frame, and merged where they overlap (so that
    no marker is read in two crops): ``(x0, y0, x1, y1)``, end exclusive; None (read
    the whole frame) when they cover more than :data:`CROP_MAX_SHARE` of it."""
    grown = []
    for x0, y0, x1, y1 in boxes:
        m = CROP_MARGIN_PX + max(x1 - x0, y1 - y0) // 4
        grown.append([max(0, x0 - m), max(0, y0 - m), min(width, x1 + m), min(height, y1 + m)])
    merged = True
    while merged:
        merged = False
        for i in range(len(grown)):
            for j in range(len(grown) - 1, i, -1):
                a, b = grown[i], grown[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    grown[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]),
                                max(a[3], b[3])]
                    del grown[j]
                    merged = True
    if sum((b[2] - b[0]) * (b[3] - b[1]) for b in grown) > CROP_MAX_SHARE * width * height:
        return None
    return [tuple(b) for b in grown]


def aruco_markers(grey: np.ndarray, dictionary: str,
                  crops: list[tuple[int, int, int, int]] | None = None
                  ) -> list[tuple[int, np.ndarray]]:
    """The markers ``cv2.aruco``'s default detector reads on the full frame, or with
    ``crops`` (:func:`marker_crops`) on those parts of it only, its perimeter limits
    kept at the full frame's pixels: ``(id, corners (4, 2) px)`` in aruco's corner
    order (the printed top-left, top-right, bottom-right, bottom-left: SPEC §2's corner
    k), coarse (no sub-pixel refinement: :func:`measure_sides` measures the sides). An
    id read twice is left out (which of the two is the site's marker is not known)."""
    got: list[tuple[int, np.ndarray]] = []
    if crops is None:
        _read(_aruco_detector(dictionary), grey, 0, 0, got)
    else:
        h, w = grey.shape
        det, full = _aruco_detector(dictionary, True), cv2.aruco.DetectorParameters()
        for x0, y0, x1, y1 in crops:
            p = cv2.aruco.DetectorParameters()
            scale = max(w, h) / max(x1 - x0, y1 - y0, 1)
            p.minMarkerPerimeterRate = full.minMarkerPerimeterRate * scale
            p.maxMarkerPerimeterRate = full.maxMarkerPerimeterRate * scale
            det.setDetectorParameters(p)
            _read(det, grey[y0:y1, x0:x1], x0, y0, got)
    seen = [i for i, _ in got]
    return [(i, c) for i, c in got if seen.count(i) == 1]


def _read(det: cv2.aruco.ArucoDetector, grey: np.ndarray, x0: int, y0: int,
          got: list[tuple[int, np.ndarray]]) -> None:
    """The markers ``det`` reads on ``grey`` (a crop whose top-left is pixel ``(x0,
    y0)`` of the frame) into ``got``, in frame pixels."""
    corners, ids, _ = det.detectMarkers(grey)
    if ids is None or len(corners) == 0:
        return
    off = np.array([x0, y0], np.float64)
    got.extend((int(i), np.asarray(c, np.float64).reshape(4, 2) + off)
               for i, c in zip(np.asarray(ids).ravel(), corners, strict=True))


def fit_side_lines(points: np.ndarray, side: np.ndarray) -> np.ndarray:
    """``(4, 3)`` total-least-squares lines ``(a, b, c)``, ``|(a, b)| = 1``, of the points
    ``(M, 2)`` of each side ``side`` ``(M,)`` (0..3) at once (every side needs two)."""
    n = np.bincount(side, minlength=4).astype(float)
    mx = np.bincount(side, points[:, 0], 4) / n
    my = np.bincount(side, points[:, 1], 4) / n
    dx, dy = points[:, 0] - mx[side], points[:, 1] - my[side]
    sxx = np.bincount(side, dx * dx, 4)
    syy = np.bincount(side, dy * dy, 4)
    sxy = np.bincount(side, dx * dy, 4)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)        # the major axis: the side's run
    a, b = -np.sin(theta), np.cos(theta)
    return np.stack([a, b, -(a * mx + b * my)], axis=1)


def sharpen_corners(grey: np.ndarray, corners_px: np.ndarray, per_side: int = 8
                    ) -> np.ndarray | None:
    """A quad's corners ``(4, 2)`` px as its sides' edge lines meet, on ``grey`` itself
    (no lens model: straight sides over a short run); None if a side shows fewer than
    three edge points."""
    pts, side = edge_points(grey, corners_px, per_side)
    if np.any(np.bincount(side, minlength=4) < 3):
        return None
    return line_corners(fit_side_lines(pts, side))


_NEXT_CORNER = np.array([1, 2, 3, 0])      # corner k+1 of a quad


def side_lengths_m(points_v: np.ndarray) -> np.ndarray:
    """``(4,)`` side lengths of a quad ``(4, 2)`` on the ceiling (side k: corner k to k+1)."""
    d = points_v[_NEXT_CORNER] - points_v
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


@functools.lru_cache(maxsize=8)
def _cell_grid(n: int) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """read_marker's samples ``(k*k, 1, 2)`` float32 (column, row in cells of an n-cell
    black square, its quiet ring included), k, the samples per side, and the flat
    indices of the quiet ring's cells and of the black border's (read-only)."""
    t = (np.arange(n + 2 * QUIET_CELLS) - QUIET_CELLS + 0.5)[:, None] + _CELL_SUB[None, :]
    cols, rows = np.meshgrid(t.ravel(), t.ravel())
    grid = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
    g = n + 2 * QUIET_CELLS
    ring = np.ones((g, g), bool)
    ring[1:-1, 1:-1] = False
    border = np.zeros((g, g), bool)
    border[1:-1, 1:-1] = True
    border[2:-2, 2:-2] = False
    out = (grid.astype(np.float32), t.size, np.flatnonzero(ring), np.flatnonzero(border))
    for a in (out[0], out[2], out[3]):
        a.flags.writeable = False
    return out


def read_marker(grey: np.ndarray, corners_norm: np.ndarray, geo: PlanarGeometry,
                codes: MarkerCodes) -> tuple[int, int, int] | None:
    """The marker whose black square has the corners ``corners_norm`` ``(4, 2)``
    (normalized, a quad's order), read from its cells.

    A homography from the printed grid (black border included, with the white quiet
    ring around it) to the corners gives each cell's centre on the undistorted image;
    the lens puts them on the frame, where 2x2 samples per cell are averaged
    (bilinear). The threshold is half way between the border's grey and the quiet
    ring's; a border with more than :data:`BORDER_ERRORS` white cells is not a marker.

    Returns:
        ``(id, s, errors)`` (:meth:`MarkerCodes.identify`: corner ``s`` of the quad is
        the printed top-left, aruco's corner 0), or None.
    """
    n = codes.cells                                      # cells across the black square
    square = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)
    H = cv2.getPerspectiveTransform(square, np.asarray(corners_norm, np.float32))
    found, errors = read_core(arr(grey, np.uint8), H, _cell_read(codes), *geo.camera.lens)
    if found < 0 or errors > codes.max_errors:
        return None
    i, s = divmod(found, 4)
    return i, s, errors


@functools.lru_cache(maxsize=8)
def _cell_read(codes: MarkerCodes) -> CellRead:
    """:func:`read_core`'s constants for one dictionary (its grid and its codes)."""
    grid, _, ring, border = _cell_grid(codes.cells)
    return CellRead(arr(grid.reshape(-1, 2), np.float32), arr(ring, np.int64),
                    arr(border, np.int64), arr(codes.packed, np.uint64))


class CellRead(NamedTuple):
    """What :func:`read_marker` reads the cells with: ``grid (k*k, 2)`` float32 samples
    (column, row in cells, :func:`_cell_grid`), the flat indices of the quiet ring's
    cells ``ring`` and of the black border's ``border``, and the dictionary's codes
    ``packed (4 ids,)`` uint64 (:attr:`~ceilkit.runtime.features.quads.MarkerCodes.packed`)."""

    grid: np.ndarray
    ring: np.ndarray
    border: np.ndarray
    packed: np.ndarray


@njit
def read_core(grey, H, cells, code, lens):  # pragma: no cover - compiled
    """:func:`read_marker` after its homography ``H`` (3, 3), in one compiled loop:
    ``(k, errors)``, ``k`` the nearest code's row of ``cells.packed`` (id 4 + s), -1
    where the samples leave the lens, the contrast is short or the border is broken.

    The samples' steps are OpenCV's own, number for number: ``perspectiveTransform``
    of float32 points (a double homography, float32 out), the lens
    (:func:`~ceilkit.runtime.geometry.camera.distort_points`) to float32 maps, and
    ``remap``'s bilinear read with a replicated border
    (:func:`~ceilkit.runtime.features.edges.remap_linear`: OpenCV 5's float
    interpolation; releases before it rounded the sample's place to 1/32 px, a grey
    level apart at most)."""
    n = cells.grid.shape[0]
    norm = np.empty((n, 2))
    for i in range(n):
        x, y = np.float64(cells.grid[i, 0]), np.float64(cells.grid[i, 1])
        w = x * H[2, 0] + y * H[2, 1] + H[2, 2]
        if abs(w) > 1.1920928955078125e-07:
            w = 1.0 / w
            norm[i, 0] = np.float32((x * H[0, 0] + y * H[0, 1] + H[0, 2]) * w)
            norm[i, 1] = np.float32((x * H[1, 0] + y * H[1, 1] + H[1, 2]) * w)
        else:
            norm[i, 0] = norm[i, 1] = 0.0
    px = np.empty((n, 2))
    distort_points(norm, code, lens, px)
    k = int(round(math.sqrt(n)))
    g = k // 2
    cell = np.zeros(g * g, np.float32)
    for i in range(n):
        u, v = np.float32(px[i, 0]), np.float32(px[i, 1])
        if not (np.isfinite(u) and np.isfinite(v)):
            return -1, 0
        r, c = i // k, i % k
        cell[(r // 2) * g + c // 2] += np.float32(remap_linear(grey, u, v))
    for j in range(g * g):
        cell[j] *= np.float32(0.25)
    white = np.float64(median_of(cell[cells.ring]))   # multiples of 1/4: exact either way
    on_border = cell[cells.border]
    black = np.float64(median_of(on_border))
    if white - black < MIN_MARKER_CONTRAST:
        return -1, 0
    thr = np.float32(0.5 * (white + black))        # as numpy compares a float32 array
    if np.count_nonzero(on_border > thr) > BORDER_ERRORS:
        return -1, 0
    word = np.uint64(0)
    b = 0
    for r in range(2, g - 2):
        for c in range(2, g - 2):
            if cell[r * g + c] > thr:
                word |= np.uint64(1) << np.uint64(b)
            b += 1
    return _nearest_code(cells.packed, word)


@njit
def _nearest_code(packed, word):  # pragma: no cover - compiled
    """``(k, bits)``: the first row of ``packed`` with the fewest bits differing from
    ``word`` (:meth:`~ceilkit.runtime.features.quads.MarkerCodes.identify`)."""
    best, errors = -1, 65
    for i in range(packed.size):
        c = popcount(packed[i] ^ word)
        if c < errors:
            best, errors = i, c
    return best, errors


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


class EdgeSearch(NamedTuple):
    """The edge passes of :func:`measure_core` as it reads them: offsets across a side
    ``first (K,)`` px on the first pass and ``rest`` after, stations along it ``t (S,)``
    (fractions of the side, :func:`~ceilkit.runtime.features.quads.edge_stations`), the
    profile's sampling ``step_px``, the edges' polarity ``sign`` (-1, 0, +1) and a
    marker's ``cells`` across its black square (0: a plain block;
    :func:`~ceilkit.runtime.features.quads.edge_points`')."""

    first: np.ndarray
    rest: np.ndarray
    t: np.ndarray
    step_px: float
    sign: int
    cells: float = 0.0


class SidesOut(NamedTuple):
    """The arrays :func:`measure_core` writes: ``corners (4, 2)``, ``edge (4 S, 2)``
    (normalized) and ``side (4 S,)`` int64."""

    corners: np.ndarray
    edge: np.ndarray
    side: np.ndarray

    @staticmethod
    def empty(per_side: int) -> SidesOut:
        """Fresh arrays for ``per_side`` stations a side."""
        return SidesOut(np.empty((4, 2)), np.empty((4 * per_side, 2)),
                        np.empty(4 * per_side, np.int64))


def edge_search(per_side: int, search_px: float, sign: int = 0, cells: int = 0
                ) -> EdgeSearch:
    """The :class:`EdgeSearch` of ``per_side`` stations a side, the first pass
    ``search_px`` across each side, the next ones :data:`EDGE_SEARCH_PX`; ``cells`` a
    marker's cells across its black square (0: a plain block)."""
    rest, t = edge_stations(per_side, EDGE_SEARCH_PX)
    first = rest if float(search_px) == EDGE_SEARCH_PX else edge_offsets(float(search_px))
    return EdgeSearch(first, rest, t, float(EDGE_STEP_PX), int(sign), float(cells))


def measure_sides(grey: np.ndarray, corners_px: np.ndarray, geo: PlanarGeometry,
                  per_side: int, passes: int = 2, search_px: float = EDGE_SEARCH_PX,
                  sign: int = 0, cells: int = 0) -> Sides | None:
    """The quad's sides measured on the frame (see the module docstring), ``passes``
    times: each pass about the corners the previous one found (a coarse contour's
    corners, a predicted quad's, may be a few pixels off); the first pass looks for
    the edges ``search_px`` across each side, the next ones :data:`EDGE_SEARCH_PX`.
    None when a side has fewer than :data:`MIN_SIDE_POINTS` points. The passes before
    the last fit the sides in pixels (no lens model: straight over a short run, and
    only the next pass's stations depend on them). ``sign``: the edges' polarity
    (:func:`~ceilkit.runtime.features.quads.edge_points`'; 0: either); ``cells``: a
    marker's cells across its black square, its border included (the level of each
    edge read half a cell either side of it), 0 for a plain block. One compiled call
    (:func:`measure_core`)."""
    p0 = arr(corners_px, np.float64).reshape(4, 2)
    if not np.isfinite(p0).all():
        return None
    code, lens = geo.camera.lens
    out = SidesOut.empty(per_side)
    n = measure_core(arr(grey, np.uint8), p0, passes,
                     edge_search(per_side, search_px, sign, cells), code, lens, out)
    if n < 0:
        return None
    return Sides(out.corners, out.edge[:n], out.side[:n], 4 * per_side)


@njit
def measure_core(grey, p0, passes, search, code, lens, out):  # pragma: no cover
    """:func:`measure_sides` of the quad ``p0 (4, 2)`` px (finite), ``passes`` edge
    passes as ``search`` (an :class:`EdgeSearch`) says, through the lens ``code, lens``
    (:attr:`.CameraModel.lens`): the corners (normalized) into ``out.corners (4, 2)``,
    the edge points (normalized) and their sides into the first ``count`` rows of
    ``out.edge (4 S, 2)``, ``out.side (4 S,)`` (a :class:`SidesOut`); returns
    ``count``, or -1 (no measurement). A last pass that loses a side keeps the
    previous pass's points (through the lens). (numba keys this loop's cache on this
    file's contents only: a change to ``quads.edge_points_core``, compiled into it, is
    taken only once this file changes too.)"""
    corners, edge, side = out.corners, out.edge, out.side
    cur = p0.copy()
    lines = np.empty((4, 3))
    prev_pts = np.empty((0, 2))
    prev_side = np.empty(0, np.int64)
    have_prev = False
    for k in range(passes):
        pts, sd, n = edge_points_core(grey, cur, search.first if k == 0 else search.rest,
                                      search.t, search.step_px, search.sign, search.cells)
        if _too_few(sd, n):
            if k == passes - 1 and have_prev:
                return _lens_sides(prev_pts, prev_side, code, lens, lines, corners, edge, side)
            return -1
        if k == passes - 1:
            got = _lens_sides(pts[:n], sd[:n], code, lens, lines, corners, edge, side)
            if got < 0 and have_prev:
                return _lens_sides(prev_pts, prev_side, code, lens, lines, corners, edge,
                                   side)
            return got
        _fit_lines(pts[:n], sd[:n], lines)
        if not _line_corners(lines, cur):
            return -1
        prev_pts, prev_side, have_prev = pts[:n], sd[:n], True
    return -1


@njit
def _too_few(side, n):  # pragma: no cover - compiled
    """Whether a side of the first ``n`` points has fewer than MIN_SIDE_POINTS."""
    counts = np.zeros(4, np.int64)
    for i in range(n):
        counts[side[i]] += 1
    return counts.min() < MIN_SIDE_POINTS


@njit
def _lens_sides(pts, sd, code, lens, lines, corners, edge, side):  # pragma: no cover
    """The points ``pts`` (px) through the lens into ``edge``, their sides' lines met
    into ``corners``: the count, or -1 when two neighbouring sides are parallel."""
    n = pts.shape[0]
    norm = edge[:n]
    undistort_points(pts, code, lens, norm)
    side[:n] = sd
    _fit_lines(norm, sd, lines)
    return n if _line_corners(lines, corners) else -1


@njit
def _fit_lines(points, side, lines):  # pragma: no cover - compiled
    """:func:`fit_side_lines` into ``lines (4, 3)``."""
    s = np.zeros((4, 6))                       # n, Σx, Σy and the centred moments
    for i in range(points.shape[0]):
        k = side[i]
        s[k, 0] += 1.0
        s[k, 1] += points[i, 0]
        s[k, 2] += points[i, 1]
    for k in range(4):
        s[k, 1] /= s[k, 0]
        s[k, 2] /= s[k, 0]
    for i in range(points.shape[0]):
        k = side[i]
        dx, dy = points[i, 0] - s[k, 1], points[i, 1] - s[k, 2]
        s[k, 3] += dx * dx
        s[k, 4] += dy * dy
        s[k, 5] += dx * dy
    for k in range(4):
        theta = 0.5 * math.atan2(2.0 * s[k, 5], s[k, 3] - s[k, 4])
        a, b = -math.sin(theta), math.cos(theta)
        lines[k, 0], lines[k, 1], lines[k, 2] = a, b, -(a * s[k, 1] + b * s[k, 2])


@njit
def _line_corners(lines, out):  # pragma: no cover - compiled
    """:func:`~ceilkit.runtime.features.quads.line_corners` into ``out (4, 2)``;
    False (``out`` partly written) when two neighbouring sides are parallel."""
    a0, b0, c0 = lines[3, 0], lines[3, 1], lines[3, 2]
    for k in range(4):
        a1, b1, c1 = lines[k, 0], lines[k, 1], lines[k, 2]
        w = a0 * b1 - b0 * a1
        if abs(w) < 1e-12:
            return False
        out[k, 0] = (b0 * c1 - c0 * b1) / w
        out[k, 1] = (c0 * a1 - a0 * c1) / w
        a0, b0, c0 = a1, b1, c1
    return True


CONTRAST_T = (0.3, 0.5, 0.7)   # step_contrast: stations along each side
CONTRAST_INSET = 0.1           # ... inwards/outwards, share of the way to the centre


def step_contrast(grey: np.ndarray, corners_px: np.ndarray) -> float:
    """The grey just inside a quad ``(4, 2)`` px over the grey just outside it (medians
    of 12 bilinear samples each, :data:`CONTRAST_INSET` of the way from three points of
    every side towards and away from the centre): below 1 for a dark block or a
    marker's black border on the ceiling, above 1 for a bright block. NaN when the
    outside reads black. One compiled call (:func:`contrast_core`)."""
    return contrast_core(arr(grey, np.uint8), arr(corners_px, np.float64).reshape(4, 2))


@njit
def contrast_core(grey, corners):  # pragma: no cover - compiled
    """:func:`step_contrast` (samples bilinear in float, the frame's edge replicated)."""
    inside, outside = rim_samples(grey, corners)
    inside.sort()
    outside.sort()
    a, b = 0.5 * (inside[5] + inside[6]), 0.5 * (outside[5] + outside[6])
    return a / b if b > 0 else np.nan


@njit
def rim_samples(grey, corners):  # pragma: no cover - compiled
    """``(inside (12,), outside (12,))``: the grey just inside and just outside a quad
    ``(4, 2)`` px, :data:`CONTRAST_INSET` of the way from three points of every side
    (:data:`CONTRAST_T`) towards and away from its centre (bilinear in float, the
    frame's edge replicated)."""
    h, w = grey.shape
    cx = 0.25 * (corners[0, 0] + corners[1, 0] + corners[2, 0] + corners[3, 0])
    cy = 0.25 * (corners[0, 1] + corners[1, 1] + corners[2, 1] + corners[3, 1])
    inside, outside = np.empty(12), np.empty(12)
    for k in range(4):
        n = (k + 1) % 4
        for j in range(3):
            f = CONTRAST_T[j]
            ox = corners[k, 0] + f * (corners[n, 0] - corners[k, 0])
            oy = corners[k, 1] + f * (corners[n, 1] - corners[k, 1])
            sx, sy = CONTRAST_INSET * (cx - ox), CONTRAST_INSET * (cy - oy)
            inside[3 * k + j] = bilinear(grey, ox + sx, oy + sy, w, h)
            outside[3 * k + j] = bilinear(grey, ox - sx, oy - sy, w, h)
    return inside, outside


_WARM_READ = CellRead(arr(np.zeros((16, 2)), np.float32), arr(np.arange(4), np.int64),
                      arr(np.arange(4), np.int64), arr(np.zeros(4), np.uint64))


@warmer
def _warm() -> None:
    g = np.zeros((40, 40), np.uint8)
    g[10:30, 10:30] = 200
    sq = np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0]])
    step_contrast(g, sq)
    for cam in (CameraModel.pinhole(40, 40, 20.0),
                CameraModel.pinhole(40, 40, 20.0, dist=[0.1, 0, 0, 0, 0])):
        geo = PlanarGeometry(cam, np.eye(3), np.zeros(3), 3.0)
        measure_sides(g, sq, geo, 4, passes=2, search_px=4.0)
        measure_sides(g, sq, geo, 4, passes=2, search_px=4.0, sign=-1)
        read_core(arr(g, np.uint8), np.eye(3), _WARM_READ, *cam.lens)
