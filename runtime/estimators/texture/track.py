"""The ``texture`` method's tracked fast path: the pose refined from a tight prior by
following the map's own features into the frame, no detection, no descriptor.

The frame is rectified a level coarser than the map (2 cm, :data:`.estimator.TRACK_LEVELS`);
the map's mosaic is pyramided alike once, when the map is loaded
(:class:`MapTracker`). Per frame, the map features the prior puts inside the frame's
patch are ranked (:func:`corner_scores`: the smaller eigenvalue of the mosaic's
structure tensor about each, rotation invariant, computed once) and at most
:data:`PER_CELL` of the best are kept in each of :data:`CELLS` x CELLS cells of the
patch (:data:`MAX_POINTS` in all, spread). Each is followed into the frame's patch by
a Lucas-Kanade of its own (:func:`_lk_level`, one compiled loop a pyramid level):
its template is the mosaic about the feature sampled as the prior says the patch
shows it (turned by the prior's yaw; only those ``(2h + 3)²`` pixels, not the whole
predicted patch), its parameters a translation and a grey offset (the frame's
exposure is not the mosaic's), solved inverse-compositionally (the template's
gradients and normal matrix once per feature and level). The features are taken each
cell's best first, then each cell's second, ...; once :data:`PREDICT_AFTER` are
followed, each further one starts where the affine fit of those followed puts it
(:func:`_predicted`: the prior's error is a turn and a shift, affine over the patch),
not at the prior's prediction: two iterations instead of four to six from a prior
1 cm and 0.5° off. A feature is kept when the
finest level converged inside the patch's valid part and its window correlates with
the template at :data:`MIN_ZNCC` or more. The patch's own level is tried first (its
basin, about ``LK_HALF / 2`` pixels, holds a tracked prior's error); when that does
not give a pose, again from :data:`LK_LEVELS` coarser.

A feature at predicted patch pixel ``u`` found at ``u + d`` gives the pair
``q_V = (u + d - c) res`` ~ ``p_W`` (the map's point), and the pairs give the pose by
the same least squares as the global path (:func:`.match.refine`), from a rigid fit
of those within 3 MADs of the fit of all (:func:`_fit_pairs`). Each frame is tied to
the map, not to the previous frame: no drift. Under a rolling shutter (a
:class:`.shutter.Readout`) each found place is first put back to the stamp at the
prior's heading and the fit's covariance grown by the velocity's sigmas, as on the
global path; when the prior has no velocity, the frame's own is fitted with the pose
where its rows determine it (:func:`_unrolled_fit`).

What the fast path cannot do is enumerate twins: it converges to the pose nearest the
prior. The estimator takes it only when the prior's region is too narrow to hold a
twin (``window_twin_m``, :func:`~ceilkit.runtime.estimators.prior.narrower_than`), and
publishes its pose only where the prior's region holds it.

Example::

    tracker = MapTracker(cmap, levels=1)       # once per map
    got = tracker.follow(patch, valid, prior_pose, 0.03, 0.002, 12)
    got.refined.pose if got is not None else None
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap, _eroded, coarser
from ceilkit.runtime.estimators.texture.match import (
    Fitting,
    MapFit,
    Pairs,
    _refine,
    _residuals,
    _rigid,
    places,
)
from ceilkit.runtime.estimators.texture.shutter import Readout, joint_fit, widened
from ceilkit.runtime.jit import arr, njit, warmer

CELLS = 4                # the patch's CELLS x CELLS cells ...
PER_CELL = 4             # ... each keeps its best-ranked features, at most this many
MAX_POINTS = CELLS * CELLS * PER_CELL   # map features followed per frame, at most
LK_HALF = 4              # Lucas-Kanade window: (2 LK_HALF + 1)² patch pixels
LK_LEVELS = 1            # pyramid levels above the patch (basin about 2^L LK_HALF px)
LK_ITERS = 20            # iterations a level, at most
LK_EPS_PX = 0.02         # ... stopping when a step is shorter (patch pixels)
MIN_ZNCC = 0.8           # a followed window's correlation with its template, at least
PREDICT_AFTER = 6        # features followed before the rest start from their prediction


@dataclass(frozen=True, eq=False)
class Tracked:
    """The fast path's pose and the pairs it rests on.

    Attributes:
        refined: the least-squares pose on the pairs within the tolerance.
        followed: map features followed into the frame (converged, correlating).
        predicted: map features the prior put inside the patch and were followed from.
        inlier_xy: ``(N, 2)`` the map features the pose rests on (``refined.used``), W, m.
    """

    refined: MapFit
    followed: int
    predicted: int
    inlier_xy: np.ndarray


class FeatureGrid:
    """The map's features bucketed in square cells of ``cell_m`` (sorted by cell, a row
    of cells contiguous): those near a point at the cost of the cells they fill, not
    of the map."""

    def __init__(self, points_xy: np.ndarray, cell_m: float = 1.0) -> None:
        self.cell_m = float(cell_m)
        ij = np.floor(np.asarray(points_xy, float) / self.cell_m).astype(np.int64)
        self.lo = ij.min(0) if len(ij) else np.zeros(2, np.int64)
        ij -= self.lo
        self.size = (ij.max(0) + 1) if len(ij) else np.ones(2, np.int64)
        key = ij[:, 1] * self.size[0] + ij[:, 0]
        self.order = arr(np.argsort(key, kind="stable"), np.int64)
        self.starts = arr(np.searchsorted(key[self.order], np.arange(self.size.prod() + 1)),
                          np.int64)

    def cells(self, x: float, y: float, half_m: float) -> tuple[int, int, int, int]:
        """``(i0, j0, i1, j1)``: the cells (column, row; clipped to the grid, empty when
        ``i1 < i0`` or ``j1 < j0``) that meet the square of half side ``half_m`` about
        ``(x, y)``: their features are a superset of those inside it."""
        c, (lx, ly), (nx, ny) = self.cell_m, self.lo.tolist(), self.size.tolist()
        return (max(math.floor((x - half_m) / c) - lx, 0),
                max(math.floor((y - half_m) / c) - ly, 0),
                min(math.floor((x + half_m) / c) - lx, nx - 1),
                min(math.floor((y + half_m) / c) - ly, ny - 1))

    def within(self, x: float, y: float, half_m: float) -> np.ndarray:
        """Indices of the features in the cells that meet the square of half side
        ``half_m`` about ``(x, y)`` (a superset of the features inside it)."""
        i0, j0, i1, j1 = self.cells(x, y, half_m)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, np.int64)
        st, nx = self.starts, int(self.size[0])
        rows = [self.order[st[j * nx + i0]:st[j * nx + i1 + 1]] for j in range(j0, j1 + 1)]
        return np.concatenate(rows)


class MapTracker:
    """The map made ready for the fast path, once per map: its mosaic at the patch's
    resolution (``levels`` coarser than the map) and :data:`LK_LEVELS` coarser, each
    feature's mosaic pixel and rank (:func:`corner_scores`), the grid of features."""

    def __init__(self, cmap: CeilingMap, levels: int) -> None:
        self.map = coarser(cmap, levels)
        mosaics = [self.map.mosaic]
        for _ in range(LK_LEVELS):
            mosaics.append(cv2.pyrDown(mosaics[-1]))
        self.mosaics = tuple(arr(m, np.uint8) for m in mosaics)
        # a feature with several descriptors is one point to follow: its first row
        points = cmap.points_xy[np.unique(places(cmap.points_xy)[0])]
        self.points_px = arr(self.map.pixel_of(points), np.float64)
        self.score = arr(corner_scores(self.mosaics[0], self.points_px, LK_HALF), np.float64)
        self.grid = FeatureGrid(points) if len(points) else None
        self._valid: np.ndarray | None = None
        self._inner = np.zeros((0, 0), np.uint8)

    def visible(self, pose: tuple[float, float, float], inner: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """``(idx (M,), uv (M, 2))``: the map features the pose puts where ``inner``
        (the patch's valid part, eroded by the window) holds, their predicted patch
        pixels ``(col, row)``; the best :data:`PER_CELL` by rank of each cell."""
        n = inner.shape[0]
        x, y, yaw = pose
        if self.grid is None:
            return np.zeros(0, np.int64), np.zeros((0, 2))
        g, res = self.grid, self.map.resolution_m
        i0, j0, i1, j1 = g.cells(x, y, math.sqrt(2.0) * n * res / 2)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, np.int64), np.zeros((0, 2))
        ox, oy = self.map.origin_xy
        return _visible(self.points_px, self.score,
                        GridCells(g.order, g.starts, int(g.size[0]), i0, j0, i1, j1), inner,
                        Placement((x - ox) / res, (y - oy) / res, math.cos(yaw), math.sin(yaw)),
                        CELLS, PER_CELL)

    def inner(self, valid: np.ndarray) -> np.ndarray:
        """``valid`` (a rectifier's mask) eroded by the Lucas-Kanade window: where a
        window lies wholly on the ceiling; made once per mask (the estimator makes it at
        construction, not on the first frame)."""
        if valid is not self._valid:     # the rectify tables' own array: made once
            self._valid = valid
            self._inner = arr(_eroded(np.ascontiguousarray(valid, np.uint8).tobytes(),
                                      valid.shape, LK_HALF + 2), np.uint8)
        return self._inner

    def follow(self, patch: np.ndarray, valid: np.ndarray, pose: tuple[float, float, float],
               tol_m: float, sigma_floor_m: float, min_points: int,
               readout: Readout | None = None) -> Tracked | None:
        """The pose refined from ``pose`` (the prior) on the frame's rectified patch at
        this tracker's resolution (see the module docstring), or None with fewer than
        ``min_points`` map features followed or fitting within ``tol_m``. With a
        rolling shutter (``readout``) the found places are put back to the stamp
        first and the covariance grown (:mod:`.shutter`)."""
        inner = self.inner(valid)
        idx, uv = self.visible(pose, inner)
        if len(idx) < min_points:
            return None
        mpx = arr(self.points_px[idx], np.float64)
        ox, oy = self.map.origin_xy
        frame = PatchFrame((patch.shape[0] - 1) / 2, self.map.resolution_m, ox, oy)
        for levels in sorted({0, LK_LEVELS}):
            found, ok = self._lk(patch, inner, mpx, uv, pose[2], levels)
            if readout is not None:
                q_raw = (found - frame.centre) * frame.res
                tau = readout.times(q_raw)
                found = readout.unrolled(q_raw, tau, pose[2]) / frame.res + frame.centre
            good, x, y, yaw, cov, used, rms, followed = _fit_pairs(
                found, ok, mpx, frame, Fitting(tol_m, sigma_floor_m, 1), min_points)
            if good:
                fit = MapFit((x, y, yaw), cov, np.flatnonzero(used), rms)
                if readout is not None:   # _fit_pairs' pairs: the followed, in order
                    fit = _unrolled_fit(fit, readout, q_raw[ok], tau[ok],
                                        frame, mpx[ok], (tol_m, sigma_floor_m))
                xy = np.asarray(self.map.origin_xy) + mpx[ok][fit.used] * frame.res
                return Tracked(fit, followed, len(idx), xy)
        return None

    def _lk(self, patch: np.ndarray, inner: np.ndarray, mpx: np.ndarray, uv: np.ndarray,
            yaw: float, levels: int) -> tuple[np.ndarray, np.ndarray]:
        """``(found (M, 2), ok (M,))``: where the window of each feature (mosaic pixel
        ``mpx``, predicted at patch pixel ``uv``) lies in the patch, coarse to fine from
        ``levels`` above it (:func:`_lk_level`), and whether it was followed."""
        pyr = [arr(patch, np.uint8)]
        for _ in range(levels):
            pyr.append(arr(cv2.pyrDown(pyr[-1]), np.uint8))
        d = np.zeros((len(mpx), 2))
        ok = np.ones(len(mpx), np.bool_)
        c, s = math.cos(yaw), math.sin(yaw)
        fol = Following(mpx, arr(uv, np.float64), inner, c, s)   # read-only, as warmed
        for level in range(levels, -1, -1):
            _lk_level(Level(self.mosaics[level], pyr[level], 0.5 ** level, level == 0), fol,
                      LK, d, ok)
            if level:
                d *= 2.0
        d += uv
        return d, ok


