"""Which forward segments lie on the site's ceiling lines: the consensus of the matched
segments in pixels, robust to lines at another height (pipes, ducts, cable trays).

A line along the corridor at height ``z'`` below the ceiling shares the forward
vanishing point (it is parallel to the ceiling's lines: it serves the heading), but its
image line is the image of a ceiling line at ``c_y + (y' - c_y) h / h'`` (``h, h'``:
the ceiling's and the line's height above the camera). The 1-D association
(:mod:`.association`, a gate of several cm) pairs such a line with a nearby site line;
its endpoints then miss that line's predicted image line by pixels, at one end more
than at the other (a different slope through the same vanishing point), while the
ceiling's own lines fit to a fraction of a pixel. So, with the pan fixed by the
vanishing point, every matched segment proposes the camera's y that puts it exactly on
its site line (:func:`consensus_core`); each proposal is scored by the site lines
it puts within ``gate_px`` of a segment (both endpoints) and then by the truncated
squared endpoint distances of all of them (MSAC); the best proposal's segments within
the gate are the ceiling's (:func:`ceiling_consensus`). The rest are left unmatched:
in the joint fit they do not pull the lateral estimate.

Example::

    keep = ceiling_consensus(psi, candidates, gd, setup, gate_px=2.5)
    assign[matched[~keep.inlier]] = -1
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.corridor.association import SEAM_STEP, pairwise_sum
from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import (
    vanishing_directions,
)
from ceilkit.runtime.estimators.corridor.hypotheses import Labeling, angles_core
from ceilkit.runtime.estimators.corridor.refine import (
    FrameArrays,
    FrameFit,
    GNInputs,
    LevelCamera,
    RowRates,
    directions_core,
    gn_arrays,
    huber_steps,
    joint_fit,
    level_camera,
    observation,
    rows_steps,
)
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.geometry.fits import median_of
from ceilkit.runtime.jit import arr, njit, warmer


def endpoint_distances(psi_rad: float, camera_y_m: np.ndarray, gd: GNInputs,
                       setup: CorridorSetup) -> np.ndarray:
    """``(C, K)``: the signed pixel distance of each matched forward endpoint of ``gd``
    (K of them) to its site line's predicted image line, for camera pan ``psi_rad`` and
    each camera y in ``camera_y_m`` ``(C,)`` (the formula of
    :func:`.refine.residuals`, column 2, over many ``c_y`` at once)."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    _, vb = vanishing_directions(psi_rad, setup.R_rows)
    h, m2 = setup.ceiling_above_cam_m, setup.R_rows[2]
    dy = gd.y[None, :] - np.asarray(camera_y_m, dtype=float).reshape(-1, 1)    # (C, K)
    num = h * (s * gd.e0 + c * gd.e1) - dy * gd.ez
    return num * setup.f_px / np.hypot(h * vb[0] - dy * m2[0], h * vb[1] - dy * m2[1])


CONSENSUS_ROUNDS = 4
"""Most joint fits of :meth:`CorridorEstimator._fit`: the core's, then each after the
matched segments were gated again at the previous fit."""

CORE_GATE_PX = 1.0
"""The core of the consensus (:func:`~.consensus.ceiling_consensus`): the segments
whose endpoints both lie within this (px) of their site lines at the winning proposal
(at the vanishing point's pan), fitted first."""

CORE_MIN_LINES = 3
"""A core on fewer site lines fits them almost exactly whatever they are (two lines,
two unknowns): its scatter says nothing (:func:`consensus_fit`)."""

GATE_SIGMAS = 4.0
"""The gate after the core's fit: this many robust scales (1.4826 median |r|) of the
core's endpoint residuals about that fit, at least :data:`GATE_FLOOR_PX` and at most
``inlier_px``; every matched segment within it at the fit is kept."""

GATE_FLOOR_PX = 0.5
"""The fit's gate never falls below this (px)."""

VP_SIGMAS = 3.0
"""The score's scale is at least this many :func:`vanishing_scale` (the frame's own
noise, seen where the lateral geometry plays no part)."""

