"""The corridor method's per-frame stages in array code: the readings the compiled loops
(:func:`.association.match_core`, :func:`.hypotheses.hypothesis_core`,
:func:`.hypotheses.families_core`, :func:`.hypotheses.pans_core`,
:func:`.consensus.consensus_core`, :func:`.refine.rows_steps`,
:func:`.frame.counts_core`, :func:`~ceilkit.runtime.features.lines.refine_undistorted`'s
:func:`_profile_points`) stand for, kept here as the references they are tested
against."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ceilkit.runtime.estimators.corridor.association import (
    SEAM_STEP,
    OffsetMatch,
    gauss,
)
from ceilkit.runtime.estimators.corridor.consensus import (
    CONSENSUS_ROUNDS,
    CONSENSUS_SIGMA_PX,
    CORE_MIN_LINES,
    GATE_FLOOR_PX,
    GATE_SIGMAS,
    VP_SIGMAS,
    Consensus,
    endpoint_distances,
)
from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import (
    along_offsets,
    fit_pan,
    vanishing_angles,
)
from ceilkit.runtime.estimators.corridor.hypotheses import PAN_BINS, Labeling, families
from ceilkit.runtime.estimators.corridor.refine import (
    STEP_DONE,
    GNInputs,
    PanOffsetFit,
    RowRates,
    residual_cov,
    residuals,
)
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.edges import (
    OUTLIER_FLOOR_PX,
    OUTLIER_SIGMAS,
    PROFILE_STEP_PX,
    directions,
    edge_grid,
    part_indices,
    profiles_at,
)
from ceilkit.runtime.features.lines import (
    MIN_FIT_POINTS,
    ProfileGrid,
    ProfileKind,
    _fit_segments,
    _kind_and_points,
)
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.jit import arr

# ----------------------------------------------------------------------------- association


def _shift_candidates(o: np.ndarray, ys: np.ndarray, cw: np.ndarray | None,
                      tol_m: float) -> np.ndarray:
    """The shifts ``y_j - o_i`` of every allowed pairing, those closer than a quarter
    of the gate merged (the first of each, in the order of their keys, as
    ``np.unique(..., return_index=True)``); empty when nothing may pair."""
    nj = ys.size
    if cw is None:
        ii, jj = np.divmod(np.arange(o.size * nj), max(nj, 1))
    else:
        ii, jj = np.nonzero(cw > 0)
    if ii.size == 0:
        return np.zeros(0)
    cands = ys[jj] - o[ii]
    key = np.round(cands * (4.0 / tol_m))
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.empty(ks.size, bool)
    first[0] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    return cands[order[first]]


def match_offsets(offsets: np.ndarray, weights: np.ndarray, site_y: np.ndarray,
                  tol_m: float, prior_shift_m: float | None = None,
                  anchors_m: np.ndarray | None = None,
                  compat: np.ndarray | None = None) -> OffsetMatch | None:
    """:func:`~ceilkit.runtime.estimators.corridor.association.match_offsets`
    in array code (its docstring is the reference)."""
    o_all = np.asarray(offsets, dtype=float)
    ok = np.flatnonzero(np.isfinite(o_all))
    if ok.size == 0:
        return None
    o = o_all[ok]
    w = np.asarray(weights, dtype=float)[ok]
    ys = np.asarray(site_y, dtype=float)
    nj = ys.size
    cw = None if compat is None else np.asarray(compat, dtype=float).reshape(-1, nj)[ok]
    cands = _shift_candidates(o, ys, cw, tol_m)
    if cands.size == 0:
        return None
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
    g = gauss(d / sig) * inl                                                     # (K, N)
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
        soft = soft + gauss((c_ref[:, None] - a[None, :]) / sig).sum(axis=1) / a.size
    return _winner(c_ref, soft, sw, n_lines, jm, ok, o_all.size, tol_m, prior_shift_m)


def _winner(c_ref: np.ndarray, soft: np.ndarray, sw: np.ndarray, n_lines: np.ndarray,
            jm: np.ndarray, ok: np.ndarray, n_all: int, tol_m: float,
            prior_shift_m: float | None) -> OffsetMatch | None:
    """The best of the scored hypotheses (``(K,)`` shifts, soft scores, matched weights,
    lines matched; ``jm (K, N)`` their site lines) and its runner-up: see
    :func:`match_offsets`."""
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
    assign = np.full(n_all, -1)
    assign[ok] = jm[win]
    return OffsetMatch(float(c_ref[win]), assign, int(n_lines[win]), float(sw[win]), runner,
                       float(soft[win]))


def edge_compat(pol_w: np.ndarray, ceil_len_m: np.ndarray, setup: CorridorSetup
                ) -> np.ndarray:
    """``(N, J)`` compatibility of observed forward segments with the site lines' kinds
    (the ``compat`` of :func:`match_offsets`): ``pol_w (N,)`` their edge polarity in W
    (NaN: unknown), ``ceil_len_m (N,)`` their length on the ceiling. A lamp edge is a
    step with the lamp's side bright and no longer than a lamp; a seam is a thin line
    (a step only at :data:`SEAM_STEP`)."""
    sp = setup.edge_kind[None, :]
    p = pol_w[:, None]
    c = np.where(sp != 0, (p == sp).astype(float), np.where(p == 0, 1.0, SEAM_STEP))
    c = np.where(np.isnan(p), 1.0, c)
    return c * (ceil_len_m[:, None] <= setup.longest_m[None, :])


def lamp_anchors(setup: CorridorSetup, lamp_end: np.ndarray, ceil_sx: np.ndarray,
                 ceil_sy: np.ndarray, sel: np.ndarray, psi_rad: float) -> np.ndarray:
    """Camera y estimates (m) from the segments ``sel`` ``(N,)`` bool (the across family)
    as long on the ceiling as a lamp is wide (``lamp_end (L, N)``): the lamp's end,
    whose middle (``ceil_sx, ceil_sy`` ``(N,)``: twice the level-frame midpoint) lies on
    the lamp row's y, for camera pan ``psi_rad``."""
    if not setup.lamp_y_m.size or not sel.any():
        return np.zeros(0)
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    out = []
    for row_y, ends in zip(setup.lamp_y_m, lamp_end, strict=True):
        ok = ends & sel
        out.append(row_y - 0.5 * (s * ceil_sx[ok] + c * ceil_sy[ok]))  # (Rz(psi) m)_y
    return np.concatenate(out)