@njit
def corner_scores(mosaic, points_px, half):  # pragma: no cover - compiled
    """``(N,)``: the smaller eigenvalue of the structure tensor (central differences,
    grey levels² per pixel, mean over the ``(2 half + 1)²`` window) of the mosaic about
    each feature's pixel ``(col, row)`` (N, 2): how well a window there pins a
    translation; 0 off the mosaic. Nearly rotation invariant: a rank of the features
    for following whatever the heading."""
    out = np.zeros(len(points_px))
    h, w = mosaic.shape
    for k in range(len(points_px)):
        c0, r0 = int(round(points_px[k, 0])), int(round(points_px[k, 1]))
        if c0 - half - 1 < 0 or r0 - half - 1 < 0 or c0 + half + 1 >= w or r0 + half + 1 >= h:
            continue
        a = b = cc = 0.0
        for r in range(r0 - half, r0 + half + 1):
            for c in range(c0 - half, c0 + half + 1):
                gx = 0.5 * (np.float64(mosaic[r, c + 1]) - mosaic[r, c - 1])
                gy = 0.5 * (np.float64(mosaic[r + 1, c]) - mosaic[r - 1, c])
                a += gx * gx
                b += gx * gy
                cc += gy * gy
        m = (2 * half + 1) ** 2
        a, b, cc = a / m, b / m, cc / m
        out[k] = 0.5 * (a + cc) - math.sqrt(0.25 * (a - cc) ** 2 + b * b)
    return out


