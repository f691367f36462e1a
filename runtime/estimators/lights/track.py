"""The tracked fast path of ``lights``: look for each light only where the prior says.

With a prior pose (the tracker's or the fusion's prediction), the map lights the
detector should report from it (:class:`~.observe.VisibilityTable`) are placed in
the image by one lookup (:func:`prediction_cells`, no projection per frame), and each
is looked for in a small square window around its predicted pixel (a few hundred
pixels, all windows in one stack: :func:`~ceilkit.runtime.features.windows.window_stats`):
the window's border gives the
background ``I_b``, the pixels above half way from it to the window's peak are the
light, ``I_o`` their mean, and the centroid is weighted by ``max(I - I_b - 0.4 (I_o -
I_b), 0)``, the same reading as the global detector's
(:func:`~ceilkit.runtime.features.spots.detect_spots`). The association is known (a
window is its light's), so the pose is :func:`~.refine.refine_pose_ceiling` from the
prior, with the same outlier pass as the global path.

The whole path, from the prior to the refined pose, is one compiled call
(:func:`_track`, :mod:`ceilkit.runtime.jit`): a tracked frame is a few thousand pixels
and a dozen 3x3 solves, which in numpy cost a hundred calls of a few microseconds each.
Its stages (:func:`_predict`, :func:`_measure`, :func:`_fit`) are the same reading as
the array functions they stand for (:meth:`~.observe.VisibilityTable.locate`,
:func:`~ceilkit.runtime.features.windows.window_stats`,
:class:`~.rays.GridTable`, :func:`~.observe.plausible_spot`,
:func:`~.rays.ceiling_points`, :func:`~.refine.refine_pose_ceiling`), and are tested
against them.

The window check: a light counts when its window has contrast, its bright part does
not touch the window's border (not cut off, not a neighbour's), and its area and
shape fit the light at that place (:func:`~.observe.plausible_spot`); the
frame is accepted when most predicted lights were found (the same share the global
path asks of a trusted prior), at least three fit after refinement, their residual is
small and the pose stayed within the prior gate. Anything else returns ``None`` and
the estimator runs its global path (the fallback and the check); so does every
``full_every``-th tracked frame (a schedule).

Convention (SPEC §1): pixels distorted; ceiling points in V, metres.

Example::

    fast = WindowTracker(rig, H, lights_w, observer, visibility, window_px=10)
    found = fast.observe(grey, prior_x, prior_y, prior_yaw)   # WindowFix | None
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.lights.observe import (
    JAC_STEP_PX,
    GridArrays,
    SpotObserver,
    VisibilityTable,
    locate_core,
    plausible_spot,
)
from ceilkit.runtime.estimators.lights.rays import (
    ceiling_points_core,
    grid_row,
    interp_grid,
    pixel_scale,
    project_lights,
)
from ceilkit.runtime.estimators.lights.refine import (
    SHIFT_MIN_DOF,
    SIGMA_FLOOR_PX,
    NoisePool,
    _pattern_cover,
    _refine,
)
from ceilkit.runtime.features.spots import FLAT
from ceilkit.runtime.features.windows import read_windows_core
from ceilkit.runtime.jit import arr, njit, warmer

TRACK_CORE = 0.6
"""A window's centroid weights count from ``I_b + TRACK_CORE (I_o - I_b)``. A window's
``I_o`` is the mean above half way from its border to its peak, higher than the global
detector's region mean, so the global detector's 0.4
(:data:`~ceilkit.runtime.features.windows.CORE`) took in more of the halo there: on
bench_paired's lights drive (300 frames, prior 1 cm / 0.1 deg off) the window fix's
position median/p95 was 0.288/0.550 mm with 0.4 against the global path's 0.256/0.478
(mean y error -0.169 against -0.141); with 0.5 0.236/0.445, 0.6 0.211/0.437, 0.7
0.218/0.474, 0.8 0.259/0.536. On the 17 bench_realistic lights cases (tracked) 0.6
against 0.4 was better or equal in 15 (fixtures 0.23 against 0.63 mm, flicker 0.21
against 0.35, windows 0.17 against 0.28), worse in people (0.19 against 0.17) and in
jpeg's yaw (0.0030 against 0.0028 deg)."""

