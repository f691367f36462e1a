"""Spots measured in small square windows of a frame, all windows in one stack.

A window's own square (``2 half + 1`` px, centred in a stack of ``side x side``
blocks) holds one spot: the square's border gives the background ``I_b``, the pixels
above half way from it to the square's peak are the spot, ``I_o`` their mean, and the
centroid and second moments are weighted by ``max(I - I_b - CORE (I_o - I_b), 0)``,
the reading of the global detector (:func:`~.spots.detect_spots`; a large light's
window is first divided by its plateau's gain, :func:`~.spots.flattened`). No per-window
Python: every reduction is one array operation or one matrix product over the stack.

Convention (SPEC §1): pixels ``(u, v)``, origin at the centre of the top-left pixel.

Example::

    rows, ok, touches = window_stats(grey, corner, side)   # (K, 8), (K,), (K,)
    u, v = rows[:, 0], rows[:, 1]
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .spots import (
    FLAT_MIN_AREA_PX,
    SpotParams,
    Spots,
    _block_monomials,
    _examination_order,
    _select_lights,
    empty_spots,
    flattened,
    niblack_mask,
)
from .working import decimate

CORE = 0.4
"""Centroid weights count from ``I_b + CORE (I_o - I_b)`` (as the global detector)."""


@functools.lru_cache(maxsize=16)
def _counts(side: int) -> np.ndarray:
    """``(side², 2)`` float32 ``(1, on the border)`` of a ``side x side`` block: one
    product gives a block's sum and its border's sum."""
    b = np.zeros((side, side), np.float32)
    b[0, :] = b[-1, :] = b[:, 0] = b[:, -1] = 1.0
    out = np.stack([np.ones(side * side, np.float32), b.ravel()], axis=1)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=16)
def _coords(side: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` int16 ``(1, side²)`` block coordinates of a ``side x side`` block's
    pixels, row-major (read-only)."""
    y, x = np.divmod(np.arange(side * side, dtype=np.int16), np.int16(side))
    x, y = x[None, :], y[None, :]
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def window_stats(grey: np.ndarray, corner: np.ndarray, side: int,
                 rect: np.ndarray | None = None
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

    Returns:
        ``(rows (K, 8), ok (K,), contrast (K,))``: rows ``(u, v, I_o, I_b, c00, c01,
        c11, area)`` as :func:`~.spots.regions_to_spots` measures a region (centroid in
        frame pixels, second moments px², area in px); ``ok`` where the window holds
        a spot whose bright part does not reach the window's border (not cut off, not
        a neighbour's) and has positive weight; ``contrast`` the peak above ``I_b``.
    """
    grey = np.ascontiguousarray(grey)
    h, w = grey.shape
    # every side x side block of the frame as a read-only view; the wanted ones copied
    # out row by row in one indexing (no per-pixel index array)
    views = np.ndarray((h - side + 1, w - side + 1, side, side), np.uint8,
                       grey, 0, grey.strides * 2)
    g = views[corner[:, 1], corner[:, 0]].reshape(-1, side * side).astype(np.float32)
    cols = _counts(side)
    i_b = (g @ cols[:, 1]) * np.float32(1.0 / (4 * side - 4))
    if rect is None:
        inside = None
        peak = g.max(axis=1)
        obj = (g > (0.5 * (i_b + peak))[:, None]).astype(np.float32)
    else:
        x, y = _coords(side)
        r = rect.astype(np.int16)
        inside = ((x >= r[:, 0:1]) & (x <= r[:, 2:3]) & (y >= r[:, 1:2])
                  & (y <= r[:, 3:4]))
        peak = np.where(inside, g, np.float32(0.0)).max(axis=1)
        obj = ((g > (0.5 * (i_b + peak))[:, None]) & inside).astype(np.float32)
    n_obj = obj @ cols                           # (K, 2): bright pixels, on the border
    area = n_obj[:, 0]
    touches = n_obj[:, 1] > 0                    # the bright part reaches the border
    i_o = np.einsum("ij,ij->i", g, obj) / np.maximum(area, 1.0)
    # a large light's plateau divided by its own gain (vignetting), as the detector does
    for i in np.flatnonzero(area >= FLAT_MIN_AREA_PX).tolist():
        flat = flattened(g[i].reshape(side, side), obj[i].reshape(side, side),
                         float(i_o[i] - i_b[i]))
        if flat is not None:
            g[i] = flat.ravel()
    wts = np.subtract(g, (i_b + CORE * (i_o - i_b))[:, None], out=g)
    np.maximum(wts, 0.0, out=wts)
    if inside is not None:
        wts *= inside
    mom = (wts @ _block_monomials(side, side, side // 2, np.float32)  # (K, 6)
           ).astype(np.float64)
    m00 = mom[:, 0]
    ok = ~touches & (area > 0) & (m00 > 0)
    mom /= np.where(ok, m00, 1.0)[:, None]
    cx, cy = mom[:, 1], mom[:, 3]
    rows = np.empty((m00.size, 8))
    mid = side // 2
    rows[:, 0] = corner[:, 0] + mid + cx
    rows[:, 1] = corner[:, 1] + mid + cy
    rows[:, 2] = i_o
    rows[:, 3] = i_b
    rows[:, 4] = mom[:, 2] - cx * cx
    rows[:, 5] = mom[:, 5] - cx * cy
    rows[:, 6] = mom[:, 4] - cy * cy
    rows[:, 7] = area
    return rows, ok, (peak - i_b).astype(np.float64)


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


__all__ = ["CORE", "SMALL_HALF_PX", "detect_spots_windowed", "window_stats"]