class GridCells(NamedTuple):
    """A block of :class:`FeatureGrid`'s cells as the compiled loops take it: the
    grid's ``order`` and ``starts``, ``nx`` cells a row, the cells ``i0..i1`` x
    ``j0..j1`` (column, row; inside the grid)."""

    order: np.ndarray
    starts: np.ndarray
    nx: int
    i0: int
    j0: int
    i1: int
    j1: int


class Placement(NamedTuple):
    """Where a patch lies on the mosaic: its centre at mosaic pixel ``(px, py)``, turned
    by ``(c, s)`` (the cosine and sine of the vehicle's yaw)."""

    px: float
    py: float
    c: float
    s: float


@njit
def _visible(points_px, score, grid, inner, at, cells,
             per_cell):  # pragma: no cover - compiled
    """:meth:`MapTracker.visible` over the features of the cells ``grid``: each
    feature's patch pixel from its mosaic pixel (the patch ``at``), kept where ``inner``
    holds; then by ``score``, highest first, at most ``per_cell`` a cell of the patch
    (``cells`` x ``cells``). In the order each cell's best, then each cell's second, ...:
    the first features followed are spread over the patch (:func:`_lk_level`'s
    prediction)."""
    order, starts, nx = grid.order, grid.starts, grid.nx
    i0, j0, i1, j1 = grid.i0, grid.j0, grid.i1, grid.j1
    px, py, c, s = at.px, at.py, at.c, at.s
    n = inner.shape[0]
    half = (n - 1) / 2.0
    m = 0
    for j in range(j0, j1 + 1):
        m += starts[j * nx + i1 + 1] - starts[j * nx + i0]
    cand = np.empty(m, np.int64)
    t = 0
    for j in range(j0, j1 + 1):
        for r in range(starts[j * nx + i0], starts[j * nx + i1 + 1]):
            cand[t] = order[r]
            t += 1
    uv = np.empty((m, 2))
    keep = np.zeros(m, np.bool_)
    key = np.empty(m)
    for k in range(m):
        dx = points_px[cand[k], 0] - px
        dy = points_px[cand[k], 1] - py
        u = c * dx + s * dy + half
        v = -s * dx + c * dy + half
        uv[k, 0], uv[k, 1] = u, v
        iu, iv = int(round(u)), int(round(v))
        keep[k] = 0 <= iu < n and 0 <= iv < n and inner[iv, iu] > 0
        key[k] = -score[cand[k]]
    # each cell's best per_cell, by insertion (a handful a cell, hundreds of candidates)
    best = np.full((cells * cells, per_cell), -1, np.int64)
    for k in range(m):
        if not keep[k]:
            continue
        cell = min(int(uv[k, 1] * cells / n), cells - 1) * cells + \
            min(int(uv[k, 0] * cells / n), cells - 1)
        j = per_cell
        while j > 0 and (best[cell, j - 1] < 0 or key[best[cell, j - 1]] > key[k]):
            j -= 1
        if j < per_cell:
            best[cell, j + 1:] = best[cell, j:-1].copy()
            best[cell, j] = k
    count = 0
    for t in range(cells * cells):
        for j in range(per_cell):
            count += best[t, j] >= 0
    out_uv = np.empty((count, 2))
    out_idx = np.empty(count, np.int64)
    t = 0
    for j in range(per_cell):           # each cell's best, then each one's second, ...
        for cell in range(cells * cells):
            k = best[cell, j]
            if k >= 0:
                out_idx[t] = cand[k]
                out_uv[t, 0], out_uv[t, 1] = uv[k, 0], uv[k, 1]
                t += 1
    return out_idx, out_uv


