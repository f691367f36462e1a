"""The corridor estimator: heading and lateral position from the ceiling's two line families.

After Yang & Tsai, "Viewing corridors as right parallelepipeds": the ceiling carries
lines along the corridor (W's x, at ``y = site.corridor.lines_along``) and
optionally lines across it (W's y). Their vanishing points lie on the ceiling's
vanishing line, which depends on the calibrated tilt and swing only; where the
forward vanishing point sits on it gives the camera's pan in W, and the image
lines of the forward family give the lateral position.

Convention (SPEC §1): ``R_world_cam = Rz(psi) @ M`` with ``psi = yaw + pan`` and
``M = rig.mount.R_level_cam``. A segment's homogeneous line ``l`` (undistorted
normalized coordinates) seen in the level frame is ``q = M l``; the along family's
vanishing direction is ``M^T (cos psi, -sin psi, 0)`` so its lines satisfy
``q_x cos psi - q_y sin psi = 0``; the across family's satisfy
``q_x sin psi + q_y cos psi = 0``. The plane through the optical centre and an
along line at ``y = y_j`` has the world normal ``n = Rz(psi) q`` and meets the
ceiling ``z = H`` at ``y_j = c_y - n_z (H - c_z) / n_y``.

Output: the vehicle's ``yaw_rad`` and ``y_m`` in W, ``x_m = None`` (not observed),
``lateral_m = y_m - site.corridor.axis_y_m``.

Example::

    est = CorridorEstimator(rig, site)
    pose = est.estimate(gray, t_ns)       # PoseEstimate, or a falsy Failure
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.lines import (
    SegmentDetector,
    refine_segments,
    refine_undistorted,
    segment_lengths,
    undistort_segments,
)
from ceilkit.runtime.geometry.rotations import rot_z, wrap_pi

# -- pure geometry ------------------------------------------------------------------


def level_normals(lines_cam: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``q = M l`` for lines ``(N, 3)`` (camera normalized coordinates): their
    interpretation planes' normals in the level frame, ``(N, 3)``."""
    return np.asarray(lines_cam, dtype=np.float64).reshape(-1, 3) @ np.asarray(M).T


def vanishing_directions(psi_rad: float, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame directions ``(3,)`` of W's x (along) and y (across) for camera pan
    ``psi_rad`` in W: ``M^T (cos psi, -sin psi, 0)`` and ``M^T (sin psi, cos psi, 0)``."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    return M.T @ np.array([c, -s, 0.0]), M.T @ np.array([s, c, 0.0])


def angle_residuals(lines: np.ndarray, mids: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Signed angle (rad, small-angle) between each segment and the line joining its
    midpoint ``mids (N, 2)`` to the vanishing point ``v (3,)`` (homogeneous,
    possibly at infinity). ``lines (N, 3)`` have ``hypot(a, b) = 1``."""
    den = np.hypot(v[0] - v[2] * mids[:, 0], v[1] - v[2] * mids[:, 1])
    return (lines @ v) / np.maximum(den, 1e-12)


def fit_pan(q_along: np.ndarray, q_across: np.ndarray, w_along: np.ndarray,
            w_across: np.ndarray) -> float:
    """Closed-form ``psi`` minimising ``sum w (q_x c - q_y s)^2`` over the along family
    plus ``sum w (q_x s + q_y c)^2`` over the across family (``c, s = cos, sin psi``):
    the smallest eigenvector of a 2x2 matrix. Returns psi in [-pi, pi) (defined mod pi)."""
    ax, ay = q_along[:, 0], -q_along[:, 1]
    bx, by = q_across[:, 1], q_across[:, 0]
    sxx = float(w_along @ (ax * ax) + w_across @ (bx * bx))
    syy = float(w_along @ (ay * ay) + w_across @ (by * by))
    sxy = float(w_along @ (ax * ay) + w_across @ (bx * by))
    # the 2x2 matrix's major axis is at 0.5 atan2(2 sxy, sxx - syy); the minor is normal
    th = 0.5 * math.atan2(2.0 * sxy, sxx - syy) + 0.5 * math.pi
    return th if th < math.pi else th - 2 * math.pi


def along_offsets(q: np.ndarray, psi_rad: float, height_m: float) -> np.ndarray:
    """``y_line - c_y`` (m) of along lines with level normals ``q (N, 3)``, for a camera
    ``height_m`` below the ceiling. NaN where the plane is parallel to W's y-z."""
    n = q @ rot_z(psi_rad).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(n[:, 1]) > 1e-12, -n[:, 2] * height_m / n[:, 1], np.nan)


def across_offsets(q: np.ndarray, psi_rad: float, height_m: float) -> np.ndarray:
    """``x_line - c_x`` (m) of across lines (parallel to W's y) with level normals ``q``."""
    n = q @ rot_z(psi_rad).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(n[:, 0]) > 1e-12, -n[:, 2] * height_m / n[:, 0], np.nan)


