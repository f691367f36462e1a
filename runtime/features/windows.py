"""Spots measured in small square windows of a frame, all windows in one stack.

A window's own square (``2 half + 1`` px, centred in a stack of ``side x side``
blocks) holds one spot: the square's border gives the background ``I_b``, the pixels
above half way from it to the square's peak are the spot, ``I_o`` their mean, and the
centroid and second moments are weighted by ``max(I - I_b - CORE (I_o - I_b), 0)``,
the reading of the global detector (:func:`~.spots.detect_spots`; a large light's
window is first divided by its plateau's gain, :func:`~.spots.flattened`). One compiled
loop (:mod:`ceilkit.runtime.jit`) reads every window: its levels, then its moments.

Convention (SPEC §1): pixels ``(u, v)``, origin at the centre of the top-left pixel.

Example::

    rows, ok, touches = window_stats(grey, corner, side)   # (K, 8), (K,), (K,)
    u, v = rows[:, 0], rows[:, 1]
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ceilkit.runtime.jit import arr, njit, warmer

from .spots import (
    FLAT,
    SpotParams,
    Spots,
    _examination_order,
    _plateau,
    _select_lights,
    empty_spots,
    niblack_mask,
)
from .working import decimate

CORE = 0.4
"""Centroid weights count from ``I_b + CORE (I_o - I_b)`` (as the global detector)."""


def window_stats(grey: np.ndarray, corner: np.ndarray, side: int,
                 rect: np.ndarray | None = None, core: float = CORE
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spot of every window.

    Args:
        grey: ``(H, W)`` uint8 frame.
        corner: ``(K, 2)`` int ``(x, y)`` top-left pixel of each ``side x side`` window
            (inside the frame).
        side: the windows' side (odd).
        rect: ``(K, 4)`` int ``(x0, y0, x1, y1)`` (inclusive, window coordinates):
            the spot's pixels are looked for there only (its region's box; the rest of
            the window is background and neighbours); ``None``: the whole window.
        core: the centroid weights count from ``I_b + core (I_o - I_b)``.

    Returns:
        ``(rows (K, 8), ok (K,), contrast (K,))``: rows ``(u, v, I_o, I_b, c00, c01,
        c11, area)`` as :func:`~.spots.regions_to_spots` measures a region (centroid in
        frame pixels, second moments px², area in px); ``ok`` where the window holds
        a spot whose bright part does not reach the window's border (not cut off, not
        a neighbour's) and has positive weight; ``contrast`` the peak above ``I_b``.

    One compiled loop over the windows (:func:`read_windows_core`).
    """
    grey = arr(grey, np.uint8)
    corner = arr(corner, np.int64).reshape(-1, 2)
    k = corner.shape[0]
    r = (arr(rect, np.int64).reshape(-1, 4) if rect is not None
         else np.tile(np.array([0, 0, side - 1, side - 1], np.int64), (k, 1)))
    out = read_windows_core(grey, corner, side, r, float(core), FLAT)
    i_b, peak, area, i_o = out[:, 0], out[:, 1], out[:, 2], out[:, 4]
    touches = out[:, 3] > 0
    mom = out[:, 5:]                              # m00 m10 m20 m01 m02 m11
    m00 = mom[:, 0]
    ok = ~touches & (area > 0) & (m00 > 0)
    mom /= np.where(ok, m00, 1.0)[:, None]
    cx, cy = mom[:, 1], mom[:, 3]
    rows = np.empty((k, 8))
    mid = side // 2
    rows[:, 0] = corner[:, 0] + mid + cx
    rows[:, 1] = corner[:, 1] + mid + cy
    rows[:, 2] = i_o
    rows[:, 3] = i_b
    rows[:, 4] = mom[:, 2] - cx * cx
    rows[:, 5] = mom[:, 5] - cx * cy
    rows[:, 6] = mom[:, 4] - cy * cy
    rows[:, 7] = area
    return rows, ok, peak - i_b


