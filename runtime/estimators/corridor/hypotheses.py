"""Which lines are the families and which family is forward: pan candidates, the
family gate, and the labelings ``psi + k 90 deg`` scored on the site.

A frame's candidates (:func:`dominant_pans`) are the modes of its segments'
horizontal directions mod 90 deg; :func:`label` takes one to the families about it,
refines the pan (:func:`refine_pan`), picks the forward family (with a prior, the
labeling nearest it; without, the yaw range, the ceiling lengths, the site, and the
paper's ``|pan| <= 45 deg`` rule, in that order) and associates its lines with the
site's (:mod:`.association`). It returns a :class:`Labeling` or an
:class:`Unresolved` reason.

Example::

    for psi0 in dominant_pans(fr.q, weights):
        result = label(psi0, fr, prior, prior_psi, ctx)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.estimators.base import AMBIGUOUS, PoseEstimate
from ceilkit.runtime.estimators.corridor.association import (
    OffsetMatch,
    edge_compat,
    is_ambiguous,
    lamp_anchors,
    match_offsets,
    periodic_spread,
    settle_by_absence,
)
from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import (
    across_offsets,
    along_offsets,
    fit_pan,
    vanishing_angles,
)
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import rot_z, wrap_pi

DECISIVE = 2.0
"""Forward / across ceiling length ratio that settles which family is forward."""

PAN_BINS = 720
"""Bins of the histogram of horizontal directions mod 90 deg (0.125 deg each)."""

_KERNEL = np.exp(-0.5 * (np.arange(-16, 17) / 4.0) ** 2)


@dataclass(frozen=True)
class LabelContext:
    """What :func:`label` needs beyond the frame: the setup, the camera, the gates.

    Attributes:
        setup: the rig on the site. camera: its camera model.
        angle_tol_rad: family gate about a vanishing point (first pass).
        match_tol_m: 1-D association gate. min_length_px: the detector's shortest.
    """

    setup: CorridorSetup
    camera: CameraModel
    angle_tol_rad: float
    match_tol_m: float
    min_length_px: float


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


def families(ang: np.ndarray, tol: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """``(along, across)`` ``(N,)`` bool: the nearer vanishing point of ``ang``
    ``(2, N)`` (:func:`.geometry.vanishing_angles`), within ``tol`` (rad, scalar or
    ``(N,)``)."""
    along = (ang[0] <= ang[1]) & (ang[0] <= tol)
    across = (ang[1] < ang[0]) & (ang[1] <= tol)
    return along, across


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


@dataclass(frozen=True, eq=False)
class Hypothesis:
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
               ctx: LabelContext) -> Hypothesis:
    """The labeling ``psi_rad + k 90 deg`` scored on the site; ``lens``: the along and
    across families' summed ceiling lengths (m)."""
    setup = ctx.setup
    pk = wrap_pi(psi_rad + k * np.pi / 2)
    fa, fb = (along, across) if k % 2 == 0 else (across, along)
    len_a, len_b = lens if k % 2 == 0 else lens[::-1]
    wa = fr.len_n[fa] * setup.f_px
    prior_shift = None
    if prior is not None and prior.y_m is not None:
        t_v = rot_z(wrap_pi(pk - setup.pan_rad)) @ setup.t_vc
        prior_shift = prior.y_m + float(t_v[1])
    offs, n_y = along_offsets(fr.q[fa], pk, setup.ceiling_above_cam_m)
    pol_w = fr.pol[fa] * np.sign(n_y)
    compat = edge_compat(pol_w, fr.ceil_len[fa], setup)
    anchors = lamp_anchors(setup, fr.lamp_end, fr.ceil_sx, fr.ceil_sy, fb, pk)
    m = match_offsets(offs, wa, setup.site_y, ctx.match_tol_m, prior_shift, anchors, compat)
    return Hypothesis(k, pk, fa, fb, m, offs, wa, compat, len_a, len_b)


def across_on_grid(h: Hypothesis, fr: FrameLines, ctx: LabelContext) -> int:
    """How many across segments of ``h`` sit on the ``lines_across`` grid (0 unless
    two or more)."""
    spacing = ctx.setup.across_spacing_m
    if spacing is None or np.count_nonzero(h.fb) < 2:
        return 0
    offs = across_offsets(fr.q[h.fb], h.psi_rad, ctx.setup.ceiling_above_cam_m)
    n_b, _ = periodic_spread(offs, fr.len_n[h.fb], spacing, ctx.match_tol_m)
    return n_b if n_b >= 2 else 0


