"""A working resolution for large frames: detect on a decimated image, map back.

Detectors here are tuned in pixels for frames of about a megapixel (Niblack windows,
region areas, segment lengths). A larger frame is box-averaged by an integer factor
(:func:`working_factor`, :func:`decimate`), features are found there, mapped back
(:func:`undecimate`), and where the full frame adds accuracy, refined on it:

* spots (:func:`detect_spots_working`): a spot's intensity-weighted centroid is a first
  moment, which box-averaging keeps (up to the threshold's edge): the decimated
  centroid mapped back is the full-resolution one. Re-measuring it on the full frame
  (a weighted centroid above the window border's median, three standard deviations
  wide) was tried and is worse: 0.035 px against 0.021 px on Gaussian spots of
  sigma 9 px in noise 2 (tests/runtime/features/test_working.py). Areas and second
  moments are scaled to full-resolution pixels (plus a block's own spread).

Convention: pixel ``j`` of a frame decimated by ``f`` is centred on full-resolution
pixel ``f * j + (f - 1) / 2`` (SPEC §1: the origin at the centre of the top-left pixel).

Example::

    f = working_factor(grey.shape)              # 3 for a 4000x3000 frame
    spots = detect_spots_working(grey, SpotParams(), factor=f)
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .spots import SpotParams, Spots, detect_spots

WORKING_MPX = 1.0
"""Frames larger than about this many megapixels are searched decimated."""


def working_factor(shape: tuple[int, ...], working_mpx: float = WORKING_MPX) -> int:
    """The integer decimation factor for a frame of ``shape`` ``(H, W, ...)``:
    ``round(sqrt(H * W / (working_mpx * 1e6)))``, at least 1 (1, or a ``working_mpx``
    of 0: no decimation). A 4000x3000 frame at 1 Mpx is decimated by 3."""
    if working_mpx <= 0:
        return 1
    return max(1, int(math.floor(math.sqrt(shape[0] * shape[1] / (working_mpx * 1e6))
                                 + 0.5)))


def decimate(grey: np.ndarray, factor: int) -> np.ndarray:
    """``grey`` box-averaged over ``factor`` x ``factor`` pixels (the last partial rows
    and columns dropped); ``grey`` itself when ``factor`` is 1."""
    if factor <= 1:
        return grey
    h, w = grey.shape[:2]
    hs, ws = h // factor, w // factor
    return cv2.resize(grey[:hs * factor, :ws * factor], (ws, hs),
                      interpolation=cv2.INTER_AREA)


def undecimate(points_px: np.ndarray, factor: int) -> np.ndarray:
    """Pixels ``(..., 2)`` of a :func:`decimate`-d frame in the full-resolution one."""
    return np.asarray(points_px, np.float64) * factor + (factor - 1) / 2.0


def detect_spots_working(grey: np.ndarray, params: SpotParams | None = None,
                         valid: np.ndarray | None = None,
                         centre_px: tuple[float, float] | None = None,
                         max_regions: int | None = None, factor: int = 1,
                         valid_small: np.ndarray | None = None) -> Spots:
    """:func:`~.spots.detect_spots` on ``grey`` decimated by ``factor``, in
    full-resolution pixels (see the module docstring); ``factor`` 1 is
    ``detect_spots`` itself.

    Args:
        grey: ``(H, W)`` uint8 frame.
        params, centre_px, max_regions: as ``detect_spots`` (``params`` in pixels of the
            decimated frame; ``centre_px`` in full-resolution pixels).
        valid: ``(H, W)`` uint8 mask of usable pixels, or None.
        factor: the decimation factor (:func:`working_factor`).
        valid_small: ``valid`` decimated already (``decimate(valid, factor) >= 128``
            as uint8 255/0), to save the work per frame.
    """
    if factor <= 1:
        return detect_spots(grey, params, valid, centre_px, max_regions)
    small = decimate(grey, factor)
    if valid_small is None and valid is not None:
        valid_small = decimated_mask(valid, factor)
    centre = None if centre_px is None else tuple(
        (np.asarray(centre_px, float) - (factor - 1) / 2.0) / factor)
    s = detect_spots(small, params, valid_small, centre, max_regions)
    if len(s) == 0:
        return s
    f2 = float(factor * factor)
    cov = s.cov_px * f2 + np.eye(2)[None] * (f2 - 1.0) / 12.0   # a block's own spread
    return Spots(undecimate(s.centroids_px, factor), s.areas_px * f2, s.contrast, s.level,
                 cov, s.n_candidates, dict(s.rejected))


def decimated_mask(valid: np.ndarray, factor: int) -> np.ndarray:
    """A uint8 (255/0) mask decimated by ``factor``: a block is valid when at least half
    of it is."""
    if factor <= 1:
        return valid
    return np.where(decimate(valid, factor) >= 128, 255, 0).astype(np.uint8)


__all__ = ["WORKING_MPX", "decimate", "decimated_mask", "detect_spots_working",
           "undecimate", "working_factor"]