@njit
def read_windows_core(grey, corner, side, rect, core, flat):  # pragma: no cover - compiled
    """Per window ``(I_b, peak, area, on_border, I_o, m00, m10, m20, m01, m02, m11)``
    (K, 11) float64: the border's mean; the peak inside ``rect`` (0 when it holds no
    pixel); the pixels inside above half way from ``I_b`` to the peak (their count,
    whether one lies on the window's border, their mean); the raw moments, ``(x, y)``
    from the window's centre, of ``max(I - I_b - core (I_o - I_b), 0)`` inside
    ``rect``, where ``I`` is the window divided by its plateau's gain when the spot
    has ``flat.min_area_px`` pixels or more and the plane explains the plateau
    (``flat``: a :class:`~.spots.Flattening`; :func:`_plateau`, the reading of
    :func:`~.spots.flattened`)."""
    k = corner.shape[0]
    out = np.zeros((k, 11))
    last = side - 1
    obj = np.zeros((side, side), np.uint8)
    tmp = np.zeros((side, side), np.uint8)
    row_peak = np.zeros(side, np.uint8)
    for n in range(k):
        x0, y0 = corner[n, 0], corner[n, 1]
        win = grey[y0:y0 + side, x0:x0 + side]
        box = (max(rect[n, 0], 0), max(rect[n, 1], 0), min(rect[n, 2], last),
               min(rect[n, 3], last))
        i_b, peak, area, edge, i_o, above = _levels(win, box, row_peak)
        base = i_b + core * (i_o - i_b)
        plane = (False, 1.0, 0.0, 0.0, 0.0, 0.0)
        if area >= flat.min_area_px:
            _mark(win, box, above, obj)
            plane = _plateau(win, obj, tmp, i_o - i_b, flat.erode_px, flat.min_px,
                             flat.max_residual)
        out[n, 0] = i_b
        out[n, 1] = peak
        out[n, 2] = area
        out[n, 3] = edge
        out[n, 4] = i_o
        if plane[0]:
            _weighted_moments(win, box, base, plane, flat.min_gain, out[n, 5:])
        else:
            _plain_moments(win, box, base, row_peak, out[n, 5:])
    return out


@njit
def _levels(win, box, row_peak):  # pragma: no cover - compiled
    """``(I_b, peak, area, on_border, I_o, above)`` of one window
    (:func:`read_windows_core`): the spot's pixels are those of ``box`` at or above the
    integer ``above`` (a grey level is above the half-peak level ``L`` exactly when it
    is at least ``floor(L) + 1``), counted in integers. ``row_peak`` gets each box
    row's peak: the rows below a level are skipped."""
    side = win.shape[0]
    last = side - 1
    rx0, ry0, rx1, ry1 = box
    s = 0
    for j in range(side):
        s += np.int64(win[0, j]) + np.int64(win[last, j])
    for i in range(1, last):
        s += np.int64(win[i, 0]) + np.int64(win[i, last])
    i_b = s / (4 * side - 4)
    peak = 0
    for i in range(ry0, ry1 + 1):
        p = np.uint8(0)
        for j in range(rx0, rx1 + 1):
            p = max(p, win[i, j])
        row_peak[i] = p
        peak = max(peak, np.int64(p))
    above = np.int64(math.floor(0.5 * (i_b + peak))) + 1
    area = 0
    total = 0
    for i in range(ry0, ry1 + 1):
        if row_peak[i] < above:
            continue
        row_n = 0
        row_total = 0
        for j in range(rx0, rx1 + 1):
            v = np.int64(win[i, j])
            hit = v >= above
            row_n += hit
            row_total += v if hit else 0
        area += row_n
        total += row_total
    edge = 0
    if area:             # a spot pixel on the window's border (inside the box)
        for i in (0, last):
            if ry0 <= i <= ry1:
                for j in range(rx0, rx1 + 1):
                    if win[i, j] >= above:
                        edge = 1
        for j in (0, last):
            if rx0 <= j <= rx1:
                for i in range(ry0, ry1 + 1):
                    if win[i, j] >= above:
                        edge = 1
    return i_b, float(peak), float(area), float(edge), total / max(area, 1), above


@njit
def _mark(win, box, above, obj):  # pragma: no cover - compiled
    """``obj`` (the window's shape) set to the spot's pixels (1), 0 elsewhere."""
    rx0, ry0, rx1, ry1 = box
    obj[:, :] = 0
    for i in range(ry0, ry1 + 1):
        for j in range(rx0, rx1 + 1):
            obj[i, j] = win[i, j] >= above