# ----------------------------------------------------------------------------- hypotheses

_KERNEL = np.exp(-0.5 * (np.arange(-16, 17) / 4.0) ** 2)


def _smooth_circular(hist: np.ndarray) -> np.ndarray:
    """``hist (B,)`` convolved circularly with a Gaussian of 4 bins."""
    return np.convolve(np.concatenate([hist[-16:], hist, hist[:16]]), _KERNEL, "valid")


def dominant_pans(q: np.ndarray, w: np.ndarray, n_peaks: int = 3) -> list[float]:
    """Modes of the segments' horizontal directions (level normals ``q (N, 3)``,
    weights ``w (N,)``), mod 90 deg: candidate ``psi`` (rad), strongest first; a peak
    below a fifth of the first is dropped."""
    theta = np.arctan2(-q[:, 0], q[:, 1])
    nbins = PAN_BINS
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


def refine_pan(psi_rad: float, fr: FrameLines, along: np.ndarray, across: np.ndarray,
               ang: np.ndarray, den: np.ndarray, f_px: float) -> float:
    """One reweighted :func:`.geometry.fit_pan` over both families from ``ang, den``
    (:func:`.geometry.vanishing_angles` at ``psi_rad``): weights length^2 /
    |v_xy - v_z m|^2, Huber at 1 px, 0 outside the families. Returns the pan on the
    branch (mod pi) nearest ``psi_rad``."""
    r = np.where(along, ang[0], ang[1]) * fr.len_n * f_px        # px
    w = (fr.len_n / np.where(along, den[0], den[1])) ** 2 * np.minimum(
        1.0, 1.0 / np.maximum(r, 1e-9))
    new = fit_pan(fr.q, np.where(along, w, 0.0), np.where(across, w, 0.0))
    return new + np.pi * round((psi_rad - new) / np.pi)


def label_families(psi0_rad: float, fr: FrameLines, angle_tol_rad: float, setup: CorridorSetup
                   ) -> tuple[bool, float, np.ndarray, np.ndarray, float, float]:
    """The families of ``label`` about ``psi0_rad``: ``(ok, psi, along, across, along
    ceiling length, across ceiling length)``."""
    ang, den = vanishing_angles(psi0_rad, setup.R_rows, fr.lines_t, fr.mx, fr.my)
    along, across = families(ang, angle_tol_rad)
    if np.count_nonzero(along) + np.count_nonzero(across) < 2:
        return False, psi0_rad, along, across, 0.0, 0.0
    psi = refine_pan(psi0_rad, fr, along, across, ang, den, setup.f_px)
    along, across = families(vanishing_angles(psi, setup.R_rows, fr.lines_t, fr.mx,
                                              fr.my)[0], fr.tol)
    if np.count_nonzero(along) + np.count_nonzero(across) < 2:
        return False, psi, along, across, 0.0, 0.0
    return (True, psi, along, across, float(fr.ceil_len[along].sum()),
            float(fr.ceil_len[across].sum()))


