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
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.geometry.camera import distort_points
from ceilkit.runtime.geometry.ceiling import PlanarGeometry, ceiling_norm, kernel_mount
from ceilkit.runtime.jit import arr, njit, warmer

REACH_M = 3.5        # ceiling lines looked for this far from the camera's ceiling point
CHORD_M = 1.0        # a chord's length on the ceiling
STEP_M = 0.5         # sample spacing along a line: a chord's ends and middle are checked
IGNORE_STEP_M = 0.1  # a chord's samples against the site's ignore regions
MARGIN_PX = 8.0      # chord ends kept this far inside the frame
MAX_CHORDS = 20      # chords measured per frame (spread over the lines)


class SiteLines(NamedTuple):
    """A site's ceiling lines as :func:`chords_core` takes them: ``along (L,)`` the lines
    along x at these y (m), the lines across at ``first + k spacing`` (m; ``spacing`` 0:
    none), looked for within ``reach_m`` of the camera's ceiling point."""

    along: np.ndarray
    first: float
    spacing: float
    reach_m: float


class ChordGrid(NamedTuple):
    """How :func:`chords_core` samples the lines: ``samples (T,)`` positions along a line
    (m), a chord spans ``k`` of them, inside a ``width`` x ``height`` frame by
    ``margin`` px; at most ``max_chords`` (< 0: every candidate, not spread)."""

    samples: np.ndarray
    k: int
    width: float
    height: float
    margin: float
    max_chords: int


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
    With ``site``, samples inside its ``ignore`` regions are not used (SPEC §2). One
    compiled call (:func:`chords_core`); the ignore regions' test after it."""
    x, y, yaw = (float(v) for v in pose)
    along = _along(tuple(corridor.lines_along_m))
    a = corridor.lines_across
    first, spacing = (float(a.first_m), float(a.spacing_m)) if a is not None else (0.0, 0.0)
    ignoring = site is not None and bool(site.ignore_m)
    cam = geo.camera
    k = max(1, round(CHORD_M / STEP_M))      # samples a chord spans (k STEP_M metres)
    t = _samples(reach_m)
    chords, li, si, p0, d = chords_core(
        kernel_mount(geo), x, y, yaw, SiteLines(along, first, spacing, float(reach_m)),
        ChordGrid(t, k, float(cam.width), float(cam.height), MARGIN_PX,
                  -1 if ignoring else max_chords))
    if not ignoring or not len(li):
        return chords
    # SPEC §2: no chord crosses an ignore region (tested every IGNORE_STEP_M)
    step = np.arange(0.0, k * STEP_M + 1e-9, IGNORE_STEP_M)
    dense = (p0[li, None, :] + (t[si][:, None] + step)[:, :, None] * d[li, None, :])
    chords = chords[~site.ignored(dense).any(axis=1)]
    n = len(chords)
    if n > max_chords:
        chords = chords[_spread(n, max_chords)]
    return chords


def _spread(n: int, m: int) -> np.ndarray:
    """``m`` indices spread evenly over ``n`` (round(j (n - 1) / (m - 1)), in integers)."""
    m1 = max(m - 1, 1)
    return (2 * np.arange(m) * (n - 1) + m1) // (2 * m1)


@functools.lru_cache(maxsize=8)
def _along(lines_along_m: tuple[float, ...]) -> np.ndarray:
    """A corridor's ``lines_along_m`` as the read-only float array the loop takes."""
    return arr(np.asarray(lines_along_m, float).reshape(-1), np.float64)


