"""The edge-profile measurement: where, to sub-pixel, a straight edge lies in an image.

One implementation, used by the corridor method (:func:`.lines.refine_undistorted`,
:func:`.lines.edge_polarity`) and by the mount calibration (``calib.mount.measure_lines``):

1. **profiles**: the image is sampled (bilinear, ``cv2.remap`` or its compiled
   equal :func:`remap_linear`, to grey levels; the border replicated) across a
   segment at signed offsets along its left normal, at places along it
   (:func:`sample_profiles`, :func:`profiles_along`, :func:`profiles_at`);
2. **kind** (:func:`classify`): a mean profile is a *step* (a lamp's side, a wall
   junction: polarity ``+1`` or ``-1``), a *thin line* (a seam, a painted stripe:
   ``0``) or unclear (NaN);
3. **locate** (:func:`locate_steps`, :func:`locate_thin`): on each profile, the step's
   crossing of the middle of its two sides' levels, or the thin line's middle (the
   centroid of its part beyond half its height), within :data:`LOCATE_MARGIN_PX` of the
   profile's ends;
4. **fit** (:func:`fit_lines`, :func:`fit_lines_robust`): total-least-squares lines through
   the located points (the callers undistort them first), one pass dropping outliers.

Convention: a segment ``(u1, v1, u2, v2)`` in pixels (SPEC §1), ``t`` its unit direction
from ``(u1, v1)`` to ``(u2, v2)``, its left normal ``(-t_v, t_u)``; a positive offset is
on the left normal's side. Polarity ``+1``: brighter on that side.

Example::

    offs, t, inner = edge_grid(8, 4.0)
    d, nrm = directions(segs_px)
    prof = profiles_along(gray, segs_px, d, nrm, offs, t)        # (N, 8, 17)
    pol, _ = classify(prof.mean(axis=1), offs, 20.0, 8.0, shift=False)
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.jit import arr, njit, warmer

PROFILE_STEP_PX = 0.5      # spacing of profile samples across a segment
SIDE_PX = 1.0              # a profile's sides: its outer SIDE_PX at either end
THIN_MARGIN_PX = 1.5       # a thin line's dip or bump lies this far inside the profile
LOCATE_MARGIN_PX = 1.0     # an edge is located this far inside the profile's ends
ALONG_RANGE = (0.05, 0.95)  # where along a segment its profiles are taken (fractions)
OUTLIER_SIGMAS = 3.0       # the robust fit drops points beyond this many sigma ...
OUTLIER_FLOOR_PX = 0.5     # ... and beyond this many pixels


def directions(segs_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d, nrm)``: ``p2 - p1`` ``(N, 2)`` and the unit left normal ``(N, 2)`` of
    segments ``(N, 4)``."""
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    d = s[:, 2:] - s[:, :2]
    inv = 1.0 / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    nrm = np.empty_like(d)
    nrm[:, 0] = -d[:, 1] * inv
    nrm[:, 1] = d[:, 0] * inv
    return d, nrm


