"""Which lines are the families and which family is forward: pan candidates, the
family gate, and the labelings ``psi + k 90 deg`` scored on the site.

A frame's candidates (:func:`dominant_pans`) are the modes of its segments'
horizontal directions mod 90 deg; :func:`label` takes one to the families about it,
refines the pan (one reweighted :func:`.geometry.fit_pan`: :func:`families_core`),
picks the forward family (with a prior, the labeling nearest it; without, the yaw
range, the ceiling lengths, the site, and the paper's ``|pan| <= 45 deg`` rule, in
that order) and associates its lines with the site's (:mod:`.association`). It
returns a :class:`Labeling` or an :class:`Unresolved` reason.

Example::

    for psi0 in dominant_pans(fr.q, weights):
        result = label(psi0, fr, prior, prior_psi, ctx)
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.base import AMBIGUOUS, PoseEstimate
from ceilkit.runtime.estimators.corridor.association import (
    ABSENCE_PENALTY,
    MatchQuery,
    OffsetMatch,
    anchors_core,
    compat_core,
    is_ambiguous,
    match_core,
    offset_match,
    pairwise_sum,
    settle_by_absence,
    shifts_alike,
    spread_core,
    unseen_core,
)
from ceilkit.runtime.estimators.corridor.frame import FrameLines, LineArrays
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.estimators.corridor.visibility import lines_in_view
from ceilkit.runtime.estimators.prior import allows, prior_choice
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import rot_z, wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

DECISIVE = 2.0
"""Forward / across ceiling length ratio that settles which family is forward."""

PAN_BINS = 720
"""Bins of the histogram of horizontal directions mod 90 deg (0.125 deg each)."""

_KERNEL = arr(np.exp(-0.5 * (np.arange(-16, 17) / 4.0) ** 2), np.float64)


class SiteKernel(NamedTuple):
    """The setup as the labeling's compiled loops take it (read-only float64 arrays):
    the site's ``site_y``, ``edge_kind``, ``longest_m`` ``(J,)`` and ``lamp_y_m (L,)``,
    the ceiling's height above the camera ``h_m``, the focal length ``f_px`` and the
    mount's ``R_level_cam (3, 3)`` (:class:`~.setup.CorridorSetup` names them)."""

    site_y: np.ndarray
    edge_kind: np.ndarray
    longest_m: np.ndarray
    lamp_y_m: np.ndarray
    h_m: float
    f_px: float
    R_level_cam: np.ndarray


@dataclass(frozen=True)
class LabelContext:
    """What :func:`label` needs beyond the frame: the setup, the camera, the gates.

    Attributes:
        setup: the rig on the site. camera: its camera model.
        angle_tol_rad: family gate about a vanishing point (first pass).
        match_tol_m: 1-D association gate. min_length_px: the detector's shortest.
        across_seams: the site's ``lines_across`` are seams from wall to wall (a tile
            grid), not only lamp ends: the families may swap (a quarter turn) without
            the frame's ceiling lengths telling.
        assume_heading_rad: a heading the user states the vehicle is within 90 deg of
            (the ``assume_heading_deg`` option): a prior, never a frame's evidence.
        mirror_y_m: the y of the line the site's ``lines_along`` (their kinds, lengths
            and lamp rows) are symmetric about, or None (:func:`.setup.mirror_line`).
        square_grid: the site is a square tile grid (``lines_along`` every
            ``lines_across`` spacing, no lamps): a quarter turn is one of its
            symmetries (:func:`.estimator.square_grid`).
    """

    setup: CorridorSetup
    camera: CameraModel
    angle_tol_rad: float
    match_tol_m: float
    min_length_px: float
    across_seams: bool = False
    assume_heading_rad: float | None = None
    mirror_y_m: float | None = None
    square_grid: bool = False

    @functools.cached_property
    def kernel_setup(self) -> SiteKernel:
        """The setup as the compiled loops take it (:class:`SiteKernel`)."""
        st, f = self.setup, np.float64
        return SiteKernel(arr(st.site_y, f), arr(st.edge_kind, f), arr(st.longest_m, f),
                          arr(st.lamp_y_m, f), float(st.ceiling_above_cam_m),
                          float(st.f_px), arr(st.R_level_cam, f))


def dominant_pans(q: np.ndarray, w: np.ndarray, n_peaks: int = 3) -> list[float]:
    """Modes of the segments' horizontal directions (level normals ``q (N, 3)``,
    weights ``w (N,)``), mod 90 deg: candidate ``psi`` (rad), strongest first; a peak
    below a fifth of the first is dropped. One compiled call (:func:`pans_core`)."""
    return [float(v) for v in pans_core(arr(q, np.float64), arr(w, np.float64), n_peaks,
                                        _KERNEL)]


