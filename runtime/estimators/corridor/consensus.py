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
its site line (:func:`shift_candidates`); each proposal is scored by the site lines
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

from ceilkit.runtime.estimators.corridor.association import SEAM_STEP
from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import (
    along_offsets,
    vanishing_angles,
    vanishing_directions,
)
from ceilkit.runtime.estimators.corridor.hypotheses import Labeling
from ceilkit.runtime.estimators.corridor.refine import (
    GNInputs,
    PanOffsetFit,
    RowRates,
    residuals,
)
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup


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


def shift_candidates(fr_q: np.ndarray, site_y: np.ndarray, psi_rad: float,
                     setup: CorridorSetup) -> np.ndarray:
    """``(N,)``: the camera y that puts each matched segment (level normals ``fr_q
    (N, 3)``, site lines at ``site_y (N,)``) on its site line at pan ``psi_rad``; NaN
    where undefined."""
    offs, _ = along_offsets(fr_q, psi_rad, setup.ceiling_above_cam_m)
    return site_y - offs


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
    ``(2N,)``: added to every proposal's distances (a rolling shutter's,
    :func:`rate_shift`)."""
    cand = np.asarray(candidates_m, dtype=float)
    cand = cand[np.isfinite(cand)]
    n = gd.n_a
    if cand.size == 0 or n == 0:
        return Consensus(math.nan, np.zeros(n, bool), 0)
    d = endpoint_distances(psi_rad, cand, gd, setup)                       # (C, 2N)
    if shift_px is not None:
        d = d + shift_px
    ad = np.abs(d).reshape(cand.size, n, 2).max(axis=2)                     # (C, N)
    g = np.exp(-0.5 * (ad / sigma_px) ** 2)
    nj = int(line_of.max()) + 1
    best_g = np.zeros((cand.size, nj))
    np.maximum.at(best_g, (slice(None), line_of), g)
    best = int(np.argmax(best_g.sum(axis=1)))
    inl = ad[best] <= gate_px
    return Consensus(float(cand[best]), inl, int(np.unique(line_of[inl]).size))


def vanishing_scale(fr: FrameLines, along: np.ndarray, psi_rad: float,
                    setup: CorridorSetup) -> float:
    """A robust scale (px) of how far the forward family's segments ``along`` ``(N,)``
    miss its vanishing point at pan ``psi_rad``: each segment's endpoints' distance from
    the line through its midpoint and the vanishing point (half its angle residual times
    its length), 1.4826 times their median. A line at another height shares the
    vanishing point: this measures the frame's noise, not the site's fit."""
    if not along.any():
        return 0.0
    ang = vanishing_angles(psi_rad, setup.R_rows, fr.lines_t[:, along], fr.mx[along],
                           fr.my[along])[0][0]
    return 1.4826 * float(np.median(0.5 * ang * fr.len_n[along] * setup.f_px))


def rate_shift(psi_rad: float, camera_y_m: float, gd: GNInputs, setup: CorridorSetup,
               rates: RowRates | None) -> np.ndarray:
    """``(K,)``: what a rolling shutter adds to the matched forward endpoints' distances
    at ``(psi, c_y)`` (:func:`.refine.gauss_newton_rows`: first order in the rates,
    ``(J_psi w + J_cy v) tau``); zeros without ``rates`` or row times."""
    k = 2 * gd.n_a
    if rates is None or gd.tau is None:
        return np.zeros(k)
    A = residuals(psi_rad, camera_y_m, gd, setup)[:k]
    return (A[:, 0] * rates.w_rps + A[:, 1] * rates.v_mps) * gd.tau


def consensus_fit(fr: FrameLines, lab: Labeling, st: CorridorSetup, inlier_px: float,
                  inputs: Callable[[np.ndarray], GNInputs],
                  solve: Callable[[GNInputs, float, float], PanOffsetFit],
                  rates: RowRates | None = None
                  ) -> tuple[Labeling, GNInputs, PanOffsetFit]:
    """The joint fit of ``lab`` on the matched forward segments that lie on the site's
    ceiling lines: a line at another height (a pipe, a cable tray) that the 1-D
    association matched is left out. ``inputs(assign)``: the GN inputs of an
    assignment; ``solve(gd, psi, c_y)``: the fit from a start; ``rates``: a rolling
    shutter's (or None), for the distances.

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
    ``n_off_ceiling`` set), its GN inputs and the fit."""
    gd_all = inputs(lab.assign)
    ia = np.flatnonzero(lab.along & (lab.assign >= 0))
    line_of = lab.assign[ia]
    cands = np.append(shift_candidates(fr.q[ia], st.site_y[line_of], lab.psi_rad, st),
                      lab.camera_y_m)
    noise = vanishing_scale(fr, lab.along, lab.psi_rad, st)
    sigma = max(CONSENSUS_SIGMA_PX, VP_SIGMAS * noise)
    most = max(inlier_px, GATE_SIGMAS * noise)
    shift = rate_shift(lab.psi_rad, lab.camera_y_m, gd_all, st, rates)
    cons = ceiling_consensus(lab.psi_rad, cands, line_of, gd_all, st, 2.0 * sigma, sigma,
                             shift)
    pol = fr.pol[ia]
    kind_gate = np.where((st.edge_kind[line_of] == 0) & (np.abs(pol) == 1), SEAM_STEP, 1.0)
    psi, cy, inl, gate = lab.psi_rad, cons.camera_y_m, cons.inlier, None
    if cons.n_lines < CORE_MIN_LINES:
        cy, inl, gate = lab.camera_y_m, np.ones(ia.size, bool), most
    for _ in range(CONSENSUS_ROUNDS):
        assign = lab.assign.copy()
        assign[ia[~inl]] = -1
        gd = inputs(assign)
        fit = solve(gd, psi, cy)
        psi, cy = fit.psi_rad, fit.camera_y_m
        d = np.abs(endpoint_distances(psi, np.array([cy]), gd_all, st)[0]
                   + rate_shift(psi, cy, gd_all, st, rates)).reshape(-1, 2)
        if gate is None:            # the core's scatter about its own fit
            k = 2 * np.count_nonzero(inl)
            scale = 1.4826 * float(np.median(d[inl])) * math.sqrt(k / (k - 2))
            gate = min(most, max(GATE_FLOOR_PX, GATE_SIGMAS * scale))
        now = d.max(axis=1) <= gate * kind_gate
        if np.array_equal(now, inl) or not now.any():
            break
        inl = now
    n_lines = int(np.unique(assign[assign >= 0]).size)
    return (replace(lab, assign=assign, n_lines=n_lines,
                    n_off_ceiling=int(ia.size - np.count_nonzero(assign >= 0))), gd, fit)