@dataclass(frozen=True, eq=False)
class Labeling:
    """A frame's families labeled and associated: the start of the joint refinement.

    Attributes:
        score: ``(lines matched, matched weight)``: compares pan candidates.
        psi_rad, camera_y_m: the camera's pan and y in W.
        along, across: ``(N,)`` bool, the forward and across families.
        assign: ``(N,)`` the site line of each forward segment, -1 for none.
        n_lines: site lines matched. ambiguous: a tie left to the prior.
        how: the rule that chose the forward family (``prior``, ``elongation``,
            ``spacing``, ``paper_rule``, with ``+absence`` when absence settled).
        n_off_ceiling: forward segments the association matched that the pixel
            consensus left out (:mod:`.consensus`: at another height, or not the site's).
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


@dataclass(frozen=True)
class Unresolved:
    """A pan candidate whose labeling failed: a Failure reason and its detail."""

    score: tuple[int, float]
    reason: str
    detail: str


def _choose(psi_rad: float, along: np.ndarray, across: np.ndarray, fr: FrameLines,
            prior: PoseEstimate | None, prior_psi: float | None,
            ctx: LabelContext) -> tuple[Hypothesis, str]:
    """The forward family's labeling about ``psi_rad`` and the rule that chose it."""
    la, lb = float(fr.ceil_len[along].sum()), float(fr.ceil_len[across].sum())

    def hyp(k: int) -> Hypothesis:
        return hypothesis(k, psi_rad, along, across, fr, (la, lb), prior, ctx)

    if prior_psi is not None:
        k = min(range(4), key=lambda k: abs(wrap_pi(psi_rad + k * np.pi / 2 - prior_psi)))
        return hyp(k), "prior"
    # of psi + k 90 deg, two keep yaw in (-90, 90] (k and k + 2 are a half turn
    # apart); the one whose forward family is longer on the ceiling first
    pan = ctx.setup.pan_rad
    ks = [k for k in range(4) if -np.pi / 2 < wrap_pi(psi_rad + k * np.pi / 2 - pan) <= np.pi / 2]
    ks.sort(key=lambda k: -(la if k % 2 == 0 else lb))
    first = hyp(ks[0])
    if len(ks) < 2 or first.len_a >= DECISIVE * first.len_b:
        return first, "elongation"
    cands = [first, hyp(ks[1])]

    def frame_score(h: Hypothesis) -> tuple:
        return (h.n_a + min(across_on_grid(h, fr, ctx), 2), h.elong)

    cands.sort(key=frame_score, reverse=True)
    chosen, how = cands[0], "spacing"
    if frame_score(cands[1])[0] == frame_score(chosen)[0]:
        how = "elongation"
        if abs(cands[1].elong - chosen.elong) < 1e-6:
            # no evidence at all: the paper's rule, |pan| <= 45 deg
            chosen = min(cands, key=lambda h: abs(h.psi_rad))
            how = "paper_rule"
    return chosen, how


def label(psi0_rad: float, fr: FrameLines, prior: PoseEstimate | None,
          prior_psi: float | None, ctx: LabelContext) -> Labeling | Unresolved | None:
    """The families about pan candidate ``psi0_rad``, the forward one and the lateral
    shift; None when fewer than two segments belong to the families."""
    setup = ctx.setup
    ang, den = vanishing_angles(psi0_rad, setup.R_rows, fr.lines_t, fr.mx, fr.my)
    along, across = families(ang, ctx.angle_tol_rad)
    if np.count_nonzero(along) + np.count_nonzero(across) < 2:
        return None
    psi = refine_pan(psi0_rad, fr, along, across, ang, den, setup.f_px)
    along, across = families(vanishing_angles(psi, setup.R_rows, fr.lines_t, fr.mx,
                                              fr.my)[0], fr.tol)
    if np.count_nonzero(along) + np.count_nonzero(across) < 2:
        return None
    chosen, how = _choose(psi, along, across, fr, prior, prior_psi, ctx)
    m = chosen.match
    if m is None or m.n_lines < 1 or np.count_nonzero(m.assign >= 0) < 2:
        return Unresolved((-1, 0.0), "no_association",
                          "the forward lines do not match the site's lines_along")
    ambiguous = is_ambiguous(m)
    if ambiguous:
        settled, ambiguous = settle_by_absence(m, chosen.offsets_m, chosen.weights,
                                               chosen.compat, chosen.psi_rad, setup,
                                               ctx.camera, ctx.min_length_px, ctx.match_tol_m)
        if settled is not m and prior is not None and prior.y_m is not None:
            # the prior chose m (the shift nearest it); the lines the frame misses
            # choose the runner-up: neither is trusted (a flip away from a good prior
            # published a lateral three seams off, at a sigma of 0.4 mm: a wall's
            # clutter imitating seams, docs/methods/corridor.md)
            return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                              f"the prior's lateral shift ({m.shift_m:+.3f} m) and the "
                              f"frame's ({settled.shift_m:+.3f} m: fewer site lines "
                              "missing) disagree")
        m = settled
        if not ambiguous and how != "prior":
            how += "+absence"
    if ambiguous and (prior is None or prior.y_m is None):
        return Unresolved((m.n_lines, m.weight), AMBIGUOUS,
                          f"{m.n_lines} forward lines fit two lateral positions "
                          f"({m.shift_m:+.3f} m and {m.runner_up[2]:+.3f} m); no prior to choose")
    assign = np.full(fr.q.shape[0], -1)
    assign[np.flatnonzero(chosen.fa)] = m.assign
    return Labeling((m.n_lines, m.weight), chosen.psi_rad, m.shift_m, chosen.fa, chosen.fb,
                    assign, m.n_lines, ambiguous, how)