CONSENSUS_SIGMA_PX = 0.5
"""The pixel scale of a proposal's score (:func:`ceiling_consensus`): a line missed by
this much counts 0.61, by twice this 0.14."""


@dataclass(frozen=True)
class Consensus:
    """The matched segments that lie on the site's ceiling lines.

    Attributes:
        camera_y_m: the winning proposal's camera y (a start for the joint fit).
        inlier: ``(N,)`` bool over the matched segments: both endpoints within the gate.
        n_lines: distinct site lines the inliers lie on.
    """

    camera_y_m: float
    inlier: np.ndarray
    n_lines: int


def ceiling_consensus(psi_rad: float, candidates_m: np.ndarray, line_of: np.ndarray,
                      gd: GNInputs, setup: CorridorSetup, gate_px: float,
                      sigma_px: float = CONSENSUS_SIGMA_PX,
                      shift_px: np.ndarray | None = None) -> Consensus:
    """The proposal of ``candidates_m`` ``(C,)`` (camera y, m; NaN ignored) that best
    puts the site's lines on matched segments of ``gd`` (``line_of (N,)``: each
    segment's site line index): the score is the sum over site lines of
    ``exp(-d^2 / 2 sigma^2)`` for the segment on it whose farther endpoint is nearest,
    at distance ``d`` (px): about the number of lines matched, each discounted by its
    misfit, so that four lines missed by 1-2 px (a pipe taken for one of them pulls the
    fit) score less than three lines hit to a fraction of a pixel. The inliers: the
    segments with both endpoints within ``gate_px`` at the winner. ``shift_px``
    ``(2N,)``: added to every proposal's distances (a rolling shutter's, first order in
    its rates: :func:`_distances`). The distances (:func:`endpoint_distances`) scored by
    :func:`score_core`."""
    cand = np.asarray(candidates_m, dtype=float)
    cand = cand[np.isfinite(cand)]
    n = gd.n_a
    if cand.size == 0 or n == 0:
        return Consensus(math.nan, np.zeros(n, bool), 0)
    d = endpoint_distances(psi_rad, cand, gd, setup)                       # (C, 2N)
    if shift_px is not None:
        d = d + shift_px
    inl = np.empty(n, np.bool_)
    best, n_lines = score_core(arr(d, np.float64), arr(line_of, np.int64), float(sigma_px),
                               float(gate_px), inl)
    return Consensus(float(cand[best]), inl, n_lines)


@njit
def score_core(d, line_of, sigma, gate, inl):  # pragma: no cover - compiled
    """:func:`ceiling_consensus`'s scoring of the distances ``d (C, 2N)`` (each
    proposal's, endpoints in pairs): the winning proposal's index and the site lines
    its inliers (written to ``inl (N,)``) lie on."""
    n_c, n = d.shape[0], line_of.size
    nj = line_of.max() + 1
    best_g = np.empty(nj)
    best, top = 0, -np.inf
    for c in range(n_c):
        best_g[:] = 0.0
        for i in range(n):
            ad = max(abs(d[c, 2 * i]), abs(d[c, 2 * i + 1]))
            z = ad / sigma
            best_g[line_of[i]] = max(best_g[line_of[i]], math.exp(-0.5 * (z * z)))
        score = pairwise_sum(best_g, nj)
        if score > top:
            best, top = c, score
    hit = np.zeros(nj, np.bool_)
    for i in range(n):
        inl[i] = max(abs(d[best, 2 * i]), abs(d[best, 2 * i + 1])) <= gate
        hit[line_of[i]] |= inl[i]
    return best, np.count_nonzero(hit)


