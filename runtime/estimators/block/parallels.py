"""The ceiling's parallels for the block method: where the site's ceiling lines fall in
the image, which sides of a block lie on one, and the heading the lines give.

**Predicted lines** (:func:`predicted_chords`). The site's ceiling lines (the corridor
section's ``lines_along``/``lines_across``: tile seams, lamp rows' edges) predicted in
the image from a pose near the truth, as short pixel chords for
:func:`~ceilkit.runtime.features.lines.refine_chords`. A block's fix (or the tracker's
prior) is a few millimetres (centimetres) off, a pixel or two on the ceiling: measuring
the known parallels where they must be costs a fraction of a line detector over the
frame. A block's side on such a line is left out of its refinement
(:class:`LinedSides`).

**The heading** (Xu et al., eqs. 8-10), given the rig's rotation. A ceiling line
parallel to W's x axis has direction ``d_W = (1, 0, 0)``; seen by a camera of mount
``R_VC`` on a vehicle of heading ``phi`` its direction in C is
``R_VC^T Rz(-phi) e_x``. The image line through two normalized points ``p1, p2``
(homogeneous) has the normal ``l = p1 x p2`` of the plane it spans with the optical
centre, and the line's direction lies in that plane: with ``m = R_VC l`` (in V),

    x-parallel:  m_x cos(phi) - m_y sin(phi) = 0          (eqs. 8 and 10)
    y-parallel:  m_x sin(phi) + m_y cos(phi) = 0          (eq. 9)

so each line gives ``phi = atan2(m_x, m_y)`` modulo pi (x) or that plus pi/2 (y): on a
grid of both, modulo pi/2. The lines' headings are combined as a weighted circular mean
of ``4 phi`` (weights ``|m_xy|^2``, the plane's tilt off the vertical); the branch is the
one nearest a given heading (a block's, the tracker's) when there is one, and the fusion
takes the heading with its period (``yaw_period_rad``) otherwise. Fewer than two lines:
None.

**The heading stage** (:class:`ParallelsStage`, once a frame): with a pose and the
site's lines, the lines are measured where they must be (``mode = "predicted"``); else
segments are detected on the frame (FastLineDetector, ``mode = "detected"``). Segments
in the site's ``ignore`` regions are not used (SPEC §2) when a pose places them.

Example::

    chords = predicted_chords(geo, site.corridor, (x, y, yaw))   # (N, 4) pixels
    h = heading_from_parallels(p1_norm, p2_norm, rig.mount.R_vehicle_cam)
    h.yaw_rad, h.sigma_rad, h.period_rad
    stage = ParallelsStage(geo, site, min_px=60.0, gate_deg=1.0)
    h = stage(grey, hint_yaw_rad, pose)       # ParallelsHeading or None; stage.mode
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ceilkit.runtime.estimators.ignore import IgnoreRegions
from ceilkit.runtime.features.lines import (
    SegmentDetector,
    refine_chords,
    refine_undistorted,
)
from ceilkit.runtime.geometry.camera import distort_points
from ceilkit.runtime.geometry.ceiling import PlanarGeometry, ceiling_norm, kernel_mount
from ceilkit.runtime.geometry.fits import student
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

PERIOD_RAD = math.pi / 2      # lines along both axes: heading known modulo a quarter turn
MIN_LINES = 2
SIGMA_FLOOR_RAD = math.radians(0.002)


@dataclass(frozen=True)
class ParallelsHeading:
    """A heading from ceiling parallels.

    Attributes:
        yaw_rad: the vehicle's heading in W (the branch nearest the hint, if given).
        sigma_rad: its 1-sigma, from the lines' spread about it (floored).
        period_rad: the heading is known modulo this (pi/2).
        n_lines: lines used.
    """

    yaw_rad: float
    sigma_rad: float
    period_rad: float
    n_lines: int


class HeadingGate(NamedTuple):
    """How :func:`_robust` picks and combines the lines: the reference heading ``hint``
    (rad, in W) when ``has_hint``, the gate ``gate`` (rad) about it, the heading's
    ``period`` (rad), the fewest lines ``min_lines`` and the sigma's floor ``floor``
    (rad)."""

    hint: float
    has_hint: bool
    gate: float
    period: float
    min_lines: int
    floor: float


def heading_from_parallels(p1_norm: np.ndarray, p2_norm: np.ndarray,
                           R_vehicle_cam: np.ndarray, hint_yaw_rad: float | None = None,
                           period_rad: float = PERIOD_RAD) -> ParallelsHeading | None:
    """The vehicle heading from ceiling lines parallel to W's axes (see the module).

    Args:
        p1_norm, p2_norm: ``(N, 2)`` two normalized (undistorted) points of each line.
        R_vehicle_cam: the mount's rotation (tilt, swing and pan calibrated).
        hint_yaw_rad: a heading near the truth (a block's, the tracker's): picks the
            branch; None: the branch in ``[-period/2, period/2)``.
        period_rad: pi/2 for lines along both axes, pi when all are along x.

    Returns:
        :class:`ParallelsHeading`, or None with fewer than :data:`MIN_LINES` lines.
    """
    return robust_heading(p1_norm, p2_norm, R_vehicle_cam, hint_yaw_rad, math.inf, None,
                          period_rad)[0]                      # (no gate: every line)


def robust_heading(p1_norm: np.ndarray, p2_norm: np.ndarray, R_vehicle_cam: np.ndarray,
                   hint_yaw_rad: float | None = None, gate_rad: float = math.radians(1.0),
                   weights: np.ndarray | None = None, period_rad: float = PERIOD_RAD
                   ) -> tuple[ParallelsHeading | None, np.ndarray]:
    """:func:`heading_from_parallels` on the lines that agree: lines off the ceiling's
    axes (a marker turned 45 degrees, clutter) are dropped. The reference is the hint
    when given, else the weighted circular mean of all lines refined once with a gate
    of 3 ``gate_rad``; lines within ``gate_rad`` (modulo the period) of it are kept.

    ``weights`` (``(N,)``, e.g. the lines' lengths) multiply eq. 10's ``|m_xy|^2``.

    Returns:
        ``(heading or None, kept)``: ``kept`` is the ``(N,)`` mask of the lines used.
    """
    p1 = arr(p1_norm, np.float64).reshape(-1, 2)
    p2 = arr(p2_norm, np.float64).reshape(-1, 2)
    wts = (np.ones(p1.shape[0]) if weights is None
           else arr(weights, np.float64).reshape(-1))
    kept = np.zeros(p1.shape[0], np.bool_)
    gate = HeadingGate(0.0 if hint_yaw_rad is None else float(hint_yaw_rad),
                       hint_yaw_rad is not None, float(gate_rad), float(period_rad),
                       MIN_LINES, SIGMA_FLOOR_RAD)
    found, yaw, sigma, n = _robust(p1, p2, arr(R_vehicle_cam, np.float64), wts, gate, kept)[:4]
    if not found:
        return None, kept
    return _near_hint(ParallelsHeading(wrap_pi(yaw), sigma, period_rad, n), hint_yaw_rad), kept


@njit
def _robust(p1, p2, R, weights, how, kept):  # pragma: no cover - compiled
    """:func:`robust_heading` in one loop: ``(found, yaw, sigma, n, sw, sww)`` (``sw``,
    ``sww``: the sum of the kept lines' weights and of their squares) and ``kept (N,)``
    (the lines used) set, the lines picked and combined as ``how`` (a
    :class:`HeadingGate`) says. Each line's heading is eq. 10's ``atan2(m_x, m_y)``
    (modulo the period) with ``m = R l / |R l|``, ``l = (x1, y1, 1) x (x2, y2, 1)``, and
    its weight ``|m_xy|²`` times ``weights``; the heading is their weighted circular
    mean (:func:`_circular_mean`), its sigma their weighted spread about it (floored)."""
    hint, has_hint, gate, period = how.hint, how.has_hint, how.gate, how.period
    min_lines, floor = how.min_lines, how.floor
    n_l = p1.shape[0]
    phi = np.empty(n_l)
    w = np.empty(n_l)
    ok = np.zeros(n_l, np.bool_)
    n_ok = 0
    for i in range(n_l):
        l0 = p1[i, 1] - p2[i, 1]
        l1 = p2[i, 0] - p1[i, 0]
        l2 = p1[i, 0] * p2[i, 1] - p1[i, 1] * p2[i, 0]
        m0 = l0 * R[0, 0] + l1 * R[0, 1] + l2 * R[0, 2]
        m1 = l0 * R[1, 0] + l1 * R[1, 1] + l2 * R[1, 2]
        m2 = l0 * R[2, 0] + l1 * R[2, 1] + l2 * R[2, 2]
        inv = 1.0 / max(math.sqrt(m0 * m0 + m1 * m1 + m2 * m2), 1e-300)
        m0, m1 = m0 * inv, m1 * inv
        phi[i] = math.atan2(m0, m1)
        w[i] = (m0 * m0 + m1 * m1) * weights[i]
        ok[i] = math.isfinite(phi[i]) and w[i] > 1e-12
        n_ok += ok[i]
    if n_ok < min_lines:
        return False, 0.0, 0.0, 0, 0.0, 0.0
    ref = hint if has_hint else _circular_mean(phi, w, ok, period)
    if not has_hint:
        sel = ok & (np.abs(_wrap_period(phi - ref, period)) < 3 * gate)
        if sel.sum() >= min_lines:
            ref = _circular_mean(phi, w, sel, period)
    kept[:] = ok & (np.abs(_wrap_period(phi - ref, period)) < gate)
    n = int(kept.sum())
    if n < min_lines:
        return False, 0.0, 0.0, 0, 0.0, 0.0
    yaw = _circular_mean(phi, w, kept, period)
    res = _wrap_period(phi - yaw, period)
    sw = swr = sww = 0.0
    for i in range(n_l):
        if kept[i]:
            sw += w[i]
            sww += w[i] * w[i]
            swr += w[i] * res[i] * res[i]
    sigma = max(math.sqrt(swr / sw / max(n - 1, 1)), floor)
    return True, yaw, sigma, n, sw, sww


@njit
def _circular_mean(phi, w, use, period):  # pragma: no cover - compiled
    """The weighted circular mean of the headings ``phi`` of the lines ``use``, modulo
    the period."""
    k = 2 * math.pi / period
    zr = zi = 0.0
    for i in range(phi.size):
        if use[i]:
            zr += w[i] * math.cos(k * phi[i])
            zi += w[i] * math.sin(k * phi[i])
    return math.atan2(zi, zr) / k


@njit
def _wrap_period(a, period):  # pragma: no cover - compiled
    """``a`` modulo the period, in ``[-period/2, period/2)``."""
    return np.remainder(a + period / 2, period) - period / 2


def _near_hint(h: ParallelsHeading, hint_yaw_rad: float | None) -> ParallelsHeading:
    """``h`` on the branch nearest ``hint_yaw_rad`` (unchanged without a hint)."""
    if hint_yaw_rad is None:
        return h
    yaw = hint_yaw_rad + math.remainder(h.yaw_rad - hint_yaw_rad, h.period_rad)
    return ParallelsHeading(wrap_pi(yaw), h.sigma_rad, h.period_rad, h.n_lines)


@warmer
def _warm_heading() -> None:
    p1 = np.array([[0.0, 0.0], [0.0, 0.1], [0.1, 0.0]])
    robust_heading(p1, p1 + [0.2, 0.0], np.eye(3), None)
    robust_heading(p1, p1 + [0.2, 0.0], np.eye(3), 0.0, weights=np.ones(3))
    segs = np.hstack([p1, p1 + [0.2, 0.0]])
    _stage_heading(arr(segs, np.float64), arr(segs * 100.0, np.float64),
                   arr(np.ones(3, bool), np.bool_), arr(np.eye(3), np.float64),
                   HeadingGate(0.0, True, 0.02, PERIOD_RAD, MIN_LINES, SIGMA_FLOOR_RAD))


# -- the site's lines in the image ------------------------------------------------------
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
                     max_chords: int = MAX_CHORDS, site=None, reach_m: float = REACH_M,
                     mount=None) -> np.ndarray:
    """Pixel chords ``(N, 4)`` along the site's ceiling lines seen from ``pose``, at most
    ``max_chords`` of them spread over the lines (one projection of every sample).
    With ``site``, samples inside its ``ignore`` regions are not used (SPEC §2). One
    compiled call (:func:`chords_core`); the ignore regions' test after it. ``mount``:
    :func:`.ceiling.kernel_mount` of ``geo``, when the caller keeps it."""
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    along = _along(tuple(corridor.lines_along_m))
    a = corridor.lines_across
    first, spacing = (float(a.first_m), float(a.spacing_m)) if a is not None else (0.0, 0.0)
    ignoring = site is not None and bool(site.ignore_m)
    cam = geo.camera
    k = max(1, round(CHORD_M / STEP_M))      # samples a chord spans (k STEP_M metres)
    t = _samples(reach_m)
    chords, li, si, p0, d = chords_core(
        kernel_mount(geo) if mount is None else mount, x, y, yaw,
        SiteLines(along, first, spacing, float(reach_m)),
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
def _warm_chords() -> None:
    from ceilkit.runtime.geometry.camera import CameraModel
    cam = CameraModel.pinhole(64, 48, 40.0)
    geo = PlanarGeometry(cam, np.diag([1.0, -1.0, -1.0]).T.copy(), np.zeros(3), 3.0)

    class _Corridor:
        lines_along_m = (0.0, 0.6)
        lines_across = None
    predicted_chords(geo, _Corridor(), (0.0, 0.0, 0.0))


# -- the heading stage -----------------------------------------------------------------
class ParallelsStage:
    """The heading from a frame's ceiling parallels (see the module).

    Args:
        geo: the rig and ceiling.
        site: the site (its corridor section's lines, its ignore regions).
        min_px: shortest detected segment used as a parallel.
        gate_deg: a line farther than this from the heading (modulo the period) is not
            a parallel of the ceiling's axes.
    """

    def __init__(self, geo: PlanarGeometry, site: Any, min_px: float, gate_deg: float
                 ) -> None:
        self.geo, self.site = geo, site
        self.corridor = site.corridor if site.has_section("corridor") else None
        self.gate_rad = math.radians(gate_deg)
        self.min_px = float(min_px)
        self._detector: SegmentDetector | None = None     # made on first use
        self.ignore = IgnoreRegions(geo, site) if site.ignore_m else None
        self.mode = ""           # how the last heading's lines were found
        self._R = arr(geo.R_vehicle_cam, np.float64)
        self._mount = kernel_mount(geo)

    def __call__(self, grey: np.ndarray, hint: float | None,
                 pose: np.ndarray | None = None, max_chords: int = MAX_CHORDS
                 ) -> ParallelsHeading | None:
        """The heading from ``grey`` ``(H, W)`` uint8, the branch nearest ``hint``
        (radians, or None), the lines predicted from ``pose`` ``(x, y, yaw)`` when
        given (at most ``max_chords`` chords); None with fewer than two lines."""
        segs = np.zeros((0, 4))
        if pose is not None and self.corridor is not None:
            segs = predicted_chords(self.geo, self.corridor, pose, max_chords, self.site,
                                    mount=self._mount)
            mode = "predicted"
        if len(segs) < 2:
            if self._detector is None:
                self._detector = SegmentDetector("fld", self.min_px)
            segs = self._detector(grey)
            mode = "detected"
        if len(segs) < 2:
            return None
        # predicted chords sit within a pixel or two of their line: no wider retry, one
        # compiled call (refine_chords)
        if mode == "predicted":
            sn, _, rms = refine_chords(self.geo.camera, grey, segs)
        else:
            sn, _, rms = refine_undistorted(self.geo.camera, grey, segs)
        good = np.isfinite(rms) if mode == "predicted" else np.ones(len(sn), bool)
        if self.ignore is not None and pose is not None:    # SPEC §2: not in a region
            good &= self.ignore.keep_segments(sn, pose)
        how = HeadingGate(0.0 if hint is None else float(hint), hint is not None,
                          self.gate_rad, PERIOD_RAD, MIN_LINES, SIGMA_FLOOR_RAD)
        found, yaw, sigma, n = _stage_heading(arr(sn, np.float64), arr(segs, np.float64),
                                              arr(good, np.bool_), self._R, how)
        self.mode = mode
        if not found:
            return None
        return _near_hint(ParallelsHeading(wrap_pi(yaw), sigma, PERIOD_RAD, n), hint)


@njit
def _stage_heading(segs_n, segs, good, R, how):  # pragma: no cover - compiled
    """:class:`ParallelsStage`'s heading in one call: :func:`robust_heading` of the lines
    ``segs_n (N, 4)`` (normalized ends) marked ``good (N,)``, weighted by their length
    in ``segs (N, 4)`` (px), picked as ``how`` (a :class:`HeadingGate`) says, its sigma
    times :func:`_few_lines` of the kept lines' weights (eq. 10's ``|m_xy|²`` times
    the length, as :func:`robust_heading` weighs them):
    ``(found, yaw, sigma, n)``, ``yaw`` not yet on the hint's branch."""
    m = 0
    for i in range(good.size):
        m += good[i]
    p1 = np.empty((m, 2))
    p2 = np.empty((m, 2))
    length = np.empty(m)
    j = 0
    for i in range(good.size):
        if good[i]:
            p1[j, 0], p1[j, 1] = segs_n[i, 0], segs_n[i, 1]
            p2[j, 0], p2[j, 1] = segs_n[i, 2], segs_n[i, 3]
            length[j] = math.hypot(segs[i, 2] - segs[i, 0], segs[i, 3] - segs[i, 1])
            j += 1
    kept = np.zeros(m, np.bool_)
    found, yaw, sigma, n, sw, sww = _robust(p1, p2, R, length, how, kept)
    if not found:
        return False, 0.0, 0.0, 0
    return True, yaw, sigma * _few_lines(n, sw, sww), n


@njit
def _few_lines(n, sw, sww):  # pragma: no cover - compiled
    """The factor (>= 1) on :func:`robust_heading`'s sigma (the lines' weighted spread
    over ``n - 1``) for ``n`` lines whose weights sum to ``sw``, their squares to
    ``sww``: the spread of a weighted mean counts ``n_eff = (Σw)² / Σw²`` lines, not
    ``n``, and a spread from ``nu = n_eff - 1`` of them is a Student-t scale:
    ``sqrt((n - 1) / nu * nu / (nu - 2))`` (at most 3 in variance for ``nu`` at most
    3). (The sigma over ``n - 1`` was 1.1-1.5x too small in variance on 17-20 chords,
    bench_ambiguity's tile cases; issue 36.)"""
    if n < 2 or not sw > 0:
        return 1.0
    nu = max(sw * sw / sww - 1.0, 1.0)
    return math.sqrt(max((n - 1) / nu, 1.0) * student(nu))