MAX_HALF_PX = 40
"""A window is at most ``2 MAX_HALF_PX + 1`` pixels wide (large spots near the nadir)."""


def prediction_cells(rig: Rig, ceiling_height_m: float, visibility: VisibilityTable,
                     spot_table: np.ndarray) -> np.ndarray:
    """``(cells, 9)`` per cell of the visibility table (padded, in the order of
    :meth:`~.observe.VisibilityTable.locate`): the cell centre in V ``(qx, qy)``, its
    pixel ``(u, v)``, the pixel Jacobian there ``d(u, v)/d(qx, qy)`` (row-major) and the
    predicted spot area (px², from the spot table); NaN where the cell is not seen.

    A light's pixel is the centre's plus the Jacobian times the light's offset from the
    centre (at most half a cell): off by the map's curvature over half a cell, a few
    hundredths of a pixel for the fisheye of configs/lights (10 cm cells), against a
    window margin of ``window_px``. Built once per rig and site."""
    q = visibility.cell_centres()
    out = np.full((q.shape[0], 9), np.nan)
    out[:, :2] = q
    seen = np.isfinite(np.pad(visibility.table, 1, constant_values=np.inf).ravel())
    if np.any(seen):
        px = project_lights(rig, ceiling_height_m, q[seen], 0.0, 0.0, 0.0)
        out[seen, 2:4] = px
        out[seen, 4:8] = pixel_scale(rig, ceiling_height_m, q[seen]).reshape(-1, 4)
        out[seen, 8] = interp_grid(spot_table[..., 7], JAC_STEP_PX, px)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class WindowFix:
    """What the windows found and the pose they give.

    Attributes:
        x_m, y_m, yaw_rad: the refined pose; ``cov`` its covariance (3, 3);
            ``res_px`` the kept lights' residual norms (px), as
            :func:`~.refine.refine_pose_ceiling`.
        centroids_px: ``(F, 2)`` the found lights' centroids (every window that held a
            plausible light).
        pairs: ``(K, 2)`` (index in ``centroids_px``, map light index) of the kept ones.
        predicted: how many lights the prior says the detector should report.
        found: how many windows held a plausible light (``F``).
        predicted_px: ``(M, 2)`` the predicted pixels (for overlays).
        noise: ``(2,)`` the fit's own ``[SSR px², ν]`` (:meth:`~.refine.NoisePool.added`).
    """

    x_m: float
    y_m: float
    yaw_rad: float
    cov: np.ndarray
    res_px: np.ndarray
    centroids_px: np.ndarray
    pairs: np.ndarray
    predicted: int
    found: int
    predicted_px: np.ndarray
    noise: np.ndarray


# why a window fix was refused (:func:`_track`'s status; 0: a fix)
FIX, FEW_PREDICTED, WINDOW_TOO_BIG, FEW_FOUND, NO_RAY, FEW_KEPT, CHECK = range(7)

# the tracker's numbers, one read-only vector for the compiled call (_params)
_P_WINDOW, _P_CONTRAST, _P_SHARE, _P_RESIDUAL, _P_MEDIANS, _P_GATE_M, _P_GATE_RAD, \
    _P_RADIUS, _P_POOL_SSR, _P_POOL_DOF = range(10)


class PredictionArrays(NamedTuple):
    """What :func:`_predict` reads to place the map's lights in the image: the map
    ``lights (M, 2)`` in W (m), the prediction table ``cells (C, 9)``
    (:func:`prediction_cells`), the visibility table ``padded (C,)`` float32 and its
    ``geo`` (origin x, origin y, cell side; m) as
    :attr:`~.observe.VisibilityTable.arrays` holds them, and ``ints`` (NI, NJ,
    max_spots, the frame's width and height, :data:`MAX_HALF_PX`); all read-only."""

    lights: np.ndarray
    cells: np.ndarray
    padded: np.ndarray
    geo: np.ndarray
    ints: np.ndarray


