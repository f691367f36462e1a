"""The tracked fast path of ``corridor``: 1-D edge searches across the predicted lines.

With a prior (the tracker's or the fusion's predicted yaw and y), every site line
``y = y_j`` of ``lines_along`` is projected through the rig (camera pan
``psi = yaw + pan``, camera y ``c_y``; SPEC §1) at :data:`SAMPLES` points along it; at
every point that is visible (in the image, in the lens's field, within :data:`REACH_M`
of the camera on the ceiling) one short profile is sampled across the predicted image
line (its normal from the neighbouring points), ``search_px`` either side, all profiles
of the frame in one ``cv2.remap``. No line detector runs.

On each profile the edge kind is read as the global path reads it
(:func:`~ceilkit.runtime.features.edges.classify`) and the edge located to sub-pixel
(:func:`~ceilkit.runtime.features.edges.locate`: a step's crossing of its mid level
next to the gradient's peak, a thin line's middle). A point counts when its kind is the
site's (a lamp's long edge is a step, all of a line's steps of one polarity; a seam a
thin line). The located points are undistorted in one call; per site line a straight
line is fitted to them in undistorted coordinates with one 3-sigma rejection pass
(:func:`~ceilkit.runtime.features.edges.fit_lines_robust`: a point over a lamp's end or
a neighbouring edge falls out), and the points kept go straight to the joint
Gauss-Newton on ``(psi, c_y)`` (:func:`~.refine.gauss_newton`, started at the prior),
each point one residual (its distance to its site line's predicted image line): the
association is known.

The window check: at least two site lines with :data:`MIN_POINTS` points each within
:data:`MAX_LINE_RMS_PX` of their line, the fit's
rms within ``inlier_px``, the refined pose within the search's reach of the prior.
Anything else returns ``None`` and the estimator runs its global path (the fallback
and the check).

Example::

    lt = LineTracker(setup, camera, search_px=5.0)
    m = lt.measure(grey, psi_rad, camera_y_m)     # LinePoints | None
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.corridor.refine import GNInputs
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.edges import classify, edge_grid, fit_lines_robust, locate
from ceilkit.runtime.geometry.camera import CameraModel

REACH_M = 8.0
"""Ceiling points further than this from the camera are not searched (tiny, blurred)."""

SAMPLES = 121
"""Places along each site line (W's x, over ``+-REACH_M`` of the camera): about 0.13 m
apart on the ceiling, 30-50 of them in view per line at 640x480."""

MIN_POINTS = 8
"""A site line counts with at least this many located points after the rejection."""

MAX_LINE_RMS_PX = 1.0
"""... and its kept points scattering at most this about its fitted line (px): a
ceiling line is straight in undistorted coordinates (on renders 0.05-0.3 px; points on
texture or noise scatter over the whole profile)."""

MIN_STEP, MIN_DEPTH = 20.0, 8.0
"""Grey levels of a step's two sides and of a thin line's dip or bump
(:func:`~ceilkit.runtime.features.edges.classify`, as the global edge fit)."""


@dataclass(frozen=True, eq=False)
class LinePoints:
    """The located edge points of one frame, grouped by site line.

    Attributes:
        points_n: ``(P, 2)`` undistorted normalized edge points kept.
        line: ``(P,)`` the site line (index into ``setup.site_y``) of each point.
        v_px: ``(P,)`` each point's image row (px; its time with a rolling shutter).
        segs_n: ``(L, 4)`` per site line found, its fitted line between its extreme
            points (undistorted normalized), for the model checks and overlays.
        seg_line: ``(L,)`` the site line of each of ``segs_n``.
        polarity: ``(L,)`` its kind (``+-1`` step, ``0`` thin line).
        rms_px: ``(L,)`` its points' scatter about its fitted line (px).
        searched: profiles sampled.
    """

    points_n: np.ndarray
    line: np.ndarray
    v_px: np.ndarray
    segs_n: np.ndarray
    seg_line: np.ndarray
    polarity: np.ndarray
    rms_px: np.ndarray
    searched: int

    @property
    def n_lines(self) -> int:
        return int(self.seg_line.size)

    def gn_inputs(self, setup: CorridorSetup, tau_s: np.ndarray | None = None
                  ) -> GNInputs:
        """The Gauss-Newton inputs (:class:`~.refine.GNInputs`): every point one
        forward residual (``n_a``: half their number, as endpoint pairs), no across
        segments; ``tau_s (P,)`` the points' row times (s), None for a global shutter."""
        x, y = self.points_n[:, 0], self.points_n[:, 1]
        m0, m1, m2 = setup.R_rows
        empty = np.zeros(0)
        return GNInputs(n_a=x.size // 2, y=setup.site_y[self.line],
                        e0=m0[0] * x + m0[1] * y + m0[2], e1=m1[0] * x + m1[1] * y + m1[2],
                        ez=m2[0] * x + m2[1] * y + m2[2],
                        p0=empty, p1=empty, mx_b=empty, my_b=empty, scale_b=empty,
                        tau=tau_s, tau_b=None if tau_s is None else empty)


class LineTracker:
    """Edge searches across the site lines predicted from a prior (module doc).

    Args:
        setup: the estimator's :class:`~.setup.CorridorSetup`.
        camera: the intrinsics.
        search_px: half-width of the cross profiles (px): how far an edge may be from
            its prediction (the prior's error in pixels, plus a pixel).
    """

    def __init__(self, setup: CorridorSetup, camera: CameraModel, search_px: float) -> None:
        self.setup, self.camera = setup, camera
        self.search_px = float(search_px)
        self._u = np.linspace(-REACH_M, REACH_M, SAMPLES)
        self._margin = self.search_px + 2.0
        self._offs, _, self._inner = edge_grid(8, self.search_px)
        self._offs32 = self._offs.astype(np.float32)
        MT = setup.R_level_cam.T[:, :, None, None]
        self._cols = (MT[:, 0], MT[:, 1], setup.ceiling_above_cam_m * MT[:, 2])

    def predicted_points(self, psi_rad: float, camera_y_m: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(pu, pv, visible)``, each ``(J, S)``: the site lines' image points (pixel
        columns and rows) for camera pan ``psi_rad`` and camera y ``camera_y_m`` at the
        :data:`SAMPLES` places along them, and which are searched (in view, not at
        either end of the places: their normals need both neighbours)."""
        st, cam = self.setup, self.camera
        c, s = math.cos(psi_rad), math.sin(psi_rad)
        a0, a1, h_a2 = self._cols              # R_level_cam^T's columns (3, 1, 1), h a2
        dy = (st.site_y - camera_y_m)[:, None]
        # (3, J, S): R_cw (u, y_j - c_y, h), R_cw = R_level_cam^T Rz(-psi), for every
        # line j and place u
        d = (c * a0 - s * a1) * self._u + ((s * a0 + c * a1) * dy + h_a2)
        front = (d[2] > 1e-6) & self._near(dy)
        z = 1.0 / np.where(front, d[2], 1.0)
        x, y = d[0] * z, d[1] * z
        front &= x * x + y * y <= st.field_radius ** 2
        px = cam.distort(np.stack([x.ravel(), y.ravel()], axis=1))
        pu, pv = px[:, 0].reshape(x.shape), px[:, 1].reshape(x.shape)
        m = self._margin
        vis = front & (pu >= m) & (pu <= cam.width - 1 - m) \
            & (pv >= max(m, st.rows[0])) & (pv <= min(cam.height - 1 - m, st.rows[1]))
        vis[:, 0] = vis[:, -1] = False
        return pu, pv, vis

    def _near(self, dy: np.ndarray) -> np.ndarray:
        """``(J, S)``: the places within :data:`REACH_M` of the camera on the ceiling."""
        return self._u * self._u + dy * dy <= REACH_M * REACH_M

    def measure(self, grey: np.ndarray, psi_rad: float, camera_y_m: float
                ) -> LinePoints | None:
        """The edge points located on a ``(H, W)`` uint8 frame around the site lines
        predicted for ``(psi_rad, camera_y_m)``; ``None`` when fewer than two site lines
        hold :data:`MIN_POINTS` points of the right kind on a straight line."""
        pu, pv, vis = self.predicted_points(psi_rad, camera_y_m)
        jj, ss = np.nonzero(vis)
        n_lines = self.setup.site_y.size
        if jj.size == 0 or jj[0] == jj[-1]:
            return None
        # the unit left normal of the image line (central differences along it)
        tu = pu[jj, ss + 1] - pu[jj, ss - 1]
        tv = pv[jj, ss + 1] - pv[jj, ss - 1]
        inv = 1.0 / np.maximum(np.hypot(tu, tv), 1e-12)
        nu, nv = -tv * inv, tu * inv                                     # (P,)
        bu, bv = pu[jj, ss], pv[jj, ss]
        offs, inner = self._offs, self._inner
        mu = (bu[:, None] + nu[:, None] * self._offs32).astype(np.float32)   # (P, O)
        mv = (bv[:, None] + nv[:, None] * self._offs32).astype(np.float32)
        prof = cv2.remap(grey, mu, mv, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        pol, _ = classify(prof, offs, MIN_STEP, MIN_DEPTH, shift=False)
        # the site's kind; a line's steps all of its majority polarity
        want_step = self.setup.edge_kind[jj] != 0
        is_step = np.abs(pol) == 1.0
        sgn = np.sign(np.bincount(jj, weights=np.where(is_step, pol, 0.0),
                                  minlength=n_lines))[jj]
        ok = np.where(want_step, is_step & (pol == sgn), pol == 0.0)
        loc = locate(prof[:, None, :], np.where(ok, pol, np.nan), offs, inner)[:, 0]
        ok &= np.isfinite(loc)
        if np.unique(jj[ok]).size < 2:
            return None
        jj, ss = jj[ok], ss[ok]
        lo = loc[ok]
        found_px = np.stack([bu[ok] + lo * nu[ok], bv[ok] + lo * nv[ok]], axis=1)
        xy = self.camera.unproject_fast(found_px)
        # per site line, a straight line through its points (undistorted), outliers out
        S = SAMPLES
        gx = np.zeros((n_lines, S))
        gy = np.zeros((n_lines, S))
        good = np.zeros((n_lines, S), bool)
        gv = np.zeros((n_lines, S))
        gx[jj, ss], gy[jj, ss], gv[jj, ss], good[jj, ss] = xy[:, 0], xy[:, 1], \
            found_px[:, 1], True
        f = self.setup.f_px
        ln, _, cnt, ssr, kept = fit_lines_robust(gx, gy, good, f)
        rms = f * np.sqrt(ssr / np.maximum(cnt, 1.0))
        found = (cnt >= MIN_POINTS) & (rms <= MAX_LINE_RMS_PX)
        if np.count_nonzero(found) < 2:
            return None
        kept &= found[:, None]
        kj, ks = np.nonzero(kept)
        pts = np.stack([gx[kj, ks], gy[kj, ks]], axis=1)
        lines = np.flatnonzero(found)
        segs = self._segments(gx, gy, kept, ln, lines)
        return LinePoints(pts, kj, gv[kj, ks], segs, lines, np.sign(np.bincount(
            jj, weights=pol[ok], minlength=n_lines))[lines],
            rms[lines], int(vis.sum()))

    @staticmethod
    def _segments(gx: np.ndarray, gy: np.ndarray, kept: np.ndarray, ln: np.ndarray,
                  lines: np.ndarray) -> np.ndarray:
        """``(L, 4)``: for each of ``lines``, its fitted line ``ln`` between the
        projections of its first and last kept points (in sample order)."""
        k = kept[lines]
        first = np.argmax(k, axis=1)
        last = k.shape[1] - 1 - np.argmax(k[:, ::-1], axis=1)
        a, b, c = ln[lines, 0:1], ln[lines, 1:2], ln[lines, 2:3]
        ex = np.stack([gx[lines, first], gx[lines, last]], axis=1)
        ey = np.stack([gy[lines, first], gy[lines, last]], axis=1)
        d = a * ex + b * ey + c
        return np.stack([ex - d * a, ey - d * b], axis=2).reshape(-1, 4)

    def reach(self) -> tuple[float, float]:
        """``(psi_rad, c_y m)``: how far from the prior a refined fit may move and still
        be what the searches saw (about ``search_px`` at the image's scale)."""
        f = self.setup.f_px
        return (math.atan2(self.search_px, f) * 2.0,
                self.search_px / f * self.setup.ceiling_above_cam_m * 2.0)


__all__ = ["LinePoints", "LineTracker", "MAX_LINE_RMS_PX", "MIN_POINTS", "REACH_M", "SAMPLES"]
