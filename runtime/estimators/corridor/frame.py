"""One frame's features for the corridor method: segments, their edge kinds, and the
per-frame arrays every pan candidate and hypothesis shares.

A frame's path: :func:`frame_segments` (detector, optional gradient refinement, the
edge fit in undistorted coordinates: ``ceilkit.runtime.features.lines``), then
:func:`frame_lines` (lines, level normals, ceiling lengths, the family gate).

Example::

    segs, len_px, pol, fit_rms = frame_segments(grey, camera, detector, 120, False, True)
    fr = frame_lines(segs, pol, setup, angle_tol_rad, inlier_px)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.lines import (
    SegmentDetector,
    edge_half_width_px,
    refine_segments,
    refine_undistorted,
    segment_lengths,
    undistort_segments,
)
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.ceiling import meet_ceiling
from ceilkit.runtime.geometry.fits import median_of
from ceilkit.runtime.jit import arr, njit, warmer

MAX_CEILING_LENGTH_M = 10.0
"""Ceiling lengths (the forward-family evidence) are capped at this."""

LAMP_END_TOL = 0.2
"""An across segment within this share of a lamp's width of it is that lamp's end."""


def detect(grey: np.ndarray, detector: SegmentDetector, max_segments: int,
           refine: bool) -> tuple[np.ndarray, np.ndarray]:
    """Pixel segments ``(N, 4)`` of a frame (the ``max_segments`` longest), optionally
    refined on image gradients, and their fit rms ``(N,)`` (px; 0 unrefined)."""
    segs = detector(grey)
    if segs.shape[0] > max_segments:
        segs = segs[np.argsort(-segment_lengths(segs))[:max_segments]]
    rms = np.zeros(segs.shape[0])
    if refine and segs.shape[0]:
        segs, rms = refine_segments(grey, segs)
    return segs, rms


def undistorted(camera: CameraModel, segs_px: np.ndarray, polarity: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Given pixel segments ``(N, 4)``: their endpoints undistorted ``(N, 4)``, pixel
    lengths ``(N,)`` and polarities ``(N,)`` (NaN: unknown, as
    :func:`~ceilkit.runtime.features.lines.edge_polarity` otherwise)."""
    segs_px = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    segs = undistort_segments(camera, segs_px)
    pol = np.full(segs.shape[0], np.nan) if polarity is None else np.asarray(polarity, float)
    return segs, segment_lengths(segs_px), pol


def frame_segments(grey: np.ndarray, camera: CameraModel, detector: SegmentDetector,
                   max_segments: int, refine: bool, edge_fit: bool,
                   half_width_px: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's segments: ``(segs (N, 4) undistorted normalized, len_px (N,),
    polarity (N,), fit_rms (N,) px)``. With ``edge_fit`` each segment is refitted on
    its located edge points in undistorted coordinates and its kind measured
    (:func:`~ceilkit.runtime.features.lines.refine_undistorted`, over profiles
    ``half_width_px`` wide each side; None: ``edge_half_width_px(detector.factor)``);
    without, only the endpoints are undistorted and the kind is unknown."""
    segs_px, fit_rms = detect(grey, detector, max_segments, refine)
    if not edge_fit or segs_px.shape[0] < 2:
        return (*undistorted(camera, segs_px, None), fit_rms)
    # wider after a decimated search, unless told
    hw = edge_half_width_px(detector.factor) if half_width_px is None else float(half_width_px)
    segs_n, pol, rms = refine_undistorted(camera, grey, segs_px, half_width_px=hw,
                                          retry_half_width_px=1.5 * hw)
    fit_rms = np.where(np.isfinite(rms), rms, fit_rms)
    return segs_n, segment_lengths(segs_px), pol, fit_rms


@dataclass(frozen=True, eq=False)
class FrameLines:
    """One frame's segments (undistorted normalized coordinates), computed once and
    shared by every pan candidate and hypothesis (the arrays read-only and float64, as
    the compiled loops take them).

    Attributes:
        segs: ``(N, 4)`` endpoints. lines: ``(N, 3)`` their lines (``hypot(a, b) = 1``),
            a view of lines_t ``(3, N)``. len_n: ``(N,)`` lengths. mx, my: ``(N,)``
            midpoints. q: ``(N, 3)`` level normals ``R_level_cam l``. pol: ``(N,)``
            polarity.
        ceil_len: ``(N,)`` length on the ceiling (m; at most 10, 0 above the horizon).
        ceil_sx, ceil_sy: ``(N,)`` sums of the two endpoints' ceiling coordinates (m,
            level frame relative to the camera; twice the midpoint).
        lamp_end: ``(L, N)`` bool: as long on the ceiling as lamp row l is wide (20 %).
        tol: ``(N,)`` the family gate after the first pan fit (rad).
    """

    segs: np.ndarray
    lines: np.ndarray
    lines_t: np.ndarray
    len_n: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    q: np.ndarray
    pol: np.ndarray
    ceil_len: np.ndarray
    ceil_sx: np.ndarray
    ceil_sy: np.ndarray
    lamp_end: np.ndarray
    tol: np.ndarray


    @functools.cached_property
    def arrays(self) -> LineArrays:
        """The arrays the labeling's compiled loops read, as one :class:`LineArrays`."""
        return LineArrays(self.lines_t, self.mx, self.my, self.len_n, self.q, self.pol,
                          self.ceil_len, self.ceil_sx, self.ceil_sy, self.lamp_end, self.tol)


