"""Spot-light detection: Niblack local thresholding, identification, sub-pixel centroids.

Convention: pixels ``(u, v)`` with the origin at the centre of the top-left pixel
(SPEC §1); intensities are 8-bit grey levels. Nothing here undistorts: the
centroids are in the distorted image, and only they are undistorted later
(:meth:`CameraModel.unproject`), never the whole image (Roh et al. §III.1).

The pipeline (after Roh et al., "Point pattern matching based visual global
localization using ceiling lights", ASCC 2011, §II):

1. **Niblack thresholding**: a pixel is a candidate when
   ``I > mean + max(k * std, min_contrast)`` over a ``window_px`` square around it.
   The local mean and standard deviation come from box filters (integral images)
   computed on a 4x reduced (bilinearly sampled) image and interpolated back: the light-to-window
   scale is what matters, and it costs a fifth of the full-resolution filter.
2. **Identification** of real lights among the connected candidate regions:
   the perception index of the paper's Eq. (6),
   ``L = (I_o - I_b) * A**0.33 / (1.97 * I_b**0.72)`` (object mean ``I_o``,
   object-background ring mean ``I_b``, area ``A`` in pixels), plus the checks
   the paper leaves implicit: an area range and an elongation bound (the
   estimator predicts both from the light size, the ceiling height and the lens
   at each spot's place), a contrast relative to the brightest spot (rejects
   reflections on glossy ceilings), and a second, higher threshold inside
   regions too large to be one light (glare halos).
3. **Sub-pixel centroids**: intensity-weighted, ``w = max(I - I_b, 0)`` over the
   region's box grown by two pixels, other regions' pixels excluded. The window is
   first divided by the linear gain the light's own plateau shows (a plane fitted to
   the pixels at least :data:`_FLAT_ERODE_PX` inside the region, :func:`flattened`):
   vignetting tilts a light's plateau, and an intensity-weighted centroid follows the
   tilt (towards the brighter side, the image centre: up to 0.3 px on 30 px spots of
   a tilted camera, 0.8 mm of x on a 45 deg corridor rig); a flat (or saturated)
   plateau is left as it is.

Example::

    spots = detect_spots(grey)                 # SpotParams() defaults
    spots.centroids_px                         # (N, 2) float64, distorted pixels
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.jit import arr, njit, warmer

_REDUCE = 4  # the Niblack statistics are computed on a 1/_REDUCE image
_CORE = 0.4  # centroid weights count from I_b + _CORE (I_o - I_b)
_FLAT_ERODE_PX = 3  # the plateau's gain is fitted this far inside a region
_FLAT_MIN_PX = 12  # fewest plateau pixels for a fit (smaller spots: no correction)
_FLAT_MIN_GAIN = 0.5  # the fitted gain is floored here (a fit far off: no blow-up)
FLAT_MIN_AREA_PX = 300
"""Smaller regions are not flattened: their slope is mostly noise (the correction's
noise does not shrink with the spot, the bias it removes does)."""
_FLAT_MAX_RESIDUAL = 0.05  # a plateau the plane leaves this rough (x contrast) is a peak
_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
SATURATED_THRESHOLD = 254.0
"""The Niblack threshold never exceeds this: a saturated (255) pixel is always a
candidate, so a pre-thresholded (0/255) frame gives its lit regions whole."""


@dataclass(frozen=True)
class SpotParams:
    """Knobs of :func:`detect_spots`.

    Attributes:
        window_px: Niblack window side (pixels of the full image); a few light diameters.
        k: Niblack's weight on the local standard deviation.
        min_contrast, min_contrast_rel: a candidate pixel is at least
            ``max(min_contrast, min_contrast_rel * mean)`` grey levels above the local
            mean (keeps flat, noisy or textured ceiling out of the candidates; the
            relative part follows the exposure).
        min_area_px, max_area_px: absolute bounds on a region's area.
        min_level: least perception index ``L`` (Eq. 6) of a real light.
        min_relative_contrast: least contrast relative to the brightest accepted spot
            (0 disables; rejects dim reflections and lit patches).
        min_axis_ratio: least minor/major axis ratio of a region (before any
            per-spot prediction); 0 disables.
        max_spots: keep at most this many spots (the highest perception index).
        max_light_px: the largest core the glare split keeps of a region over
            ``max_area_px`` (a light's own largest image; 0: ``max_area_px``).
        lamp_window_px: a second, larger Niblack window (lights imaged wider than
            ``window_px``: :func:`lamp_mask`); 0 (or not above ``window_px``): none.
    """

    window_px: int = 41
    k: float = 0.8
    min_contrast: float = 10.0
    min_contrast_rel: float = 0.2
    min_area_px: int = 3
    max_area_px: int = 6000
    min_level: float = 1.0
    min_relative_contrast: float = 0.3
    min_axis_ratio: float = 0.15
    max_spots: int = 64
    max_light_px: int = 0
    lamp_window_px: int = 0


@dataclass(frozen=True, eq=False)
class Spots:
    """Detected spots of one frame (all arrays have N rows).

    Attributes:
        centroids_px: ``(N, 2)`` intensity-weighted centroids ``(u, v)``, distorted pixels.
        areas_px: ``(N,)`` region areas (pixels above the threshold).
        contrast: ``(N,)`` ``I_o - I_b``, grey levels.
        level: ``(N,)`` perception index ``L`` of Eq. (6).
        cov_px: ``(N, 2, 2)`` intensity-weighted second moments of each spot, px².
        n_candidates: connected regions before identification.
        rejected: why candidates were dropped, ``{reason: count}``.
    """

    centroids_px: np.ndarray
    areas_px: np.ndarray
    contrast: np.ndarray
    level: np.ndarray
    cov_px: np.ndarray
    n_candidates: int = 0
    rejected: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.centroids_px.shape[0])

    def select(self, keep: np.ndarray) -> Spots:
        """The spots where the boolean ``keep`` (N,) holds."""
        keep = np.asarray(keep, dtype=bool)
        return Spots(self.centroids_px[keep], self.areas_px[keep], self.contrast[keep],
                     self.level[keep], self.cov_px[keep], self.n_candidates,
                     dict(self.rejected))


def empty_spots(n_candidates: int = 0, rejected: dict[str, int] | None = None) -> Spots:
    return Spots(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0),
                 np.zeros((0, 2, 2)), n_candidates, dict(rejected or {}))


def perception_level(i_object: np.ndarray, i_background: np.ndarray,
                     area_px: np.ndarray) -> np.ndarray:
    """The perception index of Roh et al. Eq. (6), ``(I_o - I_b) A^0.33 / (1.97 I_b^0.72)``.

    The just-noticeable contrast of an object of area ``A`` on a background of mean
    grey ``I_b`` grows as ``1.97 I_b^0.72 / A^0.33``; the index is the object's
    contrast in units of that threshold (> 1: visible). ``I_b`` is floored at 1.
    """
    ib = np.maximum(np.asarray(i_background, float), 1.0)
    return ((np.asarray(i_object, float) - ib) * np.power(np.asarray(area_px, float), 0.33)
            / (1.97 * np.power(ib, 0.72)))


def niblack_mask(grey: np.ndarray, window_px: int = 41, k: float = 0.8,
                 min_contrast: float = 10.0, min_contrast_rel: float = 0.0) -> np.ndarray:
    """Binary ``(H, W)`` uint8 mask (0/255) of
    ``I > min(mean + max(k std, min_contrast, min_contrast_rel mean), 254)`` (a saturated
    pixel is always a candidate: :data:`SATURATED_THRESHOLD`).

    Local statistics over a ``window_px`` square, from box filters on a 4x reduced
    (bilinearly sampled) image; the threshold is bilinearly enlarged back to full size.
    """
    h, w = grey.shape
    sw, sh = max(1, w // _REDUCE), max(1, h // _REDUCE)
    small = cv2.resize(grey, (sw, sh), interpolation=cv2.INTER_LINEAR)
    win = max(3, int(round(window_px / _REDUCE)) | 1)
    mean = cv2.boxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    # whole grey levels suffice: threshold, enlarge and compare in 8 bit (clipped to
    # 0..SATURATED_THRESHOLD, the conversion truncates: the floor). The cap keeps a
    # saturated pixel a candidate: inside a light larger than the window (a panel near
    # the camera, or any light of a frame thresholded to 0/255 before it was stored)
    # the local mean is itself 255 and the threshold above it would hollow the light
    # out into a ring of fragments
    thr8 = niblack_levels(mean, sq, np.float32(k), np.float32(min_contrast),
                          np.float32(min_contrast_rel), np.float32(SATURATED_THRESHOLD))
    thr8 = cv2.resize(thr8, (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.compare(grey, thr8, cv2.CMP_GT)


def lamp_mask(grey: np.ndarray, mask: np.ndarray, params: SpotParams) -> np.ndarray:
    """``mask`` (0/255) with the regions of a Niblack mask over ``params.lamp_window_px``
    that hold no saturated plateau (no 255 pixel whose 4 neighbours are 255 too) added.

    Inside an unsaturated light wider than ``window_px`` the local mean is the light's
    own level and the threshold (at least 1.2 times it) hollows it into a ring of
    fragments; the larger window takes it whole. Around a saturated light the larger
    window's lower mean lets the raw frame's halo into its region (the held-out lamps0
    drive of seed 3: median 5.6 -> 10.4 mm), while ``window_px`` keeps the light whole
    already (a 255 pixel is always a candidate: :data:`SATURATED_THRESHOLD`): a region
    of the larger window that holds a plateau of clipped pixels is left to ``mask``.
    A plateau, not one pixel: sensor noise (sigma 2) puts single 255 pixels on
    unsaturated lamps (held-out lamps1 of seed 3 and its kidnap: 3,239 of the 1.67 M
    pixels above 240 in 200 frames), none in a cross of five. A 0/255 frame's mask is
    unchanged (its lit pixels are all in ``mask``)."""
    if params.lamp_window_px <= params.window_px:
        return mask
    grown = niblack_mask(grey, params.lamp_window_px, params.k, params.min_contrast,
                         params.min_contrast_rel)
    if cv2.countNonZero(cv2.subtract(grown, mask)) == 0:   # nothing to add (a 0/255 frame)
        return mask
    plateau = cv2.erode(cv2.compare(grey, 254, cv2.CMP_GT), _CROSS)
    if cv2.countNonZero(plateau) == 0:                     # nothing clipped
        return cv2.bitwise_or(mask, grown)
    n, labels = cv2.connectedComponents(grown, connectivity=8)
    clipped = np.zeros(n, bool)
    clipped[0] = True
    clipped[labels[plateau > 0]] = True
    return cv2.bitwise_or(mask, np.where(clipped[labels], 0, 255).astype(np.uint8))


@njit
def niblack_levels(mean, sq, k, floor_abs, floor_rel, cap):  # pragma: no cover - compiled
    """``(h, w)`` uint8 Niblack thresholds from the box means ``mean`` and ``sq`` (of
    ``I`` and ``I²``, float32) in one compiled loop, in float32 as the array reading
    ``min(max(mean + max(k sqrt(max(sq - mean², 0)), max(floor_rel mean, floor_abs)),
    0), cap)`` truncated (``k``, ``floor_abs``, ``floor_rel``, ``cap``: float32): the
    same levels, bit for bit (tests/runtime/features/test_spots.py), one call in place
    of nine array operations (0.09 ms at 160x120 on the 2-core VM, now 0.01)."""
    h, w = mean.shape
    out = np.empty((h, w), np.uint8)
    zero = np.float32(0.0)
    for i in range(h):
        for j in range(w):
            m = mean[i, j]
            v = sq[i, j] - m * m
            s = np.sqrt(max(v, zero)) * k
            f = max(m * floor_rel, floor_abs)
            t = m + max(s, f)
            out[i, j] = np.uint8(min(max(t, zero), cap))
    return out


def tile_niblack_mask(grey: np.ndarray, tile_px: int = 64, k: float = 0.8,
                      min_contrast: float = 0.0) -> np.ndarray:
    """Niblack over non-overlapping ``tile_px`` sub-images (Roh et al. §IV: 64x64).

    Each tile is thresholded at its own ``mean + max(k std, min_contrast)``; a 0/255 mask.
    """
    h, w = grey.shape
    ny, nx = -(-h // tile_px), -(-w // tile_px)
    pad = cv2.copyMakeBorder(grey, 0, ny * tile_px - h, 0, nx * tile_px - w,
                             cv2.BORDER_REFLECT)
    blocks = pad.reshape(ny, tile_px, nx, tile_px).astype(np.float32)
    mean = blocks.mean(axis=(1, 3))
    std = blocks.std(axis=(1, 3))
    thr = mean + np.maximum(k * std, min_contrast)
    full = np.repeat(np.repeat(thr, tile_px, axis=0), tile_px, axis=1)[:h, :w]
    return np.where(grey.astype(np.float32) > full, 255, 0).astype(np.uint8)


def _region_stats(grey: np.ndarray, mask: np.ndarray, contour: np.ndarray | None, x0: int,
                  y0: int, bw: int, bh: int, weighted: bool
                  ) -> tuple[float, float, float, float, np.ndarray, float]:
    """``(u, v, I_o, I_b, cov(2x2), area)`` of the region inside ``contour``.

    ``mask`` is the candidate mask (0/255), ``(x0, y0, bw, bh)`` the contour's box. The
    object-background ring is the box grown by half its size (the paper's
    ``w/2 x h/2`` dilation), minus every candidate pixel. The centroid window is the
    box grown by 2 px, other candidates' pixels excluded. ``contour=None`` says that no
    other region reaches the grown box: every candidate pixel there is this region's
    (the common case, and a third of the work).
    """
    H, W = grey.shape
    gx, gy = max(2, bw // 2), max(2, bh // 2)
    xa, ya = max(0, x0 - gx), max(0, y0 - gy)
    xb, yb = min(W, x0 + bw + gx), min(H, y0 + bh + gy)
    roi = grey[ya:yb, xa:xb]
    cand = mask[ya:yb, xa:xb]
    if contour is None:
        obj = cand
    else:
        obj = np.zeros_like(cand)
        cv2.drawContours(obj, [contour], -1, 255, -1, offset=(-xa, -ya))
        obj = cv2.bitwise_and(obj, cand)
    area = float(cv2.countNonZero(obj))
    if area == 0:
        return 0.0, 0.0, 0.0, 0.0, np.zeros((2, 2)), 0.0
    i_o = cv2.mean(roi, obj)[0]
    n_cand = area if contour is None else float(cv2.countNonZero(cand))
    n_ring = roi.size - n_cand
    if n_ring <= 0:
        i_b = float(roi.min())
    elif contour is None:
        i_b = (cv2.sumElems(roi)[0] - i_o * area) / n_ring
    else:
        i_b = cv2.mean(roi, cv2.bitwise_not(cand))[0]
    cx0, cy0 = max(0, x0 - 2) - xa, max(0, y0 - 2) - ya
    cx1, cy1 = min(W, x0 + bw + 2) - xa, min(H, y0 + bh + 2) - ya
    osub = obj[cy0:cy1, cx0:cx1]
    if weighted:
        base = i_b + _CORE * (i_o - i_b)
        win = roi[cy0:cy1, cx0:cx1]
        flat = flattened(win, osub, i_o - i_b) if area >= FLAT.min_area_px else None
        wts = cv2.max(cv2.subtract(win if flat is None else flat, base, dtype=cv2.CV_32F), 0.0)
        if contour is not None:
            others = cv2.countNonZero(cand[cy0:cy1, cx0:cx1]) - cv2.countNonZero(osub)
            if others:
                wts[(cand[cy0:cy1, cx0:cx1] > 0) & (osub == 0)] = 0.0
        m = cv2.moments(wts)
        if m["m00"] <= 0:
            m = cv2.moments(osub, True)
    else:
        m = cv2.moments(osub, True)
    u = m["m10"] / m["m00"] + cx0 + xa
    v = m["m01"] / m["m00"] + cy0 + ya
    cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
    return u, v, i_o, i_b, cov, area


def flattened(win: np.ndarray, obj: np.ndarray, contrast: float) -> np.ndarray | None:
    """A light's window divided by the linear gain its plateau shows, or ``None``.

    Vignetting multiplies a light's window by a gain that varies across it; the
    plateau of a uniform light then slopes, and an intensity-weighted centroid moves
    towards its bright side (the image centre). A plane ``a + b x + c y`` is fitted to
    the pixels at least :data:`_FLAT_ERODE_PX` inside the region (away from its blurred
    edge) and the window is divided by it, relative to its value at those pixels'
    centroid; the slope is shrunk by its own noise, ``|s|² / (|s|² + var s)``.
    ``None`` (use the window as it is) when the core has fewer than
    :data:`_FLAT_MIN_PX` pixels, when the plane does not explain it (its residual
    above :data:`_FLAT_MAX_RESIDUAL` of the light's ``contrast``: a peaked light, whose
    slope is its own shape, not a gain) or when the fit is degenerate. A flat or
    saturated plateau gives a flat plane: no change.

    Args:
        win: ``(h, w)`` uint8 grey levels; ``obj``: ``(h, w)`` the region's pixels
            (non-zero); ``contrast``: ``I_o - I_b``, grey levels.

    Returns:
        ``(h, w)`` float32 flattened grey levels, or ``None``.
    """
    core = cv2.erode((obj > 0).astype(np.uint8), _CROSS, iterations=_FLAT_ERODE_PX,
                     borderType=cv2.BORDER_CONSTANT, borderValue=0)
    mc = cv2.moments(core, True)
    n = mc["m00"]
    if n < _FLAT_MIN_PX:
        return None
    gc = np.multiply(win, core, dtype=np.float32)
    mg = cv2.moments(gc)
    xc, yc = mc["m10"] / n, mc["m01"] / n
    # the plane about the core's centroid: g = a + b (x - xc) + c (y - yc)
    sxx, sxy, syy = mc["mu20"], mc["mu11"], mc["mu02"]
    det = sxx * syy - sxy * sxy
    if not (sxx >= n and syy >= n and det > 0):          # spread over >= 1 px each way
        return None
    a = mg["m00"] / n
    gx = mg["m10"] - a * mc["m10"]                        # sum of g (x - xc)
    gy = mg["m01"] - a * mc["m01"]
    b = (syy * gx - sxy * gy) / det
    c = (sxx * gy - sxy * gx) / det
    if not a > 0:
        return None
    ssr = float(cv2.sumElems(cv2.multiply(gc, gc))[0]) - n * a * a - b * gx - c * gy
    if ssr > n * (_FLAT_MAX_RESIDUAL * contrast) ** 2:
        return None
    # the slope shrunk by its own noise (Wiener): on a small plateau the fitted slope
    # is mostly noise, and dividing by it would only add noise to the centroid
    s2 = max(ssr, 0.0) / max(n - 3.0, 1.0)
    var = s2 * (sxx + syy) / det
    slope2 = b * b + c * c
    if not slope2 > 0:
        return None
    shrink = slope2 / (slope2 + var)
    b, c = b * shrink, c * shrink
    h, w = win.shape
    gain = (1.0 + (b / a) * (np.arange(w, dtype=np.float32) - np.float32(xc)))[None, :] \
        + ((c / a) * (np.arange(h, dtype=np.float32) - np.float32(yc)))[:, None]
    return win / np.maximum(gain, _FLAT_MIN_GAIN, dtype=np.float32)


@njit
def _plateau(win, obj, tmp, contrast, erode, min_px, max_residual
             ):  # pragma: no cover - compiled
    """The plane ``a + b (x - xc) + c (y - yc)`` of a light's plateau in its window, as
    :func:`~.spots.flattened` fits it: ``(ok, a, b, c, xc, yc)``, ``(x, y)`` column and
    row in the window. ``obj`` (the spot's pixels, 0/1) is eroded ``erode`` times by a
    3x3 cross, outside the window 0 (``tmp``: scratch of its shape; ``obj`` is left
    eroded)."""
    h, w = obj.shape
    # the spot's box: erosion only removes, and beyond the box every pixel is 0
    i0, i1, j0, j1 = h, -1, w, -1
    for i in range(h):
        for j in range(w):
            if obj[i, j]:
                i0, i1 = min(i0, i), max(i1, i)
                j0, j1 = min(j0, j), max(j1, j)
    if i1 < 0:
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    for _ in range(erode):
        tmp[i0:i1 + 1, j0:j1 + 1] = obj[i0:i1 + 1, j0:j1 + 1]
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                if tmp[i, j] and (i == i0 or j == j0 or i == i1 or j == j1
                                  or not (tmp[i - 1, j] and tmp[i + 1, j]
                                          and tmp[i, j - 1] and tmp[i, j + 1])):
                    obj[i, j] = 0
    n = sx = sy = 0.0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            if obj[i, j]:
                n += 1.0
                sx += j
                sy += i
    if n < min_px:
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    xc, yc = sx / n, sy / n
    sxx = sxy = syy = g0 = gx = gy = gg = 0.0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            if obj[i, j]:
                dx, dy = j - xc, i - yc
                g = np.float64(win[i, j])
                sxx += dx * dx
                sxy += dx * dy
                syy += dy * dy
                g0 += g
                gx += g * dx
                gy += g * dy
                gg += g * g
    det = sxx * syy - sxy * sxy
    if not (sxx >= n and syy >= n and det > 0):          # spread over >= 1 px each way
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    a = g0 / n
    b = (syy * gx - sxy * gy) / det
    c = (sxx * gy - sxy * gx) / det
    if not a > 0:
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    ssr = gg - n * a * a - b * gx - c * gy
    if ssr > n * (max_residual * contrast) ** 2:
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    s2 = max(ssr, 0.0) / max(n - 3.0, 1.0)
    var = s2 * (sxx + syy) / det
    slope2 = b * b + c * c
    if not slope2 > 0:
        return False, 1.0, 0.0, 0.0, 0.0, 0.0
    shrink = slope2 / (slope2 + var)
    return True, a, b * shrink, c * shrink, xc, yc


def _alone(boxes: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: no other box of ``(N, 4)`` ``(x0, y0, bw, bh)`` reaches box ``i``
    grown as in :func:`_region_stats` (:func:`_lone`)."""
    return _lone(arr(boxes, np.int64).reshape(-1, 4))


@njit
def _lone(boxes):  # pragma: no cover - compiled
    """:func:`_alone` in a compiled loop (every box meets itself)."""
    n = boxes.shape[0]
    alone = np.ones(n, np.bool_)
    if n < 2:
        return alone
    for i in range(n):
        x0, y0, bw, bh = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        gx, gy = max(2, bw // 2), max(2, bh // 2)
        hits = 0
        for j in range(n):
            hits += (boxes[j, 0] < x0 + bw + gx and boxes[j, 0] + boxes[j, 2] > x0 - gx
                     and boxes[j, 1] < y0 + bh + gy and boxes[j, 1] + boxes[j, 3] > y0 - gy)
        alone[i] = hits == 1
    return alone


def _examination_order(boxes: np.ndarray, centre_px: tuple[float, float] | None) -> np.ndarray:
    """Indices of the regions' bounding boxes ``(N, 4)``, nearest ``centre_px`` first
    (stably; :func:`_order`)."""
    b = arr(boxes, np.float64).reshape(-1, 4)
    if centre_px is None:
        return np.arange(b.shape[0])
    return _order(b, float(centre_px[0]), float(centre_px[1]))


@njit
def _order(boxes, cu, cv):  # pragma: no cover - compiled
    """:func:`_examination_order` in a compiled loop: by the squared distance of each
    box's centre from ``(cu, cv)``, stably."""
    d2 = np.empty(boxes.shape[0])
    for i in range(boxes.shape[0]):
        du = boxes[i, 0] + boxes[i, 2] / 2 - cu          # box centre - centre
        dv = boxes[i, 1] + boxes[i, 3] / 2 - cv
        d2[i] = du ** 2 + dv ** 2
    return np.argsort(d2, kind="mergesort")


# lone regions whose grown box fits this square are measured together
# (:func:`_lone_region_stats`); larger ones, one by one (:func:`_region_stats`)
_BATCH_MAX_SIDE = 64


class Flattening(NamedTuple):
    """The plateau correction as the compiled loops read it (:func:`flattened`): a
    spot of ``min_area_px`` pixels or more has its plateau's gain fitted
    ``erode_px`` inside it, on at least ``min_px`` pixels, unless the plane leaves it
    rougher than ``max_residual`` of the contrast; the gain is floored at
    ``min_gain``."""

    min_area_px: int
    erode_px: int
    min_px: int
    max_residual: float
    min_gain: float


FLAT = Flattening(FLAT_MIN_AREA_PX, _FLAT_ERODE_PX, _FLAT_MIN_PX, _FLAT_MAX_RESIDUAL,
                  _FLAT_MIN_GAIN)
"""The detector's :class:`Flattening` (its module constants)."""


class RegionWalk(NamedTuple):
    """How :func:`_classify` and :func:`_walk` examine the regions: nearest the pixel
    ``(centre_u, centre_v)`` first when ``has_centre``, a region reaching the frame's
    edge dropped when ``drop_cut``, the plausible areas ``min_area_px`` to
    ``max_area_px``, at most ``max_regions`` rows (-1: no limit)."""

    has_centre: bool
    centre_u: float
    centre_v: float
    drop_cut: bool
    min_area_px: int
    max_area_px: int
    max_regions: int


class Classified(NamedTuple):
    """What :func:`_classify` returns: the ``order`` the regions are examined in,
    which are ``alone``, which are ``cut`` by the frame's edge, each region's row of
    ``stats`` ``row_of`` (-1: none) and the lone regions' ``stats (K, 8)``."""

    order: np.ndarray
    alone: np.ndarray
    cut: np.ndarray
    row_of: np.ndarray
    stats: np.ndarray


def _lone_region_stats(grey: np.ndarray, mask: np.ndarray, boxes: np.ndarray,
                       weighted: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_region_stats` of many lone regions at once (``contour=None``: no other
    region reaches a region's grown box), in a few array operations instead of a dozen
    calls per region.

    A lone region's candidate pixels are all inside its own box, so its area and
    object sum come from the centroid window (the box grown by 2 px) like the weights;
    only the ring needs the grown box (its grey sum). One compiled loop over the
    regions (:func:`_lone_stats`).

    Args:
        grey: ``(H, W)`` uint8 image; ``mask``: ``(H, W)`` uint8 candidate mask (0/255).
        boxes: ``(K, 4)`` int ``(x0, y0, bw, bh)`` bounding boxes of lone regions.
        weighted: intensity-weighted centroids (else binary), as in :func:`_region_stats`.

    Returns:
        ``(stats (K, 8), ok (K,))``: rows ``(u, v, I_o, I_b, c00, c01, c11, area)``
        (centroid in px, means in grey levels, second moments ``c`` in px², area in
        px): the numbers of :func:`_region_stats` (the moments to 1e-12 relative, the
        rest exactly; all exactly for binary centroids). ``ok`` is False where that
        function takes a special branch (no candidate pixel, no ring pixel, no positive
        weight): the caller measures those rows with it.
    """
    b = arr(boxes, np.int64).reshape(-1, 4)
    out = np.empty((b.shape[0], 8))
    ok = _lone_stats(arr(grey, np.uint8), arr(mask, np.uint8), b, bool(weighted), _CORE,
                     FLAT, out)
    return out, ok


@njit
def _lone_stats(grey, mask, boxes, weighted, core, flat, out):  # pragma: no cover - compiled
    """:func:`_lone_region_stats` into ``out (K, 8)``, the centroid weights counting
    from ``I_b + core (I_o - I_b)`` when ``weighted``, a plateau flattened as ``flat``
    (a :class:`Flattening`) says; returns ``ok (K,)``. The weights
    are float32 as ``cv2.subtract(..., dtype=CV_32F)`` gives them (a flattened
    plateau's gain too, as :func:`flattened` computes it), their moments summed in
    float64 (exact for these windows, as ``cv2.moments``)."""
    H, W = grey.shape
    k = boxes.shape[0]
    ok = np.zeros(k, np.bool_)
    for n in range(k):
        x0, y0, bw, bh = boxes[n, 0], boxes[n, 1], boxes[n, 2], boxes[n, 3]
        gx, gy = max(2, bw // 2), max(2, bh // 2)
        lx, ly = max(x0 - gx, 0), max(y0 - gy, 0)
        hx, hy = min(x0 + bw + gx, W), min(y0 + bh + gy, H)
        s_box = 0.0
        for i in range(ly, hy):
            for j in range(lx, hx):
                s_box += grey[i, j]
        n_box = (hx - lx) * (hy - ly)
        cx0, cy0 = max(x0 - 2, 0), max(y0 - 2, 0)
        cx1, cy1 = min(x0 + bw + 2, W), min(y0 + bh + 2, H)
        win = grey[cy0:cy1, cx0:cx1]
        obj = (mask[cy0:cy1, cx0:cx1] > 0).astype(np.uint8)
        area = 0
        s_obj = 0
        for i in range(cy1 - cy0):
            for j in range(cx1 - cx0):
                if obj[i, j]:
                    area += 1
                    s_obj += np.int64(win[i, j])
        n_ring = n_box - area
        good = area > 0 and n_ring > 0
        i_o = s_obj * (1.0 / (area if good else 1.0))      # as cv2.mean: sum * (1 / count)
        i_b = (s_box - i_o * area) / (n_ring if good else 1.0)
        m = np.zeros(6)
        if weighted:
            base = np.float32(i_b + core * (i_o - i_b))
            plane = (False, 1.0, 0.0, 0.0, 0.0, 0.0)
            if good and area >= flat.min_area_px:
                tmp = np.empty_like(obj)
                plane = _plateau(win, obj.copy(), tmp, i_o - i_b, flat.erode_px,
                                 flat.min_px, flat.max_residual)
            _float32_moments(win, base, plane, flat.min_gain, m)
        else:
            for i in range(cy1 - cy0):
                for j in range(cx1 - cx0):
                    if obj[i, j]:
                        _add_moments(m, 1.0, j, i)
        good = good and m[0] > 0
        m00 = m[0] if good else 1.0
        cx, cy = m[1] * (1.0 / m00), m[3] * (1.0 / m00)
        out[n, 0] = m[1] / m00 + float(cx0 - lx) + float(lx)
        out[n, 1] = m[3] / m00 + float(cy0 - ly) + float(ly)
        out[n, 2], out[n, 3] = i_o, i_b
        out[n, 4] = (m[2] - m[1] * cx) / m00
        out[n, 5] = (m[5] - m[1] * cy) / m00
        out[n, 6] = (m[4] - m[3] * cy) / m00
        out[n, 7] = area
        ok[n] = good
    return ok


@njit
def _float32_moments(win, base, plane, min_gain, m):  # pragma: no cover - compiled
    """Into ``m (6,)``: the raw moments of ``max(I - base, 0)`` in float32 over the
    window, ``I`` the window or, when ``plane`` holds one, the window divided by the
    plateau's gain in float32 as :func:`flattened` computes it."""
    flat, a, b, c, xc, yc = plane
    bx, cy_, x32, y32 = np.float32(b / a), np.float32(c / a), np.float32(xc), np.float32(yc)
    one, lo = np.float32(1.0), np.float32(min_gain)
    for i in range(win.shape[0]):
        gy = cy_ * (np.float32(i) - y32)
        for j in range(win.shape[1]):
            if flat:
                gain = max((one + bx * (np.float32(j) - x32)) + gy, lo)
                v = np.float32(np.float32(win[i, j]) / gain) - base
            else:
                v = np.float32(win[i, j]) - base
            if v > 0:
                _add_moments(m, np.float64(v), j, i)


@njit
def _add_moments(m, w, x, y):  # pragma: no cover - compiled
    """``m += w (1, x, x², y, y², x y)``."""
    m[0] += w
    m[1] += w * x
    m[2] += w * x * x
    m[3] += w * y
    m[4] += w * y * y
    m[5] += w * x * y


def axis_ratios(cov_px: np.ndarray) -> np.ndarray:
    """Minor/major axis ratio ``(N,)`` of second-moment matrices ``(N, 2, 2)``."""
    a, b, c = cov_px[:, 0, 0], cov_px[:, 0, 1], cov_px[:, 1, 1]
    disc = np.sqrt(np.maximum((a - c) ** 2 / 4 + b * b, 0.0))
    mid = (a + c) / 2
    return np.sqrt(np.maximum(mid - disc, 0.0) / np.maximum(mid + disc, 1e-12))


def regions_to_spots(grey: np.ndarray, mask: np.ndarray, params: SpotParams,
                     weighted: bool = True, rethreshold: bool = True,
                     relative: bool = True, centre_px: tuple[float, float] | None = None,
                     max_regions: int | None = None, drop_cut: bool = True) -> Spots:
    """Identify lights among the connected regions of ``mask`` (see the module doc).

    With ``centre_px``, regions are examined nearest that pixel first (the principal
    point: the sharpest, best-resolved lights), at most ``max_regions`` of them that
    pass the size checks. With ``drop_cut`` a region reaching the frame's edge (a light
    cut by it, its centroid biased inwards) is dropped (``rejected["cut"]``).
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    rejected: dict[str, int] = {}
    rows = _measure_regions(grey, mask, contours, params, weighted, rethreshold, centre_px,
                            max_regions, rejected, drop_cut)
    if not rows.shape[0]:
        return empty_spots(len(contours), rejected)
    return _select_lights(rows, len(contours), params, relative, rejected)


_REASONS = ("beyond_max_regions", "small", "cut", "large")   # _walk's counts, in order


def _measure_regions(grey: np.ndarray, mask: np.ndarray, contours: Sequence[np.ndarray],
                     params: SpotParams, weighted: bool, rethreshold: bool,
                     centre_px: tuple[float, float] | None, max_regions: int | None,
                     rejected: dict[str, int], drop_cut: bool = True) -> np.ndarray:
    """``(K, 8)`` rows ``(u, v, i_obj, i_bg, c_uu, c_uv, c_vv, area)``, one per region of
    a plausible size, in the order examined; the others are counted in ``rejected`` by
    reason.

    The regions' boxes are classified, ordered and the lone ones of a plausible size
    measured in one compiled call (:func:`_classify`); the walk in the order examined
    is another (:func:`_walk`), which hands back the few regions it cannot measure: one
    that another region reaches (measured inside its contour, :func:`_region_stats`) or
    one too large for a light (a glare halo, :func:`_split_glare`)."""
    H, W = grey.shape
    b = np.array([cv2.boundingRect(c) for c in contours], np.int64).reshape(-1, 4)
    n = b.shape[0]
    cu, cv = (float(centre_px[0]), float(centre_px[1])) if centre_px is not None \
        else (math.nan, math.nan)
    walk = RegionWalk(has_centre=centre_px is not None, centre_u=cu, centre_v=cv,
                      drop_cut=bool(drop_cut), min_area_px=int(params.min_area_px),
                      max_area_px=int(params.max_area_px),
                      max_regions=-1 if max_regions is None else int(max_regions))
    classified = _classify(arr(grey, np.uint8), arr(mask, np.uint8), arr(b, np.int64), walk,
                           bool(weighted), _CORE, FLAT)
    order, alone, row_of, stats = (classified.order, classified.alone, classified.row_of,
                                   classified.stats)
    rows = np.empty((n, 8))
    counts = np.zeros(len(_REASONS), np.int64)
    small, large = _REASONS.index("small"), _REASONS.index("large")
    pos = n_rows = 0
    while True:
        pos, n_rows = _walk(classified, b, walk, pos, n_rows, rows, counts)
        if pos >= n:
            break
        ci = int(order[pos])
        x0, y0, bw, bh = (int(v) for v in b[ci])
        if bw * bh > 4 * params.max_area_px:
            row, area = None, params.max_area_px + 1
        elif row_of[ci] >= 0:
            row = stats[row_of[ci]]
            area = row[7]
        else:
            u, v, i_o, i_b, cov, area = _region_stats(
                grey, mask, None if alone[ci] else contours[ci], x0, y0, bw, bh, weighted)
            row = [u, v, i_o, i_b, cov[0, 0], cov[0, 1], cov[1, 1], float(area)]
        if area < params.min_area_px:
            counts[small] += 1
        elif area > params.max_area_px:
            sub = _split_glare(grey, mask, contours[ci], x0, y0, bw, bh, params) \
                if rethreshold else None
            if sub is None:
                counts[large] += 1
            else:
                rows[n_rows] = sub
                n_rows += 1
        else:
            rows[n_rows] = row
            n_rows += 1
        pos += 1
    for reason, count in zip(_REASONS, counts.tolist(), strict=True):
        if count:
            rejected[reason] = rejected.get(reason, 0) + count
    return rows[:n_rows]


@njit
def _classify(grey, mask, boxes, walk, weighted, core, flat):  # pragma: no cover - compiled
    """The :class:`Classified` regions' boxes ``(N, 4)`` ``(x0, y0, bw, bh)``, as
    ``walk`` (a :class:`RegionWalk`) says: the order they are examined in (nearest
    its centre first, stably, with ``has_centre``); which are alone (no other box
    reaches the box grown as in :func:`_region_stats`); which reach the frame's edge (a
    light cut by it, its centroid biased inwards: dropped with ``drop_cut``; on a
    tilted rig a far light leaving the top of the frame moved the pose by 2 cm); and
    the lone regions of a plausible size whose grown box fits
    :data:`_BATCH_MAX_SIDE` measured together (:func:`_lone_stats` with ``weighted``,
    ``core``, ``flat``; rows ``stats``; ``row_of`` a region's row there, -1: none), in
    the order examined, a few more than can be examined (``max_regions`` + 2; -1: no
    limit)."""
    H, W = grey.shape
    n = boxes.shape[0]
    drop_cut, min_area, max_area = walk.drop_cut, walk.min_area_px, walk.max_area_px
    max_regions, batch_max_side = walk.max_regions, _BATCH_MAX_SIDE
    order = _order(boxes.astype(np.float64), walk.centre_u, walk.centre_v) \
        if walk.has_centre else np.arange(n)
    alone = _lone(boxes)
    cut = np.zeros(n, np.bool_)
    batch = np.zeros(n, np.bool_)
    for i in range(n):
        x0, y0, bw, bh = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        gx, gy = max(2, bw // 2), max(2, bh // 2)
        cut[i] = drop_cut and (x0 <= 0 or y0 <= 0 or x0 + bw >= W or y0 + bh >= H)
        area = bw * bh
        batch[i] = (alone[i] and min_area <= area <= 4 * max_area and not cut[i]
                    and bw + 2 * gx <= min(W, batch_max_side)
                    and bh + 2 * gy <= min(H, batch_max_side))
    todo = np.empty(n, np.int64)
    k = 0
    for i in order:
        if batch[i] and (max_regions < 0 or k < max_regions + 2):
            todo[k] = i
            k += 1
    stats = np.empty((k, 8))
    good = _lone_stats(grey, mask, boxes[todo[:k]], weighted, core, flat, stats)
    row_of = np.full(n, -1, np.int64)
    for r in range(k):
        if good[r]:
            row_of[todo[r]] = r
    return Classified(order, alone, cut, row_of, stats)


@njit
def _walk(classified, boxes, walk, start, n_rows, rows, counts):  # pragma: no cover
    """The regions of ``classified`` (:func:`_classify`'s) in the order examined from
    position ``start``, ``n_rows`` rows found so far, as ``walk`` (a
    :class:`RegionWalk`) says: each dropped (``counts`` by :data:`_REASONS`: past
    ``max_regions`` rows (-1: no limit), a box or a region below ``min_area_px``, cut
    by the frame's edge) or its row of ``stats`` appended to ``rows``, until one the
    caller must measure (no row: another region reaches it; a box beyond 4
    ``max_area_px`` or a region beyond ``max_area_px``: a glare halo). Returns ``(its
    position, or N when none is left, n_rows)``."""
    order, cut, row_of, stats = (classified.order, classified.cut, classified.row_of,
                                 classified.stats)
    min_area, max_area, max_regions = walk.min_area_px, walk.max_area_px, walk.max_regions
    n = order.size
    for pos in range(start, n):
        ci = order[pos]
        if max_regions >= 0 and n_rows >= max_regions:
            counts[0] += 1
            continue
        box_area = boxes[ci, 2] * boxes[ci, 3]
        if box_area < min_area:
            counts[1] += 1
            continue
        if cut[ci]:
            counts[2] += 1
            continue
        r = row_of[ci]
        if box_area > 4 * max_area or r < 0:
            return pos, n_rows
        if stats[r, 7] < min_area:
            counts[1] += 1
            continue
        if stats[r, 7] > max_area:
            return pos, n_rows
        rows[n_rows] = stats[r]
        n_rows += 1
    return n, n_rows


def rows_to_spots(rows: np.ndarray, n_candidates: int = 0,
                  rejected: dict[str, int] | None = None) -> Spots:
    """:class:`Spots` of measured regions ``rows (K, 8)``: ``(u, v, I_o, I_b, c00,
    c01, c11, area)`` (px, grey levels, px², px), their perception index from
    :func:`perception_level` (the area floored at 1 px)."""
    i_o, i_b, area = rows[:, 2], rows[:, 3], rows[:, 7]
    cov = np.empty((rows.shape[0], 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = rows[:, 4], rows[:, 6]
    cov[:, 0, 1] = cov[:, 1, 0] = rows[:, 5]
    return Spots(rows[:, 0:2].copy(), area.copy(), i_o - i_b,
                 perception_level(i_o, i_b, np.maximum(area, 1.0)), cov, n_candidates,
                 {} if rejected is None else rejected)


def _select_lights(r: np.ndarray, n_candidates: int, params: SpotParams, relative: bool,
                   rejected: dict[str, int]) -> Spots:
    """The measured regions ``r`` ``(K, 8)`` that look like lights: bright enough
    (perception level), round enough, not dim beside the brightest, at most
    ``params.max_spots`` of them (the brightest)."""
    spots = rows_to_spots(r, n_candidates, rejected)
    cov, contrast, level = spots.cov_px, spots.contrast, spots.level
    keep = level >= params.min_level
    rejected["level"] = rejected.get("level", 0) + keep.size - int(np.count_nonzero(keep))
    if params.min_axis_ratio > 0:
        bad = keep & (axis_ratios(cov) < params.min_axis_ratio)
        rejected["shape"] = int(np.count_nonzero(bad))
        keep &= ~bad
    if relative and params.min_relative_contrast > 0 and keep.any():
        bad = keep & (contrast < params.min_relative_contrast * contrast[keep].max())
        rejected["dim"] = int(np.count_nonzero(bad))
        keep &= ~bad
    if not keep.all():
        spots = spots.select(keep)
    if len(spots) > params.max_spots:
        order = np.argsort(-spots.level)[:params.max_spots]
        m = np.zeros(len(spots), bool)
        m[order] = True
        spots = spots.select(m)
    return spots


def _split_glare(grey: np.ndarray, mask: np.ndarray, contour: np.ndarray, x0: int, y0: int,
                 bw: int, bh: int, params: SpotParams):
    """A region too large for one light (a glare halo): keep its core.

    Re-thresholds the region at 75 % of the way from its ring mean to its peak and
    keeps the single core region, if it is small enough (``max_area_px``, or a light's
    own ``max_light_px``); ``None`` otherwise.
    """
    H, W = grey.shape
    xa, ya = max(0, x0 - 2), max(0, y0 - 2)
    xb, yb = min(W, x0 + bw + 2), min(H, y0 + bh + 2)
    roi = grey[ya:yb, xa:xb]
    cand = mask[ya:yb, xa:xb]
    inside = np.zeros_like(cand)
    cv2.drawContours(inside, [contour], -1, 255, -1, offset=(-xa, -ya))
    inside = (inside > 0) & (cand > 0)
    ring = cand == 0
    if not np.any(ring) or not np.any(inside):
        return None
    i_b = float(roi[ring].mean())
    peak = float(roi[inside].max())
    level = i_b + 0.75 * (peak - i_b)
    core = np.where((roi > level) & inside, 255, 0).astype(np.uint8)
    cs, _ = cv2.findContours(core, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if len(cs) != 1:
        return None
    cx, cy, cw, ch = cv2.boundingRect(cs[0])
    # stats around the core, inside the halo: I_b is the halo level around the core
    u, v, i_o, i_b2, cov, area = _region_stats(roi, core, cs[0], cx, cy, cw, ch, True)
    if not (params.min_area_px <= area <= max(params.max_area_px, params.max_light_px)):
        return None
    return [u + xa, v + ya, i_o, min(i_b2, i_b + 0.5 * (peak - i_b)), cov[0, 0], cov[0, 1],
            cov[1, 1], float(area)]


def detect_spots(image: np.ndarray, params: SpotParams | None = None,
                 valid: np.ndarray | None = None,
                 centre_px: tuple[float, float] | None = None,
                 max_regions: int | None = None) -> Spots:
    """Bright spots of a frame: Niblack, identification, weighted centroids.

    Args:
        image: ``(H, W)`` grey or ``(H, W, 3)`` BGR frame, 8 or 16 bit.
        params: thresholds (:class:`SpotParams` defaults if ``None``).
        valid: optional ``(H, W)`` uint8 mask (non-zero: usable pixels, e.g. the part of a
            wide-angle image that sees the ceiling); candidates elsewhere are ignored.
        centre_px, max_regions: examine regions nearest ``centre_px`` first, at most
            ``max_regions`` of them (see :func:`regions_to_spots`).

    Returns:
        :class:`Spots`, possibly empty (a blank frame is not an error).
    """
    params = params or SpotParams()
    grey = to_grey(np.asarray(image))
    if grey.ndim != 2 or grey.size == 0:
        return empty_spots()
    mask = niblack_mask(grey, params.window_px, params.k, params.min_contrast,
                        params.min_contrast_rel)
    mask = lamp_mask(grey, mask, params)
    if valid is not None and valid.shape == mask.shape:
        mask = cv2.bitwise_and(mask, valid, dst=mask)
    return regions_to_spots(grey, mask, params, centre_px=centre_px, max_regions=max_regions)


@warmer
def _warm() -> None:
    g = np.full((12, 12), 40, np.uint8)
    g[4:8, 4:8] = 200
    m = np.where(g > 100, 255, 0).astype(np.uint8)
    for weighted in (True, False):
        for centre in (None, (6.0, 6.0)):
            regions_to_spots(g, m, SpotParams(), weighted, centre_px=centre, max_regions=4)
    niblack_mask(g)
    _examination_order(np.ones((2, 4)), (1.0, 1.0))


__all__ = ["SpotParams", "Spots", "detect_spots", "empty_spots", "lamp_mask", "niblack_mask",
           "perception_level", "regions_to_spots", "rows_to_spots", "tile_niblack_mask"]