def hypothesis_arrays(pk: float, fa: np.ndarray, fb: np.ndarray, fr: FrameLines,
                      setup: CorridorSetup, tol_m: float, prior_shift: float | None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, OffsetMatch | None]:
    """``hypothesis``' forward offsets, weights, compatibility and match at pan ``pk``."""
    wa = fr.len_n[fa] * setup.f_px
    offs, n_y = along_offsets(fr.q[fa], pk, setup.ceiling_above_cam_m)
    pol_w = fr.pol[fa] * np.sign(n_y)
    compat = edge_compat(pol_w, fr.ceil_len[fa], setup)
    anchors = lamp_anchors(setup, fr.lamp_end, fr.ceil_sx, fr.ceil_sy, fb, pk)
    return offs, wa, compat, match_offsets(offs, wa, setup.site_y, tol_m, prior_shift,
                                           anchors, compat)


# ----------------------------------------------------------------------------- consensus


def shift_candidates(fr_q: np.ndarray, site_y: np.ndarray, psi_rad: float,
                     setup: CorridorSetup) -> np.ndarray:
    """``(N,)``: the camera y that puts each matched segment (level normals ``fr_q
    (N, 3)``, site lines at ``site_y (N,)``) on its site line at pan ``psi_rad``; NaN
    where undefined."""
    offs, _ = along_offsets(fr_q, psi_rad, setup.ceiling_above_cam_m)
    return site_y - offs


def ceiling_consensus(psi_rad: float, candidates_m: np.ndarray, line_of: np.ndarray,
                      gd: GNInputs, setup: CorridorSetup, gate_px: float,
                      sigma_px: float = CONSENSUS_SIGMA_PX,
                      shift_px: np.ndarray | None = None) -> Consensus:
    """:func:`~ceilkit.runtime.estimators.corridor.consensus.ceiling_consensus`
    in array code (its docstring is the reference)."""
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
    """:func:`~ceilkit.runtime.estimators.corridor.consensus.consensus_fit` before its
    rounds were compiled (``inputs(assign)``: the GN inputs of an assignment;
    ``solve(gd, psi, c_y)``: the fit from a start; ``rates``: a rolling shutter's or
    None); its docstring is the reference."""
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


# ----------------------------------------------------------------------------- refine


def gauss_newton_rows(psi_rad: float, camera_y_m: float, gd: GNInputs,
                      setup: CorridorSetup, iterations: int, rates: RowRates
                      ) -> PanOffsetFit:
    """:func:`~ceilkit.runtime.estimators.corridor.refine.gauss_newton_rows`
    in array code (its docstring is the reference)."""
    x = np.array([psi_rad, camera_y_m])
    tau = np.concatenate([gd.tau, gd.tau_b])
    r = np.zeros(0)
    H = Jw = Jr = None
    for _ in range(max(1, iterations)):
        A = residuals(float(x[0]), float(x[1]), gd, setup)
        J = A[:, :2]
        Jr = J * tau[:, None]                       # d r / d (w, v)
        r = A[:, 2] + Jr @ np.array([rates.w_rps, rates.v_mps])
        hw = np.minimum(1.0, 1.0 / np.maximum(np.abs(r), 1e-9))    # Huber, k = 1 px
        Jw = J * hw[:, None]
        H = Jw.T @ J
        try:
            d = -np.linalg.solve(H, Jw.T @ r)
        except np.linalg.LinAlgError:
            H = None
            break
        x = x + d
        if abs(d[0]) < STEP_DONE[0] and abs(d[1]) < STEP_DONE[1]:
            break
    C = None
    if H is not None:
        try:
            Hi = np.linalg.inv(H)
            S = -Hi @ (Jw.T @ Jr)                     # d (psi, c_y) / d (w, v)
            sig = np.array([rates.sigma_w_rps, rates.sigma_v_mps])
            Cr = residual_cov(float(x[0]), float(x[1]), gd, setup, rates)
            C = None if Cr is None else Cr + (S * sig ** 2) @ S.T
        except np.linalg.LinAlgError:
            C = None
    if C is None or not np.all(np.isfinite(C)):
        nan = float("nan")
        cov = ((np.inf, nan), (nan, np.inf))
    else:
        cov = ((float(C[0, 0]), float(C[0, 1])), (float(C[1, 0]), float(C[1, 1])))
    rms_px = math.sqrt(float(r @ r) / r.size) if r.size else float("nan")
    return PanOffsetFit(float(x[0]), float(x[1]), cov, rms_px, r)


