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
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.edges import (
    OUTLIER_FLOOR_PX,
    OUTLIER_SIGMAS,
    PROFILE_STEP_PX,
    RowFits,
    classify,
    classify_rows,
    edge_grid,
    fit_robust_rows,
    locate_rows,
    part_indices,
    profile_offsets,
    profiles_at,
    remap_along,
    sample_profiles,
)
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.quads import bilinear
from ceilkit.runtime.features.working import decimate, undecimate
from ceilkit.runtime.geometry.camera import (
    CameraModel,
    fixed_iterations,
    undistort_fixed_points,
    undistort_points,
    unproject_many,
)
from ceilkit.runtime.jit import arr, njit, warmer

MIN_FIT_POINTS = 4   # located edge points a segment needs to be refitted


def segment_lengths(segs: np.ndarray) -> np.ndarray:
    """Lengths ``(N,)`` of segments ``(N, 4)``, in their own units."""
    s = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    return np.hypot(s[:, 2] - s[:, 0], s[:, 3] - s[:, 1])


class FldKernel:
    """cv2.ximgproc's FastLineDetector (Canny thresholds ``canny``; ``merge``: OpenCV's
    ``do_merge`` of collinear pieces)."""

    def __init__(self, min_length_px: float, canny: tuple[float, float],
                 merge: bool) -> None:
        self._det = cv2.ximgproc.createFastLineDetector(
            int(max(5, min_length_px * 0.5)), 1.414, canny[0], canny[1], 3, bool(merge))

    def detect(self, gray: np.ndarray) -> np.ndarray | None:
        """Raw segments of an 8-bit grey image (any shape OpenCV returns), or None."""
        return self._det.detect(gray)


class LsdKernel:
    """OpenCV's LSD with standard refinement (``canny`` and ``merge`` do not apply)."""

    def __init__(self, min_length_px: float, canny: tuple[float, float],
                 merge: bool) -> None:
        self._det = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)

    def detect(self, gray: np.ndarray) -> np.ndarray | None:
        """Raw segments of an 8-bit grey image, or None."""
        return self._det.detect(gray)[0]


class HoughKernel:
    """Canny edges, then the probabilistic Hough transform (``merge`` does not apply)."""

    def __init__(self, min_length_px: float, canny: tuple[float, float],
                 merge: bool) -> None:
        self.min_length_px = min_length_px
        self.canny = canny

    def detect(self, gray: np.ndarray) -> np.ndarray | None:
        """Raw segments of an 8-bit grey image, or None."""
        edges = cv2.Canny(gray, self.canny[0], self.canny[1], L2gradient=True)
        return cv2.HoughLinesP(edges, 1.0, np.pi / 720, 30,
                               minLineLength=self.min_length_px, maxLineGap=3)


class EdKernel:
    """cv2.ximgproc's EdgeDrawing with its EDLines line fit (``canny`` and ``merge`` do
    not apply; its own gradient threshold and anchors; ``min_length_px`` is its
    shortest line)."""

    def __init__(self, min_length_px: float, canny: tuple[float, float],
                 merge: bool) -> None:
        self._ed = cv2.ximgproc.createEdgeDrawing()
        params = cv2.ximgproc.EdgeDrawing.Params()
        params.MinLineLength = int(max(5, min_length_px * 0.5))
        self._ed.setParams(params)

    def detect(self, gray: np.ndarray) -> np.ndarray | None:
        """Raw segments of an 8-bit grey image, or None."""
        self._ed.detectEdges(np.ascontiguousarray(gray))
        return self._ed.detectLines()


KERNELS: Mapping[str, type] = MappingProxyType({
    "fld": FldKernel, "lsd": LsdKernel, "hough": HoughKernel, "ed": EdKernel})
"""Line detector name -> its kernel class: to add or replace a detector, write a class
with ``__init__(min_length_px, canny, merge)`` and ``detect(gray)`` and add it here."""
DETECTORS = tuple(KERNELS)


