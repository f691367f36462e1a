"""The array reading of the spot detector's region walk, kept as the oracle of its
compiled calls (:func:`ceilkit.runtime.features.spots._classify`, ``_walk``): the
regions' boxes ordered, the lone ones measured together, the rest one by one, each
dropped or kept in the order examined."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ceilkit.runtime.features.spots import (
    _BATCH_MAX_SIDE,
    SpotParams,
    _lone_region_stats,
    _region_stats,
    _split_glare,
)


def boxes_alone(boxes: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: no other box reaches box ``i`` grown as in :func:`_region_stats`."""
    n = boxes.shape[0]
    if n < 2:
        return np.ones(n, bool)
    x0, y0 = boxes[:, 0], boxes[:, 1]
    x1, y1 = x0 + boxes[:, 2], y0 + boxes[:, 3]
    gx, gy = np.maximum(2, boxes[:, 2] // 2), np.maximum(2, boxes[:, 3] // 2)
    # hit[i, j]: box j meets box i grown; every box meets itself
    hit = ((x0 < (x1 + gx)[:, None]) & (x1 > (x0 - gx)[:, None])
           & (y0 < (y1 + gy)[:, None]) & (y1 > (y0 - gy)[:, None]))
    return hit.sum(axis=1) == 1



def examination_order(boxes: np.ndarray, centre_px: tuple[float, float] | None) -> np.ndarray:
    """Indices of the regions' bounding boxes ``(N, 4)``, nearest ``centre_px`` first."""
    if centre_px is None or not boxes.shape[0]:
        return np.arange(boxes.shape[0])
    du = boxes[:, 0] + boxes[:, 2] / 2 - centre_px[0]          # box centre - centre_px
    dv = boxes[:, 1] + boxes[:, 3] / 2 - centre_px[1]
    return (du ** 2 + dv ** 2).argsort(kind="stable")



def measure_regions(grey: np.ndarray, mask: np.ndarray, contours: Sequence[np.ndarray],
                     params: SpotParams, weighted: bool, rethreshold: bool,
                     centre_px: tuple[float, float] | None, max_regions: int | None,
                     rejected: dict[str, int], drop_cut: bool = True) -> list[list[float]]:
    """One row ``(u, v, i_obj, i_bg, c_uu, c_uv, c_vv, area)`` per region of a plausible
    size, in the order examined; the others are counted in ``rejected`` by reason."""

    def drop(reason: str) -> None:
        rejected[reason] = rejected.get(reason, 0) + 1

    b = np.array([cv2.boundingRect(c) for c in contours], np.int64).reshape(-1, 4)
    order = examination_order(b, centre_px)
    box_area = b[:, 2] * b[:, 3]
    alone = boxes_alone(b)
    H, W = grey.shape
    # a region reaching the frame's edge is a light cut by it: its centroid lies inside
    # the light's, by up to its radius (on a tilted rig a far light leaving the top of
    # the frame moved the pose by 2 cm)
    cut = drop_cut & ((b[:, 0] <= 0) | (b[:, 1] <= 0) | (b[:, 0] + b[:, 2] >= W)
                      | (b[:, 1] + b[:, 3] >= H))
    # lone regions of a plausible size are measured together, in the order examined
    # (a few more than can be examined: some are dropped); any other one by one
    grown = b[:, 2:] + 2 * np.maximum(2, b[:, 2:] // 2)
    batch = (alone & (box_area >= params.min_area_px) & (box_area <= 4 * params.max_area_px)
             & (grown[:, 0] <= min(W, _BATCH_MAX_SIDE)) & (grown[:, 1] <= min(H, _BATCH_MAX_SIDE))
             & ~cut)
    todo = order[batch[order]]
    if max_regions is not None:
        todo = todo[:max_regions + 2]
    row_of = [-1] * b.shape[0]
    table: list[list[float]] = []
    if todo.size:
        stats, good = _lone_region_stats(grey, mask, b[todo], weighted)
        for i, ci in enumerate(todo[good].tolist()):
            row_of[ci] = i
        table = stats[good].tolist()
    rects, lone, cut_l = b.tolist(), alone.tolist(), cut.tolist()
    rows: list[list[float]] = []
    for ci in order.tolist():
        if max_regions is not None and len(rows) >= max_regions:
            drop("beyond_max_regions")
            continue
        x0, y0, bw, bh = rects[ci]
        if bw * bh < params.min_area_px:
            drop("small")
            continue
        if cut_l[ci]:
            drop("cut")
            continue
        if bw * bh > 4 * params.max_area_px:
            area = params.max_area_px + 1
        elif row_of[ci] >= 0:
            row = table[row_of[ci]]
            area = row[7]
        else:
            u, v, i_o, i_b, cov, area = _region_stats(
                grey, mask, None if lone[ci] else contours[ci], x0, y0, bw, bh, weighted)
            row = [u, v, i_o, i_b, cov[0, 0], cov[0, 1], cov[1, 1], float(area)]
        if area < params.min_area_px:
            drop("small")
            continue
        if area > params.max_area_px:
            sub = _split_glare(grey, mask, contours[ci], x0, y0, bw, bh, params) \
                if rethreshold else None
            if sub is None:
                drop("large")
            else:
                rows.append(sub)
            continue
        rows.append(row)
    return rows