def free_vanishing_point(lines: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The unit homogeneous point ``(3,)`` closest (algebraically) to all ``lines``."""
    S = (lines * w[:, None]).T @ lines
    _, vecs = np.linalg.eigh(S)
    return vecs[:, 0]


def mount_from_vanishing_line(n_cam: np.ndarray) -> tuple[float, float]:
    """``(tilt, swing)`` radians whose ceiling vanishing line is ``n_cam`` (3,):
    the level frame's z seen from the camera is ``(-sin s cos t, -cos s cos t, sin t)``."""
    n = np.asarray(n_cam, dtype=float) / np.linalg.norm(n_cam)
    if n[2] < 0:
        n = -n
    return math.asin(min(1.0, n[2])), math.atan2(-n[0], -n[1])


@dataclass(frozen=True)
class OffsetMatch:
    """A 1-D association of observed offsets with the site's lines.

    Attributes:
        shift_m: ``c`` such that ``offset_i + c = site_y[assign_i]`` (the camera's y).
        assign: ``(N,)`` index into the site's lines, -1 for an unmatched offset.
        n_lines: how many distinct site lines are matched.
        weight: total weight of the matched offsets.
        runner_up: ``(score, weight, shift_m)`` of the best different hypothesis.
        score: sum over the site's lines of ``exp(-e^2 / 2 sigma^2)`` for the closest
            offset matched to each (``sigma = tol / 3``): about the number of lines
            matched, discounted by their misfit.
    """

    shift_m: float
    assign: np.ndarray
    n_lines: int
    weight: float
    runner_up: tuple[float, float, float] | None
    score: float = 0.0


def match_offsets(offsets: np.ndarray, weights: np.ndarray, site_y: np.ndarray,
                  tol_m: float, prior_shift_m: float | None = None,
                  anchors_m: np.ndarray | None = None,
                  compat: np.ndarray | None = None) -> OffsetMatch | None:
    """Find the shift ``c`` placing the observed offsets on the site's lines.

    Every pairing ``c = y_j - o_i`` is a hypothesis (refined once by a weighted
    mean over its inliers); it scores by the number of distinct site lines matched
    within ``tol_m``, then by the matched weight. With ``prior_shift_m`` the
    hypothesis nearest the prior wins among those matching at least as many lines
    as the best one less one. Missing, extra and shifted lines are tolerated.
    ``anchors_m``, independent estimates of the shift (lamp ends: see
    :class:`CorridorEstimator`), add up to one to the score of the hypotheses they
    agree with: they break the tie between hypotheses shifted by a line spacing.
    ``compat`` ``(N, J)`` in [0, 1] says how well offset i can be site line j (its
    edge kind: a lamp's edge is a step with its bright side inward, a seam a thin
    line); 0 forbids the pairing, other values scale its score. None: all 1.
    Returns None when nothing is matched.
    """
    o_all = np.asarray(offsets, dtype=float)
    ok = np.flatnonzero(np.isfinite(o_all))
    if ok.size == 0:
        return None
    o = o_all[ok]
    w = np.asarray(weights, dtype=float)[ok]
    ys = np.asarray(site_y, dtype=float)
    nj = ys.size
    if compat is None:
        cw = None
        ii, jj = np.divmod(np.arange(o.size * nj), max(nj, 1))
    else:
        cw = np.asarray(compat, dtype=float).reshape(-1, nj)[ok]
        ii, jj = np.nonzero(cw > 0)
    if ii.size == 0:
        return None
    cands = ys[jj] - o[ii]
    # pairings closer than a quarter of the gate are one hypothesis (they refine alike):
    # the first of each, in the order of their keys (np.unique(..., return_index=True))
    key = np.round(cands * (4.0 / tol_m))
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.empty(ks.size, bool)
    first[0] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    cands = cands[order[first]]
    # each hypothesis: every offset to its nearest (allowed) site line; the shift is
    # refined once by the weighted mean over the inliers, keeping that association
    x = o[None, :] + cands[:, None]                                              # (K, N)
    D = np.abs(x[:, :, None] - ys)                                              # (K, N, J)
    if cw is not None:
        D += np.where(cw > 0, 0.0, 1e9)
    j = np.argmin(D, axis=2)
    d = x - ys[j]                                                                # (K, N)
    inl = np.abs(d) <= tol_m
    if cw is not None:
        cj = cw[np.arange(o.size), j]
        inl &= cj > 0
    wi = inl * w
    shift = (wi * d).sum(axis=1) / np.maximum(wi.sum(axis=1), 1e-300)
    c_ref = cands - shift
    d -= shift[:, None]
    inl &= np.abs(d) <= tol_m
    wi = inl * w
    sw = wi.sum(axis=1)
    sig = tol_m / 3.0
    g = _gauss(d / sig) * inl                                                    # (K, N)
    if cw is not None:
        g *= cj
    # per hypothesis and site line (bin 0: no line), the best inlier matched to it (the
    # soft score; g >= 0) and how many are
    jm = np.where(inl, j, -1)                                                    # (K, N)
    nk = cands.size
    bins = (np.arange(nk)[:, None] * (nj + 1) + (jm + 1)).ravel()
    best = np.zeros(nk * (nj + 1))
    np.maximum.at(best, bins, g.ravel())
    soft = best.reshape(nk, nj + 1)[:, 1:].sum(axis=1)
    n_hit = np.bincount(bins, minlength=nk * (nj + 1)).reshape(nk, nj + 1)[:, 1:]
    n_lines = np.count_nonzero(n_hit, axis=1)
    if anchors_m is not None and len(anchors_m):
        a = np.asarray(anchors_m, dtype=float)
        soft = soft + _gauss((c_ref[:, None] - a[None, :]) / sig).sum(axis=1) / a.size
    idx = np.flatnonzero(n_lines)
    if idx.size == 0:
        return None
    if prior_shift_m is not None:
        top = soft[idx].max()
        pool = idx[soft[idx] >= top - 1.0]
        win = int(pool[np.argmin(np.abs(c_ref[pool] - prior_shift_m))])
    else:
        win = int(idx[np.lexsort((-sw[idx], -soft[idx]))[0]])
    others = idx[np.abs(c_ref[idx] - c_ref[win]) > tol_m]
    runner = None
    if others.size:
        r = int(others[np.lexsort((-sw[others], -soft[others]))[0]])
        runner = (float(soft[r]), float(sw[r]), float(c_ref[r]))
    assign = np.full(o_all.size, -1)
    assign[ok] = jm[win]
    return OffsetMatch(float(c_ref[win]), assign, int(n_lines[win]), float(sw[win]), runner,
                       float(soft[win]))


def _gauss(z: np.ndarray) -> np.ndarray:
    """``exp(-z^2 / 2)``, floored at ``exp(-700)`` (1e-304) instead of going subnormal or
    to 0 (where numpy's exp is many times slower); the floor is far below anything
    these scores can resolve (it vanishes when added to a score)."""
    return np.exp(np.maximum(-0.5 * z ** 2, -700.0))


def periodic_spread(offsets: np.ndarray, weights: np.ndarray, spacing_m: float,
                    tol_m: float) -> tuple[int, float]:
    """How well offsets sit on a grid of ``spacing_m``: ``(inliers, weight)`` about the
    weighted circular mean phase."""
    o = np.asarray(offsets, dtype=float)
    ok = np.isfinite(o)
    if np.count_nonzero(ok) == 0:
        return 0, 0.0
    ph = 2 * np.pi * o[ok] / spacing_m
    m = math.atan2(float(np.sum(weights[ok] * np.sin(ph))), float(np.sum(weights[ok] *
                                                                          np.cos(ph))))
    r = np.abs(((ph - m + np.pi) % (2 * np.pi)) - np.pi) * spacing_m / (2 * np.pi)
    inl = r <= tol_m
    return int(np.count_nonzero(inl)), float(np.sum(weights[ok][inl]))


def visible_along_lines(rig: Rig, site: Site, x_m: float, y_m: float, yaw_rad: float,
                        min_length_px: float, step_m: float = 0.01,
                        reach_m: float = 40.0) -> np.ndarray:
    """Which ``lines_along`` a vehicle pose sees: ``(J,)`` bool, True where the line
    has a visible stretch at least ``min_length_px`` long in the image.

    The line ``y = y_j`` on the ceiling is sampled every ``step_m`` within ``reach_m``
    of the camera (a lamp edge only where its lamps are: see
    :class:`CorridorEstimator`), projected through the rig at the pose (SPEC §1), and
    its longest run of consecutive samples inside the image (and inside the lens's
    field, the image corners' radius) is measured in pixels. For benchmarks and tests:
    "frames with two or more forward lines in view".
    """
    cam, mount = rig.camera, rig.mount
    corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [-0.5, cam.height - 0.5],
                        [cam.width - 0.5, cam.height - 0.5]])
    r_max = float(np.max(np.hypot(*cam.unproject(corners).T))) * 1.02
    R_cw = mount.R_world_cam(yaw_rad).T
    C = mount.camera_position(x_m, y_m, yaw_rad)
    H = site.ceiling_height_m
    ys = np.asarray(site.corridor.lines_along_m, dtype=float)
    out = np.zeros(ys.size, bool)
    for j, yj in enumerate(ys):
        pieces = []
        for row in site.lamps:
            if min(abs(yj - row.y_m - 0.5 * row.width_m),
                   abs(yj - row.y_m + 0.5 * row.width_m)) < 0.01:
                for cx in row.centres()[:, 0]:
                    if abs(cx - C[0]) < reach_m:
                        pieces.append((cx - 0.5 * row.length_m, cx + 0.5 * row.length_m))
        if not pieces and not any(
                min(abs(yj - r.y_m - 0.5 * r.width_m), abs(yj - r.y_m + 0.5 * r.width_m))
                < 0.01 for r in site.lamps):
            pieces = [(C[0] - reach_m, C[0] + reach_m)]
        for x0, x1 in pieces:
            xs = np.arange(x0, x1 + 1e-9, step_m)
            P = np.stack([xs, np.full_like(xs, yj), np.full_like(xs, H)], axis=1)
            Pc = (P - C) @ R_cw.T
            z = Pc[:, 2]
            ok = z > 1e-6
            xy = np.where(ok[:, None], Pc[:, :2] / np.where(ok, z, 1.0)[:, None], 0.0)
            ok &= np.hypot(xy[:, 0], xy[:, 1]) <= r_max
            px = np.full((xs.size, 2), np.nan)
            if np.any(ok):
                px[ok] = cam.distort(xy[ok])
            ok &= np.isfinite(px[:, 0]) & cam.in_image(np.nan_to_num(px, nan=-1e9))
            if np.count_nonzero(ok) < 2:
                continue
            seg = np.hypot(*np.diff(px, axis=0).T)
            both = ok[1:] & ok[:-1]
            run = np.cumsum(~both)          # runs of consecutive visible samples
            if np.any(both) and np.bincount(run[both], seg[both]).max() >= min_length_px:
                out[j] = True
                break
    return out


