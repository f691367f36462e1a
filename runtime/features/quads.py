"""Quadrilaterals on the ceiling: printed fiducial markers and plain blocks in a grey frame.

* Markers (SPEC §2 ``markers``): :class:`MarkerDetector` wraps ``cv2.aruco.ArucoDetector``
  with sub-pixel corner refinement; corners come in aruco's order (the printed image's
  top-left, top-right, bottom-right, bottom-left as the camera sees it).
* Plain blocks (SPEC §2 ``blocks``): :func:`detect_quads` thresholds the frame at a level
  between the block and the ceiling around it, takes the outer contours, and keeps the
  convex four-sided ones (``approxPolyDP``); the caller checks their size and shape on
  the ceiling through the lens and rig.
* :class:`MarkerCodes` reads a marker from its sampled cells once its outline is known
  (the same dictionary as ``cv2.aruco``, without its search over the frame).
* :func:`edge_points` measures, along each side of a coarse quad, sub-pixel points of the
  strongest grey step: the side's own evidence, many points instead of one corner.

Pixels are in the image's convention (SPEC §1: origin at the centre of the top-left pixel);
everything here is in distorted pixels, as captured (the lens model undistorts later).

Example::

    det = MarkerDetector("DICT_APRILTAG_36h11")
    ids, corners_px = det.detect(grey)              # (N,), (N, 4, 2)
    quads = detect_quads(grey, dark=True)           # list of Quad
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.jit import arr, njit, warmer

DICTIONARY_NAMES = tuple(sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_")))
"""Every dictionary name ``cv2.aruco`` knows (``DICT_4X4_50`` ... ``DICT_APRILTAG_36h11``)."""

QUIET_CELLS = 1            # white margin printed around a marker, in cells
MIN_QUAD_AREA_PX = 150.0   # smaller contours are noise or texture
POLY_EPS_RATE = 0.04       # approxPolyDP tolerance, fraction of the perimeter
SIDE_FIT_KEEP = 0.7        # detect_quads: the middle share of each side fitted to its line
BORDER_PX = 2.0            # a quad this close to the image edge may be cut by it
EDGE_SEARCH_PX = 3.0       # edge_points: how far across the side a step is looked for
THRESH_WIN_PX = 23        # aruco's adaptive threshold window (one scale)
EDGE_STEP_PX = 0.5         # edge_points: sampling step across the side
EDGE_END_SKIP = 0.15       # edge_points: fraction of each side left out at the corners
_NEXT = np.array([1, 2, 3, 0])      # corner k+1 of a quad


@functools.lru_cache(maxsize=16)
def marker_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The ``cv2.aruco`` dictionary called ``name`` (e.g. ``DICT_APRILTAG_36h11``).

    Raises:
        ConfigError: ``markers.dictionary`` for a name OpenCV does not know.
    """
    if name not in DICTIONARY_NAMES:
        raise ConfigError(None, "markers.dictionary",
                          f"unknown aruco dictionary {name!r} (e.g. DICT_APRILTAG_36h11, "
                          "DICT_4X4_50)")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def square_cells(name: str) -> int:
    """Cells across a marker's black square of the dictionary ``name``, its border
    included: the code's bits + 2."""
    return int(marker_dictionary(name).markerSize) + 2


@functools.lru_cache(maxsize=256)
def marker_cells(name: str, marker_id: int) -> np.ndarray:
    """The printed marker ``(N, N)`` as 1 (white) / 0 (black) cells, its black border
    included (N = bits + 2), row 0 the printed image's top, read-only.

    Raises:
        ConfigError: an unknown dictionary, or an id beyond the dictionary's size.
    """
    d = marker_dictionary(name)
    n_ids = int(d.bytesList.shape[0])
    if not 0 <= int(marker_id) < n_ids:
        raise ConfigError(None, "markers.poses",
                          f"marker id {marker_id} is not in {name} (ids 0..{n_ids - 1})")
    n = square_cells(name)
    cells = (cv2.aruco.generateImageMarker(d, int(marker_id), n) // 255).astype(np.uint8)
    cells.setflags(write=False)
    return cells


class MarkerDetector:
    """``cv2.aruco.ArucoDetector`` for one dictionary, corners refined to sub-pixel.

    Args:
        dictionary: a name of :data:`DICTIONARY_NAMES`.
        refine_win_px: half size of the sub-pixel corner search window, px.
    """

    def __init__(self, dictionary: str, refine_win_px: int = 3) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = int(refine_win_px)
        params.cornerRefinementMinAccuracy = 0.01
        params.cornerRefinementMaxIterations = 50
        params.adaptiveThreshWinSizeMin = THRESH_WIN_PX   # one scale: ~8x faster
        params.adaptiveThreshWinSizeMax = THRESH_WIN_PX
        self.dictionary = dictionary
        self._detector = cv2.aruco.ArucoDetector(marker_dictionary(dictionary), params)

    def detect(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Markers in a ``(H, W)`` uint8 frame: ids ``(N,)`` int and corners ``(N, 4, 2)``
        px in aruco's order (printed top-left, top-right, bottom-right, bottom-left)."""
        corners, ids, _ = self._detector.detectMarkers(grey)
        if ids is None or len(corners) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 2))
        pts = np.array([np.asarray(c, float).reshape(4, 2) for c in corners])
        return np.asarray(ids, dtype=np.int64).ravel(), pts