def consensus_fit(fr: FrameLines, lab: Labeling, st: CorridorSetup, inlier_px: float,
                  iterations: int, rates: RowRates | None = None,
                  tau_s: np.ndarray | None = None) -> FrameFit:
    """The joint fit of ``lab`` on the matched forward segments that lie on the site's
    ceiling lines: a line at another height (a pipe, a cable tray) that the 1-D
    association matched is left out. The fit from a start: :func:`.refine.joint_fit`,
    at most ``iterations`` steps (with ``rates``, a rolling shutter's, and the
    endpoints' row times ``tau_s (N, 2)``: :func:`.refine.gauss_newton_rows`).

    The consensus (:func:`ceiling_consensus`, at the vanishing point's pan; its scale
    :data:`CONSENSUS_SIGMA_PX`, or :data:`VP_SIGMAS` times the frame's
    :func:`vanishing_scale` if larger) picks the core, which is fitted first; the
    core's scatter about that fit sets the gate (:data:`GATE_SIGMAS` robust scales, at
    least :data:`GATE_FLOOR_PX`, at most ``inlier_px`` or :data:`GATE_SIGMAS` times the
    frame's scale if larger; a step on a seam's line, a doubtful kind, within
    :data:`~.association.SEAM_STEP` of it), and the matched segments within the gate at
    each fit are fitted again until they settle (at most :data:`CONSENSUS_ROUNDS`
    fits). A core on
    fewer than :data:`CORE_MIN_LINES` site lines says nothing of the scatter: then all
    matched segments are fitted first, and the gate is its largest. Returns the
    :class:`~.refine.FrameFit`: the labeling with the segments left out unmatched
    (``n_lines`` recounted, ``n_off_ceiling`` set), its GN inputs and the fit. The
    rounds run in one compiled call (:func:`consensus_core`), which gives the last
    fit's assignment, GN inputs and start; that fit is made again here
    (:func:`.refine.joint_fit`) for its residuals and covariance."""
    f64 = np.float64
    rows = rates is not None and tau_s is not None
    assign = np.empty(lab.assign.size, np.int64)
    lines = FrameArrays(fr.segs, fr.lines_t, fr.mx, fr.my, fr.len_n)
    labeled = Labeled(fr.q, fr.pol, arr(lab.along, np.bool_), arr(lab.across, np.bool_),
                      arr(lab.assign, np.int64))
    # the rounds need the rates only (their sigmas make the covariance, solve()'s)
    shutter = Shutter(rows, RowRates(w_rps=float(rates.w_rps) if rows else 0.0,
                                     v_mps=float(rates.v_mps) if rows else 0.0,
                                     sigma_w_rps=0.0, sigma_v_mps=0.0),
                      arr(tau_s if rows else np.zeros((0, 2)), f64))
    start = FitStart(float(lab.psi_rad), float(lab.camera_y_m), float(inlier_px),
                     max(1, iterations))
    psi, cy, n_lines, n_off, arrays, (tau, tau_b) = consensus_core(
        lines, labeled, SiteLines(arr(st.site_y, f64), arr(st.edge_kind, f64)),
        level_camera(st, st.R_level_cam), start, shutter, assign)
    gd = GNInputs(*arrays, tau=tau if rows else None, tau_b=tau_b if rows else None)
    return FrameFit(fr, replace(lab, assign=assign, n_lines=n_lines, n_off_ceiling=n_off),
                    gd, joint_fit(gd, psi, cy, st, iterations, rates))


class Labeled(NamedTuple):
    """A labeled frame as :func:`consensus_core` takes it: the level normals ``q (N, 3)``
    and polarities ``pol (N,)`` (:class:`~.frame.FrameLines`'), the families ``along,
    across (N,)`` bool and the site line of each forward segment ``assign (N,)`` (-1:
    none)."""

    q: np.ndarray
    pol: np.ndarray
    along: np.ndarray
    across: np.ndarray
    assign: np.ndarray


class SiteLines(NamedTuple):
    """The site's ``lines_along`` as :func:`consensus_core` takes them: ``site_y (J,)``
    (m) and ``edge_kind (J,)`` (:class:`~.setup.CorridorSetup`'s)."""

    site_y: np.ndarray
    edge_kind: np.ndarray


class FitStart(NamedTuple):
    """Where the consensus starts: the labeling's camera pan ``psi_rad`` and y
    ``camera_y_m``, the fit's endpoint gate ``inlier_px`` and its most Gauss-Newton
    steps ``iterations``."""

    psi_rad: float
    camera_y_m: float
    inlier_px: float
    iterations: int


