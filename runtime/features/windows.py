"""Spots measured in small square windows of a frame, all windows in one stack.

A window's own square (``2 half + 1`` px, centred in a stack of ``side x side``
blocks) holds one spot: the square's border gives the background ``I_b``, the pixels
above half way from it to the square's peak are the spot, ``I_o`` their mean, and the
centroid and second moments are weighted by ``max(I - I_b - CORE (I_o - I_b), 0)``,
the reading of the global detector (:func:`~.spots.detect_spots`). No per-window
Python: every reduction is one array operation or one matrix product over the stack.

Convention (SPEC §1): pixels ``(u, v)``, origin at the centre of the top-left pixel.

Example::

    rows, ok, touches = window_stats(grey, corner, side)   # (K, 8), (K,), (K,)
    u, v = rows[:, 0], rows[:, 1]
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.lib.stride_tricks import as_strided

CORE = 0.4
"""Centroid weights count from ``I_b + CORE (I_o - I_b)`` (as the global detector)."""


@functools.lru_cache(maxsize=16)
def _monomials(side: int) -> np.ndarray:
    """``(side², 6)`` float32 ``(1, x, x², y, y², x y)`` of a ``side x side`` block,
    row-major, ``x, y`` from the block's centre (small numbers: float32 keeps the
    moments to ~1e-6 px)."""
    y, x = np.divmod(np.arange(side * side, dtype=float), side)
    x -= side // 2
    y -= side // 2
    out = np.stack([np.ones_like(x), x, x * x, y, y * y, x * y], axis=1).astype(np.float32)
    out.setflags(write=False)
    return out


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
def _rings(side: int) -> np.ndarray:
    """``(side²,)`` int16: each pixel's Chebyshev distance from the block's centre."""
    y, x = np.divmod(np.arange(side * side), side)
    out = np.maximum(np.abs(x - side // 2), np.abs(y - side // 2)).astype(np.int16)
    out.setflags(write=False)
    return out


def window_stats(grey: np.ndarray, corner: np.ndarray, side: int,
                 half: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spot of every window.

    Args:
        grey: ``(H, W)`` uint8 frame.
        corner: ``(K, 2)`` int ``(x, y)`` top-left pixel of each ``side x side`` block
            (inside the frame).
        side: the blocks' side (odd).
        half: ``(K,)`` int, each window's own half side (``<= side // 2``; its square
            is centred in the block); ``None``: every window is its whole block.

    Returns:
        ``(rows (K, 8), ok (K,), contrast (K,))``: rows ``(u, v, I_o, I_b, c00, c01,
        c11, area)`` as :func:`~.spots.regions_to_spots` measures a region (centroid in
        frame pixels, second moments px², area in px); ``ok`` where the window holds
        a spot whose bright part does not reach the window's border (not cut off, not
        a neighbour's) and has positive weight; ``contrast`` the peak above ``I_b``.
    """
    h, w = grey.shape
    # every side x side block of the frame as a read-only view; the wanted ones copied
    # out row by row in one indexing (no per-pixel index array)
    views = as_strided(grey, (h - side + 1, w - side + 1, side, side), grey.strides * 2,
                       writeable=False)
    g = views[corner[:, 1], corner[:, 0]].reshape(-1, side * side).astype(np.float32)
    if half is None:
        cols = _counts(side)
        i_b = (g @ cols[:, 1]) * np.float32(1.0 / (4 * side - 4))
        peak = g.max(axis=1)
        obj = (g > (0.5 * (i_b + peak))[:, None]).astype(np.float32)
        n_obj = obj @ cols                       # (K, 2): bright pixels, on the border
        inside = None
    else:
        ring = _rings(side)[None, :]
        hh = half[:, None]
        inside = ring <= hh                                          # (K, side²)
        border = (ring == hh).astype(np.float32)
        i_b = np.einsum("ij,ij->i", g, border) / (8.0 * half).astype(np.float32)
        peak = np.where(inside, g, 0.0).max(axis=1)
        obj = ((g > (0.5 * (i_b + peak))[:, None]) & inside).astype(np.float32)
        n_obj = np.stack([obj.sum(axis=1), np.einsum("ij,ij->i", obj, border)], axis=1)
    area = n_obj[:, 0]
    touches = n_obj[:, 1] > 0                    # the bright part reaches the border
    i_o = np.einsum("ij,ij->i", g, obj) / np.maximum(area, 1.0)
    wts = np.subtract(g, (i_b + CORE * (i_o - i_b))[:, None], out=g)
    np.maximum(wts, 0.0, out=wts)
    if inside is not None:
        wts *= inside
    mom = (wts @ _monomials(side)).astype(np.float64)                     # (K, 6)
    m00 = mom[:, 0]
    ok = ~touches & (area > 0) & (m00 > 0)
    mom /= np.where(ok, m00, 1.0)[:, None]
    cx, cy = mom[:, 1], mom[:, 3]
    rows = np.empty((m00.size, 8))
    c = side // 2
    rows[:, 0] = corner[:, 0] + c + cx
    rows[:, 1] = corner[:, 1] + c + cy
    rows[:, 2] = i_o
    rows[:, 3] = i_b
    rows[:, 4] = mom[:, 2] - cx * cx
    rows[:, 5] = mom[:, 5] - cx * cy
    rows[:, 6] = mom[:, 4] - cy * cy
    rows[:, 7] = area
    return rows, ok, (peak - i_b).astype(np.float64)


__all__ = ["CORE", "window_stats"]