class LineArrays(NamedTuple):
    """A frame's arrays as the labeling's compiled loops take them
    (:class:`FrameLines`', read-only, float64 but ``lamp_end``): ``lines_t (3, N)``,
    midpoints ``mx, my (N,)``, lengths ``len_n (N,)``, level normals ``q (N, 3)``,
    polarities ``pol (N,)``, ceiling lengths and endpoint sums ``ceil_len, ceil_sx,
    ceil_sy (N,)``, ``lamp_end (L, N)`` bool and the family gate ``tol (N,)``."""

    lines_t: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    len_n: np.ndarray
    q: np.ndarray
    pol: np.ndarray
    ceil_len: np.ndarray
    ceil_sx: np.ndarray
    ceil_sy: np.ndarray
    lamp_end: np.ndarray
    tol: np.ndarray


def frame_lines(segs: np.ndarray, pol: np.ndarray, setup: CorridorSetup,
                angle_tol_rad: float, inlier_px: float) -> FrameLines:
    """The per-frame arrays of undistorted normalized segments ``segs (N, 4)`` with
    polarities ``pol (N,)``; the family gate is ``angle_tol_rad``, or ``2 inlier_px``
    over a segment's pixel length where that is tighter."""
    segs = arr(segs, np.float64).reshape(-1, 4)
    out = _frame_arrays(
        segs, arr(setup.R_level_cam, np.float64),
        float(setup.ceiling_above_cam_m), arr(setup.lamp_width_m, np.float64),
        float(angle_tol_rad), float(inlier_px), float(setup.f_px))
    return frame_of(segs, pol, out)


def frame_of(segs: np.ndarray, pol: np.ndarray, out: tuple) -> FrameLines:
    """The :class:`FrameLines` of segments ``segs (N, 4)`` (float64, C order), polarities
    ``pol (N,)`` and :func:`_frame_arrays`' output ``out`` (made read-only here)."""
    for a in out:               # read-only, as the compiled loops take them
        a.flags.writeable = False
    lines_t, len_n, mx, my, q, ceil_len, ceil_sx, ceil_sy, lamp_end, tol = out
    return FrameLines(segs=segs, lines=lines_t.T, lines_t=lines_t, len_n=len_n, mx=mx, my=my,
                      q=q, pol=arr(pol, np.float64), ceil_len=ceil_len, ceil_sx=ceil_sx,
                      ceil_sy=ceil_sy, lamp_end=lamp_end, tol=tol)