class MarkerCodes:
    """Every code of one ``cv2.aruco`` dictionary, for reading a marker's bits directly.

    Where a marker's outline is already known (a dark quad measured on its edges), its
    cells can be sampled and matched here instead of running ``cv2.aruco``'s candidate
    search over the frame: the same dictionary, a fraction of the time.

    Args:
        dictionary: a name of :data:`DICTIONARY_NAMES`.

    Attributes:
        bits: cells per side of the code (the black border excluded), e.g. 6 for 36h11.
        cells: cells across the black square, its border included (``bits + 2``).
        max_errors: bits that may be wrong in a read (the dictionary's correction bits).
    """

    def __init__(self, dictionary: str) -> None:
        d = marker_dictionary(dictionary)
        self.dictionary = dictionary
        self.bits = int(d.markerSize)
        self.cells = self.bits + 2
        self.max_errors = int(d.maxCorrectionBits)
        n_ids = int(d.bytesList.shape[0])
        printed = np.array([marker_cells(dictionary, i)[1:-1, 1:-1] for i in range(n_ids)])
        # table[id, s]: the code as read from an outline whose corner s is the printed
        # top-left (rolling the outline's corners by s turns the read by 90° s times)
        table = np.stack([np.rot90(printed, -s, axes=(1, 2)) for s in range(4)],
                         axis=1).reshape(n_ids * 4, -1).astype(bool)
        # each read packed in one 64-bit word (every dictionary has at most 49 bits): a
        # read is matched by XOR and a bit count over the table (a bool table's compare
        # and count took 10x as long)
        self._packed = _pack_bits(table)

    @property
    def packed(self) -> np.ndarray:
        """``(4 ids,)`` uint64: every code as read from an outline whose corner ``s`` is the
        printed top-left, row ``4 id + s``, bit ``i`` the code's cell ``i`` (row-major)."""
        return self._packed

    def identify(self, cells: np.ndarray) -> tuple[int, int, int] | None:
        """``(id, s, errors)`` of the code nearest ``cells`` ``(bits, bits)`` bool (True:
        white; row 0 along the outline's corner 0 -> 1), ``s`` the outline corner that is
        the printed top-left; None when more than :attr:`max_errors` bits differ."""
        c = _pack_bits(np.asarray(cells, bool).reshape(1, -1))
        dist = _bit_count(self._packed ^ c)
        k = int(np.argmin(dist))
        errors = int(dist[k])
        if errors > self.max_errors:
            return None
        i, s = divmod(k, 4)
        return i, s, errors


def _pack_bits(bits: np.ndarray) -> np.ndarray:
    """Rows of ``bits`` ``(N, B)`` bool, ``B <= 64``, as ``(N,)`` uint64 words."""
    weights = np.left_shift(np.uint64(1), np.arange(bits.shape[1], dtype=np.uint64))
    return (bits.astype(np.uint64) * weights).sum(axis=1, dtype=np.uint64)


_BYTE_BITS = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def _bit_count(words: np.ndarray) -> np.ndarray:
    """The set bits of each uint64 of ``words`` ``(N,)``."""
    if hasattr(np, "bitwise_count"):                       # numpy >= 2.0
        return np.bitwise_count(words)
    return _BYTE_BITS[words.view(np.uint8).reshape(-1, 8)].sum(axis=1)