# -- the estimator ----------------------------------------------------------------------


_KERNEL = np.exp(-0.5 * (np.arange(-16, 17) / 4.0) ** 2)


def _median_finite(a: np.ndarray) -> float:
    """The median of the finite values of ``a`` (NaN if none); as ``np.median``, without
    its overhead on a few values."""
    v = np.sort(a[np.isfinite(a)])
    m = v.size // 2
    if v.size == 0:
        return float("nan")
    return float(v[m]) if v.size % 2 else float(0.5 * (v[m - 1] + v[m]))


def _smooth_circular(hist: np.ndarray) -> np.ndarray:
    """``hist (B,)`` convolved circularly with a Gaussian of 4 bins."""
    return np.convolve(np.concatenate([hist[-16:], hist, hist[:16]]), _KERNEL, "valid")


@dataclass(frozen=True, eq=False)
class _Frame:
    """One frame's segments (undistorted normalized coordinates), computed once and
    shared by every pan candidate and hypothesis of :class:`CorridorEstimator`.

    Attributes:
        segs: ``(N, 4)`` endpoints. lines: ``(N, 3)`` their lines (``hypot(a, b) = 1``),
            a view of lines_t ``(3, N)``. len_n: ``(N,)`` lengths. mx, my: ``(N,)``
            midpoints. q: ``(N, 3)`` level normals ``M l``. pol: ``(N,)`` polarity.
        ceil_len: ``(N,)`` length on the ceiling (m; at most 10, 0 above the horizon).
        ceil_sx, ceil_sy: ``(N,)`` sums of the two endpoints' ceiling coordinates (m,
            level frame relative to the camera; twice the midpoint).
        lamp_end: ``(L, N)`` bool: as long on the ceiling as lamp row l is wide (20 %).
        tol: ``(N,)`` the family gate after the first pan fit (rad).
    """

    segs: np.ndarray
    lines: np.ndarray
    lines_t: np.ndarray
    len_n: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    q: np.ndarray
    pol: np.ndarray
    ceil_len: np.ndarray
    ceil_sx: np.ndarray
    ceil_sy: np.ndarray
    lamp_end: np.ndarray
    tol: np.ndarray


def check_setup(method: str, rig: Rig, site: Site, options: dict[str, Any],
                allowed: tuple[str, ...]) -> None:
    """The checks a corridor estimator makes when it is built: every option known, a
    `corridor` section in the site, and a rig that fits the site
    (:func:`~.site.check_rig_site`).

    Raises:
        ConfigError: naming the option or the site file's key.
    """
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(None, f"options.{unknown[0]}",
                          f"unknown option for {method} (expected one of "
                          f"{', '.join(allowed)})")
    if site.corridor is None:
        raise ConfigError(site.source, "corridor",
                          f"method {method!r} needs a `corridor` section")
    check_rig_site(rig, site)


_OPTIONS = ("detector", "refine", "edge_fit", "min_length_px", "max_segments", "angle_tol_deg",
            "match_tol_m", "inlier_px", "gn_iterations", "min_contrast", "min_elevation_deg")

_SEAM_STEP = 0.3        # compat of a step edge with a seam (a seam is seen as a thin line)
_DECISIVE = 2.0         # forward / across ceiling length ratio that settles the family


