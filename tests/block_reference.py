"""The block method's per-frame stages in array code: the readings the compiled loops
(:func:`.detect.measure_core`, :func:`.detect.contrast_core`, :func:`.pnp.solve_core`,
:func:`.parallels.chords_core`, :func:`.window.predict_core`) stand for, kept here as the
references they are tested against."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ceilkit.runtime.estimators.block.detect import MIN_SIDE_POINTS, Sides, fit_side_lines
from ceilkit.runtime.estimators.block.parallels import (
    CHORD_M,
    MARGIN_PX,
    STEP_M,
    _few_lines,
    site_lines,
)
from ceilkit.runtime.estimators.block.pnp import (
    PlanarGeometry,
    closed_form,
    magnification,
    project_norm,
    project_px,
    refine,
)
from ceilkit.runtime.features.quads import EDGE_SEARCH_PX, edge_points, line_corners
from ceilkit.runtime.geometry.rotations import rot_z


def _sides_of(pts, side, geo, per_side):
    norm = geo.camera.unproject(pts)
    corners = line_corners(fit_side_lines(norm, side))
    return None if corners is None else Sides(corners, norm, side, 4 * per_side)


def measure_sides(grey, corners_px, geo, per_side, passes=2, search_px=EDGE_SEARCH_PX):
    """:func:`.detect.measure_sides`: the passes in pixels, the last through the lens;
    a last pass that loses a side keeps the previous pass's points."""
    pts = side = None
    for k in range(passes - 1):
        pts, side = edge_points(grey, corners_px, per_side,
                                search_px if k == 0 else EDGE_SEARCH_PX)
        if np.any(np.bincount(side, minlength=4) < MIN_SIDE_POINTS):
            return None
        corners_px = line_corners(fit_side_lines(pts, side))
        if corners_px is None:
            return None
    last, lside = edge_points(grey, corners_px, per_side,
                              search_px if passes == 1 else EDGE_SEARCH_PX)
    got = None
    if not np.any(np.bincount(lside, minlength=4) < MIN_SIDE_POINTS):
        got = _sides_of(last, lside, geo, per_side)
    if got is not None or pts is None:
        return got
    return _sides_of(pts, side, geo, per_side)