class Shutter(NamedTuple):
    """A rolling shutter as :func:`consensus_core` takes it: whether there is one
    (``rows``), its ``rates`` (:class:`~.refine.RowRates`) and the segments' endpoints'
    row times ``tau_s (N, 2)`` (s; empty without)."""

    rows: bool
    rates: RowRates
    tau_s: np.ndarray


class Motion(NamedTuple):
    """What a rolling shutter adds to :func:`_distances`: whether there is one
    (``rows``), its rates ``w_rps``, ``v_mps`` and the forward endpoints' row times
    ``tau (2K,)`` (s)."""

    rows: bool
    w_rps: float
    v_mps: float
    tau: np.ndarray


class Matched(NamedTuple):
    """The matched forward segments as :func:`_proposed` takes them: the frame's level
    normals ``q (N, 3)``, the segments' indices ``ia (M,)`` and their site lines
    ``line_of (M,)``."""

    q: np.ndarray
    ia: np.ndarray
    line_of: np.ndarray


@njit
def consensus_core(lines, labeled, site, cam, start, shutter, assign
                   ):  # pragma: no cover - compiled
    """:func:`consensus_fit`'s rounds on the frame's segments ``lines`` (a
    :class:`~.refine.FrameArrays`) labeled as ``labeled`` (:class:`Labeled`), the site's
    lines ``site`` (:class:`SiteLines`) and the camera ``cam``
    (:class:`~.refine.LevelCamera`), from ``start`` (:class:`FitStart`); the fits by
    :func:`.refine.huber_steps` (or with ``shutter.rows``, :func:`.refine.rows_steps`
    with its rates and row times: :class:`Shutter`): the last fit's assignment into
    ``assign (N,)`` and ``(psi, c_y)`` its start, the site lines it matches, the
    matched segments it left out, its GN inputs' arrays (:func:`.refine.gn_arrays`)
    and row times (empty without ``rows``)."""
    q, pol, along, across, assign0 = labeled
    site_y, kind = site
    psi0, cy0, inlier_px, iterations = start
    rows, tau_s = shutter.rows, shutter.tau_s
    R, f_px = cam.R, cam.f_px
    gd_all = gn_arrays(lines, along, across, assign0, site_y, cam)
    ia = np.flatnonzero(along & (assign0 >= 0))
    m = ia.size
    line_of = assign0[ia]
    tau_all = (_row_times(tau_s, along & (assign0 >= 0), across) if rows
               else (np.zeros(0), np.zeros(0)))
    noise = vanishing_scale(psi0, R, lines.lines_t, lines.mx, lines.my, lines.len_n, along,
                            f_px)
    sigma = max(CONSENSUS_SIGMA_PX, VP_SIGMAS * noise)
    most = max(inlier_px, GATE_SIGMAS * noise)
    inl = np.zeros(m, np.bool_)
    motion = Motion(rows, shutter.rates.w_rps, shutter.rates.v_mps, tau_all[0])
    n_core, cy = _proposed(Matched(q, ia, line_of), site_y, cam, (psi0, cy0), gd_all, motion,
                           sigma, inl)
    kind_gate = np.empty(m)
    for t in range(m):
        seam_step = kind[line_of[t]] == 0 and abs(pol[ia[t]]) == 1
        kind_gate[t] = SEAM_STEP if seam_step else 1.0
    psi, gate = psi0, -1.0
    if n_core < CORE_MIN_LINES:
        cy, gate = cy0, most
        inl[:] = True
    dist = np.empty(2 * m)
    C = np.empty((2, 2))
    psi_s, cy_s, gd, tau = psi, cy, gd_all, tau_all
    for _ in range(CONSENSUS_ROUNDS):
        assign[:] = assign0
        for t in range(m):
            if not inl[t]:
                assign[ia[t]] = -1
        psi_s, cy_s = psi, cy
        gd = gn_arrays(lines, along, across, assign, site_y, cam)
        r = np.empty(gd[1].size + gd[5].size)
        if rows:
            tau = _row_times(tau_s, along & (assign >= 0), across)
            psi, cy, _ = rows_steps((psi, cy), gd, np.concatenate(tau), cam, iterations,
                                    shutter.rates, r, C)
        else:
            psi, cy = huber_steps((psi, cy), gd, cam, iterations, r)[:2]
        _distances((psi, cy), gd_all, cam, motion, (psi, cy), dist)
        for t in range(2 * m):
            dist[t] = abs(dist[t])
        if gate < 0:                # the core's scatter about its own fit
            gate = _core_gate(dist, inl, most)
        same, any_now = True, False
        for t in range(m):
            now = max(dist[2 * t], dist[2 * t + 1]) <= gate * kind_gate[t]
            same &= now == inl[t]
            any_now |= now
            inl[t] = now
        if same or not any_now:
            break
    hit = np.zeros(site_y.size, np.bool_)
    n_matched = 0
    for i in range(assign.size):
        if assign[i] >= 0:
            hit[assign[i]] = True
            n_matched += 1
    return psi_s, cy_s, np.count_nonzero(hit), m - n_matched, gd, tau