class LKSettings(NamedTuple):
    """The Lucas-Kanade's window half side ``half`` (px), its ``iters`` a level and the
    step ``eps`` (px) that ends them, the correlation ``min_zncc`` a followed window
    needs."""

    half: int
    iters: int
    eps: float
    min_zncc: float


LK = LKSettings(LK_HALF, LK_ITERS, LK_EPS_PX, MIN_ZNCC)


class Level(NamedTuple):
    """One pyramid level: the ``mosaic`` and the frame's ``patch`` there, ``scale`` its
    pixels per level-0 pixel, ``final``: the patch's own level (level 0)."""

    mosaic: np.ndarray
    patch: np.ndarray
    scale: float
    final: bool


class Following(NamedTuple):
    """The features followed: their mosaic pixels ``mpx (M, 2)`` and predicted patch
    pixels ``uv (M, 2)`` (level 0), the patch's valid part eroded by the window
    ``inner``, the prior's turn ``(c, s)``."""

    mpx: np.ndarray
    uv: np.ndarray
    inner: np.ndarray
    c: float
    s: float


@njit
def _lk_level(level, fol, lk, d, ok):  # pragma: no cover - compiled
    """One pyramid level of each feature's Lucas-Kanade (see the module docstring),
    in place: ``d (M, 2)`` the displacement from ``uv`` (the level-0 patch pixels
    ``uv``, the mosaic pixels ``mpx`` and ``d`` all times ``scale`` at this level);
    ``ok`` cleared where the template leaves the mosaic or is flat, or (``final``) the
    window leaves the patch, does not converge, correlates with the template under
    ``min_zncc`` or ends where ``inner`` (the patch's valid part, eroded) does not
    hold. A coarse level whose window leaves the patch keeps its displacement (the
    finer one decides). The window moves as a whole: one bilinear weight set an
    iteration for all its pixels."""
    mosaic, patch, scale, final = level.mosaic, level.patch, level.scale, level.final
    mpx, uv, inner, c, s = fol.mpx, fol.uv, fol.inner, fol.c, fol.s
    half, iters, eps, min_zncc = lk.half, lk.iters, lk.eps, lk.min_zncc
    w = 2 * half + 1
    centre = 0.5 * (patch.shape[0] - 1)
    acc = np.zeros(12)
    tpl = np.empty((w + 2, w + 2))
    gx = np.empty((w, w))
    gy = np.empty((w, w))
    win = np.empty((w, w))
    for k in range(len(mpx)):
        if not ok[k]:
            continue
        u0, v0 = uv[k, 0] * scale - half, uv[k, 1] * scale - half
        if not _template(mosaic, mpx[k, 0] * scale, mpx[k, 1] * scale, c, s, half, tpl):
            ok[k] = False
            continue
        good, i00, i01, i02, i11, i12 = _inverse_rows(tpl, w, gx, gy)
        if not good:
            ok[k] = False
            continue
        dx, dy = d[k, 0], d[k, 1]
        if dx == 0.0 and dy == 0.0 and acc[0] >= PREDICT_AFTER:
            dx, dy = _predicted(acc, uv[k, 0] * scale - centre, uv[k, 1] * scale - centre)
        inside, done = True, False
        for _ in range(iters):
            inside = _window(patch, u0 + dx, v0 + dy, w, win)
            if not inside:
                break
            bx = by = bb = 0.0
            for i in range(w):
                for j in range(w):
                    e = win[i, j] - tpl[i + 1, j + 1]
                    bx += gx[i, j] * e
                    by += gy[i, j] * e
                    bb += e
            sx = i00 * bx + i01 * by + i02 * bb
            sy = i01 * bx + i11 * by + i12 * bb
            dx -= sx
            dy -= sy
            if sx * sx + sy * sy < eps * eps:
                done = True
                break
        if not inside:
            ok[k] = not final
            continue
        d[k, 0], d[k, 1] = dx, dy
        if final:
            ok[k] = done and _window(patch, u0 + dx, v0 + dy, w, win) and \
                _zncc(win, tpl, half) >= min_zncc
            iu, iv = int(round(u0 + half + dx)), int(round(v0 + half + dy))
            ok[k] &= 0 <= iu < inner.shape[1] and 0 <= iv < inner.shape[0] and \
                inner[iv, iu] > 0
        if done and ok[k]:
            _add_shift(acc, u0 + half - centre, v0 + half - centre, dx, dy)
    return d


