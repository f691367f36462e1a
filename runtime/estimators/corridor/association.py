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
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.estimators.corridor.visibility import lines_in_view
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.jit import arr, njit, warmer

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
        prior_rival_m: with a prior, the shift nearest it after ``shift_m`` of those
            the frame supports as well (scoring within :data:`AMBIGUITY_RATIO` of
            it); None without a prior or such a shift. The prior singles
            ``shift_m`` out only if its region holds neither this nor the runner-up.
        alike: ``(shift_m, score)`` of every other shift scoring within
            :data:`AMBIGUITY_RATIO` of this one, more than the gate apart, best first
            (the runner-up among them when the match is ambiguous): on a tile grid, a
            shift a period either side of the chosen one and as many more as the
            frame's lines fit (:func:`shifts_alike` counts their absent lines).
    """

    shift_m: float
    assign: np.ndarray
    n_lines: int
    weight: float
    runner_up: tuple[float, float, float] | None
    score: float = 0.0
    prior_rival_m: float | None = None
    alike: tuple[tuple[float, float], ...] = ()


class MatchQuery(NamedTuple):
    """What :func:`match_core` is asked besides the offsets: the gate ``tol_m`` (m),
    whether there is a prior ``has_prior`` and its camera y ``prior_shift_m`` (m)."""

    tol_m: float
    has_prior: bool
    prior_shift_m: float


def is_ambiguous(m: OffsetMatch) -> bool:
    """Whether the runner-up of ``m`` scores within :data:`AMBIGUITY_RATIO` of it."""
    return m.runner_up is not None and m.runner_up[0] >= AMBIGUITY_RATIO * m.score


def gauss(z: np.ndarray) -> np.ndarray:
    """``exp(-z^2 / 2)``, floored at ``exp(-700)`` (1e-304) instead of going subnormal or
    to 0 (where numpy's exp is many times slower); the floor is far below anything
    these scores can resolve (it vanishes when added to a score)."""
    return np.exp(np.maximum(-0.5 * z ** 2, -700.0))


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
    score. None: all 1. Returns None when nothing is matched. One compiled call
    (:func:`match_core`).
    """
    o = arr(offsets, np.float64).ravel()
    ys = arr(site_y, np.float64).ravel()
    cw = (np.ones((o.size, ys.size)) if compat is None
          else np.asarray(compat, dtype=np.float64).reshape(-1, ys.size))
    a = np.zeros(0) if anchors_m is None else np.asarray(anchors_m, dtype=np.float64)
    assign = np.empty(o.size, np.int64)
    query = MatchQuery(float(tol_m), prior_shift_m is not None,
                       0.0 if prior_shift_m is None else float(prior_shift_m))
    res = match_core(o, arr(weights, np.float64).ravel(), ys, query, arr(a, np.float64),
                     arr(cw, np.float64), assign)
    return offset_match(res, assign)


def offset_match(res: tuple, assign: np.ndarray) -> OffsetMatch | None:
    """The :class:`OffsetMatch` of :func:`match_core`'s tuple ``res`` (None: nothing
    matched)."""
    found, shift, n_lines, weight, has_runner, r_score, r_weight, r_shift, score, rival, \
        alike = res
    if not found:
        return None
    return OffsetMatch(shift, assign, n_lines, weight,
                       (r_score, r_weight, r_shift) if has_runner else None, score,
                       None if math.isnan(rival) else float(rival),
                       tuple((float(c), float(v)) for c, v in alike))


@njit
def pairwise_sum(a, n):  # pragma: no cover - compiled
    """The sum of ``a[:n]`` in numpy's order (its pairwise summation: blocks of 8
    accumulators up to 128 values, halves beyond), so that a loop's sum is the array
    reading's to the bit."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    if n <= 128:
        r = np.empty(8)
        for j in range(8):
            r[j] = a[j]
        i = 8
        while i < n - n % 8:
            for j in range(8):
                r[j] += a[i + j]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += a[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return pairwise_sum(a, n2) + pairwise_sum(a[n2:], n - n2)


@njit
def _gauss(z):  # pragma: no cover - compiled
    """:func:`gauss` of a number."""
    return math.exp(max(-0.5 * (z * z), -700.0))


@njit
def _best_of(idx, soft, sw):  # pragma: no cover - compiled
    """The index of ``idx`` with the highest ``soft``, then ``sw``; the first of ties
    (``lexsort((-sw, -soft))[0]``)."""
    b = idx[0]
    for k in idx[1:]:
        if soft[k] > soft[b] or (soft[k] == soft[b] and sw[k] > sw[b]):
            b = k
    return b


@njit
def match_core(o_all, w_all, ys, query, anchors, cw_all, assign
               ):  # pragma: no cover - compiled
    """:func:`match_offsets` of offsets ``o_all (N,)`` with weights ``w_all (N,)`` on
    the site lines ``ys (J,)`` (``query``: a :class:`MatchQuery`), with ``compat``
    ``cw_all (N, J)`` (ones: none) and ``anchors (A,)`` (empty: none), the site line of
    each offset written to ``assign (N,)``: ``(found, shift, n_lines, weight,
    has_runner, runner score, runner weight, runner shift, score, prior rival shift
    (NaN: none), alike (K, 2))``: the hypotheses
    (:func:`_merged_shifts`) scored (:func:`_scored`), the winner and the runner-up
    (the best more than ``tol`` from it) as :func:`match_offsets` says, and every
    other shift within :data:`AMBIGUITY_RATIO` of the winner (:attr:`OffsetMatch.alike`)."""
    tol, has_prior, prior_shift = query
    nothing = (False, 0.0, 0, 0.0, False, 0.0, 0.0, 0.0, 0.0, math.nan, np.empty((0, 2)))
    assign[:] = -1
    ok = np.flatnonzero(np.isfinite(o_all))
    n = ok.size
    if n == 0:
        return nothing
    o = o_all[ok]
    w = w_all[ok]
    cw = np.empty((n, ys.size))
    for i in range(n):
        cw[i] = cw_all[ok[i]]
    cands = _merged_shifts(o, ys, cw, tol)
    if cands.size == 0:
        return nothing
    jm = np.full((cands.size, n), -1)
    c_ref, soft, sw, n_lines = _scored(o, w, ys, cw, cands, tol, anchors, jm)
    idx = np.flatnonzero(n_lines)
    if idx.size == 0:
        return nothing
    if has_prior:
        top = soft[idx[0]]
        for k in idx:
            top = max(top, soft[k])
        win, near = -1, math.inf
        for k in idx:
            if soft[k] >= top - 1.0 and abs(c_ref[k] - prior_shift) < near:
                win, near = k, abs(c_ref[k] - prior_shift)
    else:
        win = _best_of(idx, soft, sw)
    others = idx[np.abs(c_ref[idx] - c_ref[win]) > tol]
    has_runner = others.size > 0
    r_score = r_weight = r_shift = 0.0
    rival = math.nan
    if has_runner:
        r = _best_of(others, soft, sw)
        r_score, r_weight, r_shift = soft[r], sw[r], c_ref[r]
        if has_prior:
            # the next nearest the prior of those the frame supports as well (within
            # AMBIGUITY_RATIO): the one it must rule out (a tile grid's seams fit a
            # shift a period either side; the best scoring other may lie beyond the
            # prior, this one not)
            near = math.inf
            for k in others:
                if soft[k] >= AMBIGUITY_RATIO * soft[win] and \
                        abs(c_ref[k] - prior_shift) < near:
                    rival, near = c_ref[k], abs(c_ref[k] - prior_shift)
    for i in range(n):
        assign[ok[i]] = jm[win, i]
    return (True, c_ref[win], n_lines[win], sw[win], has_runner, r_score, r_weight, r_shift,
            soft[win], rival, _alike(others, c_ref, soft, soft[win], tol))


@njit
def _alike(others, c_ref, soft, top, tol):  # pragma: no cover - compiled
    """``(shift, score)`` of the hypotheses ``others`` scoring at least
    :data:`AMBIGUITY_RATIO` of ``top``, best first, each more than ``tol`` from those
    before it (the refined shifts of two pairings can meet)."""
    out = np.empty((others.size, 2))
    na = 0
    order = others[np.argsort(-soft[others], kind="mergesort")]
    for k in order:
        if soft[k] < AMBIGUITY_RATIO * top:
            break
        dup = False
        for a in range(na):
            dup = dup or abs(out[a, 0] - c_ref[k]) <= tol
        if not dup:
            out[na, 0], out[na, 1] = c_ref[k], soft[k]
            na += 1
    return out[:na].copy()


@njit
def _merged_shifts(o, ys, cw, tol):  # pragma: no cover - compiled
    """The shifts ``y_j - o_i`` of every allowed pairing (``cw > 0``, in row order),
    those closer than a quarter of the gate merged: the first of each, in the order of
    their keys (as ``np.unique(..., return_index=True)``)."""
    raw = np.empty(o.size * ys.size)
    m = 0
    for i in range(o.size):
        for j in range(ys.size):
            if cw[i, j] > 0:
                raw[m] = ys[j] - o[i]
                m += 1
    key = np.rint(raw[:m] * (4.0 / tol))
    order = np.argsort(key, kind="mergesort")
    cands = np.empty(m)
    nk = 0
    for r in range(m):
        if r == 0 or key[order[r]] != key[order[r - 1]]:
            cands[nk] = raw[order[r]]
            nk += 1
    return cands[:nk]


@njit
def _scored(o, w, ys, cw, cands, tol, anchors, jm):  # pragma: no cover - compiled
    """Each hypothesis of ``cands (K,)``: every offset to its nearest allowed site line,
    the shift refined once by the weighted mean over the inliers, then scored (see
    :class:`OffsetMatch`; the anchors add their mean agreement): ``(c_ref, soft, sw,
    n_lines)`` ``(K,)``, the inliers' site lines in ``jm (K, N)``."""
    n, nj, nk = o.size, ys.size, cands.size
    sig = tol / 3.0
    c_ref, soft, sw = np.empty(nk), np.empty(nk), np.empty(nk)
    n_lines = np.empty(nk, np.int64)
    d, buf, wbuf = np.empty(n), np.empty(n), np.empty(n)
    jj = np.empty(n, np.int64)
    inl = np.empty(n, np.bool_)
    best = np.empty(nj + 1)
    hit = np.empty(nj, np.bool_)
    g = np.empty(anchors.size)
    for k in range(nk):
        for i in range(n):
            x = o[i] + cands[k]
            jb, db = 0, math.inf
            for j in range(nj):
                if cw[i, j] > 0 and abs(x - ys[j]) < db:
                    jb, db = j, abs(x - ys[j])
            jj[i] = jb
            d[i] = x - ys[jb]
            inl[i] = db <= tol
            wbuf[i] = w[i] if inl[i] else 0.0
            buf[i] = wbuf[i] * d[i]
        shift = pairwise_sum(buf, n) / max(pairwise_sum(wbuf, n), 1e-300)
        c_ref[k] = cands[k] - shift
        best[:] = 0.0
        hit[:] = False
        for i in range(n):
            d[i] -= shift
            inl[i] = inl[i] and abs(d[i]) <= tol
            wbuf[i] = w[i] if inl[i] else 0.0
            if inl[i]:
                jm[k, i] = jj[i]
                hit[jj[i]] = True
                best[jj[i] + 1] = max(best[jj[i] + 1], _gauss(d[i] / sig) * cw[i, jj[i]])
        sw[k] = pairwise_sum(wbuf, n)
        soft[k] = pairwise_sum(best[1:], nj)
        n_lines[k] = np.count_nonzero(hit)
        if anchors.size:
            for a in range(anchors.size):
                g[a] = _gauss((c_ref[k] - anchors[a]) / sig)
            soft[k] = soft[k] + pairwise_sum(g, anchors.size) / anchors.size
    return c_ref, soft, sw, n_lines


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


@njit
def spread_core(q, sel, weights, psi, h, spacing, tol):  # pragma: no cover - compiled
    """:func:`periodic_spread`'s inliers of the across offsets
    (:func:`.geometry.across_offsets` at pan ``psi``, height ``h``) of the segments
    ``sel (N,)`` with level normals ``q (N, 3)`` and ``weights (N,)``, in one loop."""
    c, s = math.cos(psi), math.sin(psi)
    n = sel.size
    ph = np.empty(n)
    ws = np.empty(n)
    wc = np.empty(n)
    k = 0
    for i in range(n):
        if not sel[i]:
            continue
        nx = c * q[i, 0] - s * q[i, 1]
        if abs(nx) > 1e-12:
            ph[k] = 2 * np.pi * (-q[i, 2] * h / nx) / spacing
            ws[k] = weights[i] * math.sin(ph[k])
            wc[k] = weights[i] * math.cos(ph[k])
            k += 1
    if k == 0:
        return 0
    m = math.atan2(pairwise_sum(ws, k), pairwise_sum(wc, k))
    n_in = 0
    for t in range(k):
        r = abs(((ph[t] - m + np.pi) % (2 * np.pi)) - np.pi) * spacing / (2 * np.pi)
        n_in += r <= tol
    return n_in


@njit
def unseen_core(offsets, compat, site_y, shift, tol, view):  # pragma: no cover - compiled
    """How many site lines ``view (J,)`` puts clearly in view that no forward segment
    (``offsets (N,)``, NaN ignored, ``compat (N, J)``) lies on at camera y ``shift``
    (within ``tol``, of a fitting kind: ``compat > 0``)."""
    n_out = 0
    for j in range(site_y.size):
        if not view[j]:
            continue
        seen = False
        for i in range(offsets.size):
            if (math.isfinite(offsets[i]) and abs(offsets[i] + shift - site_y[j]) <= tol
                    and compat[i, j] > 0):
                seen = True
                break
        n_out += not seen
    return n_out


def edge_compat(pol_w: np.ndarray, ceil_len_m: np.ndarray, setup: CorridorSetup
                ) -> np.ndarray:
    """``(N, J)`` compatibility of observed forward segments with the site lines' kinds
    (the ``compat`` of :func:`match_offsets`): ``pol_w (N,)`` their edge polarity in W
    (NaN: unknown), ``ceil_len_m (N,)`` their length on the ceiling. A lamp edge is a
    step with the lamp's side bright and no longer than a lamp; a seam is a thin line
    (a step only at :data:`SEAM_STEP`). (:func:`compat_core`.)"""
    return compat_core(arr(pol_w, np.float64), arr(ceil_len_m, np.float64),
                       arr(setup.edge_kind, np.float64), arr(setup.longest_m, np.float64))


@njit
def compat_core(pol_w, ceil_len, kind, longest):  # pragma: no cover - compiled
    """:func:`edge_compat` ``(N, J)`` of polarities and ceiling lengths ``(N,)`` with the
    site lines' kinds and longest stretches ``(J,)``."""
    n, nj = pol_w.size, kind.size
    out = np.empty((n, nj))
    for i in range(n):
        p = pol_w[i]
        for j in range(nj):
            if math.isnan(p):
                c = 1.0
            elif kind[j] != 0:
                c = 1.0 if p == kind[j] else 0.0
            else:
                c = 1.0 if p == 0 else SEAM_STEP
            out[i, j] = c if ceil_len[i] <= longest[j] else 0.0
    return out


def lamp_anchors(setup: CorridorSetup, lamp_end: np.ndarray, ceil_sx: np.ndarray,
                 ceil_sy: np.ndarray, sel: np.ndarray, psi_rad: float) -> np.ndarray:
    """Camera y estimates (m) from the segments ``sel`` ``(N,)`` bool (the across family)
    as long on the ceiling as a lamp is wide (``lamp_end (L, N)``): the lamp's end,
    whose middle (``ceil_sx, ceil_sy`` ``(N,)``: twice the level-frame midpoint) lies on
    the lamp row's y, for camera pan ``psi_rad`` (:func:`anchors_core`)."""
    return anchors_core(arr(setup.lamp_y_m, np.float64), arr(lamp_end, np.bool_),
                        arr(ceil_sx, np.float64), arr(ceil_sy, np.float64),
                        arr(sel, np.bool_), float(psi_rad))


@njit
def anchors_core(lamp_y, lamp_end, ceil_sx, ceil_sy, sel, psi
                 ):  # pragma: no cover - compiled
    """:func:`lamp_anchors`: row by row, the selected lamp ends' camera y."""
    c, s = math.cos(psi), math.sin(psi)
    out = np.empty(lamp_end.size)
    k = 0
    for r in range(lamp_y.size):
        for i in range(sel.size):
            if lamp_end[r, i] and sel[i]:
                out[k] = lamp_y[r] - 0.5 * (s * ceil_sx[i] + c * ceil_sy[i])  # (Rz(psi) m)_y
                k += 1
    return out[:k]


def settle_by_absence(m: OffsetMatch, offsets: np.ndarray, weights: np.ndarray,
                      compat: np.ndarray, psi_rad: float, setup: CorridorSetup,
                      camera: CameraModel, min_length_px: float, tol_m: float
                      ) -> tuple[OffsetMatch, bool]:
    """Between the winning lateral shift of ``m`` and its runner-up, count against each
    the site lines it puts clearly in view (:func:`.visibility.lines_in_view`) that no
    forward segment of a fitting kind lies on (``offsets``, ``weights`` ``(N,)`` and
    ``compat (N, J)`` of the forward family); :data:`ABSENCE_PENALTY` each. Returns the
    match kept (the runner-up's only when it misses fewer lines and so scores higher:
    a winner a prior chose may score a little below its runner-up, which is not
    absence) and whether the two are still within :data:`AMBIGUITY_RATIO`."""
    c_w, c_r = m.shift_m, m.runner_up[2]
    in_view = lines_in_view(setup, camera, min_length_px, psi_rad, (c_w, c_r))
    o, cw, ys = arr(offsets, np.float64), arr(compat, np.float64), arr(setup.site_y, np.float64)
    adj = [unseen_core(o, cw, ys, float(c), float(tol_m), in_view[r])
           for r, c in enumerate((c_w, c_r))]
    s_w = m.score - ABSENCE_PENALTY * adj[0]
    s_r = m.runner_up[0] - ABSENCE_PENALTY * adj[1]
    if s_r > s_w and adj[1] < adj[0]:
        # only the absence settles here: with a prior the winner may score up to a line
        # below the runner-up (the prior chose it), and that is the prior's to judge
        alt = match_offsets(offsets, weights, setup.site_y, tol_m, c_r, None, compat)
        if alt is None or abs(alt.shift_m - c_r) > tol_m:
            return m, True
        m, s_w, s_r = alt, s_r, s_w
    return m, bool(s_r >= AMBIGUITY_RATIO * s_w)


def shifts_alike(m: OffsetMatch, offsets: np.ndarray, compat: np.ndarray, psi_rad: float,
                 setup: CorridorSetup, camera: CameraModel, min_length_px: float,
                 tol_m: float) -> tuple[float, ...]:
    """The other lateral shifts (camera y, m) the frame supports as well as ``m``'s: of
    :attr:`OffsetMatch.alike`, those whose score less :data:`ABSENCE_PENALTY` per site
    line they put clearly in view that no forward segment of a fitting kind lies on is
    at least :data:`AMBIGUITY_RATIO` of ``m``'s so charged (:func:`settle_by_absence`'s
    rule, over every shift instead of the runner-up alone). On a tile grid these are
    the shifts by whole tiles that keep the frame's seams on seams: every one is a pose
    the frame supports, none a choice the frame made."""
    if not m.alike:
        return ()
    cs = (m.shift_m,) + tuple(c for c, _ in m.alike)
    in_view = lines_in_view(setup, camera, min_length_px, psi_rad, cs)
    o, cw, ys = arr(offsets, np.float64), arr(compat, np.float64), arr(setup.site_y, np.float64)
    adj = [unseen_core(o, cw, ys, float(c), float(tol_m), in_view[r])
           for r, c in enumerate(cs)]
    own = m.score - ABSENCE_PENALTY * adj[0]
    return tuple(c for (c, s), a in zip(m.alike, adj[1:], strict=True)
                 if s - ABSENCE_PENALTY * a >= AMBIGUITY_RATIO * own)


@warmer
def _warm() -> None:
    f = np.float64
    one = arr(np.ones(2), f)
    match_core(arr(np.array([0.0, np.nan]), f), one, arr(np.array([0.0, 1.0]), f),
               MatchQuery(0.1, True, 0.0), one, arr(np.ones((2, 2)), f), np.empty(2, np.int64))
    compat_core(one, one, one, one)
    anchors_core(one, arr(np.ones((2, 2), bool), np.bool_), one, one,
                 arr(np.ones(2, bool), np.bool_), 0.0)
    q = arr(np.array([[1.0, 0.0, 0.1], [1.0, 0.0, 0.7]]), f)
    spread_core(q, arr(np.ones(2, bool), np.bool_), one, 0.0, 2.0, 0.6, 0.05)
    unseen_core(one, arr(np.ones((2, 2)), f), one, 0.0, 0.1, np.ones(2, np.bool_))
