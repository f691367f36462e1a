"""The tracked fast path of ``corridor``: 1-D edge searches across the predicted lines.

With a prior (the tracker's or the fusion's predicted yaw and y), every site line
``y = y_j`` of ``lines_along`` is projected through the rig (camera pan
``psi = yaw + pan``, camera y ``c_y``; SPEC §1) and its visible stretch (in the image,
in the lens's field, within :data:`REACH_M` of the camera on the ceiling) is cut into
short pixel chords. On each chord the edge is located on cross profiles by the one
edge-profile measurement (:func:`~ceilkit.runtime.features.lines.refine_undistorted`:
kind, sub-pixel location, a line fitted in undistorted coordinates), within
``search_px`` of the prediction. No full-frame line detector runs.

A chord counts when its edge is of the kind the site says (a lamp's long edge is a
step, a seam a thin line) and fits well (its points' scatter within
:data:`MAX_CHORD_RMS_PX` and :data:`CHORD_RMS_MEDIANS` times the frame's median);
the association is known (a chord is its line's), so the located chords go straight
to the joint Gauss-Newton on ``(psi, c_y)`` (:func:`~.refine.gauss_newton`, started
at the prior) as forward segments.
The window check: at least two site lines found, the fit's rms within ``inlier_px``,
the refined pose within the search's reach of the prior. Anything else returns
``None`` and the estimator runs its global path (the fallback and the check).

Example::

    lt = LineTracker(setup, camera, search_px=5.0, inlier_px=2.5)
    m = lt.measure(grey, psi_rad, camera_y_m)     # LineMeasurement | None
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.lines import refine_undistorted
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.jit import arr, njit, warmer

REACH_M = 8.0
"""Ceiling points further than this from the camera are not searched (tiny, blurred)."""

CHORD_PX = 48.0
"""Pixel length of a chord of a predicted line (short: a curved image line is straight
on it to a fraction of a pixel)."""

MIN_CHORD_PX = 20.0
"""A visible stretch shorter than this is not searched."""

SAMPLES = 121
"""Samples along each site line (W's x, over ``±REACH_M`` of the camera)."""

MAX_CHORD_RMS_PX = 1.0
"""A chord whose located points scatter more than this about their line is dropped."""

CHORD_RMS_MEDIANS = 3.0
"""... and so is one scattering more than this many times the frame's median chord
scatter: a chord over a lamp's end or a neighbouring edge fits worse than the clean
chords by far (on renders, clean chords 0.02-0.14 px, the others 0.4-0.95), and the
few such chords biased the fit (corridor_60 of bench_all: yaw error median/p95 0.0054/0.021 deg with
them, 0.0017/0.0058 without, the global path's 0.0023/0.0061)."""


@dataclass(frozen=True, eq=False)
class LineMeasurement:
    """The located chords of one frame.

    Attributes:
        segs_n: ``(K, 4)`` undistorted normalized chords (the fitted edge).
        segs_px: ``(K, 4)`` the predicted pixel chords searched.
        line: ``(K,)`` the site line (index into ``setup.site_y``) of each chord.
        polarity: ``(K,)`` the located kind (``+-1`` step, ``0`` thin line).
        rms_px: ``(K,)`` the located points' scatter about each chord's fit (px).
        searched: chords searched (before the checks).
    """

    segs_n: np.ndarray
    segs_px: np.ndarray
    line: np.ndarray
    polarity: np.ndarray
    rms_px: np.ndarray
    searched: int

    @property
    def n_lines(self) -> int:
        return int(np.unique(self.line).size)


def without_ignored(m: LineMeasurement | None, regions, pose) -> LineMeasurement | None:
    """``m`` without the chords inside the site's ``ignore`` regions seen from ``pose``
    (:class:`~ceilkit.runtime.estimators.ignore.IgnoreRegions`; SPEC §2), None when
    fewer than two site lines keep a chord; ``m`` itself with no region or no pose."""
    keep = None if m is None or regions is None else regions.keep_segments(m.segs_n, pose)
    if keep is None or keep.all():
        return m
    if np.unique(m.line[keep]).size < 2:
        return None
    return dataclasses.replace(m, segs_n=m.segs_n[keep], segs_px=m.segs_px[keep],
                               line=m.line[keep], polarity=m.polarity[keep],
                               rms_px=m.rms_px[keep])


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

    def predicted_chords(self, psi_rad: float, camera_y_m: float
                         ) -> tuple[np.ndarray, np.ndarray]:
        """``(chords (K, 4) px, line (K,))``: the visible stretches of every site line
        for camera pan ``psi_rad`` and camera y ``camera_y_m``, cut into chords of about
        :data:`CHORD_PX`."""
        st, cam = self.setup, self.camera
        R_cw = st.R_level_cam.T @ rot_z(-psi_rad)
        h = st.ceiling_above_cam_m
        u = self._u[None, :]
        dy = (st.site_y - camera_y_m)[:, None]
        d0, d1, d2 = (u * R[0] + (dy * R[1] + h * R[2]) for R in R_cw)      # (J, S)
        front = (d2 > 1e-6) & (u * u + dy * dy <= REACH_M * REACH_M)
        z = np.where(front, d2, 1.0)
        x, y = d0 / z, d1 / z
        front &= x * x + y * y <= st.field_radius ** 2
        px = cam.distort(np.stack([x.ravel(), y.ravel()], axis=1)).reshape(*x.shape, 2)
        m = self._margin
        vis = front & (px[..., 0] >= m) & (px[..., 0] <= cam.width - 1 - m) \
            & (px[..., 1] >= max(m, st.rows[0])) & (px[..., 1] <= min(cam.height - 1 - m,
                                                                      st.rows[1]))
        return _cut_chords(px, vis)

    def measure(self, grey: np.ndarray, psi_rad: float, camera_y_m: float
                ) -> LineMeasurement | None:
        """The chords located on a ``(H, W)`` uint8 frame around the site lines
        predicted for ``(psi_rad, camera_y_m)``; ``None`` when fewer than two site lines
        hold a located chord of the right kind."""
        chords, line = self.predicted_chords(psi_rad, camera_y_m)
        if np.unique(line).size < 2:
            return None
        segs_n, pol, rms = refine_undistorted(self.camera, grey, chords,
                                              half_width_px=self.search_px,
                                              retry_half_width_px=None)
        want_step = self.setup.edge_kind[line] != 0
        ok = (np.isfinite(rms) & (rms <= MAX_CHORD_RMS_PX)
              & np.where(want_step, np.abs(pol) == 1.0, pol == 0.0))
        if ok.any():
            ok &= rms <= CHORD_RMS_MEDIANS * float(np.median(rms[ok]))
        if np.unique(line[ok]).size < 2:
            return None
        return LineMeasurement(segs_n[ok], chords[ok], line[ok], pol[ok], rms[ok],
                               int(chords.shape[0]))

    def reach(self) -> tuple[float, float]:
        """``(psi_rad, c_y m)``: how far from the prior a refined fit may move and still
        be what the searches saw (about ``search_px`` at the image's scale)."""
        f = self.setup.f_px
        return (math.atan2(self.search_px, f) * 2.0,
                self.search_px / f * self.setup.ceiling_above_cam_m * 2.0)


def _cut_chords(px: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(chords (K, 4), line (K,))``: each line's longest run of visible samples
    (``px (J, S, 2)``, ``vis (J, S)``; the first of equal runs), cut into chords of
    about :data:`CHORD_PX` of arc length (ends interpolated along the arc as
    ``np.interp``); runs shorter than :data:`MIN_CHORD_PX` are left out."""
    return _chords_of_runs(arr(px, np.float64), arr(vis, np.bool_), CHORD_PX, MIN_CHORD_PX)


@njit
def _chords_of_runs(px, vis, chord_px, min_chord_px):  # pragma: no cover - compiled
    """:func:`_cut_chords`: ``(chords, line)``."""
    n_lines, n_s = vis.shape
    runs = np.zeros((n_lines, 2), np.int64)
    for j in range(n_lines):
        best_a, best_len, a = 0, 0, -1
        for i in range(n_s + 1):
            on = i < n_s and vis[j, i]
            if on and a < 0:
                a = i
            elif not on and a >= 0:
                if i - a > best_len:
                    best_a, best_len = a, i - a
                a = -1
        runs[j, 0], runs[j, 1] = best_a, best_a + best_len
    arc = np.zeros((n_lines, n_s))           # arc length along each run from its start
    count = np.zeros(n_lines, np.int64)      # chords of each line
    for j in range(n_lines):
        a, b = runs[j, 0], runs[j, 1]
        if b - a < 2:
            continue
        for i in range(a + 1, b):
            arc[j, i - a] = arc[j, i - a - 1] + math.hypot(px[j, i, 0] - px[j, i - 1, 0],
                                                           px[j, i, 1] - px[j, i - 1, 1])
        if arc[j, b - a - 1] >= min_chord_px:
            count[j] = max(1, int(np.rint(arc[j, b - a - 1] / chord_px)))
    chords = np.empty((count.sum(), 4))
    line = np.empty(count.sum(), np.int64)
    n = 0                                    # chords written
    for j in range(n_lines):
        k = count[j]
        if k == 0:
            continue
        a, b = runs[j, 0], runs[j, 1]
        m = b - a
        total = arc[j, m - 1]
        seg = 0
        pu, pv = px[j, a, 0], px[j, a, 1]
        for c in range(1, k + 1):
            x = total * (c / k)
            while seg < m - 2 and arc[j, seg + 1] <= x:
                seg += 1
            if x >= total:
                u, v = px[j, b - 1, 0], px[j, b - 1, 1]
            else:
                t = (x - arc[j, seg]) / (arc[j, seg + 1] - arc[j, seg])
                u = px[j, a + seg, 0] + t * (px[j, a + seg + 1, 0] - px[j, a + seg, 0])
                v = px[j, a + seg, 1] + t * (px[j, a + seg + 1, 1] - px[j, a + seg, 1])
            chords[n, 0], chords[n, 1], chords[n, 2], chords[n, 3] = pu, pv, u, v
            line[n] = j
            n += 1
            pu, pv = u, v
    return chords, line


@warmer
def _warm() -> None:
    px = np.stack([np.linspace(0.0, 100.0, 5), np.zeros(5)], axis=1)[None]
    _cut_chords(px, np.ones((1, 5), bool))


__all__ = ["CHORD_PX", "CHORD_RMS_MEDIANS", "LineMeasurement", "LineTracker", "REACH_M"]