@njit
def pans_core(q, w, n_peaks, kernel):  # pragma: no cover - compiled
    """:func:`dominant_pans` ``(P,)``: the directions ``atan2(-q_x, q_y)`` times 4 in a
    circular histogram of :data:`PAN_BINS` (linear between bins), smoothed circularly
    by ``kernel`` (a Gaussian of 4 bins), its peaks by parabola, each clearing
    +-24 bins about it."""
    nbins = PAN_BINS
    lo_h = np.zeros(nbins)
    hi_h = np.zeros(nbins)
    for i in range(w.size):
        theta = math.atan2(-q[i, 0], q[i, 1])
        b = ((4 * theta) % (2 * np.pi)) / (2 * np.pi) * nbins
        fl = math.floor(b)
        i0 = int(fl) % nbins
        fr = b - fl
        lo_h[i0] += w[i] * (1 - fr)
        hi_h[(i0 + 1) % nbins] += w[i] * fr
    half = kernel.size // 2
    ext = np.empty(nbins + 2 * half)
    for k in range(ext.size):
        b = (k - half) % nbins
        ext[k] = lo_h[b] + hi_h[b]
    # smoothed where a bin within the kernel holds weight (elsewhere a sum of zeros)
    near = np.zeros(nbins, np.bool_)
    for b in range(nbins):
        if ext[b + half] != 0:
            for k in range(b - half, b + half + 1):
                near[k % nbins] = True
    sm = np.zeros(nbins)
    for p in range(nbins):
        if near[p]:
            acc = 0.0
            for k in range(kernel.size):
                acc += ext[p + k] * kernel[kernel.size - 1 - k]
            sm[p] = acc
    out = np.empty(n_peaks)
    first = 0.0
    n = 0
    work = sm.copy()
    for _ in range(n_peaks):
        p = np.argmax(work)
        top = work[p]
        if top <= 0 or (n and top < 0.2 * first):
            break
        y0, y1, y2 = sm[(p - 1) % nbins], sm[p], sm[(p + 1) % nbins]
        den = y0 - 2 * y1 + y2
        off = 0.5 * (y0 - y2) / den if abs(den) > 1e-12 else 0.0
        if n == 0:
            first = y1
        out[n] = -((p + 0.5 + off) / nbins * 2 * np.pi / 4)
        n += 1
        for k in range(p - 24, p + 25):          # clear +-24 bins about the peak
            work[k % nbins] = 0.0
    return out[:n]


