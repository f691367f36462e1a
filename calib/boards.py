"""Calibration boards: what they look like, how they are found, and a renderer for tests.

Convention: board coordinates are metres in the board plane, ``z = 0``; x runs along
the board's first (width) axis, y along its second, both as the printed board is read
(x right, y down). Pixels follow SPEC §1: ``(u, v)`` with the origin at the centre of
the top-left pixel.

* :class:`ChessBoard`: ``cols`` x ``rows`` *inner* corners (the count OpenCV wants:
  a board of 10 x 7 squares has 9 x 6 inner corners), spaced ``square_m``; corner
  ``k`` sits at ``((k % cols) * square_m, (k // cols) * square_m, 0)``.
* :class:`CharucoBoard`: ``squares_x`` x ``squares_y`` squares with ArUco markers in the
  white ones; its inner corners are numbered as OpenCV's ``cv2.aruco.CharucoBoard``
  does, with the board origin at the outer top-left corner. ``legacy`` selects the
  layout of boards printed before OpenCV 4.6 (``setLegacyPattern``).

A detection is a :class:`Detection`: the corner ids, their pixels and their board
coordinates. :func:`render_board` draws a board seen through a known pose and a
known :class:`~ceilkit.runtime.geometry.camera.CameraModel`, by inverse mapping (pixel ray ->
board plane -> board texture) with supersampling, so the true corner pixels are the
exact projections of the board corners.

Example::

    board = parse_board("chess:9x6", square_m=0.025)
    det = board.detect(grey)             # Detection or None
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.grey import to_grey

if TYPE_CHECKING:  # the renderer imports the camera (and numba) when it first draws
    from ceilkit.runtime.geometry.camera import CameraModel

ARUCO_DICTIONARIES = tuple(n[5:] for n in dir(cv2.aruco) if n.startswith("DICT_"))
MIN_CHARUCO_CORNERS = 6


SUBPIX_FRACTION = 0.35      # cornerSubPix half-window over the corner's shortest spacing
WORKING_MPX = 1.0
"""Boards are found on an image decimated to about this many megapixels (an integer
factor, box-averaged: :mod:`ceilkit.runtime.features.working`), then refined at full
resolution: ``findChessboardCorners`` on a 12 Mpx view takes seconds to minutes, on
its 1 Mpx decimation well under a second."""


def refine_corners(grey: np.ndarray, corners: np.ndarray, cols: int, rows: int,
                   half: int | None = None, max_half: int = 11) -> np.ndarray:
    """Chessboard corners refined by ``cv2.cornerSubPix``, each with its own window.

    ``cornerSubPix`` assumes that every edge inside its window passes through the
    corner; an edge that does not (the far side of a neighbouring square, the board's
    border) pulls the corner. A square of side ``s`` px puts such edges ``s`` away, so
    each corner gets the half-window ``0.35 * s`` (3 to ``max_half`` px, 11 unless a
    decimated detection scales it), ``s`` its shortest
    distance to a grid neighbour: the shortest sides of a foreshortened board are where a
    fixed window fails (OpenCV's sample ``left02.jpg``: 11 px against 22 px squares moves
    its corners by up to 5 px). Corners that share a half-window are refined together.

    Args:
        grey: the 8-bit grey image.
        corners: ``(rows * cols, 1, 2)`` float32 from ``findChessboardCorners``, row-major.
        cols, rows: inner corners across and down.
        half: one half-window for every corner (px) instead, or None.
        max_half: the largest half-window, px.

    Returns:
        ``(rows * cols, 1, 2)`` float32 refined corners, px (SPEC §1).
    """
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1)
    pts = np.asarray(corners, np.float32).reshape(-1, 1, 2).copy()
    if half is not None:
        return cv2.cornerSubPix(grey, pts, (half, half), (-1, -1), crit)
    grid = pts.reshape(rows, cols, 2).astype(np.float64)
    near = np.full((rows, cols), np.inf)
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)          # (rows, cols - 1)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)          # (rows - 1, cols)
    near[:, :-1] = np.minimum(near[:, :-1], dx)
    near[:, 1:] = np.minimum(near[:, 1:], dx)
    near[:-1, :] = np.minimum(near[:-1, :], dy)
    near[1:, :] = np.minimum(near[1:, :], dy)
    halves = np.clip(np.floor(SUBPIX_FRACTION * near), 3, max_half).astype(int).ravel()
    for h in np.unique(halves):
        idx = np.flatnonzero(halves == h)
        pts[idx] = cv2.cornerSubPix(grey, np.ascontiguousarray(pts[idx]), (int(h), int(h)),
                                    (-1, -1), crit)
    return pts


@dataclass(frozen=True, eq=False)
class Detection:
    """The corners of one board found in one image.

    Attributes:
        name: the image's name (file name, or ``frame000123`` for a video).
        image_size: ``(width, height)`` in pixels.
        ids: ``(N,)`` int corner ids (index into the board's corners).
        points_px: ``(N, 2)`` float pixels (SPEC §1 convention).
        points_board: ``(N, 3)`` float board coordinates in metres (z = 0).
    """

    name: str
    image_size: tuple[int, int]
    ids: np.ndarray
    points_px: np.ndarray
    points_board: np.ndarray

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int32).ravel()
        px = np.asarray(self.points_px, dtype=np.float64).reshape(-1, 2)
        obj = np.asarray(self.points_board, dtype=np.float64).reshape(-1, 3)
        if not (ids.size == px.shape[0] == obj.shape[0]):
            raise ValueError("ids, points_px and points_board must have the same length")
        for name, a in (("ids", ids), ("points_px", px), ("points_board", obj)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "image_size", (int(self.image_size[0]),
                                                int(self.image_size[1])))

    def __len__(self) -> int:
        return int(self.ids.size)

    def subset(self, keep: np.ndarray) -> Detection:
        """The same detection with only the corners where ``keep`` is true."""
        k = np.asarray(keep, dtype=bool)
        return Detection(self.name, self.image_size, self.ids[k], self.points_px[k],
                         self.points_board[k])


class Board:
    """What every board offers (see :class:`ChessBoard`, :class:`CharucoBoard`)."""

    spec: str

    @property
    def corners_board(self) -> np.ndarray:
        """``(N, 3)`` board coordinates of every corner, in metres."""
        raise NotImplementedError

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)``: the printed board (squares only), metres."""
        raise NotImplementedError

    def detect(self, image: np.ndarray, name: str = "") -> Detection | None:
        """The board's corners in ``image`` (grey or BGR), or None if not found."""
        raise NotImplementedError

    def texture(self, xy_m: np.ndarray) -> np.ndarray:
        """Reflectance in [0, 1] at board points ``(..., 2)`` (metres); the white
        margin and the background beyond it included."""
        raise NotImplementedError

    def alternatives(self) -> list[Board]:
        """Other plausible boards a user may have meant (for the wrong-size hint)."""
        return []


@dataclass(frozen=True)
class ChessBoard(Board):
    """A chessboard of ``cols`` x ``rows`` inner corners spaced ``square_m`` metres.

    ``detector``: ``classic`` (``findChessboardCorners`` + ``cornerSubPix``, each corner
    with a half-window of 0.35 of its own shortest grid spacing, 3 to 11 px: see
    :func:`refine_corners`; ``subpix_half`` fixes one half-window for every corner, as
    OpenCV's calibration sample does with 11), ``sb`` (``findChessboardCornersSB``, more
    robust to blur but biased by about 0.4% in focal length on our renders), or ``auto``
    (classic, then sb).

    ``working_mpx``: an image larger than this (megapixels) is searched decimated by
    :func:`working_factor` and its corners refined at full resolution by
    :func:`refine_corners` with windows up to ``11 * factor`` px; 0 searches at full
    resolution.
    """

    cols: int
    rows: int
    square_m: float
    margin_squares: float = 1.0
    detector: str = "auto"
    subpix_half: int | None = None
    working_mpx: float = WORKING_MPX

    def __post_init__(self) -> None:
        if self.subpix_half is not None and self.subpix_half < 2:
            raise ConfigError(None, "subpix_half", f"expected a half-window of at least 2 px, "
                              f"found {self.subpix_half}")
        if self.cols < 2 or self.rows < 2:
            raise ConfigError(None, "board", f"a chessboard needs at least 2x2 inner "
                              f"corners, found {self.cols}x{self.rows}")
        if not (self.square_m > 0 and math.isfinite(self.square_m)):
            raise ConfigError(None, "square", f"expected a positive size in metres, "
                              f"found {self.square_m:g}")
        if self.detector not in ("auto", "sb", "classic"):
            raise ConfigError(None, "detector", f"expected auto, sb or classic, found "
                              f"{self.detector!r}")
        _check_working(self.working_mpx)

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"chess:{self.cols}x{self.rows}"

    @cached_property
    def corners_board(self) -> np.ndarray:  # type: ignore[override]
        k = np.arange(self.cols * self.rows)
        pts = np.stack([(k % self.cols) * self.square_m, (k // self.cols) * self.square_m,
                        np.zeros(k.size)], axis=1)
        pts.setflags(write=False)
        return pts

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        s = self.square_m
        return (-s, -s, self.cols * s, self.rows * s)

    def detect(self, image: np.ndarray, name: str = "") -> Detection | None:
        decimate, undecimate, working_factor = _working()
        grey = to_grey(image)
        f = working_factor(grey.shape, self.working_mpx)
        corners = self._find(decimate(grey, f), self.subpix_half if f == 1 else None)
        if corners is None:
            return None
        if f > 1:              # found at the working size: refined at full resolution
            corners = refine_corners(grey, undecimate(corners, f).astype(np.float32),
                                     self.cols, self.rows, self.subpix_half, 11 * f)
        px = corners.reshape(-1, 2).astype(np.float64)
        ids = np.arange(px.shape[0])
        h, w = grey.shape[:2]
        return Detection(name, (w, h), ids, px, self.corners_board)

    def _find(self, grey: np.ndarray, half: int | None) -> np.ndarray | None:
        """``(rows * cols, 1, 2)`` corners of ``grey`` by the chosen detector, or None."""
        found, corners = False, None
        if self.detector in ("auto", "classic"):
            flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
            found, corners = cv2.findChessboardCorners(grey, (self.cols, self.rows), flags=flags)
            if found and corners is not None:
                corners = refine_corners(grey, corners, self.cols, self.rows, half)
        if not found and self.detector in ("auto", "sb"):
            flags = (cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
                     | cv2.CALIB_CB_ACCURACY)
            found, corners = cv2.findChessboardCornersSB(grey, (self.cols, self.rows),
                                                         flags=flags)
        if not found or corners is None or len(corners) != self.cols * self.rows:
            return None
        return corners

    def texture(self, xy_m: np.ndarray) -> np.ndarray:
        s = self.square_m
        x, y = xy_m[..., 0], xy_m[..., 1]
        i, j = np.floor(x / s), np.floor(y / s)
        x0, y0, x1, y1 = self.extent_m
        on = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        m = self.margin_squares * s
        paper = (x >= x0 - m) & (x < x1 + m) & (y >= y0 - m) & (y < y1 + m)
        black = on & ((i + j) % 2 == 1)
        out = np.where(paper, 0.92, 0.35)
        return np.where(black, 0.06, out)

    def grid_extends(self, image: np.ndarray, det: Detection, max_steps: int = 4
                     ) -> tuple[int, int, int, int]:
        """How many rows or columns of further chessboard corners lie beyond a detected
        grid: ``(left, right, top, bottom)`` in the grid's own order (0 when the grid
        ends at the board's edge, as it should).

        A wrong size that still matches part of the board (``8x5`` given for a ``9x6``
        board) is found, but leaves corners outside it. Each step extrapolates the grid
        by one square (from its last two rows or columns) and tests every predicted point
        for an X-junction: the intensity on a ring about it alternates dark, light,
        dark, light (a strong second harmonic, a weak first); the board's edge against
        its white margin is a T-junction and fails.
        """
        grey = to_grey(image).astype(np.float32)
        if len(det) != self.cols * self.rows:
            return (0, 0, 0, 0)
        grid = det.points_px.reshape(self.rows, self.cols, 2)
        out = []
        for axis, first in ((1, True), (1, False), (0, True), (0, False)):
            g = np.moveaxis(grid, axis, 0)          # lines of corners across the axis
            if first:
                g = g[::-1]
            a, b = g[-2], g[-1]
            n = 0
            for _ in range(max_steps):
                nxt = 2 * b - a
                if not _x_junctions(grey, nxt, np.linalg.norm(b - a, axis=1))[0]:
                    break
                a, b = b, nxt
                n += 1
            out.append(n)
        return (out[0], out[1], out[2], out[3])

    def alternatives(self) -> list[Board]:
        c, r = self.cols, self.rows
        sizes = [(r, c), (c - 1, r), (c, r - 1), (c + 1, r), (c, r + 1), (c - 1, r - 1),
                 (c + 1, r + 1), (r - 1, c), (r, c - 1)]
        seen, out = {(c, r)}, []
        for a, b in sizes:
            if a >= 2 and b >= 2 and (a, b) not in seen:
                seen.add((a, b))
                out.append(ChessBoard(a, b, self.square_m, detector=self.detector,
                                      working_mpx=self.working_mpx))
        return out


@dataclass(frozen=True)
class CharucoBoard(Board):
    """A ChArUco board of ``squares_x`` x ``squares_y`` squares.

    Attributes:
        squares_x, squares_y: squares along x and y (inner corners: one less each).
        square_m, marker_m: square and marker side lengths in metres.
        dictionary: an ArUco dictionary name without ``DICT_`` (e.g. ``4X4_50``).
        legacy: the pre-4.6 layout (``cv2.aruco.CharucoBoard.setLegacyPattern``).
        working_mpx: as :class:`ChessBoard`: markers and corners are found on a
            decimated image, the corners refined by ``cornerSubPix`` at full resolution
            (half-window 0.8 of the gap between a corner and the nearest marker edge,
            2 to ``11 * factor`` px).
    """

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str = "4X4_50"
    legacy: bool = False
    margin_squares: float = 0.5
    working_mpx: float = WORKING_MPX
    _cv: object = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise ConfigError(None, "board", f"a ChArUco board needs at least 2x2 squares, "
                              f"found {self.squares_x}x{self.squares_y}")
        if not (self.square_m > 0 and math.isfinite(self.square_m)):
            raise ConfigError(None, "square", f"expected a positive size in metres, "
                              f"found {self.square_m:g}")
        if not 0 < self.marker_m < self.square_m:
            raise ConfigError(None, "marker", f"expected a marker size in (0, "
                              f"{self.square_m:g}) metres, found {self.marker_m:g}")
        _check_working(self.working_mpx)
        name = self.dictionary.upper().removeprefix("DICT_")
        if name not in ARUCO_DICTIONARIES:
            raise ConfigError(None, "board", f"unknown ArUco dictionary {self.dictionary!r} "
                              f"(e.g. 4X4_50, 5X5_100, 6X6_250, ARUCO_ORIGINAL)")
        object.__setattr__(self, "dictionary", name)
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, "DICT_" + name))
        n_markers = (self.squares_x * self.squares_y) // 2
        if n_markers > d.bytesList.shape[0]:
            raise ConfigError(None, "board", f"{self.squares_x}x{self.squares_y} squares need "
                              f"{n_markers} markers; DICT_{name} has {d.bytesList.shape[0]}")
        b = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m,
                                   self.marker_m, d)
        b.setLegacyPattern(bool(self.legacy))
        object.__setattr__(self, "_cv", b)

    @property
    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object."""
        return self._cv  # type: ignore[return-value]

    @property
    def spec(self) -> str:  # type: ignore[override]
        s = f"charuco:{self.squares_x}x{self.squares_y}:{self.dictionary}"
        return s + (":legacy" if self.legacy else "")

    @cached_property
    def corners_board(self) -> np.ndarray:  # type: ignore[override]
        pts = np.asarray(self.cv_board.getChessboardCorners(), np.float64).reshape(-1, 3)
        pts.setflags(write=False)
        return pts

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, self.squares_x * self.square_m, self.squares_y * self.square_m)

    def detect(self, image: np.ndarray, name: str = "") -> Detection | None:
        decimate, undecimate, working_factor = _working()
        grey = to_grey(image)
        h, w = grey.shape[:2]
        f = working_factor(grey.shape, self.working_mpx)
        detector = cv2.aruco.CharucoDetector(self.cv_board)
        corners, ids, _, _ = detector.detectBoard(decimate(grey, f))
        if ids is None or corners is None or len(ids) < MIN_CHARUCO_CORNERS:
            return None
        ids = ids.ravel().astype(np.int32)
        if self.cv_board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
            return None
        if f > 1:              # found at the working size: refined at full resolution
            gap = 0.5 * (1.0 - self.marker_m / self.square_m)    # marker edge, squares
            corners = _refine_scattered(grey, undecimate(corners.reshape(-1, 2), f),
                                        0.8 * gap, 11 * f)
        obj, img = self.cv_board.matchImagePoints(
            np.asarray(corners, np.float32).reshape(-1, 1, 2), ids.reshape(-1, 1))
        return Detection(name, (w, h), ids, np.asarray(img, np.float64).reshape(-1, 2),
                         np.asarray(obj, np.float64).reshape(-1, 3))

    def markers_found(self, image: np.ndarray) -> int:
        """How many markers of this board's dictionary ``image`` shows."""
        detector = cv2.aruco.CharucoDetector(self.cv_board)
        decimate, _, working_factor = _working()
        grey = to_grey(image)
        _, _, _, marker_ids = detector.detectBoard(
            decimate(grey, working_factor(grey.shape, self.working_mpx)))
        return 0 if marker_ids is None else len(marker_ids)

    @cached_property
    def _texture_image(self) -> tuple[np.ndarray, float]:
        ppm = 40.0 / self.square_m                      # 40 texture pixels per square
        w = int(round(self.squares_x * self.square_m * ppm))
        h = int(round(self.squares_y * self.square_m * ppm))
        return self.cv_board.generateImage((w, h), marginSize=0, borderBits=1), ppm

    def texture(self, xy_m: np.ndarray) -> np.ndarray:
        img, ppm = self._texture_image
        h, w = img.shape
        u = np.floor(xy_m[..., 0] * ppm).astype(np.int64)
        v = np.floor(xy_m[..., 1] * ppm).astype(np.int64)
        on = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        val = img[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)].astype(np.float64) / 255.0
        val = 0.06 + 0.86 * val
        m = self.margin_squares * self.square_m
        x0, y0, x1, y1 = self.extent_m
        x, y = xy_m[..., 0], xy_m[..., 1]
        paper = (x >= x0 - m) & (x < x1 + m) & (y >= y0 - m) & (y < y1 + m)
        return np.where(on, val, np.where(paper, 0.92, 0.35))

    def alternatives(self) -> list[Board]:
        sx, sy = self.squares_x, self.squares_y
        out: list[Board] = []
        for a, b, leg in ((sx, sy, not self.legacy), (sy, sx, self.legacy),
                          (sy, sx, not self.legacy)):
            try:
                out.append(CharucoBoard(a, b, self.square_m, self.marker_m, self.dictionary,
                                        leg, working_mpx=self.working_mpx))
            except ConfigError:
                pass
        return out