class CorridorEstimator:
    """Heading and lateral position from the ceiling's along/across line families.

    Args:
        rig: the camera and its mount (tilt and swing are used as calibrated).
        site: needs ``corridor``; ``ceiling_height_m`` must exceed ``mount.z_m``.
        detector: ``fld`` (default), ``lsd`` or ``hough`` (see :mod:`.lines`).
        refine: sub-pixel refinement of segments on image gradients in pixel space
            (:func:`.lines.refine_segments`; default False).
        edge_fit: locate each segment's edge on cross profiles, fit it in undistorted
            coordinates and tell steps from thin lines (:func:`.lines.refine_undistorted`;
            default True). Lamp edges are steps whose bright side is the lamp: this
            settles which site line a forward line is.
        min_length_px: shortest segment used (default 4 % of the image width).
        max_segments: only the longest ones are kept (default 120).
        angle_tol_deg: family membership gate about the vanishing point (default 2).
        match_tol_m: 1-D association gate for lateral offsets (default: a quarter of
            the closest spacing of ``lines_along``, at most 0.08 m).
        inlier_px: endpoint distance (px) gate of the final fit (default 2.5).
        gn_iterations: most joint Gauss-Newton steps on ``(psi, c_y)`` (default 6).
        min_contrast: grey-level spread below which a frame is blank (default 8).
        min_elevation_deg: image rows whose rays all rise less than this above the
            horizon hold no useful ceiling and are not searched (default 3).
    """

    name = "corridor"

    def __init__(self, rig: Rig, site: Site, **options: Any) -> None:
        check_setup(self.name, rig, site, options, _OPTIONS)
        self.rig, self.site = rig, site
        cam = rig.camera
        self.M = rig.mount.R_level_cam
        self.height_m = site.ceiling_height_m - rig.mount.z_m
        self.f_px = 0.5 * (cam.fx + cam.fy)
        self.site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
        gaps = np.diff(np.sort(self.site_y))
        default_tol = min(0.08, 0.25 * float(gaps.min())) if gaps.size else 0.08
        self.match_tol_m = float(options.get("match_tol_m", default_tol))
        self.refine = bool(options.get("refine", False))
        self.edge_fit = bool(options.get("edge_fit", True))
        min_len = float(options.get("min_length_px", 0.04 * cam.width))
        self.min_elevation = math.radians(float(options.get("min_elevation_deg", 3.0)))
        self.rows = self._ceiling_rows()
        self.detector = SegmentDetector(str(options.get("detector", "fld")), min_len,
                                        rows=self.rows, merge=False)
        self.max_segments = int(options.get("max_segments", 120))
        self.angle_tol = math.radians(float(options.get("angle_tol_deg", 2.0)))
        self.inlier_px = float(options.get("inlier_px", 2.5))
        self.gn_iterations = int(options.get("gn_iterations", 6))
        self.min_contrast = float(options.get("min_contrast", 8.0))
        self.site_pol, self.site_longest = self._site_polarity()
        self._MT = np.ascontiguousarray(self.M.T)
        self._M_rows = tuple(tuple(float(v) for v in row) for row in self.M)
        self._lamp_width = np.array([row.width_m for row in site.lamps], dtype=float)
        self._lamp_y = np.array([row.y_m for row in site.lamps], dtype=float)
        mount = rig.mount
        self._t_vc = mount.t_vehicle_cam
        self._pan = mount.pan_rad
        corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [-0.5, cam.height - 0.5],
                            [cam.width - 0.5, cam.height - 0.5]])
        self._r_max = float(np.max(np.hypot(*cam.unproject(corners).T))) * 1.02
        self._view_u = np.linspace(-30.0, 30.0, 601)
        self._lamp_pitch = np.zeros(self.site_y.size)
        for row in site.lamps:
            hw = 0.5 * row.width_m
            on = (np.abs(self.site_y - row.y_m - hw) < 0.01) | (
                np.abs(self.site_y - row.y_m + hw) < 0.01)
            self._lamp_pitch[on] = (row.pitch_m if row.count > 1 else 0.0) + row.length_m

    # -- per-rig and per-site constants -------------------------------------------------
    def _ceiling_rows(self) -> tuple[int, int]:
        """``(v0, v1)``: the image rows where some ray rises at least
        ``min_elevation_deg`` (where the ceiling can be)."""
        cam = self.rig.camera
        u = np.linspace(-0.5, cam.width - 0.5, 41)
        v = np.arange(cam.height, dtype=float)
        uu, vv = np.meshgrid(u, v)
        xy = cam.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
        r = np.hstack([xy, np.ones((xy.shape[0], 1))]) @ self.M.T
        with np.errstate(invalid="ignore"):
            elev = r[:, 2] / np.linalg.norm(r, axis=1)
        up = np.any((elev > math.sin(self.min_elevation)).reshape(v.size, u.size), axis=1)
        if not np.any(up):
            return 0, cam.height
        rows = np.flatnonzero(up)
        return max(0, int(rows[0]) - 2), min(cam.height, int(rows[-1]) + 3)

    def _site_polarity(self) -> tuple[np.ndarray, np.ndarray]:
        """Edge kind of each ``lines_along`` ``(J,)``: ``+1`` a lamp edge brighter on
        its +y side (the lamp), ``-1`` brighter on its -y side, ``0`` a seam; and
        the longest stretch ``(J,)`` (m) a segment on it can have on the ceiling:
        a lamp's length (with a margin) for a lamp edge, inf for a seam."""
        pol = np.zeros(self.site_y.size)
        longest = np.full(self.site_y.size, np.inf)
        for row in self.site.lamps:
            hw = 0.5 * row.width_m
            for sign in (1.0, -1.0):
                on = np.abs(self.site_y - (row.y_m - sign * hw)) < 0.01
                pol[on] = sign
                longest[on] = 1.15 * row.length_m + 0.1
        return pol, longest

    def _compat(self, pol_w: np.ndarray, ceil_len: np.ndarray) -> np.ndarray:
        """``(N, J)`` compatibility of observed forward segments (world polarity, NaN:
        unknown; ceiling length, m) with the site lines' kinds (see
        :func:`match_offsets`): a lamp edge is a step with the lamp's side bright and
        no longer than a lamp; a seam is a thin line (a step only at ``_SEAM_STEP``)."""
        sp = self.site_pol[None, :]
        p = pol_w[:, None]
        c = np.where(sp != 0, (p == sp).astype(float), np.where(p == 0, 1.0, _SEAM_STEP))
        c = np.where(np.isnan(p), 1.0, c)
        return c * (ceil_len[:, None] <= self.site_longest[None, :])

    # -- helpers -------------------------------------------------------------------------
    def _fail(self, t_ns: int, reason: str, detail: str, **diag: Any) -> Failure:
        return Failure(int(t_ns), self.name, reason, detail, diag)

    def _check_frame(self, gray: np.ndarray, t_ns: int) -> Failure | None:
        cam = self.rig.camera
        if gray.shape != (cam.height, cam.width):
            return self._fail(t_ns, "bad_frame", f"frame is {gray.shape[1]}x{gray.shape[0]}, "
                              f"the camera is {cam.width}x{cam.height}")
        sub = gray[::4, ::4]
        mean, std = (float(np.ravel(v)[0]) for v in cv2.meanStdDev(sub))
        if std < 0.5 * self.min_contrast:
            if mean >= 250:
                return self._fail(t_ns, "saturated_frame", "the frame is saturated")
            return self._fail(t_ns, "blank_frame", "the frame has no contrast")
        return None

    def _segments(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        segs = self.detector(gray)
        if segs.shape[0] > self.max_segments:
            segs = segs[np.argsort(-segment_lengths(segs))[:self.max_segments]]
        rms = np.zeros(segs.shape[0])
        if self.refine and segs.shape[0]:
            segs, rms = refine_segments(gray, segs)
        return segs, rms

    def _dominant_pans(self, q: np.ndarray, w: np.ndarray, n_peaks: int = 3) -> list[float]:
        """Modes of the segments' horizontal directions, mod 90 deg: candidate ``psi``."""
        theta = np.arctan2(-q[:, 0], q[:, 1])
        nbins = 720
        b = ((4 * theta) % (2 * np.pi)) / (2 * np.pi) * nbins
        fl = np.floor(b)
        i0 = fl.astype(int) % nbins
        fr = b - fl
        hist = np.bincount(i0, w * (1 - fr), nbins) + np.bincount((i0 + 1) % nbins, w * fr, nbins)
        sm = _smooth_circular(hist)
        peaks = []
        work = sm.copy()
        for _ in range(n_peaks):
            p = int(np.argmax(work))
            top = float(work[p])
            if top <= 0 or (peaks and top < 0.2 * peaks[0][1]):
                break
            y0, y1, y2 = float(sm[(p - 1) % nbins]), float(sm[p]), float(sm[(p + 1) % nbins])
            den = y0 - 2 * y1 + y2
            off = 0.5 * (y0 - y2) / den if abs(den) > 1e-12 else 0.0
            peaks.append((p, y1, (p + 0.5 + off) / nbins * 2 * np.pi / 4))
            # clear +-24 bins about the peak (circularly)
            lo, hi = p - 24, p + 25
            work[max(lo, 0):min(hi, nbins)] = 0.0
            if lo < 0:
                work[lo:] = 0.0
            if hi > nbins:
                work[:hi - nbins] = 0.0
        return [-th for _, _, th in peaks]

    def _vp_angles(self, psi: float, fr: _Frame) -> tuple[np.ndarray, np.ndarray]:
        """Each segment against the along (row 0) and across (row 1) vanishing points
        for camera pan ``psi``: ``(2, N)`` absolute angles (rad, small-angle; see
        :func:`angle_residuals`) and ``(2, N)`` ``|v_xy - v_z m|`` (at least 1e-12)."""
        V = np.array(self._vp_dirs(psi))                           # rows: va, vb (camera)
        vz = V[:, 2:]
        den = np.maximum(np.hypot(V[:, :1] - vz * fr.mx, V[:, 1:2] - vz * fr.my), 1e-12)
        return np.abs(V @ fr.lines_t) / den, den

    def _vp_dirs(self, psi: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """:func:`vanishing_directions` as floats: ``va = M^T (c, -s, 0)``,
        ``vb = M^T (s, c, 0)`` (``c, s = cos, sin psi``)."""
        c, s = math.cos(psi), math.sin(psi)
        m0, m1 = self._M_rows[0], self._M_rows[1]
        return (tuple(c * a - s * b for a, b in zip(m0, m1, strict=True)),
                tuple(s * a + c * b for a, b in zip(m0, m1, strict=True)))

    @staticmethod
    def _families(ang: np.ndarray, tol: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """``(along, across)`` ``(N,)`` bool: the nearer vanishing point of ``ang``
        ``(2, N)`` (:meth:`_vp_angles`), within ``tol`` (rad, scalar or ``(N,)``)."""
        along = (ang[0] <= ang[1]) & (ang[0] <= tol)
        across = (ang[1] < ang[0]) & (ang[1] <= tol)
        return along, across

    def _refine_pan(self, psi: float, fr: _Frame, along: np.ndarray, across: np.ndarray,
                    ang: np.ndarray, den: np.ndarray, iterations: int = 1) -> float:
        """IRLS on ``psi`` (weights length^2 / |v_xy - v_z m|^2, Huber at 1 px) from
        ``ang, den`` (:meth:`_vp_angles` at ``psi``): :func:`fit_pan` over both
        families, with weight 0 for the other segments."""
        q0, q1 = fr.q[:, 0], fr.q[:, 1]
        q00, q11, q01 = q0 * q0, q1 * q1, q0 * q1
        for it in range(iterations):
            if it:
                ang, den = self._vp_angles(psi, fr)
            r = np.where(along, ang[0], ang[1]) * fr.len_n * self.f_px        # px
            w = (fr.len_n / np.where(along, den[0], den[1])) ** 2 * np.minimum(
                1.0, 1.0 / np.maximum(r, 1e-9))
            wa = np.where(along, w, 0.0)
            wb = np.where(across, w, 0.0)
            # fit_pan: along rows (q_x, -q_y), across rows (q_y, q_x)
            sxx = float(wa @ q00 + wb @ q11)
            syy = float(wa @ q11 + wb @ q00)
            sxy = float((wb - wa) @ q01)
            th = 0.5 * math.atan2(2.0 * sxy, sxx - syy) + 0.5 * math.pi
            new = th if th < math.pi else th - 2 * math.pi
            # keep the branch (mod pi) nearest the current estimate
            new += np.pi * round((psi - new) / np.pi)
            done = abs(new - psi) < 1e-8
            psi = new
            if done:
                break
        return psi

    def _gn_setup(self, fr: _Frame, along: np.ndarray, across: np.ndarray,
                  assign: np.ndarray) -> dict[str, Any]:
        """The fixed inputs of :meth:`_residuals`, for the matched along segments'
        endpoints ``e = (ex, ey, 1)`` (K of them): ``e0, e1, ez (K,)`` = ``M[i] . e``
        (i = 0, 1, 2; then ``vb . e = s e0 + c e1`` and ``va . e = c e0 - s e1`` for
        ``c, s = cos, sin psi``) and their site lines' y ``(K,)``; for the across
        segments' lines ``l`` (B of them): ``p0, p1 (B,)`` = ``M[i] . l``, their
        midpoints ``(B,)`` and pixel scale (length f / sqrt 2)."""
        ia = np.flatnonzero(along & (assign >= 0))
        ep = fr.segs[ia].reshape(-1, 2)
        ex, ey = ep[:, 0], ep[:, 1]
        m0, m1, m2 = self._M_rows
        ib = np.flatnonzero(across)
        lb = fr.lines_t[:, ib]
        return {"n_a": ia.size, "y": np.repeat(self.site_y[assign[ia]], 2),
                "e0": m0[0] * ex + m0[1] * ey + m0[2], "e1": m1[0] * ex + m1[1] * ey + m1[2],
                "ez": m2[0] * ex + m2[1] * ey + m2[2],
                "p0": m0[0] * lb[0] + m0[1] * lb[1] + m0[2] * lb[2],
                "p1": m1[0] * lb[0] + m1[1] * lb[1] + m1[2] * lb[2],
                "mx_b": fr.mx[ib], "my_b": fr.my[ib],
                "scale_b": fr.len_n[ib] * (self.f_px / math.sqrt(2.0))}

    def _residuals(self, psi: float, cy: float, gd: dict[str, Any]) -> np.ndarray:
        """``(K + B, 3)``: the pixel residuals (column 2) and their Jacobian in
        ``(psi, c_y)`` (columns 0, 1): along endpoints (``gd``: :meth:`_gn_setup`) to
        their predicted ceiling line, and across segments' endpoint offsets from the
        line joining their midpoint to the across vanishing point.

        With ``R_cw = M^T Rz(-psi)`` the ceiling line ``y = y_j`` is seen as
        ``l = R_cw (0, h, -(y_j - c_y)) = h vb - (y_j - c_y) m2`` (``vb`` the across
        direction, ``R_cw``'s y column; ``m2 = M[2]``, its z column), so
        ``dl/dpsi = h va`` and ``dl/dc_y = m2``."""
        c, s = math.cos(psi), math.sin(psi)
        va, vb = self._vp_dirs(psi)
        h, f = self.height_m, self.f_px
        m2 = self._M_rows[2]
        e0, e1, ez = gd["e0"], gd["e1"], gd["ez"]
        na, kb = e0.size, gd["p0"].size
        out = np.empty((na + kb, 3))
        dy = gd["y"] - cy
        l0 = h * vb[0] - dy * m2[0]
        l1 = h * vb[1] - dy * m2[1]
        q = 1.0 / np.hypot(l0, l1)
        u = (h * (s * e0 + c * e1) - dy * ez) * q                  # signed distance
        dn_psi = h * (l0 * va[0] + l1 * va[1]) * q                  # d|l_xy|/dpsi
        dn_cy = (l0 * m2[0] + l1 * m2[1]) * q
        fq = f * q
        out[:na, 0] = (h * (c * e0 - s * e1) - u * dn_psi) * fq
        out[:na, 1] = (ez - u * dn_cy) * fq
        out[:na, 2] = u * f
        if kb:
            mx, my = gd["mx_b"], gd["my_b"]
            p0, p1 = gd["p0"], gd["p1"]
            bx = vb[0] - vb[2] * mx
            by = vb[1] - vb[2] * my
            den = np.hypot(bx, by)
            dden = (bx * (va[0] - va[2] * mx) + by * (va[1] - va[2] * my)) / den
            num = s * p0 + c * p1                                   # l . vb
            scale = gd["scale_b"] / den
            out[na:, 0] = ((c * p0 - s * p1) - num * dden / den) * scale   # l . va = dnum
            out[na:, 1] = 0.0
            out[na:, 2] = num * scale
        return out

    # -- the estimate -----------------------------------------------------------------------
    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> PoseEstimate | Failure:
        """Estimate ``(y, yaw)`` of the vehicle from one frame.

        Args:
            image: ``(H, W)`` grey or ``(H, W, 3)`` BGR frame, as captured.
            t_ns: capture time, ns.
            prior: a predicted pose; chooses among the 90/180 deg and line-shift
                hypotheses when the frame alone cannot.

        Returns:
            :class:`PoseEstimate` (``x_m = None``) or :class:`Failure` with reason
            ``bad_frame``, ``blank_frame``, ``saturated_frame``, ``too_few_lines``,
            ``no_ceiling_lines``, ``no_association`` or ``ambiguous``.
        """
        t0 = time.perf_counter()
        gray = to_grey(image)
        bad = self._check_frame(gray, t_ns)
        if bad is not None:
            return bad
        segs_px, fit_rms = self._segments(gray)
        if not self.edge_fit or segs_px.shape[0] < 2:
            return self.estimate_segments(segs_px, t_ns, prior, fit_rms, t0)
        segs_n, pol, rms = refine_undistorted(self.rig.camera, gray, segs_px)
        fit_rms = np.where(np.isfinite(rms), rms, fit_rms)
        return self._estimate(segs_n, segment_lengths(segs_px), t_ns, prior, fit_rms, pol, t0)

    def estimate_segments(self, segs_px: np.ndarray, t_ns: int,
                          prior: PoseEstimate | None = None,
                          fit_rms: np.ndarray | None = None,
                          t0: float | None = None,
                          polarity: np.ndarray | None = None) -> PoseEstimate | Failure:
        """The estimate from segments ``(N, 4)`` in pixels (already detected); only
        their endpoints are undistorted. ``polarity`` ``(N,)``: as
        :func:`.lines.edge_polarity` (None: unknown)."""
        t0 = time.perf_counter() if t0 is None else t0
        segs_px = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
        segs = undistort_segments(self.rig.camera, segs_px)
        pol = np.full(segs.shape[0], np.nan) if polarity is None else np.asarray(polarity, float)
        return self._estimate(segs, segment_lengths(segs_px), t_ns, prior, fit_rms, pol, t0)

    def _estimate(self, segs: np.ndarray, len_px: np.ndarray, t_ns: int,
                  prior: PoseEstimate | None, fit_rms: np.ndarray | None,
                  pol: np.ndarray, t0: float) -> PoseEstimate | Failure:
        """The estimate from undistorted normalized segments ``(N, 4)``, their pixel
        lengths ``(N,)`` and polarities ``(N,)``."""
        n_seg = segs.shape[0]
        fit_rms = np.zeros(n_seg) if fit_rms is None else fit_rms
        if n_seg < 2:
            return self._fail(t_ns, "too_few_lines", f"{n_seg} line segments found",
                              n_segments=n_seg)
        fr = self._frame(segs, pol)
        qxy = np.hypot(fr.q[:, 0], fr.q[:, 1])
        w_hist = len_px * np.minimum(1.0, qxy / 0.2)
        pans = self._dominant_pans(fr.q, w_hist)
        if not pans:
            return self._fail(t_ns, "no_ceiling_lines", "no dominant ceiling direction",
                              n_segments=n_seg)

        prior_psi = None if prior is None else prior.yaw_rad + self._pan
        if prior_psi is not None:   # the peak nearest the prior first (mod 90 deg)
            pans.sort(key=lambda p: abs(math.remainder(p - prior_psi, np.pi / 2)))
        best = None
        for psi0 in pans:
            cand = self._solve_from(psi0, fr, prior, prior_psi)
            if cand is None:
                continue
            if best is None or cand["score"] > best["score"]:
                best = cand
            if "failure" not in best and best["n_lines"] >= 2:
                break
        if best is None:
            return self._fail(t_ns, "too_few_lines",
                              "fewer than two forward ceiling lines could be associated",
                              n_segments=n_seg)
        if isinstance(best.get("failure"), tuple):
            reason, detail = best["failure"]
            return self._fail(t_ns, reason, detail, n_segments=n_seg)

        # -- joint Gauss-Newton on (psi, c_y) ------------------------------------------------
        psi, cy = best["psi"], best["cy"]
        along, across, assign = best["along"], best["across"], best["assign"]
        gd = self._gn_setup(fr, along, across, assign)
        # (the residuals and weights of the last step describe the solution: its step
        # was below 1e-5 rad and 0.2 mm (the one after it far smaller), or they ran out)
        h00 = h01 = h10 = h11 = wrr = 0.0
        r = np.zeros(0)
        for _ in range(max(1, self.gn_iterations)):
            A = self._residuals(psi, cy, gd)                 # (K, 3): J_psi, J_cy, r
            r = A[:, 2]
            w = np.minimum(1.0, 1.0 / np.maximum(np.abs(r), 1e-9))  # Huber, k = 1 px
            # the weighted normal equations and sum of w r^2 in one product
            (h00, h01, g0), (h10, h11, g1), (_, _, wrr) = ((A * w[:, None]).T @ A).tolist()
            det = h00 * h11 - h01 * h10
            if not abs(det) > 1e-300:
                break
            d_psi = -(h11 * g0 - h01 * g1) / det
            d_cy = -(h00 * g1 - h10 * g0) / det
            psi, cy = psi + d_psi, cy + d_cy
            if abs(d_psi) < 1e-5 and abs(d_cy) < 2e-4:   # converging: the next is far smaller
                break
        dof = max(1, r.size - 2)
        sigma2 = wrr / dof
        det = h00 * h11 - h01 * h10
        if abs(det) > 1e-300:
            k = max(sigma2, 0.01) / det
            p00, p01, p10, p11 = h11 * k, -h01 * k, -h10 * k, h00 * k     # cov of (psi, c_y)
        else:
            p00 = p11 = np.inf
            p01 = p10 = float("nan")        # (as T diag(inf, inf) T^T: inf * 0)
        rms_px = math.sqrt(float(r @ r) / r.size) if r.size else float("nan")

        yaw = wrap_pi(psi - self._pan)
        cyaw, syaw = math.cos(yaw), math.sin(yaw)
        t_vx = cyaw * self._t_vc[0] - syaw * self._t_vc[1]      # (Rz(yaw) t_VC)_x, _y
        t_vy = syaw * self._t_vc[0] + cyaw * self._t_vc[1]
        y_m = cy - t_vy
        # (yaw, y) = (psi - pan, c_y - t_vy(yaw)): d(yaw, y)/d(psi, c_y) = [[1, 0], [-t_vx, 1]]
        cov = np.zeros((3, 3))
        cov[0, 0] = np.inf
        cov[2, 2] = p00
        cov[1, 2] = cov[2, 1] = p10 - t_vx * p00
        cov[1, 1] = t_vx * t_vx * p00 - t_vx * (p01 + p10) + p11

        vl = self._vanishing_line_check(fr, along, across)
        n_lines = int(best["n_lines"])
        quality = (min(1.0, n_lines / 3.0) * min(1.0, gd["n_a"] / 4.0)
                   / (1.0 + (rms_px / 1.5) ** 2))
        if best["ambiguous"]:
            quality *= 0.5
        pol_a = pol[along]
        diag = {
            "n_segments": n_seg,
            "n_along": int(np.count_nonzero(along)),
            "n_across": int(np.count_nonzero(across)),
            "n_lines_matched": n_lines,
            "n_steps": int(np.count_nonzero(np.abs(pol_a) == 1)),
            "n_thin": int(np.count_nonzero(pol_a == 0)),
            "rms_px": rms_px,
            "segment_fit_rms_px": _median_finite(fit_rms),
            "psi_deg": math.degrees(psi),
            "camera_y_m": cy,
            "ambiguous": bool(best["ambiguous"]),
            "hypothesis": best["how"],
            **vl,
            "time_ms": 1e3 * (time.perf_counter() - t0),
        }
        return PoseEstimate(int(t_ns), self.name, None, y_m, yaw, float(np.clip(quality, 0, 1)),
                            y_m - self.site.corridor.axis_y_m, cov, diag)

    def _frame(self, segs: np.ndarray, pol: np.ndarray) -> _Frame:
        """The per-frame arrays of undistorted normalized segments ``segs (N, 4)`` with
        polarities ``pol (N,)``, shared by every hypothesis."""
        dx, dy = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
        len_n = np.hypot(dx, dy)
        lines_t = np.empty((3, segs.shape[0]))                      # segment_lines, (3, N)
        inv = 1.0 / np.maximum(len_n, 1e-300)
        np.multiply(-dy, inv, out=lines_t[0])
        np.multiply(dx, inv, out=lines_t[1])
        np.multiply(segs[:, 0] * segs[:, 3] - segs[:, 2] * segs[:, 1], inv, out=lines_t[2])
        lines = lines_t.T
        ceil_pts = self._ceiling_points(segs)
        cdx, cdy = ceil_pts[:, 2] - ceil_pts[:, 0], ceil_pts[:, 3] - ceil_pts[:, 1]
        ceil_full = np.hypot(cdx, cdy)                  # NaN above the horizon
        ceil_len = np.minimum(ceil_full, 10.0)
        ceil_len[~(ceil_len >= 0)] = 0.0
        # across segments as long as a lamp is wide (see :meth:`_lamp_anchors`)
        lamp_end = (np.isfinite(ceil_full)[None, :]
                    & (np.abs(ceil_full[None, :] - self._lamp_width[:, None])
                       < 0.2 * self._lamp_width[:, None]))
        return _Frame(
            segs=segs, lines=lines, lines_t=lines_t, len_n=len_n,
            mx=0.5 * (segs[:, 0] + segs[:, 2]), my=0.5 * (segs[:, 1] + segs[:, 3]),
            q=lines @ self._MT, pol=pol, ceil_len=ceil_len,
            ceil_sx=ceil_pts[:, 0] + ceil_pts[:, 2], ceil_sy=ceil_pts[:, 1] + ceil_pts[:, 3],
            lamp_end=lamp_end,
            tol=np.minimum(self.angle_tol, 2 * self.inlier_px / np.maximum(len_n * self.f_px, 1)))

    def _hypothesis(self, k: int, psi: float, along: np.ndarray, across: np.ndarray,
                    fr: _Frame, lens: tuple[float, float],
                    prior: PoseEstimate | None) -> dict[str, Any]:
        """The labeling ``psi + k 90 deg`` (odd k: the families swap) scored on the site;
        ``lens``: the along and across families' summed ceiling lengths (m)."""
        pk = wrap_pi(psi + k * np.pi / 2)
        fa, fb = (along, across) if k % 2 == 0 else (across, along)
        len_a, len_b = lens if k % 2 == 0 else lens[::-1]
        wa = fr.len_n[fa] * self.f_px
        prior_shift = None
        if prior is not None and prior.y_m is not None:
            t_v = rot_z(wrap_pi(pk - self._pan)) @ self._t_vc
            prior_shift = prior.y_m + float(t_v[1])
        qa = fr.q[fa]
        c, s = math.cos(pk), math.sin(pk)
        n_y = s * qa[:, 0] + c * qa[:, 1]                 # (Rz(pk) q)_y
        offs = np.full(n_y.size, np.nan)                  # NaN: parallel to W's y-z
        np.divide(-qa[:, 2] * self.height_m, n_y, out=offs, where=np.abs(n_y) > 1e-12)
        pol_w = fr.pol[fa] * np.sign(n_y)
        compat = self._compat(pol_w, fr.ceil_len[fa])
        m = match_offsets(offs, wa, self.site_y, self.match_tol_m, prior_shift,
                          self._lamp_anchors(fr, fb, pk), compat)
        n_a = 0 if m is None else m.n_lines
        return {"k": k, "psi": pk, "fa": fa, "fb": fb, "match": m, "n_a": n_a,
                "offs": offs, "w": wa, "pol_w": pol_w, "compat": compat, "q_b": fr.q[fb],
                "len_nb": fr.len_n[fb],
                "elong": len_a - len_b, "len_a": len_a, "len_b": len_b}

    def _across_on_grid(self, h: dict[str, Any]) -> int:
        """How many across segments of hypothesis ``h`` sit on the ``lines_across``
        grid (0 unless two or more)."""
        corr = self.site.corridor
        if corr.lines_across is None or h["q_b"].shape[0] < 2:
            return 0
        n_b, _ = periodic_spread(across_offsets(h["q_b"], h["psi"], self.height_m),
                                 h["len_nb"], corr.lines_across.spacing_m, self.match_tol_m)
        return n_b if n_b >= 2 else 0

    def _solve_from(self, psi0: float, fr: _Frame, prior: PoseEstimate | None,
                    prior_psi: float | None) -> dict[str, Any] | None:
        """The families about pan candidate ``psi0``, the forward one and the lateral
        shift (a dict with ``score``, and ``failure`` or the solution); None when fewer
        than two segments belong to the families."""
        ang, den = self._vp_angles(psi0, fr)
        along, across = self._families(ang, self.angle_tol)
        if np.count_nonzero(along) + np.count_nonzero(across) < 2:
            return None
        psi = self._refine_pan(psi0, fr, along, across, ang, den)
        along, across = self._families(self._vp_angles(psi, fr)[0], fr.tol)
        if np.count_nonzero(along) + np.count_nonzero(across) < 2:
            return None
        la, lb = float(fr.ceil_len[along].sum()), float(fr.ceil_len[across].sum())

        def hyp(k: int) -> dict[str, Any]:
            return self._hypothesis(k, psi, along, across, fr, (la, lb), prior)

        how = "spacing"
        if prior_psi is not None:
            k = min(range(4), key=lambda k: abs(wrap_pi(psi + k * np.pi / 2 - prior_psi)))
            chosen = hyp(k)
            how = "prior"
        else:
            # of psi + k 90 deg, two keep yaw in (-90, 90] (k and k + 2 are a half
            # turn apart); the one whose forward family is longer on the ceiling first
            ks = [k for k in range(4)
                  if -np.pi / 2 < wrap_pi(psi + k * np.pi / 2 - self._pan) <= np.pi / 2]
            ks.sort(key=lambda k: -(la if k % 2 == 0 else lb))
            first = hyp(ks[0])
            if len(ks) < 2 or first["len_a"] >= _DECISIVE * first["len_b"]:
                chosen, how = first, "elongation"
            else:
                cands = [first, hyp(ks[1])]

                def frame_score(h: dict[str, Any]) -> tuple:
                    return (h["n_a"] + min(self._across_on_grid(h), 2), h["elong"])

                cands.sort(key=frame_score, reverse=True)
                chosen = cands[0]
                if frame_score(cands[1])[0] == frame_score(chosen)[0]:
                    how = "elongation"
                    if abs(cands[1]["elong"] - chosen["elong"]) < 1e-6:
                        # no evidence at all: the paper's rule, |pan| <= 45 deg
                        chosen = min(cands, key=lambda h: abs(h["psi"]))
                        how = "paper_rule"
        m = chosen["match"]
        if m is None or m.n_lines < 1 or np.count_nonzero(m.assign >= 0) < 2:
            return {"score": (-1, 0.0), "failure": (
                "no_association", "the forward lines do not match the site's lines_along")}
        ambiguous = self._is_ambiguous(m)
        if ambiguous:
            m, ambiguous = self._settle_by_absence(chosen, m)
            if not ambiguous and how != "prior":
                how += "+absence"
        if ambiguous and (prior is None or prior.y_m is None):
            return {"score": (m.n_lines, m.weight), "failure": (
                "ambiguous", f"{m.n_lines} forward lines fit two lateral positions "
                f"({m.shift_m:+.3f} m and {m.runner_up[2]:+.3f} m); no prior to choose")}
        assign = np.full(fr.q.shape[0], -1)
        assign[np.flatnonzero(chosen["fa"])] = m.assign
        return {"score": (m.n_lines, m.weight), "psi": chosen["psi"], "cy": m.shift_m,
                "along": chosen["fa"], "across": chosen["fb"], "assign": assign,
                "n_lines": m.n_lines, "ambiguous": ambiguous, "how": how}

    @staticmethod
    def _is_ambiguous(m: OffsetMatch) -> bool:
        return m.runner_up is not None and m.runner_up[0] >= 0.85 * m.score

    def _settle_by_absence(self, h: dict[str, Any], m: OffsetMatch
                           ) -> tuple[OffsetMatch, bool]:
        """Between the winning lateral shift and the runner-up, count against each the
        site lines it puts clearly in view (:meth:`_in_view`) that no forward segment
        of a fitting kind lies on; half a line each. Returns the match kept and whether
        the two are still within 15 %."""
        offs = h["offs"]
        ok = np.isfinite(offs)
        c_w, c_r = m.shift_m, m.runner_up[2]
        in_view = self._in_view(h["psi"], (c_w, c_r))
        adj = []
        for c, view in zip((c_w, c_r), in_view, strict=True):
            seen = np.any((np.abs(offs[ok][:, None] + c - self.site_y[None, :])
                           <= self.match_tol_m) & (h["compat"][ok] > 0), axis=0)
            adj.append(np.count_nonzero(view & ~seen))
        s_w, s_r = m.score - 0.5 * adj[0], m.runner_up[0] - 0.5 * adj[1]
        if s_r > s_w:
            alt = match_offsets(offs, h["w"], self.site_y, self.match_tol_m, c_r, None,
                                h["compat"])
            if alt is None or abs(alt.shift_m - c_r) > self.match_tol_m:
                return m, True
            m, s_w, s_r = alt, s_r, s_w
        return m, bool(s_r >= 0.85 * s_w)

    def _in_view(self, psi: float, cys: tuple[float, ...]) -> np.ndarray:
        """``(C, J)``: the site's ``lines_along`` clearly in view for camera pan ``psi``
        and each camera y in ``cys`` (C,): a visible stretch of at least 3
        ``min_length_px``, and for a lamp edge at least a lamp pitch of ceiling (so a
        lamp is in it)."""
        cam = self.rig.camera
        u = self._view_u                                         # (S,) m along W's x
        R_cw = self.M.T @ rot_z(-psi)
        J = self.site_y.size
        dy = (self.site_y[None, :] - np.asarray(cys, dtype=float)[:, None]).reshape(-1, 1)
        # the ceiling points (u, y_j - c_y, h) in the camera frame, per coordinate (C J, S)
        d0, d1, d2 = (u * R[0] + (dy * R[1] + self.height_m * R[2]) for R in R_cw)
        front = d2 > 1e-6
        z = np.where(front, d2, 1.0)
        x, y = d0 / z, d1 / z
        front &= np.hypot(x, y) <= self._r_max
        px = cam.distort(np.stack([x.ravel(), y.ravel()], axis=1)).reshape(*x.shape, 2)
        vis = front & cam.in_image(px.reshape(-1, 2), 2.0).reshape(x.shape)
        step = np.hypot(*np.diff(px, axis=1).transpose(2, 0, 1))
        both = vis[:, 1:] & vis[:, :-1]
        length_px = np.sum(np.where(both, step, 0.0), axis=1).reshape(-1, J)
        stretch_m = (np.sum(both, axis=1) * (u[1] - u[0])).reshape(-1, J)
        return (length_px >= 3 * self.detector.min_length_px) & (stretch_m >= self._lamp_pitch)

    def _ceiling_points(self, segs: np.ndarray) -> np.ndarray:
        """Endpoints ``(N, 4)`` back-projected onto the ceiling, in the level frame
        relative to the camera (m; NaN above the horizon). Needs no pan."""
        n = segs.shape[0]
        p = segs.reshape(-1, 2) @ self._MT[:2] + self._MT[2]         # M (x, y, 1), (2N, 3)
        up = p[:, 2:3] > 1e-6
        X = np.full((2 * n, 2), np.nan)
        np.multiply(p[:, :2], self.height_m / np.where(up, p[:, 2:3], 1.0), out=X,
                    where=up)
        return X.reshape(n, 4)

    def _lamp_anchors(self, fr: _Frame, sel: np.ndarray, psi: float) -> np.ndarray:
        """Camera y estimates from the segments ``sel`` ``(N,)`` bool (the across family)
        as long on the ceiling as a lamp is wide: the lamp's end, whose middle lies on
        the lamp row's y (for camera pan ``psi``)."""
        if not self.site.lamps or not sel.any():
            return np.zeros(0)
        c, s = math.cos(psi), math.sin(psi)
        out = []
        for row_y, ends in zip(self._lamp_y, fr.lamp_end, strict=True):
            ok = ends & sel
            out.append(row_y - 0.5 * (s * fr.ceil_sx[ok] + c * fr.ceil_sy[ok]))  # (Rz(psi) m)_y
        return np.concatenate(out)

    def _vanishing_line_check(self, fr: _Frame, along: np.ndarray,
                              across: np.ndarray) -> dict[str, float]:
        """The mount check: free vanishing points of both families against the
        calibrated tilt and swing."""
        n_pred = self.M[2, :]
        nan = float("nan")
        out = {"vanishing_line_residual_deg": nan, "vp_along_elevation_deg": nan,
               "implied_tilt_deg": nan, "implied_swing_deg": nan}
        ia = np.flatnonzero(along)
        if ia.size < 2:
            return out
        two = np.count_nonzero(across) >= 2
        # free_vanishing_point of each family: its scatter sum w l l^T (w = length^2)
        # from one product, the eigenproblems in one call
        w = fr.len_n ** 2
        Wl = np.empty((fr.len_n.size, 6 if two else 3))
        np.multiply(fr.lines, np.where(along, w, 0.0)[:, None], out=Wl[:, :3])
        if two:
            np.multiply(fr.lines, np.where(across, w, 0.0)[:, None], out=Wl[:, 3:])
        S = (fr.lines_t @ Wl).reshape(3, -1, 3).transpose(1, 0, 2)     # (F, 3, 3)
        v = np.linalg.eigh(S)[1][:, :, 0]                              # (F, 3) unit
        va = v[0]
        out["vp_along_elevation_deg"] = math.degrees(math.asin(min(1.0, abs(float(
            n_pred @ va)))))
        if two:
            vb = v[1]
            n = np.array([va[1] * vb[2] - va[2] * vb[1], va[2] * vb[0] - va[0] * vb[2],
                          va[0] * vb[1] - va[1] * vb[0]])
            nn = math.sqrt(float(n @ n))
            if nn > 1e-12:
                n /= nn
                out["vanishing_line_residual_deg"] = math.degrees(
                    math.acos(min(1.0, abs(float(n @ n_pred)))))
                tilt, swing = mount_from_vanishing_line(n)
                out["implied_tilt_deg"] = math.degrees(tilt)
                out["implied_swing_deg"] = math.degrees(swing)
        return out
