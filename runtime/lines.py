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

import cv2
import numpy as np

from .camera import CameraModel
from .errors import ConfigError

DETECTORS = ("fld", "lsd", "hough")


def as_gray(image: np.ndarray) -> np.ndarray:
    """An 8-bit single-channel view of a grey ``(H, W)`` or BGR ``(H, W, 3)`` frame."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


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
    """

    def __init__(self, method: str = "fld", min_length_px: float = 20.0,
                 canny: tuple[float, float] = (40.0, 100.0)) -> None:
        if method not in DETECTORS:
            raise ConfigError(None, "detector",
                              f"expected one of {', '.join(DETECTORS)}, found {method!r}")
        self.method = method
        self.min_length_px = float(min_length_px)
        self.canny = (float(canny[0]), float(canny[1]))
        if method == "fld":
            self._det = cv2.ximgproc.createFastLineDetector(
                int(max(5, min_length_px * 0.5)), 1.414, self.canny[0], self.canny[1], 3, True)
        elif method == "lsd":
            self._det = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        else:
            self._det = None

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Segments ``(N, 4)`` in pixels, at least ``min_length_px`` long."""
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
        return segs[segment_lengths(segs) >= self.min_length_px]


def detect_segments(gray: np.ndarray, method: str = "fld",
                    min_length_px: float = 20.0) -> np.ndarray:
    """One-off detection: see :class:`SegmentDetector`. Returns ``(N, 4)`` pixels."""
    return SegmentDetector(method, min_length_px)(as_gray(gray))


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
