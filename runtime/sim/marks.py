"""Blocks and printed markers on the simulated ceiling (SPEC §2 ``blocks``, ``markers``).

:func:`mark_features` gives :mod:`ceilkit.runtime.sim.render` the cells each block or
marker can touch and how to shade a sample there, from its position on the ceiling
relative to the camera; the renderer casts the rays through the lens, so blocks and
markers are exact through any distortion.

* a block is a polygon of grey :data:`BLOCK_GREY` (``appearance: dark``, the default) or
  :data:`BLOCK_BRIGHT_GREY` (``bright``), its edges anti-aliased over a sample footprint;
* a marker is the dictionary's printed image (``cv2.aruco.generateImageMarker``, one cell
  per bit plus the black border) with a white margin of ``QUIET_CELLS`` cells, each
  cell's coverage of a sample a footprint-wide box (separable, so edges and corners are
  unbiased). Corner k of the black square is at SPEC §2's
  ``(x, y) + Rz(yaw) (s/2) d_k``: the printed image's top along +x of W at yaw 0, its
  left side towards -y.

Example (the renderer's side)::

    for cells, shade in mark_features(site, cam_x_m, cam_y_m, cxr, cyr, reach):
        value = shade(xr, yr, inv_fp, value)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ceilkit.runtime.features.quads import QUIET_CELLS, marker_cells

BLOCK_GREY = 40.0          # a dark block (access hatch, dark tile)
BLOCK_BRIGHT_GREY = 225.0  # a bright block (a white tile, a painted square)
MARKER_BLACK_GREY = 30.0   # printed black
MARKER_WHITE_GREY = 235.0  # printed white (paper)

Shade = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def ramp(sd: np.ndarray, inv_fp: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] of a signed distance (> 0 inside), a footprint-wide ramp."""
    return np.clip(0.5 + sd * inv_fp, 0.0, 1.0)