class SegmentDetector:
    """A reusable line-segment detector on 8-bit grey images.

    Args:
        method: a name in :data:`KERNELS`: ``fld`` (cv2.ximgproc FastLineDetector),
            ``lsd`` (cv2 LSD), ``hough`` (Canny + probabilistic Hough) or ``ed``
            (cv2.ximgproc EdgeDrawing/EDLines).
        min_length_px: shortest segment kept, pixels.
        canny: ``(low, high)`` hysteresis thresholds for ``fld`` and ``hough``.
        rows: ``(v0, v1)``: detect only in image rows ``v0 <= v < v1`` (a region of
            interest, e.g. where the ceiling can be); segments keep full-image pixel
            coordinates. None: the whole image.
        merge: ``fld`` merges collinear pieces (OpenCV's ``do_merge``; default True).
        factor: detect on the image box-averaged by this integer factor (a working
            resolution for large frames: :mod:`~ceilkit.runtime.features.working`);
            segments come back in full-resolution pixels, ``min_length_px`` counts
            full-resolution pixels. Refine them on the full image
            (:func:`refine_undistorted`).
    """

    def __init__(self, method: str = "fld", min_length_px: float = 20.0,
                 canny: tuple[float, float] = (40.0, 100.0),
                 rows: tuple[int, int] | None = None, merge: bool = True,
                 factor: int = 1) -> None:
        if method not in KERNELS:
            raise ConfigError(None, "detector",
                              f"expected one of {', '.join(DETECTORS)}, found {method!r}")
        self.method = method
        self.min_length_px = float(min_length_px)
        self.canny = (float(canny[0]), float(canny[1]))
        self.rows = None if rows is None else (max(0, int(rows[0])), int(rows[1]))
        self.factor = max(1, int(factor))
        self.kernel = KERNELS[method](self.min_length_px / self.factor, self.canny, merge)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Segments ``(N, 4)`` in pixels, at least ``min_length_px`` long."""
        v0 = 0
        if self.rows is not None:
            v0 = min(self.rows[0], gray.shape[0])
            gray = gray[v0:max(v0, self.rows[1])]
            if gray.shape[0] < 2:
                return np.zeros((0, 4))
        found = self.kernel.detect(decimate(gray, self.factor))
        if found is None or len(found) == 0:
            return np.zeros((0, 4))
        segs = np.asarray(found, dtype=np.float64).reshape(-1, 4)
        if self.factor > 1:
            segs = undecimate(segs.reshape(-1, 2), self.factor).reshape(-1, 4)
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
    ok = counts >= MIN_FIT_POINTS
    if not np.any(ok):
        return segs, rms
    idx = np.repeat(np.arange(n)[ok], counts[ok])
    start = np.concatenate([[0], np.cumsum(counts[ok])[:-1]])
    k = np.arange(idx.size) - np.repeat(start, counts[ok])
    s_along = inset_px + k * step_px
    base = p1[idx] + t_hat[idx] * s_along[:, None]                       # (K, 2)
    prof = profiles_at(gray.astype(np.float32), base.T[:, :, None], nrm[idx].T[:, :, None],
                       offs)[:, 0, :]                                   # (K, O)
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
        if np.count_nonzero(sel) < MIN_FIT_POINTS:
            continue
        w = mass[sel]
        line = fit_line(edge[sel], w)
        res = edge[sel] @ line[:2] + line[2]
        # one robust pass: drop points far from the first fit
        keep = np.abs(res) <= max(3.0 * np.sqrt(np.average(res ** 2, weights=w)), 0.3)
        if np.count_nonzero(keep) >= MIN_FIT_POINTS:
            line = fit_line(edge[sel][keep], w[keep])
            res = edge[sel][keep] @ line[:2] + line[2]
        rms[i] = float(np.sqrt(np.mean(res ** 2)))
        for j in (0, 2):
            q = segs[i, j:j + 2]
            segs[i, j:j + 2] = q - (q @ line[:2] + line[2]) * line[:2]
    return segs, rms


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
    offs = profile_offsets(half_width_px)
    return classify(sample_profiles(gray, segs_px, offs), offs, min_step, min_depth)


def edge_half_width_px(factor: int = 1) -> float:
    """The profile half-width :func:`refine_undistorted` needs for segments found at a
    working resolution decimated by ``factor``: 4 px at full resolution, 6 more per
    step of the factor (the mapped-back segments lie up to about a decimated pixel off
    their edge; on simulated 4000x3000 corridor frames 12 px at factor 3 still fails
    the misfit test, 16 passes, and 10 at factor 2)."""
    return 4.0 + 6.0 * (max(1, int(factor)) - 1)


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
    if n == 0:
        return np.zeros((0, 4)), np.zeros(0), np.full(0, np.nan)
    retry = retry_half_width_px is not None and retry_half_width_px > half_width_px
    iterations = fixed_iterations(camera)
    kind = ProfileKind(float(min_step), float(min_depth), PROFILE_STEP_PX)
    if iterations:
        # the whole fit, retry included, in one compiled call (the same numbers)
        g2 = _grid(n_along, retry_half_width_px if retry else half_width_px)
        lens = FixedLens(camera.lens[1], iterations, 0.5 * (camera.fx + camera.fy))
        return _refine_fixed(arr(gray, np.uint8), arr(s, np.float64),
                             _grid(n_along, half_width_px), g2, retry, kind, lens)
    rms = np.full(n, np.nan)
    # each segment's kind from its mean profile, then its edge on every profile (steps
    # and thin lines; a segment of unclear kind is not located) as pixels, after the
    # segments' endpoints
    pol, px, good = _profile_points(arr(gray, np.uint8), arr(s, np.float64),
                                    _grid(n_along, half_width_px), kind)
    # the endpoints and the located points through the lens in one call
    xy = unproject_many(camera, px)
    ends = xy[:2 * n].reshape(n, 4)
    _fit_segments(arr(xy[2 * n:], np.float64), good, ends, rms, 0.5 * (camera.fx + camera.fy),
                  OUTLIER_FLOOR_PX, OUTLIER_SIGMAS, MIN_FIT_POINTS)
    unclear = np.flatnonzero(np.isnan(pol))
    if unclear.size and retry:
        e2, p2, r2 = refine_undistorted(camera, gray, s[unclear], n_along,
                                        retry_half_width_px, min_step, min_depth, None)
        now = np.isfinite(p2)
        ends[unclear[now]], pol[unclear[now]], rms[unclear[now]] = e2[now], p2[now], r2[now]
    return ends, pol, rms


class ProfileGrid(NamedTuple):
    """:func:`~.edges.edge_grid` and :func:`~.edges.part_indices` as the compiled loops
    take them: the offsets across a segment ``offs (O,)`` px, the places along it
    ``t (A,)``, the left, right and inner parts' indices ``il, ir, ii`` and the inner
    part's first and last index plus one ``i0, i1``."""

    offs: np.ndarray
    t: np.ndarray
    il: np.ndarray
    ir: np.ndarray
    ii: np.ndarray
    i0: int
    i1: int


