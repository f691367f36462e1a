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

from .errors import ConfigError
from .estimate import Failure, PoseEstimate
from .geometry import rot_z, wrap_pi
from .lines import (
    SegmentDetector,
    as_gray,
    refine_segments,
    segment_lengths,
    segment_lines,
    undistort_segments,
)
from .rig import Rig
from .site import Site, check_rig_site

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
    Ja = np.stack([q_along[:, 0], -q_along[:, 1]], axis=1)
    Jb = np.stack([q_across[:, 1], q_across[:, 0]], axis=1)
    S = (Ja * w_along[:, None]).T @ Ja + (Jb * w_across[:, None]).T @ Jb
    _, vecs = np.linalg.eigh(S)
    u = vecs[:, 0]
    return math.atan2(u[1], u[0])


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
                  anchors_m: np.ndarray | None = None) -> OffsetMatch | None:
    """Find the shift ``c`` placing the observed offsets on the site's lines.

    Every pairing ``c = y_j - o_i`` is a hypothesis (refined once by a weighted
    mean over its inliers); it scores by the number of distinct site lines matched
    within ``tol_m``, then by the matched weight. With ``prior_shift_m`` the
    hypothesis nearest the prior wins among those matching at least as many lines
    as the best one less one. Missing, extra and shifted lines are tolerated.
    ``anchors_m``, independent estimates of the shift (lamp ends: see
    :class:`CorridorEstimator`), add up to one to the score of the hypotheses they
    agree with: they break the tie between hypotheses shifted by a line spacing.
    Returns None when nothing is matched.
    """
    o_all = np.asarray(offsets, dtype=float)
    w_all = np.asarray(weights, dtype=float)
    ok = np.isfinite(o_all)
    if not np.any(ok):
        return None
    o, w = o_all[ok], w_all[ok]
    ys = np.asarray(site_y, dtype=float)
    cands = (ys[None, :] - o[:, None]).ravel()

    def assoc(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = np.abs(o[None, :, None] + c[:, None, None] - ys[None, None, :])   # (K, N, J)
        j = np.argmin(d, axis=2)
        e = np.take_along_axis(d, j[..., None], axis=2)[..., 0]
        return j, e, e <= tol_m

    j, e, inl = assoc(cands)
    wi = inl * w[None, :]
    sw = wi.sum(axis=1)
    c_ref = np.where(sw > 0, (wi * (ys[j] - o[None, :])).sum(axis=1) / np.maximum(sw, 1e-300),
                     cands)
    j, e, inl = assoc(c_ref)
    wi = inl * w[None, :]
    sw = wi.sum(axis=1)
    matched = np.zeros((c_ref.size, ys.size), bool)
    soft = np.zeros(c_ref.size)
    sig = tol_m / 3.0
    for jj in range(ys.size):
        hit = inl & (j == jj)
        matched[:, jj] = np.any(hit, axis=1)
        soft += np.max(np.where(hit, np.exp(-0.5 * (e / sig) ** 2), 0.0), axis=1)
    if anchors_m is not None and len(anchors_m):
        a = np.asarray(anchors_m, dtype=float)
        soft += np.mean(np.exp(-0.5 * ((c_ref[:, None] - a[None, :]) / sig) ** 2), axis=1)
    n_lines = matched.sum(axis=1)
    good = n_lines > 0
    if not np.any(good):
        return None
    idx = np.flatnonzero(good)
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
    score = float(soft[win])
    assign = np.full(o_all.size, -1)
    assign[np.flatnonzero(ok)] = np.where(inl[win], j[win], -1)
    return OffsetMatch(float(c_ref[win]), assign, int(n_lines[win]), float(sw[win]), runner,
                       score)


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


# -- the estimator ----------------------------------------------------------------------


_OPTIONS = ("detector", "refine", "min_length_px", "max_segments", "angle_tol_deg",
            "match_tol_m", "inlier_px", "gn_iterations", "min_contrast")


class CorridorEstimator:
    """Heading and lateral position from the ceiling's along/across line families.

    Args:
        rig: the camera and its mount (tilt and swing are used as calibrated).
        site: needs ``corridor``; ``ceiling_height_m`` must exceed ``mount.z_m``.
        detector: ``fld`` (default), ``lsd`` or ``hough`` (see :mod:`.lines`).
        refine: sub-pixel refinement of segments on image gradients (default False:
            FLD alone meets the accuracy targets, see docs/methods/corridor.md).
        min_length_px: shortest segment used (default 4 % of the image width).
        max_segments: only the longest ones are kept (default 120).
        angle_tol_deg: family membership gate about the vanishing point (default 2).
        match_tol_m: 1-D association gate for lateral offsets (default: a quarter of
            the closest spacing of ``lines_along``, at most 0.08 m).
        inlier_px: endpoint distance (px) gate of the final fit (default 2.5).
        gn_iterations: joint Gauss-Newton steps on ``(psi, c_y)`` (default 6).
        min_contrast: grey-level spread below which a frame is blank (default 8).
    """

    name = "corridor"

    def __init__(self, rig: Rig, site: Site, **options: Any) -> None:
        unknown = sorted(set(options) - set(_OPTIONS))
        if unknown:
            raise ConfigError(None, f"options.{unknown[0]}",
                              f"unknown option for {self.name} (expected one of "
                              f"{', '.join(_OPTIONS)})")
        if site.corridor is None:
            raise ConfigError(site.source, "corridor",
                              f"method {self.name!r} needs a `corridor` section")
        check_rig_site(rig, site)
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
        min_len = float(options.get("min_length_px", 0.04 * cam.width))
        self.detector = SegmentDetector(str(options.get("detector", "fld")), min_len)
        self.max_segments = int(options.get("max_segments", 120))
        self.angle_tol = math.radians(float(options.get("angle_tol_deg", 2.0)))
        self.inlier_px = float(options.get("inlier_px", 2.5))
        self.gn_iterations = int(options.get("gn_iterations", 6))
        self.min_contrast = float(options.get("min_contrast", 8.0))

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
        i0 = np.floor(b).astype(int) % nbins
        fr = b - np.floor(b)
        hist = np.bincount(i0, w * (1 - fr), nbins) + np.bincount((i0 + 1) % nbins, w * fr, nbins)
        k = np.arange(-16, 17)
        kern = np.exp(-0.5 * (k / 4.0) ** 2)
        sm = np.convolve(np.concatenate([hist[-16:], hist, hist[:16]]), kern, "valid")
        peaks = []
        work = sm.copy()
        for _ in range(n_peaks):
            p = int(np.argmax(work))
            if work[p] <= 0 or (peaks and work[p] < 0.2 * sm[peaks[0][0]]):
                break
            y0, y1, y2 = sm[(p - 1) % nbins], sm[p], sm[(p + 1) % nbins]
            den = y0 - 2 * y1 + y2
            off = 0.5 * (y0 - y2) / den if abs(den) > 1e-12 else 0.0
            peaks.append((p, (p + 0.5 + off) / nbins * 2 * np.pi / 4))
            for d in range(-24, 25):
                work[(p + d) % nbins] = 0.0
        return [-th for _, th in peaks]

    def _classify(self, psi: float, lines: np.ndarray, mids: np.ndarray,
                  tol: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        va, vb = vanishing_directions(psi, self.M)
        ra = angle_residuals(lines, mids, va)
        rb = angle_residuals(lines, mids, vb)
        along = (np.abs(ra) <= np.abs(rb)) & (np.abs(ra) <= tol)
        across = (np.abs(rb) < np.abs(ra)) & (np.abs(rb) <= tol)
        return along, across, np.where(np.abs(ra) <= np.abs(rb), ra, rb)

    def _refine_pan(self, psi: float, q: np.ndarray, lines: np.ndarray, mids: np.ndarray,
                    len_n: np.ndarray, along: np.ndarray, across: np.ndarray) -> float:
        for _ in range(4):
            va, vb = vanishing_directions(psi, self.M)
            da = np.hypot(va[0] - va[2] * mids[:, 0], va[1] - va[2] * mids[:, 1])
            db = np.hypot(vb[0] - vb[2] * mids[:, 0], vb[1] - vb[2] * mids[:, 1])
            ra = np.abs(lines @ va) / np.maximum(da, 1e-12) * len_n * self.f_px
            rb = np.abs(lines @ vb) / np.maximum(db, 1e-12) * len_n * self.f_px
            hub_a = np.minimum(1.0, 1.0 / np.maximum(ra, 1e-9))
            hub_b = np.minimum(1.0, 1.0 / np.maximum(rb, 1e-9))
            wa = (len_n ** 2 / np.maximum(da, 1e-12) ** 2 * hub_a)[along]
            wb = (len_n ** 2 / np.maximum(db, 1e-12) ** 2 * hub_b)[across]
            new = fit_pan(q[along], q[across], wa, wb)
            # keep the branch (mod pi) nearest the current estimate
            new += np.pi * round((psi - new) / np.pi)
            done = abs(new - psi) < 1e-10
            psi = new
            if done:
                break
        return psi

    def _residuals(self, params: np.ndarray, ep_h: np.ndarray, y_ep: np.ndarray,
                   across_lines: np.ndarray, across_mids: np.ndarray, across_len: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Pixel residuals and their Jacobian ``(K, 2)`` in ``(psi, c_y)``: along
        endpoints to their predicted ceiling line, and across segments' endpoint
        offsets from the line joining their midpoint to the across vanishing point."""
        psi, cy = float(params[0]), float(params[1])
        c, s = math.cos(psi), math.sin(psi)
        Rz_t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])   # Rz(-psi)
        dRz_t = np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])
        R_cw = self.M.T @ Rz_t
        dR_cw = self.M.T @ dRz_t
        dy = y_ep - cy
        n_w = np.stack([np.zeros_like(dy), np.full_like(dy, self.height_m), -dy], axis=1)
        lc = n_w @ R_cw.T
        dlc_psi = n_w @ dR_cw.T
        dlc_cy = np.broadcast_to(R_cw[:, 2], lc.shape)
        sp = np.sum(lc * ep_h, axis=1)
        nrm = np.hypot(lc[:, 0], lc[:, 1])
        ra = sp / nrm * self.f_px
        Ja = np.empty((ra.size, 2))
        for k, dl in enumerate((dlc_psi, dlc_cy)):
            ds = np.sum(dl * ep_h, axis=1)
            dn = (lc[:, 0] * dl[:, 0] + lc[:, 1] * dl[:, 1]) / nrm
            Ja[:, k] = (ds * nrm - sp * dn) / nrm ** 2 * self.f_px
        if not across_lines.shape[0]:
            return ra, Ja
        va, vb = vanishing_directions(psi, self.M)
        ex = vb[0] - vb[2] * across_mids[:, 0]
        ey = vb[1] - vb[2] * across_mids[:, 1]
        den = np.hypot(ex, ey)
        dex = va[0] - va[2] * across_mids[:, 0]
        dey = va[1] - va[2] * across_mids[:, 1]
        num = across_lines @ vb
        dnum = across_lines @ va
        dden = (ex * dex + ey * dey) / den
        scale = across_len * self.f_px / math.sqrt(2.0)
        rb = num / den * scale
        Jb = np.zeros((rb.size, 2))
        Jb[:, 0] = (dnum * den - num * dden) / den ** 2 * scale
        return np.concatenate([ra, rb]), np.vstack([Ja, Jb])

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
        gray = as_gray(image)
        bad = self._check_frame(gray, t_ns)
        if bad is not None:
            return bad
        segs_px, fit_rms = self._segments(gray)
        return self.estimate_segments(segs_px, t_ns, prior, fit_rms, t0)

    def estimate_segments(self, segs_px: np.ndarray, t_ns: int,
                          prior: PoseEstimate | None = None,
                          fit_rms: np.ndarray | None = None,
                          t0: float | None = None) -> PoseEstimate | Failure:
        """The estimate from segments ``(N, 4)`` in pixels (already detected)."""
        t0 = time.perf_counter() if t0 is None else t0
        segs_px = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
        fit_rms = np.zeros(segs_px.shape[0]) if fit_rms is None else fit_rms
        n_seg = segs_px.shape[0]
        if n_seg < 2:
            return self._fail(t_ns, "too_few_lines", f"{n_seg} line segments found",
                              n_segments=n_seg)
        segs = undistort_segments(self.rig.camera, segs_px)
        lines = segment_lines(segs)
        mids = 0.5 * (segs[:, :2] + segs[:, 2:])
        len_n = segment_lengths(segs)
        q = level_normals(lines, self.M)
        qxy = np.hypot(q[:, 0], q[:, 1])
        w_hist = segment_lengths(segs_px) * np.minimum(1.0, qxy / 0.2)
        pans = self._dominant_pans(q, w_hist)
        if not pans:
            return self._fail(t_ns, "no_ceiling_lines", "no dominant ceiling direction",
                              n_segments=n_seg)

        prior_psi = None if prior is None else prior.yaw_rad + self.rig.mount.pan_rad
        best = None
        for psi0 in pans:
            cand = self._solve_from(psi0, q, lines, mids, len_n, segs, prior, prior_psi)
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
        use_a = along & (assign >= 0)
        ep = segs[use_a].reshape(-1, 2)
        ep_h = np.hstack([ep, np.ones((ep.shape[0], 1))])
        y_ep = np.repeat(self.site_y[assign[use_a]], 2)
        al, am, alen = lines[across], mids[across], len_n[across]
        params = np.array([psi, cy])
        for _ in range(self.gn_iterations):
            r, J = self._residuals(params, ep_h, y_ep, al, am, alen)
            w = np.minimum(1.0, 1.0 / np.maximum(np.abs(r), 1e-9))  # Huber, k = 1 px
            H = (J * w[:, None]).T @ J
            g = (J * w[:, None]).T @ r
            try:
                step = np.linalg.solve(H + 1e-12 * np.eye(2), -g)
            except np.linalg.LinAlgError:
                break
            params = params + step
            if abs(step[0]) < 1e-9 and abs(step[1]) < 1e-8:
                break
        r, J = self._residuals(params, ep_h, y_ep, al, am, alen)
        w = np.minimum(1.0, 1.0 / np.maximum(np.abs(r), 1e-9))
        psi, cy = float(params[0]), float(params[1])
        dof = max(1, r.size - 2)
        sigma2 = float(np.sum(w * r ** 2) / dof)
        H = (J * w[:, None]).T @ J
        try:
            cov_pc = np.linalg.inv(H) * max(sigma2, 0.01)
        except np.linalg.LinAlgError:
            cov_pc = np.diag([np.inf, np.inf])
        rms_px = float(np.sqrt(np.mean(r ** 2))) if r.size else float("nan")

        mount = self.rig.mount
        yaw = wrap_pi(psi - mount.pan_rad)
        t_v = rot_z(yaw) @ mount.t_vehicle_cam
        y_m = cy - float(t_v[1])
        T = np.array([[1.0, 0.0], [-float(t_v[0]), 1.0]])   # d(yaw, y)/d(psi, c_y)
        cov_yy = T @ cov_pc @ T.T
        cov = np.zeros((3, 3))
        cov[0, 0] = np.inf
        cov[1, 1], cov[2, 2] = cov_yy[1, 1], cov_yy[0, 0]
        cov[1, 2] = cov[2, 1] = cov_yy[1, 0]

        vl = self._vanishing_line_check(lines, len_n, along, across)
        n_lines = int(best["n_lines"])
        quality = (min(1.0, n_lines / 3.0) * min(1.0, np.count_nonzero(use_a) / 4.0)
                   / (1.0 + (rms_px / 1.5) ** 2))
        if best["ambiguous"]:
            quality *= 0.5
        diag = {
            "n_segments": n_seg,
            "n_along": int(np.count_nonzero(along)),
            "n_across": int(np.count_nonzero(across)),
            "n_lines_matched": n_lines,
            "rms_px": rms_px,
            "segment_fit_rms_px": float(np.nanmedian(fit_rms)) if fit_rms.size else float("nan"),
            "psi_deg": math.degrees(psi),
            "camera_y_m": cy,
            "ambiguous": bool(best["ambiguous"]),
            "hypothesis": best["how"],
            **vl,
            "time_ms": 1e3 * (time.perf_counter() - t0),
        }
        return PoseEstimate(int(t_ns), self.name, None, y_m, yaw, float(np.clip(quality, 0, 1)),
                            y_m - self.site.corridor.axis_y_m, cov, diag)

    def _solve_from(self, psi0: float, q: np.ndarray, lines: np.ndarray, mids: np.ndarray,
                    len_n: np.ndarray, segs: np.ndarray, prior: PoseEstimate | None,
                    prior_psi: float | None) -> dict[str, Any] | None:
        along, across, _ = self._classify(psi0, lines, mids, self.angle_tol)
        if np.count_nonzero(along) + np.count_nonzero(across) < 2:
            return None
        psi = self._refine_pan(psi0, q, lines, mids, len_n, along, across)
        tol = np.minimum(self.angle_tol, 2 * self.inlier_px / np.maximum(len_n * self.f_px, 1))
        along, across, _ = self._classify(psi, lines, mids, tol)
        if np.count_nonzero(along) + np.count_nonzero(across) < 2:
            return None
        psi = self._refine_pan(psi, q, lines, mids, len_n, along, across)
        # the four labelings: psi + k * 90 deg; odd k swaps the families
        mount = self.rig.mount
        ceil_pts = self._ceiling_points(segs)
        seg_len_w = np.nan_to_num(np.minimum(np.hypot(ceil_pts[:, 2] - ceil_pts[:, 0],
                                                      ceil_pts[:, 3] - ceil_pts[:, 1]), 10.0))
        corr = self.site.corridor
        hyps = []
        for k in range(4):
            pk = wrap_pi(psi + k * np.pi / 2)
            fa, fb = (along, across) if k % 2 == 0 else (across, along)
            wa = len_n[fa] * self.f_px
            prior_shift = None
            if prior is not None and prior.y_m is not None:
                t_v = rot_z(wrap_pi(pk - mount.pan_rad)) @ mount.t_vehicle_cam
                prior_shift = prior.y_m + float(t_v[1])
            offs = along_offsets(q[fa], pk, self.height_m)
            m = match_offsets(offs, wa, self.site_y, self.match_tol_m, prior_shift,
                              self._lamp_anchors(ceil_pts[fb], pk))
            n_a = 0 if m is None else m.n_lines
            n_b = 0
            if corr.lines_across is not None and np.count_nonzero(fb) >= 2:
                n_b, _ = periodic_spread(across_offsets(q[fb], pk, self.height_m),
                                         len_n[fb], corr.lines_across.spacing_m,
                                         self.match_tol_m)
                n_b = n_b if n_b >= 2 else 0
            elong = float(np.sum(seg_len_w[fa]) - np.sum(seg_len_w[fb]))
            hyps.append({"k": k, "psi": pk, "fa": fa, "fb": fb, "match": m, "n_a": n_a,
                         "n_b": n_b, "elong": elong})

        def frame_score(h: dict[str, Any]) -> tuple:
            return (h["n_a"] + min(h["n_b"], 2), h["elong"])

        how = "spacing"
        if prior_psi is not None:
            ranked = sorted(hyps, key=lambda h: abs(wrap_pi(h["psi"] - prior_psi)))
            chosen = ranked[0]
            how = "prior"
        else:
            # pair k with k+2 (a 180 deg turn): keep yaw in (-90, 90]
            def yaw_ok(h: dict[str, Any]) -> bool:
                y = wrap_pi(h["psi"] - mount.pan_rad)
                return -np.pi / 2 < y <= np.pi / 2

            cands = [h for h in hyps if yaw_ok(h)]
            cands.sort(key=frame_score, reverse=True)
            chosen = cands[0]
            if len(cands) > 1 and frame_score(cands[1])[0] == frame_score(chosen)[0]:
                how = "elongation"
                if abs(cands[1]["elong"] - chosen["elong"]) < 1e-6:
                    # no evidence at all: the paper's rule, |pan| <= 45 deg
                    chosen = min(cands, key=lambda h: abs(h["psi"]))
                    how = "paper_rule"
        m = chosen["match"]
        if m is None or m.n_lines < 1 or np.count_nonzero(m.assign >= 0) < 2:
            return {"score": (-1, 0.0), "failure": (
                "no_association", "the forward lines do not match the site's lines_along")}
        ambiguous = False
        if m.runner_up is not None and m.runner_up[0] >= 0.85 * m.score:
            ambiguous = True
            if prior is None or prior.y_m is None:
                return {"score": (m.n_lines, m.weight), "failure": (
                    "ambiguous", f"{m.n_lines} forward lines fit two lateral positions "
                    f"({m.shift_m:+.3f} m and {m.runner_up[2]:+.3f} m); no prior to choose")}
        assign = np.full(q.shape[0], -1)
        assign[np.flatnonzero(chosen["fa"])] = m.assign
        return {"score": (m.n_lines, m.weight), "psi": chosen["psi"], "cy": m.shift_m,
                "along": chosen["fa"], "across": chosen["fb"], "assign": assign,
                "n_lines": m.n_lines, "ambiguous": ambiguous, "how": how}

    def _ceiling_points(self, segs: np.ndarray) -> np.ndarray:
        """Endpoints ``(N, 4)`` back-projected onto the ceiling, in the level frame
        relative to the camera (m; NaN above the horizon). Needs no pan."""
        n = segs.shape[0]
        p = np.hstack([segs.reshape(-1, 2), np.ones((2 * n, 1))]) @ self.M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            X = p[:, :2] * (self.height_m / p[:, 2:3])
        return np.where(p[:, 2:3] > 1e-6, X, np.nan).reshape(n, 4)

    def _lamp_anchors(self, pts: np.ndarray, psi: float) -> np.ndarray:
        """Camera y estimates from across segments as long as a lamp is wide: the
        lamp's end, whose middle lies on the lamp row's y."""
        if not self.site.lamps or pts.shape[0] == 0:
            return np.zeros(0)
        R = rot_z(psi)[:2, :2]
        a = pts[:, :2] @ R.T
        b = pts[:, 2:] @ R.T
        length = np.hypot(*(b - a).T)
        mid_y = 0.5 * (a[:, 1] + b[:, 1])
        out = []
        for row in self.site.lamps:
            ok = np.isfinite(length) & (np.abs(length - row.width_m) < 0.2 * row.width_m)
            out.append(row.y_m - mid_y[ok])
        return np.concatenate(out)

    def _vanishing_line_check(self, lines: np.ndarray, len_n: np.ndarray, along: np.ndarray,
                              across: np.ndarray) -> dict[str, float]:
        """The mount check: free vanishing points of both families against the
        calibrated tilt and swing."""
        n_pred = self.M[2, :]
        out = {"vanishing_line_residual_deg": float("nan"), "vp_along_elevation_deg":
               float("nan"), "implied_tilt_deg": float("nan"), "implied_swing_deg": float("nan")}
        if np.count_nonzero(along) >= 2:
            va = free_vanishing_point(lines[along], len_n[along] ** 2)
            out["vp_along_elevation_deg"] = math.degrees(math.asin(
                min(1.0, abs(float(n_pred @ va)) / float(np.linalg.norm(va)))))
            if np.count_nonzero(across) >= 2:
                vb = free_vanishing_point(lines[across], len_n[across] ** 2)
                n = np.cross(va, vb)
                if np.linalg.norm(n) > 1e-12:
                    n /= np.linalg.norm(n)
                    out["vanishing_line_residual_deg"] = math.degrees(
                        math.acos(min(1.0, abs(float(n @ n_pred)))))
                    tilt, swing = mount_from_vanishing_line(n)
                    out["implied_tilt_deg"] = math.degrees(tilt)
                    out["implied_swing_deg"] = math.degrees(swing)
        return out
