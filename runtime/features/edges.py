"""The edge-profile measurement: where, to sub-pixel, a straight edge lies in an image.

One implementation, used by the corridor method (:func:`.lines.refine_undistorted`,
:func:`.lines.edge_polarity`) and by the mount calibration (``calib.mount.measure_lines``):

1. **profiles**: the image is sampled (bilinear, ``cv2.remap``, to 1/32 px; the border
   replicated) across a segment at signed offsets along its left normal, at places along
   it (:func:`sample_profiles`, :func:`profiles_along`, :func:`profiles_at`);
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

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError

PROFILE_STEP_PX = 0.5      # spacing of profile samples across a segment
SIDE_PX = 1.0              # a profile's sides: its outer SIDE_PX at either end
THIN_MARGIN_PX = 1.5       # a thin line's dip or bump lies this far inside the profile
LOCATE_MARGIN_PX = 1.0     # an edge is located this far inside the profile's ends
ALONG_RANGE = (0.05, 0.95)  # where along a segment its profiles are taken (fractions)
OUTLIER_SIGMAS = 3.0       # the robust fit drops points beyond this many sigma ...
OUTLIER_FLOOR_PX = 0.5     # ... and beyond this many pixels
_NEIGHBOURS = np.array([-1, 0, 1])


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
    of segments ``(N, 4)`` (``d, nrm`` from :func:`directions`)."""
    base = segs_px[:, :2].T[:, :, None] + along * d.T[:, :, None]              # (2, N, A)
    return profiles_at(gray, base, nrm.T[:, :, None], offs)


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
    sl, sr, inner, inv_l, inv_r = profile_parts(offs)
    left = prof[:, sl].sum(axis=1) * inv_l
    right = prof[:, sr].sum(axis=1) * inv_r
    step = right - left
    pin = np.ascontiguousarray(prof[:, inner])
    k_lo = np.argmin(pin, axis=1)
    k_hi = np.argmax(pin, axis=1)
    dip = np.minimum(left, right) - pin.min(axis=1)
    bump = pin.max(axis=1) - np.maximum(left, right)
    valley = dip >= bump
    depth = np.where(valley, dip, bump)
    k = np.where(valley, k_lo, k_hi)
    a_step = np.abs(step)
    thin = (depth >= min_depth) & (depth > a_step) & (k > 0) & (k < pin.shape[1] - 1)
    is_step = (a_step >= min_step) & (a_step > np.maximum(depth, 0.0))
    pol = np.where(thin, 0.0, np.where(is_step, np.sign(step), np.nan))
    if not shift:
        return pol, None
    out = np.full(n, np.nan)
    r = np.flatnonzero(thin)
    if r.size:
        kk = k[r]
        out[r] = offs[inner][kk] + PROFILE_STEP_PX * vertex(pin[r, kk - 1], pin[r, kk],
                                                             pin[r, kk + 1])
    return pol, out


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
    i0, i1 = inner.start + 1, inner.stop + 1     # the inner part, in offs
    o_max = offs[1:-1][inner][-1]
    gs = prof * polarity[:, None, None]                      # rises across the step
    mid = gs[:, :, [0, 1, -2, -1]].sum(axis=2) * 0.25        # the two sides' middle
    k = np.argmax(gs[:, :, i0 + 1:i1 + 1] - gs[:, :, i0 - 1:i1 - 1], axis=2) + i0
    # the samples at k - 1, k, k + 1 by flat indices (np.take_along_axis's own index
    # building costs more than the gather on these small arrays)
    o_n = gs.shape[2]
    flat = (np.arange(k.size) * o_n + k.ravel())[:, None] + _NEIGHBOURS
    near = gs.reshape(-1)[flat].reshape(*k.shape, 3) - mid[:, :, None]
    hm, hk, hp = near[:, :, 0], near[:, :, 1], near[:, :, 2]    # at k - 1, k, k + 1
    # the crossing is in [k - 1, k] or [k, k + 1] (the derivative peaks at k)
    lo = hk > 0
    h0 = np.where(lo, hm, hk)
    h1 = np.where(lo, hk, hp)
    o = offs[k - lo] + PROFILE_STEP_PX * (-h0) / np.where(h1 > h0, h1 - h0, 1.0)
    ok = (h0 <= 0) & (h1 > 0) & (np.abs(o) <= o_max)
    return np.where(ok, o, np.nan)


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
    i0, i1 = inner.start + 1, inner.stop + 1
    o_in = offs[1:-1][inner]
    sgn, side = thin_sign(prof, inner)
    gt = prof[:, :, i0:i1] * sgn[:, None, None]               # peaks on the line
    top = gt.max(axis=2, keepdims=True)
    w = np.maximum(gt - 0.5 * ((sgn * side)[:, None, None] + top), 0.0)
    sw = w.sum(axis=2)
    o = (w * o_in).sum(axis=2) / np.maximum(sw, 1e-12)
    k_pk = np.argmax(gt, axis=2)
    ok = (sw > 0) & (k_pk > 0) & (k_pk < o_in.size - 1)
    return np.where(ok, o, np.nan)