class ProfileKind(NamedTuple):
    """What a profile needs to be of a kind (:func:`~.edges.classify`): its step
    ``min_step`` and thin line's depth ``min_depth`` (grey levels), the profile's
    sampling ``step_px`` (px)."""

    min_step: float
    min_depth: float
    step_px: float


class FixedLens(NamedTuple):
    """A lens :func:`undistort_fixed_points` inverts: its ``params (13,)``
    (:attr:`~ceilkit.runtime.geometry.camera.CameraModel.lens`), the fixed-point
    ``iterations`` and the focal length ``f_px`` (px) the residuals are scaled by."""

    params: np.ndarray
    iterations: int
    f_px: float


@functools.lru_cache(maxsize=16)
def _grid(n_along: int, half_width_px: float) -> ProfileGrid:
    """:func:`~.edges.edge_grid` and :func:`~.edges.part_indices` as the compiled loops
    take them (a :class:`ProfileGrid`)."""
    offs, t, inner = edge_grid(n_along, half_width_px)
    il, ir, ii = part_indices(offs)
    return ProfileGrid(arr(offs, np.float64), arr(t, np.float64), arr(il, np.int64),
                       arr(ir, np.int64), arr(ii, np.int64), inner.start + 1, inner.stop + 1)


@njit
def _refine_fixed(grey, s, grid, grid2, retry, kind, lens):  # pragma: no cover - compiled
    """:func:`refine_undistorted` for a lens :func:`unproject_many` inverts in its
    compiled loop (``lens``: a :class:`FixedLens`), in one call: ``(segs_n (N, 4),
    polarity (N,), rms (N,))``; the profiles read on ``grid`` (a :class:`ProfileGrid`)
    as ``kind`` (a :class:`ProfileKind`) says, the rows of unclear kind measured again
    on ``grid2`` when ``retry``."""
    ends, pol, rms = _refine_pass(grey, s, grid, kind, lens)
    rows = np.flatnonzero(np.isnan(pol))
    if not retry or rows.size == 0:
        return ends, pol, rms
    e2, p2, r2 = _refine_pass(grey, s[rows], grid2, kind, lens)
    for k in range(rows.size):
        if math.isfinite(p2[k]):
            r = rows[k]
            ends[r, :] = e2[k, :]
            pol[r], rms[r] = p2[k], r2[k]
    return ends, pol, rms


