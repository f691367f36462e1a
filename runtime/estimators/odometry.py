"""Ceiling-plane odometry: the vehicle's planar motion between two frames from ceiling
features tracked through the rig (an estimator-side stage any method can use).

Corners (``cv2.goodFeaturesToTrack``) of the earlier frame are tracked into the later
one by pyramidal KLT and checked back (forward-backward error); when the tracks turn
the image by more than :data:`TURN_WARP_MIN_RAD`, the later frame is turned back onto
the earlier one by their rigid fit in pixels and the corners are tracked again (KLT's
window does not turn: it read every turn short); both sets are
undistorted and met with the ceiling plane in V
(:func:`~ceilkit.runtime.geometry.ceiling.ceiling_points_vehicle`);
a rigid 2-D fit ``q_prev ~ R(dyaw) p_now + (dx, dy)`` with three passes dropping
pairs off by more than 3 MADs, the first about the median translation (:func:`plane_motion`),
gives the motion in the earlier frame's V. The covariance is the
fit's residual scatter, ``s² (JᵀJ)⁻¹``, scaled by :data:`VAR_FACTOR`: the ratio of
the measured scatter of increments (against the truth) to that covariance
(``benchmarks/calib_odometry_noise.py`` measures it). Only corner-like features,
spread over the frame, are tracked (:func:`corner_like`). The corners a step tracked
(its fit's inliers) are carried to the next step: they are detected afresh only every
:data:`REDETECT_EVERY` steps, or when fewer than :data:`REDETECT_SHARE` of them remain
(the detection is two thirds of a step's time). Corners detected afresh sit at whole
pixels, where KLT samples the earlier frame without interpolating and the later one
bilinearly: the mismatch moves every track of the step alike, which the fit's scatter
does not show (issue 36: such steps read a mean NEES of 11.7 of 3 on the held-out
marker drives). So a detection step is fitted from the tracks carried into it alone;
its fresh corners are tracked beside them and, those the fit explains, carried on and
fitted from their next step, sub-pixel at both ends. Only a step with no carried
tracks (a stream's first, after a gap or a failed step) is fitted from fresh corners;
a frame kept without measuring (``measure=False``) is followed by the carried tracks
(KLT alone, no fit; corners detected only when too few remain) when the next step
that measures comes, before it measures, so a leg between fixes does not start from
fresh corners and a run of fixes pays no tracking (only the last kept frame is
followed: a run of two or more starts from corners detected on the frame before it).

Example::

    odo = PlaneOdometry(PlanarGeometry.of(rig, site))
    inc = odo.step(grey)          # None on the first frame or with too few tracks
    inc.dx_m, inc.dy_m, inc.dyaw_rad, inc.cov
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.base import PlaneIncrement, elapsed_ms
from ceilkit.runtime.estimators.ignore import ignored_from
from ceilkit.runtime.geometry.ceiling import (
    PlanarGeometry,
    ceiling_jacobian,
    ceiling_points_vehicle,
)
from ceilkit.runtime.geometry.ekf import chi2_quantile
from ceilkit.runtime.geometry.fits import fit_rigid_2d

MAX_CORNERS = 150        # corners tracked per frame, at most
CANDIDATES = 150         # corner candidates (goodFeaturesToTrack) before the filter
CORNER_QUALITY = 0.01    # of the frame's strongest
GRID = (4, 3)            # corner_like: cells across and down; strength judged per cell
MIN_ISOTROPY = 0.4       # smaller / larger structure-tensor eigenvalue of a kept corner
HALF_WIN = 3
WEAK_SHARE = 0.15        # a kept corner's smaller eigenvalue, as a share of ...
STRONG_PERCENTILE = 90   # ... this percentile of its cell's candidates' (not of the
                         # frame's: a marker's corners would leave only the marker)
MIN_TRACKS = 12
MAX_GAP_S = 0.5          # frames farther apart than this are not matched
VAR_FACTOR = np.array([1.0, 1.8, 3.5])
"""Measured / fitted variance of (dx, dy, dyaw) by ``benchmarks/calib_odometry_noise.py``
(``--drives 6 --frames 160``, seeds 1 and 2: 954 increments each through configs/block,
3 cm steps, blocks and markers on frames 0-3 of every 30; 2026-12-07, with detection
steps fitted from carried tracks alone), the larger of per step and over sums of 50
steps (the legs between fixes of bench_block's fused drives), the two seeds' mean:
per step 1.01²/0.94², 1.10²/1.09², 1.20²/1.18²; 50-step sums 0.74²/0.84²,
1.37²/1.28², 1.85²/1.90² (seed 1/2): the heading errors are correlated from step to
step, so a white chain of the fit's covariance under-covers a long leg. The fit's
covariance is scaled by it (``cov * outer(sqrt f, sqrt f)``): honest at a 50-frame
horizon, over-covering shorter gaps, under-covering much longer ones. Before, with
the steps that detect fitted from their fresh corners (biased: the module), the same
drives gave (1.1, 2.0, 4.5); with the corners detected afresh on every step (before
the tracks were carried, :data:`REDETECT_EVERY`) (1.4, 5.3, 6.1); the earlier
(1.3, 1.3, 8) was measured when the tracks bunched on the strongest corners."""
FB_MAX_PX = 0.5          # forward-backward disagreement of a kept track
TRACK_NOISE_PX = 1.0     # a kept track's 1σ per image axis in the misfit test
MISFIT_ALPHA = 1e-3      # the misfit test's false-alarm rate (:func:`explained`)
REDETECT_EVERY = 5       # the tracks carried from frame to frame are detected afresh
                         # after this many steps ...
REDETECT_SHARE = 0.7     # ... or when fewer than this share of those detected remain
NEW_APART_PX = 8.0       # a fresh corner this close to a carried track is that track
TURN_WARP_MIN_RAD = math.radians(1.0)
"""A step whose tracks turn the image by more than this is tracked again on the later
frame turned back (:func:`_turn_warp`). KLT matches a window by translation alone: in
a turned window each track errs by the turn times its window's offset of structure,
and over a frame that reads the turn short (0.06-0.17 % at 0.5-9.5 deg a step, the
office ceiling, 80-200 random poses; per-step yaw error RMS 0.042 deg at 9.5 deg;
-0.36 % on the loop of ``bench_survey.py --against-known``). Turned back, the same
steps read the turn within 0.01 % (RMS 0.0014 deg; docs/methods/block.md). Below it
the second pass is not paid (the error is the turn's share)."""
LK = {"winSize": (21, 21), "maxLevel": 3,
      "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}


@dataclass(frozen=True)
class Increment:
    """The motion between two frames in the earlier frame's V: forward, left, CCW."""

    dx_m: float
    dy_m: float
    dyaw_rad: float
    cov: np.ndarray
    n: int
    kept: np.ndarray | None = None    # (N,) bool: the pairs the fit kept (not outliers)


def plane_motion(q_prev: np.ndarray, p_now: np.ndarray) -> Increment | None:
    """The rigid fit of ceiling points (V, ``(N, 2)`` each) after three outlier passes,
    the first about the median translation (at the fit's turn), the next two about the
    least-squares fit of the pairs kept: on held-out texture seed 9
    ``scatter0`` a vent grille's bars held a share of the tracks one bar off, and the
    least-squares start kept them: nine survey steps 5-7 % short at a stated 1.2 mm 1σ,
    48 mm by the tenth frame (now within 0.1 mm)."""
    keep = np.ones(len(q_prev), bool)
    for k in range(3):
        if np.count_nonzero(keep) < MIN_TRACKS:
            return None
        yaw, t = fit_rigid_2d(p_now[keep], q_prev[keep])
        c, s = math.cos(yaw), math.sin(yaw)
        if k == 0:
            # the translation's median first: tracks locked onto the next bar of a
            # grille (a periodic texture) are many, and moved the first fit with them
            t = np.median(q_prev - p_now @ np.array([[c, s], [-s, c]]), axis=0)
        r = q_prev - (p_now @ np.array([[c, s], [-s, c]]) + t)
        d = np.hypot(r[:, 0], r[:, 1])
        med = float(np.median(d[keep]))
        keep = d <= max(3.0 * 1.4826 * med + med, 1e-6)
    n = int(np.count_nonzero(keep))
    if n < MIN_TRACKS:
        return None
    yaw, t = fit_rigid_2d(p_now[keep], q_prev[keep])
    c, s = math.cos(yaw), math.sin(yaw)
    pk = p_now[keep]
    r = q_prev[keep] - (pk @ np.array([[c, s], [-s, c]]) + t)
    s2 = float(np.sum(r * r)) / max(2 * n - 3, 1)
    # d(R p + t)/d(tx, ty, yaw): rows for x and y of every point
    rp = pk @ np.array([[c, s], [-s, c]])
    J = np.zeros((2 * n, 3))
    J[0::2, 0] = 1.0
    J[1::2, 1] = 1.0
    J[0::2, 2] = -rp[:, 1]
    J[1::2, 2] = rp[:, 0]
    cov = s2 * np.linalg.inv(J.T @ J)
    f = np.sqrt(VAR_FACTOR)
    cov = cov * np.outer(f, f)
    return Increment(float(t[0]), float(t[1]), float(yaw), cov, n, keep)


def explained(inc: Increment, q_prev: np.ndarray, p_now: np.ndarray,
              m_per_px: np.ndarray) -> bool:
    """Whether the rigid fit ``inc`` explains the tracks it kept: the chi-square of
    their residuals in px (metres on the ceiling over ``m_per_px (N,)``, each track's
    ceiling metres per pixel) at :data:`TRACK_NOISE_PX` per axis, within its
    ``1 - MISFIT_ALPHA`` quantile over ``2n - 3`` degrees of freedom (the model checks'
    test, docs/methods/honesty.md). A step whose tracks mix two motions (KLT slipping
    on a repeating texture) leaves a scatter of pixels that no rigid motion explains;
    its fit's covariance, the scatter itself, does not cover its error (a kidnapped
    small-marker drive at noise 5, supersample 3: one step 175 mm and 9.8 deg off with
    a 1σ of 26-37 mm, 24 px RMS, against 0.3 px on the others; issue 36)."""
    k = np.ones(len(q_prev), bool) if inc.kept is None else inc.kept
    c, s = math.cos(inc.dyaw_rad), math.sin(inc.dyaw_rad)
    r = q_prev[k] - (p_now[k] @ np.array([[c, s], [-s, c]]) + [inc.dx_m, inc.dy_m])
    chi2 = float(np.sum((r / m_per_px[k, None]) ** 2)) / TRACK_NOISE_PX ** 2
    return chi2 <= chi2_quantile(1.0 - MISFIT_ALPHA, 2 * int(np.count_nonzero(k)) - 3)


def corner_like(grey: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Which points are corners, not points on a straight edge: the structure tensor's
    smaller eigenvalue at least :data:`MIN_ISOTROPY` of its larger. A point on a tile
    seam or a lamp's side slides along it (the aperture problem): its track
    under-measures the motion along the line, the same way frame after frame (on the
    tile ceiling of configs/block a -1.6 % scale bias, correlated from step to step).
    A corner is also strong for its part of the frame (:data:`GRID` cells) and among
    the first ``MAX_CORNERS / cells`` kept there (``pts`` in the order of strength):
    tracks spread over the ceiling, not bunched on a marker, whose corners' KLT errors
    share their windows' pixels and move together (the fit's scatter then hides them:
    increments beside a marker were 2-2.6x their sigma, NEES 42)."""
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    h, w = grey.shape
    c = np.rint(pts).astype(int)
    c[:, 0] = np.clip(c[:, 0], HALF_WIN, w - HALF_WIN - 1)
    c[:, 1] = np.clip(c[:, 1], HALF_WIN, h - HALF_WIN - 1)
    o = np.arange(-HALF_WIN, HALF_WIN + 1)
    ys = c[:, 1, None, None] + o[None, :, None]
    xs = c[:, 0, None, None] + o[None, None, :]
    ax, ay = gx[ys, xs].reshape(len(c), -1), gy[ys, xs].reshape(len(c), -1)
    a, b, d = np.sum(ax * ax, 1), np.sum(ax * ay, 1), np.sum(ay * ay, 1)
    root = np.sqrt((a - d) ** 2 + 4 * b * b)
    lo, hi = 0.5 * (a + d - root), 0.5 * (a + d + root)
    cell = (c[:, 1] * GRID[1] // h) * GRID[0] + c[:, 0] * GRID[0] // w
    ref = _cell_percentiles(cell, lo, GRID[0] * GRID[1], STRONG_PERCENTILE)
    used = np.unique(cell)
    # a cell of noise has no strong corners of its own: the cells' median is the floor
    ref = np.maximum(ref, np.median(ref[used]))
    good = (lo >= WEAK_SHARE * ref[cell]) & (lo >= MIN_ISOTROPY * np.maximum(hi, 1e-9))
    # the first few good ones of each cell (rank within the cell, in the given order)
    idx = np.flatnonzero(good)
    order = np.argsort(cell[idx], kind="stable")
    sc = cell[idx][order]
    start = np.searchsorted(sc, sc)                      # first index of each's cell
    rank = np.empty(len(idx), int)
    rank[order] = np.arange(len(idx)) - start
    good[idx[rank >= MAX_CORNERS // ref.size]] = False
    return good


def _cell_percentiles(cell: np.ndarray, value: np.ndarray, cells: int, q: float
                      ) -> np.ndarray:
    """``(cells,)`` the ``q``-th percentile of ``value`` in each cell (``np.percentile``'s
    linear interpolation; 0 where a cell has none), one sort for all cells."""
    order = np.lexsort((value, cell))
    v, c = value[order], cell[order]
    n = np.bincount(c, minlength=cells)
    first = np.cumsum(n) - n
    has = np.flatnonzero(n)
    pos = (q / 100.0) * (n[has] - 1)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, n[has] - 1)
    a, b = v[first[has] + lo], v[first[has] + hi]
    out = np.zeros(cells)
    out[has] = a + (pos - lo) * (b - a)
    return out


class PlaneOdometry:
    """Frame-to-frame ceiling-plane odometry (see the module); one instance per stream."""

    def __init__(self, geo: PlanarGeometry, site=None) -> None:
        self.geo = geo
        self.site = site if site is not None and site.ignore_m else None
        self._prev: np.ndarray | None = None
        self._t_prev: int | None = None
        # the corners tracked into the previous frame (N, 1, 2) float32, carried to
        # the next step instead of detecting again; how many were detected, how old
        self._tracks: np.ndarray | None = None
        # a frame kept without measuring, not yet followed: (the frame before it, the
        # corners carried into that one or None); followed only when a step needs it
        self._kept: tuple[np.ndarray, np.ndarray | None] | None = None
        self._detected = 0
        self._age = 0
        self.fresh_fit = False   # the last step fitted corners detected on that step

    def reset(self) -> None:
        self._prev = None
        self._t_prev = None
        self._tracks = None
        self._kept = None

    def step(self, grey: np.ndarray) -> Increment | None:
        """The motion since the previous frame given to :meth:`step`, or None."""
        prev, self._prev = self._prev, grey
        if prev is None:
            return None
        return self._motion(prev, grey)

    def increment(self, grey: np.ndarray, t_ns: int, measure: bool = True, near=None
                  ) -> PlaneIncrement | None:
        """The motion since the previous frame (at its stamp ``t0_ns``) as a
        :class:`~ceilkit.runtime.estimators.base.PlaneIncrement`; ``measure=False``
        publishes nothing (an absolute fix makes the increment moot) and costs nothing
        then: the frame is kept, and the carried corners are followed into it
        (:meth:`_keep_alive`) by the next step that measures, before it measures, so no
        step is fitted from fresh corners (issue 38: a run of fixes pays no tracking; a
        step after a lone kept frame tracks as if it had been followed at once).
        ``near``: a pose (``x_m``, ``y_m``, ``yaw_rad``; the prior) that places the
        tracks on the ceiling: those inside the site's ``ignore`` regions are not used
        (SPEC §2: a fan, a moving shadow); without it every track counts."""
        prev, t_prev = self._prev, self._t_prev
        kept, self._kept = self._kept, None
        self._prev, self._t_prev = grey, int(t_ns)
        if prev is None or t_prev is None or not 0 < (t_ns - t_prev) * 1e-9 <= MAX_GAP_S:
            self._tracks = None          # the carried corners belong to another frame
            return None
        if not measure:                  # followed later, if a step needs it
            self._kept, self._tracks = (prev, self._tracks), None
            return None
        if kept is not None:             # the kept frame (prev) followed now
            self._tracks = kept[1]
            self._keep_alive(kept[0], prev)
        inc = self._motion(prev, grey, near)
        if inc is None:
            return None
        return PlaneIncrement(t_prev, inc.dx_m, inc.dy_m, inc.dyaw_rad, inc.cov)

    def _keep_alive(self, prev: np.ndarray, grey: np.ndarray) -> None:
        """A frame kept without measuring: only what the next step needs. The carried
        tracks are followed from ``prev`` into ``grey`` by KLT (:func:`_tracked`: both
        ways, back within :data:`FB_MAX_PX`; no turn warp, no fit: a track's position
        on the frame only chooses the patch the next step tracks, whose motion its fit
        then tests) and kept off the frame's edge; fewer than :data:`MIN_TRACKS` are
        dropped. Corners are detected on ``prev`` only when fewer than
        :data:`REDETECT_SHARE` of those detected remain (or none: a stream's first
        frames, after a gap or a failed step), not every :data:`REDETECT_EVERY` steps,
        and followed into ``grey`` beside the carried ones, so that the next step fits
        tracks at sub-pixel, never fresh whole-pixel corners (the module)."""
        carried, self._tracks = self._tracks, None
        if carried is None or len(carried) < MIN_TRACKS:
            carried = np.zeros((0, 1, 2), np.float32)
        fresh = len(carried) < max(MIN_TRACKS, REDETECT_SHARE * self._detected)
        if fresh:
            carried = np.concatenate([carried, _fresh_corners(prev, carried)])
        if len(carried) < MIN_TRACKS:
            return
        nxt, ok = _tracked(prev, grey, carried)
        ok &= _off_edge(nxt, grey.shape)
        if np.count_nonzero(ok) < MIN_TRACKS:
            return
        self._tracks = nxt[ok]
        if fresh:
            self._detected, self._age = len(self._tracks), 1

    def _corners(self, prev: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(pts (N, 1, 2) float32, fit (N,) bool)``: the corners of ``prev`` to track
        and which of them enter this step's fit. The corners carried from the last step
        (tracked into ``prev``) are tracked and fitted; every :data:`REDETECT_EVERY`
        steps, or when fewer than :data:`REDETECT_SHARE` of them remain, corners are
        detected afresh (:func:`corner_like` of ``goodFeaturesToTrack``'s, not within
        :data:`NEW_APART_PX` of a carried one) and tracked beside them, but fitted only
        from their next step (the module: unbiased). With fewer than
        :data:`MIN_TRACKS` carried (the stream's first step, after a gap or a failed
        step) the fresh corners are fitted on their first step. Carrying
        costs no detection (two thirds of a step's time) and measures the same motion:
        each step's KLT error is its own, wherever the patch came from."""
        carried = self._tracks
        if carried is not None and self._age < REDETECT_EVERY \
                and len(carried) >= max(MIN_TRACKS, REDETECT_SHARE * self._detected):
            self._age += 1
            self.fresh_fit = False
            return carried, np.ones(len(carried), bool)
        if carried is None or len(carried) < MIN_TRACKS:
            carried = np.zeros((0, 1, 2), np.float32)
        pts = _fresh_corners(prev, carried)
        fit = np.zeros(len(carried) + len(pts), bool)
        fit[:len(carried)] = True
        if not len(carried):
            fit[:] = True
        self._detected, self._age = len(fit), 1
        self.fresh_fit = not len(carried)
        return (np.concatenate([carried, pts]), fit) if np.count_nonzero(fit) >= MIN_TRACKS \
            else None

    def _motion(self, prev: np.ndarray, grey: np.ndarray, near=None) -> Increment | None:
        got = self._corners(prev)
        self._tracks = None
        if got is None:
            return None
        pts, fit = got
        nxt, ok = _tracked(prev, grey, pts)
        if np.count_nonzero(ok) < MIN_TRACKS:
            return None
        warp = _turn_warp(pts[ok], nxt[ok])
        if warp is not None:
            # the later frame turned back onto the earlier one, tracked again, and the
            # tracks carried back to its own pixels (see _turn_warp)
            aligned = cv2.warpAffine(grey, warp, grey.shape[::-1],
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_REPLICATE)
            nxt, ok = _tracked(prev, aligned, pts)
            if np.count_nonzero(ok) < MIN_TRACKS:
                return None
            nxt = (nxt @ warp[:, :2].T.astype(np.float32) + warp[:, 2].astype(np.float32))
            h, w = grey.shape                    # not on the turned frame's filled border
            u, v = nxt[:, 0, 0], nxt[:, 0, 1]
            ok &= (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
            if np.count_nonzero(ok) < MIN_TRACKS:
                return None
        inc, carry = self._fit(pts, nxt, ok, near, fit)
        if inc is not None:
            # carried to the next step: the fit's inliers and the fresh corners it
            # explains, not at the frame's edge
            idx = np.flatnonzero(ok)[carry]
            self._tracks = nxt[idx[_off_edge(nxt[idx], grey.shape)]]
        return inc

    def _fit(self, pts: np.ndarray, nxt: np.ndarray, ok: np.ndarray, near,
             fit: np.ndarray) -> tuple[Increment | None, np.ndarray]:
        """The increment of the tracks ``pts -> nxt`` kept by ``ok`` and chosen by
        ``fit`` (None when the fit does not explain them, :func:`explained`), and the
        mask (over the kept) of the tracks to carry: those that met the ceiling outside
        the site's ignore regions and are the fit's inliers, or were not fitted (fresh)
        and lie within the fit's :data:`MISFIT_ALPHA` quantile of two degrees of
        freedom at :data:`TRACK_NOISE_PX`."""
        cam = self.geo.camera
        q = ceiling_points_vehicle(self.geo, cam.unproject(pts.reshape(-1, 2)[ok]))
        p_norm = cam.unproject(nxt.reshape(-1, 2)[ok])
        p = ceiling_points_vehicle(self.geo, p_norm)
        good = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
        hit = None if self.site is None else ignored_from(self.site, q, near)
        if hit is not None:                      # SPEC §2: a region's tracks are not used
            good &= ~hit
        use = good & fit[ok]
        carry = np.zeros(len(q), bool)
        inc = plane_motion(q[use], p[use])
        if inc is None:
            return None, carry
        jac = ceiling_jacobian(p_norm[good], self.geo.R_vehicle_cam, self.geo.rise_m)
        m_per_px = np.zeros(len(q))
        m_per_px[good] = np.sqrt(np.abs(np.linalg.det(jac))) / cam.fx
        if not explained(inc, q[use], p[use], m_per_px[use]):
            return None, carry
        carry[np.flatnonzero(use)[inc.kept]] = True
        new = np.flatnonzero(good & ~fit[ok])
        if len(new):
            c, s = math.cos(inc.dyaw_rad), math.sin(inc.dyaw_rad)
            r = q[new] - (p[new] @ np.array([[c, s], [-s, c]]) + [inc.dx_m, inc.dy_m])
            chi2 = np.sum((r / m_per_px[new, None]) ** 2, axis=1) / TRACK_NOISE_PX ** 2
            carry[new[chi2 <= chi2_quantile(1.0 - MISFIT_ALPHA, 2)]] = True
        return inc, carry


def _off_edge(pts: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(N,)`` bool: which of the tracks ``pts (N, 1, 2)`` lie :data:`HALF_WIN` px or
    more inside a frame of ``shape`` (a window KLT can follow them with)."""
    h, w = shape
    u, v = pts[:, 0, 0], pts[:, 0, 1]
    return (u >= HALF_WIN) & (u < w - HALF_WIN) & (v >= HALF_WIN) & (v < h - HALF_WIN)


def _tracked(prev: np.ndarray, grey: np.ndarray, pts: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """``(nxt (N, 1, 2) float32, ok (N,) bool)``: the corners ``pts`` of ``prev``
    tracked into ``grey`` by pyramidal KLT, kept when both ways succeed and the
    track back lands within :data:`FB_MAX_PX` of the start."""
    nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, grey, pts, None, **LK)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, prev, nxt, None, **LK)
    fb = np.linalg.norm((back - pts).reshape(-1, 2), axis=1)
    return nxt, (st.ravel() == 1) & (st2.ravel() == 1) & (fb < FB_MAX_PX)


def _turn_warp(p0: np.ndarray, p1: np.ndarray) -> np.ndarray | None:
    """The rigid map of pixels ``(2, 3)`` (``p1 ~ A[:, :2] p0 + A[:, 2]``) fitted to
    tracks ``(N, 1, 2)`` of a step, or None when it turns less than
    :data:`TURN_WARP_MIN_RAD`."""
    yaw, t = fit_rigid_2d(p0.reshape(-1, 2).astype(float), p1.reshape(-1, 2).astype(float))
    if abs(yaw) < TURN_WARP_MIN_RAD:
        return None
    c, s = math.cos(yaw), math.sin(yaw)
    t = np.rint(t)               # whole pixels: a shift alone is not resampled
    return np.array([[c, -s, t[0]], [s, c, t[1]]])


def _fresh_corners(prev: np.ndarray, carried: np.ndarray) -> np.ndarray:
    """``(M, 1, 2) float32``: the corners detected on ``prev`` (:func:`corner_like` of
    ``goodFeaturesToTrack``'s) not within :data:`NEW_APART_PX` of a ``carried`` track."""
    pts = cv2.goodFeaturesToTrack(prev, CANDIDATES, CORNER_QUALITY, 8, blockSize=5)
    if pts is None:
        return np.zeros((0, 1, 2), np.float32)
    pts = pts[corner_like(prev, pts.reshape(-1, 2))]
    if len(carried) and len(pts):
        d = np.linalg.norm(pts[:, None, 0, :] - carried[None, :, 0, :], axis=2)
        pts = pts[d.min(axis=1) >= NEW_APART_PX]
    return pts.astype(np.float32)


def with_increment(odo: PlaneOdometry, got, grey: np.ndarray, t_ns: int, measure: bool,
                   prior, t0: float):
    """``got`` (a method's estimate of this frame) carrying the ceiling-plane increment
    since the previous frame (:meth:`PlaneOdometry.increment`; ``measure``: whether it
    is wanted: not after an absolute fix that followed another), and the method's time
    ``ms`` since ``t0`` (``time.perf_counter``) with it; ``got`` itself when there is
    none, its ``ms`` (when it has one) again with the tracking that ran (a step after a
    kept frame first follows the tracks into it: :meth:`PlaneOdometry.increment`)."""
    inc = odo.increment(grey, t_ns, measure, prior)
    if inc is None:
        if not measure or "ms" not in got.diagnostics:     # a kept frame: nothing ran
            return got
        return dataclasses.replace(got, diagnostics={**got.diagnostics, "ms": elapsed_ms(t0)})
    return dataclasses.replace(got, increment=inc,
                               diagnostics={**got.diagnostics, "ms": elapsed_ms(t0)})
