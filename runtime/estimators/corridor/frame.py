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

from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.corridor.geometry import ceiling_points, level_normals
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
                   max_segments: int, refine: bool, edge_fit: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's segments: ``(segs (N, 4) undistorted normalized, len_px (N,),
    polarity (N,), fit_rms (N,) px)``. With ``edge_fit`` each segment is refitted on
    its located edge points in undistorted coordinates and its kind measured
    (:func:`~ceilkit.runtime.features.lines.refine_undistorted`); without, only the
    endpoints are undistorted and the kind is unknown."""
    segs_px, fit_rms = detect(grey, detector, max_segments, refine)
    if not edge_fit or segs_px.shape[0] < 2:
        return (*undistorted(camera, segs_px, None), fit_rms)
    hw = edge_half_width_px(detector.factor)        # wider after a decimated search
    segs_n, pol, rms = refine_undistorted(camera, grey, segs_px, half_width_px=hw,
                                          retry_half_width_px=1.5 * hw)
    fit_rms = np.where(np.isfinite(rms), rms, fit_rms)
    return segs_n, segment_lengths(segs_px), pol, fit_rms


@dataclass(frozen=True, eq=False)
class FrameLines:
    """One frame's segments (undistorted normalized coordinates), computed once and
    shared by every pan candidate and hypothesis.

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


def frame_lines(segs: np.ndarray, pol: np.ndarray, setup: CorridorSetup,
                angle_tol_rad: float, inlier_px: float) -> FrameLines:
    """The per-frame arrays of undistorted normalized segments ``segs (N, 4)`` with
    polarities ``pol (N,)``; the family gate is ``angle_tol_rad``, or ``2 inlier_px``
    over a segment's pixel length where that is tighter."""
    dx, dy = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
    len_n = np.hypot(dx, dy)
    lines_t = np.empty((3, segs.shape[0]))                      # segment_lines, (3, N)
    inv = 1.0 / np.maximum(len_n, 1e-300)
    np.multiply(-dy, inv, out=lines_t[0])
    np.multiply(dx, inv, out=lines_t[1])
    np.multiply(segs[:, 0] * segs[:, 3] - segs[:, 2] * segs[:, 1], inv, out=lines_t[2])
    lines = lines_t.T
    ceil_pts = ceiling_points(segs, setup.R_level_cam, setup.ceiling_above_cam_m)
    cdx, cdy = ceil_pts[:, 2] - ceil_pts[:, 0], ceil_pts[:, 3] - ceil_pts[:, 1]
    ceil_full = np.hypot(cdx, cdy)                  # NaN above the horizon
    ceil_len = np.minimum(ceil_full, MAX_CEILING_LENGTH_M)
    ceil_len[~(ceil_len >= 0)] = 0.0
    # across segments as long as a lamp is wide (see association.lamp_anchors)
    width = setup.lamp_width_m[:, None]
    lamp_end = (np.isfinite(ceil_full)[None, :]
                & (np.abs(ceil_full[None, :] - width) < LAMP_END_TOL * width))
    return FrameLines(
        segs=segs, lines=lines, lines_t=lines_t, len_n=len_n,
        mx=0.5 * (segs[:, 0] + segs[:, 2]), my=0.5 * (segs[:, 1] + segs[:, 3]),
        q=level_normals(lines, setup.R_level_cam), pol=pol, ceil_len=ceil_len,
        ceil_sx=ceil_pts[:, 0] + ceil_pts[:, 2], ceil_sy=ceil_pts[:, 1] + ceil_pts[:, 3],
        lamp_end=lamp_end,
        tol=np.minimum(angle_tol_rad, 2 * inlier_px / np.maximum(len_n * setup.f_px, 1)))