@njit
def _refine_pass(grey, s, grid, kind, lens):  # pragma: no cover - compiled
    """One pass of :func:`refine_undistorted` (no retry): the profiles and points
    (:func:`_profile_points`), the lens (:func:`undistort_fixed_points`), the fit
    (:func:`_fit_segments`)."""
    pol, px, good = _profile_points(grey, s, grid, kind)
    xy = np.empty_like(px)
    undistort_fixed_points(px, lens.params, lens.iterations, xy)
    ends, rms = _ends_and_fit(xy, good, lens.f_px)
    return ends, pol, rms


@njit
def _ends_and_fit(xy, good, f_px):  # pragma: no cover - compiled
    """``(ends (N, 4), rms (N,))`` of undistorted points ``xy (2N + K, 2)`` (the
    segments' endpoints, then the K located points of ``good (N, A)``): the endpoints
    projected on each segment's fitted line (:func:`_fit_segments`; NaN rms where not
    refitted)."""
    n = good.shape[0]
    ends = xy[:2 * n].copy().reshape(n, 4)
    rms = np.full(n, np.nan)
    _fit_segments(xy[2 * n:].copy(), good, ends, rms, f_px, OUTLIER_FLOOR_PX, OUTLIER_SIGMAS,
                  MIN_FIT_POINTS)
    return ends, rms