@njit
def _inverse_rows(tpl, w, gx, gy):  # pragma: no cover - compiled
    """Fill ``gx, gy (w, w)`` with the template's gradients (central differences of
    ``tpl (w + 2, w + 2)``); ``(good, i00, i01, i02, i11, i12)``: the rows of the inverse
    of the normal matrix ``[[hxx, hxy, hx], [hxy, hyy, hy], [hx, hy, w²]]`` (translation
    and grey offset) that give the translation; not good when it is near singular (a
    flat or one-directional template)."""
    hxx = hxy = hyy = hx = hy = 0.0
    for i in range(w):
        for j in range(w):
            a = 0.5 * (tpl[i + 1, j + 2] - tpl[i + 1, j])
            b = 0.5 * (tpl[i + 2, j + 1] - tpl[i, j + 1])
            gx[i, j], gy[i, j] = a, b
            hxx += a * a
            hxy += a * b
            hyy += b * b
            hx += a
            hy += b
    m = float(w * w)
    c00, c01, c02 = hyy * m - hy * hy, hx * hy - hxy * m, hxy * hy - hyy * hx
    c11, c12 = hxx * m - hx * hx, hxy * hx - hxx * hy
    det = hxx * c00 + hxy * c01 + hx * c02
    if not det > 1e-6 * m * (hxx + hyy) ** 2:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    return True, c00 / det, c01 / det, c02 / det, c11 / det, c12 / det