class WindowTracker:
    """Spots looked for in windows around the lights a prior predicts (module doc).

    Args:
        rig, ceiling_height_m, lights_w: as the estimator's.
        observer: the estimator's :class:`SpotObserver` (its spot table and checks).
        visibility: the estimator's :class:`VisibilityTable`.
        window_px: how far (px) a light may be from its predicted place (the prior's
            error in pixels), beyond the light's own predicted radius.
        min_contrast: least ``peak - I_b`` of a window with a light (grey levels).
        min_share: found / predicted share the frame needs.
        max_residual_px, outlier_medians: the outlier pass (as the global path's).
        gate_m, gate_rad: the refined pose must stay this near the prior.
    """

    def __init__(self, rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                 observer: SpotObserver, visibility: VisibilityTable, window_px: float,
                 min_contrast: float, min_share: float, max_residual_px: float,
                 outlier_medians: float, gate_m: float, gate_rad: float) -> None:
        self.rig, self.ceiling_height_m = rig, ceiling_height_m
        self.lights_w = arr(lights_w, np.float64)
        self.observer, self.visibility = observer, visibility
        self.window_px = float(window_px)
        self.min_contrast = float(min_contrast)
        self.min_share = float(min_share)
        self.max_residual_px, self.outlier_medians = max_residual_px, outlier_medians
        self.gate_m, self.gate_rad = gate_m, gate_rad
        cam = rig.camera
        self.width, self.height = cam.width, cam.height
        # everything the compiled call reads, made once (read-only arrays)
        params = np.zeros(10)    # the run's pixel noise (_P_POOL_*) set per call
        params[[_P_WINDOW, _P_CONTRAST, _P_SHARE, _P_RESIDUAL, _P_MEDIANS, _P_GATE_M,
                _P_GATE_RAD, _P_RADIUS]] = (
            window_px, min_contrast, min_share, max_residual_px, outlier_medians, gate_m,
            gate_rad, observer.light_radius_m)
        self._params = arr(params, np.float64)
        vis = visibility
        self._seen = PredictionArrays(
            self.lights_w,
            arr(prediction_cells(rig, ceiling_height_m, visibility, observer.table),
                np.float64),
            arr(vis.padded, np.float32),
            arr([vis.origin_m[0], vis.origin_m[1], vis.cell_m], np.float64),
            arr([vis.table.shape[0], vis.table.shape[1], vis.max_spots, cam.width,
                 cam.height, MAX_HALF_PX], np.int64))
        self._grid = observer.grid_arrays
        self._mount = observer.mount   # the same rig and ceiling
        self._cells = self._seen.cells

    def observe(self, grey: np.ndarray, x_m: float, y_m: float, yaw_rad: float,
                pool: NoisePool = NoisePool()) -> WindowFix | None:
        """The pose from the windows around the lights predicted from ``(x, y, yaw)``
        on a ``(H, W)`` uint8 frame, or ``None`` when the window check fails; its
        covariance with the run's pixel noise ``pool`` (:class:`~.refine.NoisePool`)."""
        params = self._params
        if pool.dof > 0:
            params = params.copy()
            params[_P_POOL_SSR], params[_P_POOL_DOF] = pool.ssr_px2, pool.dof
            params = arr(params, np.float64)
        out = _track(arr(grey, np.uint8), float(x_m), float(y_m), float(yaw_rad),
                     self._seen, self._grid, self._mount, params)
        status, x, y, yaw, cov, res, cen, pairs, m, found, px, own = out
        if status != FIX:
            return None
        return WindowFix(x, y, yaw, cov, res, cen, pairs, m, found, px, own)

    def _predict(self, x_m: float, y_m: float, yaw_rad: float):
        """``(map indices, predicted px, predicted count, window corners, half side)``
        of the finite predictions, or ``None`` (fewer than 3, or windows too big)
        (:func:`_predict`)."""
        status, idx, px, m, corner, half = _predict(
            float(x_m), float(y_m), float(yaw_rad), self._seen, self._params[_P_WINDOW])
        return None if status != FIX else (idx, px, m, corner, half)

    def _measure(self, grey: np.ndarray, corner: np.ndarray, half: int, m: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(rows (K, 8), good (K,), table rows (K, 10))`` of the windows at
        ``corner (K, 2)``: :func:`~ceilkit.runtime.features.windows.window_stats`'s
        rows, which pass the window check and the spot table's (:func:`_measure`)."""
        return _measure(arr(grey, np.uint8), np.ascontiguousarray(corner, np.int64),
                        int(half), self._grid, self._params)


@njit
def _track(grey, x, y, yaw, seen, grid, mount, params):  # pragma: no cover - compiled
    """The window fix from a prior ``(x, y, yaw)`` (module doc): ``(status, x, y, yaw,
    cov (3, 3), res (K,), centroids (F, 2), pairs (K, 2), predicted, found,
    predicted_px (M, 2))``, status :data:`FIX` or why not (the rest then empty). The
    lights placed by ``seen`` (a :class:`PredictionArrays`), read with the spot table
    ``grid`` (:class:`~.observe.GridArrays`), their ceiling points through ``mount`` (a
    :class:`~ceilkit.runtime.geometry.ceiling.KernelMount`)."""
    lights = seen.lights
    status, idx, px, m, corner, half = _predict(x, y, yaw, seen, params[_P_WINDOW])
    if status != FIX:
        return _refused(status, px, m)
    rows, good, tab = _measure(grey, corner, half, grid, params)
    n_found = 0
    for i in range(good.size):
        n_found += good[i]
    if n_found < max(3, math.ceil(params[_P_SHARE] * m)):
        return _refused(FEW_FOUND, px, m)
    cen = np.empty((n_found, 2))
    jac = np.empty((n_found, 2, 2))
    centres = np.empty((n_found, 2))
    L = np.empty((n_found, 2))
    pairs = np.empty((n_found, 2), np.int64)
    f = 0
    for i in range(good.size):
        if not good[i]:
            continue
        cen[f, 0], cen[f, 1] = rows[i, 0], rows[i, 1]
        # the light's centre: the centroid minus its disc's offset (SpotObserver.centres)
        ou, ov = tab[i, 8], tab[i, 9]
        centres[f, 0] = rows[i, 0] - (ou if math.isfinite(ou) else 0.0)
        centres[f, 1] = rows[i, 1] - (ov if math.isfinite(ov) else 0.0)
        jac[f, 0, 0], jac[f, 0, 1], jac[f, 1, 0], jac[f, 1, 1] = (tab[i, 0], tab[i, 1],
                                                                  tab[i, 2], tab[i, 3])
        L[f, 0], L[f, 1] = lights[idx[i], 0], lights[idx[i], 1]
        pairs[f, 0], pairs[f, 1] = f, idx[i]
        f += 1
    q = np.empty((n_found, 2))
    dz = mount.ceiling_m - mount.t[2]                 # the ceiling above the camera
    if not ceiling_points_core(centres, mount.code, mount.lens, mount.R, mount.t, dz,
                               q).all():
        return _refused(NO_RAY, px, m)
    shift = np.empty((n_found, 2))             # the radial pattern (refine._pattern_cover)
    for f in range(n_found):
        shift[f, 0] = centres[f, 0] - mount.lens[2]
        shift[f, 1] = centres[f, 1] - mount.lens[3]
    status, fx, fy, fyaw, cov, res, keep, own = _fit(q, jac, L, x, y, yaw, shift, params)
    if status != FIX:
        return _refused(status, px, m)
    return (FIX, fx, fy, fyaw, cov, res, cen, pairs[keep], m, n_found, px, own)


@njit
def _refused(status, px, m):  # pragma: no cover - compiled
    return (status, 0.0, 0.0, 0.0, np.full((3, 3), np.inf), np.empty(0), np.empty((0, 2)),
            np.empty((0, 2), np.int64), m, 0, px, np.full(2, np.nan))


@njit
def _predict(x, y, yaw, seen, window_px):  # pragma: no cover - compiled
    """``(status, map indices (K,), predicted px (K, 2), predicted count, window corners
    (K, 2), half side)`` of the lights (``seen``, a :class:`PredictionArrays`) the
    visibility table reports from ``(x, y, yaw)``
    (:meth:`~.observe.VisibilityTable.locate`: the ``max_spots`` nearest the nadir, ties
    in map order), placed by the prediction table
    (:func:`prediction_cells`: the cell centre's pixel plus its Jacobian times the
    light's offset from the centre) and kept where that is finite. Status
    :data:`FEW_PREDICTED` below 3, :data:`WINDOW_TOO_BIG` when the windows (sized by
    the largest predicted spot) would not fit the frame."""
    lights, cells, ints = seen.lights, seen.cells, seen.ints
    w, h, max_half = ints[3], ints[4], ints[5]
    ok, cell, zr, zi = locate_core(x, y, yaw, lights, seen.padded, seen.geo, ints)
    n = lights.shape[0]
    seen = 0
    for k in range(n):
        seen += ok[k]
    m = seen
    idx = np.empty(m, np.int64)
    px = np.empty((m, 2))
    area = np.empty(m)
    fin = np.zeros(m, np.bool_)
    r = 0
    for k in range(n):
        if ok[k]:
            idx[r] = k
            e = cells[cell[k]]
            dx, dy = zr[k] - e[0], zi[k] - e[1]
            px[r, 0] = e[2] + (e[4] * dx + e[5] * dy)
            px[r, 1] = e[3] + (e[6] * dx + e[7] * dy)
            area[r] = e[8]
            fin[r] = math.isfinite(px[r, 0]) and math.isfinite(area[r])
            r += 1
    n_fin = 0
    a_max = -np.inf
    for r in range(m):
        if fin[r]:
            n_fin += 1
            a_max = max(a_max, area[r])
    none = np.empty(0, np.int64)
    if m < 3 or n_fin < 3:
        return FEW_PREDICTED, none, px, m, np.empty((0, 2), np.int64), 0
    r_spot = math.sqrt(max(a_max, 1.0) / math.pi)
    half = np.int64(min(max_half, math.ceil(r_spot * 1.6 + window_px)))
    side = 2 * half + 1
    if side >= min(w, h):
        return WINDOW_TOO_BIG, none, px, m, np.empty((0, 2), np.int64), 0
    if n_fin < m:
        idx, px = idx[fin], px[fin]
    corner = np.empty((n_fin, 2), np.int64)
    for r in range(n_fin):
        # a window at the border is shifted in
        corner[r, 0] = min(max(np.int64(np.rint(px[r, 0])) - half, 0), w - side)
        corner[r, 1] = min(max(np.int64(np.rint(px[r, 1])) - half, 0), h - side)
    return FIX, idx, px, m, corner, half


@njit
def _measure(grey, corner, half, grid, params):  # pragma: no cover - compiled
    """``(rows (K, 8), good (K,), table (K, 10))`` of the windows at ``corner``:
    :func:`~ceilkit.runtime.features.windows.window_stats`' rows ``(u, v, I_o, I_b,
    c00, c01, c11, area)``; ``good`` where the window check passes (a spot clear of
    the window's border, contrast ``>= min_contrast``), the spot table is finite at the
    centroid and (a light of known radius) its size and shape fit
    (:func:`~.observe.plausible_spot`); the spot table's row at each good
    centroid (``grid``, a :class:`~.observe.GridArrays`; NaN elsewhere)."""
    coef, limits = grid.coef, grid.limits
    k = corner.shape[0]
    side = 2 * half + 1
    rect = np.empty((k, 4), np.int64)
    for i in range(k):
        rect[i, 0], rect[i, 1], rect[i, 2], rect[i, 3] = 0, 0, side - 1, side - 1
    out = read_windows_core(grey, corner, side, rect, TRACK_CORE, FLAT)
    rows = np.empty((k, 8))
    good = np.zeros(k, np.bool_)
    tab = np.full((k, coef.shape[2]), np.nan)
    check_shape = params[_P_RADIUS] > 0
    for i in range(k):
        i_b, peak, area, touches, i_o = out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4]
        m00 = out[i, 5]
        ok = touches == 0 and area > 0 and m00 > 0
        div = m00 if ok else 1.0
        cx, cy = out[i, 6] / div, out[i, 8] / div
        rows[i, 0] = corner[i, 0] + half + cx
        rows[i, 1] = corner[i, 1] + half + cy
        rows[i, 2] = i_o
        rows[i, 3] = i_b
        rows[i, 4] = out[i, 7] / div - cx * cx
        rows[i, 5] = out[i, 10] / div - cx * cy
        rows[i, 6] = out[i, 9] / div - cy * cy
        rows[i, 7] = area
        if not (ok and peak - i_b >= params[_P_CONTRAST]):
            continue
        grid_row(coef, limits, rows[i, 0], rows[i, 1], tab[i])
        if not math.isfinite(tab[i, 0]):
            continue
        good[i] = not check_shape or plausible_spot(rows[i, 7], rows[i, 4], rows[i, 5],
                                                    rows[i, 6], tab[i])
    return rows, good, tab