@njit
def _proposed(matched, site_y, cam, start, gd_all, motion, sigma, inl
              ):  # pragma: no cover - compiled
    """The consensus at the labeling's ``start = (psi0, cy0)``: the proposals (each
    matched segment, :class:`Matched`, on its site line of ``site_y``, by
    :func:`.geometry.along_offsets`, then ``cy0``; NaN left out) scored by
    :func:`score_core` (scale ``sigma``, gate ``2 sigma``; the distances
    :func:`_distances` with ``motion``): the site lines of the winner's inliers
    (written to ``inl``) and its camera y (``cy0`` when nothing was proposed)."""
    q, ia, line_of = matched
    psi0, cy0 = start
    h = cam.h_m
    m = ia.size
    c, s = math.cos(psi0), math.sin(psi0)
    cands = np.empty(m + 1)
    k = 0
    for t in range(m):
        i = ia[t]
        n_y = s * q[i, 0] + c * q[i, 1]
        v = site_y[line_of[t]] - (-q[i, 2] * h / n_y if abs(n_y) > 1e-12 else np.nan)
        if math.isfinite(v):
            cands[k] = v
            k += 1
    if math.isfinite(cy0):
        cands[k] = cy0
        k += 1
    if k == 0 or m == 0:
        return 0, cy0
    d = np.empty((k, 2 * m))
    for r in range(k):
        _distances((psi0, cands[r]), gd_all, cam, motion, start, d[r])
    best, n_lines = score_core(d, line_of, sigma, 2.0 * sigma, inl)
    return n_lines, cands[best]


@njit
def _core_gate(dist, inl, most):  # pragma: no cover - compiled
    """The gate from the core's (``inl``) endpoint distances ``dist (2N,)`` about its own
    fit: :data:`GATE_SIGMAS` robust scales (1.4826 median, corrected for the two
    parameters fitted), at least :data:`GATE_FLOOR_PX`, at most ``most``."""
    kk = 2 * np.count_nonzero(inl)
    vals = np.empty(kk)
    e = 0
    for t in range(inl.size):
        if inl[t]:
            vals[e], vals[e + 1] = dist[2 * t], dist[2 * t + 1]
            e += 2
    scale = 1.4826 * median_of(vals) * math.sqrt(kk / (kk - 2))
    return min(most, max(GATE_FLOOR_PX, GATE_SIGMAS * scale))