@dataclass(frozen=True, eq=False)
class Quad:
    """A convex four-sided region of the frame.

    Attributes:
        corners_px: ``(4, 2)`` corners with a positive shoelace area in (u, v), that is
            clockwise as displayed (v down), like a printed image's top-left, top-right,
            bottom-right, bottom-left; starting anywhere.
        area_px: the contour's area, px².
        at_border: the region comes within :data:`BORDER_PX` of the image edge.
        contour_px: ``(M, 2)`` the region's boundary pixels (for :func:`sharpen_quad`),
            in the same pixels as the corners; ``pixel_px`` their pixel's size there
            (2 when found on a frame decimated by 2).
    """

    corners_px: np.ndarray
    area_px: float
    at_border: bool
    contour_px: np.ndarray | None = None
    pixel_px: float = 1.0


def sharpen_quad(quad: Quad) -> Quad:
    """The quad with its corners where its sides' lines meet (fitted to the contour,
    :func:`_side_fit_corners`), instead of ``approxPolyDP``'s vertices."""
    if quad.contour_px is None:
        return quad
    pts = _side_fit_corners(quad.contour_px, quad.corners_px, 0.5 * quad.pixel_px)
    if signed_area(pts) < 0:
        pts = pts[::-1].copy()
    return Quad(pts, quad.area_px, quad.at_border, None, quad.pixel_px)


def _threshold(grey: np.ndarray, dark: bool) -> np.ndarray:
    """Foreground mask: Otsu's level between the block and the ceiling around it."""
    kind = cv2.THRESH_BINARY_INV if dark else cv2.THRESH_BINARY
    _, mask = cv2.threshold(grey, 0, 255, kind | cv2.THRESH_OTSU)
    return mask


def detect_quads(grey: np.ndarray, dark: bool, min_area_px: float = MIN_QUAD_AREA_PX,
                 regions: list[np.ndarray] | None = None, sharpen: bool = True
                 ) -> list[Quad]:
    """Convex quadrilaterals darker (``dark``) or brighter than their surroundings.

    The frame is thresholded (Otsu) with its polarity, outer contours are simplified
    with ``approxPolyDP`` (tolerance :data:`POLY_EPS_RATE` of the perimeter) and the
    convex four-vertex ones of at least ``min_area_px`` kept. Regions that are not
    quadrilaterals (lamps of another shape, seams, clutter) drop out here; a quad's size
    and shape are checked by the caller. ``regions`` (list of contours) receives every
    large region that was not a convex quad, for the caller's diagnostics.
    """
    return quads_of_mask(_threshold(grey, dark), min_area_px, regions, sharpen)


def quads_of_mask(mask: np.ndarray, min_area_px: float = MIN_QUAD_AREA_PX,
                  regions: list[np.ndarray] | None = None, sharpen: bool = True
                  ) -> list[Quad]:
    """:func:`detect_quads` of a foreground mask ``(H, W)`` uint8 (0 or 255) already
    made: its outer contours' convex four-vertex simplifications."""
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    h, w = mask.shape
    out: list[Quad] = []
    # a closed path of n unit or diagonal steps encloses at most (n sqrt 2)² / (4 pi):
    # shorter contours cannot reach min_area_px (most are specks: skipped uncounted)
    min_len = math.sqrt(2.0 * math.pi * min_area_px)
    for c in contours:
        if len(c) < min_len:
            continue
        area = cv2.contourArea(c)
        if area < min_area_px:
            continue
        x, y, bw, bh = cv2.boundingRect(c)
        at_border = (x <= BORDER_PX or y <= BORDER_PX or x + bw >= w - BORDER_PX
                     or y + bh >= h - BORDER_PX)
        poly = cv2.approxPolyDP(c, POLY_EPS_RATE * cv2.arcLength(c, True), True)
        if len(poly) != 4 or not cv2.isContourConvex(poly):
            if regions is not None:
                regions.append(c)
            continue
        q = Quad(poly.reshape(4, 2).astype(float), float(area), bool(at_border),
                 c.reshape(-1, 2).astype(float))
        out.append(sharpen_quad(q) if sharpen else q)
    return out


def line_corners(lines: np.ndarray) -> np.ndarray | None:
    """``(4, 2)`` corners of four side lines ``(4, 3)`` ``(a, b, c)`` (corner k: side
    k-1 meets side k), None when two neighbouring sides are parallel. The cross product
    of each line with the previous one, in Python floats (four 3-vectors: numpy's calls
    cost more than the arithmetic)."""
    ls = np.asarray(lines, float).tolist()
    out = []
    a0, b0, c0 = ls[3]
    for a1, b1, c1 in ls:
        w = a0 * b1 - b0 * a1
        if abs(w) < 1e-12:
            return None
        out.append(((b0 * c1 - c0 * b1) / w, (c0 * a1 - a0 * c1) / w))
        a0, b0, c0 = a1, b1, c1
    return np.array(out)