# ----------------------------------------------------------------------------- lines


def refine_undistorted(camera: CameraModel, gray: np.ndarray, segs_px: np.ndarray,
                       n_along: int = 8, half_width_px: float = 4.0, min_step: float = 20.0,
                       min_depth: float = 8.0, retry_half_width_px: float | None = 6.0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~ceilkit.runtime.features.lines.refine_undistorted`
    in array code (its docstring is the reference)."""
    s = np.asarray(segs_px, dtype=np.float64).reshape(-1, 4)
    n = s.shape[0]
    rms = np.full(n, np.nan)
    if n == 0:
        return np.zeros((0, 4)), np.zeros(0), rms
    offs, t, inner = edge_grid(n_along, half_width_px)
    d_all, nrm_all = directions(s)
    base = s[:, :2].T[:, :, None] + t * d_all.T[:, :, None]                     # (2, N, A)
    prof = profiles_at(gray, base, nrm_all.T[:, :, None], offs)                 # (N, A, O)
    il, ir, ii = part_indices(offs)
    # each segment's kind from its mean profile, then its edge on every profile (steps
    # and thin lines; a segment of unclear kind is not located) as pixels
    grid = ProfileGrid(arr(offs, np.float64), arr(t, np.float64), arr(il, np.int64),
                       arr(ir, np.int64), arr(ii, np.int64), inner.start + 1, inner.stop + 1)
    pol, pts, good = _kind_and_points(arr(prof, np.float64), arr(s, np.float64), d_all,
                                      nrm_all, grid,
                                      ProfileKind(float(min_step), float(min_depth),
                                                  PROFILE_STEP_PX))
    # the endpoints and the located points through the lens in one call
    xy = camera.unproject_fast(np.concatenate([s.reshape(-1, 2), pts[good]]))
    ends = xy[:2 * n].reshape(n, 4)
    _fit_segments(arr(xy[2 * n:], np.float64), good, ends, rms, 0.5 * (camera.fx + camera.fy),
                  OUTLIER_FLOOR_PX, OUTLIER_SIGMAS, MIN_FIT_POINTS)
    unclear = np.flatnonzero(np.isnan(pol))
    if unclear.size and retry_half_width_px is not None \
            and retry_half_width_px > half_width_px:
        e2, p2, r2 = refine_undistorted(camera, gray, s[unclear], n_along,
                                        retry_half_width_px, min_step, min_depth, None)
        now = np.isfinite(p2)
        ends[unclear[now]], pol[unclear[now]], rms[unclear[now]] = e2[now], p2[now], r2[now]
    return ends, pol, rms


# ----------------------------------------------------------------------------- pose


def _median_finite(a: np.ndarray) -> float:
    """The median of the finite values of ``a`` (NaN if none); as ``np.median``, without
    its overhead on a few values."""
    v = np.sort(a[np.isfinite(a)])
    m = v.size // 2
    if v.size == 0:
        return float("nan")
    return float(v[m]) if v.size % 2 else float(0.5 * (v[m - 1] + v[m]))


def labeled_counts(fr: FrameLines, along: np.ndarray, across: np.ndarray,
                   assign: np.ndarray, fit_rms: np.ndarray) -> tuple:
    """``_pose``'s counts, median and span (the estimator's ``_spread`` before its
    scale)."""
    pol_a = fr.pol[along]
    matched = along & (assign >= 0)
    span = 0.0
    if matched.any():
        ep = fr.segs[matched].reshape(-1, 2)
        span = math.hypot(float(np.ptp(ep[:, 0])), float(np.ptp(ep[:, 1])))
    return (int(np.count_nonzero(along)), int(np.count_nonzero(across)),
            int(np.count_nonzero(np.abs(pol_a) == 1)), int(np.count_nonzero(pol_a == 0)),
            _median_finite(fit_rms), span)
