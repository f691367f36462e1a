"""The site's ceiling lines (the corridor section's ``lines_along``/``lines_across``: tile
seams, lamp rows' edges) predicted in the image from a pose near the truth, as short
pixel chords for :func:`~ceilkit.runtime.features.lines.refine_undistorted`.

A block's fix (or the tracker's prior) is a few millimetres (centimetres) off, a pixel
or two on the ceiling: measuring the known parallels where they must be costs a
fraction of a line detector over the frame. Pure math: arrays in, arrays out.

Example::

    chords = predicted_chords(geo, site.corridor, (x, y, yaw))   # (N, 4) pixels, (N,) axis
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, ceiling_norm
from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.jit import arr

REACH_M = 3.5        # ceiling lines looked for this far from the camera's ceiling point
CHORD_M = 1.0        # a chord's length on the ceiling
STEP_M = 0.5         # sample spacing along a line: a chord's ends and middle are checked
IGNORE_STEP_M = 0.1  # a chord's samples against the site's ignore regions
MARGIN_PX = 8.0      # chord ends kept this far inside the frame
MAX_CHORDS = 20      # chords measured per frame (spread over the lines)


def site_lines(corridor, centre: np.ndarray, reach_m: float = REACH_M
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(points, directions)`` ``(L, 2)`` each, in W, of the site's ceiling lines within
    ``reach_m`` of ``centre`` (W, ``(2,)``): the lines along x first, then across."""
    along = np.asarray(corridor.lines_along_m, float).reshape(-1)
    along = along[np.abs(along - centre[1]) < reach_m]
    p0 = np.empty((len(along), 2))
    p0[:, 0], p0[:, 1] = centre[0], along
    d = np.zeros((len(along), 2))
    d[:, 0] = 1.0
    a = corridor.lines_across
    if a is not None and a.spacing_m > 0:
        k0 = math.ceil((centre[0] - reach_m - a.first_m) / a.spacing_m)
        k1 = math.floor((centre[0] + reach_m - a.first_m) / a.spacing_m)
        across = a.first_m + np.arange(k0, k1 + 1) * a.spacing_m
        q0 = np.empty((len(across), 2))
        q0[:, 0], q0[:, 1] = across, centre[1]
        e = np.zeros((len(across), 2))
        e[:, 1] = 1.0
        p0, d = np.concatenate([p0, q0]), np.concatenate([d, e])
    return p0, d


ON_LINE_M = 0.015     # sides_on_lines: a block's side this near a ceiling line touches it
ON_LINE_SIN = math.sin(math.radians(2.0))   # ... and this near parallel to it


def sides_on_lines(corridor, corners_w: np.ndarray, tol_m: float = ON_LINE_M) -> np.ndarray:
    """``(4,)`` bool: which sides of a block (side k from corner k to k+1 of
    ``corners_w`` ``(4, 2)``, W) lie on one of the site's ceiling lines (a seam, a
    T-bar, a lamp's edge): parallel to it and both ends within ``tol_m``. Such a side's
    edge is not a clean step: a line narrower than the blur just outside it moves
    every station's half-way crossing the same way (configs/block's tile B ends on the
    x = 5.4 m seam: ~0.3 px, 1.3 mm of x error). ``corridor=None``: none."""
    out = np.zeros(4, bool)
    if corridor is None:
        return out
    c = np.asarray(corners_w, float)
    p0, d = site_lines(corridor, c.mean(axis=0), float(np.ptp(c, axis=0).max()) + 1.0)
    if len(p0) == 0:
        return out
    a, b = c, c[[1, 2, 3, 0]]
    run = b - a
    length = np.hypot(run[:, 0], run[:, 1])
    for k in range(4):
        cross = np.abs(run[k, 0] * d[:, 1] - run[k, 1] * d[:, 0]) / max(length[k], 1e-12)
        da = np.abs((a[k, 0] - p0[:, 0]) * d[:, 1] - (a[k, 1] - p0[:, 1]) * d[:, 0])
        db = np.abs((b[k, 0] - p0[:, 0]) * d[:, 1] - (b[k, 1] - p0[:, 1]) * d[:, 0])
        out[k] = bool(np.any((cross < ON_LINE_SIN) & (da < tol_m) & (db < tol_m)))
    return out