def families(ang: np.ndarray, tol: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """``(along, across)`` ``(N,)`` bool: the nearer vanishing point of ``ang``
    ``(2, N)`` (:func:`.geometry.vanishing_angles`), within ``tol`` (rad, scalar or
    ``(N,)``)."""
    along = (ang[0] <= ang[1]) & (ang[0] <= tol)
    across = (ang[1] < ang[0]) & (ang[1] <= tol)
    return along, across


@dataclass(frozen=True, eq=False)
class TurnLabeling:
    """The labeling ``psi + k 90 deg`` of a frame's families (odd k: they swap).

    Attributes:
        k: the quarter turns. psi_rad: the camera's pan in W for this labeling.
        fa, fb: ``(N,)`` bool, the forward (along) and across segments.
        match: the association of the forward offsets (None: nothing matched).
        offsets_m, weights, compat: the forward segments' offsets ``(A,)``, weights
            ``(A,)`` (pixel length) and edge compatibility ``(A, J)``.
        len_a, len_b: the forward and across families' summed ceiling lengths (m).
    """

    k: int
    psi_rad: float
    fa: np.ndarray
    fb: np.ndarray
    match: OffsetMatch | None
    offsets_m: np.ndarray
    weights: np.ndarray
    compat: np.ndarray
    len_a: float
    len_b: float

    @property
    def n_a(self) -> int:
        """Site lines the forward family matches."""
        return 0 if self.match is None else self.match.n_lines

    @property
    def elong(self) -> float:
        """How much longer the forward family is on the ceiling (m)."""
        return self.len_a - self.len_b


def hypothesis(k: int, psi_rad: float, along: np.ndarray, across: np.ndarray,
               fr: FrameLines, lens: tuple[float, float], prior: PoseEstimate | None,
               ctx: LabelContext) -> TurnLabeling:
    """The labeling ``psi_rad + k 90 deg`` scored on the site; ``lens``: the along and
    across families' summed ceiling lengths (m). One compiled call
    (:func:`hypothesis_core`: the forward offsets, their edge compatibility, the lamp
    anchors of the across family, :func:`.association.match_offsets`)."""
    setup = ctx.setup
    pk = wrap_pi(psi_rad + k * np.pi / 2)
    fa, fb = (along, across) if k % 2 == 0 else (across, along)
    len_a, len_b = lens if k % 2 == 0 else lens[::-1]
    prior_shift = None
    if prior is not None and prior.y_m is not None:
        t_v = rot_z(wrap_pi(pk - setup.pan_rad)) @ setup.t_vc
        prior_shift = prior.y_m + float(t_v[1])
    assign = np.empty(np.count_nonzero(fa), np.int64)
    query = MatchQuery(float(ctx.match_tol_m), prior_shift is not None,
                       0.0 if prior_shift is None else float(prior_shift))
    offs, wa, compat, res = hypothesis_core(ctx.kernel_setup, fr.arrays, arr(fa, np.bool_),
                                            arr(fb, np.bool_), pk, query, assign)
    return TurnLabeling(k, pk, fa, fb, offset_match(res, assign), offs, wa, compat, len_a, len_b)


@njit
def hypothesis_core(ks, la, fa, fb, psi, query, assign):  # pragma: no cover - compiled
    """:func:`hypothesis`' arrays and match at camera pan ``psi`` (``ks``: a
    :class:`SiteKernel`, ``la``: the frame's :class:`~.frame.LineArrays`): the forward
    segments' (``fa``) offsets (:func:`.geometry.along_offsets`), weights (pixel length)
    and compatibility (:func:`.association.compat_core` of their polarity in W), the
    across family's (``fb``) lamp anchors and :func:`.association.match_core` of them
    (``query``: a :class:`~.association.MatchQuery`) into ``assign``: ``(offsets,
    weights, compat, match tuple)``."""
    q, pol, len_n, ceil_len = la.q, la.pol, la.len_n, la.ceil_len
    h, f_px = ks.h_m, ks.f_px
    c, s = math.cos(psi), math.sin(psi)
    n_a = assign.size
    offs = np.empty(n_a)
    wa = np.empty(n_a)
    pol_w = np.empty(n_a)
    cl = np.empty(n_a)
    k = 0
    for i in range(fa.size):
        if fa[i]:
            n_y = s * q[i, 0] + c * q[i, 1]
            offs[k] = -q[i, 2] * h / n_y if abs(n_y) > 1e-12 else np.nan
            wa[k] = len_n[i] * f_px
            pol_w[k] = pol[i] * np.sign(n_y)
            cl[k] = ceil_len[i]
            k += 1
    compat = compat_core(pol_w, cl, ks.edge_kind, ks.longest_m)
    anchors = anchors_core(ks.lamp_y_m, la.lamp_end, la.ceil_sx, la.ceil_sy, fb, psi)
    match = match_core(offs, wa, ks.site_y, query, anchors, compat, assign)
    return offs, wa, compat, match


def across_on_grid(h: TurnLabeling, fr: FrameLines, ctx: LabelContext) -> int:
    """How many across segments of ``h`` sit on the ``lines_across`` grid (0 unless
    two or more)."""
    spacing = ctx.setup.across_spacing_m
    if spacing is None or np.count_nonzero(h.fb) < 2:
        return 0
    # across_offsets, then periodic_spread of them, in one loop
    n_b = spread_core(fr.q, arr(h.fb, np.bool_), fr.len_n, float(h.psi_rad),
                      float(ctx.setup.ceiling_above_cam_m), float(spacing),
                      float(ctx.match_tol_m))
    return n_b if n_b >= 2 else 0


@dataclass(frozen=True, eq=False)
class Labeling:
    """A frame's families labeled and associated: the start of the joint refinement.

    Attributes:
        score: ``(lines matched, matched weight)``: compares pan candidates.
        psi_rad, camera_y_m: the camera's pan and y in W.
        along, across: ``(N,)`` bool, the forward and across families.
        assign: ``(N,)`` the site line of each forward segment, -1 for none.
        n_lines: site lines matched. ambiguous: a lateral shift's tie left to the prior.
        how: the rule that chose the forward family (``prior``, ``elongation``,
            ``spacing``, ``paper_rule``, with ``+absence`` when absence settled).
        n_off_ceiling: forward segments the association matched that the pixel
            consensus left out (:mod:`.consensus`: at another height, or not the site's).
        twins: the other labelings the frame supports as well (a half turn, a quarter
            turn of a tile grid), ruled out by the prior or the stated heading.
    """

    score: tuple[int, float]
    psi_rad: float
    camera_y_m: float
    along: np.ndarray
    across: np.ndarray
    assign: np.ndarray
    n_lines: int
    ambiguous: bool
    how: str
    n_off_ceiling: int = 0
    twins: tuple[LabelingTwin, ...] = ()


@dataclass(frozen=True)
class LabelingTwin:
    """A labeling the frame supports as well as the chosen one: the camera's pan and y
    in W, and what makes it a twin (``half_turn``, ``quarter_turn``, ``shift``)."""

    psi_rad: float
    camera_y_m: float
    label: str
    exact: bool = True      # False: not every lateral shift of it the frame fits is listed


@dataclass(frozen=True)
class Unresolved:
    """A pan candidate whose labeling failed: a Failure reason and its detail (and,
    for ``ambiguous``, every labeling the frame supports, the best first)."""

    score: tuple[int, float]
    reason: str
    detail: str
    twins: tuple[LabelingTwin, ...] = ()


def _choose(psi_rad: float, along: np.ndarray, across: np.ndarray,
            lens: tuple[float, float], fr: FrameLines, prior: PoseEstimate | None,
            prior_psi: float | None, ctx: LabelContext
            ) -> tuple[TurnLabeling, str, list[LabelingTwin]]:
    """The forward family's labeling about ``psi_rad``, the rule that chose it and its
    rivals: the labelings the frame supports as well (``lens``: the families' summed
    ceiling lengths). Nothing the frame cannot check decides between a labeling and
    its rivals: the half turn is always examined (a corridor symmetric about its
    centre line looks the same driven either way), the quarter turn where the site's
    ``lines_across`` are seams (a tile grid); the prior, or the user's stated heading
    (``assume_heading_rad``), then chooses."""
    la, lb = lens
    cache: dict[int, TurnLabeling] = {}

    def hyp(k: int) -> TurnLabeling:
        k %= 4
        if k not in cache:
            cache[k] = hypothesis(k, psi_rad, along, across, fr, (la, lb), prior, ctx)
        return cache[k]

    grid = _per_labeling(lambda h: across_on_grid(h, fr, ctx))
    sup = _per_labeling(lambda h: _support(h, grid, ctx))

    if prior_psi is not None:
        k = min(range(4), key=lambda k: abs(wrap_pi(psi_rad + k * np.pi / 2 - prior_psi)))
        chosen = hyp(k)
        rivals, better = _rivals(chosen, hyp, sup, ctx)
        # the prior chooses only a heading inside its region (estimators/prior.py);
        # else (a kidnap, a wrong start pose; or the frame prefers a turn of the
        # prior's labeling: an asymmetric cue) the frame alone decides below
        yaw = wrap_pi(chosen.psi_rad - ctx.setup.pan_rad)
        if better is None and allows(prior, (None, None, yaw, None)):
            return chosen, "prior", rivals
    # of psi + k 90 deg, two share a heading window of 180 deg (k and k + 2 are a half
    # turn apart): the frame's evidence chooses the family (its ceiling length, the
    # across grid), then the half turn is compared, never assumed
    centre = ctx.setup.pan_rad + (ctx.assume_heading_rad or 0.0)
    ks = [k for k in range(4)
          if -np.pi / 2 < wrap_pi(psi_rad + k * np.pi / 2 - centre) <= np.pi / 2]
    ks.sort(key=lambda k: -(la if k % 2 == 0 else lb))
    first = hyp(ks[0])
    if len(ks) < 2 or first.len_a >= DECISIVE * first.len_b:
        chosen, how = first, "elongation"
    else:
        cands = [first, hyp(ks[1])]

        def frame_score(h: TurnLabeling) -> tuple:
            return (h.n_a + min(grid(h), 2), h.elong)

        cands.sort(key=frame_score, reverse=True)
        chosen, how = cands[0], "spacing"
        if frame_score(cands[1])[0] == frame_score(chosen)[0]:
            how = "elongation"
            if abs(cands[1].elong - chosen.elong) < 1e-6:
                # no evidence between the families: a tile grid's quarter turn (a
                # rival below where the site's across lines are seams)
                chosen = min(cands, key=lambda h: abs(wrap_pi(h.psi_rad - centre)))
                how = "nearest"
    rivals, better = _rivals(chosen, hyp, sup, ctx)
    if better is not None:      # the frame prefers a turn: it is taken, a statement or not
        chosen, how = better, how + "+turn"
        rivals, _ = _rivals(chosen, hyp, sup, ctx)
    if how.startswith("nearest") and not ctx.across_seams:
        # the families tie on everything the frame shows: the other one is a quarter
        # turn the frame does not rule out (a tile grid's are among the rivals already)
        other = hyp(chosen.k + 1) if hyp(chosen.k + 1) in cands else hyp(chosen.k + 3)
        if other.match is not None and other.match.n_lines >= 1:
            rivals += labeling_twins(other, "quarter_turn", ctx)
    if ctx.assume_heading_rad is not None and rivals:
        # the user's statement, not the frame, rules out the rivals beyond 90 deg of it
        kept = [t for t in rivals if abs(wrap_pi(t.psi_rad - centre)) < np.pi / 2 - 1e-9]
        if len(kept) < len(rivals):
            rivals, how = kept, how + "+stated"
    return chosen, how, rivals


def _per_labeling(fn: Callable[[TurnLabeling], float]) -> Callable[[TurnLabeling], float]:
    """``fn`` computed once per labeling (its quarter turns ``k``) of one pan candidate."""
    memo: dict[int, float] = {}

    def get(h: TurnLabeling) -> float:
        if h.k not in memo:
            memo[h.k] = fn(h)
        return memo[h.k]

    return get


TWIN_RATIO = 0.85
"""A labeling whose support is at least this share of the chosen one's is its rival
(the 1-D association's :data:`~.association.AMBIGUITY_RATIO`)."""


def _support(h: TurnLabeling, grid, ctx: LabelContext) -> float:
    """How well labeling ``h`` explains the frame: its association's score (about the
    site lines matched, discounted by misfit), less :data:`~.association.ABSENCE_PENALTY`
    per site line it puts clearly in view that no forward segment lies on; where the
    site's ``lines_across`` are seams, its across family off their grid counts against
    it (``grid(h)``: :func:`across_on_grid` of ``h``, computed once per labeling). 0
    when it matches fewer than two segments."""
    m = h.match
    if m is None or m.n_lines < 1 or np.count_nonzero(m.assign >= 0) < 2:
        return 0.0
    score = m.score - ABSENCE_PENALTY * _missing(h, m.shift_m, ctx)
    if ctx.across_seams and ctx.setup.across_spacing_m is not None:
        score += 0.5 * min(grid(h), 2)
    return max(score, 0.0)


def _missing(h: TurnLabeling, shift_m: float, ctx: LabelContext) -> int:
    """Site lines the labeling ``h`` at camera y ``shift_m`` puts clearly in view that
    no forward segment of a fitting kind lies on."""
    st = ctx.setup
    view = lines_in_view(st, ctx.camera, ctx.min_length_px, h.psi_rad, (shift_m,))[0]
    return int(unseen_core(arr(h.offsets_m, np.float64), arr(h.compat, np.float64),
                           ctx.kernel_setup.site_y, float(shift_m), float(ctx.match_tol_m),
                           view))


def _rivals(chosen: TurnLabeling, hyp, sup, ctx: LabelContext
            ) -> tuple[list[LabelingTwin], TurnLabeling | None]:
    """The labelings that explain the frame as well as ``chosen`` (support ``sup``,
    :func:`_support`, at least :data:`TWIN_RATIO` of its): its half turn, and its quarter
    turns where the site's ``lines_across`` are seams; and the one the frame prefers
    (support above the chosen's over the ratio), or None. On a site symmetric about a
    centre line (``mirror_y_m``) the half turn is a twin by that symmetry, its camera y
    mirrored (:func:`label` mirrors the lateral shift it settles on), never preferred,
    with nothing to compute; elsewhere a turn whose association alone scores below the
    ratio is out before its absent lines are counted."""
    if chosen.match is None:
        return [], None
    turns = [(2, "half_turn")]
    if ctx.across_seams:
        turns += [(1, "quarter_turn"), (3, "quarter_turn")]
    out, better, own = [], None, None
    for dk, lbl in turns:
        if dk == 2 and ctx.mirror_y_m is not None:
            out.append(LabelingTwin(wrap_pi(chosen.psi_rad + np.pi),
                            2.0 * ctx.mirror_y_m - chosen.match.shift_m, lbl, MIRRORED))
            continue
        h = hyp(chosen.k + dk)
        if h.match is None or h.match.n_lines < 1:
            continue
        if dk != 2 and ctx.square_grid:
            # a square grid is its own quarter turn: the turned labeling explains the
            # frame as well whatever the two families' counts (the frame's aspect
            # shows more lines of one), unless site lines it puts in view are missing
            if h.match.n_lines >= 2 and sup(h) >= TWIN_RATIO * h.match.score:
                out += labeling_twins(h, lbl, ctx)
            continue
        own = sup(chosen) if own is None else own
        bound = h.match.score + (1.0 if ctx.across_seams else 0.0)
        if own > 0.0 and bound < TWIN_RATIO * own:
            continue
        theirs = sup(h)
        if own <= 0.0 and theirs <= 0.0:
            continue
        # only the half turn can be preferred: it labels the same segments, so its
        # support is comparable; a quarter turn's counts another family's lines, more
        # or fewer by the frame's aspect alone (a square grid): a rival at most
        if dk == 2 and theirs > own / TWIN_RATIO:
            better = h
        elif theirs >= TWIN_RATIO * own or (dk != 2 and theirs > own):
            out += labeling_twins(h, lbl, ctx)
    return out, better


def alike_shifts(m: OffsetMatch, h: TurnLabeling, ctx: LabelContext) -> tuple[float, ...]:
    """The lateral shifts other than ``m``'s that labeling ``h``'s forward lines fit as
    well (:func:`~.association.shifts_alike`), or its runner-up when absence leaves
    none of them but called the match ambiguous (:func:`settle_by_absence` compares
    the two alone)."""
    out = shifts_alike(m, h.offsets_m, h.compat, h.psi_rad, ctx.setup, ctx.camera,
                       ctx.min_length_px, ctx.match_tol_m)
    return out or ((m.runner_up[2],) if m.runner_up is not None else ())


def labeling_twins(h: TurnLabeling, lbl: str, ctx: LabelContext) -> list[LabelingTwin]:
    """The twins a rival labeling ``h`` makes: its shift and, when another fits as well
    (a tile grid turned a quarter), every such shift: each a pose the frame supports,
    so the list is complete (``exact``)."""
    m = h.match
    shifts = (m.shift_m,) + (alike_shifts(m, h, ctx) if is_ambiguous(m) else ())
    return [LabelingTwin(h.psi_rad, c, lbl) for c in shifts]


MIRRORED = True
"""A mirrored twin's shift is exact once :func:`label` mirrors the settled one."""


def best_labeling(pans: list[float], fr: FrameLines, prior: PoseEstimate | None,
                  ctx: LabelContext) -> Labeling | Unresolved | None:
    """The best-scoring labeling (:func:`label`) over the pan candidates ``pans``
    (with a prior, the one nearest it first, mod 90 deg); the first that matches two
    site lines wins."""
    prior_psi = None if prior is None else prior.yaw_rad + ctx.setup.pan_rad
    if prior_psi is not None:
        pans = sorted(pans, key=lambda p: abs(math.remainder(p - prior_psi, np.pi / 2)))
    best = None
    for psi0 in pans:
        cand = label(psi0, fr, prior, prior_psi, ctx)
        if cand is None:
            continue
        if best is None or cand.score > best.score:
            best = cand
        if isinstance(best, Labeling) and best.n_lines >= 2:
            break
    return best


def label(psi0_rad: float, fr: FrameLines, prior: PoseEstimate | None,
          prior_psi: float | None, ctx: LabelContext) -> Labeling | Unresolved | None:
    """The families about pan candidate ``psi0_rad``, the forward one and the lateral
    shift; None when fewer than two segments belong to the families."""
    setup = ctx.setup
    n = fr.len_n.size
    along, across = np.empty(n, np.bool_), np.empty(n, np.bool_)
    ok, psi, la, lb = families_core(fr.arrays, ctx.kernel_setup, float(psi0_rad),
                                    float(ctx.angle_tol_rad), along, across)
    if not ok:
        return None
    chosen, how, rivals = _choose(psi, along, across, (la, lb), fr, prior, prior_psi, ctx)
    m = chosen.match
    if m is None or m.n_lines < 1 or np.count_nonzero(m.assign >= 0) < 2:
        return Unresolved((-1, 0.0), "no_association",
                          "the forward lines do not match the site's lines_along")
    ambiguous = is_ambiguous(m)
    alike: tuple[float, ...] = ()
    if ambiguous:
        settled, ambiguous = settle_by_absence(m, chosen.offsets_m, chosen.weights,
                                               chosen.compat, chosen.psi_rad, setup,
                                               ctx.camera, ctx.min_length_px, ctx.match_tol_m)
        alike = alike_shifts(settled, chosen, ctx) if ambiguous else ()
        if prior is not None and prior.y_m is not None and settled is m and ambiguous \
                and not _prior_single_shift(m, alike, chosen, prior, ctx):
            return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                              f"{m.n_lines} forward lines fit {len(alike) + 1} lateral "
                              f"positions ({m.shift_m:+.3f} m, {alike[0]:+.3f} m, ...) and "
                              "the prior does not single one out",
                              (LabelingTwin(chosen.psi_rad, m.shift_m, "chosen"),)
                              + _shift_twins(chosen.psi_rad, alike, rivals, ctx)
                              + tuple(rivals))
        if settled is not m and prior is not None and prior.y_m is not None:
            # the prior chose m (the shift nearest it); the lines the frame misses
            # choose the runner-up: neither is trusted (a flip away from a good prior
            # published a lateral three seams off, at a sigma of 0.4 mm: a wall's
            # clutter imitating seams, docs/methods/corridor.md), unless the prior's
            # region holds m and none of the others (the vehicle cannot be there)
            others = _other_shifts(m.shift_m, (settled.shift_m,) + alike, ctx)
            if not _prior_single_shift(m, others, chosen, prior, ctx):
                return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                                  f"the prior's lateral shift ({m.shift_m:+.3f} m) and the "
                                  f"frame's ({settled.shift_m:+.3f} m: fewer site lines "
                                  "missing) disagree", _disagreeing(m, settled, alike,
                                                                    chosen, rivals, ctx))
            settled, ambiguous, alike = m, True, others
        m = settled
        if not ambiguous and how != "prior":
            how += "+absence"
    if ctx.mirror_y_m is not None:     # mirror the lateral shift the frame settled on
        rivals = [LabelingTwin(t.psi_rad, 2.0 * ctx.mirror_y_m - m.shift_m, t.label, t.exact)
                  if t.label == "half_turn" else t for t in rivals]
    twins = tuple(rivals)
    if ambiguous:
        twins += _shift_twins(chosen.psi_rad, alike, rivals, ctx)
    if ambiguous and (prior is None or prior.y_m is None):
        return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                          f"{m.n_lines} forward lines fit {len(alike) + 1} lateral "
                          f"positions ({m.shift_m:+.3f} m, {alike[0]:+.3f} m, ...); no "
                          "prior to choose",
                          (LabelingTwin(chosen.psi_rad, m.shift_m, "chosen"),) + twins)
    if rivals and how != "prior":
        kinds = " and ".join(sorted({t.label.replace("_", " ") for t in rivals}))
        return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                          f"the lines fit {len(rivals) + 1} headings equally well (a "
                          f"{kinds}: the ceiling looks the same); no prior to choose",
                          (LabelingTwin(chosen.psi_rad, m.shift_m, "chosen"),) + twins)
    assign = np.full(fr.q.shape[0], -1)
    assign[np.flatnonzero(chosen.fa)] = m.assign
    return Labeling((m.n_lines, m.weight), chosen.psi_rad, m.shift_m, chosen.fa, chosen.fb,
                    assign, m.n_lines, ambiguous, how, twins=twins)


