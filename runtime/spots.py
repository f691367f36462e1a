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
   region's box grown by two pixels, other regions' pixels excluded.

Example::

    spots = detect_spots(grey)                 # SpotParams() defaults
    spots.centroids_px                         # (N, 2) float64, distorted pixels
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .sources import to_grey

_REDUCE = 4  # the Niblack statistics are computed on a 1/_REDUCE image
_CORE = 0.4  # centroid weights count from I_b + _CORE (I_o - I_b)


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
    ``I > mean + max(k std, min_contrast, min_contrast_rel mean)``.

    Local statistics over a ``window_px`` square, from box filters on a 4x reduced
    (bilinearly sampled) image; the threshold is bilinearly enlarged back to full size.
    """
    h, w = grey.shape
    sw, sh = max(1, w // _REDUCE), max(1, h // _REDUCE)
    small = cv2.resize(grey, (sw, sh), interpolation=cv2.INTER_LINEAR)
    win = max(3, int(round(window_px / _REDUCE)) | 1)
    mean = cv2.boxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    std = cv2.sqrt(cv2.max(sq - mean * mean, 0.0))
    floor = cv2.max(mean * np.float32(min_contrast_rel), float(min_contrast))
    thr = mean + cv2.max(std * np.float32(k), floor)
    # whole grey levels suffice: threshold, enlarge and compare in 8 bit
    thr8 = np.clip(np.floor(thr), 0, 255).astype(np.uint8)
    thr8 = cv2.resize(thr8, (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.compare(grey, thr8, cv2.CMP_GT)


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
        wts = cv2.max(cv2.subtract(roi[cy0:cy1, cx0:cx1], base, dtype=cv2.CV_32F), 0.0)
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


def _alone(boxes: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: no other box reaches box ``i`` grown as in :func:`_region_stats`."""
    n = boxes.shape[0]
    if n < 2:
        return np.ones(n, bool)
    x0, y0, bw, bh = boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3]
    gx, gy = np.maximum(2, bw // 2), np.maximum(2, bh // 2)
    ax0, ay0, ax1, ay1 = x0 - gx, y0 - gy, x0 + bw + gx, y0 + bh + gy
    hit = ((x0[None, :] < ax1[:, None]) & (x0[None, :] + bw[None, :] > ax0[:, None])
           & (y0[None, :] < ay1[:, None]) & (y0[None, :] + bh[None, :] > ay0[:, None]))
    np.fill_diagonal(hit, False)
    return ~hit.any(axis=1)


def axis_ratios(cov_px: np.ndarray) -> np.ndarray:
    """Minor/major axis ratio ``(N,)`` of second-moment matrices ``(N, 2, 2)``."""
    a, b, c = cov_px[:, 0, 0], cov_px[:, 0, 1], cov_px[:, 1, 1]
    disc = np.sqrt(np.maximum((a - c) ** 2 / 4 + b * b, 0.0))
    hi, lo = (a + c) / 2 + disc, (a + c) / 2 - disc
    return np.sqrt(np.clip(lo, 0.0, None) / np.maximum(hi, 1e-12))


def regions_to_spots(grey: np.ndarray, mask: np.ndarray, params: SpotParams,
                     weighted: bool = True, rethreshold: bool = True,
                     relative: bool = True, centre_px: tuple[float, float] | None = None,
                     max_regions: int | None = None) -> Spots:
    """Identify lights among the connected regions of ``mask`` (see the module doc).

    With ``centre_px``, regions are examined nearest that pixel first (the principal
    point: the sharpest, best-resolved lights), at most ``max_regions`` of them that
    pass the size checks.
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    n = len(contours) + 1
    rejected: dict[str, int] = {}

    def drop(reason: str) -> None:
        rejected[reason] = rejected.get(reason, 0) + 1

    boxes = [cv2.boundingRect(c) for c in contours]
    order = range(len(contours))
    b = np.array(boxes, np.int64).reshape(-1, 4)
    alone = _alone(b)
    if centre_px is not None and boxes:
        d2 = (b[:, 0] + b[:, 2] / 2 - centre_px[0]) ** 2 + (b[:, 1] + b[:, 3] / 2
                                                             - centre_px[1]) ** 2
        order = np.argsort(d2, kind="stable")
    rows = []
    for ci in order:
        if max_regions is not None and len(rows) >= max_regions:
            drop("beyond_max_regions")
            continue
        contour = contours[ci]
        x0, y0, bw, bh = boxes[ci]
        if bw * bh < params.min_area_px:
            drop("small")
            continue
        if bw * bh > 4 * params.max_area_px:
            area = params.max_area_px + 1
        else:
            u, v, i_o, i_b, cov, area = _region_stats(
                grey, mask, None if alone[ci] else contour, x0, y0, bw, bh, weighted)
        if area < params.min_area_px:
            drop("small")
            continue
        if area > params.max_area_px:
            sub = _split_glare(grey, mask, contour, x0, y0, bw, bh, params) if rethreshold \
                else None
            if sub is None:
                drop("large")
            else:
                rows.append(sub)
            continue
        rows.append((u, v, float(area), i_o, i_b, cov))
    if not rows:
        return empty_spots(n - 1, rejected)
    c = np.array([[r[0], r[1]] for r in rows])
    area = np.array([r[2] for r in rows])
    i_o = np.array([r[3] for r in rows])
    i_b = np.array([r[4] for r in rows])
    cov = np.array([r[5] for r in rows]).reshape(-1, 2, 2)
    contrast = i_o - i_b
    level = perception_level(i_o, i_b, area)
    keep = level >= params.min_level
    rejected["level"] = rejected.get("level", 0) + int(np.sum(~keep))
    if params.min_axis_ratio > 0:
        ratio = axis_ratios(cov)
        bad = keep & (ratio < params.min_axis_ratio)
        rejected["shape"] = int(np.sum(bad))
        keep &= ~bad
    if relative and params.min_relative_contrast > 0 and np.any(keep):
        bad = keep & (contrast < params.min_relative_contrast * contrast[keep].max())
        rejected["dim"] = int(np.sum(bad))
        keep &= ~bad
    spots = Spots(c, area, contrast, level, cov, n - 1, rejected).select(keep)
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
    keeps the single core region, if it is small enough; ``None`` otherwise.
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
    if not (params.min_area_px <= area <= params.max_area_px):
        return None
    return (u + xa, v + ya, float(area), i_o, min(i_b2, i_b + 0.5 * (peak - i_b)), cov)


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
    if valid is not None and valid.shape == mask.shape:
        mask = cv2.bitwise_and(mask, valid)
    return regions_to_spots(grey, mask, params, centre_px=centre_px, max_regions=max_regions)


__all__ = ["SpotParams", "Spots", "detect_spots", "empty_spots", "niblack_mask",
           "perception_level", "regions_to_spots", "tile_niblack_mask"]