@njit
def _frame_arrays(segs, R, h, lamp_w, angle_tol, inlier_px, f_px
                  ):  # pragma: no cover - compiled
    """:func:`frame_lines`' arrays in one loop over the segments: ``(lines_t (3, N),
    len_n, mx, my, q (N, 3), ceil_len, ceil_sx, ceil_sy, lamp_end (L, N), tol)``.
    A segment's line ``(-dy, dx, x0 y1 - x1 y0) / len``; its level normal ``R l``; its
    endpoints on the ceiling ``h (R p)_xy / (R p)_z`` (NaN where ``(R p)_z <= 1e-6``,
    above the horizon: :func:`~ceilkit.runtime.geometry.ceiling.meet_ceiling`), their
    distance capped at
    :data:`MAX_CEILING_LENGTH_M` (0 when NaN); as long as lamp row l is wide within
    :data:`LAMP_END_TOL`; the family gate ``min(angle_tol, 2 inlier_px / max(len
    f_px, 1))``."""
    n = segs.shape[0]
    n_l = lamp_w.size
    lines_t = np.empty((3, n))
    len_n = np.empty(n)
    mx = np.empty(n)
    my = np.empty(n)
    q = np.empty((n, 3))
    ceil_len = np.empty(n)
    ceil_sx = np.empty(n)
    ceil_sy = np.empty(n)
    lamp_end = np.zeros((n_l, n), np.bool_)
    tol = np.empty(n)
    cx = np.empty(2)
    cy = np.empty(2)
    for i in range(n):
        x0, y0, x1, y1 = segs[i, 0], segs[i, 1], segs[i, 2], segs[i, 3]
        dx, dy = x1 - x0, y1 - y0
        ln = math.hypot(dx, dy)
        inv = 1.0 / max(ln, 1e-300)
        a, b, c = -dy * inv, dx * inv, (x0 * y1 - x1 * y0) * inv
        lines_t[0, i], lines_t[1, i], lines_t[2, i] = a, b, c
        len_n[i] = ln
        mx[i], my[i] = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        for k in range(3):
            q[i, k] = a * R[k, 0] + b * R[k, 1] + c * R[k, 2]
        for e in range(2):
            _, cx[e], cy[e] = meet_ceiling(R, segs[i, 2 * e], segs[i, 2 * e + 1], h, 1e-6, 0.0)
        full = math.hypot(cx[1] - cx[0], cy[1] - cy[0])        # NaN above the horizon
        ceil_len[i] = min(full, MAX_CEILING_LENGTH_M) if full >= 0 else 0.0
        ceil_sx[i], ceil_sy[i] = cx[0] + cx[1], cy[0] + cy[1]
        if math.isfinite(full):
            for m in range(n_l):
                lamp_end[m, i] = abs(full - lamp_w[m]) < LAMP_END_TOL * lamp_w[m]
        tol[i] = min(angle_tol, 2 * inlier_px / max(ln * f_px, 1.0))
    return lines_t, len_n, mx, my, q, ceil_len, ceil_sx, ceil_sy, lamp_end, tol


def labeled_counts(fr: FrameLines, along: np.ndarray, across: np.ndarray,
                   assign: np.ndarray, fit_rms: np.ndarray) -> tuple[int, int, int, int,
                                                                   float, float]:
    """The diagnostics of a labeled frame in one compiled call (:func:`counts_core`):
    ``(n_along, n_across, n_steps, n_thin, median finite fit_rms, span)``: the forward
    segments that are steps and thin lines, the median of the finite ``fit_rms (N,)``
    (NaN if none) and the extent of the matched forward endpoints (their bounding
    box's diagonal, normalized; 0 if none)."""
    return counts_core(fr.segs, fr.pol, arr(along, np.bool_), arr(across, np.bool_),
                       arr(assign, np.int64), arr(fit_rms, np.float64))


@njit
def counts_core(segs, pol, along, across, assign, fit_rms):  # pragma: no cover - compiled
    """:func:`labeled_counts`."""
    n_a = n_b = n_steps = n_thin = 0
    lo_x = lo_y = np.inf
    hi_x = hi_y = -np.inf
    for i in range(pol.size):
        n_b += across[i]
        if not along[i]:
            continue
        n_a += 1
        n_steps += abs(pol[i]) == 1
        n_thin += pol[i] == 0
        if assign[i] >= 0:
            for e in range(2):
                lo_x, hi_x = min(lo_x, segs[i, 2 * e]), max(hi_x, segs[i, 2 * e])
                lo_y, hi_y = min(lo_y, segs[i, 2 * e + 1]), max(hi_y, segs[i, 2 * e + 1])
    span = math.hypot(hi_x - lo_x, hi_y - lo_y) if hi_x >= lo_x else 0.0
    return n_a, n_b, n_steps, n_thin, median_of(fit_rms[np.isfinite(fit_rms)]), span


@warmer
def _warm() -> None:
    f = np.float64
    seg = arr(np.array([[0.0, 0.0, 0.1, 0.0]]), f)
    _frame_arrays(seg, arr(np.eye(3), f), 2.0, arr(np.array([0.3]), f), 0.1, 2.0, 500.0)
    on = arr(np.ones(1, bool), np.bool_)
    counts_core(seg, arr(np.ones(1), f), on, on, arr(np.zeros(1, np.int64), np.int64),
                arr(np.ones(1), f))