@njit
def _fit(q, jac, L, x, y, yaw, shift, params):  # pragma: no cover - compiled
    """``(status, x, y, yaw, cov, res, keep, own)``: :func:`~.refine.refine_pose_ceiling`
    from the prior, one outlier pass (residuals beyond ``max(max_residual_px,
    outlier_medians x median)`` dropped, refitted from the first fit), the covariance
    of :func:`~.refine.pattern_cover` with the lights' radial pattern ``shift (K, 2)``
    (px about the principal point) and the run's pixel noise (``params``' pool), and
    the frame's checks (RMS, a finite covariance, within the prior's gate): status
    :data:`FEW_KEPT` or :data:`CHECK` when they fail; ``own`` the fit's ``[SSR, ν]``
    (:class:`~.refine.NoisePool`)."""
    k = q.shape[0]
    keep = np.ones(k, np.bool_)
    fx, fy, fyaw, cov, res = _refine(q, jac, L, x, y, yaw, 3, SIGMA_FLOOR_PX)
    limit = max(params[_P_RESIDUAL], params[_P_MEDIANS] * _median(res))
    n_bad = 0
    for i in range(k):
        if res[i] > limit:
            keep[i] = False
            n_bad += 1
    if n_bad:
        if k - n_bad < 3:
            return FEW_KEPT, 0.0, 0.0, 0.0, cov, res, keep, np.full(2, np.nan)
        fx, fy, fyaw, cov, res = _refine(q[keep], jac[keep], L[keep], fx, fy, fyaw, 3,
                                         SIGMA_FLOOR_PX)
    noise = np.array([params[_P_POOL_SSR], params[_P_POOL_DOF], np.nan, np.nan])
    if 2 * res.size - 4 >= SHIFT_MIN_DOF:
        covered = np.empty((3, 3))
        if _pattern_cover(q[keep], jac[keep], L[keep], np.array([fx, fy, fyaw]),
                          shift[keep], covered, noise):
            cov = covered
    ss = 0.0
    for i in range(res.size):
        ss += res[i] * res[i]
    rms = math.sqrt(ss / res.size)
    finite = True
    for a in range(3):
        for b in range(3):
            finite = finite and math.isfinite(cov[a, b])
    d_yaw = fyaw - yaw
    d_yaw -= 2 * math.pi * np.rint(d_yaw / (2 * math.pi))
    if (rms > params[_P_RESIDUAL] or not finite
            or math.hypot(fx - x, fy - y) > params[_P_GATE_M]
            or abs(d_yaw) > params[_P_GATE_RAD]):
        return CHECK, fx, fy, fyaw, cov, res, keep, noise[2:]
    return FIX, fx, fy, fyaw, cov, res, keep, noise[2:]