@njit
def _add_shift(acc, u, v, dx, dy):  # pragma: no cover - compiled
    """Add a followed feature (at ``(u, v)`` from the patch's centre, displaced by
    ``(dx, dy)``) to ``acc`` (12,): the sums of the least squares of the displacement
    as an affine function of the place, ``d = a + b u + c v`` a coordinate (the
    count, the normal matrix's five other sums, then those of ``dx`` and ``dy``)."""
    acc[0] += 1.0
    acc[1] += u
    acc[2] += v
    acc[3] += u * u
    acc[4] += u * v
    acc[5] += v * v
    acc[6] += dx
    acc[7] += u * dx
    acc[8] += v * dx
    acc[9] += dy
    acc[10] += u * dy
    acc[11] += v * dy


@njit
def _predicted(acc, u, v):  # pragma: no cover - compiled
    """``(dx, dy)``: the displacement at ``(u, v)`` of the affine fit of the features in
    ``acc`` (:func:`_add_shift`; the prior's error is a turn and a shift, affine over
    the patch); ``(0, 0)`` when their places are nearly on a line."""
    n, su, sv, suu, suv, svv = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5]
    c00, c01, c02 = suu * svv - suv * suv, sv * suv - su * svv, su * suv - sv * suu
    c11, c12, c22 = n * svv - sv * sv, su * sv - n * suv, n * suu - su * su
    det = n * c00 + su * c01 + sv * c02
    if not det > 1e-9 * (n * suu * svv + 1.0):
        return 0.0, 0.0
    out = np.zeros(2)
    for a in range(2):
        b0, b1, b2 = acc[6 + 3 * a], acc[7 + 3 * a], acc[8 + 3 * a]
        k0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
        k1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
        k2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
        out[a] = k0 + k1 * u + k2 * v
    return out[0], out[1]


