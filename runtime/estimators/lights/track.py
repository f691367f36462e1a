"""The tracked fast path of ``lights``: look for each light only where the prior says.

With a prior pose (the tracker's or the fusion's prediction), the map lights the
detector should report from it (:class:`~.observe.VisibilityTable`) are placed in
the image by one lookup (:func:`prediction_cells`, no projection per frame), and each
is looked for in a small square window around its predicted pixel (a few hundred
pixels, all windows in one stack: :func:`~ceilkit.runtime.features.windows.window_stats`):
the window's border gives the
background ``I_b``, the pixels above half way from it to the window's peak are the
light, ``I_o`` their mean, and the centroid is weighted by ``max(I - I_b - 0.4 (I_o -
I_b), 0)``, the same reading as the global detector's
(:func:`~ceilkit.runtime.features.spots.detect_spots`). The association is known (a
window is its light's), so the pose is :func:`~.refine.refine_pose_ceiling` from the
prior, with the same outlier pass as the global path.

The window check: a light counts when its window has contrast, its bright part does
not touch the window's border (not cut off, not a neighbour's), and its area and
shape fit the light at that place (:meth:`~.observe.SpotObserver.plausible`); the
frame is accepted when most predicted lights were found (the same share the global
path asks of a trusted prior), at least three fit after refinement, their residual is
small and the pose stayed within the prior gate. Anything else returns ``None`` and
the estimator runs its global path (the fallback and the check); so does every
``full_every``-th tracked frame (a schedule).

Convention (SPEC §1): pixels distorted; ceiling points in V, metres.

Example::

    fast = WindowTracker(rig, H, lights_w, observer, visibility, window_px=10)
    found = fast.observe(grey, prior_x, prior_y, prior_yaw)   # WindowFix | None
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.lights.observe import JAC_STEP_PX, SpotObserver, VisibilityTable
from ceilkit.runtime.estimators.lights.rays import (
    ceiling_points,
    interp_grid,
    pixel_scale,
    project_lights,
)
from ceilkit.runtime.estimators.lights.refine import refine_pose_ceiling
from ceilkit.runtime.features.spots import Spots, rows_to_spots
from ceilkit.runtime.features.windows import CORE, window_stats
from ceilkit.runtime.geometry.fits import short_median

MAX_HALF_PX = 40
"""A window is at most ``2 MAX_HALF_PX + 1`` pixels wide (large spots near the nadir)."""


def prediction_cells(rig: Rig, ceiling_height_m: float, visibility: VisibilityTable,
                     spot_table: np.ndarray) -> np.ndarray:
    """``(cells, 9)`` per cell of the visibility table (padded, in the order of
    :meth:`~.observe.VisibilityTable.locate`): the cell centre in V ``(qx, qy)``, its
    pixel ``(u, v)``, the pixel Jacobian there ``d(u, v)/d(qx, qy)`` (row-major) and the
    predicted spot area (px², from the spot table); NaN where the cell is not seen.

    A light's pixel is the centre's plus the Jacobian times the light's offset from the
    centre (at most half a cell): off by the map's curvature over half a cell, a few
    hundredths of a pixel for the fisheye of configs/lights (10 cm cells), against a
    window margin of ``window_px``. Built once per rig and site."""
    q = visibility.cell_centres()
    out = np.full((q.shape[0], 9), np.nan)
    out[:, :2] = q
    seen = np.isfinite(np.pad(visibility.table, 1, constant_values=np.inf).ravel())
    if np.any(seen):
        px = project_lights(rig, ceiling_height_m, q[seen], 0.0, 0.0, 0.0)
        out[seen, 2:4] = px
        out[seen, 4:8] = pixel_scale(rig, ceiling_height_m, q[seen]).reshape(-1, 4)
        out[seen, 8] = interp_grid(spot_table[..., 7], JAC_STEP_PX, px)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class WindowFix:
    """What the windows found and the pose they give.

    Attributes:
        x_m, y_m, yaw_rad, cov, res_px: the refined pose, its covariance and the kept
            lights' residuals (px), as :func:`~.refine.refine_pose_ceiling`.
        spots: the found lights (the kept ones), as the global detector's :class:`Spots`.
        pairs: ``(K, 2)`` (index in ``spots``, map light index).
        predicted: how many lights the prior says the detector should report.
        found: how many windows held a plausible light.
        predicted_px: ``(M, 2)`` the predicted pixels (for overlays).
    """

    x_m: float
    y_m: float
    yaw_rad: float
    cov: np.ndarray
    res_px: np.ndarray
    spots: Spots
    pairs: np.ndarray
    predicted: int
    found: int
    predicted_px: np.ndarray


class WindowTracker:
    """Spots looked for in windows around the lights a prior predicts (module doc).

    Args:
        rig, ceiling_height_m, lights_w: as the estimator's.
        observer: the estimator's :class:`SpotObserver` (its spot table and checks).
        visibility: the estimator's :class:`VisibilityTable`.
        window_px: how far (px) a light may be from its predicted place (the prior's
            error in pixels), beyond the light's own predicted radius.
        min_contrast: least ``peak - I_b`` of a window with a light (grey levels).
        min_share: found / predicted share the frame needs.
        max_residual_px, outlier_medians: the outlier pass (as the global path's).
        gate_m, gate_rad: the refined pose must stay this near the prior.
    """

    def __init__(self, rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                 observer: SpotObserver, visibility: VisibilityTable, window_px: float,
                 min_contrast: float, min_share: float, max_residual_px: float,
                 outlier_medians: float, gate_m: float, gate_rad: float) -> None:
        self.rig, self.ceiling_height_m = rig, ceiling_height_m
        self.lights_w = np.asarray(lights_w, float)
        self.observer, self.visibility = observer, visibility
        self._cells = prediction_cells(rig, ceiling_height_m, visibility, observer.table)
        self.window_px = float(window_px)
        self.min_contrast = float(min_contrast)
        self.min_share = float(min_share)
        self.max_residual_px, self.outlier_medians = max_residual_px, outlier_medians
        self.gate_m, self.gate_rad = gate_m, gate_rad
        cam = rig.camera
        self.width, self.height = cam.width, cam.height

    def observe(self, grey: np.ndarray, x_m: float, y_m: float, yaw_rad: float
                ) -> WindowFix | None:
        """The pose from the windows around the lights predicted from ``(x, y, yaw)``
        on a ``(H, W)`` uint8 frame, or ``None`` when the window check fails."""
        pred = self._predict(x_m, y_m, yaw_rad)
        if pred is None:
            return None
        idx, px, m, corner, half = pred
        spots, good, tab = self._measure(grey, corner, half, m)
        n_found = int(np.count_nonzero(good))
        if n_found < max(3, math.ceil(self.min_share * m)):
            return None
        fit = self._fit(spots.select(good), idx[good], tab[good], x_m, y_m, yaw_rad)
        if fit is None:
            return None
        x, y, yaw, cov_p, res, spots, pairs = fit
        return WindowFix(x, y, yaw, cov_p, res, spots, pairs, m, n_found, px)

    def _predict(self, x_m: float, y_m: float, yaw_rad: float):
        """``(map indices, predicted px, predicted count, window corners, half side)``
        of the finite predictions, or ``None`` (fewer than 3, or windows too big).

        One lookup: the visibility table's cell of every map light, and the pixel
        there from :func:`prediction_cells` (the cell centre's pixel plus its
        Jacobian times the light's offset from the centre); no projection."""
        ok, cell, z = self.visibility.locate(x_m, y_m, yaw_rad)
        idx = np.flatnonzero(ok)
        m = idx.size
        if m < 3:
            return None
        c = self._cells[cell[idx]]                                          # (M, 9)
        z = z[idx]
        dq = np.stack([z.real, z.imag], axis=1) - c[:, :2]                 # (M, 2) m
        px = c[:, 2:4] + (c[:, 4:8].reshape(-1, 2, 2) @ dq[:, :, None])[:, :, 0]
        area = c[:, 8]
        fin = np.isfinite(px[:, 0]) & np.isfinite(area)
        n_fin = int(np.count_nonzero(fin))
        if n_fin < 3:
            return None
        r_spot = math.sqrt(max(float(area[fin].max()), 1.0) / math.pi)
        half = int(min(MAX_HALF_PX, math.ceil(r_spot * 1.6 + self.window_px)))
        side = 2 * half + 1
        w, h = self.width, self.height
        if side >= min(w, h):
            return None
        if n_fin < m:
            idx, px = idx[fin], px[fin]
        # window corners, kept inside the image (a window at the border is shifted in)
        corner = np.rint(px).astype(np.int64) - half
        np.maximum(corner, 0, out=corner)
        np.minimum(corner, (w - side, h - side), out=corner)
        return idx, px, m, corner, half

    def _measure(self, grey: np.ndarray, corner: np.ndarray, half: int, m: int
                 ) -> tuple[Spots, np.ndarray, np.ndarray]:
        """The windows' spots (centroids in the frame), which pass the window check and
        the spot table at their centroids."""
        rows, good, contrast = window_stats(grey, corner, 2 * half + 1)
        good &= contrast >= self.min_contrast
        spots = rows_to_spots(rows, m)
        tab = self.observer.grid(spots.centroids_px)
        good &= np.isfinite(tab[:, 0])
        if self.observer.light_radius_m > 0 and good.any():
            good &= self.observer.plausible(spots, tab, good)
        return spots, good, tab

    def _fit(self, spots: Spots, idx: np.ndarray, tab: np.ndarray, x_m: float, y_m: float,
             yaw_rad: float):
        """The refined pose from the found lights (known association) with the outlier
        pass and the frame's checks: ``(x, y, yaw, cov, res, spots, pairs)`` or ``None``."""
        q, ok = ceiling_points(self.rig, self.ceiling_height_m,
                               self.observer.centres(spots.centroids_px, tab))
        if not ok.all():
            return None
        J = tab[:, :4].reshape(-1, 2, 2)
        pairs = np.stack([np.arange(idx.size), idx], axis=1)
        L = self.lights_w[idx]
        fit = refine_pose_ceiling(q, J, L, x_m, y_m, yaw_rad)
        res = fit[4]
        bad = res > max(self.max_residual_px, self.outlier_medians * short_median(res))
        if bad.any():
            if idx.size - int(bad.sum()) < 3:
                return None
            keep = ~bad
            pairs = pairs[keep]
            fit = refine_pose_ceiling(q[keep], J[keep], L[keep], *fit[:3])
            res = fit[4]
        x, y, yaw, cov_p, res = fit
        rms = math.sqrt(float((res * res).sum()) / res.size)
        if (rms > self.max_residual_px or not np.all(np.isfinite(cov_p))
                or math.hypot(x - x_m, y - y_m) > self.gate_m
                or abs(math.remainder(yaw - yaw_rad, 2 * math.pi)) > self.gate_rad):
            return None
        return x, y, yaw, cov_p, res, spots, pairs


__all__ = ["CORE", "MAX_HALF_PX", "WindowFix", "WindowTracker", "prediction_cells"]