def _working():
    """``(decimate, undecimate, working_factor)`` of :mod:`ceilkit.runtime.features.working`,
    imported when a board is first searched for: that module loads the spot detector and
    numba (about 130 MB), which printing a board does not need."""
    from ceilkit.runtime.features import working

    return working.decimate, working.undecimate, working.working_factor


def __getattr__(name: str):
    """``decimate``, ``undecimate`` and ``working_factor``, as this module has always
    offered them (imported on first use: see :func:`_working`)."""
    if name in ("decimate", "undecimate", "working_factor"):
        return getattr(__import__("ceilkit.runtime.features.working",
                                  fromlist=[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _check_working(working_mpx: float) -> None:
    if not (math.isfinite(working_mpx) and working_mpx >= 0):
        raise ConfigError(None, "working_mpx", f"expected a size in megapixels >= 0 (0: full "
                          f"resolution), found {working_mpx!r}")


def _refine_scattered(grey: np.ndarray, pts_px: np.ndarray, fraction: float, max_half: int
                      ) -> np.ndarray:
    """Corners ``(N, 2)`` (not a full grid) refined by ``cornerSubPix`` with one
    half-window: ``fraction`` of their median nearest-neighbour spacing, 2 to
    ``max_half`` px (a ChArUco corner's window must stop short of the markers' edges)."""
    pts = np.asarray(pts_px, np.float32).reshape(-1, 1, 2).copy()
    d = np.linalg.norm(pts[:, None, 0, :] - pts[None, :, 0, :], axis=2)
    np.fill_diagonal(d, np.inf)
    half = int(np.clip(np.floor(fraction * np.median(d.min(axis=1))), 2, max_half))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    return cv2.cornerSubPix(grey, pts, (half, half), (-1, -1), crit)


def _x_junctions(grey: np.ndarray, pts_px: np.ndarray, spacing_px: np.ndarray,
                 min_share: float = 0.6) -> np.ndarray:
    """Whether most points ``(N, 2)`` are chessboard X-junctions (see
    :meth:`ChessBoard.grid_extends`); ``spacing_px`` ``(N,)`` sets each ring's radius.
    Returns a one-element array: the share of X-junctions is at least ``min_share``."""
    h, w = grey.shape[:2]
    th = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
    r = np.clip(0.3 * spacing_px, 2.0, 12.0)
    inside = (pts_px[:, 0] > r + 1) & (pts_px[:, 0] < w - r - 2) & \
        (pts_px[:, 1] > r + 1) & (pts_px[:, 1] < h - r - 2)
    if np.count_nonzero(inside) < max(2, pts_px.shape[0] // 2):
        return np.array([False])
    p, rr = pts_px[inside], r[inside]
    xs = (p[:, 0:1] + rr[:, None] * np.cos(th)[None, :]).astype(np.float32)
    ys = (p[:, 1:2] + rr[:, None] * np.sin(th)[None, :]).astype(np.float32)
    ring = cv2.remap(grey, xs, ys, cv2.INTER_LINEAR).astype(np.float64)
    ring -= ring.mean(axis=1, keepdims=True)
    spec = np.abs(np.fft.rfft(ring, axis=1))
    contrast = ring.max(axis=1) - ring.min(axis=1)
    x_like = (spec[:, 2] > 2.0 * spec[:, 1]) & (spec[:, 2] > spec[:, 3]) & \
        (contrast > 30.0)
    return np.array([np.mean(x_like) >= min_share])

_CHESS = re.compile(r"^chess(?:board)?:(\d+)x(\d+)$", re.I)
_CHARUCO = re.compile(r"^charuco:(\d+)x(\d+)(?::([A-Za-z0-9_]+))?(:legacy)?$", re.I)


def parse_board(spec: str, square_m: float, marker_m: float | None = None,
                legacy: bool = False, detector: str = "auto") -> Board:
    """A board from its command-line description.

    ``chess:COLSxROWS`` (inner corners, e.g. ``chess:9x6``) or
    ``charuco:SQUARES_XxSQUARES_Y[:DICT][:legacy]`` (squares, e.g.
    ``charuco:5x7:4X4_50``); ``square_m`` and ``marker_m`` in metres (the marker
    defaults to 0.75 of the square; a chessboard takes none); ``detector`` for
    chessboards (see :class:`ChessBoard`). Raises ConfigError keyed ``board``, or
    ``marker`` for a marker size given to a chessboard.
    """
    s = spec.strip()
    m = _CHESS.match(s)
    if m:
        if marker_m is not None:
            raise ConfigError(None, "marker", f"a chessboard ({spec!r}) has no markers: "
                              "give the marker size for a charuco board only")
        return ChessBoard(int(m.group(1)), int(m.group(2)), float(square_m),
                          detector=detector)
    m = _CHARUCO.match(s)
    if m:
        marker = 0.75 * square_m if marker_m is None else marker_m
        return CharucoBoard(int(m.group(1)), int(m.group(2)), float(square_m), float(marker),
                            m.group(3) or "4X4_50", legacy or bool(m.group(4)))
    raise ConfigError(None, "board", f"expected chess:COLSxROWS (inner corners, e.g. "
                      f"chess:9x6) or charuco:SXxSY[:DICT][:legacy] (squares, e.g. "
                      f"charuco:5x7:4X4_50), found {spec!r}")


# -- rendering (tests and simulation) --------------------------------------------------------


_RENDER_SUBPIXELS = 4_000_000   # sub-pixels traced at once (bounds a large render's memory)


def _render_rows(board: Board, camera: CameraModel, R: np.ndarray, t: np.ndarray,
                 supersample: int, v0: int, v1: int) -> np.ndarray:
    """Rows ``v0:v1`` of the noise-free render, grey levels 0..255 (float)."""
    K = camera.K.copy()
    K[1, 2] -= v0                           # the strip is a camera with its centre moved
    strip = dataclasses.replace(camera, height=v1 - v0, K=K)
    from ceilkit.runtime.geometry.camera import subpixel_rays

    rays = subpixel_rays(strip, supersample)
    n = R[:, 2]
    denom = rays @ n
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = (n @ t) / denom
        X = rays * lam[..., None] - t
        xy = X @ R[:, :2]                     # R^T (X - t), first two components
    valid = np.isfinite(lam) & (lam > 0)
    xy = np.where(valid[..., None], xy, 1e6)
    val = np.where(valid, board.texture(xy), 0.35)
    return val.reshape(v1 - v0, supersample, camera.width, supersample).mean(axis=(1, 3)) * 255.0


def render_board(board: Board, camera: CameraModel, rvec_cam_board: np.ndarray,
                 t_cam_board_m: np.ndarray, rng: np.random.Generator | None = None,
                 noise_sigma: float = 2.0, blur_sigma_px: float = 0.7,
                 supersample: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw ``board`` seen by ``camera`` at a known pose.

    Args:
        board: the board.
        camera: the lens (any model of :class:`CameraModel`).
        rvec_cam_board, t_cam_board_m: Rodrigues vector (3,) and translation (3,) m
            with ``X_cam = R(rvec) X_board + t``.
        rng: random generator for the pixel noise (seed it).
        noise_sigma: Gaussian pixel noise in grey levels (0..255).
        blur_sigma_px: Gaussian blur (pixels) applied before the noise.
        supersample: samples per pixel along each axis.

    Returns:
        ``(image, corners_px, visible)``: ``(H, W)`` uint8 grey image; ``(N, 2)`` exact
        pixels of every board corner (``board.corners_board`` order); ``(N,)`` bool,
        true for corners in front of the camera and inside the image.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    R, _ = cv2.Rodrigues(np.asarray(rvec_cam_board, np.float64).reshape(3))
    t = np.asarray(t_cam_board_m, np.float64).reshape(3)
    H, W = camera.height, camera.width
    # whole pairs of rows: subpixel_rays inverts the lens every 2 px from a strip's top
    # row, so strips that start on even rows share one node grid (an odd start moved
    # the sub-pixel samples by up to 0.2 px: a seam between strips)
    strip = max(2, _RENDER_SUBPIXELS // (W * supersample * supersample) // 2 * 2)
    img = np.concatenate([_render_rows(board, camera, R, t, supersample, v0,
                                       min(H, v0 + strip)) for v0 in range(0, H, strip)])
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    image = np.clip(np.round(img), 0, 255).astype(np.uint8)
    Xc = board.corners_board @ R.T + t
    corners_px = camera.project(Xc)
    visible = np.isfinite(corners_px).all(axis=1) & camera.in_image(
        np.nan_to_num(corners_px, nan=-1e9), margin_px=2.0)
    if camera.model == "equidistant":
        visible &= Xc[:, 2] > 0
    return image, corners_px, visible


def look_at_pose(board: Board, distance_m: float, tilt_deg: float, tilt_dir_deg: float,
                 roll_deg: float, offset_m: tuple[float, float] = (0.0, 0.0)
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A pose ``(rvec, t)`` that shows ``board``'s centre ``offset_m`` off the optical axis.

    The board is turned by ``roll_deg`` about its normal and tilted by ``tilt_deg``
    about an in-plane axis at ``tilt_dir_deg``; its centre sits at
    ``(offset_x, offset_y, distance_m)`` in the camera frame.
    """
    x0, y0, x1, y1 = board.extent_m
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    Rz, _ = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(roll_deg)]))
    a = np.radians(tilt_dir_deg)
    axis = np.array([np.cos(a), np.sin(a), 0.0]) * np.radians(tilt_deg)
    Rt, _ = cv2.Rodrigues(axis)
    R = Rt @ Rz
    t = np.array([offset_m[0], offset_m[1], distance_m]) - R @ centre
    rvec, _ = cv2.Rodrigues(R)
    return rvec.ravel(), t


def render_views(board: Board, camera: CameraModel, n_views: int, rng: np.random.Generator,
                 noise_sigma: float = 2.0, blur_sigma_px: float = 0.7, supersample: int = 2,
                 distance_m: tuple[float, float] | None = None, max_tilt_deg: float = 40.0,
                 all_visible: bool = True
                 ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``n_views`` renders of ``board`` at random, varied poses (see :func:`render_board`).

    Poses spread the board over the image (centres up to 0.7 of the half-field off
    axis), tilt it by up to ``max_tilt_deg`` in every direction and roll it freely by
    +-30 deg. ``distance_m`` defaults to the range where the board fills 35-70 % of the
    image width. With ``all_visible`` a pose that hides a corner is drawn again.

    Returns:
        A list of ``(image, corners_px, visible)`` as :func:`render_board` returns.
    """
    x0, y0, x1, y1 = board.extent_m
    if distance_m is None:
        hfov = 2 * np.arctan(camera.width / 2 / camera.fx)
        span = x1 - x0
        d_hi = span / (0.35 * 2 * np.tan(hfov / 2))
        d_lo = span / (0.70 * 2 * np.tan(hfov / 2))
        distance_m = (d_lo, d_hi)
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    tries = 0
    while len(out) < n_views:
        tries += 1
        if tries > 200 * n_views:
            raise RuntimeError("could not place the board in view; widen the pose ranges")
        d = rng.uniform(*distance_m)
        k = len(out) % 3
        tilt = rng.uniform(max_tilt_deg * k / 3, max_tilt_deg * (k + 1) / 3)
        off = rng.uniform(-0.7, 0.7, 2) * np.array([camera.width / 2 / camera.fx,
                                                     camera.height / 2 / camera.fy]) * d
        rvec, t = look_at_pose(board, d, tilt, rng.uniform(0, 360), rng.uniform(-30, 30),
                               (off[0], off[1]))
        Xc = board.corners_board @ cv2.Rodrigues(rvec)[0].T + t
        px = camera.project(Xc)
        vis = np.isfinite(px).all(axis=1) & camera.in_image(np.nan_to_num(px, nan=-1e9), 8.0)
        if (all_visible and not vis.all()) or vis.sum() < 6:
            continue
        out.append(render_board(board, camera, rvec, t, rng, noise_sigma, blur_sigma_px,
                                supersample))
    return out


__all__ = ["ARUCO_DICTIONARIES", "SUBPIX_FRACTION", "WORKING_MPX", "Board", "CharucoBoard",
           "ChessBoard", "Detection", "look_at_pose", "parse_board", "refine_corners",
           "render_board", "render_views"]
