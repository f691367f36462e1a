"""The block method's window path (option ``window_search``): with a prior, the site's
blocks and markers are measured where the prior puts them, with no search of the frame.

:class:`Windows` projects every block and marker of the site from the prior
(:meth:`Windows.predicted`: those fully in view, the largest first) and measures one on
its predicted outline (:meth:`Windows.fix`): a first edge pass ``window_px``
across each side in pixels, then the undistorted pass about the corners it found
(:func:`.detect.measure_sides`), solved by planar PnP (:func:`.pnp.solve`), all in one
compiled call; the **window check** refuses a fix that does not look like the predicted
block. The estimator falls back to its global path then (docs/methods/block.md).

Example::

    win = Windows(geo, targets_of(site, site.markers, 0.08), options)
    for target, px in win.predicted((x, y, yaw)):
        got = win.fix(grey, target, px)     # a OutlineFix, or None: the check failed
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ceilkit.runtime.estimators.block.detect import (
    Sides,
    SidesOut,
    contrast_core,
    edge_search,
    measure_core,
    read_marker,
    rim_samples,
    side_lengths_m,
)
from ceilkit.runtime.estimators.block.pnp import (
    SOLVED,
    PlanarFit,
    PlanarGeometry,
    SeenBlock,
    SolvedOut,
    solve_core,
)
from ceilkit.runtime.features.quads import BORDER_PX, bilinear, mean_side_px, signed_area
from ceilkit.runtime.geometry.camera import distort_points
from ceilkit.runtime.geometry.ceiling import ceiling_norm, kernel_mount
from ceilkit.runtime.geometry.fits import rigid_fit_rms
from ceilkit.runtime.jit import arr, njit, warmer

TRACK_MIN_SHARE = 0.75      # window check: share of a side's stations with an edge point
TRACK_MAX_RMS_PX = 0.5      # window check: edge residual RMS of the refined pose
MARKER_WINDOW_CELLS = 0.6   # a marker's first edge pass: at most this share of a cell
MARKER_MIN_CELL_PX = 5.0    # a marker smaller than this a cell (px) is left to the global path
FILL_CELLS = 8              # window check: a block's inside sampled on this grid squared
FILL_MAX_SHARE = 0.0        # ... at most this share of the samples may read as the outside
WINDOW = "window"           # diagnostics["mode"] of a window fix (else "global")


@dataclass(frozen=True, eq=False)
class Target:
    """A block or marker of the site as the window path predicts it: ``corners_w``
    ``(4, 2)`` in the order its sides are measured, ``symmetric`` when its shape also
    fits its corners turned (the prior then decides the correspondence)."""

    source: str
    corners_w: np.ndarray
    dark: bool
    symmetric: bool
    min_side_m: float
    marker_id: int | None = None


def targets_of(site: Any, markers: Any, shape_tol: float) -> list[Target]:
    """Every block and marker of the site as a :class:`Target` (``shape_tol``: the
    block method's option, relative to the shortest side)."""
    out = []
    for b in site.blocks:
        c = np.asarray(b.corners_m, float)
        side = float(side_lengths_m(c).min())
        out.append(Target(f"block:{b.id}", c, b.appearance != "bright",
                          turn_fits(c, shape_tol * side), side))
    for p in markers.poses if markers is not None else ():
        out.append(Target(f"marker:{p.id}", p.corners_m(), True, False, float(p.size_m),
                          int(p.id)))
    return out


def turn_fits(corners: np.ndarray, tol_m: float) -> bool:
    """Whether the quad ``(4, 2)`` fits itself with its corners turned by one, two or
    three places within ``tol_m`` (RMS): a square (4 ways), a rectangle (2)."""
    return any(rigid_fit_rms(corners, np.roll(corners, -shift, axis=0))[2] < tol_m
               for shift in (1, 2, 3))


def shape_fits(blocks: Any, pv: np.ndarray, dark: bool, shape_tol: float
               ) -> list[tuple[Any, int, float, tuple]]:
    """``(block, shift, rms_m, (x, y, yaw))`` of every block of ``blocks`` (the site's)
    of that polarity and corner shift whose shape the quad ``pv`` (V, counter-clockwise)
    fits within ``shape_tol`` of its shortest side (the global path's matching)."""
    out = []
    for blk in blocks:
        if (blk.appearance == "bright") == dark:
            continue
        tol = shape_tol * float(side_lengths_m(blk.corners_m).min())
        for shift in range(4):
            yaw, t, rms = rigid_fit_rms(pv, blk.corners_m[(np.arange(4) + shift) % 4])
            if rms < tol:
                out.append((blk, shift, rms, (float(t[0]), float(t[1]), yaw)))
    return out


class WindowCheck(NamedTuple):
    """The window check of one target as :func:`window_core` applies it: the edge
    points each side needs ``min_count``, the target's polarity ``dark`` and the
    contrast it needs across its outline (``dark_ratio`` below, ``bright_ratio``
    above), the largest edge residual ``max_rms_px``, shape misfit ``max_shape_m`` and
    move of the refined outline from the predicted one ``window_px``."""

    min_count: float
    dark: bool
    dark_ratio: float
    bright_ratio: float
    max_rms_px: float
    max_shape_m: float
    window_px: float


class WindowResult(NamedTuple):
    """What :func:`window_core` returns: whether the check passed ``ok``, the edge
    points measured ``n`` and used ``m``, the edge residual ``rms_px``, the variance
    scale ``var_b`` and whether ``unit`` was written ``has_unit``."""

    ok: bool
    n: int
    m: int
    rms_px: float
    var_b: float
    has_unit: bool


@dataclass(frozen=True, eq=False)
class OutlineFix:
    """A target measured on its predicted outline and solved: its ``sides`` (the
    corners and edge points, normalized), the closed form's ``shape_m`` and the
    ``refined`` pose (its covariance not yet pooled)."""

    sides: Sides
    shape_m: float
    refined: PlanarFit


class Windows:
    """The site's targets predicted and measured from a prior (see the module).

    Args:
        geo: the rig and ceiling.
        targets: :func:`targets_of` the site.
        options: the block method's options (``window_px``, ``edge_points``,
            ``dark_ratio``, ``bright_ratio``, ``shape_tol``).
        drop: ``drop(corners_w)``: ``(4,)`` bool, the sides the refinement leaves out
            (:class:`.parallels.LinedSides`); none when not given.
        codes: the site's marker dictionary (:class:`~..features.quads.MarkerCodes`):
            a marker's code is read on its measured outline (the window check).
    """

    def __init__(self, geo: PlanarGeometry, targets: list[Target], options: Any,
                 drop: Callable[[np.ndarray], np.ndarray] | None = None,
                 codes: Any = None) -> None:
        self.geo, self.codes = geo, codes
        self.targets = targets
        self.options = options
        self._corners = arr(np.concatenate([t.corners_w for t in targets]) if targets
                            else np.zeros((0, 2)), np.float64)
        self._bright = arr(np.array([not t.dark for t in targets], bool), np.bool_)
        none = arr(np.zeros(4, bool), np.bool_)
        self._drop = {t.source: none if drop is None else arr(drop(t.corners_w), np.bool_)
                      for t in targets}
        self._mount = kernel_mount(geo)

    def predicted(self, pose: np.ndarray) -> list[tuple[Target, np.ndarray]]:
        """``(target, corners px (4, 2))`` of the targets fully in view from ``pose``
        (a margin of the search window inside the frame): the dark ones first (markers,
        dark blocks), each polarity the largest first, the global path's order. One
        compiled call (:func:`predict_core`)."""
        if not self.targets:
            return []
        x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
        cam = self.geo.camera
        px, order = predict_core(self._mount, (x, y, yaw), self._corners, self._bright,
                                 (float(cam.width), float(cam.height)),
                                 BORDER_PX + self.options.window_px + 1.0)
        return [(self.targets[k], px[k]) for k in order]

    def fixes(self, grey: np.ndarray, pose: np.ndarray,
              accept: Callable[[Target, OutlineFix], Any], most: int
              ) -> tuple[list[Any], int]:
        """Up to ``most`` fixes of the targets in view from ``pose``, in
        :meth:`predicted`'s order (each :meth:`fix` that passes the window check, given
        to ``accept(target, window_fix)``: the estimator's fix, or None), and how many
        targets were tried."""
        out: list[Any] = []
        tried = 0
        for tgt, px in self.predicted(pose):
            tried += 1
            got = self.fix(grey, tgt, px)
            got = accept(tgt, got) if got is not None else None
            if got is not None:
                out.append(got)
                if len(out) >= most:
                    break
        return out, tried

    def fix(self, grey: np.ndarray, tgt: Target, px: np.ndarray) -> OutlineFix | None:
        """The target measured on its predicted outline ``px`` ``(4, 2)`` and solved
        (:func:`.detect.measure_sides` in two passes, :func:`.pnp.solve`), or None when
        the window check fails: a side with fewer than :data:`TRACK_MIN_SHARE` of its
        stations on an edge, the wrong contrast across the outline
        (:func:`.detect.step_contrast` against ``dark_ratio`` / ``bright_ratio``), a
        shape off the block's by more than ``shape_tol``, an edge residual over
        :data:`TRACK_MAX_RMS_PX`, a refined outline more than ``window_px``
        from the predicted one (one compiled call, :func:`window_core`), or what is
        inside the outline is not the target's (:meth:`_inside_ok`)."""
        o = self.options
        reach = self.search_px(tgt, px)
        if reach <= 0.0:
            return None
        check = WindowCheck(float(TRACK_MIN_SHARE * o.edge_points), bool(tgt.dark),
                            float(o.dark_ratio), float(o.bright_ratio), TRACK_MAX_RMS_PX,
                            float(o.shape_tol * tgt.min_side_m), reach)
        out = SidesOut.empty(o.edge_points)
        got = SolvedOut(np.empty(4), np.empty((3, 3)), np.empty((3, 3)))
        # the edges of the target's polarity only (dark inside a dark target, as the
        # fallback measures aruco's markers): a cell inside a small marker, its first
        # inner cells' edges are of the other polarity
        sign = (-1 if signed_area(px) > 0 else 1) * (1 if tgt.dark else -1)
        # a marker's edge level read half a cell either side (quads.edge_points' cells)
        cells = 0 if tgt.marker_id is None else self.codes.cells
        r = window_core(arr(grey, np.uint8), arr(px, np.float64),
                        edge_search(o.edge_points, reach, sign, cells), self._mount,
                        (arr(tgt.corners_w, np.float64), self._drop[tgt.source]), check,
                        out, got)
        if not r.ok or not self._inside_ok(grey, tgt, px, out.corners):
            return None
        sides = Sides(out.corners, out.edge[:r.n], out.side[:r.n], 4 * o.edge_points)
        return OutlineFix(sides, float(got.pose[3]),
                          PlanarFit(got.pose[:3].copy(), got.cov, r.rms_px, r.m, r.var_b,
                                  got.unit if r.has_unit else None))


    def search_px(self, tgt: Target, px: np.ndarray) -> float:
        """How far (px) the first edge pass searches across a target's predicted
        outline ``px`` and its refined outline may move: ``window_px``; for a marker at
        most :data:`MARKER_WINDOW_CELLS` of its cell in the image (its side over its
        cells across, the black border included: its first inner cells' edges, a cell
        in, are of the outline's polarity where a black cell follows a white one), and
        0 (not measured here: the global path reads it) below
        :data:`MARKER_MIN_CELL_PX` a cell. On tiles with 16 cm tags at 3.2 px a cell
        (49 frames, a prior 3 mm off) the window path measured the markers worse than
        the global path on the same frames whatever the search (paired median
        difference +0.22 mm at 4 px, +0.10 mm at 0.6 of a cell, its error 2.5 times
        its sigma at 4 px); at 6-8 px a cell the two agree to a fraction of a mm
        (``tests/runtime/estimators/test_block_track.py``)."""
        reach = float(self.options.window_px)
        if tgt.marker_id is None:
            return reach
        if self.codes is None:
            return 0.0
        cell_px = mean_side_px(arr(px, np.float64)) / self.codes.cells
        return 0.0 if cell_px < MARKER_MIN_CELL_PX else min(reach, MARKER_WINDOW_CELLS * cell_px)

    def _inside_ok(self, grey: np.ndarray, tgt: Target, px: np.ndarray,
                   corners_norm: np.ndarray) -> bool:
        """What the global path checks inside a target, checked inside its outline: a
        block's inside is of its grey all over (at most :data:`FILL_MAX_SHARE` of a
        :data:`FILL_CELLS` squared grid of samples reads as the outside, :func:`fill_core`:
        a block partly painted over, which the global path's quad search does not
        take for the block, is refused); a marker's code, read on the measured corners
        ``corners_norm`` (:func:`.detect.read_marker`), is its id with its top-left
        where the site puts it (unread: refused, the global path reads it)."""
        if tgt.marker_id is None:
            return fill_core(arr(grey, np.uint8), arr(px, np.float64), FILL_CELLS,
                             bool(tgt.dark)) <= FILL_MAX_SHARE
        if self.codes is None:
            return False
        read = read_marker(grey, corners_norm, self.geo, self.codes)
        return read is not None and (read[0], read[1]) == (tgt.marker_id, 0)


@njit
def fill_core(grey, corners, n, dark):  # pragma: no cover - compiled
    """The share of ``n x n`` samples inside the quad ``corners (4, 2)`` px (bilinear in
    its corners, from 0.08 to 0.92 of the way across) that read as the outside: above
    (``dark``; else below) half way between their median and the median just outside
    the quad (:func:`.detect.rim_samples`' 12 outside samples)."""
    outside = rim_samples(grey, corners)[1]
    h, w = grey.shape
    vals = np.empty(n * n)
    for i in range(n):
        a = 0.08 + 0.84 * (i + 0.5) / n
        for j in range(n):
            b = 0.08 + 0.84 * (j + 0.5) / n
            x = ((1 - a) * (1 - b) * corners[0, 0] + a * (1 - b) * corners[1, 0]
                 + a * b * corners[2, 0] + (1 - a) * b * corners[3, 0])
            y = ((1 - a) * (1 - b) * corners[0, 1] + a * (1 - b) * corners[1, 1]
                 + a * b * corners[2, 1] + (1 - a) * b * corners[3, 1])
            vals[i * n + j] = bilinear(grey, x, y, w, h)
    thr = 0.5 * (np.median(vals) + np.median(outside))
    wrong = 0
    for v in vals:
        if (v > thr) if dark else (v < thr):
            wrong += 1
    return wrong / (n * n)


@njit
def predict_core(mount, pose, corners_w, bright, size, margin):  # pragma: no cover
    """:meth:`Windows.predicted` from ``pose (x, y, yaw)`` through the rig ``mount`` (a
    :class:`KernelMount`): ``(px (T, 4, 2), order)``, the targets (corners
    ``corners_w (4 T, 2)``, ``bright (T,)``) fully inside the frame ``size (width,
    height)`` px by ``margin`` px, dark first, each polarity by decreasing area in the
    image."""
    n = bright.size
    x, y, yaw = pose
    width, height = size
    norm = ceiling_norm(mount.R, mount.t, mount.ceiling_m, x, y, yaw, corners_w, 1e-9)
    flat = np.empty_like(norm)
    distort_points(norm, mount.code, mount.lens, flat)
    px = flat.reshape(n, 4, 2)
    key = np.empty(n)
    inside = np.zeros(n, np.bool_)
    lo_u, hi_u = -0.5 + margin, width - 0.5 - margin
    lo_v, hi_v = -0.5 + margin, height - 0.5 - margin
    for i in range(n):
        ok = True
        area = 0.0
        for c in range(4):
            u, v = px[i, c, 0], px[i, c, 1]
            ok = ok and lo_u <= u <= hi_u and lo_v <= v <= hi_v
            nu, nv = px[i, (c + 1) % 4, 0], px[i, (c + 1) % 4, 1]
            area += u * nv - nu * v
        inside[i] = ok
        key[i] = (1e12 if bright[i] else 0.0) - abs(area)
    order = np.argsort(key, kind="mergesort")
    kept = np.empty(n, np.int64)
    m = 0
    for i in order:
        if inside[i]:
            kept[m] = i
            m += 1
    return px, kept[:m]


@njit
def window_core(grey, px, search, mount, target, check, sides, solved):  # pragma: no cover
    """:meth:`Windows.fix` in one call: the target ``target (corners_w (4, 2), drop
    (4,))`` measured about ``px (4, 2)`` (two edge passes as ``search``, a
    :class:`.detect.EdgeSearch`, says), solved through ``mount`` (a :class:`KernelMount`) and
    checked by ``check`` (a :class:`WindowCheck`): a :class:`WindowResult`; the sides
    into ``sides`` (a :class:`.detect.SidesOut`), the pose, shape and covariance into
    ``solved`` (a :class:`.pnp.SolvedOut`) as :func:`.pnp.solve_core` writes them."""
    corners_w, drop = target
    corners, edge, side = sides.corners, sides.edge, sides.side
    out, code, lens = solved.pose, mount.code, mount.lens
    fail = WindowResult(False, 0, 0, np.nan, 0.0, False)
    n = measure_core(grey, px, 2, search, code, lens, sides)
    if n < 0:
        return fail
    counts = np.zeros(4)
    for i in range(n):
        counts[side[i]] += 1.0
    if counts.min() < check.min_count:
        return fail
    cpx = np.empty((4, 2))
    distort_points(corners, code, lens, cpx)
    ratio = contrast_core(grey, cpx)
    if not (ratio < check.dark_ratio if check.dark else ratio > check.bright_ratio):
        return fail
    status, m, rms, var_b, has_unit = solve_core(
        mount, SeenBlock(corners, corners_w, edge[:n], side[:n], drop), solved)
    if status != SOLVED or rms > check.max_rms_px or out[3] > check.max_shape_m:
        return fail
    if not (math.isfinite(out[0]) and math.isfinite(out[1]) and math.isfinite(out[2])):
        return fail
    norm = ceiling_norm(mount.R, mount.t, mount.ceiling_m, out[0], out[1], out[2],
                        corners_w, 1e-9)
    moved = np.empty((4, 2))
    distort_points(norm, code, lens, moved)
    for c in range(4):
        if not math.hypot(moved[c, 0] - px[c, 0],
                          moved[c, 1] - px[c, 1]) <= check.window_px:
            return fail
    return WindowResult(True, n, m, rms, var_b, has_unit)


@warmer
def _warm() -> None:
    from types import SimpleNamespace

    from ceilkit.runtime.geometry.camera import CameraModel
    geo = PlanarGeometry(CameraModel.pinhole(64, 48, 40.0), np.eye(3), np.zeros(3), 3.0)
    square = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    options = SimpleNamespace(window_px=4.0, edge_points=4, dark_ratio=0.6,
                              bright_ratio=1.3, shape_tol=0.08)
    win = Windows(geo, [Target("block:warm", square, True, True, 1.0)], options)
    grey = np.full((48, 64), 200, np.uint8)
    win.fix(grey, win.targets[0], win.predicted((0.0, 0.0, 0.0))[0][1])
    fill_core(grey, arr(square * 10.0 + 20.0, np.float64), 2, True)
    mean_side_px(arr(square, np.float64))