def _shift_twins(psi_rad: float, alike: tuple[float, ...], rivals: list[LabelingTwin],
                 ctx: LabelContext) -> tuple[LabelingTwin, ...]:
    """The twins of the other lateral shifts ``alike`` (camera y, m) at pan ``psi_rad``,
    and, on a site symmetric about a centre line whose half turn is among ``rivals``,
    each one's mirror (the half turn of every shift the frame fits)."""
    out = tuple(LabelingTwin(psi_rad, c, "shift") for c in alike)
    if ctx.mirror_y_m is not None and any(t.label == "half_turn" for t in rivals):
        out += tuple(LabelingTwin(wrap_pi(psi_rad + np.pi), 2.0 * ctx.mirror_y_m - c, "half_turn")
                     for c in alike)
    return out


def _disagreeing(m: OffsetMatch, settled: OffsetMatch, alike: tuple[float, ...],
                 chosen: TurnLabeling, rivals: list[LabelingTwin], ctx: LabelContext
                 ) -> tuple[LabelingTwin, ...]:
    """Every pose of a frame whose missing lines chose ``settled`` against the prior's
    ``m``: both shifts, the others alike (``alike``, of ``settled``) and the rival
    turns; a track then sees whether any lies where it expects the vehicle (a kidnap
    shows none)."""
    shifts = (settled.shift_m,) + _other_shifts(settled.shift_m, alike + (m.shift_m,), ctx)
    return ((LabelingTwin(chosen.psi_rad, shifts[0], "chosen"),)
            + _shift_twins(chosen.psi_rad, shifts[1:], rivals, ctx) + tuple(rivals))