@njit
def _distances(at, gd, cam, motion, ref, out):  # pragma: no cover - compiled
    """:func:`endpoint_distances` at ``at = (psi, c_y)`` of the along endpoints of ``gd``
    (the arrays of :func:`.refine.gn_arrays`; ``cam``: the
    :class:`~.refine.LevelCamera`) into ``out``, plus with ``motion.rows`` what a
    rolling shutter adds to them at ``ref = (psi_r, c_y_r)``: first order in the rates
    (:func:`.refine.gauss_newton_rows`), ``(J_psi w + J_cy v) tau`` (:class:`Motion`)."""
    psi, cy = at
    R, h, f_px = cam.R, cam.h_m, cam.f_px
    y, e0, e1, ez = gd.y, gd.e0, gd.e1, gd.ez
    k = y.size
    m2x, m2y = R[2, 0], R[2, 1]
    c, s, _, _, _, vb0, vb1, _ = directions_core(psi, R)
    for i in range(k):
        dy = y[i] - cy
        num = h * (s * e0[i] + c * e1[i]) - dy * ez[i]
        out[i] = num * f_px / math.hypot(h * vb0 - dy * m2x, h * vb1 - dy * m2y)
    if motion.rows:
        dirs = directions_core(ref[0], R)
        for i in range(k):
            j0, j1, _ = observation(i, k, dirs, ref[1], gd, cam)
            out[i] += (j0 * motion.w_rps + j1 * motion.v_mps) * motion.tau[i]


@njit
def _row_times(tau_s, sel_a, sel_b):  # pragma: no cover - compiled
    """The row times of :func:`.refine.gn_inputs`: the endpoints of the segments
    ``sel_a`` in pairs, the mean of each of ``sel_b``'s."""
    tau = np.empty(2 * np.count_nonzero(sel_a))
    tau_b = np.empty(np.count_nonzero(sel_b))
    a = b = 0
    for i in range(sel_a.size):
        if sel_a[i]:
            tau[a], tau[a + 1] = tau_s[i, 0], tau_s[i, 1]
            a += 2
        if sel_b[i]:
            tau_b[b] = (tau_s[i, 0] + tau_s[i, 1]) / 2
            b += 1
    return tau, tau_b


@njit
def vanishing_scale(psi, R, lines_t, mx, my, len_n, along, f_px
                    ):  # pragma: no cover - compiled
    """A robust scale (px) of how far the forward family's segments ``along`` ``(N,)``
    miss its vanishing point at pan ``psi``: each segment's endpoints' distance from
    the line through its midpoint and the vanishing point (half its angle residual times
    its length), 1.4826 times their median. A line at another height shares the
    vanishing point: this measures the frame's noise, not the site's fit."""
    n = np.count_nonzero(along)
    if n == 0:
        return 0.0
    ang = np.empty((2, len_n.size))
    den = np.empty((2, len_n.size))
    angles_core(psi, R, lines_t, mx, my, ang, den)
    v = np.empty(n)
    k = 0
    for i in range(len_n.size):
        if along[i]:
            v[k] = 0.5 * ang[0, i] * len_n[i] * f_px
            k += 1
    return 1.4826 * median_of(v)


@warmer
def _warm() -> None:
    f, b = np.float64, np.bool_
    segs = arr(np.array([[-0.2, 0.1, 0.2, 0.1], [-0.2, -0.1, 0.2, -0.1]]), f)
    one, on = arr(np.ones(2), f), arr(np.ones(2, bool), b)
    lines_t = arr(np.array([[0.0, 0.0], [1.0, 1.0], [-0.1, 0.1]]), f)
    q = arr(np.array([[0.0, 1.0, -0.1], [0.0, 1.0, 0.1]]), f)
    assign0 = arr(np.array([0, 1]), np.int64)
    lines = FrameArrays(segs, lines_t, one, one, one)
    labeled = Labeled(q, one, on, arr(~on, b), assign0)
    site = SiteLines(arr(np.array([-0.2, 0.2]), f), one)
    cam = LevelCamera(arr(np.eye(3), f), 2.0, 400.0)
    for rows in (False, True):
        shutter = Shutter(rows, RowRates(0.1, 0.1, 0.0, 0.0), arr(np.zeros((2, 2)), f))
        consensus_core(lines, labeled, site, cam, FitStart(0.0, 0.0, 2.5, 6), shutter,
                       np.empty(2, np.int64))
    score_core(arr(np.zeros((1, 4)), f), assign0, 0.5, 1.0, np.empty(2, b))