def _side_fit_corners(contour: np.ndarray, poly: np.ndarray, outwards_px: float = 0.5
                      ) -> np.ndarray:
    """Corners ``(4, 2)`` of a four-sided contour ``(M, 2)`` (every boundary pixel) as
    its sides' lines meet.

    ``approxPolyDP``'s vertices ``poly`` ``(4, 2)`` are contour points within its
    tolerance of the outline, often pixels off the true corners; here each side's line
    is fitted to the contour points along its middle (:data:`SIDE_FIT_KEEP` of the run
    between two vertices; total least squares, :func:`_side_lines`), moved half a pixel
    outwards (the contour runs through the region's boundary pixels, the edge lies
    between them and the background: ``outwards_px``) and met with its neighbours'.
    Falls back to ``poly`` when a side has too few points."""
    poly = arr(poly, np.float64)
    ok, lines = _side_lines(arr(contour, np.float64), poly, SIDE_FIT_KEEP,
                            float(outwards_px))
    if not ok:
        return poly
    out = line_corners(lines)
    if out is None:
        return poly
    d, moved = poly[_NEXT] - poly, out - poly
    if (moved * moved).sum(axis=1).max() > 0.0625 * float((d * d).sum(axis=1).min()):
        return poly                                  # a corner moved over 1/4 of a side
    return out


@njit
def _side_lines(contour, poly, keep, outwards_px):  # pragma: no cover - compiled
    """``(ok, lines (4, 3))`` of :func:`_side_fit_corners`: each vertex's first place on
    the contour (not found: not ok), the middle ``keep`` of each run between two
    vertices (fewer than 3 points: not ok) fitted by total least squares (the major
    axis, as ``cv2.fitLine``'s L2), its normal turned outwards (from the vertices'
    centroid) and the line moved ``outwards_px`` along it."""
    m = contour.shape[0]
    lines = np.zeros((4, 3))
    i0 = np.empty(4, np.int64)
    for k in range(4):
        i0[k] = -1
        for i in range(m):
            if contour[i, 0] == poly[k, 0] and contour[i, 1] == poly[k, 1]:
                i0[k] = i
                break
        if i0[k] < 0:
            return False, lines
    cx = 0.25 * (poly[0, 0] + poly[1, 0] + poly[2, 0] + poly[3, 0])
    cy = 0.25 * (poly[0, 1] + poly[1, 1] + poly[2, 1] + poly[3, 1])
    for k in range(4):
        run = (i0[(k + 1) % 4] - i0[k]) % m
        first = int(np.rint(run * (0.5 - keep / 2)))
        count = int(np.rint(run * (0.5 + keep / 2))) - first
        if count < 3:
            return False, lines
        start = (i0[k] + first) % m
        mx = my = 0.0
        for j in range(count):
            mx += contour[(start + j) % m, 0]
            my += contour[(start + j) % m, 1]
        mx /= count
        my /= count
        sxx = syy = sxy = 0.0
        for j in range(count):
            dx = contour[(start + j) % m, 0] - mx
            dy = contour[(start + j) % m, 1] - my
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
        t = 0.5 * math.atan2(2.0 * sxy, sxx - syy)          # the run's direction
        a, b = -math.sin(t), math.cos(t)                   # normal to it
        if a * (mx - cx) + b * (my - cy) < 0:              # outwards
            a, b = -a, -b
        lines[k, 0], lines[k, 1], lines[k, 2] = a, b, -(a * mx + b * my) - outwards_px
    return True, lines


def signed_area(pts: np.ndarray) -> float:
    """Shoelace area of a polygon ``(n, 2)`` in (u, v): > 0 clockwise as displayed (in
    Python floats: a quad's four corners)."""
    p = np.asarray(pts, float).tolist()
    u0, v0 = p[-1]
    twice = 0.0
    for u1, v1 in p:
        twice += u0 * v1 - u1 * v0
        u0, v0 = u1, v1
    return 0.5 * twice