def _other_shifts(first: float, shifts: tuple[float, ...], ctx: LabelContext
                  ) -> tuple[float, ...]:
    """Those of ``shifts`` (camera y, m), in order, farther than the association's
    tolerance from ``first`` and from each one kept before."""
    kept = [first]
    for c in shifts:
        if all(abs(c - d) > ctx.match_tol_m for d in kept):
            kept.append(c)
    return tuple(kept[1:])


def _prior_single_shift(m: OffsetMatch, alike: tuple[float, ...], chosen: TurnLabeling,
                        prior: PoseEstimate, ctx: LabelContext) -> bool:
    """Whether the prior allows the lateral shift it chose (``m``, the nearest it) and
    none of the others the frame fits as well (``alike``: :func:`alike_shifts`; on a
    tile grid the best scoring other can lie beyond the prior while a shift a period
    nearer fits as well; the runner-up and ``m.prior_rival_m`` are among them)
    (:func:`~ceilkit.runtime.estimators.prior.prior_choice` over the vehicle's y of
    each)."""
    yaw = wrap_pi(chosen.psi_rad - ctx.setup.pan_rad)
    off = float((rot_z(yaw) @ ctx.setup.t_vc)[1])     # the shift is the camera's
    shifts = [m.shift_m, *alike, m.runner_up[2]] + ([] if m.prior_rival_m is None
                                                    else [m.prior_rival_m])
    return prior_choice(prior, [(None, c - off, yaw, None) for c in shifts]) == 0


