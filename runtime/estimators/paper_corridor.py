"""The paper's corridor procedure, as a baseline (Yang & Tsai, "Viewing corridors as
right parallelepipeds for vision-based vehicle localization").

Steps, as literally as the text allows (its equations are re-derived here in the
conventions of SPEC §1):

1. Canny edges and the (probabilistic) Hough transform give candidate lines.
2. Candidates with similar slopes whose centres are close are merged; each merged
   line is refitted by least squares to its edge pixels.
3. The lines are divided into two sets by their image direction (the forward set
   is the one closer to the forward direction expected at zero pan).
4. Each set's vanishing point is the MEAN of the pairwise intersections of its lines.
5. The vanishing line's direction ``D = v_along - v_across`` (normalized coordinates,
   not normalized in length) follows ``D = N / (rho sin(2 psi + phi))`` with
   ``N = (a b_z - b a_z)_xy``, ``a, b = R[0], R[1]`` (``R = R_level_cam``),
   ``rho = (a_z^2 + b_z^2) / 2``,
   ``phi = atan2(2 a_z b_z, a_z^2 - b_z^2)`` (our eq. 8); its u-component (eq. 11)
   gives ``sin(2 psi + phi)``, hence two complementary solutions; the one smaller
   than 45 deg in magnitude is kept.
6. Lateral from the slope of one forward line (eq. 24): an image line ``l`` of the
   ceiling line ``y = y_j`` satisfies ``y_j - c_y = h (g1 l2 - g2 l1) / (k1 l2 - k2 l1)``
   with ``g = R_cam_world e_y``, ``k = R_cam_world e_z`` and ``h`` the ceiling's
   height above the camera (the slope ``-l1/l2`` form of the paper, written without
   the division so near-vertical lines stay finite). The line used is the longest
   forward line; which site line it is comes from a 1-D matching of all forward
   lines' offsets (the paper assumes it is known).

Deviations, needed to run at all: endpoints are undistorted (the paper has no lens
model), and the frame checks and failure values are ours.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import (
    Estimate,
    Estimator,
    EstimatorOptions,
    PoseEstimate,
    elapsed_ms,
)
from ceilkit.runtime.estimators.corridor.association import match_offsets
from ceilkit.runtime.estimators.corridor.setup import check_setup, default_match_tol_m
from ceilkit.runtime.features.lines import (
    fit_line,
    merge_segments,
    segment_lengths,
    undistort_segments,
)
from ceilkit.runtime.geometry.rotations import rot_z, wrap_half_pi, wrap_pi


@dataclass(frozen=True)
class PaperCorridorOptions(EstimatorOptions):
    """What a user may set (``--option KEY=VALUE``).

    Attributes:
        canny_low, canny_high: Canny hysteresis thresholds.
        hough_threshold: accumulator votes a Hough line needs.
        min_length_px: shortest line (None: 4 % of the image width).
        merge_angle_deg, merge_dist_px: candidates closer than this in slope and
            centre are merged.
        min_contrast: (inherited) grey-level spread below which a frame is blank.
    """

    canny_low: float = 40.0
    canny_high: float = 100.0
    hough_threshold: int = 30
    min_length_px: float | None = None
    merge_angle_deg: float = 2.0
    merge_dist_px: float = 3.0


def pan_from_vanishing_line(D: np.ndarray, R_level_cam: np.ndarray) -> tuple[float, float]:
    """The two complementary solutions (rad) of the paper's eq. 11 for camera pan.

    Args:
        D: ``(2,)`` ``v_along - v_across`` in normalized coordinates.
        R_level_cam: ``(3, 3)`` the mount's tilt and swing.
    """
    a, b = R_level_cam[0, :], R_level_cam[1, :]
    N = a[:2] * b[2] - b[:2] * a[2]
    rho = 0.5 * (a[2] ** 2 + b[2] ** 2)
    phi = math.atan2(2 * a[2] * b[2], a[2] ** 2 - b[2] ** 2)
    k = 0 if abs(N[0]) >= abs(N[1]) else 1      # eq. 11 (u), or eq. 12 when u is degenerate
    s = N[k] / (rho * D[k]) if D[k] != 0 else 0.0
    alpha = math.asin(max(-1.0, min(1.0, s)))
    p1 = wrap_half_pi(0.5 * (alpha - phi))
    p2 = wrap_half_pi(0.5 * (math.pi - alpha - phi))
    return p1, p2


def lateral_from_line(line: np.ndarray, psi_rad: float, R_level_cam: np.ndarray,
                      ceiling_above_cam_m: float) -> float:
    """The paper's eq. 24: ``y_line - c_y`` (m) from one forward image line ``(3,)``, for
    a camera ``ceiling_above_cam_m`` below the ceiling."""
    R_cw = (rot_z(psi_rad) @ R_level_cam).T
    g, k = R_cw[:, 1], R_cw[:, 2]
    l1, l2 = float(line[0]), float(line[1])
    den = k[0] * l2 - k[1] * l1
    return (ceiling_above_cam_m * (g[0] * l2 - g[1] * l1) / den if abs(den) > 1e-12
            else float("nan"))


def mean_intersection(lines: np.ndarray) -> np.ndarray | None:
    """Mean ``(2,)`` of the pairwise intersections of ``lines (N, 3)``; None if all are parallel."""
    pts = []
    for i in range(lines.shape[0]):
        for j in range(i + 1, lines.shape[0]):
            p = np.cross(lines[i], lines[j])
            if abs(p[2]) > 1e-12:
                pts.append(p[:2] / p[2])
    return np.mean(pts, axis=0) if pts else None


class PaperCorridorEstimator(Estimator):
    """Yang & Tsai's procedure (see the module docstring), on the Estimator contract;
    same output types as :class:`~.corridor.CorridorEstimator`. ``prior`` is not used
    (the paper has none). Failure reasons besides the frame check's:
    ``too_few_lines``, ``no_association``."""

    name = "paper-corridor"
    Options = PaperCorridorOptions
    site_sections = ("corridor",)

    def __init__(self, rig: Rig, site: Site,
                 options: PaperCorridorOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(rig, site, options)
        check_setup(rig, site)
        o: PaperCorridorOptions = self.options
        self.R_level_cam = rig.mount.R_level_cam
        self.ceiling_above_cam_m = site.ceiling_height_m - rig.mount.z_m
        self.canny = (float(o.canny_low), float(o.canny_high))
        self.min_length_px = (0.04 * rig.camera.width if o.min_length_px is None
                              else float(o.min_length_px))
        self.merge_angle_rad = math.radians(o.merge_angle_deg)
        self.site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
        self.match_tol_m = default_match_tol_m(self.site_y)

    def _lines(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Merged, least-squares refitted lines: ``(segments px (N, 4), lengths (N,))``."""
        edges = cv2.Canny(grey, self.canny[0], self.canny[1], L2gradient=True)
        found = cv2.HoughLinesP(edges, 1.0, np.pi / 720, self.options.hough_threshold,
                                minLineLength=self.min_length_px, maxLineGap=3)
        if found is None:
            return np.zeros((0, 4)), np.zeros(0)
        segs = found.reshape(-1, 4).astype(np.float64)
        ev, eu = np.nonzero(edges)
        epts = np.stack([eu, ev], axis=1).astype(np.float64)
        out = []
        for g in merge_segments(segs, self.merge_angle_rad, self.options.merge_dist_px):
            pts = segs[g].reshape(-1, 2)
            line = fit_line(pts)
            t_dir = np.array([-line[1], line[0]])
            ts = pts @ t_dir
            lo, hi = ts.min(), ts.max()
            near = np.abs(epts @ line[:2] + line[2]) <= 1.5
            te = epts[near] @ t_dir
            sel = epts[near][(te >= lo) & (te <= hi)]
            if sel.shape[0] >= 5:
                line = fit_line(sel)                                   # least squares
            base = -line[2] * line[:2]
            out.append(np.r_[base + lo * t_dir, base + hi * t_dir])
        segs = np.array(out).reshape(-1, 4)
        return segs, segment_lengths(segs)

    def _two_sets(self, segs: np.ndarray, len_px: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray] | str:
        """The forward and across sets ``(N,)`` bool by image direction (one round of
        2-means on doubled angles, seeded at the zero-pan directions from the image
        centre), or why there are not two sets of two."""
        ang = np.arctan2(segs[:, 3] - segs[:, 1], segs[:, 2] - segs[:, 0])
        R = self.R_level_cam
        va0, vb0 = (R.T @ np.array([1.0, 0, 0]), R.T @ np.array([0, 1.0, 0]))
        c = np.array([0.0, 0.0, 1.0])
        ref = []
        for v in (va0, vb0):       # direction from the image centre to each vanishing point
            dv = v[:2] - v[2] * c[:2]
            ref.append(math.atan2(dv[1], dv[0]))
        da = np.abs(wrap_pi(2 * (ang - ref[0]))) / 2
        db = np.abs(wrap_pi(2 * (ang - ref[1]))) / 2
        cen = []
        for sel in (da <= db, db < da):
            if np.count_nonzero(sel) == 0:
                cen.append(None)
                continue
            w = len_px[sel]
            cen.append(0.5 * math.atan2(np.sum(w * np.sin(2 * ang[sel])),
                                        np.sum(w * np.cos(2 * ang[sel]))))
        if cen[0] is None or cen[1] is None:
            return "the lines form only one set"
        da = np.abs(wrap_pi(2 * (ang - cen[0]))) / 2
        db = np.abs(wrap_pi(2 * (ang - cen[1]))) / 2
        fwd, acr = da <= db, db < da
        if np.count_nonzero(fwd) < 2 or np.count_nonzero(acr) < 2:
            return ("each set needs two lines "
                    f"({np.count_nonzero(fwd)} forward, {np.count_nonzero(acr)} across)")
        return fwd, acr

    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        """The paper's estimate of ``(y, yaw)`` from a checked frame."""
        segs_px, len_px = self._lines(grey)
        if segs_px.shape[0] < 4:
            return self.fail(t_ns, "too_few_lines", f"{segs_px.shape[0]} lines found")
        segs = undistort_segments(self.rig.camera, segs_px)
        p1 = np.hstack([segs[:, :2], np.ones((segs.shape[0], 1))])
        p2 = np.hstack([segs[:, 2:], np.ones((segs.shape[0], 1))])
        lines = np.cross(p1, p2)
        lines /= np.hypot(lines[:, 0], lines[:, 1])[:, None]
        sets = self._two_sets(segs, len_px)
        if isinstance(sets, str):
            return self.fail(t_ns, "too_few_lines", sets)
        fwd, acr = sets
        v_a = mean_intersection(lines[fwd])
        v_b = mean_intersection(lines[acr])
        if v_a is None or v_b is None:
            return self.fail(t_ns, "too_few_lines", "a set's lines are parallel in the image")
        sols = pan_from_vanishing_line(v_a - v_b, self.R_level_cam)
        psi = min(sols, key=abs)
        offs = np.array([lateral_from_line(ln, psi, self.R_level_cam, self.ceiling_above_cam_m)
                         for ln in lines[fwd]])
        m = match_offsets(offs, len_px[fwd], self.site_y, self.match_tol_m)
        if m is None:
            return self.fail(t_ns, "no_association",
                             "no forward line matches the site's lines_along")
        matched = np.flatnonzero(m.assign >= 0)
        one = matched[np.argmax(len_px[fwd][matched])]
        cy = float(self.site_y[m.assign[one]] - offs[one])
        mount = self.rig.mount
        yaw = wrap_pi(psi - mount.pan_rad)
        y_m = cy - float((rot_z(yaw) @ mount.t_vehicle_cam)[1])
        spread = float(np.std(self.site_y[m.assign[matched]] - offs[matched])) \
            if matched.size > 1 else 0.05
        cov = np.zeros((3, 3))
        cov[0, 0] = np.inf
        cov[1, 1] = max(spread, 0.005) ** 2
        cov[2, 2] = math.radians(1.0) ** 2
        quality = min(1.0, matched.size / 4.0) / (1.0 + (spread / 0.02) ** 2)
        diag = {"n_lines": int(segs.shape[0]), "n_forward": int(np.count_nonzero(fwd)),
                "n_across": int(np.count_nonzero(acr)), "psi_deg": math.degrees(psi),
                "psi_alternative_deg": math.degrees(max(sols, key=abs)),
                "vp_forward": v_a.tolist(), "vp_across": v_b.tolist(),
                "ms": elapsed_ms(t0)}
        return PoseEstimate(int(t_ns), self.name, None, y_m, yaw, float(quality),
                            y_m - self.site.corridor.axis_y_m, cov, diag)
