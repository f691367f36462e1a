"""Mount calibration: the camera's tilt, swing, pan and offsets on the vehicle from corridor images.

This is the step Yang & Tsai take from their reference [15]: everything the
corridor method needs to know about the rig, measured rather than typed in.

Model (SPEC §1). For a vehicle at heading ``yaw`` and lateral position ``y`` in
the corridor, the camera's rotation is ``R_world_cam = Rz(yaw + pan) M`` with
``M = Ry(-tilt) R0 Rz(swing)``, and its centre is at lateral
``c_y = y + sin(yaw) mx + cos(yaw) my``, a height ``h`` below the ceiling. A
ceiling line along x at ``y_k`` is seen as the image line (normalized
coordinates) ``l = R_world_cam^T (0, h, c_y - y_k)``; a line along y (at an
unknown x) passes through the vanishing point ``R_world_cam^T e_y``.

Two ways in:

* **Measured placements** (:func:`calibrate_mount`): the vehicle stands at a few
  measured lateral positions and headings. Segment endpoints are fitted jointly
  by Levenberg-Marquardt over (pan, tilt, swing, my[, mx][, h]); ``mx`` is free
  when the headings differ by more than a few degrees, ``h`` when two or more
  lines of known spacing are seen (otherwise they come from the rig).
* **A straight drive** (:func:`calibrate_tilt_swing`): no measuring at all. While
  the vehicle drives on a level floor the ceiling's vanishing line does not
  move; tilt and swing follow from the vanishing points of every frame (each
  frame's heading a nuisance). Then one measured placement gives pan and the
  offsets (``calibrate_mount(..., fixed={"tilt", "swing"})``).

The start needs no typed value: a coarse search over (pan, tilt, swing) on
segment directions, then a search over the lateral offset, then the joint fit
with associations re-made at shrinking tolerances. Uncertainty: the covariance
``s^2 (J^T J)^-1`` with ``s`` the residual RMS, plus that of a shift common to every
measured line (``SYSTEMATIC_SHIFT_PX``, 1 sigma, in u and in v); placements whose
residuals stand out are named.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError
from ceilkit.runtime.features.edges import (
    classify,
    directions,
    edge_grid,
    fit_lines_robust,
    locate,
    profiles_at,
    thin_sign,
)
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.lines import SegmentDetector, segment_lengths
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import R_level_cam, rot_z
from ceilkit.runtime.io.images import read_image

PARAMS = ("pan", "tilt", "swing", "mx", "my", "h")
_ANGLES = {"pan", "tilt", "swing"}


@dataclass(frozen=True, eq=False)
class Placement:
    """One image's segments and where the vehicle stood.

    Attributes:
        segments_n: ``(N, 4)`` segment endpoints in undistorted normalized coordinates.
        y_m: measured lateral position of the vehicle in W, or ``None`` (a drive frame).
        yaw_rad: measured heading in W, or ``None``.
        label: a name for reports (the image file).
        weights: ``(N, 2)`` residual weights of each segment's offset and turn (see
            :func:`lines_to_segments`), or ``None``: endpoints measured independently
            with equal noise.
        noise_px: the noise the weighted residuals should have (px): the median scatter
            of the edge points about their own lines, measured apart from any model, or
            ``None`` (unknown: the fit's chi-square test is skipped).
    """

    segments_n: np.ndarray
    y_m: float | None = None
    yaw_rad: float | None = None
    label: str = ""
    weights: np.ndarray | None = None
    noise_px: float | None = None

    def residual_weights(self) -> np.ndarray:
        """``(N, 2)`` weights: the given ones or ``(sqrt 2, 1/sqrt 2)`` (independent ends)."""
        if self.weights is not None:
            return np.asarray(self.weights, dtype=float).reshape(-1, 2)
        return np.tile([math.sqrt(2.0), math.sqrt(0.5)], (self.segments_n.shape[0], 1))

    @property
    def measured(self) -> bool:
        return self.y_m is not None and self.yaw_rad is not None


def placement_from_image(camera: CameraModel, image: np.ndarray, y_m: float | None = None,
                         yaw_rad: float | None = None, label: str = "",
                         min_length_px: float = 25.0) -> Placement:
    """Detect the segments of one image and measure them (:func:`measure_lines`)."""
    gray = to_grey(image)
    segs = SegmentDetector("fld", min_length_px)(gray)
    lines = measure_lines(camera, gray, segs)
    segs_n, weights = lines_to_segments(lines)
    noise = float(np.median([e.rms_px for e in lines])) if lines else None
    return Placement(segs_n, y_m, yaw_rad, label, weights, noise)


@dataclass(frozen=True, eq=False)
class MountResult:
    """The fitted mount and its report.

    Attributes:
        mount: the rig's new mount (angles radians, lengths metres).
        height_m: camera height below the ceiling used or fitted.
        sigma: 1-sigma of each fitted parameter (radians / metres), by name.
        fixed: parameters held at the rig's value, with the reason.
        rms_px: residual RMS over inlier endpoints, pixels.
        per_placement_rms_px: RMS by placement label.
        outliers: placements that disagree (label, rms px, why).
        inliers, segments: counts.
    """

    mount: Mount
    height_m: float
    sigma: dict[str, float]
    fixed: dict[str, str]
    rms_px: float
    per_placement_rms_px: dict[str, float]
    outliers: list[tuple[str, float, str]] = field(default_factory=list)
    inliers: int = 0
    segments: int = 0
    chi2_per_dof: float = math.nan

    def lines(self) -> list[str]:
        m = self.mount
        out = [f"tilt  {math.degrees(m.tilt_rad):9.4f} deg" + self._s("tilt", True),
               f"swing {math.degrees(m.swing_rad):9.4f} deg" + self._s("swing", True),
               f"pan   {math.degrees(m.pan_rad):9.4f} deg" + self._s("pan", True),
               f"x     {m.x_m:9.4f} m  " + self._s("mx", False),
               f"y     {m.y_m:9.4f} m  " + self._s("my", False),
               f"h     {self.height_m:9.4f} m   (camera below ceiling)" + self._s("h", False),
               f"residual RMS {self.rms_px:.3f} px over {self.inliers} of "
               f"{self.segments} segments"
               + ("" if not math.isfinite(self.chi2_per_dof) else
                  f", chi-square {self.chi2_per_dof:.2f} per degree of freedom against the "
                  f"edge points' own scatter (refused above {MAX_CHI2_PER_DOF:g})")]
        for label, rms, why in self.outliers:
            out.append(f"placement {label} disagrees: {why} (RMS {rms:.2f} px)")
        return out

    def _s(self, name: str, angle: bool) -> str:
        if name in self.fixed:
            return f"   (held: {self.fixed[name]})"
        s = self.sigma.get(name, math.nan)
        return f"   +- {math.degrees(s):.4f} deg (1 sigma)" if angle else \
            f" +- {1000 * s:.2f} mm (1 sigma)"


# ----------------------------------------------------------------------------- edges
# Calibration is off the hot path: every segment is re-measured from the image, with the
# one edge measurement (runtime/features/edges.py) on float samples.
_STEP_PX = 2.0          # spacing of edge points along a segment (nearly independent noise)
_TRIM_PX = 4.0          # left out at both ends of a segment, px
_KIND_HALF_PX = 5.0     # profiles that give a segment's kind and its first edge points
_SECOND_HALF_PX = 3.5   # profiles across the first fit's curve (it is within 1-2 px)
_MIN_STEP = 20.0        # grey levels: a step edge (edges.classify) ...
_MIN_DEPTH = 8.0        # ... and a thin line
# a line's offset is not better known than this, however long it is (pixel locking,
# ceiling texture: errors that do not average out along a line), px. Measured with
# this edge measurement on rendered placements (blur 0.8 px, with and without noise):
# the lines' offsets from the true image lines scatter by 0.007 px beyond what their
# points' residuals (rms / sqrt(n)) explain
SYSTEMATIC_PX = 0.007
# every measured line may also sit this far off together, in u and in v (1 sigma), px:
# a shift common to all lines and images, which no number of lines averages away.
# On rendered placements (benchmarks/bench_mount.py --sigma-seeds 12) tilt comes out
# +0.0025 deg on average and +0.0057 deg at most (one pixel is 1/f rad of tilt, f = 400
# px: 0.017 and 0.040 px); the reported 1 sigma covers the largest
SYSTEMATIC_SHIFT_PX = 0.04
# a fit that leaves more than this (px, RMS over inlier endpoints) has laid the lines on
# the wrong site lines: typically seams too blurred to see (only lamp edges and wall
# junctions left, which fit several offsets) or lines missing from site.yaml
MAX_RMS_PX = 1.0
# the weighted residuals should scatter like the edge points about their own lines
# (Placement.noise_px, measured apart from the model): on rendered placements the ratio
# RMS / noise is 0.64-1.17 (blur 0.8-1.5 px); placements whose measured y are all 5 cm
# off give 2.1, 10 cm 4.0. A fit whose chi-square per degree of freedom exceeds this
# has data that disagree with the model (wrong measurements or site), whatever its RMS.
MAX_CHI2_PER_DOF = 2.5
# a fitted parameter whose 1 sigma exceeds this is not determined by the data (too few
# lines, placements too alike): refused rather than written (radians, metres)
MAX_SIGMA = {"pan": math.radians(0.25), "tilt": math.radians(0.25),
             "swing": math.radians(0.25), "mx": 0.01, "my": 0.01, "h": 0.01}
_KINDS = {1.0: "step", -1.0: "step", 0.0: "thin"}


@dataclass(frozen=True)
class EdgeLine:
    """A ceiling line measured in one image: a straight line in undistorted
    normalized coordinates fitted to its edge points.

    Attributes:
        centre_n: ``(2,)`` centroid of the edge points, normalized.
        direction_n: ``(2,)`` unit direction.
        spread_n: standard deviation of the points along the line, normalized.
        n: number of edge points kept.
        rms_px: RMS of the points about the line, pixels.
        kind: ``step``, ``dark`` or ``bright`` (a seam).
    """

    centre_n: np.ndarray
    direction_n: np.ndarray
    spread_n: float
    n: int
    rms_px: float
    kind: str


def _located_fit(camera: CameraModel, base_px: np.ndarray, nrm_px: np.ndarray,
                 loc: np.ndarray, f_px: float, min_points: int):
    """The robust line (:func:`edges.fit_lines_robust`) through the located edge points
    ``base + loc nrm`` (``(K, 2)``, ``(K, 2)``, ``(K,)`` NaN: not located), undistorted.
    Returns ``(centre_n, direction_n, points_n (M, 2) kept, rms_px)`` or None when fewer
    than ``min_points`` are kept."""
    good = np.isfinite(loc)
    if np.count_nonzero(good) < min_points:
        return None
    pts = camera.unproject(base_px[good] + loc[good, None] * nrm_px[good])
    line, _, cnt, ssr, kept = fit_lines_robust(pts[None, :, 0], pts[None, :, 1],
                                               np.ones((1, pts.shape[0]), bool), f_px)
    if cnt[0] < min_points:
        return None
    p = pts[kept[0]]
    a, b = line[0, 0], line[0, 1]
    direction = np.array([b, -a])
    return p.mean(axis=0), direction, p, f_px * math.sqrt(ssr[0] / cnt[0])


def _curve_normals(camera: CameraModel, c: np.ndarray, d: np.ndarray, tt: np.ndarray,
                   f_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(K, 2)`` and unit normals ``(K, 2)`` of the image (a curve) of the
    normalized line ``c + t d`` at ``tt (K,)``."""
    q = c[None, :] + tt[:, None] * d[None, :]
    dq = 0.5 / f_px * d
    tan = camera.distort(q + dq) - camera.distort(q - dq)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    return camera.distort(q), np.stack([-tan[:, 1], tan[:, 0]], axis=1)


def _measure_one(camera: CameraModel, gray_f: np.ndarray, s: np.ndarray, f_px: float,
                 min_points: int) -> EdgeLine | None:
    """One detector segment ``(4,)`` (pixels) measured as an :class:`EdgeLine`, or None."""
    p1, p2 = s[:2], s[2:]
    length = float(np.hypot(*(p2 - p1)))
    k = int((length - 6.0) // _STEP_PX) + 1
    if k < min_points:
        return None
    _, nrm = directions(s[None])
    base = p1 + (p2 - p1) / length * (3.0 + _STEP_PX * np.arange(k))[:, None]
    nrm_k = np.tile(nrm, (k, 1))
    # kind from the mean profile, then pass 1: edge points across the detected chord
    offs, _, inner = edge_grid(1, _KIND_HALF_PX)
    prof = profiles_at(gray_f, base.T[:, None, :], nrm_k.T[:, None, :], offs)   # (1, K, O)
    pol, _ = classify(prof.mean(axis=1), offs, _MIN_STEP, _MIN_DEPTH, shift=False)
    if not np.isfinite(pol[0]):
        return None
    kind = _KINDS[float(pol[0])]
    if kind == "thin":
        kind = "dark" if thin_sign(prof, inner)[0][0] < 0 else "bright"
    fit = _located_fit(camera, base, nrm_k, locate(prof, pol, offs, inner)[0], f_px,
                       min_points)
    if fit is None:
        return None
    c, d, pts_n, _ = fit
    # pass 2: across the fitted line's image (a curve), ends trimmed: near a lamp's
    # corner the other side's edge enters the profiles
    t = (pts_n - c) @ d
    tt = np.arange(t.min() + _TRIM_PX / f_px, t.max() - _TRIM_PX / f_px + 1e-12,
                   _STEP_PX / f_px)
    if tt.size < min_points:
        return None
    base2, nrm2 = _curve_normals(camera, c, d, tt, f_px)
    # keep the polarity of pass 1 (the normals may have flipped with the fit's direction)
    pol2 = pol * (float(np.sign(np.mean(nrm2 @ nrm[0]))) or 1.0)
    h, w = gray_f.shape[:2]
    inside = (base2[:, 0] > 3) & (base2[:, 0] < w - 4) & (base2[:, 1] > 3) & \
        (base2[:, 1] < h - 4)
    base2, nrm2 = base2[inside], nrm2[inside]
    if base2.shape[0] < min_points:
        return None
    offs2, _, inner2 = edge_grid(1, _SECOND_HALF_PX)
    prof2 = profiles_at(gray_f, base2.T[:, None, :], nrm2.T[:, None, :], offs2)
    fit = _located_fit(camera, base2, nrm2, locate(prof2, pol2, offs2, inner2)[0], f_px,
                       min_points)
    if fit is None:
        return None
    c2, d2, p, rms_px = fit
    return EdgeLine(c2, d2, float(np.std((p - c2) @ d2)), p.shape[0], rms_px, kind)


def measure_lines(camera: CameraModel, gray: np.ndarray, segs_px: np.ndarray,
                  min_points: int = 8) -> list[EdgeLine]:
    """Re-measure detected segments ``(N, 4)`` (pixels) to sub-pixel, lens removed.

    The one edge measurement (``runtime/features/edges.py``) on float samples: each
    segment's kind comes from its mean profile (:func:`edges.classify`: a step edge, a
    lamp's side, or a thin seam, dark or bright; unclear segments are left out); edge
    points every 2 px are located on the profiles across it (:func:`edges.locate`: a
    step's crossing of the middle of its two sides, a seam's middle, not one of its two
    edges), undistorted and fitted by a robust straight line in normalized coordinates
    (:func:`edges.fit_lines_robust`, so the lens' curvature is not folded into the fit);
    then the points are re-measured across that line's image (a curve) and fitted
    again. Segments that measure the same line (a seam's two edges) are kept once.
    """
    gray_f = np.asarray(gray, dtype=np.float32)
    f_px = 0.5 * (camera.fx + camera.fy)
    out = [e for s in np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
           if (e := _measure_one(camera, gray_f, s, f_px, min_points)) is not None]
    return _dedupe(out, f_px)


def _dedupe(lines: list[EdgeLine], f_px: float, tol_px: float = 1.0) -> list[EdgeLine]:
    """Keep one of the lines measuring the same image line over overlapping extents."""
    order = sorted(range(len(lines)), key=lambda i: -lines[i].n)
    kept: list[EdgeLine] = []
    for i in order:
        e = lines[i]
        dup = False
        for k in kept:
            nk = np.array([-k.direction_n[1], k.direction_n[0]])
            if abs(float(e.direction_n @ nk)) > 0.02:
                continue
            ends = e.centre_n[None, :] + np.array([[-1.0], [1.0]]) * math.sqrt(3.0) * \
                e.spread_n * e.direction_n[None, :]
            if np.max(np.abs((ends - k.centre_n) @ nk)) * f_px > tol_px:
                continue
            te = (ends - k.centre_n) @ k.direction_n
            half_k = math.sqrt(3.0) * k.spread_n
            overlap = min(te.max(), half_k) - max(te.min(), -half_k)
            if overlap > 0.3 * (te.max() - te.min()):
                dup = True
                break
        if not dup:
            kept.append(e)
    return kept


def lines_to_segments(lines: Sequence[EdgeLine], floor_px: float = SYSTEMATIC_PX
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Equivalent segments ``(N, 4)`` (normalized) and residual weights ``(N, 2)``.

    A line fitted to ``n`` points spread ``s`` along it is represented by the segment
    ``centre -+ sqrt(3) s direction``: its endpoints' distances ``d1, d2`` to a model
    line give the offset at the centre ``(d1 + d2) / 2`` (variance ``sigma^2 / n``)
    and the turn ``d2 - d1`` (variance ``12 sigma^2 / n``), independent of each other.
    The weights ``(sqrt(n), sqrt(n / 12))``, divided by the line's noise relative to
    the median line's, make both residuals carry one edge point's noise.
    """
    if not lines:
        return np.zeros((0, 4)), np.zeros((0, 2))
    rms = np.array([e.rms_px for e in lines])
    ref = float(np.median(rms))
    segs, wts = [], []
    for e in lines:
        half = math.sqrt(3.0) * e.spread_n * e.direction_n
        segs.append(np.concatenate([e.centre_n - half, e.centre_n + half]))
        sig = max(e.rms_px, 0.5 * ref)
        wts.append([ref / math.sqrt(sig ** 2 / e.n + floor_px ** 2),
                    ref / math.sqrt(12.0 * sig ** 2 / e.n + (2.0 * floor_px) ** 2)])
    return np.array(segs), np.array(wts)


# ----------------------------------------------------------------------------- model
def _endpoints_h(segs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = segs.shape[0]
    p1 = np.hstack([segs[:, :2], np.ones((n, 1))])
    p2 = np.hstack([segs[:, 2:], np.ones((n, 1))])
    return p1, p2, 0.5 * (p1 + p2)


def _line_dist(l: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distances (normalized units) of points ``p`` (N,3) to lines ``l`` (N,3)."""
    return np.sum(l * p, axis=1) / np.maximum(np.hypot(l[:, 0], l[:, 1]), 1e-300)


def _rotation(pan: float, tilt: float, swing: float, yaw: float) -> np.ndarray:
    return rot_z(yaw + pan) @ R_level_cam(tilt, swing)


def _direction_residuals(segs: np.ndarray, R: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Endpoint distances to the line through each midpoint and its family's vanishing
    point (``which``: 0 along x, 1 along y). ``(N, 2)``."""
    p1, p2, m = _endpoints_h(segs)
    d = np.where(which[:, None] == 0, R.T[:, 0][None, :], R.T[:, 1][None, :])
    l = np.cross(m, d)
    return np.stack([_line_dist(l, p1), _line_dist(l, p2)], axis=1)


def _along_residuals(segs: np.ndarray, R: np.ndarray, c_y: float, h: float,
                     y_lines: np.ndarray) -> np.ndarray:
    """Endpoint distances to the image of the ceiling line ``y_lines[i]`` (N, 2)."""
    p1, p2, _ = _endpoints_h(segs)
    nW = np.stack([np.zeros_like(y_lines), np.full_like(y_lines, h), c_y - y_lines], axis=1)
    l = nW @ R  # rows: R^T n
    return np.stack([_line_dist(l, p1), _line_dist(l, p2)], axis=1)


class _Problem:
    """Parameters, associations and residuals of one calibration."""

    def __init__(self, placements: Sequence[Placement], site: Site, start: dict[str, float],
                 free: Sequence[str], f_px: float):
        self.pl = list(placements)
        self.site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
        self.start = dict(start)
        self.free = list(free)
        self.f_px = f_px
        self.n_drive = sum(1 for p in self.pl if not p.measured)
        # association per placement: -1 outlier, 0 across family, 1 + k along line k
        self.assoc = [np.full(p.segments_n.shape[0], -1) for p in self.pl]

    def unpack(self, theta: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
        vals = dict(self.start)
        for i, name in enumerate(self.free):
            vals[name] = float(theta[i])
        return vals, theta[len(self.free):]

    def theta0(self, psi0: Sequence[float] = ()) -> np.ndarray:
        return np.array([self.start[n] for n in self.free] + list(psi0), dtype=float)

    def residuals(self, theta: np.ndarray, per_placement: bool = False):
        v, psis = self.unpack(theta)
        out, k_drive = [], 0
        for p, a in zip(self.pl, self.assoc, strict=True):
            use = a >= 0
            if not np.any(use):
                out.append(np.zeros(0))
                if not p.measured:
                    k_drive += 1
                continue
            segs = p.segments_n[use]
            aa = a[use]
            wts = p.residual_weights()[use]
            if p.measured:
                R = _rotation(v["pan"], v["tilt"], v["swing"], p.yaw_rad)
                c_y = p.y_m + math.sin(p.yaw_rad) * v["mx"] + math.cos(p.yaw_rad) * v["my"]
                along = aa >= 1
                parts = []
                if np.any(along):
                    d = _along_residuals(segs[along], R, c_y, v["h"], self.site_y[aa[along] - 1])
                    parts.append(_whiten(d, wts[along]).ravel())
                if np.any(~along):
                    # a line across: only its direction is modelled (its x is unknown)
                    d = _direction_residuals(segs[~along], R, np.ones(int(np.sum(~along)), int))
                    parts.append(_whiten(d, wts[~along])[:, 1])
                r = np.concatenate(parts)
            else:
                R = _rotation(0.0, v["tilt"], v["swing"], float(psis[k_drive]))
                k_drive += 1
                d = _direction_residuals(segs, R, (aa == 0).astype(int))
                r = _whiten(d, wts)[:, 1]
            out.append(self.f_px * r)
        return out if per_placement else np.concatenate(out) if out else np.zeros(0)

    def associate(self, theta: np.ndarray, tol_px: float) -> int:
        """Re-make every segment's association at the current parameters."""
        v, psis = self.unpack(theta)
        k_drive, total = 0, 0
        for i, p in enumerate(self.pl):
            segs = p.segments_n
            n = segs.shape[0]
            if n == 0:
                continue
            cand = np.full((n, 1 + self.site_y.size), np.inf)
            if p.measured:
                R = _rotation(v["pan"], v["tilt"], v["swing"], p.yaw_rad)
                c_y = p.y_m + math.sin(p.yaw_rad) * v["mx"] + math.cos(p.yaw_rad) * v["my"]
                cand[:, 0] = _rms(_direction_residuals(segs, R, np.ones(n, int)))
                for k, yk in enumerate(self.site_y):
                    cand[:, 1 + k] = _rms(_along_residuals(segs, R, c_y, v["h"],
                                                           np.full(n, yk)))
            else:
                R = _rotation(0.0, v["tilt"], v["swing"], float(psis[k_drive]))
                k_drive += 1
                cand[:, 0] = _rms(_direction_residuals(segs, R, np.ones(n, int)))
                cand[:, 1] = _rms(_direction_residuals(segs, R, np.zeros(n, int)))
            cand *= self.f_px
            best = np.argmin(cand, axis=1)
            ok = cand[np.arange(n), best] < tol_px
            # a segment equally close to two lines is ambiguous: leave it out
            srt = np.sort(cand, axis=1)
            ok &= (srt[:, 1] > 2.0 * srt[:, 0]) | (srt[:, 1] > tol_px)
            self.assoc[i] = np.where(ok, best, -1)
            total += int(np.sum(ok))
        return total


def _whiten(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Endpoint distances ``(N, 2)`` to weighted (offset, turn) residuals ``(N, 2)``."""
    return np.stack([0.5 * (d[:, 0] + d[:, 1]) * w[:, 0], (d[:, 1] - d[:, 0]) * w[:, 1]],
                    axis=1)


def _rms(r: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(r * r, axis=1))


def _levenberg_marquardt(fun, theta: np.ndarray, iters: int = 50
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Minimize ``|fun(theta)|^2``; returns theta and the Jacobian at the solution."""
    lam = 1e-3
    r = fun(theta)
    cost = float(r @ r)
    J = _jacobian(fun, theta, r)
    for _ in range(iters):
        A = J.T @ J
        g = J.T @ r
        step = np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-12)), -g)
        cand = theta + step
        rc = fun(cand)
        cc = float(rc @ rc)
        if cc < cost:
            theta, r = cand, rc
            converged = cost - cc < 1e-12 * max(cost, 1e-30)
            cost = cc
            lam = max(lam / 5, 1e-9)
            J = _jacobian(fun, theta, r)
            if converged or np.max(np.abs(step)) < 1e-12:
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    return theta, J


def _jacobian(fun, theta: np.ndarray, r0: np.ndarray) -> np.ndarray:
    J = np.empty((r0.size, theta.size))
    for i in range(theta.size):
        h = 1e-7 * max(1.0, abs(theta[i]))
        tp = theta.copy()
        tm = theta.copy()
        tp[i] += h
        tm[i] -= h
        J[:, i] = (fun(tp) - fun(tm)) / (2 * h)
    return J


# ----------------------------------------------------------------------------- start
def _family_costs(p: Placement, Rs: np.ndarray, tau_px: float, f_px: float) -> np.ndarray:
    """Length-weighted, capped direction cost ``(K,)`` of one image's segments under each
    rotation ``Rs (K, 3, 3)``: every segment takes the nearer family (along x or y)."""
    p1, p2, m = _endpoints_h(p.segments_n)
    w = segment_lengths(p.segments_n) * f_px
    r = np.full((Rs.shape[0], m.shape[0]), np.inf)
    for fam in (0, 1):
        d = Rs[:, fam, :]                                   # R^T e_fam, (K, 3)
        l = np.cross(m[None, :, :], d[:, None, :])          # (K, N, 3)
        nrm = np.maximum(np.hypot(l[..., 0], l[..., 1]), 1e-300)
        d1 = np.sum(l * p1[None], axis=2) / nrm
        d2 = np.sum(l * p2[None], axis=2) / nrm
        r = np.minimum(r, np.sqrt(0.5 * (d1 * d1 + d2 * d2)) * f_px)
    r = np.minimum(r, tau_px)
    return (r * r) @ w


def _rotations(pans: np.ndarray, tilt: float, swing: float) -> np.ndarray:
    """``(K, 3, 3)`` rotations ``Rz(pan_k) R_level_cam(tilt, swing)``."""
    c, s = np.cos(pans), np.sin(pans)
    Rz = np.zeros((pans.size, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    return Rz @ R_level_cam(tilt, swing)


_DRIVE_YAWS = np.radians(np.arange(-40.0, 41.0, 4.0))


def _direction_costs(placements: Sequence[Placement], pans: np.ndarray, tilt: float,
                     swing: float, tau_px: float, f_px: float) -> np.ndarray:
    """Direction cost ``(K,)`` of the placements at each pan in ``pans`` ``(K,)``; a drive
    frame takes its best heading (every 4 deg within 40)."""
    cost = np.zeros(pans.size)
    for p in placements:
        if p.segments_n.shape[0] == 0:
            continue
        if p.measured:
            cost += _family_costs(p, _rotations(pans + p.yaw_rad, tilt, swing), tau_px, f_px)
        else:
            cost += float(np.min(_family_costs(p, _rotations(_DRIVE_YAWS, tilt, swing),
                                               tau_px, f_px)))
    return cost


def _coarse_angles(placements: Sequence[Placement], f_px: float, fixed: dict[str, float]
                   ) -> tuple[float, float, float]:
    pans = np.array([fixed["pan"]]) if "pan" in fixed else np.radians(np.arange(-40.0, 41.0,
                                                                                5.0))
    tilts = [fixed["tilt"]] if "tilt" in fixed else np.radians(np.arange(10.0, 90.1, 5.0))
    swings = [fixed["swing"]] if "swing" in fixed else np.radians(np.arange(-10.0, 10.1, 5.0))
    best = (math.inf, 0.0, 0.0, 0.0)
    for t in tilts:
        for s in swings:
            c = _direction_costs(placements, pans, t, s, 20.0, f_px)
            k = int(np.argmin(c))
            if c[k] < best[0]:
                best = (float(c[k]), float(pans[k]), t, s)
    return best[1], best[2], best[3]


# ----------------------------------------------------------------------------- API
def unobservable(placements: Sequence[Placement], fixed: Sequence[str] = ()
                 ) -> dict[str, str]:
    """The parameters these placements cannot determine (not in ``fixed``), each with
    what to add: ``mx`` (the forward offset) needs measured headings 5 deg or more apart
    (with one heading it only moves the camera along the corridor, which the lines
    along x do not see)."""
    measured = [p for p in placements if p.measured]
    out: dict[str, str] = {}
    yaws = np.array([p.yaw_rad for p in measured]) if measured else np.zeros(1)
    if "mx" not in fixed and np.ptp(yaws) < math.radians(5.0):
        out["mx"] = ("placements need headings at least 5 deg apart (add a placement "
                     "turned 10 deg or more)")
    return out


def calibrate_mount(rig: Rig, site: Site, placements: Sequence[Placement],
                    fixed: Sequence[str] = (), start: Mount | None = None,
                    fit_height: bool | None = None,
                    shift_px: float = SYSTEMATIC_SHIFT_PX) -> MountResult:
    """Fit the mount to measured placements (and any drive frames).

    Args:
        rig: the camera (its intrinsics are used) and the mount values used for
            held parameters (``mx`` when the headings barely differ; ``h`` from
            ``site.ceiling_height - mount.z``).
        site: the corridor's ``lines_along`` (required).
        placements: at least one measured placement; drive frames (no y, yaw) add
            to tilt and swing.
        fixed: parameter names (``pan tilt swing mx my h``) to hold at ``start``, or
            a mapping of them to the reason reported (``{"mx": "--fix mx=0.3"}``).
        start: the starting mount; ``None`` searches from scratch.
        fit_height: fit ``h``; default: when some placement shows two or more lines.
        shift_px: 1 sigma (px) of a shift common to every line of an image, in u and
            in v, added to the covariance (:func:`_shift_covariance`); 0 for the fit's
            noise alone.

    Raises:
        CalibrationError: no measured placement, or too few ceiling lines to fit.
    """
    if site.corridor is None:
        raise CalibrationError("the site has no `corridor` lines to calibrate against")
    measured = [p for p in placements if p.measured]
    if not measured:
        raise CalibrationError("no measured placement (each needs y and yaw)")
    f_px = 0.5 * (rig.camera.fx + rig.camera.fy)
    vals, fixed_set, held, fit_height = _start_values(rig, site, placements, fixed, start,
                                                      fit_height, f_px)
    prob, theta, J, free = _fit_stages(placements, site, vals, fixed_set, fit_height, f_px)
    n_in = sum(int(np.sum(a >= 0)) for a in prob.assoc)
    n_along = sum(int(np.sum(a >= 1)) for a in prob.assoc)
    if n_in < len(free) + 2 or n_along == 0 or J.shape[0] == 0:
        raise CalibrationError(
            f"too few ceiling lines matched the site ({n_in} segments, {n_along} along x): "
            "check the images show the corridor's lines and the site's lines_along")
    vals, _ = prob.unpack(theta)
    s2, sigma = _fit_sigmas(prob, theta, J, free, rig, shift_px)
    per_rms, outliers = _placement_outliers(prob, theta, site, vals, f_px, sigma)
    noises = [p.noise_px for p in prob.pl if p.measured and p.noise_px]
    chi2 = s2 / float(np.median(noises)) ** 2 if noises else math.nan
    _check_fit(s2, chi2, noises, sigma, free)
    z_m = site.ceiling_height_m - vals["h"]
    mount = Mount(pan_rad=vals["pan"], tilt_rad=vals["tilt"], swing_rad=vals["swing"],
                  x_m=vals["mx"], y_m=vals["my"], z_m=z_m)
    total = sum(p.segments_n.shape[0] for p in placements)
    return MountResult(mount, vals["h"], sigma, held, float(math.sqrt(s2)), per_rms, outliers,
                       n_in, total, chi2)


def _start_values(rig: Rig, site: Site, placements: Sequence[Placement],
                  fixed: Sequence[str] | Mapping[str, str], start: Mount | None,
                  fit_height: bool | None, f_px: float
                  ) -> tuple[dict[str, float], set[str], dict[str, str], bool]:
    """The starting values of :data:`PARAMS` (a coarse angle search without ``start``),
    the parameters held with why, and whether ``h`` is fitted."""
    m0 = start or rig.mount
    h0 = site.ceiling_height_m - rig.mount.z_m
    held: dict[str, str] = {}
    reasons = dict(fixed) if isinstance(fixed, Mapping) else {}
    fixed_set = set(fixed)
    for name in fixed_set:
        held[name] = reasons.get(name, "fixed by the caller")
    for name, why in unobservable(placements, fixed_set).items():
        fixed_set.add(name)
        held[name] = f"not observable: {why}"
    vals = {"pan": m0.pan_rad, "tilt": m0.tilt_rad, "swing": m0.swing_rad, "mx": m0.x_m,
            "my": m0.y_m, "h": h0}
    if start is None:
        pan, tilt, swing = _coarse_angles(placements, f_px,
                                          {k: vals[k] for k in fixed_set & _ANGLES})
        vals.update(pan=pan, tilt=tilt, swing=swing)
    if vals["tilt"] > math.radians(88.0) and "swing" not in fixed_set:
        fixed_set.add("swing")
        vals["swing"] = 0.0
        held["swing"] = "looking straight up: only pan + swing is observable (SPEC)"
    if fit_height is None:
        fit_height = "h" not in fixed_set
    if not fit_height:
        fixed_set.add("h")
        held.setdefault("h", "from the site's ceiling height and the rig's z")
    return vals, fixed_set, held, fit_height


def _fit_stages(placements: Sequence[Placement], site: Site, vals: dict[str, float],
                fixed_set: set[str], fit_height: bool, f_px: float
                ) -> tuple[_Problem, np.ndarray, np.ndarray, list[str]]:
    """The three stages of the fit: the angles from the lines' directions, the lateral
    offset (and height) by a search, then every free parameter; the last problem, its
    parameters, their Jacobian (no rows: never solved) and the free names."""
    # stage 1: directions only (angles)
    ang_free = [n for n in ("pan", "tilt", "swing") if n not in fixed_set]
    prob = _Problem(placements, site, vals, ang_free, f_px)
    psi0 = [0.0] * prob.n_drive
    theta = prob.theta0(psi0)
    for tol in (20.0, 8.0, 4.0):
        _associate_directions(prob, theta, tol)
        if any(np.any(a >= 0) for a in prob.assoc):
            theta, _ = _levenberg_marquardt(prob.residuals, theta)
    vals, psis = prob.unpack(theta)

    # stage 2: the lateral offset (and the height, when it is fitted), by a search
    # against the site's lines
    if "my" not in fixed_set:
        vals["my"], vals["h"] = _search_lateral(placements, site, vals, f_px,
                                                fit_height="h" not in fixed_set)

    # stage 3: everything, associations re-made at shrinking tolerances
    free = [n for n in PARAMS if n not in fixed_set]
    prob = _Problem(placements, site, vals, free, f_px)
    theta = prob.theta0(psis)
    J = np.zeros((0, len(free)))
    for tol in (12.0, 5.0, 3.0, 2.0):
        if prob.associate(theta, tol) < len(free) + 2:
            continue
        theta, J = _levenberg_marquardt(prob.residuals, theta)
    return prob, theta, J, free


def _fit_sigmas(prob: _Problem, theta: np.ndarray, J: np.ndarray, free: list[str],
                rig: Rig, shift_px: float) -> tuple[float, dict[str, float]]:
    """The residual variance per degree of freedom and each free parameter's 1 sigma
    (the fit's noise, plus a common shift of ``shift_px``)."""
    r = prob.residuals(theta)
    dof = max(r.size - theta.size, 1)
    s2 = float(r @ r) / dof
    try:
        JtJ_inv = np.linalg.inv(J.T @ J)
        cov = s2 * JtJ_inv
        if shift_px > 0:
            cov = cov + _shift_covariance(prob, theta, J, JtJ_inv, rig.camera, shift_px)
    except np.linalg.LinAlgError:
        cov = np.full((theta.size, theta.size), np.inf)
    sigma = {name: float(math.sqrt(max(cov[i, i], 0.0))) for i, name in enumerate(free)}
    return s2, sigma


def _placement_outliers(prob: _Problem, theta: np.ndarray, site: Site,
                        vals: dict[str, float], f_px: float, sigma: dict[str, float]
                        ) -> tuple[dict[str, float], list[tuple[str, float, str]]]:
    """Each measured placement's residual RMS, and those that disagree: their own lines
    put the vehicle elsewhere than measured (beyond 4 sigma of the fitted offset and
    1 cm), or their residuals stand out."""
    per = prob.residuals(theta, per_placement=True)
    per_rms = {}
    for p, rr in zip(prob.pl, per, strict=True):
        if p.measured:
            per_rms[p.label or f"#{len(per_rms)}"] = \
                float(np.sqrt(np.mean(rr * rr))) if rr.size else math.nan
    finite = [v for v in per_rms.values() if math.isfinite(v)]
    med = float(np.median(finite)) if finite else math.nan
    tol_m = max(0.01, 4.0 * sigma.get("my", 0.0))
    outliers = []
    for p, (label, rms) in zip([q for q in prob.pl if q.measured], per_rms.items(),
                               strict=True):
        dy = _placement_disagreement(p, site, vals, f_px)
        if abs(dy) > tol_m:
            outliers.append((label, rms, f"its lines put the vehicle {100 * dy:+.1f} cm "
                             "from the measured y"))
        elif math.isfinite(rms) and rms > max(3.0 * med, 1.0):
            outliers.append((label, rms, "residuals stand out"))
    return per_rms, outliers


def _check_fit(s2: float, chi2: float, noises: list[float], sigma: dict[str, float],
               free: list[str]) -> None:
    """Refuse a fit whose residuals exceed the edge points' own scatter, one that leaves
    a free parameter undetermined, or one whose residuals are large."""
    if math.sqrt(s2) <= MAX_RMS_PX and chi2 > MAX_CHI2_PER_DOF:
        raise CalibrationError(
            f"the fit's residuals ({math.sqrt(s2):.3f} px RMS) are "
            f"{math.sqrt(chi2):.1f} times the edge points' own scatter "
            f"({float(np.median(noises)):.3f} px; chi-square {chi2:.1f} per degree of "
            f"freedom, refused above {MAX_CHI2_PER_DOF:g}): the measured placements (y, "
            "yaw) and the site's lines_along disagree; re-measure the placements (a tape "
            "from the same wall for every y) and check site.yaml")
    weak = [f"{n} (1 sigma {math.degrees(sigma[n]):.2f} deg)" if n in _ANGLES else
            f"{n} (1 sigma {1e3 * sigma[n]:.1f} mm)"
            for n in free if not sigma[n] <= MAX_SIGMA[n]]
    if weak and math.sqrt(s2) <= MAX_RMS_PX:
        raise CalibrationError(
            f"these data do not determine {', '.join(weak)}: add placements (different "
            "lateral positions, headings 10 deg or more apart, images showing two or more "
            "lines along the corridor) or hold the parameter with --fix NAME=VALUE")
    if math.sqrt(s2) > MAX_RMS_PX:
        raise CalibrationError(
            f"the fit leaves {math.sqrt(s2):.2f} px RMS (a good one < 0.5): the lines seen "
            "do not lay on the site's lines_along at any offset; check that site.yaml lists "
            "every ceiling line along the corridor and that the seams are sharp in the "
            "images (focus, exposure)")


def _associate_directions(prob: _Problem, theta: np.ndarray, tol_px: float) -> None:
    v, psis = prob.unpack(theta)
    k_drive = 0
    for i, p in enumerate(prob.pl):
        segs = p.segments_n
        n = segs.shape[0]
        if n == 0:
            continue
        if p.measured:
            R = _rotation(v["pan"], v["tilt"], v["swing"], p.yaw_rad)
        else:
            R = _rotation(0.0, v["tilt"], v["swing"], float(psis[k_drive]))
            k_drive += 1
        ra = _rms(_direction_residuals(segs, R, np.zeros(n, int))) * prob.f_px
        rc = _rms(_direction_residuals(segs, R, np.ones(n, int))) * prob.f_px
        # families in the direction stage: 0 across (y), 1 along (x: code >= 1)
        prob.assoc[i] = np.where(np.minimum(ra, rc) < tol_px, np.where(ra <= rc, 1, 0), -1)
    prob.site_y = prob.site_y  # unchanged
    # along segments use only their direction in this stage
    prob_residuals = prob.residuals

    def direction_only(theta_: np.ndarray, per_placement: bool = False):
        v_, ps_ = prob.unpack(theta_)
        out, kd = [], 0
        for p_, a_ in zip(prob.pl, prob.assoc, strict=True):
            use = a_ >= 0
            if p_.measured:
                R_ = _rotation(v_["pan"], v_["tilt"], v_["swing"], p_.yaw_rad)
            else:
                R_ = _rotation(0.0, v_["tilt"], v_["swing"], float(ps_[kd]))
                kd += 1
            if not np.any(use):
                out.append(np.zeros(0))
                continue
            which = (a_[use] == 0).astype(int)
            d_ = _direction_residuals(p_.segments_n[use], R_, which)
            out.append(prob.f_px * _whiten(d_, p_.residual_weights()[use])[:, 1])
        return out if per_placement else np.concatenate(out)

    prob.residuals = direction_only  # type: ignore[method-assign]
    del prob_residuals


def _lateral_costs(p: Placement, R: np.ndarray, c_y: np.ndarray, h: float,
                   site_y: np.ndarray, f_px: float, cap_px: float = 6.0) -> np.ndarray:
    """Robust cost of laying a placement's segments on the site's along-lines, for each
    candidate camera lateral ``c_y`` (M,). Returns (M,)."""
    p1, p2, _ = _endpoints_h(p.segments_n)
    a, b = R.T[:, 1], R.T[:, 2]  # l = h a + (c_y - y_k) b
    # distances of both endpoints for each candidate (M), line (K), segment (N)
    off = c_y[:, None] - site_y[None, :]                       # (M, K)
    la = h * a
    norm = np.hypot(la[0] + off * b[0], la[1] + off * b[1])[:, :, None]
    sq = 0.0
    for q in (p1, p2):
        num = (q @ la)[None, None, :] + off[:, :, None] * (q @ b)[None, None, :]
        sq = sq + (num / norm * f_px) ** 2
    best = np.minimum(np.sqrt(0.5 * sq).min(axis=1), cap_px)  # (M, N)
    return np.sum(best ** 2 * segment_lengths(p.segments_n)[None, :], axis=1)


def _search_lateral(placements: Sequence[Placement], site: Site, vals: dict[str, float],
                    f_px: float, fit_height: bool = False) -> tuple[float, float]:
    """``(my, h)``: the lateral offset that best lays the along segments on the site's
    lines and, with ``fit_height``, the camera's height below the ceiling with it.

    The offsets of the lines scale with the height, so a height that is off (a rig
    file's guessed z) moves the far lines out of the cost's reach and can make a wrong
    offset win (one that lays wall junctions and seams on the site's seams and lamp
    edges). With ``fit_height`` the search is over both: a coarse grid of ``my`` (1 cm)
    by ``h`` (0.6-1.6 times the start, 2 % steps), then a fine one around the best.
    """
    site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
    use = [p for p in placements if p.measured and p.segments_n.shape[0]]
    rots = [_rotation(vals["pan"], vals["tilt"], vals["swing"], p.yaw_rad) for p in use]

    def best(grid: np.ndarray, heights: np.ndarray) -> tuple[float, float]:
        costs = np.zeros((heights.size, grid.size))
        for p, R in zip(use, rots, strict=True):
            c_y = p.y_m + math.sin(p.yaw_rad) * vals["mx"] + math.cos(p.yaw_rad) * grid
            for i, h in enumerate(heights):
                costs[i] += _lateral_costs(p, R, c_y, float(h), site_y, f_px)
        i, j = np.unravel_index(int(np.argmin(costs)), costs.shape)
        return float(grid[j]), float(heights[i])

    h0 = vals["h"]
    if not fit_height:
        return best(np.arange(-1.5, 1.5001, 0.005), np.array([h0]))[0], h0
    my, h = best(np.arange(-1.5, 1.5001, 0.01), h0 * 1.02 ** np.arange(-26, 24))
    return best(my + np.arange(-0.015, 0.0151, 0.001), h * (1.0 + np.arange(-0.03, 0.0301,
                                                                             0.003)))


def _shift_covariance(prob: _Problem, theta: np.ndarray, J: np.ndarray,
                      JtJ_inv: np.ndarray, camera: CameraModel, shift_px: float
                      ) -> np.ndarray:
    """Covariance of the parameters ``theta`` from a shift of ``shift_px`` (1 sigma)
    common to every line of every measured image, in u and in v.

    For each axis the segments are moved by ``eps`` pixels (``eps / fx`` or ``eps / fy``
    in normalized coordinates, associations kept) and the first-order response ``d theta
    = -(J^T J)^-1 J^T d r`` of the fit to one pixel is accumulated as ``shift_px^2
    d theta d theta^T``.
    """
    r0 = prob.residuals(theta)
    cov = np.zeros((theta.size, theta.size))
    eps = 0.01
    original = list(prob.pl)
    for axis, f in ((0, camera.fx), (1, camera.fy)):
        d = np.zeros(4)
        d[axis] = d[axis + 2] = eps / f
        prob.pl = [Placement(p.segments_n + d, p.y_m, p.yaw_rad, p.label, p.weights)
                   if p.measured else p for p in original]
        try:
            dr = (prob.residuals(theta) - r0) / eps
        finally:
            prob.pl = original
        dtheta = -JtJ_inv @ (J.T @ dr)
        cov += shift_px ** 2 * np.outer(dtheta, dtheta)
    return cov


def _placement_disagreement(p: Placement, site: Site, vals: dict[str, float],
                            f_px: float) -> float:
    """How far (m) this placement's own lines put the vehicle from its measured y."""
    site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
    spacing = float(np.min(np.diff(site_y))) if site_y.size > 1 else 1.0
    grid = np.arange(-0.45 * spacing, 0.45 * spacing + 1e-9, 0.001)
    R = _rotation(vals["pan"], vals["tilt"], vals["swing"], p.yaw_rad)
    c_y = p.y_m + math.sin(p.yaw_rad) * vals["mx"] + math.cos(p.yaw_rad) * vals["my"]
    cost = _lateral_costs(p, R, c_y + grid, vals["h"], site_y, f_px, cap_px=3.0)
    return float(grid[int(np.argmin(cost))])


def calibrate_tilt_swing(rig: Rig, drive: Sequence[Placement]) -> tuple[float, float, dict]:
    """Tilt and swing (radians) from frames of a straight drive, nothing measured.

    Returns ``(tilt, swing, report)`` with 1-sigma values and the residual RMS.
    """
    frames = [Placement(p.segments_n, None, None, p.label) for p in drive]
    if len(frames) < 2:
        raise CalibrationError("a drive needs at least two frames")
    f_px = 0.5 * (rig.camera.fx + rig.camera.fy)
    _, tilt, swing = _coarse_angles(frames, f_px, {"pan": 0.0})
    vals = {"pan": 0.0, "tilt": tilt, "swing": swing, "mx": 0.0, "my": 0.0, "h": 1.0}
    from ceilkit.runtime.config.site import Corridor
    from ceilkit.runtime.config.site import Site as _Site

    dummy = _Site(1.0, Corridor((0.0,)))
    prob = _Problem(frames, dummy, vals, ["tilt", "swing"], f_px)
    # each frame's heading: start from the coarse search's best
    psis = []
    for p in frames:
        yaws = np.radians(np.arange(-40.0, 41.0, 2.0))
        c = _family_costs(p, _rotations(yaws, tilt, swing), 20.0, f_px)
        psis.append(float(yaws[int(np.argmin(c))]))
    theta = prob.theta0(psis)
    J = np.zeros((0, 2))
    for tol in (20.0, 8.0, 4.0, 2.5):
        _associate_directions(prob, theta, tol)
        theta, J = _levenberg_marquardt(prob.residuals, theta)
    r = prob.residuals(theta)
    s2 = float(r @ r) / max(r.size - theta.size, 1)
    cov = s2 * np.linalg.pinv(J.T @ J)
    report = {"sigma_tilt": math.sqrt(max(cov[0, 0], 0.0)),
              "sigma_swing": math.sqrt(max(cov[1, 1], 0.0)),
              "rms_px": math.sqrt(s2), "frames": len(frames)}
    return float(theta[0]), float(theta[1]), report


# ----------------------------------------------------------------------------- files
def load_placements(source: str | Path, camera: CameraModel, max_frames: int = 0
                    ) -> list[Placement]:
    """Measured placements from a placements file or a recording with ``truth.csv``.

    A placements file (YAML), image paths relative to it, y in metres, yaw in degrees::

        placements:
          - {image: p1.png, y: 0.00, yaw: 0.0}
          - {image: p2.png, y: 0.30, yaw: 0.0}
          - {image: p3.png, y: -0.10, yaw: 12.0}

    A recording folder: every frame with a truth row (at most ``max_frames``, spread
    evenly) is a placement.
    """
    from ceilkit.runtime.config.yaml import load_yaml
    from ceilkit.runtime.errors import ConfigError
    from ceilkit.runtime.io.recording import Recording

    source = Path(source)
    out: list[Placement] = []
    if source.is_dir():
        rec = Recording(source)
        if rec.truth is None:
            raise ConfigError(source / "truth.csv", None,
                              "file not found: a recording used for placements needs it")
        ks = [k for k in range(len(rec)) if rec.truth.lookup(int(rec.t_ns[k])) is not None]
        if max_frames and len(ks) > max_frames:
            ks = [ks[int(i)] for i in np.linspace(0, len(ks) - 1, max_frames).round()]
        for k in ks:
            f = rec.frame(k)
            _, y, yaw = rec.truth.lookup(f.t_ns)
            out.append(placement_from_image(camera, f.image, y, yaw, f"frame {f.index}"))
        return out
    node = load_yaml(source).mapping(("placements",), required=("placements",))
    for pn in node.get("placements").items():
        pn.mapping(("image", "y", "yaw"), required=("image", "y", "yaw"))
        img_path = Path(pn.get("image").string())
        if not img_path.is_absolute():
            img_path = source.parent / img_path
        image, damage = read_image(img_path)  # a truncated JPEG is refused, not half grey
        if image is None:
            raise pn.get("image").error(f"cannot read the image: {damage}")
        out.append(placement_from_image(
            camera, image, pn.get("y").number(-100, 100, what=" m"),
            math.radians(pn.get("yaw").number(-180, 180, what=" degrees")), img_path.name))
    if not out:
        raise node.get("placements").error("expected at least one placement")
    return out


def load_drive(source: str | Path, camera: CameraModel, max_frames: int = 30
               ) -> list[Placement]:
    """Unmeasured drive frames from a recording or an image folder (truth ignored)."""
    from ceilkit.runtime.io.capture import ImageFolderSource
    from ceilkit.runtime.io.recording import Recording

    source = Path(source)
    src = Recording(source) if (source / "frames.csv").exists() else \
        ImageFolderSource(source)
    frames = list(src)
    if max_frames and len(frames) > max_frames:
        frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, max_frames).round()]
    return [placement_from_image(camera, f.image, label=f"drive {f.index}") for f in frames]
