"""The lights tracker's window fix in array code: the reading the compiled
:func:`ceilkit.runtime.estimators.lights.track._track` stands for (its stages one
array function each), kept here as the reference it is tested against."""

from __future__ import annotations

import math

import numpy as np
from lights_reference import centres, locate, plausible

from ceilkit.runtime.estimators.lights.rays import ceiling_points
from ceilkit.runtime.estimators.lights.refine import pattern_cover, refine_pose_ceiling
from ceilkit.runtime.estimators.lights.track import MAX_HALF_PX, TRACK_CORE, WindowTracker
from ceilkit.runtime.features.spots import rows_to_spots
from ceilkit.runtime.features.windows import window_stats
from ceilkit.runtime.geometry.fits import short_median


def observe(w: WindowTracker, grey: np.ndarray, x_m: float, y_m: float, yaw_rad: float):
    """``(x, y, yaw, cov, res, centroids, pairs, predicted, found, predicted_px)`` or
    ``None``, as :meth:`WindowTracker.observe`."""
    pred = predict(w, x_m, y_m, yaw_rad)
    if pred is None:
        return None
    idx, px, m, corner, half = pred
    spots, good, tab = measure(w, grey, corner, half)
    n_found = int(np.count_nonzero(good))
    if n_found < max(3, math.ceil(w.min_share * m)):
        return None
    fit = fit_pose(w, spots.select(good), idx[good], tab[good], x_m, y_m, yaw_rad)
    if fit is None:
        return None
    x, y, yaw, cov, res, spots, pairs = fit
    return x, y, yaw, cov, res, spots.centroids_px, pairs, m, n_found, px


def predict(w: WindowTracker, x_m: float, y_m: float, yaw_rad: float):
    ok, cell, z = locate(w.visibility, x_m, y_m, yaw_rad)
    idx = np.flatnonzero(ok)
    m = idx.size
    if m < 3:
        return None
    c = w._cells[cell[idx]]
    z = z[idx]
    dq = np.stack([z.real, z.imag], axis=1) - c[:, :2]
    px = c[:, 2:4] + (c[:, 4:8].reshape(-1, 2, 2) @ dq[:, :, None])[:, :, 0]
    area = c[:, 8]
    fin = np.isfinite(px[:, 0]) & np.isfinite(area)
    n_fin = int(np.count_nonzero(fin))
    if n_fin < 3:
        return None
    r_spot = math.sqrt(max(float(area[fin].max()), 1.0) / math.pi)
    half = int(min(MAX_HALF_PX, math.ceil(r_spot * 1.6 + w.window_px)))
    side = 2 * half + 1
    if side >= min(w.width, w.height):
        return None
    if n_fin < m:
        idx, px = idx[fin], px[fin]
    corner = np.rint(px).astype(np.int64) - half
    np.maximum(corner, 0, out=corner)
    np.minimum(corner, (w.width - side, w.height - side), out=corner)
    return idx, px, m, corner, half


def measure(w: WindowTracker, grey: np.ndarray, corner: np.ndarray, half: int):
    rows, good, contrast = window_stats(grey, corner, 2 * half + 1, core=TRACK_CORE)
    good &= contrast >= w.min_contrast
    spots = rows_to_spots(rows, corner.shape[0])
    tab = w.observer.grid(spots.centroids_px)
    good &= np.isfinite(tab[:, 0])
    if w.observer.light_radius_m > 0 and good.any():
        good &= plausible(spots, tab, good)
    return spots, good, tab


def fit_pose(w: WindowTracker, spots, idx, tab, x_m, y_m, yaw_rad):
    cen = centres(spots.centroids_px, tab)
    q, ok = ceiling_points(w.rig, w.ceiling_height_m, cen)
    if not ok.all():
        return None
    J = tab[:, :4].reshape(-1, 2, 2)
    pairs = np.stack([np.arange(idx.size), idx], axis=1)
    L = w.lights_w[idx]
    fit = refine_pose_ceiling(q, J, L, x_m, y_m, yaw_rad)
    res = fit[4]
    bad = res > max(w.max_residual_px, w.outlier_medians * short_median(res))
    keep = ~bad
    if bad.any():
        if idx.size - int(bad.sum()) < 3:
            return None
        pairs = pairs[keep]
        fit = refine_pose_ceiling(q[keep], J[keep], L[keep], *fit[:3])
        res = fit[4]
    # the covariance without the lights' shared radial shift (refine.pattern_cover)
    cam = w.rig.camera
    fit = pattern_cover(q[keep], J[keep], L[keep], cen[keep] - (cam.cx, cam.cy), fit)
    x, y, yaw, cov_p, res = fit
    rms = math.sqrt(float((res * res).sum()) / res.size)
    if (rms > w.max_residual_px or not np.all(np.isfinite(cov_p))
            or math.hypot(x - x_m, y - y_m) > w.gate_m
            or abs(math.remainder(yaw - yaw_rad, 2 * math.pi)) > w.gate_rad):
        return None
    return x, y, yaw, cov_p, res, spots, pairs