def refine_chords(camera: CameraModel, gray: np.ndarray, segs_px: np.ndarray,
                  half_width_px: float = 4.0, n_along: int = 8, min_step: float = 20.0,
                  min_depth: float = 8.0, local_share: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_undistorted` of short chords predicted near their edges (no wider
    retry), in one compiled call (:func:`refine_chords_core`): the same stages, with the
    profiles sampled bilinear in float (the frame's edge replicated; not OpenCV's
    remap, rounded to grey levels) and the lens inverted exactly
    (:func:`~ceilkit.runtime.geometry.camera.undistort_points`). ``local_share`` > 0:
    a place along a chord is used only where its own profile is of the chord's kind
    at that share of ``min_step`` / ``min_depth`` (:func:`_local_kind`; 0: every
    place, as :func:`refine_undistorted`). Returns ``(segs_n, polarity, rms_px)`` as
    :func:`refine_undistorted`."""
    s = arr(segs_px, np.float64).reshape(-1, 4)
    kind = ProfileKind(float(min_step), float(min_depth), PROFILE_STEP_PX)
    return refine_chords_core(arr(gray, np.uint8), s, _grid(n_along, half_width_px), kind,
                              *camera.lens, 0.5 * (camera.fx + camera.fy),
                              float(local_share))


@njit
def refine_chords_core(grey, chords, grid, kind, lens_code, lens, f_px, local_share
                       ):  # pragma: no cover - compiled
    """:func:`refine_chords`: ``(segs_n (N, 4), polarity (N,), rms (N,))``, the profiles
    read on ``grid`` (a :class:`ProfileGrid`) as ``kind`` (a :class:`ProfileKind`) says,
    through the lens ``lens_code, lens``; ``f_px``: the focal length the residuals are
    scaled by; ``local_share`` > 0: only the places whose own profile is of the chord's
    kind (:func:`_local_kind`)."""
    offs, t = grid.offs, grid.t
    n = chords.shape[0]
    n_a, n_o = t.size, offs.size
    hh, w = grey.shape
    d = np.empty((n, 2))
    nrm = np.empty((n, 2))
    prof = np.empty((n, n_a, n_o))
    for r in range(n):
        d[r, 0], d[r, 1] = chords[r, 2] - chords[r, 0], chords[r, 3] - chords[r, 1]
        inv = 1.0 / max(math.hypot(d[r, 0], d[r, 1]), 1e-9)
        nrm[r, 0], nrm[r, 1] = -d[r, 1] * inv, d[r, 0] * inv
        # the chord's samples all inside the frame (its box's corners): no clamping
        inside = True
        for a in (0, n_a - 1):
            for o in (0, n_o - 1):
                su = chords[r, 0] + t[a] * d[r, 0] + offs[o] * nrm[r, 0]
                sv = chords[r, 1] + t[a] * d[r, 1] + offs[o] * nrm[r, 1]
                inside = inside and 0.0 <= su < w - 1 and 0.0 <= sv < hh - 1
        for a in range(n_a):
            bu, bv = chords[r, 0] + t[a] * d[r, 0], chords[r, 1] + t[a] * d[r, 1]
            for o in range(n_o):
                su, sv = bu + offs[o] * nrm[r, 0], bv + offs[o] * nrm[r, 1]
                if inside:
                    prof[r, a, o] = _bilinear_inside(grey, su, sv)
                else:
                    prof[r, a, o] = bilinear(grey, su, sv, w, hh)
    pol, pts, good = _kind_and_points(prof, chords, d, nrm, grid, kind)
    ends_px = chords
    if local_share > 0.0:
        _local_kind(prof, pol, grid, ProfileKind(local_share * kind.min_step,
                                                 local_share * kind.min_depth, kind.step_px),
                    good)
        ends_px = _located_extent(chords, d, t, good)
    px = _stack_points(ends_px, pts, good)
    xy = np.empty_like(px)
    undistort_points(px, lens_code, lens, xy)
    ends, rms = _ends_and_fit(xy, good, f_px)
    return ends, pol, rms


@njit
def _local_kind(prof, pol, grid, kind, good):  # pragma: no cover - compiled
    """Unmark in ``good (N, A)`` the places whose own profile ``prof[r, a]``, or a
    neighbouring place's (``a - 1``, ``a + 1`` on the segment), is not of segment
    ``r``'s kind ``pol[r]`` (:func:`~.edges.classify` of that one profile, as ``kind``,
    a :class:`ProfileKind`, says). A chord predicted along an interrupted edge (a lamp
    row's long edge, lamps and gaps) keeps the kind of its mean profile where only
    part of it lies on the edge: a place in a gap would locate the noise's largest
    gradient anywhere across the profile, one beside a lamp's end the end's blur."""
    n, n_a, _ = prof.shape
    for r in range(n):
        if not math.isfinite(pol[r]):
            continue
        local, _ = classify_rows(prof[r], grid.offs, grid.il, grid.ir, grid.ii,
                                 kind.min_step, kind.min_depth, kind.step_px)
        on = np.empty(n_a, np.bool_)
        for a in range(n_a):
            on[a] = local[a] == pol[r]
        for a in range(n_a):
            good[r, a] = (good[r, a] and on[a] and (a == 0 or on[a - 1])
                          and (a == n_a - 1 or on[a + 1]))


@njit
def _located_extent(chords, d, t, good):  # pragma: no cover - compiled
    """``(N, 4)`` px: each chord cut to its first and last located place (``good (N,
    A)`` at ``t (A,)`` along ``d (N, 2)``), the chord itself where none is: a chord
    measured over part of its length says nothing of the rest, and its endpoints,
    projected on the fitted line, should not extrapolate it."""
    out = chords.copy()
    n, n_a = good.shape
    for r in range(n):
        a0, a1 = -1, -1
        for a in range(n_a):
            if good[r, a]:
                a1 = a
                if a0 < 0:
                    a0 = a
        if a0 >= 0 and a1 > a0:
            for e, a in ((0, a0), (1, a1)):
                out[r, 2 * e] = chords[r, 0] + t[a] * d[r, 0]
                out[r, 2 * e + 1] = chords[r, 1] + t[a] * d[r, 1]
    return out


@njit
def _profile_points(grey, s, grid, kind):  # pragma: no cover - compiled
    """:func:`refine_undistorted`'s profiles (:func:`~.edges.remap_along`, as
    :func:`~.edges.profiles_along`) and located points (:func:`_kind_and_points`) of
    segments ``s (N, 4)`` on ``grid`` (a :class:`ProfileGrid`) as ``kind`` (a
    :class:`ProfileKind`) says: ``(polarity (N,), pixels (2N + K, 2): the endpoints,
    then the K located points in the order of located (N, A))``."""
    offs, t = grid.offs, grid.t
    n = s.shape[0]
    d = np.empty((n, 2))
    nrm = np.empty((n, 2))
    for r in range(n):
        d[r, 0], d[r, 1] = s[r, 2] - s[r, 0], s[r, 3] - s[r, 1]
        inv = 1.0 / max(math.hypot(d[r, 0], d[r, 1]), 1e-9)
        nrm[r, 0], nrm[r, 1] = -d[r, 1] * inv, d[r, 0] * inv
    prof = np.empty((n, t.size, offs.size))
    remap_along(grey, s, d, nrm, offs, t, prof)
    pol, pts, good = _kind_and_points(prof, s, d, nrm, grid, kind)
    return pol, _stack_points(s, pts, good), good


@njit
def _stack_points(s, pts, good):  # pragma: no cover - compiled
    """``(2N + K, 2)``: the endpoints of segments ``s (N, 4)``, then the K points of
    ``pts (N, A, 2)`` that are ``good (N, A)``."""
    n, n_a = good.shape
    n_good = 0
    for r in range(n):
        for a in range(n_a):
            n_good += good[r, a]
    px = np.empty((2 * n + n_good, 2))
    for r in range(n):
        px[2 * r, 0], px[2 * r, 1] = s[r, 0], s[r, 1]
        px[2 * r + 1, 0], px[2 * r + 1, 1] = s[r, 2], s[r, 3]
    k = 2 * n
    for r in range(n):
        for a in range(n_a):
            if good[r, a]:
                px[k, 0], px[k, 1] = pts[r, a, 0], pts[r, a, 1]
                k += 1
    return px


@njit
def _bilinear_inside(grey, x, y):  # pragma: no cover - compiled
    """:func:`~.quads.bilinear` at ``(x, y)`` with ``0 <= x < W - 1`` and ``0 <= y <
    H - 1`` (no clamping): the same number."""
    x0 = np.int64(x)
    y0 = np.int64(y)
    fx, fy = x - x0, y - y0
    a, b = np.float64(grey[y0, x0]), np.float64(grey[y0, x0 + 1])
    c, d = np.float64(grey[y0 + 1, x0]), np.float64(grey[y0 + 1, x0 + 1])
    top = a + fx * (b - a)
    bot = c + fx * (d - c)
    return top + fy * (bot - top)


@njit
def _kind_and_points(prof, s, d, nrm, grid, kind):  # pragma: no cover - compiled
    """``(polarity (N,), points (N, A, 2) px, located (N, A))``: each segment's kind
    from its mean profile (:func:`~.edges.classify`, as ``kind``, a
    :class:`ProfileKind`, says) and, for a step or a thin line, its edge on the profile
    at each place ``t`` along it (:func:`~.edges.locate`; ``grid``, a
    :class:`ProfileGrid`) as a pixel ``p1 + t d + offset nrm``."""
    offs, t, step_px = grid.offs, grid.t, kind.step_px
    n, n_a, n_o = prof.shape
    mean = np.zeros((n, n_o))
    for r in range(n):
        for a in range(n_a):
            for o in range(n_o):
                mean[r, o] += prof[r, a, o]
        for o in range(n_o):
            mean[r, o] *= 1.0 / n_a
    pol, _ = classify_rows(mean, offs, grid.il, grid.ir, grid.ii, kind.min_step,
                           kind.min_depth, step_px)
    loc = np.full((n, n_a), np.nan)
    locate_rows(prof, pol, offs, grid.i0, grid.i1, step_px, loc)
    pts = np.zeros((n, n_a, 2))
    good = np.zeros((n, n_a), np.bool_)
    for r in range(n):
        for a in range(n_a):
            if math.isfinite(loc[r, a]):
                good[r, a] = True
                pts[r, a, 0] = s[r, 0] + t[a] * d[r, 0] + loc[r, a] * nrm[r, 0]
                pts[r, a, 1] = s[r, 1] + t[a] * d[r, 1] + loc[r, a] * nrm[r, 1]
    return pol, pts, good


@njit
def _fit_segments(xy, good, ends, rms, f_px, floor_px, sigmas, min_points
                  ):  # pragma: no cover - compiled
    """Each segment's line through its located points (undistorted, ``xy (K, 2)`` in
    the order of ``good (N, A)``; :func:`~.edges.fit_lines_robust`): with at least
    ``min_points`` points, its undistorted endpoints ``ends (N, 4)`` are projected on
    the line (its left side, as the pixel segment's, kept positive) and ``rms (N,)``
    set (pixels of the focal length ``f_px``); other rows are left as they are."""
    n, n_a = good.shape
    x = np.zeros((n, n_a))
    y = np.zeros((n, n_a))
    k = 0
    for r in range(n):
        for a in range(n_a):
            if good[r, a]:
                x[r, a], y[r, a] = xy[k, 0], xy[k, 1]
                k += 1
    kept = good.copy()
    line = np.empty((n, 3))
    res = np.empty((n, n_a))
    cnt = np.empty(n)
    ssr = np.empty(n)
    fit_robust_rows(x, y, kept, floor_px / f_px, sigmas, RowFits(line, res, cnt, ssr))
    for r in range(n):
        if cnt[r] < min_points:
            continue
        a, b, c = line[r, 0], line[r, 1], line[r, 2]
        # keep the orientation of the pixel segment: its left side stays positive
        if (ends[r, 2] - ends[r, 0]) * b - (ends[r, 3] - ends[r, 1]) * a < 0:
            a, b, c = -a, -b, -c
        for e in range(2):
            dist = ends[r, 2 * e] * a + ends[r, 2 * e + 1] * b + c
            ends[r, 2 * e] -= dist * a
            ends[r, 2 * e + 1] -= dist * b
        rms[r] = f_px * math.sqrt(ssr[r] / max(cnt[r], 1.0))


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
    x1, y1, x2, y2 = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
    ln = np.stack([y1 - y2, x2 - x1, x1 * y2 - y1 * x2], axis=1)    # (x1, y1, 1) x (x2, y2, 1)
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


@warmer
def _warm() -> None:
    g = np.full((40, 60), 50, np.uint8)
    g[:, 30:] = 200
    cam = CameraModel.pinhole(60, 40, 50.0)
    segs = np.array([[30.0, 5.0, 30.0, 35.0], [10.0, 5.0, 12.0, 35.0]])
    refine_undistorted(cam, g, segs)
    lens = CameraModel.pinhole(60, 40, 50.0, dist=[0.1, 0, 0, 0, 0])
    refine_undistorted(lens, g, segs)         # the one compiled call (_refine_fixed)
    refine_chords(cam, g, segs)
    px = arr(np.zeros((1, 2)), np.float64)
    undistort_fixed_points(px, lens.lens[1], 10, np.empty((1, 2)))