@functools.lru_cache(maxsize=16)
def edge_stations(per_side: int, search_px: float) -> tuple[np.ndarray, np.ndarray]:
    """edge_points' offsets across a side ``(K,)`` and stations along it ``(S,)``
    (read-only: shared between calls)."""
    offs = edge_offsets(search_px)
    t = np.linspace(EDGE_END_SKIP, 1 - EDGE_END_SKIP, per_side)
    t.flags.writeable = False
    return offs, t


def edge_offsets(search_px: float) -> np.ndarray:
    """edge_points' offsets across a side ``(K,)``, ``-search_px`` to ``search_px`` by
    :data:`EDGE_STEP_PX` (read-only; not cached: a reach a frame sets costs an
    ``arange``, not a cache entry)."""
    offs = np.arange(-search_px, search_px + 1e-9, EDGE_STEP_PX)
    offs.flags.writeable = False
    return offs


def edge_points(grey: np.ndarray, corners_px: np.ndarray, per_side: int = 12,
                search_px: float = EDGE_SEARCH_PX, sign: int = 0, cells: int = 0
                ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel points of each side of a coarse quad ``(4, 2)`` (side k: corner k to k+1).

    Along each side, ``per_side`` stations (leaving :data:`EDGE_END_SKIP` of the side out
    at each end); at each, the grey profile across the side (±``search_px``, bilinear)
    is searched for its steepest interval and the step located where the profile
    crosses half way between its two ends. Stations whose step is weak (below a
    quarter of the side's median) or at the search window's end are dropped. One
    compiled loop (:func:`edge_points_core`); the samples are bilinear in float (the
    frame's edge replicated), not rounded to OpenCV's 1/32 px grid.

    ``sign``: 0 takes the steepest step of either polarity; -1 only a step darker
    towards the side's left normal (inside a quad of positive shoelace area: a dark
    quad's edge), +1 only one brighter there. A signed search is what tells a small
    marker's outer edge from the edges of its first inner cells and of its quiet ring
    one cell either side (both of the other polarity), where an unsigned one within
    ``search_px`` of about a cell may take either.

    ``cells``: a marker's cells across its black square (its border included: the
    dictionary's bits + 2), 0 for a plain block. On a marker the half-way level is
    then read half a cell either side of the step (the black border cell's centre
    inside, the quiet ring's outside; :func:`half_cell_level`) instead of at the
    profile's ends: on a cell of about 4 px the inner end lies on the blurred edge of
    the first code cell, whose colour moved the level and with it the step (a white
    cell there: outwards, about 0.17 px at 4 px a cell and blur 1.2, docs/methods/
    block.md).

    Returns:
        points_px ``(M, 2)`` and side ``(M,)`` int (0..3) of each point.
    """
    offs, t = edge_stations(per_side, float(search_px))
    p0 = arr(corners_px, np.float64).reshape(4, 2)
    if not np.isfinite(p0).all():
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    pts, side, n = edge_points_core(arr(grey, np.uint8), p0, arr(offs, np.float64),
                                    arr(t, np.float64), EDGE_STEP_PX, int(sign),
                                    float(cells))
    return pts[:n], side[:n]


@njit
def edge_points_core(grey, p0, offs, t, step, sign=0, cells=0.0):  # pragma: no cover
    """:func:`edge_points` on a ``(4, 2)`` quad of finite corners: ``(points (4 S, 2),
    side (4 S,), count)``, the first ``count`` kept. Samples are bilinear in float
    (the frame's edge replicated beyond it), at offsets ``offs (K,)`` across each side
    at the fractions ``t (S,)`` along it; ``sign`` and ``cells`` as
    :func:`edge_points`'s."""
    h, w = grey.shape
    half_cell = 0.5 * mean_side_px(p0) / cells if cells > 0 else 0.0
    n_st, n_off = t.size, offs.size
    prof = np.empty(n_off)
    pts = np.empty((4 * n_st, 2))
    side = np.empty(4 * n_st, np.int64)
    strength = np.empty((4, n_st))
    good = np.zeros((4, n_st), np.bool_)
    for s in range(4):
        ax, ay = p0[s, 0], p0[s, 1]
        dx, dy = p0[(s + 1) % 4, 0] - ax, p0[(s + 1) % 4, 1] - ay
        inv = 1.0 / max(math.sqrt(dx * dx + dy * dy), 1e-9)
        nx, ny = -dy * inv, dx * inv                       # the side's left normal
        for j in range(n_st):
            bx, by = ax + t[j] * dx, ay + t[j] * dy
            for i in range(n_off):
                prof[i] = bilinear(grey, bx + offs[i] * nx, by + offs[i] * ny, w, h)
            k, best = 0, -1.0
            for i in range(n_off - 1):
                d = prof[i + 1] - prof[i]
                g = abs(d) if sign == 0 else sign * d
                if g > best:
                    k, best = i, g
            # the step's middle: where the profile crosses half way between its two
            # ends, in the steepest interval (unbiased for a symmetric blur, unlike the
            # peak of a sampled gradient)
            mid = 0.25 * (prof[0] + prof[1] + prof[n_off - 1] + prof[n_off - 2])
            frac = _crossing(prof[k], prof[k + 1], mid)
            # a marker: the level half a cell either side of the step found, twice
            # (the second about the first's step: 2.2-4.7x less of the code cell's
            # colour than the ends, the noise 1.1-1.2x, docs/methods/block.md)
            for _ in range(2 if half_cell > 0 else 0):
                o = offs[0] + (k + min(max(frac, -1.0), 2.0)) * step
                mid = half_cell_level(grey, (bx, by), (nx, ny), o, half_cell)
                frac = _crossing(prof[k], prof[k + 1], mid)
            o = offs[0] + (k + min(max(frac, -1.0), 2.0)) * step
            strength[s, j] = best
            u, v = bx + o * nx, by + o * ny
            good[s, j] = (0 < k < n_off - 2 and -1.0 < frac < 2.0
                          and 0.0 < u < w - 1 and 0.0 < v < h - 1)
            pts[s * n_st + j, 0] = u
            pts[s * n_st + j, 1] = v
    n = 0
    for s in range(4):
        srt = np.sort(strength[s])
        med = 0.5 * (srt[(n_st - 1) // 2] + srt[n_st // 2])
        for j in range(n_st):
            if good[s, j] and strength[s, j] > 0.25 * med:
                pts[n] = pts[s * n_st + j]
                side[n] = s
                n += 1
    return pts, side, n


@njit
def _crossing(p0, p1, mid):  # pragma: no cover - compiled
    """Where (a fraction of the interval) the segment ``p0`` -> ``p1`` crosses ``mid``;
    0.5 for a flat one."""
    d0, d1 = p0 - mid, p1 - mid
    return d0 / (d0 - d1) if abs(d0 - d1) > 1e-6 else 0.5


@njit
def mean_side_px(px):  # pragma: no cover - compiled
    """The mean length (px) of the sides of the quad ``px (4, 2)``."""
    total = 0.0
    for c in range(4):
        total += np.hypot(px[(c + 1) % 4, 0] - px[c, 0], px[(c + 1) % 4, 1] - px[c, 1])
    return total / 4.0


@njit
def half_cell_level(grey, base, normal, o, half_cell):  # pragma: no cover - compiled
    """The half-way level of a marker's edge at ``o`` px along ``normal (nx, ny)`` from
    ``base (x, y)``: the mean of the grey ``half_cell`` px either side (the centres of
    the black border cell and of the quiet ring's, as far from the code's first cells
    as a read can be), each side the mean of two bilinear samples a quarter pixel
    either side of it."""
    h, w = grey.shape
    bx, by = base
    nx, ny = normal
    total = 0.0
    for d in (o - half_cell - 0.25, o - half_cell + 0.25,
              o + half_cell - 0.25, o + half_cell + 0.25):
        total += bilinear(grey, bx + d * nx, by + d * ny, w, h)
    return 0.25 * total


@njit
def bilinear(grey, x, y, w, h):  # pragma: no cover - compiled
    """The frame's grey level at ``(x, y)`` (px), bilinear, its edge replicated (a
    place far outside reads the edge, as OpenCV's remap does)."""
    x = min(max(x, -1.0), float(w))
    y = min(max(y, -1.0), float(h))
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx, fy = x - x0, y - y0
    xa, xb = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
    ya, yb = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
    top = grey[ya, xa] + fx * (np.float64(grey[ya, xb]) - grey[ya, xa])
    bot = grey[yb, xa] + fx * (np.float64(grey[yb, xb]) - grey[yb, xa])
    return top + fy * (bot - top)


@warmer
def _warm() -> None:
    g = np.zeros((40, 40), np.uint8)
    g[10:30, 10:30] = 200
    edge_points(g, np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0]]), 4)
    detect_quads(g, False, 100.0)                    # a contour's sides (_side_lines)