@njit
def _median(x):  # pragma: no cover - compiled
    """:func:`~ceilkit.runtime.geometry.fits.short_median`."""
    s = np.sort(x)
    n = s.size
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


@warmer
def _warm() -> None:
    from ceilkit.runtime.geometry.camera import CameraModel
    from ceilkit.runtime.geometry.ceiling import PlanarGeometry, kernel_mount

    cam = CameraModel.pinhole(16, 16, 10.0)
    grey = arr(np.zeros((16, 16), np.uint8), np.uint8)
    seen = PredictionArrays(arr(np.zeros((1, 2)), np.float64),
                            arr(np.zeros((1, 9)), np.float64), arr(np.zeros(1), np.float32),
                            arr(np.zeros(3), np.float64), arr(np.ones(6), np.int64))
    grid = GridArrays(arr(np.zeros((1, 4, 10)), np.float64), arr(np.ones(6), np.float64))
    params = arr(np.zeros(10), np.float64)
    _track(grey, 0.0, 0.0, 0.0, seen, grid,
           kernel_mount(PlanarGeometry(cam, np.eye(3), np.zeros(3), 0.0)), params)
    _measure(grey, np.zeros((1, 2), np.int64), 1, grid, params)


__all__ = ["MAX_HALF_PX", "TRACK_CORE", "PredictionArrays", "WindowFix", "WindowTracker",
           "prediction_cells"]