@njit
def _plain_moments(win, box, base, row_peak, out):  # pragma: no cover - compiled
    """:func:`_weighted_moments` without a plateau: the pixels above ``base`` (the
    integers from ``floor(base) + 1``; rows whose peak ``row_peak`` is below, none)
    summed in integers per row (exact), the weights' ``- base`` applied to each row's
    sums."""
    mid = win.shape[0] // 2
    rx0, ry0, rx1, ry1 = box
    above = np.int64(math.floor(base)) + 1
    out[:] = 0.0
    for i in range(ry0, ry1 + 1):
        if row_peak[i] < above:
            continue
        n = sv = svx = svxx = sx = sxx = 0
        for j in range(rx0, rx1 + 1):
            v = np.int64(win[i, j])
            if v >= above:
                x = j - mid
                n += 1
                sv += v
                svx += v * x
                svxx += v * x * x
                sx += x
                sxx += x * x
        _add_row(out, sv - base * n, svx - base * sx, svxx - base * sxx, i - mid)


@njit
def _weighted_moments(win, box, base, plane, min_gain, out):  # pragma: no cover - compiled
    """Into ``out (6,)``: ``m00, m10, m20, m01, m02, m11`` of ``max(I - base, 0)`` over
    ``box``, ``(x, y)`` from the window's centre, ``I`` divided by the gain ``plane``
    (:func:`_plateau`)."""
    flat, a, b, c, xc, yc = plane
    mid = win.shape[0] // 2
    rx0, ry0, rx1, ry1 = box
    ba, ca = b / a, c / a                          # the gain's slopes
    out[:] = 0.0
    for i in range(ry0, ry1 + 1):
        r0 = r1 = r2 = 0.0
        gy = 1.0 + ca * (i - yc)
        for j in range(rx0, rx1 + 1):
            v = win[i, j] / max(gy + ba * (j - xc), min_gain) - base
            if v > 0.0:
                x = j - mid
                r0 += v
                r1 += v * x
                r2 += v * x * x
        _add_row(out, r0, r1, r2, i - mid)


@njit
def _add_row(m, r0, r1, r2, y):  # pragma: no cover - compiled
    """A row's sums ``r0, r1, r2`` (``w``, ``w x``, ``w x²``) at ``y`` into the moments
    ``m (6,)``: ``m00, m10, m20, m01, m02, m11``."""
    m[0] += r0
    m[1] += r1
    m[2] += r2
    m[3] += r0 * y
    m[4] += r0 * y * y
    m[5] += r1 * y


SMALL_HALF_PX = 10
"""Windows up to this half side are measured in one stack, the larger ones in another."""