def polygon_sd(x: np.ndarray, y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Signed distance to a simple polygon ``(n, 2)``: > 0 inside."""
    inside = np.zeros(x.shape, dtype=bool)
    dist = np.full(x.shape, np.inf, dtype=np.float64)
    n = pts.shape[0]
    for i in range(n):
        (x1, y1), (x2, y2) = pts[i], pts[(i + 1) % n]
        ex, ey = x2 - x1, y2 - y1
        ll = ex * ex + ey * ey
        t = np.clip(((x - x1) * ex + (y - y1) * ey) / ll, 0.0, 1.0)
        dist = np.minimum(dist, np.hypot(x - x1 - t * ex, y - y1 - t * ey))
        cross = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = x1 + (y - y1) * ex / ey
        inside ^= cross & (x < xi)
    return np.where(inside, dist, -dist)


def block_grey(appearance: str | None) -> float:
    """The radiance of a block of ``appearance`` (``dark``, ``bright`` or None: dark)."""
    return BLOCK_BRIGHT_GREY if appearance == "bright" else BLOCK_GREY


def _near(pts_r: np.ndarray, cxr: np.ndarray, cyr: np.ndarray, reach: np.ndarray
          ) -> np.ndarray:
    """Cells (centres ``cxr, cyr``, radius ``reach``) that may touch the polygon ``pts_r``."""
    ctr = pts_r.mean(axis=0)
    rad = float(np.max(np.linalg.norm(pts_r - ctr, axis=1)))
    with np.errstate(invalid="ignore"):
        return np.hypot(cxr - ctr[0], cyr - ctr[1]) < reach + rad


def _block_shade(pts_r: np.ndarray, grey: float) -> Shade:
    def shade(xr, yr, inv_fp, val):
        return val + ramp(polygon_sd(xr, yr, pts_r), inv_fp) * (grey - val)
    return shade


def _marker_table(dictionary: str, marker_id: int) -> np.ndarray:
    """Radiance per cell ``(M + 2, M + 2)``: the printed marker with its white margin,
    NaN in the outermost ring (the ceiling itself)."""
    cells = marker_cells(dictionary, marker_id)
    grey = np.where(cells > 0, MARKER_WHITE_GREY, MARKER_BLACK_GREY)
    printed = np.pad(grey, QUIET_CELLS, constant_values=MARKER_WHITE_GREY)
    return np.pad(printed, 1, constant_values=np.nan)


def _marker_shade(table: np.ndarray, ctr_r: np.ndarray, yaw_rad: float, cell_m: float,
                  half_m: float) -> Shade:
    """Shade of a marker whose printed area (margin included) has half side ``half_m``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    n = table.shape[0] - 2                      # printed cells per side

    def shade(xr, yr, inv_fp, val):
        dx, dy = xr - ctr_r[0], yr - ctr_r[1]
        lx, ly = c * dx + s * dy, -s * dx + c * dy       # marker frame
        col = (ly + half_m) / cell_m                     # printed image: left to right
        row = (half_m - lx) / cell_m                     # top to bottom
        inv = inv_fp * cell_m
        i0, j0 = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
        out = np.zeros_like(val)
        cov_r = [ramp(row - (i0 + k), inv) - ramp(row - (i0 + k) - 1, inv)
                 for k in (-1, 0, 1)]
        cov_c = [ramp(col - (j0 + k), inv) - ramp(col - (j0 + k) - 1, inv)
                 for k in (-1, 0, 1)]
        for a, ka in zip((-1, 0, 1), cov_r, strict=True):
            ii = np.clip(i0 + a + 1, 0, n + 1)
            for b, kb in zip((-1, 0, 1), cov_c, strict=True):
                t = table[ii, np.clip(j0 + b + 1, 0, n + 1)]
                out += ka * kb * np.where(np.isnan(t), val, t)
        return out.astype(val.dtype)
    return shade


def mark_features(site: Any, cam_x_m: float, cam_y_m: float, cxr: np.ndarray,
                  cyr: np.ndarray, reach: np.ndarray) -> list[tuple[np.ndarray, Shade]]:
    """Every block and marker of ``site`` as ``(cells, shade)`` for the renderer.

    Args:
        site: the :class:`~ceilkit.runtime.config.site.Site` (its ``blocks``, ``markers``).
        cam_x_m, cam_y_m: the camera centre in W.
        cxr, cyr: ``(n_cells,)`` cell centres on the ceiling relative to the camera, m.
        reach: ``(n_cells,)`` cell radius plus a footprint, m (NaN: no ceiling samples).

    Returns:
        ``(cells, shade)`` per mark: ``cells`` the ``(n_cells,)`` bool cells it may touch,
        ``shade(xr, yr, inv_fp, value) -> value`` on samples at ``(xr, yr)`` relative to
        the camera (m) with ``inv_fp`` their inverse footprint (1/m).
    """
    cam = np.array([cam_x_m, cam_y_m])
    out: list[tuple[np.ndarray, Shade]] = []
    for blk in site.blocks:
        pts_r = np.asarray(blk.corners_m, float) - cam
        grey = block_grey(getattr(blk, "appearance", None))
        out.append((_near(pts_r, cxr, cyr, reach), _block_shade(pts_r, grey)))
    markers = getattr(site, "markers", None)
    if markers is None:
        return out
    for pose in markers.poses:
        table = _marker_table(markers.dictionary, pose.id)
        n_printed = table.shape[0] - 2
        cell_m = pose.size_m / (n_printed - 2 * QUIET_CELLS)
        half_m = 0.5 * n_printed * cell_m
        ctr_r = np.array([pose.x_m, pose.y_m]) - cam
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        sq = half_m * np.array([[1, -1], [1, 1], [-1, 1], [-1, -1]], float)
        outline = ctr_r + sq @ np.array([[c, s], [-s, c]])
        out.append((_near(outline, cxr, cyr, reach),
                    _marker_shade(table, ctr_r, pose.yaw_rad, cell_m, half_m)))
    return out
