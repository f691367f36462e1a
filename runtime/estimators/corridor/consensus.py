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
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ceilkit.runtime.estimators.corridor.association import SEAM_STEP, pairwise_sum
from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import (
    vanishing_directions,
)
from ceilkit.runtime.estimators.corridor.hypotheses import Labeling, angles_core
from ceilkit.runtime.estimators.corridor.refine import (
    STEP_DONE,
    GNInputs,
    PanOffsetFit,
    RowRates,
    directions_core,
    gn_arrays,
    huber_steps,
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
                  solve: Callable[[GNInputs, float, float], PanOffsetFit], iterations: int,
                  rates: RowRates | None = None, tau_s: np.ndarray | None = None
                  ) -> tuple[Labeling, GNInputs, PanOffsetFit]:
    """The joint fit of ``lab`` on the matched forward segments that lie on the site's
    ceiling lines: a line at another height (a pipe, a cable tray) that the 1-D
    association matched is left out. ``solve(gd, psi, c_y)``: the fit from a start (at
    most ``iterations`` steps: :func:`.refine.gauss_newton`, or with ``rates``, a
    rolling shutter's, and the endpoints' row times ``tau_s (N, 2)``,
    :func:`.refine.gauss_newton_rows`).

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
    labeling with the segments left out unmatched (``n_lines`` recounted,
    ``n_off_ceiling`` set), its GN inputs and the fit. The rounds run in one compiled
    call (:func:`consensus_core`), which gives the last fit's assignment, GN inputs and
    start; that fit is made again here (``solve``) for its residuals and covariance."""
    f64 = np.float64
    rows = rates is not None and tau_s is not None
    w_rps, v_mps = (rates.w_rps, rates.v_mps) if rows else (0.0, 0.0)
    assign = np.empty(lab.assign.size, np.int64)
    psi, cy, n_lines, n_off, arrays, (tau, tau_b) = consensus_core(
        fr.segs, fr.lines_t, fr.mx, fr.my, fr.len_n, fr.q, fr.pol, arr(lab.along, np.bool_),
        arr(lab.across, np.bool_), arr(lab.assign, np.int64),
        arr(tau_s if rows else np.zeros((0, 2)), f64), arr(st.site_y, f64),
        arr(st.edge_kind, f64), arr(st.R_level_cam, f64), float(st.ceiling_above_cam_m),
        float(st.f_px), float(lab.psi_rad), float(lab.camera_y_m), float(inlier_px),
        max(1, iterations), rows, float(w_rps), float(v_mps), assign)
    gd = GNInputs(*arrays, tau=tau if rows else None, tau_b=tau_b if rows else None)
    return (replace(lab, assign=assign, n_lines=n_lines, n_off_ceiling=n_off), gd,
            solve(gd, psi, cy))


