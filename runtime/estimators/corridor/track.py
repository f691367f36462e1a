"""The tracked fast path of ``corridor``: 1-D edge searches across the predicted lines.

With a prior (the tracker's or the fusion's predicted yaw and y), every site line
``y = y_j`` of ``lines_along`` is projected through the rig (camera pan
``psi = yaw + pan``, camera y ``c_y``; SPEC §1) and its visible stretch (in the image,
in the lens's field, within :data:`REACH_M` of the camera on the ceiling) is cut into
short pixel chords. On each chord the edge is located on cross profiles by the one
edge-profile measurement (:func:`~ceilkit.runtime.features.lines.refine_undistorted`:
kind, sub-pixel location, a line fitted in undistorted coordinates), within
``search_px`` of the prediction. No full-frame line detector runs.

A chord counts when its edge is of the kind the site says (a lamp's long edge is a
step, a seam a thin line) and fits well (its points' scatter within
:data:`MAX_CHORD_RMS_PX` and :data:`CHORD_RMS_MEDIANS` times the frame's median);
the association is known (a chord is its line's), so the located chords go straight
to the joint Gauss-Newton on ``(psi, c_y)`` (:func:`~.refine.gauss_newton`, started
at the prior) as forward segments.
The window check: at least two site lines found, the fit's rms within ``inlier_px``,
the refined pose within the search's reach of the prior. Anything else returns
``None`` and the estimator runs its global path (the fallback and the check).

Example::

    lt = LineTracker(setup, camera, search_px=5.0, inlier_px=2.5)
    m = lt.measure(grey, psi_rad, camera_y_m)     # LineMeasurement | None
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.edges import PROFILE_STEP_PX, edge_grid, part_indices
from ceilkit.runtime.features.lines import ProfileGrid, ProfileKind, _refine_core
from ceilkit.runtime.geometry.camera import CameraModel, distort_points
from ceilkit.runtime.jit import arr, njit, warmer

REACH_M = 8.0
"""Ceiling points further than this from the camera are not searched (tiny, blurred)."""

CHORD_PX = 48.0
"""Pixel length of a chord of a predicted line (short: a curved image line is straight
on it to a fraction of a pixel)."""

MIN_CHORD_PX = 20.0
"""A visible stretch shorter than this is not searched."""

SAMPLES = 121
"""Samples along each site line (W's x, over ``±REACH_M`` of the camera)."""

N_ALONG = 8
"""Cross profiles per chord (as :func:`~ceilkit.runtime.features.lines.refine_undistorted`)."""

MIN_STEP, MIN_DEPTH = 20.0, 8.0
"""A chord's edge kind: the least step and thin-line depth (grey levels; as
:func:`~ceilkit.runtime.features.lines.refine_undistorted`'s defaults)."""

MAX_CHORD_RMS_PX = 1.0
"""A chord whose located points scatter more than this about their line is dropped."""

CHORD_RMS_MEDIANS = 3.0
"""... and so is one scattering more than this many times the frame's median chord
scatter: a chord over a lamp's end or a neighbouring edge fits worse than the clean
chords by far (on renders, clean chords 0.02-0.14 px, the others 0.4-0.95), and the
few such chords biased the fit (corridor_60 of bench_all: yaw error median/p95 0.0054/0.021 deg with
them, 0.0017/0.0058 without, the global path's 0.0023/0.0061)."""


@dataclass(frozen=True, eq=False)
class LineMeasurement:
    """The located chords of one frame.

    Attributes:
        segs_n: ``(K, 4)`` undistorted normalized chords (the fitted edge).
        segs_px: ``(K, 4)`` the predicted pixel chords searched.
        line: ``(K,)`` the site line (index into ``setup.site_y``) of each chord.
        polarity: ``(K,)`` the located kind (``+-1`` step, ``0`` thin line).
        rms_px: ``(K,)`` the located points' scatter about each chord's fit (px).
        searched: chords searched (before the checks).
    """

    segs_n: np.ndarray
    segs_px: np.ndarray
    line: np.ndarray
    polarity: np.ndarray
    rms_px: np.ndarray
    searched: int

    @property
    def n_lines(self) -> int:
        return int(np.unique(self.line).size)


def without_ignored(m: LineMeasurement | None, regions, pose) -> LineMeasurement | None:
    """``m`` without the chords inside the site's ``ignore`` regions seen from ``pose``
    (:class:`~ceilkit.runtime.estimators.ignore.IgnoreRegions`; SPEC §2), None when
    fewer than two site lines keep a chord; ``m`` itself with no region or no pose."""
    keep = None if m is None or regions is None else regions.keep_segments(m.segs_n, pose)
    if keep is None or keep.all():
        return m
    if np.unique(m.line[keep]).size < 2:
        return None
    return dataclasses.replace(m, segs_n=m.segs_n[keep], segs_px=m.segs_px[keep],
                               line=m.line[keep], polarity=m.polarity[keep],
                               rms_px=m.rms_px[keep])


class LineTracker:
    """Edge searches across the site lines predicted from a prior (module doc).

    Args:
        setup: the estimator's :class:`~.setup.CorridorSetup`.
        camera: the intrinsics.
        search_px: half-width of the cross profiles (px): how far an edge may be from
            its prediction (the prior's error in pixels, plus a pixel).
    """

    def __init__(self, setup: CorridorSetup, camera: CameraModel, search_px: float) -> None:
        self.setup, self.camera = setup, camera
        self.search_px = float(search_px)
        offs, t, inner = edge_grid(N_ALONG, self.search_px)
        il, ir, ii = part_indices(offs)
        params = np.array([setup.ceiling_above_cam_m, setup.field_radius, self.search_px + 2.0,
                           setup.rows[0], setup.rows[1], camera.width, camera.height,
                           setup.f_px, inner.start + 1, inner.stop + 1])
        # what the compiled measurement reads, made once (read-only arrays)
        self._consts = (arr(setup.R_level_cam, np.float64), arr(setup.site_y, np.float64),
                        arr(np.linspace(-REACH_M, REACH_M, SAMPLES), np.float64),
                        arr(setup.edge_kind, np.float64),
                        arr(offs, np.float64), arr(t, np.float64), arr(il, np.int64),
                        arr(ir, np.int64), arr(ii, np.int64), *camera.lens,
                        arr(params, np.float64))

    def predicted_chords(self, psi_rad: float, camera_y_m: float
                         ) -> tuple[np.ndarray, np.ndarray]:
        """``(chords (K, 4) px, line (K,))``: the visible stretches of every site line
        for camera pan ``psi_rad`` and camera y ``camera_y_m``, cut into chords of about
        :data:`CHORD_PX` (:func:`_predict`)."""
        c = self._consts
        return _predict(float(psi_rad), float(camera_y_m), c[0], c[1], c[2], c[9], c[10],
                        c[11])

    def measure(self, grey: np.ndarray, psi_rad: float, camera_y_m: float
                ) -> LineMeasurement | None:
        """The chords located on a ``(H, W)`` uint8 frame around the site lines
        predicted for ``(psi_rad, camera_y_m)``; ``None`` when fewer than two site lines
        hold a located chord of the right kind. One compiled call (:func:`_measure`)."""
        found, segs_n, chords, line, pol, rms, n = _measure(
            arr(grey, np.uint8), float(psi_rad), float(camera_y_m), *self._consts)
        if not found:
            return None
        return LineMeasurement(segs_n, chords, line, pol, rms, n)

    def shift_px(self, d_psi_rad: float, d_cy_m: float) -> float:
        """How far (px, at the image's scale) a change of the camera's pan and y moves
        the predicted lines: the larger of its two parts."""
        f = self.setup.f_px
        return max(abs(d_psi_rad) * f, abs(d_cy_m) * f / self.setup.ceiling_above_cam_m)

    def reach(self) -> tuple[float, float]:
        """``(psi_rad, c_y m)``: how far from the prior a refined fit may move and still
        be what the searches saw (about ``search_px`` at the image's scale)."""
        f = self.setup.f_px
        return (math.atan2(self.search_px, f) * 2.0,
                self.search_px / f * self.setup.ceiling_above_cam_m * 2.0)


@njit
def _predict(psi, cam_y, R_lc, site_y, u, lens_code, lens, p):  # pragma: no cover - compiled
    """``(chords (K, 4) px, line (K,))`` of :meth:`LineTracker.predicted_chords`: every
    site line ``y = site_y[j]`` sampled at ``u`` (W's x from the camera), seen from
    the camera rotation ``R_cw = R_level_camᵀ Rz(-psi)`` at ``h = p[0]`` below the
    ceiling; a sample is visible in front of the camera, within :data:`REACH_M` on the
    ceiling, inside the lens's field (``p[1]``) and ``p[2]`` px inside the image's
    rows ``p[3]..p[4]`` (``p[5] x p[6]`` px); each line's longest visible run is cut
    into chords (:func:`_chords_of_runs`)."""
    h, field_r, m = p[0], p[1], p[2]
    row0, row1, w, hh = p[3], p[4], p[5], p[6]
    c, s = math.cos(-psi), math.sin(-psi)
    R = np.empty((3, 3))
    for i in range(3):                     # R_lcᵀ Rz(-psi)
        R[i, 0] = R_lc[0, i] * c + R_lc[1, i] * s
        R[i, 1] = -R_lc[0, i] * s + R_lc[1, i] * c
        R[i, 2] = R_lc[2, i]
    n_j, n_s = site_y.size, u.size
    xy = np.empty((n_j * n_s, 2))
    front = np.empty((n_j, n_s), np.bool_)
    for j in range(n_j):
        dy = site_y[j] - cam_y
        for i in range(n_s):
            d0 = u[i] * R[0, 0] + (dy * R[0, 1] + h * R[0, 2])
            d1 = u[i] * R[1, 0] + (dy * R[1, 1] + h * R[1, 2])
            d2 = u[i] * R[2, 0] + (dy * R[2, 1] + h * R[2, 2])
            f = d2 > 1e-6 and u[i] * u[i] + dy * dy <= REACH_M * REACH_M
            z = d2 if f else 1.0
            x, y = d0 / z, d1 / z
            front[j, i] = f and x * x + y * y <= field_r * field_r
            xy[j * n_s + i, 0], xy[j * n_s + i, 1] = x, y
    px = np.empty((n_j * n_s, 2))
    distort_points(xy, lens_code, lens, px)
    px = px.reshape(n_j, n_s, 2)
    vis = np.empty((n_j, n_s), np.bool_)
    lo_v, hi_v = max(m, row0), min(hh - 1 - m, row1)
    for j in range(n_j):
        for i in range(n_s):
            pu, pv = px[j, i, 0], px[j, i, 1]
            vis[j, i] = front[j, i] and m <= pu <= w - 1 - m and lo_v <= pv <= hi_v
    return _chords_of_runs(px, vis, CHORD_PX, MIN_CHORD_PX)


@njit
def _measure(grey, psi, cam_y, R_lc, site_y, u, edge_kind, offs, t, il, ir, ii,
             lens_code, lens, p):  # pragma: no cover - compiled
    """:meth:`LineTracker.measure`: ``(found, segs_n, chords, line, polarity, rms,
    searched)``. The chords of :func:`_predict` are measured by
    :func:`~ceilkit.runtime.features.lines.refine_chords`' loop; then the chords of the
    wrong kind or a poor fit are dropped (:data:`MAX_CHORD_RMS_PX`,
    :data:`CHORD_RMS_MEDIANS`). ``found`` is False when fewer than two site lines are
    predicted or keep a chord."""
    chords, line = _predict(psi, cam_y, R_lc, site_y, u, lens_code, lens, p)
    n = chords.shape[0]
    empty = (False, np.empty((0, 4)), np.empty((0, 4)), np.empty(0, np.int64),
             np.empty(0), np.empty(0), n)
    if _distinct(line) < 2:
        return empty
    grid = ProfileGrid(offs, t, il, ir, ii, np.int64(p[8]), np.int64(p[9]))
    kind = ProfileKind(MIN_STEP, MIN_DEPTH, PROFILE_STEP_PX)
    ends, pol, rms = _refine_core(grey, chords, grid, kind, lens_code, lens, p[7])
    ok = np.zeros(n, np.bool_)
    for r in range(n):
        kind_ok = abs(pol[r]) == 1.0 if edge_kind[line[r]] != 0 else pol[r] == 0.0
        ok[r] = math.isfinite(rms[r]) and rms[r] <= MAX_CHORD_RMS_PX and kind_ok
    if ok.any():
        limit = CHORD_RMS_MEDIANS * np.median(rms[ok])
        for r in range(n):
            ok[r] = ok[r] and rms[r] <= limit
    if _distinct(line[ok]) < 2:
        return empty
    return True, ends[ok], chords[ok], line[ok], pol[ok], rms[ok], n


@njit
def _distinct(line):  # pragma: no cover - compiled
    """How many distinct values a sorted ``line`` holds."""
    k = 0
    for i in range(line.size):
        if i == 0 or line[i] != line[i - 1]:
            k += 1
    return k


def _cut_chords(px: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(chords (K, 4), line (K,))``: each line's longest run of visible samples
    (``px (J, S, 2)``, ``vis (J, S)``; the first of equal runs), cut into chords of
    about :data:`CHORD_PX` of arc length (ends interpolated along the arc as
    ``np.interp``); runs shorter than :data:`MIN_CHORD_PX` are left out."""
    return _chords_of_runs(arr(px, np.float64), arr(vis, np.bool_), CHORD_PX, MIN_CHORD_PX)


@njit
def _chords_of_runs(px, vis, chord_px, min_chord_px):  # pragma: no cover - compiled
    """:func:`_cut_chords`: ``(chords, line)``."""
    n_lines, n_s = vis.shape
    runs = np.zeros((n_lines, 2), np.int64)
    for j in range(n_lines):
        best_a, best_len, a = 0, 0, -1
        for i in range(n_s + 1):
            on = i < n_s and vis[j, i]
            if on and a < 0:
                a = i
            elif not on and a >= 0:
                if i - a > best_len:
                    best_a, best_len = a, i - a
                a = -1
        runs[j, 0], runs[j, 1] = best_a, best_a + best_len
    arc = np.zeros((n_lines, n_s))           # arc length along each run from its start
    count = np.zeros(n_lines, np.int64)      # chords of each line
    for j in range(n_lines):
        a, b = runs[j, 0], runs[j, 1]
        if b - a < 2:
            continue
        for i in range(a + 1, b):
            arc[j, i - a] = arc[j, i - a - 1] + math.hypot(px[j, i, 0] - px[j, i - 1, 0],
                                                           px[j, i, 1] - px[j, i - 1, 1])
        if arc[j, b - a - 1] >= min_chord_px:
            count[j] = max(1, int(np.rint(arc[j, b - a - 1] / chord_px)))
    chords = np.empty((count.sum(), 4))
    line = np.empty(count.sum(), np.int64)
    n = 0                                    # chords written
    for j in range(n_lines):
        k = count[j]
        if k == 0:
            continue
        a, b = runs[j, 0], runs[j, 1]
        m = b - a
        total = arc[j, m - 1]
        seg = 0
        pu, pv = px[j, a, 0], px[j, a, 1]
        for c in range(1, k + 1):
            x = total * (c / k)
            while seg < m - 2 and arc[j, seg + 1] <= x:
                seg += 1
            if x >= total:
                u, v = px[j, b - 1, 0], px[j, b - 1, 1]
            else:
                t = (x - arc[j, seg]) / (arc[j, seg + 1] - arc[j, seg])
                u = px[j, a + seg, 0] + t * (px[j, a + seg + 1, 0] - px[j, a + seg, 0])
                v = px[j, a + seg, 1] + t * (px[j, a + seg + 1, 1] - px[j, a + seg, 1])
            chords[n, 0], chords[n, 1], chords[n, 2], chords[n, 3] = pu, pv, u, v
            line[n] = j
            n += 1
            pu, pv = u, v
    return chords, line


@warmer
def _warm() -> None:
    px = np.stack([np.linspace(0.0, 100.0, 5), np.zeros(5)], axis=1)[None]
    _cut_chords(px, np.ones((1, 5), bool))
    cam = CameraModel.pinhole(64, 48, 50.0)
    offs, t, inner = edge_grid(N_ALONG, 4.0)
    il, ir, ii = part_indices(offs)
    f = np.float64
    _measure(arr(np.zeros((48, 64), np.uint8), np.uint8), 0.0, 0.0, arr(np.eye(3), f),
             arr([-1.0, 1.0], f), arr(np.linspace(-1.0, 1.0, 5), f), arr([0.0, 0.0], f),
             arr(offs, f), arr(t, f), arr(il, np.int64), arr(ir, np.int64),
             arr(ii, np.int64), *cam.lens,
             arr([2.0, 1.0, 6.0, 0.0, 48.0, 64.0, 48.0, 50.0, inner.start + 1,
                  inner.stop + 1], f))


__all__ = ["CHORD_PX", "CHORD_RMS_MEDIANS", "LineMeasurement", "LineTracker", "REACH_M"]