@njit
def chords_core(mount, x, y, yaw, lines, grid):  # pragma: no cover
    """:func:`predicted_chords` without the ignore regions, from the pose ``(x, y, yaw)``
    through ``mount`` (:class:`.ceiling.KernelMount`), of ``lines`` (:class:`SiteLines`)
    sampled by ``grid`` (:class:`ChordGrid`): ``(chords (N, 4) px, line (N,), start (N,),
    line points (L, 2), directions (L, 2))`` (:func:`site_lines` about the camera's
    ceiling point). ``grid.max_chords < 0``: every candidate, not spread."""
    R, t, ceiling_m, code, lens = mount
    along, first, spacing, reach_m = lines
    samples, k, width, height, margin, max_chords = grid
    cz, sz = math.cos(yaw), math.sin(yaw)
    # the optical axis meets the ceiling at the centre of the lines looked for
    ax = cz * R[0, 2] - sz * R[1, 2]
    ay = sz * R[0, 2] + cz * R[1, 2]
    az = R[2, 2]
    cx = cz * t[0] - sz * t[1] + x
    cy = sz * t[0] + cz * t[1] + y
    s = (ceiling_m - t[2]) / az if az > 1e-6 else 0.0
    ox, oy = cx + s * ax, cy + s * ay
    n_along = 0
    for i in range(along.size):
        n_along += abs(along[i] - oy) < reach_m
    k0 = k1 = 0
    if spacing > 0:
        k0 = math.ceil((ox - reach_m - first) / spacing)
        k1 = math.floor((ox + reach_m - first) / spacing)
    n_lines = n_along + max(k1 - k0 + 1, 0) if spacing > 0 else n_along
    p0, d = np.empty((n_lines, 2)), np.zeros((n_lines, 2))
    j = 0
    for i in range(along.size):
        if abs(along[i] - oy) < reach_m:
            p0[j, 0], p0[j, 1], d[j, 0] = ox, along[i], 1.0
            j += 1
    for i in range(n_lines - n_along):
        p0[j, 0], p0[j, 1], d[j, 1] = first + (k0 + i) * spacing, oy, 1.0
        j += 1
    n_t = samples.size
    pts = np.empty((n_lines * n_t, 2))
    for li in range(n_lines):
        for ti in range(n_t):
            pts[li * n_t + ti, 0] = p0[li, 0] + samples[ti] * d[li, 0]
            pts[li * n_t + ti, 1] = p0[li, 1] + samples[ti] * d[li, 1]
    norm = ceiling_norm(R, t, ceiling_m, x, y, yaw, pts, 1e-6)
    px = np.empty_like(norm)
    distort_points(norm, code, lens, px)
    inside = np.empty(n_lines * n_t, np.bool_)
    lo_u, hi_u = -0.5 + margin, width - 0.5 - margin
    lo_v, hi_v = -0.5 + margin, height - 0.5 - margin
    for i in range(n_lines * n_t):
        u, v = px[i, 0], px[i, 1]
        inside[i] = (math.isfinite(norm[i, 0]) and lo_u <= u <= hi_u and lo_v <= v <= hi_v)
    # non-overlapping chords, every k-th sample a start, each of its k + 1 samples
    # inside (its ends and middle: a chord is short against the frame, and its
    # measurement drops it if it leaves the frame between them)
    n_start = (n_t - k + k - 1) // k if n_t > k else 0
    cand_l = np.empty(n_lines * n_start, np.int64)
    cand_s = np.empty(n_lines * n_start, np.int64)
    n = 0
    for li in range(n_lines):
        for sj in range(n_start):
            st = sj * k
            ok = True
            for q in range(k + 1):
                ok = ok and inside[li * n_t + st + q]
            if ok:
                cand_l[n], cand_s[n] = li, st
                n += 1
    m = n
    if 0 <= max_chords < n:
        m = max_chords
    chords = np.empty((m, 4))
    out_l, out_s = np.empty(m, np.int64), np.empty(m, np.int64)
    m1 = max(m - 1, 1)
    for j in range(m):
        c = j if m == n else (2 * j * (n - 1) + m1) // (2 * m1)
        li, st = cand_l[c], cand_s[c]
        a, b = li * n_t + st, li * n_t + st + k
        chords[j, 0], chords[j, 1] = px[a, 0], px[a, 1]
        chords[j, 2], chords[j, 3] = px[b, 0], px[b, 1]
        out_l[j], out_s[j] = li, st
    return chords, out_l, out_s, p0, d


@functools.lru_cache(maxsize=4)
def _samples(reach_m: float) -> np.ndarray:
    """The samples' positions along a line, ``-reach_m`` to ``reach_m`` by
    :data:`STEP_M` (read-only: shared between calls)."""
    t = np.arange(-reach_m, reach_m + 1e-9, STEP_M)
    t.flags.writeable = False
    return t


@warmer
def _warm() -> None:
    from ceilkit.runtime.geometry.camera import CameraModel
    cam = CameraModel.pinhole(64, 48, 40.0)
    geo = PlanarGeometry(cam, np.diag([1.0, -1.0, -1.0]).T.copy(), np.zeros(3), 3.0)

    class _Corridor:
        lines_along_m = (0.0, 0.6)
        lines_across = None
    predicted_chords(geo, _Corridor(), (0.0, 0.0, 0.0))