def profiles_at(gray: np.ndarray, base: np.ndarray, nrm: np.ndarray, offs: np.ndarray
                ) -> np.ndarray:
    """Samples ``(N, A, O)`` at ``base + o nrm``: ``base (2, N, A)`` pixels (u row, v row),
    ``nrm (2, N, A)`` or ``(2, N, 1)`` unit normals, ``offs (O,)`` pixels. ``gray``
    ``(H, W)`` uint8 (rounded samples, fast) or float32."""
    # the u and v maps apart, (2, N, A, O): numpy is slow on a trailing axis of 2
    maps = (base[..., None] + offs * nrm[..., None]).astype(np.float32)
    n, a = base.shape[1], base.shape[2]
    maps = maps.reshape(2, -1, offs.size)
    val = cv2.remap(gray, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return val.reshape(n, a, offs.size).astype(np.float64)


def profiles_along(gray: np.ndarray, segs_px: np.ndarray, d: np.ndarray, nrm: np.ndarray,
                   offs: np.ndarray, along: np.ndarray) -> np.ndarray:
    """:func:`profiles_at` ``(N, A, O)`` at ``p1 + a d`` for the fractions ``along (A,)``
    of segments ``(N, 4)`` (``d, nrm`` from :func:`directions`); of a uint8 frame in one
    compiled call (:func:`remap_along`, the same numbers)."""
    if gray.dtype == np.uint8 and gray.ndim == 2:
        f64 = np.float64
        prof = np.empty((segs_px.shape[0], along.size, offs.size))
        remap_along(arr(gray, np.uint8), arr(segs_px, f64), arr(d, f64), arr(nrm, f64),
                    arr(offs, f64), arr(along, f64), prof)
        return prof
    base = segs_px[:, :2].T[:, :, None] + along * d.T[:, :, None]              # (2, N, A)
    return profiles_at(gray, base, nrm.T[:, :, None], offs)


@njit
def remap_along(grey, s, d, nrm, offs, t, prof):  # pragma: no cover - compiled
    """:func:`profiles_along` of a uint8 frame into ``prof (N, A, O)``: the maps as
    :func:`profiles_at` makes them (in float64, then float32), each sample as
    :func:`remap_linear`."""
    for r in range(s.shape[0]):
        for a in range(t.size):
            bu, bv = s[r, 0] + t[a] * d[r, 0], s[r, 1] + t[a] * d[r, 1]
            for o in range(offs.size):
                prof[r, a, o] = remap_linear(grey, np.float32(bu + offs[o] * nrm[r, 0]),
                                             np.float32(bv + offs[o] * nrm[r, 1]))


@njit
def remap_linear(grey, x, y):  # pragma: no cover - compiled
    """``cv2.remap`` (``INTER_LINEAR``, ``BORDER_REPLICATE``) of a uint8 frame at the
    float32 point ``(x, y)``, as OpenCV 5 computes it: float32 weights ``x - floor(x)``,
    two fused multiply-adds along x and one along y (exact in float64 here: the
    products of these few-bit numbers fit), the tap indices clamped to the frame, the
    result rounded half to even. (Its fixed-point predecessor rounded the weights to
    1/32; this is bit-equal to ``cv2.remap`` where OpenCV dispatches its FMA code.)"""
    h, w = grey.shape
    f32 = np.float32
    # a point far outside reads the edge (its taps clamped), as OpenCV's; clamped first,
    # so that no coordinate overflows the integer floor
    x, y = min(max(x, f32(-1.0)), f32(w)), min(max(y, f32(-1.0)), f32(h))
    x0, y0 = math.floor(x), math.floor(y)
    a, b = np.float64(f32(x - f32(x0))), np.float64(f32(y - f32(y0)))
    xa, xb = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
    ya, yb = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
    p00, p01 = np.float64(grey[ya, xa]), np.float64(grey[ya, xb])
    p10, p11 = np.float64(grey[yb, xa]), np.float64(grey[yb, xb])
    top = f32(a * (p01 - p00) + p00)
    bot = f32(a * (p11 - p10) + p10)
    return np.rint(f32(b * np.float64(f32(bot - top)) + np.float64(top)))


def sample_profiles(gray: np.ndarray, segs_px: np.ndarray, offsets_px: np.ndarray,
                    n_along: int = 8, inset: float = 0.1, mean: bool = True) -> np.ndarray:
    """Intensity profiles across segments.

    Each segment ``(u1, v1, u2, v2)`` is sampled at ``n_along`` points evenly spread
    over its middle (``inset`` of its length left out at each end), at signed distances
    ``offsets_px`` along its left normal; with ``mean`` the samples are averaged along
    the segment.

    Args:
        gray: ``(H, W)`` uint8 (or float32) image.
        segs_px: ``(N, 4)`` segments, pixels.
        offsets_px: ``(O,)`` distances across, pixels.

    Returns:
        ``(N, O)`` float64 mean grey levels, or ``(N, n_along, O)`` without ``mean``.
    """
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    o = np.asarray(offsets_px, dtype=np.float64).ravel()
    if s.shape[0] == 0:
        return np.zeros((0, o.size)) if mean else np.zeros((0, n_along, o.size))
    d, nrm = directions(s)
    val = profiles_along(gray, s, d, nrm, o, np.linspace(inset, 1.0 - inset, n_along))
    return val.sum(axis=1) * (1.0 / n_along) if mean else val


def profile_offsets(half_width_px: float) -> np.ndarray:
    """Profile offsets ``(O,)``: every :data:`PROFILE_STEP_PX` within ``half_width_px``."""
    return np.arange(-half_width_px, half_width_px + 1e-9, PROFILE_STEP_PX)


@functools.lru_cache(maxsize=16)
def edge_grid(n_along: int, half_width_px: float) -> tuple[np.ndarray, np.ndarray, slice]:
    """Constants of one measurement: the profile offsets ``(O,)`` (:func:`profile_offsets`),
    the places along a segment ``(A,)`` (fractions of its length over
    :data:`ALONG_RANGE`) and the slice of ``offs[1:-1]`` within
    ``half_width_px - LOCATE_MARGIN_PX`` (where an edge is located). Read-only arrays.

    Raises:
        ConfigError: naming ``half_width_px`` when it leaves no room to locate an edge.
    """
    offs = profile_offsets(half_width_px)
    t = np.linspace(ALONG_RANGE[0], ALONG_RANGE[1], n_along)
    inner = np.flatnonzero(np.abs(offs[1:-1]) <= half_width_px - LOCATE_MARGIN_PX + 1e-9)
    if inner.size == 0:
        raise ConfigError(None, "half_width_px", f"expected more than {LOCATE_MARGIN_PX} px "
                          f"(room to locate an edge), found {half_width_px}")
    offs.flags.writeable = False
    t.flags.writeable = False
    return offs, t, slice(int(inner[0]), int(inner[-1]) + 1)


# ----------------------------------------------------------------------------- kind
def classify(prof: np.ndarray, offs: np.ndarray, min_step: float, min_depth: float,
             shift: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The kind of edge of mean profiles ``prof (N, O)`` at ``offs (O,)`` (ascending,
    :data:`PROFILE_STEP_PX` apart).

    A **step** when the two sides (the outer :data:`SIDE_PX` of either end) differ by at
    least ``min_step`` grey levels and by more than the depth of any dip or bump
    between them; a **thin line** when the inner part (within
    ``THIN_MARGIN_PX`` of the ends) dips below (or rises above) both sides by at least
    ``min_depth`` and more than the sides differ.

    Returns:
        ``(polarity, shift_px)`` ``(N,)``: polarity ``+1`` (brighter on the positive
        side), ``-1``, ``0`` (a thin line) or NaN (unclear); ``shift_px`` the thin line's
        centre (the sub-pixel extremum, a parabola), NaN unless a thin line; None
        unless ``shift``.
    """
    n = prof.shape[0]
    if n == 0:
        return np.full(n, np.nan), (np.full(n, np.nan) if shift else None)
    il, ir, ii = part_indices(offs)
    pol, out = classify_rows(arr(prof, np.float64), arr(offs, np.float64), arr(il, np.int64),
                             arr(ir, np.int64), arr(ii, np.int64), float(min_step),
                             float(min_depth), PROFILE_STEP_PX)
    return pol, (out if shift else None)


@njit
def classify_rows(prof, offs, il, ir, ii, min_step, min_depth, step_px
              ):  # pragma: no cover - compiled
    """:func:`classify` of ``prof (N, O)``, the parts' indices from
    :func:`part_indices`: ``(polarity (N,), shift (N,))``."""
    n = prof.shape[0]
    m = ii.size
    pol = np.full(n, np.nan)
    out = np.full(n, np.nan)
    for r in range(n):
        left = 0.0
        for i in il:
            left += prof[r, i]
        left /= il.size
        right = 0.0
        for i in ir:
            right += prof[r, i]
        right /= ir.size
        step = right - left
        k_lo = k_hi = 0
        lo = hi = prof[r, ii[0]]
        for j in range(1, m):
            v = prof[r, ii[j]]
            if v < lo:
                lo, k_lo = v, j
            if v > hi:
                hi, k_hi = v, j
        dip = min(left, right) - lo
        bump = hi - max(left, right)
        if dip >= bump:
            depth, k = dip, k_lo
        else:
            depth, k = bump, k_hi
        a_step = abs(step)
        if depth >= min_depth and depth > a_step and 0 < k < m - 1:
            pol[r] = 0.0
            out[r] = offs[ii[k]] + step_px * _vertex(prof[r, ii[k - 1]], prof[r, ii[k]],
                                                     prof[r, ii[k + 1]])
        elif a_step >= min_step and a_step > max(depth, 0.0):
            pol[r] = np.sign(step)
    return pol, out


@njit
def _vertex(y0, y1, y2):  # pragma: no cover - compiled
    """:func:`vertex` of three numbers."""
    den = y0 - 2.0 * y1 + y2
    if abs(den) > 1e-9:
        return min(max(0.5 * (y0 - y2) / den, -1.0), 1.0)
    return 0.0


def part_indices(offs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`profile_parts`' left, right and inner parts as index arrays (int64)."""
    return _part_indices_of(offs.tobytes())


@functools.lru_cache(maxsize=64)
def _part_indices_of(offs_bytes: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    offs = np.frombuffer(offs_bytes, dtype=np.float64)
    idx = np.arange(offs.size)
    out = tuple(np.ascontiguousarray(idx[p], np.int64) for p in _profile_parts(offs_bytes)[:3])
    for a in out:
        a.flags.writeable = False
    return out


def profile_parts(offs: np.ndarray) -> tuple:
    """For profile offsets ``offs (O,)`` (pixels): the indices (a slice where they are
    consecutive) of the left side and the right side (the outer :data:`SIDE_PX` of either
    end) and of the inner part (``|offset| <= half - THIN_MARGIN_PX``, ``half =
    offs[-1]``), and one over the number of samples on the left and on the right.
    Cached per ``offs``."""
    return _profile_parts(offs.tobytes())


@functools.lru_cache(maxsize=64)
def _profile_parts(offs_bytes: bytes) -> tuple:
    offs = np.frombuffer(offs_bytes, dtype=np.float64)
    half = float(offs[-1])
    side = np.abs(offs) >= half - SIDE_PX + 1e-9
    il = np.flatnonzero(side & (offs < 0))
    ir = np.flatnonzero(side & (offs > 0))
    ii = np.flatnonzero(np.abs(offs) <= half - THIN_MARGIN_PX + 1e-9)

    def run(idx: np.ndarray) -> slice | np.ndarray:
        if idx.size and np.all(np.diff(idx) == 1):
            return slice(int(idx[0]), int(idx[-1]) + 1)
        return idx

    return run(il), run(ir), run(ii), 1.0 / il.size, 1.0 / ir.size


def vertex(y0: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Sub-sample offset in [-1, 1] of the parabola's vertex through three samples."""
    den = y0 - 2 * y1 + y2
    safe = np.where(np.abs(den) > 1e-9, den, 1.0)
    return np.clip(np.where(np.abs(den) > 1e-9, 0.5 * (y0 - y2) / safe, 0.0), -1.0, 1.0)


# ----------------------------------------------------------------------------- locate
def locate_steps(prof: np.ndarray, polarity: np.ndarray, offs: np.ndarray, inner: slice
                 ) -> np.ndarray:
    """Offsets ``(S, A)`` (px, NaN where not found) of step edges on profiles
    ``prof (S, A, O)`` of polarity ``(S,)`` (``+-1``), ``inner`` from :func:`edge_grid`.

    The edge is where the profile crosses the middle of its two sides' levels (its two
    outer samples at either end), the crossing nearest the derivative's peak (less
    locked to the pixel grid than a parabola), within the inner part."""
    return locate(prof, polarity, offs, inner)


def thin_sign(prof: np.ndarray, inner: slice) -> tuple[np.ndarray, np.ndarray]:
    """``(sign, side)`` ``(S,)``: ``-1`` where the thin lines of profiles ``prof (S, A, O)``
    are darker than their sides (a valley, a dark seam), ``+1`` where brighter (a bump);
    the sides' mean level (the two outermost samples)."""
    i0, i1 = inner.start + 1, inner.stop + 1
    inv_a = 1.0 / prof.shape[1]
    side = 0.5 * (prof[:, :, 0] + prof[:, :, -1]).sum(axis=1) * inv_a
    inner_p = prof[:, :, i0:i1]
    valley = (side - inner_p.min(axis=2).sum(axis=1) * inv_a
              >= inner_p.max(axis=2).sum(axis=1) * inv_a - side)
    return np.where(valley, -1.0, 1.0), side


def locate_thin(prof: np.ndarray, offs: np.ndarray, inner: slice) -> np.ndarray:
    """Offsets ``(S, A)`` (px, NaN where not found) of the middles of thin lines on
    profiles ``prof (S, A, O)``: the centroid of the line's part beyond half its height
    (over its sides), within the inner part; not found where the extremum is at the
    inner part's end."""
    return locate(prof, np.zeros(prof.shape[0]), offs, inner)


def locate(prof: np.ndarray, polarity: np.ndarray, offs: np.ndarray, inner: slice
           ) -> np.ndarray:
    """Edge offsets ``(S, A)`` (px, NaN where not found) on profiles ``prof (S, A, O)``
    of segments of known kind ``polarity (S,)`` (``+-1`` steps, ``0`` thin lines, NaN
    not located): :func:`locate_steps` and :func:`locate_thin`."""
    out = np.full(prof.shape[:2], np.nan)
    locate_rows(arr(prof, np.float64), arr(polarity, np.float64), arr(offs, np.float64),
                inner.start + 1, inner.stop + 1, PROFILE_STEP_PX, out)
    return out


@njit
def locate_rows(prof, pol, offs, i0, i1, step_px, out):  # pragma: no cover - compiled
    """:func:`locate` into ``out (S, A)`` (left NaN where not located): the inner part
    is ``offs[i0:i1]``."""
    n_s, n_a, n_o = prof.shape
    o_max = offs[i1 - 1]
    m = i1 - i0
    for s in range(n_s):
        p = pol[s]
        if abs(p) == 1.0:
            for a in range(n_a):
                g = prof[s, a]
                mid = 0.25 * p * (g[0] + g[1] + g[n_o - 2] + g[n_o - 1])
                k, best = i0, -np.inf
                for j in range(i0, i1):
                    d = p * (g[j + 1] - g[j - 1])
                    if d > best:
                        k, best = j, d
                hm, hk, hp = p * g[k - 1] - mid, p * g[k] - mid, p * g[k + 1] - mid
                if hk > 0:
                    h0, h1, kk = hm, hk, k - 1
                else:
                    h0, h1, kk = hk, hp, k
                o = offs[kk] + step_px * (-h0) / (h1 - h0 if h1 > h0 else 1.0)
                if h0 <= 0 and h1 > 0 and abs(o) <= o_max:
                    out[s, a] = o
        elif p == 0.0:
            # a valley (dark line) or a bump, from the mean of its sides and extremes
            side = lo = hi = 0.0
            for a in range(n_a):
                g = prof[s, a]
                side += 0.5 * (g[0] + g[n_o - 1])
                mn = mx = g[i0]
                for j in range(i0 + 1, i1):
                    mn = min(mn, g[j])
                    mx = max(mx, g[j])
                lo += mn
                hi += mx
            side /= n_a
            sgn = -1.0 if side - lo / n_a >= hi / n_a - side else 1.0
            for a in range(n_a):
                g = prof[s, a]
                top, k_pk = -np.inf, 0
                for j in range(m):
                    v = sgn * g[i0 + j]
                    if v > top:
                        top, k_pk = v, j
                level = 0.5 * (sgn * side + top)
                sw = swo = 0.0
                for j in range(m):
                    w = sgn * g[i0 + j] - level
                    if w > 0.0:
                        sw += w
                        swo += w * offs[i0 + j]
                if sw > 0 and 0 < k_pk < m - 1:
                    out[s, a] = swo / max(sw, 1e-12)


# ----------------------------------------------------------------------------- fit
def fit_lines(x: np.ndarray, y: np.ndarray, w: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares lines through points with coordinates ``x, y (N, A)``, those
    with ``w (N, A)`` True: ``(lines, res, n, ssr)``, the lines ``(N, 3)``
    (``|(a, b)| = 1``), the points' signed residuals ``(N, A)``, how many points
    ``(N,)`` (float) and the sum of their squared residuals ``(N,)``."""
    x, y, w = arr(x, np.float64), arr(y, np.float64), arr(w, np.bool_)
    line, res, n, ssr = _empty_fits(x.shape)
    _fit_rows(x, y, w, line, res, n, ssr)
    return line, res, n, ssr


class RowFits(NamedTuple):
    """The arrays a row-by-row line fit writes (:func:`fit_robust_rows`): the lines
    ``line (N, 3)``, the residuals ``res (N, A)``, the points' count ``cnt (N,)``
    (float) and the sum of their squared residuals ``ssr (N,)``."""

    line: np.ndarray
    res: np.ndarray
    cnt: np.ndarray
    ssr: np.ndarray


def _empty_fits(shape: tuple[int, int]) -> RowFits:
    return RowFits(np.empty((shape[0], 3)), np.empty(shape), np.empty(shape[0]),
                   np.empty(shape[0]))


@njit
def _fit_row(x, y, w, line, res, cnt, ssr, r):  # pragma: no cover - compiled
    """The total-least-squares line of one row's points ``x, y, w (A,)`` into ``line
    (3,)``, ``res (A,)``, ``cnt[r]``, ``ssr[r]`` (:func:`fit_lines`)."""
    n = sx = sy = 0.0
    for i in range(x.size):
        if w[i]:
            n += 1.0
            sx += x[i]
            sy += y[i]
    sw = max(n, 1e-12)
    cx, cy = sx / sw, sy / sw
    sxx = syy = sxy = 0.0
    for i in range(x.size):
        if w[i]:
            dx, dy = x[i] - cx, y[i] - cy
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    th = 0.5 * math.atan2(2.0 * sxy, sxx - syy)          # direction of the major axis
    a, b = -math.sin(th), math.cos(th)
    c = -(a * cx + b * cy)
    line[0], line[1], line[2] = a, b, c
    q = 0.0
    for i in range(x.size):
        res[i] = x[i] * a + y[i] * b + c
        if w[i]:
            q += res[i] * res[i]
    cnt[r] = n
    ssr[r] = q


@njit
def _fit_rows(x, y, w, line, res, cnt, ssr):  # pragma: no cover - compiled
    """:func:`_fit_row` of every row."""
    for r in range(x.shape[0]):
        _fit_row(x[r], y[r], w[r], line[r], res[r], cnt, ssr, r)


@njit
def fit_robust_rows(x, y, good, floor, sigmas, fits):  # pragma: no cover - compiled
    """:func:`fit_lines_robust` row by row into ``fits`` (a :class:`RowFits`), the
    points beyond ``sigmas`` sigma and ``floor`` (normalized units) dropped once;
    ``good`` becomes the points kept."""
    line, res, cnt, ssr = fits
    for r in range(x.shape[0]):
        _fit_row(x[r], y[r], good[r], line[r], res[r], cnt, ssr, r)
        lim = max(sigmas * math.sqrt(ssr[r] / max(cnt[r], 1.0)), floor)
        dropped = False
        for i in range(x.shape[1]):
            if good[r, i] and not abs(res[r, i]) <= lim:
                good[r, i] = False
                dropped = True
        if dropped:
            _fit_row(x[r], y[r], good[r], line[r], res[r], cnt, ssr, r)


def fit_lines_robust(x: np.ndarray, y: np.ndarray, good: np.ndarray, f_px: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_lines` of undistorted points ``x, y (N, A)`` (those ``good``), then once
    more without the points beyond :data:`OUTLIER_SIGMAS` sigma and
    :data:`OUTLIER_FLOOR_PX` (``f_px``: pixels per normalized unit). Returns ``(lines,
    res, n, ssr, kept)`` (``kept (N, A)``: the points of the final fit)."""
    x, y = arr(x, np.float64), arr(y, np.float64)
    good = np.array(good, np.bool_, order="C")
    fits = _empty_fits(x.shape)
    fit_robust_rows(x, y, good, OUTLIER_FLOOR_PX / f_px, OUTLIER_SIGMAS, fits)
    return (*fits, good)


@warmer
def _warm() -> None:
    offs, t, inner = edge_grid(4, 4.0)
    prof = np.tile(np.where(offs > 0, 200.0, 50.0), (2, t.size, 1))
    pol, _ = classify(prof.mean(axis=1), offs, 20.0, 8.0)
    locate(prof, pol, offs, inner)
    x = np.tile(np.arange(6.0), (2, 1))
    segs = np.array([[1.0, 1.0, 4.0, 4.0]])
    d, nrm = directions(segs)
    profiles_along(np.zeros((6, 6), np.uint8), segs, d, nrm, offs, t)
    fit_lines(x, x, np.ones(x.shape, bool))
    fit_lines_robust(x, x, np.ones(x.shape, bool), 500.0)


__all__ = ["RowFits", "classify", "classify_rows", "directions", "edge_grid", "fit_lines",
           "fit_lines_robust", "fit_robust_rows", "locate", "locate_rows", "part_indices",
           "locate_steps", "locate_thin", "profile_offsets", "profile_parts", "profiles_along",
           "profiles_at", "sample_profiles", "thin_sign", "vertex"]