class LinedSides:
    """The sides of a block the refinement leaves out: those on a ceiling line of the
    site (:func:`sides_on_lines`) whose opposite side is not (a pair both on lines
    shrinks or grows the block evenly: its centre does not move, and the size check's
    term, :func:`.pnp.side_offset_cov`, covers it). ``self(corners_w)`` gives ``(4,)``
    bool, cached per corner order (a block's, and each of its symmetric turns)."""

    def __init__(self, corridor) -> None:
        self.corridor = corridor
        self._cache: dict[bytes, np.ndarray] = {}

    def __call__(self, corners_w: np.ndarray) -> np.ndarray:
        key = np.asarray(corners_w, float).tobytes()
        got = self._cache.get(key)
        if got is None:
            on = sides_on_lines(self.corridor, corners_w)
            got = on & ~on[[2, 3, 0, 1]]
            got.setflags(write=False)
            self._cache[key] = got
        return got

    def clean(self, corners_w: np.ndarray, edge: np.ndarray, side: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """The edge points ``(M, 2)`` and their sides ``(M,)`` without those of the
        left-out sides of ``corners_w``."""
        drop = self(corners_w)
        if not drop.any():
            return edge, side
        keep = ~drop[side]
        return edge[keep], side[keep]


def predicted_chords(geo: PlanarGeometry, corridor, pose: np.ndarray,
                     max_chords: int = MAX_CHORDS, site=None, reach_m: float = REACH_M
                     ) -> np.ndarray:
    """Pixel chords ``(N, 4)`` along the site's ceiling lines seen from ``pose``, at most
    ``max_chords`` of them spread over the lines (one projection of every sample).
    With ``site``, samples inside its ``ignore`` regions are not used (SPEC §2)."""
    x, y, yaw = (float(v) for v in pose)
    rz = rot_z(yaw)
    R_wc = rz @ geo.R_vehicle_cam
    c = rz @ geo.t_vehicle_cam + np.array([x, y, 0.0])
    axis = R_wc[:, 2]
    s = (geo.ceiling_m - c[2]) / axis[2] if axis[2] > 1e-6 else 0.0
    centre = (c + s * axis)[:2]
    p0, d = site_lines(corridor, centre, reach_m)
    if not len(p0):
        return np.zeros((0, 4))
    t = _samples(reach_m)
    n_lines, n_t = len(p0), len(t)
    pts = (p0[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 2)
    norm = ceiling_norm(arr(geo.R_vehicle_cam, np.float64), arr(geo.t_vehicle_cam, np.float64),
                        float(geo.ceiling_m), x, y, yaw, arr(pts, np.float64), 1e-6)
    front = np.isfinite(norm[:, 0])
    if front.all():
        px = geo.camera.distort(norm)
    else:
        px = np.full((len(norm), 2), np.nan)
        if np.any(front):
            px[front] = geo.camera.distort(norm[front])
    inside = (front & geo.camera.in_image(px, MARGIN_PX)).reshape(n_lines, n_t)
    px = px.reshape(n_lines, n_t, 2)
    k = max(1, round(CHORD_M / STEP_M))      # samples a chord spans (k STEP_M metres)
    # non-overlapping chords, every k-th sample a start, each of its k + 1 samples inside
    # (its ends and middle: a chord is short against the frame, and its measurement
    # drops it if it leaves the frame between them)
    starts = np.arange(0, n_t - k, k)
    ok = inside[:, starts]
    for j in range(1, k + 1):
        ok = ok & inside[:, starts + j]
    li, sj = np.nonzero(ok)
    si = starts[sj]
    if site is not None and site.ignore_m and len(li):
        # SPEC §2: no chord crosses an ignore region (tested every IGNORE_STEP_M)
        along = np.arange(0.0, k * STEP_M + 1e-9, IGNORE_STEP_M)
        dense = (p0[li, None, :] + (t[si][:, None] + along)[:, :, None] * d[li, None, :])
        clear = ~site.ignored(dense).any(axis=1)
        li, si = li[clear], si[clear]
    n = len(li)
    if n > max_chords:
        # spread evenly over the list (round(j (n - 1) / (m - 1)), in integers)
        m1 = max(max_chords - 1, 1)
        pick = (2 * np.arange(max_chords) * (n - 1) + m1) // (2 * m1)
        li, si = li[pick], si[pick]
    return np.concatenate([px[li, si], px[li, si + k]], axis=1)


@functools.lru_cache(maxsize=4)
def _samples(reach_m: float) -> np.ndarray:
    """The samples' positions along a line, ``-reach_m`` to ``reach_m`` by
    :data:`STEP_M` (read-only: shared between calls)."""
    t = np.arange(-reach_m, reach_m + 1e-9, STEP_M)
    t.flags.writeable = False
    return t