@njit
def _template(mosaic, cx, cy, c, s, half, tpl):  # pragma: no cover - compiled
    """Fill ``tpl (w + 2, w + 2)`` with the mosaic (bilinear) about ``(cx, cy)`` as a
    patch turned by ``(c, s)`` shows it (patch offset ``(a, b)`` at mosaic
    ``(cx + c a - s b, cy + s a + c b)``); False when it leaves the mosaic."""
    h, w = mosaic.shape
    r = (half + 1) * 1.4143 + 1.0
    if not (r <= cx < w - 1 - r and r <= cy < h - 1 - r):
        return False
    n = tpl.shape[0]
    for i in range(n):
        for j in range(n):
            a, b = j - half - 1.0, i - half - 1.0
            x, y = cx + c * a - s * b, cy + s * a + c * b
            x0, y0 = int(x), int(y)
            fx, fy = x - x0, y - y0
            top = mosaic[y0, x0] + fx * (np.float64(mosaic[y0, x0 + 1]) - mosaic[y0, x0])
            bot = mosaic[y0 + 1, x0] + fx * (np.float64(mosaic[y0 + 1, x0 + 1])
                                              - mosaic[y0 + 1, x0])
            tpl[i, j] = top + fy * (bot - top)
    return True


@njit
def _window(img, x, y, w, out):  # pragma: no cover - compiled
    """Fill ``out (w, w)`` with the image (bilinear) at ``(x + j, y + i)``: one shift
    for the whole window, so one set of weights; False when it leaves the image."""
    h, wi = img.shape
    if not (0.0 <= x and 0.0 <= y and x + w < wi and y + w < h):
        return False
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    w00, w01, w10, w11 = (1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy
    for i in range(w):
        r0, r1 = img[y0 + i], img[y0 + i + 1]
        for j in range(w):
            out[i, j] = (w00 * r0[x0 + j] + w01 * r0[x0 + j + 1] + w10 * r1[x0 + j]
                         + w11 * r1[x0 + j + 1])
    return True


@njit
def _zncc(win, tpl, half):  # pragma: no cover - compiled
    """The normalized cross-correlation of a window ``(w, w)`` with the template's
    inside (``tpl[1:-1, 1:-1]``); 0 when either is flat."""
    w = 2 * half + 1
    sa = sb = saa = sbb = sab = 0.0
    for i in range(w):
        for j in range(w):
            a, b = win[i, j], tpl[i + 1, j + 1]
            sa += a
            sb += b
            saa += a * a
            sbb += b * b
            sab += a * b
    m = w * w
    va, vb = saa - sa * sa / m, sbb - sb * sb / m
    if va <= 0.0 or vb <= 0.0:
        return 0.0
    return (sab - sa * sb / m) / math.sqrt(va * vb)


def _unrolled_fit(fit: MapFit, readout: Readout, q_raw: np.ndarray, tau: np.ndarray,
                  frame: PatchFrame, mpx: np.ndarray, tol: tuple[float, float]) -> MapFit:
    """The followed pairs' fit under a rolling shutter: with the prior's velocity
    ``fit`` (on the places put back to the stamp) with its covariance grown
    (:func:`.shutter.widened`); without, the frame's own velocity fitted with the pose
    where its rows determine it (:func:`.shutter.joint_fit`, on the places as observed,
    ``q_raw`` at row times ``tau``, against the map's ``mpx``; ``tol``: the inlier
    tolerance and the covariance's floor, m), else the ``unknown_*`` growth."""
    if not readout.known:
        p = np.column_stack([frame.ox + mpx[:, 0] * frame.res, frame.oy + mpx[:, 1] * frame.res])
        joint = joint_fit(q_raw, tau, p, np.arange(len(p)), fit.pose, *tol, readout.sigma)
        if joint is not None:
            return joint
    return widened(fit, readout, q_raw, tau)


class PatchFrame(NamedTuple):
    """A patch's pixel ``(col, row)`` as a point of V, ``((col, row) - centre) res``,
    and a mosaic pixel as one of W, ``(ox, oy) + (col, row) res`` (m)."""

    centre: float
    res: float
    ox: float
    oy: float


@njit
def _fit_pairs(found, ok, mpx, frame, fitting, min_points):  # pragma: no cover - compiled
    """The pose of the followed features (``ok``): pairs ``q_V = (found - centre) res``
    ~ ``p_W = origin + mpx res`` (m, ``frame``), robust to a few followed to the wrong
    place (``fitting``'s tolerance ``tol``; one round of refining): the
    rigid fit of all; again of those within 3 MADs of its residuals (or ``tol``); then
    :func:`.match.refine`'s least squares (one round, every pair its own feature) on
    the pairs within ``tol`` of that. Returns ``(good, x, y, yaw, cov (3, 3), used (N,)
    bool over the followed, rms_m, followed)``: good with ``min_points`` followed and
    used; the covariance ``s² (JᵀJ)⁻¹``, ``s²`` the residuals' variance per axis
    (``2n - 3`` dof), never below ``sigma_floor²``."""
    centre, res, ox, oy = frame.centre, frame.res, frame.ox, frame.oy
    tol = fitting.tol
    n = 0
    for k in range(len(ok)):
        n += ok[k]
    q = np.empty((n, 2))
    p = np.empty((n, 2))
    j = 0
    for k in range(len(ok)):
        if ok[k]:
            q[j, 0], q[j, 1] = (found[k, 0] - centre) * res, (found[k, 1] - centre) * res
            p[j, 0], p[j, 1] = ox + mpx[k, 0] * res, oy + mpx[k, 1] * res
            j += 1
    used = np.ones(n, np.bool_)
    if n < max(min_points, 3):
        return False, 0.0, 0.0, 0.0, np.zeros((3, 3)), used, 0.0, n
    x, y, yaw = _rigid(q, p, used)
    r = _residuals(q, p, x, y, yaw)
    med = np.median(r)
    keep = r <= max(med + 3.0 * 1.4826 * med, tol)
    if keep.sum() < 3:
        return False, x, y, yaw, np.zeros((3, 3)), used, 0.0, n
    x, y, yaw = _rigid(q, p, keep)
    good, x, y, yaw, cov, idx, rms = _refine(Pairs(q, p, np.zeros(n, np.int64)), False,
                                             (x, y, yaw), fitting)
    used = np.zeros(n, np.bool_)
    used[idx] = True
    return good and len(idx) >= min_points, x, y, yaw, cov, used, rms, n


@warmer
def _warm() -> None:
    g = np.zeros((24, 24), np.uint8)
    g[8:16, 8:16] = 200
    pts = arr(np.array([[12.0, 12.0]]), np.float64)
    corner_scores(arr(g, np.uint8), pts, 2)
    grid = FeatureGrid(pts)
    inner = arr(np.ones((24, 24), np.uint8), np.uint8)
    _visible(pts, arr(np.ones(1), np.float64), GridCells(grid.order, grid.starts, 1, 0, 0, 0, 0),
             inner, Placement(12.0, 12.0, 1.0, 0.0), 2, 2)
    d, ok = np.zeros((1, 2)), np.ones(1, np.bool_)
    for final in (False, True):
        _lk_level(Level(arr(g, np.uint8), arr(g, np.uint8), 1.0, final),
                  Following(pts, pts, inner, 1.0, 0.0), LK, d, ok)
    q = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    _fit_pairs(q, np.ones(4, np.bool_), arr(q, np.float64), PatchFrame(0.5, 0.02, 0.0, 0.0),
               Fitting(0.03, 0.001, 1), 3)


__all__ = ["FeatureGrid", "MapTracker", "Tracked", "corner_scores"]