@njit
def families_core(la, ks, psi0, angle_tol, along, across):  # pragma: no cover - compiled
    """:func:`label`'s families of the frame's :class:`~.frame.LineArrays` ``la`` (``ks``:
    the :class:`SiteKernel`): :func:`families` about ``psi0`` within ``angle_tol``,
    one reweighted :func:`.geometry.fit_pan` over both families (weights length^2 /
    den^2, Huber at 1 px, on the branch mod pi nearest ``psi0``), :func:`families`
    again within ``tol (N,)``, written to ``along``
    and ``across (N,)``: ``(ok, psi, along length, across length)`` (ok False when
    either pass leaves fewer than two segments in the families; the lengths are the
    summed ``ceil_len``)."""
    R, f_px = ks.R_level_cam, ks.f_px
    lines_t, mx, my, len_n, q, tol, ceil_len = la.lines_t, la.mx, la.my, la.len_n, la.q, \
        la.tol, la.ceil_len
    n = len_n.size
    ang = np.empty((2, n))
    den = np.empty((2, n))
    angles_core(psi0, R, lines_t, mx, my, ang, den)
    if _families(ang, np.full(n, angle_tol), along, across) < 2:
        return False, psi0, 0.0, 0.0
    w_a = np.zeros(n)
    w_b = np.zeros(n)
    for i in range(n):
        r = 0 if along[i] else 1
        ri = ang[r, i] * len_n[i] * f_px
        x = len_n[i] / den[r, i]
        wi = (x * x) * min(1.0, 1.0 / max(ri, 1e-9))
        if along[i]:
            w_a[i] = wi
        if across[i]:
            w_b[i] = wi
    sxx = syy = sxy = 0.0
    for i in range(n):
        q00, q11, q01 = q[i, 0] * q[i, 0], q[i, 1] * q[i, 1], q[i, 0] * q[i, 1]
        sxx += w_a[i] * q00 + w_b[i] * q11
        syy += w_a[i] * q11 + w_b[i] * q00
        sxy += (w_b[i] - w_a[i]) * q01
    th = 0.5 * math.atan2(2.0 * sxy, sxx - syy) + 0.5 * math.pi
    new = th if th < math.pi else th - 2 * math.pi
    psi = new + np.pi * np.rint((psi0 - new) / np.pi)
    angles_core(psi, R, lines_t, mx, my, ang, den)
    if _families(ang, tol, along, across) < 2:
        return False, psi, 0.0, 0.0
    buf = np.empty(n)
    lens = np.empty(2)
    for f in range(2):
        k = 0
        for i in range(n):
            if along[i] if f == 0 else across[i]:
                buf[k] = ceil_len[i]
                k += 1
        lens[f] = pairwise_sum(buf, k)
    return True, psi, lens[0], lens[1]