def locate(prof: np.ndarray, polarity: np.ndarray, offs: np.ndarray, inner: slice
           ) -> np.ndarray:
    """Edge offsets ``(S, A)`` (px, NaN where not found) on profiles ``prof (S, A, O)``
    of segments of known kind ``polarity (S,)`` (``+-1`` steps, ``0`` thin lines, NaN
    not located): :func:`locate_steps` and :func:`locate_thin`."""
    loc = np.full(prof.shape[:2], np.nan)
    st = np.abs(polarity) == 1.0
    th = polarity == 0.0
    if np.any(st):
        loc[st] = locate_steps(prof[st], polarity[st], offs, inner)
    if np.any(th):
        loc[th] = locate_thin(prof[th], offs, inner)
    return loc


# ----------------------------------------------------------------------------- fit
def fit_lines(x: np.ndarray, y: np.ndarray, w: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares lines through points with coordinates ``x, y (N, A)``, those
    with ``w (N, A)`` True: ``(lines, res, n, ssr)``, the lines ``(N, 3)``
    (``|(a, b)| = 1``), the points' signed residuals ``(N, A)``, how many points
    ``(N,)`` (float) and the sum of their squared residuals ``(N,)``."""
    wf = w.astype(np.float64)
    n = wf.sum(axis=1)
    sw = np.maximum(n, 1e-12)
    cx = (wf * x).sum(axis=1) / sw
    cy = (wf * y).sum(axis=1) / sw
    dx = x - cx[:, None]
    dy = y - cy[:, None]
    wdx = wf * dx
    sxx = (wdx * dx).sum(axis=1)
    syy = (wf * dy * dy).sum(axis=1)
    sxy = (wdx * dy).sum(axis=1)
    th = 0.5 * np.arctan2(2 * sxy, sxx - syy)          # direction of the major axis
    a, b = -np.sin(th), np.cos(th)
    line = np.empty((a.size, 3))
    line[:, 0] = a
    line[:, 1] = b
    line[:, 2] = -(a * cx + b * cy)
    res = x * a[:, None] + y * b[:, None] + line[:, 2:3]
    return line, res, n, ((wf * res) * res).sum(axis=1)


def fit_lines_robust(x: np.ndarray, y: np.ndarray, good: np.ndarray, f_px: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_lines` of undistorted points ``x, y (N, A)`` (those ``good``), then once
    more without the points beyond :data:`OUTLIER_SIGMAS` sigma and
    :data:`OUTLIER_FLOOR_PX` (``f_px``: pixels per normalized unit). Returns ``(lines,
    res, n, ssr, kept)`` (``kept (N, A)``: the points of the final fit)."""
    line, res, cnt, ssr = fit_lines(x, y, good)
    sig = np.sqrt(ssr / np.maximum(cnt, 1))
    keep = good & (np.abs(res) <= np.maximum(OUTLIER_SIGMAS * sig,
                                             OUTLIER_FLOOR_PX / f_px)[:, None])
    if (keep != good).any():
        good = keep
        line, res, cnt, ssr = fit_lines(x, y, good)
    return line, res, cnt, ssr, good


__all__ = ["classify", "directions", "edge_grid", "fit_lines", "fit_lines_robust", "locate",
           "locate_steps", "locate_thin", "profile_offsets", "profile_parts", "profiles_along",
           "profiles_at", "sample_profiles", "thin_sign", "vertex"]