def _read_boxes(grey: np.ndarray, box: np.ndarray, centre: np.ndarray, half: np.ndarray,
                min_contrast: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`window_stats` rows ``(K, 8)`` and ``ok (K,)`` of regions' boxes ``(K, 4)``
    ``(x, y, w, h)`` (full-frame px): windows of half side ``half (K,)`` centred on
    ``centre (K, 2)`` (shifted into the frame at its border), in two stacks (the small
    ones, the large ones); the spot's pixels within its box grown by 2 px (the
    detector's centroid window), the window's border beyond it the background."""
    H, W = grey.shape
    rows = np.empty((box.shape[0], 8))
    ok = np.zeros(box.shape[0], bool)
    big = half > SMALL_HALF_PX
    for sel in (~big, big):
        if not sel.any():
            continue
        hs = int(half[sel].max())
        side = 2 * hs + 1
        if side >= min(H, W):
            continue
        corner = centre[sel] - hs
        np.maximum(corner, 0, out=corner)
        np.minimum(corner, (W - side, H - side), out=corner)
        b = box[sel]
        rect = np.concatenate([b[:, :2] - 2, b[:, :2] + b[:, 2:] + 1], 1) - np.tile(corner, 2)
        r, good, contrast = window_stats(grey, corner, side, rect)
        rows[sel] = r
        ok[sel] = good & (contrast >= min_contrast)
    return rows, ok


def detect_spots_windowed(grey: np.ndarray, params: SpotParams | None = None,
                          valid_small: np.ndarray | None = None,
                          centre_px: tuple[float, float] | None = None,
                          max_regions: int | None = None, factor: int = 2,
                          margin_px: int = 3, max_half_px: int = 40) -> Spots:
    """Spots found on the frame decimated by ``factor`` and measured at full resolution
    in windows around them: :func:`~.spots.detect_spots`'s result from a quarter of its
    pixel work.

    The Niblack mask (:func:`~.spots.niblack_mask`, its window scaled by ``1/factor``)
    and the connected regions are found on the decimated frame; each region's box,
    mapped back and grown by ``margin_px``, is a window of the full frame whose spot is
    read as :func:`window_stats` reads it (border background, half-peak object, the
    detector's weighted centroid), and the same identification follows (area bounds,
    perception index, shape, relative contrast: ``_select_lights``).

    Args:
        grey: ``(H, W)`` uint8 frame.
        params: thresholds in pixels of the full frame (:class:`SpotParams`).
        valid_small: the valid mask decimated (:func:`~.working.decimated_mask`), or None.
        centre_px, max_regions: regions are examined nearest ``centre_px`` (full-frame
            pixels) first, at most ``max_regions`` of a plausible box size.
        factor: the decimation (2: a 640x480 frame searched at 320x240).
        margin_px, max_half_px: a window's half side is the box's half plus this
            margin; a region needing more than ``max_half_px`` is dropped as ``large``.

    Returns:
        :class:`Spots` in the examination order (nearest ``centre_px`` first).
    """
    params = params or SpotParams()
    f = int(factor)
    small = decimate(grey, f)
    win = max(3, int(round(params.window_px / f)) | 1)
    mask = niblack_mask(small, win, params.k, params.min_contrast, params.min_contrast_rel)
    if valid_small is not None and valid_small.shape == mask.shape:
        mask = cv2.bitwise_and(mask, valid_small, dst=mask)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    n = len(contours)
    if n == 0:
        return empty_spots()
    b = np.array([cv2.boundingRect(c) for c in contours], np.int64).reshape(-1, 4)
    # each box's centre and half extent in full-frame pixels
    centre = f * (b[:, :2] + 0.5 * (b[:, 2:] - 1)) + 0.5 * (f - 1)
    box_area = b[:, 2] * b[:, 3] * (f * f)
    half = np.ceil(0.5 * f * b[:, 2:].max(axis=1) + margin_px).astype(np.int64)
    rejected: dict[str, int] = {}
    small_box = box_area < params.min_area_px
    large_box = (box_area > 4 * params.max_area_px) | (half > max_half_px)
    order = _examination_order(np.column_stack([centre - 0.5, np.ones((n, 2))]), centre_px)
    todo = order[~(small_box | large_box)[order]]
    rejected["small"] = int(small_box.sum())
    rejected["large"] = int(large_box.sum())
    if max_regions is not None and todo.size > max_regions:
        rejected["beyond_max_regions"] = int(todo.size - max_regions)
        todo = todo[:max_regions]
    if todo.size == 0:
        return empty_spots(n, rejected)
    rows, ok = _read_boxes(grey, f * b[todo], np.rint(centre[todo]).astype(np.int64),
                           half[todo], params.min_contrast)
    area = rows[:, 7]
    small_spot = ok & (area < params.min_area_px)
    large_spot = ok & (area > params.max_area_px)
    rejected["small"] += int(small_spot.sum())
    rejected["large"] += int(large_spot.sum())
    rejected["window"] = int(todo.size - ok.sum())
    ok &= ~(small_spot | large_spot)
    if not ok.any():
        return empty_spots(n, rejected)
    return _select_lights(rows[ok], n, params, True, rejected)


@warmer
def _warm() -> None:
    g = np.zeros((9, 9), np.uint8)
    g[4, 4] = 200
    window_stats(g, np.zeros((1, 2), np.int64), 9)
    window_stats(g, np.zeros((1, 2), np.int64), 9, np.array([[1, 1, 7, 7]]))


__all__ = ["CORE", "SMALL_HALF_PX", "detect_spots_windowed", "window_stats"]
