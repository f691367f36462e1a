"""Line segments: detection, sub-pixel refinement, undistortion, homogeneous lines.

Convention: a set of segments is a float64 array ``(N, 4)`` of endpoints
``(u1, v1, u2, v2)`` in pixels (SPEC §1: origin at the centre of the top-left
pixel), or of ``(x1, y1, x2, y2)`` in undistorted normalized coordinates after
:func:`undistort_segments`. A homogeneous line ``l = (a, b, c)`` holds the points
``(x, y)`` with ``a x + b y + c = 0``; :func:`segment_lines` scales it so that
``hypot(a, b) = 1`` (then ``l . (x, y, 1)`` is a signed distance).

Only segment endpoints are undistorted, never whole images.

Example::

    segs_px = detect_segments(gray)                 # (N, 4) pixels
    segs_px = refine_segments(gray, segs_px)         # sub-pixel edge fit
    segs_n = undistort_segments(camera, segs_px)     # (N, 4) normalized
    lines = segment_lines(segs_n)                    # (N, 3), unit normals
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry.camera import CameraModel

DETECTORS = ("fld", "lsd", "hough")


def segment_lengths(segs: np.ndarray) -> np.ndarray:
    """Lengths ``(N,)`` of segments ``(N, 4)``, in their own units."""
    s = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    return np.hypot(s[:, 2] - s[:, 0], s[:, 3] - s[:, 1])


class SegmentDetector:
    """A reusable line-segment detector on 8-bit grey images.

    Args:
        method: ``fld`` (cv2.ximgproc FastLineDetector), ``lsd`` (cv2 LSD) or
            ``hough`` (Canny + probabilistic Hough).
        min_length_px: shortest segment kept, pixels.
        canny: ``(low, high)`` hysteresis thresholds for ``fld`` and ``hough``.
        rows: ``(v0, v1)``: detect only in image rows ``v0 <= v < v1`` (a region of
            interest, e.g. where the ceiling can be); segments keep full-image pixel
            coordinates. None: the whole image.
        merge: ``fld`` merges collinear pieces (OpenCV's ``do_merge``; default True).
    """

    def __init__(self, method: str = "fld", min_length_px: float = 20.0,
                 canny: tuple[float, float] = (40.0, 100.0),
                 rows: tuple[int, int] | None = None, merge: bool = True) -> None:
        if method not in DETECTORS:
            raise ConfigError(None, "detector",
                              f"expected one of {', '.join(DETECTORS)}, found {method!r}")
        self.method = method
        self.min_length_px = float(min_length_px)
        self.canny = (float(canny[0]), float(canny[1]))
        self.rows = None if rows is None else (max(0, int(rows[0])), int(rows[1]))
        if method == "fld":
            self._det = cv2.ximgproc.createFastLineDetector(
                int(max(5, min_length_px * 0.5)), 1.414, self.canny[0], self.canny[1], 3,
                bool(merge))
        elif method == "lsd":
            self._det = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        else:
            self._det = None

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Segments ``(N, 4)`` in pixels, at least ``min_length_px`` long."""
        v0 = 0
        if self.rows is not None:
            v0 = min(self.rows[0], gray.shape[0])
            gray = gray[v0:max(v0, self.rows[1])]
            if gray.shape[0] < 2:
                return np.zeros((0, 4))
        if self.method == "hough":
            edges = cv2.Canny(gray, self.canny[0], self.canny[1], L2gradient=True)
            found = cv2.HoughLinesP(edges, 1.0, np.pi / 720, 30,
                                    minLineLength=self.min_length_px, maxLineGap=3)
        else:
            found = self._det.detect(gray)
            if isinstance(found, tuple):
                found = found[0]
        if found is None or len(found) == 0:
            return np.zeros((0, 4))
        segs = np.asarray(found, dtype=np.float64).reshape(-1, 4)
        if v0:
            segs[:, 1::2] += v0
        return segs[segment_lengths(segs) >= self.min_length_px]


def detect_segments(gray: np.ndarray, method: str = "fld",
                    min_length_px: float = 20.0) -> np.ndarray:
    """One-off detection: see :class:`SegmentDetector`. Returns ``(N, 4)`` pixels."""
    return SegmentDetector(method, min_length_px)(to_grey(gray))


def fit_line(points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted total-least-squares line ``(a, b, c)``, ``|(a, b)| = 1``, of points ``(N, 2)``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = w.sum()
    c = (w[:, None] * p).sum(axis=0) / sw
    d = p - c
    S = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0)
    _, vecs = np.linalg.eigh(S)
    n = vecs[:, 0]
    return np.array([n[0], n[1], -n @ c])


def refine_segments(gray: np.ndarray, segs_px: np.ndarray, half_width_px: float = 2.5,
                    step_px: float = 1.0, inset_px: float = 3.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel refinement: fit each segment's line to gradient-weighted edge points.

    Along each segment (``inset_px`` in from both ends, every ``step_px``) the
    intensity is sampled across it at offsets up to ``half_width_px``; the edge point
    is the centroid of the derivative's peak, weighted by its strength. The
    endpoints are projected onto the weighted total-least-squares line.

    Args:
        gray: ``(H, W)`` uint8 image.
        segs_px: ``(N, 4)`` segments in pixels.

    Returns:
        ``(segs, rms)``: refined ``(N, 4)`` segments (a segment whose fit fails is
        returned unchanged) and ``(N,)`` RMS of the edge points about their line, px
        (NaN where the fit failed).
    """
    segs = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4).copy()
    n = segs.shape[0]
    rms = np.full(n, np.nan)
    if n == 0:
        return segs, rms
    p1, p2 = segs[:, :2], segs[:, 2:]
    d = p2 - p1
    length = np.hypot(d[:, 0], d[:, 1])
    t_hat = d / np.maximum(length, 1e-9)[:, None]
    nrm = np.stack([-t_hat[:, 1], t_hat[:, 0]], axis=1)
    offs = np.arange(-half_width_px - 1.0, half_width_px + 1.0 + 1e-9, 0.5)
    counts = np.maximum(((length - 2 * inset_px) / step_px).astype(int) + 1, 0)
    ok = counts >= 4
    if not np.any(ok):
        return segs, rms
    idx = np.repeat(np.arange(n)[ok], counts[ok])
    start = np.concatenate([[0], np.cumsum(counts[ok])[:-1]])
    k = np.arange(idx.size) - np.repeat(start, counts[ok])
    s_along = inset_px + k * step_px
    base = p1[idx] + t_hat[idx] * s_along[:, None]                       # (K, 2)
    pts = base[:, None, :] + offs[None, :, None] * nrm[idx][:, None, :]  # (K, O, 2)
    mx = pts[..., 0].astype(np.float32)
    my = pts[..., 1].astype(np.float32)
    prof = cv2.remap(gray.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    der = prof[:, 2:] - prof[:, :-2]                                    # (K, O-2)
    so = offs[1:-1]
    pol = np.sign(np.bincount(idx, weights=der.sum(axis=1), minlength=n))[idx]
    g = der * pol[:, None]
    central = np.abs(so) <= half_width_px
    g = np.where(central[None, :], g, -np.inf)
    peak = np.argmax(g, axis=1)
    win = np.abs(np.arange(so.size)[None, :] - peak[:, None]) <= 2
    gw = np.where(win & np.isfinite(g), np.maximum(g, 0.0), 0.0)
    mass = gw.sum(axis=1)
    good = mass > 1e-6
    loc = np.where(good, (gw * so[None, :]).sum(axis=1) / np.maximum(mass, 1e-12), 0.0)
    edge = base + loc[:, None] * nrm[idx]
    for i in np.flatnonzero(ok):
        sel = (idx == i) & good
        if np.count_nonzero(sel) < 4:
            continue
        w = mass[sel]
        line = fit_line(edge[sel], w)
        res = edge[sel] @ line[:2] + line[2]
        # one robust pass: drop points far from the first fit
        keep = np.abs(res) <= max(3.0 * np.sqrt(np.average(res ** 2, weights=w)), 0.3)
        if np.count_nonzero(keep) >= 4:
            line = fit_line(edge[sel][keep], w[keep])
            res = edge[sel][keep] @ line[:2] + line[2]
        rms[i] = float(np.sqrt(np.mean(res ** 2)))
        for j in (0, 2):
            q = segs[i, j:j + 2]
            segs[i, j:j + 2] = q - (q @ line[:2] + line[2]) * line[:2]
    return segs, rms


def sample_profiles(gray: np.ndarray, segs_px: np.ndarray, offsets_px: np.ndarray,
                    n_along: int = 8, inset: float = 0.1, mean: bool = True) -> np.ndarray:
    """Mean intensity profiles across segments.

    Each segment ``(u1, v1, u2, v2)`` is sampled (bilinear by ``cv2.remap``, to 1/32
    px; the border replicated) at ``n_along`` points evenly spread over its middle
    (``inset`` of its length left out at each end), at signed distances ``offsets_px``
    along its left normal
    ``(-t_v, t_u)`` (``t`` the unit direction from ``(u1, v1)`` to ``(u2, v2)``); with
    ``mean`` the samples are averaged along the segment.

    Args:
        gray: ``(H, W)`` uint8 (or float) image.
        segs_px: ``(N, 4)`` segments, pixels.
        offsets_px: ``(O,)`` distances across, pixels.

    Returns:
        ``(N, O)`` float64 mean grey levels, or ``(N, n_along, O)`` without ``mean``.
    """
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    o = np.asarray(offsets_px, dtype=np.float64).ravel()
    if s.shape[0] == 0:
        return np.zeros((0, o.size)) if mean else np.zeros((0, n_along, o.size))
    d, nrm = _directions(s)
    val = _profiles(gray, s, d, nrm, o, np.linspace(inset, 1.0 - inset, n_along))
    return val.sum(axis=1) * (1.0 / n_along) if mean else val


def _directions(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d, nrm)``: ``p2 - p1`` ``(N, 2)`` and the unit left normal ``(N, 2)``."""
    d = s[:, 2:] - s[:, :2]
    inv = 1.0 / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    nrm = np.empty_like(d)
    nrm[:, 0] = -d[:, 1] * inv
    nrm[:, 1] = d[:, 0] * inv
    return d, nrm


def _profiles(gray: np.ndarray, s: np.ndarray, d: np.ndarray, nrm: np.ndarray,
              o: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Samples ``(N, A, O)`` at ``p1 + a d + o nrm`` (bilinear, ``cv2.remap``)."""
    # the u and v maps apart, (2, N, A, O): numpy is slow on a trailing axis of 2
    base = s[:, :2].T[:, :, None] + a * d.T[:, :, None]                          # (2, N, A)
    maps = (base[..., None] + o * nrm.T[:, :, None, None]).astype(np.float32)
    maps = maps.reshape(2, -1, o.size)
    val = cv2.remap(gray, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return val.reshape(s.shape[0], a.size, o.size).astype(np.float64)


def edge_polarity(gray: np.ndarray, segs_px: np.ndarray, min_step: float = 20.0,
                  min_depth: float = 8.0, half_width_px: float = 4.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """What kind of edge each segment lies on, and where a thin line's centre is.

    The mean profile across each segment (:func:`sample_profiles`, offsets up to
    ``half_width_px`` every 0.5 px) is a **step** when its two sides (the outer 1 px
    of either end) differ by at least ``min_step`` grey levels and by more than the
    depth of any dip or bump between them; a **thin line** (a seam, a painted stripe)
    when the inner part (``|offset| <= half_width_px - 1.5``) dips below (or rises
    above) both sides by at least ``min_depth`` and more than the sides differ.
    Line detectors put a thin line's segments on one of its two edges; the centre is
    the sub-pixel extremum (parabola) of the profile.

    Args:
        gray: ``(H, W)`` uint8 image.
        segs_px: ``(N, 4)`` segments in pixels.

    Returns:
        ``(polarity, shift_px)``, both ``(N,)``: polarity ``+1`` (brighter on the left
        normal's side, see :func:`sample_profiles`), ``-1`` (brighter on the other
        side), ``0`` (a thin line) or NaN (neither: weak or unclear); shift_px the
        thin line's centre along the left normal, px (NaN unless a thin line).

    Example::

        pol, shift = edge_polarity(gray, segs_px)
        segs_px = shift_segments(segs_px, np.nan_to_num(shift))
    """
    offs = np.arange(-half_width_px, half_width_px + 1e-9, 0.5)
    prof = sample_profiles(gray, segs_px, offs)
    return _classify_profiles(prof, offs, min_step, min_depth)


def _classify_profiles(prof: np.ndarray, offs: np.ndarray, min_step: float,
                       min_depth: float, shift: bool = True
                       ) -> tuple[np.ndarray, np.ndarray | None]:
    """``(polarity, shift_px)`` of mean profiles ``(N, O)`` at ``offs (O,)`` (step 0.5,
    ascending); ``shift_px`` is None unless ``shift``."""
    n = prof.shape[0]
    if n == 0:
        return np.full(n, np.nan), (np.full(n, np.nan) if shift else None)
    sl, sr, inner, inv_l, inv_r = _profile_parts(offs)
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
        out[r] = offs[inner][kk] + 0.5 * _vertex(pin[r, kk - 1], pin[r, kk], pin[r, kk + 1])
    return pol, out


_PARTS: dict[bytes, tuple] = {}


def _profile_parts(offs: np.ndarray) -> tuple:
    """For profile offsets ``offs (O,)`` (pixels): the indices (a slice where they are
    consecutive) of the left side and the right side (the outer 1 px of either end)
    and of the inner part (``|offset| <= half - 1.5``, ``half = offs[-1]``), and one
    over the number of samples on the left and on the right. Cached per ``offs``."""
    key = offs.tobytes()
    parts = _PARTS.get(key)
    if parts is None:
        if len(_PARTS) > 64:
            _PARTS.clear()
        half = float(offs[-1])
        side = np.abs(offs) >= half - 1.0 + 1e-9
        il = np.flatnonzero(side & (offs < 0))
        ir = np.flatnonzero(side & (offs > 0))
        ii = np.flatnonzero(np.abs(offs) <= half - 1.5 + 1e-9)

        def run(idx: np.ndarray) -> slice | np.ndarray:
            if idx.size and np.all(np.diff(idx) == 1):
                return slice(int(idx[0]), int(idx[-1]) + 1)
            return idx

        parts = (run(il), run(ir), run(ii), 1.0 / il.size, 1.0 / ir.size)
        _PARTS[key] = parts
    return parts


def _vertex(y0: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Sub-sample offset in [-1, 1] of the parabola's vertex through three samples."""
    den = y0 - 2 * y1 + y2
    safe = np.where(np.abs(den) > 1e-9, den, 1.0)
    return np.clip(np.where(np.abs(den) > 1e-9, 0.5 * (y0 - y2) / safe, 0.0), -1.0, 1.0)


def refine_undistorted(camera: CameraModel, gray: np.ndarray, segs_px: np.ndarray,
                       n_along: int = 8, half_width_px: float = 4.0, min_step: float = 20.0,
                       min_depth: float = 8.0, retry_half_width_px: float | None = 6.0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel segments fitted in undistorted coordinates, with their edge kind.

    A straight ceiling line is straight only after undistortion: a detector's segment
    is a chord of the curved image, and a thin line (a seam) is found on one of its
    two edges. Here each segment's kind comes from its mean cross profile
    (:func:`edge_polarity`); at ``n_along`` points along it the edge is located on
    the profile there (a step: the sub-pixel peak of the derivative with the
    segment's sign; a thin line: the sub-pixel extremum), within
    ``half_width_px - 1`` px of the segment; the points are undistorted and a
    total-least-squares line is fitted to them (one pass dropping points over
    3 sigma, at least 0.5 px). The endpoints are the undistorted detector endpoints
    projected onto that line. A segment of unclear kind is looked at again over
    ``retry_half_width_px`` (None: not): a detector's segment on one edge of a blurred
    seam sits 1-2 px off the seam's middle, and the seam then reaches past one side of
    the narrow profile, which is neither a step nor a thin line there. A segment still
    unclear, or with fewer than 4 located points, keeps its undistorted endpoints.

    Args:
        camera: the intrinsics (``camera.unproject``).
        gray: ``(H, W)`` uint8 image.
        segs_px: ``(N, 4)`` detector segments, pixels.

    Returns:
        ``(segs_n, polarity, rms_px)``: ``(N, 4)`` segments in undistorted normalized
        coordinates, ``(N,)`` polarity as :func:`edge_polarity` (the left normal of the
        pixel segment; the line through ``segs_n`` keeps that side positive), ``(N,)``
        RMS of the located points about the line in pixels of the focal length (NaN
        where not refitted).
    """
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    n = s.shape[0]
    rms = np.full(n, np.nan)
    if n == 0:
        return np.zeros((0, 4)), np.zeros(0), rms
    offs, t, inner = _edge_grid(n_along, half_width_px)
    o_in = offs[1:-1][inner]                     # where an edge may be located
    d_all, nrm_all = _directions(s)
    prof = _profiles(gray, s, d_all, nrm_all, offs, t)                         # (N, A, O)
    pol, _ = _classify_profiles(prof.sum(axis=1) * (1.0 / n_along), offs, min_step, min_depth,
                                shift=False)
    # the steps, then the thin lines (each segment is fitted on its own: order is free)
    i_step = np.flatnonzero(np.abs(pol) == 1.0)
    i_thin = np.flatnonzero(pol == 0.0)
    sel = np.concatenate([i_step, i_thin])
    n_st = i_step.size
    loc = np.empty((sel.size, n_along))          # edge offsets along the left normal, px
    i0, i1 = inner.start + 1, inner.stop + 1     # the inner part, in offs
    if n_st:
        # a step: where the profile crosses the middle of its two sides' levels, the
        # crossing nearest the derivative's peak (less locked to the pixel grid than
        # a parabola)
        gs = prof[i_step] * pol[i_step][:, None, None]          # rises across the step
        mid = gs[:, :, [0, 1, -2, -1]].sum(axis=2) * 0.25     # the two sides' middle
        k = np.argmax(gs[:, :, i0 + 1:i1 + 1] - gs[:, :, i0 - 1:i1 - 1], axis=2) + i0
        near = np.take_along_axis(gs, k[:, :, None] + _NEIGHBOURS, axis=2) - mid[:, :, None]
        hm, hk, hp = near[:, :, 0], near[:, :, 1], near[:, :, 2]    # at k - 1, k, k + 1
        # the crossing is in [k - 1, k] or [k, k + 1] (the derivative peaks at k)
        lo = hk > 0
        h0 = np.where(lo, hm, hk)
        h1 = np.where(lo, hk, hp)
        o = offs[k - lo] + 0.5 * (-h0) / np.where(h1 > h0, h1 - h0, 1.0)
        ok = (h0 <= 0) & (h1 > 0) & (np.abs(o) <= o_in[-1])
        loc[:n_st] = np.where(ok, o, np.nan)
    if i_thin.size:
        # a thin line: the centroid of its part beyond half its height
        p = prof[i_thin]
        inv_a = 1.0 / n_along
        side = 0.5 * (p[:, :, 0] + p[:, :, -1]).sum(axis=1) * inv_a
        inner_p = p[:, :, i0:i1]
        valley = (side - inner_p.min(axis=2).sum(axis=1) * inv_a
                  >= inner_p.max(axis=2).sum(axis=1) * inv_a - side)
        sgn = np.where(valley, -1.0, 1.0)
        gt = inner_p * sgn[:, None, None]                        # peaks on the line
        top = gt.max(axis=2, keepdims=True)
        w = np.maximum(gt - 0.5 * ((sgn * side)[:, None, None] + top), 0.0)
        sw = w.sum(axis=2)
        o = (w * o_in).sum(axis=2) / np.maximum(sw, 1e-12)
        k_pk = np.argmax(gt, axis=2)
        ok = (sw > 0) & (k_pk > 0) & (k_pk < o_in.size - 1)
        loc[n_st:] = np.where(ok, o, np.nan)
    good = np.isfinite(loc)
    # the located edge points in pixels, undistorted with all endpoints in one call
    # (the others stay at 0: they have no weight in the fit)
    n_good = int(np.count_nonzero(good))
    px = np.empty((2 * n + n_good, 2))
    px[:2 * n] = s.reshape(-1, 2)
    pts = (s[sel, :2].T[:, :, None] + t * d_all[sel].T[:, :, None]
           + loc * nrm_all[sel].T[:, :, None])                                  # (2, S, A)
    px[2 * n:] = pts[:, good].T
    xy_all = unproject_fast(camera, px)
    ends = xy_all[:2 * n].reshape(n, 4)
    x = np.zeros(good.shape)
    y = np.zeros(good.shape)
    x[good] = xy_all[2 * n:, 0]
    y[good] = xy_all[2 * n:, 1]
    f = 0.5 * (camera.fx + camera.fy)
    line, res, cnt, ssr = _fit_lines(x, y, good)
    sig = np.sqrt(ssr / np.maximum(cnt, 1))
    keep = good & (np.abs(res) <= np.maximum(3 * sig, 0.5 / f)[:, None])
    if (keep != good).any():
        good = keep
        line, res, cnt, ssr = _fit_lines(x, y, good)
    ok = cnt >= 4
    idx = sel[ok]
    ln = line[ok]
    e = ends[idx].reshape(-1, 2, 2)                   # (M, endpoint, xy)
    # keep the orientation of the pixel segment: its left side stays positive
    flip = ((e[:, 1, 0] - e[:, 0, 0]) * ln[:, 1] - (e[:, 1, 1] - e[:, 0, 1]) * ln[:, 0] < 0)
    ln[flip] *= -1
    dist = e[:, :, 0] * ln[:, 0, None] + e[:, :, 1] * ln[:, 1, None] + ln[:, 2, None]
    ends[idx] = (e - dist[:, :, None] * ln[:, None, :2]).reshape(-1, 4)
    rms[idx] = f * np.sqrt(ssr[ok] / cnt[ok])
    unclear = np.flatnonzero(np.isnan(pol))
    if unclear.size and retry_half_width_px is not None \
            and retry_half_width_px > half_width_px:
        e2, p2, r2 = refine_undistorted(camera, gray, s[unclear], n_along,
                                        retry_half_width_px, min_step, min_depth, None)
        now = np.isfinite(p2)
        ends[unclear[now]], pol[unclear[now]], rms[unclear[now]] = e2[now], p2[now], r2[now]
    return ends, pol, rms


_NEIGHBOURS = np.array([-1, 0, 1])


@functools.lru_cache(maxsize=16)
def _edge_grid(n_along: int, half_width_px: float) -> tuple[np.ndarray, np.ndarray, slice]:
    """Constants of :func:`refine_undistorted`: the profile offsets ``(O,)`` (px, every
    0.5 px within ``half_width_px``), the places along a segment ``(A,)`` (fractions of
    its length, 0.05 to 0.95) and the slice of ``offs[1:-1]`` within
    ``half_width_px - 1`` px (where an edge is located). Read-only arrays."""
    offs = np.arange(-half_width_px, half_width_px + 1e-9, 0.5)
    t = np.linspace(0.05, 0.95, n_along)
    inner = np.flatnonzero(np.abs(offs[1:-1]) <= half_width_px - 1.0 + 1e-9)
    if inner.size == 0:
        raise ValueError(f"half_width_px {half_width_px} leaves no room to locate an edge")
    offs.flags.writeable = False
    t.flags.writeable = False
    return offs, t, slice(int(inner[0]), int(inner[-1]) + 1)


_FAST_OK: dict[tuple, bool] = {}


def unproject_fast(camera: CameraModel, points_px: np.ndarray) -> np.ndarray:
    """``camera.unproject`` ``(N, 2)`` for many points per frame: for the polynomial
    models a fixed 10 iterations of OpenCV's undistortion (no reprojection test). Used
    only for a camera whose image border reprojects within 1e-4 px after those 10
    iterations (checked once per camera); other cameras go to ``camera.unproject``."""
    px = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if (px.shape[0] == 0 or not camera.is_distorted
            or camera.model not in ("plumb_bob", "rational_polynomial")):
        return camera.unproject(px)
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes())
    ok = _FAST_OK.get(key)
    if ok is None:
        u = np.linspace(-0.5, camera.width - 0.5, 33)
        v = np.linspace(-0.5, camera.height - 0.5, 25)
        border = np.concatenate([np.stack([u, np.full_like(u, v[0])], 1),
                                 np.stack([u, np.full_like(u, v[-1])], 1),
                                 np.stack([np.full_like(v, u[0]), v], 1),
                                 np.stack([np.full_like(v, u[-1]), v], 1)])
        back = camera.distort(_undistort10(camera, border))
        ok = bool(np.all(np.abs(back - border) <= 1e-4))
        _FAST_OK[key] = ok
    return _undistort10(camera, px) if ok else camera.unproject(px)


def _undistort10(camera: CameraModel, px: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(px.reshape(-1, 1, 2), camera.K, camera.dist,
                               criteria=(cv2.TERM_CRITERIA_COUNT, 10, 0.0)).reshape(-1, 2)


def _fit_lines(x: np.ndarray, y: np.ndarray, w: np.ndarray
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


def shift_segments(segs_px: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
    """Segments ``(N, 4)`` moved by ``shift_px (N,)`` along their left normal (see
    :func:`sample_profiles`)."""
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    d = s[:, 2:] - s[:, :2]
    t_hat = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)[:, None]
    nrm = np.stack([-t_hat[:, 1], t_hat[:, 0]], axis=1) * np.asarray(shift_px)[:, None]
    return s + np.hstack([nrm, nrm])


def undistort_segments(camera: CameraModel, segs_px: np.ndarray) -> np.ndarray:
    """Segments ``(N, 4)`` in undistorted normalized coordinates (endpoints only)."""
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    xy = camera.unproject(s.reshape(-1, 2))
    return xy.reshape(-1, 4)


def segment_lines(segs: np.ndarray) -> np.ndarray:
    """Homogeneous lines ``(N, 3)`` through segments ``(N, 4)``, ``hypot(a, b) = 1``."""
    s = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    p1 = np.hstack([s[:, :2], np.ones((s.shape[0], 1))])
    p2 = np.hstack([s[:, 2:], np.ones((s.shape[0], 1))])
    ln = np.cross(p1, p2)
    return ln / np.maximum(np.hypot(ln[:, 0], ln[:, 1]), 1e-300)[:, None]


def merge_segments(segs: np.ndarray, angle_tol_rad: float = np.radians(2.0),
                   dist_tol: float = 3.0) -> list[np.ndarray]:
    """Group segments lying on one line (similar direction, each midpoint near the
    other's line). Returns index arrays, one per group, longest segment first."""
    s = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    n = s.shape[0]
    if n == 0:
        return []
    lines = segment_lines(s)
    mid = 0.5 * (s[:, :2] + s[:, 2:])
    ang = np.arctan2(s[:, 3] - s[:, 1], s[:, 2] - s[:, 0])
    order = np.argsort(-segment_lengths(s))
    label = np.full(n, -1)
    groups: list[np.ndarray] = []
    for i in order:
        if label[i] >= 0:
            continue
        da = np.abs((ang - ang[i] + np.pi / 2) % np.pi - np.pi / 2)
        dist = np.abs(mid @ lines[i, :2] + lines[i, 2])
        members = np.flatnonzero((label < 0) & (da <= angle_tol_rad) & (dist <= dist_tol))
        label[members] = len(groups)
        groups.append(np.concatenate([[i], members[members != i]]))
    return groups