@njit
def consensus_core(segs, lines_t, mx, my, len_n, q, pol, along, across, assign0, tau_s,
                   site_y, kind, R, h, f_px, psi0, cy0, inlier_px, iterations, rows, w_rps,
                   v_mps, assign):  # pragma: no cover - compiled
    """:func:`consensus_fit`'s rounds, the fits by :func:`.refine.huber_steps` (or with
    ``rows``, :func:`.refine.rows_steps` with the rates ``w_rps, v_mps`` and row times
    ``tau_s (N, 2)``): the last fit's assignment into ``assign (N,)`` and ``(psi, c_y)``
    its start, the site lines it matches, the matched segments it left out, its GN
    inputs' arrays (:func:`.refine.gn_arrays`) and row times (empty without ``rows``)."""
    gd_all = gn_arrays(segs, lines_t, mx, my, len_n, along, across, assign0, site_y, R, f_px)
    ia = np.flatnonzero(along & (assign0 >= 0))
    m = ia.size
    line_of = assign0[ia]
    tau_all = (_row_times(tau_s, along & (assign0 >= 0), across) if rows
               else (np.zeros(0), np.zeros(0)))
    noise = vanishing_scale(psi0, R, lines_t, mx, my, len_n, along, f_px)
    sigma = max(CONSENSUS_SIGMA_PX, VP_SIGMAS * noise)
    most = max(inlier_px, GATE_SIGMAS * noise)
    inl = np.zeros(m, np.bool_)
    n_core, cy = _proposed(q, ia, line_of, site_y, h, psi0, cy0, gd_all, R, f_px, rows, w_rps,
                           v_mps, tau_all[0], sigma, inl)
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
        gd = gn_arrays(segs, lines_t, mx, my, len_n, along, across, assign, site_y, R, f_px)
        r = np.empty(gd[1].size + gd[5].size)
        if rows:
            tau = _row_times(tau_s, along & (assign >= 0), across)
            psi, cy, _ = rows_steps(psi, cy, *gd[1:], np.concatenate(tau), R, h, f_px,
                                    iterations, STEP_DONE[0], STEP_DONE[1], w_rps, v_mps, 0.0,
                                    0.0, r, C)
        else:
            psi, cy = huber_steps(psi, cy, *gd[1:], R, h, f_px, iterations, STEP_DONE[0],
                                  STEP_DONE[1], r)[:2]
        _distances(psi, cy, gd_all, R, h, f_px, rows, w_rps, v_mps, psi, cy, tau_all[0], dist)
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
def _proposed(q, ia, line_of, site_y, h, psi0, cy0, gd_all, R, f_px, rows, w_rps, v_mps, tau,
              sigma, inl):  # pragma: no cover - compiled
    """The consensus at pan ``psi0``: the proposals (each matched segment ``ia`` on its
    site line, by :func:`.geometry.along_offsets`, then the labeling's ``cy0``; NaN
    left out) scored by :func:`score_core` (scale ``sigma``, gate ``2 sigma``): the
    site lines of the winner's inliers (written to ``inl``) and its camera y (``cy0``
    when nothing was proposed)."""
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
        _distances(psi0, cands[r], gd_all, R, h, f_px, rows, w_rps, v_mps, psi0, cy0, tau,
                   d[r])
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
def _distances(psi, cy, gd, R, h, f_px, rows, w_rps, v_mps, psi_r, cy_r, tau, out
               ):  # pragma: no cover - compiled
    """:func:`endpoint_distances` at ``(psi, c_y)`` of the along endpoints of ``gd`` (the
    arrays of :func:`.refine.gn_arrays`) into ``out``, plus with ``rows`` what a
    rolling shutter adds to them at ``(psi_r, c_y_r)``: first order in the rates
    (:func:`.refine.gauss_newton_rows`), ``(J_psi w + J_cy v) tau`` (row times
    ``tau``)."""
    _, y, e0, e1, ez, p0, p1, mx_b, my_b, scale_b = gd
    k = y.size
    m2x, m2y = R[2, 0], R[2, 1]
    c, s, _, _, _, vb0, vb1, _ = directions_core(psi, R)
    for i in range(k):
        dy = y[i] - cy
        num = h * (s * e0[i] + c * e1[i]) - dy * ez[i]
        out[i] = num * f_px / math.hypot(h * vb0 - dy * m2x, h * vb1 - dy * m2y)
    if rows:
        c, s, va0, va1, va2, vb0, vb1, vb2 = directions_core(psi_r, R)
        for i in range(k):
            j0, j1, _ = observation(i, k, c, s, va0, va1, va2, vb0, vb1, vb2, m2x, m2y, cy_r,
                                    y, e0, e1, ez, p0, p1, mx_b, my_b, scale_b, h, f_px)
            out[i] += (j0 * w_rps + j1 * v_mps) * tau[i]


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
    for rows in (False, True):
        consensus_core(segs, lines_t, one, one, one, q, one, on, arr(~on, b), assign0,
                       arr(np.zeros((2, 2)), f), arr(np.array([-0.2, 0.2]), f), one,
                       arr(np.eye(3), f), 2.0, 400.0, 0.0, 0.0, 2.5, 6, rows, 0.1, 0.1,
                       np.empty(2, np.int64))
    score_core(arr(np.zeros((1, 4)), f), assign0, 0.5, 1.0, np.empty(2, b))
