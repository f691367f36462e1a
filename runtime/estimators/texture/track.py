"""The ``texture`` method's tracked fast path: the pose refined from a tight prior by
following the map's own features into the frame, no detection, no descriptor.

The map's mosaic is resampled as the prior says the frame should show it
(:func:`.ceilmap.predicted_patch`); the map features inside that predicted patch are
followed into the frame's rectified patch by pyramidal Lucas-Kanade
(``cv2.calcOpticalFlowPyrLK``, as the ceiling-plane odometry of
:mod:`~ceilkit.runtime.estimators.odometry` does between frames). A feature at
predicted patch pixel ``u`` found at ``u + d`` in the frame's patch gives the pair
``q_V = (u + d - c) res`` ~ ``p_W`` (the map's point: the predicted patch shows it at
``u`` by construction), and the pairs give the pose by the same least squares as the
global path (:func:`.match.refine`). Each frame is tied to the map, not to the
previous frame: no drift.

What the fast path cannot do is enumerate twins: it converges to the pose nearest the
prior. The estimator takes it only when the prior's region is too narrow to hold a
twin (``window_twin_m``, :func:`~ceilkit.runtime.estimators.prior.narrower_than`), and
publishes its pose only where the prior's region holds it.

Example::

    grid = FeatureGrid(cmap.points_xy)
    got = track_map(cmap, grid, patch, valid, prior_pose, 0.03, 0.002, 12)
    got.refined.pose if got is not None else None
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap, _eroded, predicted_patch
from ceilkit.runtime.estimators.texture.match import Refined, refine, residuals
from ceilkit.runtime.geometry.fits import fit_rigid_2d

MAX_POINTS = 64          # map features followed per frame, at most
CELLS = 4                # ... spread over CELLS x CELLS cells of the patch
LK_WIN = 11              # Lucas-Kanade window, patch pixels (odd)
LK_LEVELS = 1            # pyramid levels above the patch (basin about 2^L * LK_WIN / 2)
FB_MAX_PX = 0.3          # forward-backward disagreement of a kept track, patch pixels
LK = {"winSize": (LK_WIN, LK_WIN), "maxLevel": LK_LEVELS,
      "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.02)}


@dataclass(frozen=True, eq=False)
class Tracked:
    """The fast path's pose and the pairs it rests on.

    Attributes:
        refined: the least-squares pose on the pairs within the tolerance.
        followed: map features followed into the frame (LK converged).
        predicted: map features the prior put inside the patch.
    """

    refined: Refined
    followed: int
    predicted: int


class FeatureGrid:
    """The map's features bucketed in square cells of ``cell_m`` (sorted by cell, a row
    of cells contiguous): those near a point at the cost of the cells they fill, not of
    the map (a k-d tree's ball query built a Python list of every index)."""

    def __init__(self, points_xy: np.ndarray, cell_m: float = 1.0) -> None:
        self.cell_m = float(cell_m)
        ij = np.floor(np.asarray(points_xy, float) / self.cell_m).astype(np.int64)
        self.lo = ij.min(0) if len(ij) else np.zeros(2, np.int64)
        ij -= self.lo
        self.size = (ij.max(0) + 1) if len(ij) else np.ones(2, np.int64)
        key = ij[:, 1] * self.size[0] + ij[:, 0]
        self.order = np.argsort(key, kind="stable")
        self.starts = np.searchsorted(key[self.order], np.arange(self.size.prod() + 1))

    def within(self, x: float, y: float, half_m: float) -> np.ndarray:
        """Indices of the features in the cells that meet the square of half side
        ``half_m`` about ``(x, y)`` (a superset of the features inside it)."""
        c = self.cell_m
        i0, j0 = (max(int(math.floor((v - half_m) / c)) - o, 0)
                  for v, o in ((x, self.lo[0]), (y, self.lo[1])))
        i1, j1 = (min(int(math.floor((v + half_m) / c)) - o, int(n) - 1)
                  for v, o, n in ((x, self.lo[0], self.size[0]), (y, self.lo[1], self.size[1])))
        if i1 < i0 or j1 < j0:
            return np.zeros(0, np.int64)
        w = int(self.size[0])
        rows = [self.order[self.starts[j * w + i0]:self.starts[j * w + i1 + 1]]
                for j in range(j0, j1 + 1)]
        return np.concatenate(rows)


def visible_features(cmap: CeilingMap, grid: FeatureGrid, pose: tuple[float, float, float],
                     valid: np.ndarray, margin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """``(idx (M,), uv (M, 2) float32)``: map features the pose puts inside the patch
    (``valid``, at least ``margin_px`` from its edge), their predicted patch pixels
    ``(col, row)``; of more than :data:`MAX_POINTS`, the first few of each of
    :data:`CELLS` x CELLS cells (in the map's order): spread over the patch."""
    n = valid.shape[0]
    res = cmap.resolution_m
    x, y, yaw = pose
    idx = grid.within(x, y, math.sqrt(2.0) * n * res / 2)
    if len(idx) == 0:
        return idx, np.zeros((0, 2), np.float32)
    c, s = math.cos(yaw), math.sin(yaw)
    d = cmap.points_xy[idx] - (x, y)
    uv = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]) / res \
        + (n - 1) / 2
    inside = np.all((uv >= margin_px) & (uv <= n - 1 - margin_px), axis=1)
    idx, uv = idx[inside], uv[inside]
    ok = valid[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    idx, uv = idx[ok], uv[ok]
    if len(idx) > MAX_POINTS:
        cell = (uv[:, 1] * CELLS // n).astype(int) * CELLS + (uv[:, 0] * CELLS // n).astype(int)
        order = np.argsort(cell, kind="stable")
        first = np.searchsorted(cell[order], cell[order])
        rank = np.empty(len(idx), int)
        rank[order] = np.arange(len(idx)) - first
        keep = rank < max(1, MAX_POINTS // (CELLS * CELLS))
        idx, uv = idx[keep], uv[keep]
    return idx, uv.astype(np.float32)


def track_map(cmap: CeilingMap, grid: FeatureGrid, patch: np.ndarray, valid: np.ndarray,
              pose: tuple[float, float, float], tol_m: float, sigma_floor_m: float,
              min_points: int) -> Tracked | None:
    """The pose refined from ``pose`` (the prior) on the frame's rectified patch (see
    the module docstring), or None with fewer than ``min_points`` map features
    followed or fitting within ``tol_m``."""
    n = patch.shape[0]
    half = LK_WIN // 2 + 2
    inner = _eroded(np.ascontiguousarray(valid, np.uint8).tobytes(), valid.shape, half)
    idx, uv = visible_features(cmap, grid, pose, inner.astype(bool), half)
    if len(idx) < min_points:
        return None
    pred, _ = predicted_patch(cmap, pose, n, cover=False)
    start = uv.reshape(-1, 1, 2)
    found, st, _ = cv2.calcOpticalFlowPyrLK(pred, patch, start, None, **LK)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(patch, pred, found, None, **LK)
    fb = np.linalg.norm((back - start).reshape(-1, 2), axis=1)
    found = found.reshape(-1, 2)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < FB_MAX_PX)
    ok &= np.all((found >= 0) & (found <= n - 1), axis=1)
    if np.count_nonzero(ok) < min_points:
        return None
    res = cmap.resolution_m
    q = (found[ok].astype(float) - (n - 1) / 2) * res
    p = cmap.points_xy[idx[ok]]
    start = _robust_start(q, p, tol_m)
    if start is None:
        return None
    refined = refine(q, p, None, start, tol_m, sigma_floor_m, rounds=1)
    if refined is None or len(refined.used) < min_points:
        return None
    return Tracked(refined, int(np.count_nonzero(ok)), len(idx))


def _robust_start(q: np.ndarray, p: np.ndarray, tol_m: float
                  ) -> tuple[float, float, float] | None:
    """The rigid fit of all pairs, then of those within 3 MADs of its residuals (or
    ``tol_m``): where :func:`.match.refine` starts (the prior may be off by more than
    the tolerance; a few pairs LK followed to the wrong place are dropped)."""
    yaw, t = fit_rigid_2d(q, p)
    r = residuals((float(t[0]), float(t[1]), float(yaw)), q, p)
    med = float(np.median(r))
    keep = r <= max(med + 3.0 * 1.4826 * med, tol_m)
    if np.count_nonzero(keep) < 3:
        return None
    yaw, t = fit_rigid_2d(q[keep], p[keep])
    return float(t[0]), float(t[1]), float(yaw)


__all__ = ["FeatureGrid", "Tracked", "track_map", "visible_features"]