def step_contrast(grey, corners_px):
    """:func:`.detect.step_contrast` with OpenCV's remap (its 1/32 px grid)."""
    c = corners_px.mean(axis=0)
    t = np.array([0.3, 0.5, 0.7])
    on = (corners_px[:, None, :] + t[None, :, None]
          * (np.roll(corners_px, -1, axis=0) - corners_px)[:, None, :]).reshape(-1, 2)
    step = 0.1 * (c - on)
    pts = np.concatenate([on + step, on - step]).astype(np.float32)
    vals = cv2.remap(grey, pts.reshape(1, -1, 2), None, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(2, -1).astype(float)
    inside, outside = np.median(vals, axis=1)
    return inside / outside if outside > 0 else math.nan


def solve(geo: PlanarGeometry, corners_norm, corners_w, edge_norm, side, drop):
    """:func:`.pnp.solve`: the closed form, the sides in ``drop`` left out, refine."""
    x, y, yaw, shape = closed_form(geo, corners_norm, corners_w)
    if not math.isfinite(x):
        return None
    keep = ~np.asarray(drop, bool)[side]
    edge, sd = edge_norm[keep], side[keep]
    return shape, refine(geo, (x, y, yaw), corners_w, edge, sd, magnification(geo.camera, edge))


def predicted_chords(geo, corridor, pose, max_chords, site=None, reach_m=3.5):
    """:func:`.parallels.predicted_chords` in arrays."""
    x, y, yaw = (float(v) for v in pose)
    rz = rot_z(yaw)
    R_wc = rz @ geo.R_vehicle_cam
    c = rz @ geo.t_vehicle_cam + np.array([x, y, 0.0])
    axis = R_wc[:, 2]
    s = (geo.ceiling_m - c[2]) / axis[2] if axis[2] > 1e-6 else 0.0
    p0, d = site_lines(corridor, (c + s * axis)[:2], reach_m)
    if not len(p0):
        return np.zeros((0, 4))
    t = np.arange(-reach_m, reach_m + 1e-9, STEP_M)
    n_lines, n_t = len(p0), len(t)
    pts = (p0[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 2)
    norm = project_norm(geo, (x, y, yaw), pts)
    front = np.isfinite(norm[:, 0])
    px = np.full((len(norm), 2), np.nan)
    px[front] = geo.camera.distort(norm[front])
    inside = (front & geo.camera.in_image(px, MARGIN_PX)).reshape(n_lines, n_t)
    px = px.reshape(n_lines, n_t, 2)
    k = max(1, round(CHORD_M / STEP_M))
    starts = np.arange(0, n_t - k, k)
    ok = inside[:, starts]
    for j in range(1, k + 1):
        ok = ok & inside[:, starts + j]
    li, sj = np.nonzero(ok)
    si = starts[sj]
    if site is not None and site.ignore_m and len(li):
        along = np.arange(0.0, k * STEP_M + 1e-9, 0.1)
        dense = (p0[li, None, :] + (t[si][:, None] + along)[:, :, None] * d[li, None, :])
        clear = ~site.ignored(dense).any(axis=1)
        li, si = li[clear], si[clear]
    n = len(li)
    if n > max_chords:
        m1 = max(max_chords - 1, 1)
        pick = (2 * np.arange(max_chords) * (n - 1) + m1) // (2 * m1)
        li, si = li[pick], si[pick]
    return np.concatenate([px[li, si], px[li, si + k]], axis=1)


def predicted(geo, targets, pose, margin):
    """:meth:`.window.Windows.predicted`: ``[(index, px (4, 2))]``."""
    if not targets:
        return []
    corners = np.concatenate([t.corners_w for t in targets])
    px = project_px(geo, pose, corners).reshape(-1, 4, 2)
    inside = geo.camera.in_image(px.reshape(-1, 2), margin).reshape(-1, 4).all(1)
    u, v = px[..., 0], px[..., 1]
    nxt = [1, 2, 3, 0]
    area = np.abs(np.sum(u * v[:, nxt] - u[:, nxt] * v, axis=1))
    bright = np.array([not t.dark for t in targets])
    return [(k, px[k]) for k in np.lexsort((-area, bright)) if inside[k]]


def side_offset_cov(r, J, side, A):
    """:func:`.pnp.side_offset_cov` in arrays: ``(σ_b², U or None)``."""
    onehot = (side[:, None] == np.arange(4)).astype(float)              # (M, 4)
    n = onehot.sum(axis=0)
    on = n > 0
    K = int(np.count_nonzero(on))
    if K < 3:
        return 0.0, None
    n = n[on]
    sums = onehot.T @ np.column_stack([r, r * r, J])                    # (4, 5)
    m = sums[on, 0] / n
    within = np.maximum(sums[on, 1] - n * m * m, 0.0) / np.maximum(n - 1.0, 1.0)
    g = sums[on, 2:]
    c, dof = (float(r.mean()), 1) if K == 4 else (0.0, K - 2)   # four sides: less their mean
    var_b = max(float((m - c) @ (m - c)) - float((within / n).sum()) * dof / K, 0.0) / dof
    return var_b, A @ (g.T @ g) @ A


def line_weights(p1_norm: np.ndarray, p2_norm: np.ndarray, R_vehicle_cam: np.ndarray,
                 length: np.ndarray) -> np.ndarray:
    """``(N,)`` the weights :func:`.parallels.robust_heading` gives lines through the
    normalized points ``p1, p2 (N, 2)``: eq. 10's ``|m_xy|²`` (``m = R l / |R l|``, ``l``
    the plane of the line and the optical centre) times ``length`` (the reading
    :func:`.parallels._stage_heading` stands for)."""
    ones = np.ones((len(p1_norm), 1))
    m = np.cross(np.hstack([p1_norm, ones]), np.hstack([p2_norm, ones])) @ \
        np.asarray(R_vehicle_cam, float).T
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    return (m[:, 0] ** 2 + m[:, 1] ** 2) * np.asarray(length, float)


def few_lines_factor(w: np.ndarray) -> float:
    """:func:`.parallels._few_lines` of lines of weights ``w (n,)``."""
    return _few_lines(w.size, float(np.sum(w)), float(np.sum(w * w)))


def read_marker(grey, corners_norm, geo, codes):
    """:func:`.detect.read_marker` in OpenCV and array code (its reading before
    :func:`.detect.read_core`): the homography, ``perspectiveTransform``, the lens,
    ``remap``, each cell's mean of its 2x2 samples, and the dictionary's nearest code."""
    from ceilkit.runtime.estimators.block.detect import (
        BORDER_ERRORS,
        MIN_MARKER_CONTRAST,
        _cell_grid,
    )
    from ceilkit.runtime.features.quads import QUIET_CELLS
    from ceilkit.runtime.geometry.camera import distort_points
    from ceilkit.runtime.geometry.fits import short_median

    n = codes.cells
    g = n + 2 * QUIET_CELLS
    grid, k, ring, border = _cell_grid(n)
    square = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)
    H = cv2.getPerspectiveTransform(square, np.asarray(corners_norm, np.float32))
    norm = np.ascontiguousarray(cv2.perspectiveTransform(grid, H).reshape(-1, 2), np.float64)
    px = np.empty_like(norm)
    distort_points(norm, *geo.camera.lens, px)
    px = px.astype(np.float32)
    if not np.all(np.isfinite(px)):
        return None
    vals = cv2.remap(grey, px[:, 0].reshape(k, k), px[:, 1].reshape(k, k),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cells = vals.reshape(g, 2, g, 2).sum(axis=(1, 3), dtype=np.float32) * np.float32(0.25)
    flat = cells.ravel()
    on_border = flat[border]
    white, black = short_median(flat[ring]), short_median(on_border)
    if white - black < MIN_MARKER_CONTRAST:
        return None
    thr = 0.5 * (white + black)
    if int(np.count_nonzero(on_border > thr)) > BORDER_ERRORS:
        return None
    return codes.identify(cells[2:-2, 2:-2] > thr)
