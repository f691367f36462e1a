"""Which site line is which: the 1-D association of forward offsets with ``lines_along``.

Every pairing of an observed offset with a site line is a hypothesis of the camera's
y (:func:`match_offsets`); what the frame holds settles between them: the segments'
edge kinds (:func:`edge_compat`: a lamp's edge is a step with the lamp's side bright,
a seam a thin line), the lamp ends (:func:`lamp_anchors`) and, when two shifts still
score alike, the site lines each puts in view that no segment lies on
(:func:`settle_by_absence`).

Example::

    m = match_offsets(offsets_m, weights, site_y, tol_m=0.07)
    if m is not None and not is_ambiguous(m):
        camera_y_m = m.shift_m
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.estimators.corridor.visibility import lines_in_view
from ceilkit.runtime.geometry.camera import CameraModel

AMBIGUITY_RATIO = 0.85
"""A runner-up shift scoring at least this share of the winner's leaves the frame
ambiguous (the two are within 15 %)."""

SEAM_STEP = 0.3
"""Compatibility of a step edge with a seam (a seam is seen as a thin line)."""

ABSENCE_PENALTY = 0.5
"""Score charged to a shift per site line it puts clearly in view that no segment of a
fitting kind lies on."""


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


def is_ambiguous(m: OffsetMatch) -> bool:
    """Whether the runner-up of ``m`` scores within :data:`AMBIGUITY_RATIO` of it."""
    return m.runner_up is not None and m.runner_up[0] >= AMBIGUITY_RATIO * m.score


def gauss(z: np.ndarray) -> np.ndarray:
    """``exp(-z^2 / 2)``, floored at ``exp(-700)`` (1e-304) instead of going subnormal or
    to 0 (where numpy's exp is many times slower); the floor is far below anything
    these scores can resolve (it vanishes when added to a score)."""
    return np.exp(np.maximum(-0.5 * z ** 2, -700.0))


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
    """Find the shift ``c`` placing the observed offsets on the site's lines.

    Every pairing ``c = y_j - o_i`` is a hypothesis (refined once by a weighted
    mean over its inliers); it scores by the number of distinct site lines matched
    within ``tol_m``, then by the matched weight. With ``prior_shift_m`` the
    hypothesis nearest the prior wins among those matching at least as many lines
    as the best one less one. Missing, extra and shifted lines are tolerated.
    ``anchors_m``, independent estimates of the shift (lamp ends:
    :func:`lamp_anchors`), add up to one to the score of the hypotheses they
    agree with: they break the tie between hypotheses shifted by a line spacing.
    ``compat`` ``(N, J)`` in [0, 1] says how well offset i can be site line j (its
    edge kind: :func:`edge_compat`); 0 forbids the pairing, other values scale its
    score. None: all 1. Returns None when nothing is matched.
    """
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


def settle_by_absence(m: OffsetMatch, offsets: np.ndarray, weights: np.ndarray,
                      compat: np.ndarray, psi_rad: float, setup: CorridorSetup,
                      camera: CameraModel, min_length_px: float, tol_m: float
                      ) -> tuple[OffsetMatch, bool]:
    """Between the winning lateral shift of ``m`` and its runner-up, count against each
    the site lines it puts clearly in view (:func:`.visibility.lines_in_view`) that no
    forward segment of a fitting kind lies on (``offsets``, ``weights`` ``(N,)`` and
    ``compat (N, J)`` of the forward family); :data:`ABSENCE_PENALTY` each. Returns the
    match kept and whether the two are still within :data:`AMBIGUITY_RATIO`."""
    ok = np.isfinite(offsets)
    c_w, c_r = m.shift_m, m.runner_up[2]
    in_view = lines_in_view(setup, camera, min_length_px, psi_rad, (c_w, c_r))
    adj = []
    for c, view in zip((c_w, c_r), in_view, strict=True):
        seen = np.any((np.abs(offsets[ok][:, None] + c - setup.site_y[None, :])
                       <= tol_m) & (compat[ok] > 0), axis=0)
        adj.append(np.count_nonzero(view & ~seen))
    s_w = m.score - ABSENCE_PENALTY * adj[0]
    s_r = m.runner_up[0] - ABSENCE_PENALTY * adj[1]
    if s_r > s_w:
        alt = match_offsets(offsets, weights, setup.site_y, tol_m, c_r, None, compat)
        if alt is None or abs(alt.shift_m - c_r) > tol_m:
            return m, True
        m, s_w, s_r = alt, s_r, s_w
    return m, bool(s_r >= AMBIGUITY_RATIO * s_w)