@njit
def angles_core(psi, R, lines_t, mx, my, ang, den):  # pragma: no cover - compiled
    """:func:`.geometry.vanishing_angles` into ``ang, den (2, N)``."""
    c, s = math.cos(psi), math.sin(psi)
    for r in range(2):
        v0 = c * R[0, 0] - s * R[1, 0] if r == 0 else s * R[0, 0] + c * R[1, 0]
        v1 = c * R[0, 1] - s * R[1, 1] if r == 0 else s * R[0, 1] + c * R[1, 1]
        v2 = c * R[0, 2] - s * R[1, 2] if r == 0 else s * R[0, 2] + c * R[1, 2]
        for i in range(mx.size):
            d = max(math.hypot(v0 - v2 * mx[i], v1 - v2 * my[i]), 1e-12)
            den[r, i] = d
            ang[r, i] = abs(v0 * lines_t[0, i] + v1 * lines_t[1, i] + v2 * lines_t[2, i]) / d


@njit
def _families(ang, tol, along, across):  # pragma: no cover - compiled
    """:func:`families` into ``along, across``; how many segments they hold."""
    n = 0
    for i in range(tol.size):
        along[i] = ang[0, i] <= ang[1, i] and ang[0, i] <= tol[i]
        across[i] = ang[1, i] < ang[0, i] and ang[1, i] <= tol[i]
        n += along[i] + across[i]
    return n


@warmer
def _warm() -> None:
    f, b = np.float64, np.bool_
    one, on = arr(np.ones(2), f), arr(np.ones(2, bool), b)
    q = arr(np.array([[0.0, 1.0, 0.1], [1.0, 0.0, 0.1]]), f)
    pans_core(q, one, 3, _KERNEL)
    along, across = np.empty(2, bool), np.empty(2, bool)
    la = LineArrays(arr(np.ones((3, 2)), f), one, one, one, q, one, one, one, one,
                    arr(np.ones((2, 2), bool), b), one)
    ks = SiteKernel(one, one, one, one, 2.0, 400.0, arr(np.eye(3), f))
    families_core(la, ks, 0.0, 0.1, along, across)
    hypothesis_core(ks, la, on, on, 0.0, MatchQuery(0.1, True, 0.0), np.empty(2, np.int64))
