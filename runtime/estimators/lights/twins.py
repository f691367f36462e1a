"""The twins of a lights pose: the light map's own symmetries applied to a frame's poses.

A regular grid looks the same from every cell and under a half (or quarter) turn; a
pose the matcher finds has a twin for each symmetry of the map that keeps enough of its
matched lights on lights (:func:`~.matching.map_symmetries`, found once per map).
:class:`TwinJudge` moves a pose by them, verifies the moved poses against the frame
(:meth:`~.matching.PatternMatcher.twins`) and scores every candidate by the same
evidence, so that the estimator can say whether the frame singles one out
(docs/methods/lights.md, docs/methods/honesty.md).

Example::

    judge = TwinJudge(lights_w, matcher, extent, options)
    twins, complete = judge.twins(obs, best)
    ambiguous = any(judge.evidence(t, w) >= judge.evidence(best, w) - margin for t in twins)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import Hypothesis
from ceilkit.runtime.estimators.honesty import SiteExtent
from ceilkit.runtime.estimators.lights.matching import (
    MISSING_PENALTY,
    SYMMETRY_MAX_LIGHTS,
    Candidate,
    PatternMatcher,
    map_symmetries,
    symmetry_table,
    twin_poses,
)
from ceilkit.runtime.estimators.lights.observe import Observation
from ceilkit.runtime.geometry.rotations import wrap_pi

MAX_TWIN_CHECKS = 1000  # at most this many of the map's symmetries are verified per frame
MAX_HYPOTHESES = 32  # an ambiguous frame carries at most this many poses
HYPOTHESIS_SHARPNESS = 2.0  # a hypothesis' weight goes as exp(this x its evidence score)


class TwinJudge:
    """The map's symmetries and the evidence that tells a pose from its twins.

    Args:
        lights_w: ``(N, 2)`` the map's lights in W (m).
        matcher: the estimator's :class:`~.matching.PatternMatcher`.
        extent: the site's extent (a pose outside it is not possible).
        options: the estimator's options (``twins``, ``gate_m``, ``min_inliers``,
            ``site_margin_m``).
    """

    def __init__(self, lights_w: np.ndarray, matcher: PatternMatcher, extent: SiteExtent,
                 options: Any) -> None:
        o = options
        self.matcher, self.extent, self.options = matcher, extent, o
        sym = (map_symmetries(lights_w, o.gate_m, o.min_inliers) if o.twins
               else np.zeros((0, 3)))
        self.searched = bool(o.twins and lights_w.shape[0] <= SYMMETRY_MAX_LIGHTS)
        # nearest first: beyond MAX_TWIN_CHECKS that apply to a pose the far ones go
        # unchecked, and no global fix is then singled out (the estimator's _candidate)
        self.symmetries = sym[np.argsort(np.hypot(sym[:, 1], sym[:, 2]), kind="stable")]
        self.lights = symmetry_table(lights_w, self.symmetries, o.gate_m)

    def possible(self, c: Candidate) -> bool:
        """Whether a candidate may be the pose: ``min_inliers`` spots, inside the site
        (by ``site_margin_m``: the model check refuses a pose outside)."""
        e, m = self.extent, self.options.site_margin_m
        return (c.inliers >= self.options.min_inliers
                and e.x_lo - m <= c.x_m <= e.x_hi + m and e.y_lo - m <= c.y_m <= e.y_hi + m)

    def rivals(self, obs: Observation, c: Candidate) -> tuple[list[Candidate], bool]:
        """The possible twins of ``c`` (:meth:`twins`, :meth:`possible`), ``c``'s own
        pose left out, and whether every twin was checked."""
        found, complete = self.twins(obs, c)
        return [t for t in distinct([c] + found) if self.possible(t)
                and not t.same_pose(c, 0.3, math.radians(5.0))], complete

    @staticmethod
    def evidence(c: Candidate, weights: np.ndarray) -> float:
        """A candidate's score with each spot at its weight (:meth:`Observation.weights`):
        the weighted spots it explains less :data:`~.matching.MISSING_PENALTY` per map
        light it should show that matched nothing."""
        return float(weights[c.pairs[:, 0]].sum()) - MISSING_PENALTY * c.missing

    def twins(self, obs: Observation, best: Candidate) -> tuple[list[Candidate], bool]:
        """The best pose moved by each of the map's symmetries (on a regular grid the
        other cells and the turned placements, which a vote over pair lengths may leave
        unverified) that keeps at least ``min_inliers`` of its matched lights on lights,
        verified (:meth:`PatternMatcher.twins`); and whether they were all checked (the
        map was searched for symmetries, and at most :data:`MAX_TWIN_CHECKS` apply)."""
        if self.symmetries.shape[0] == 0:
            return [], self.searched
        kept = self.lights[:, best.pairs[:, 1]].sum(axis=1)
        # a twin explains at most the best's spots it keeps on lights and the spots the
        # best leaves unexplained: one that cannot come within the margin of the best
        # is no rival, and is not verified (most partial symmetries of an irregular map)
        bound = kept + (len(obs.spots) - best.inliers)
        reach = self.evidence(best, obs.weights()) - self.options.ambiguity_margin
        sym = self.symmetries[(kept >= self.options.min_inliers) & (bound >= reach)]
        complete = self.searched and sym.shape[0] <= MAX_TWIN_CHECKS
        if sym.shape[0] == 0:
            return [], complete
        starts = twin_poses(sym[:MAX_TWIN_CHECKS], best.x_m, best.y_m, best.yaw_rad)
        return self.matcher.twins(obs.q_v, starts, 2.0 * self.options.gate_m,
                                  self.options.min_inliers), complete

    def ranked(self, obs: Observation, cands: list[Candidate], weights: np.ndarray
               ) -> tuple[list[Candidate], bool]:
        """Every placement of the best candidate's spots on the map's lights (its twins,
        with the matcher's ``cands``), distinct, the possible ones ranked by evidence,
        and whether every twin was checked. Empty when only a pose outside the site
        (which its model check would refuse) explains the frame best, by more than
        ``ambiguity_margin``."""
        twins, complete = self.twins(obs, cands[0])
        every = [c for c in distinct(cands + twins) if c.inliers >= self.options.min_inliers]
        ev = [self.evidence(c, weights) for c in every]          # each scored once
        ok = [self.possible(c) for c in every]
        out_e = max((e for e, o in zip(ev, ok, strict=True) if not o), default=-math.inf)
        in_e = max((e for e, o in zip(ev, ok, strict=True) if o), default=-math.inf)
        if not any(ok) or out_e > in_e + self.options.ambiguity_margin:
            return [], complete
        order = sorted((i for i in range(len(every)) if ok[i]),
                       key=lambda i: (-ev[i], -every[i].inliers, every[i].rms_m))
        return [every[i] for i in order], complete

    def hypotheses(self, obs: Observation, cands: list[Candidate], cov: np.ndarray | None
                   ) -> tuple[Hypothesis, ...]:
        """The poses of ``cands`` (the first the chosen or best one) as hypotheses, at
        most :data:`MAX_HYPOTHESES`, weighted by ``exp(HYPOTHESIS_SHARPNESS x
        evidence)`` normalized (:meth:`evidence`: the frame's likelihood, the prior
        left out), all with covariance ``cov`` (None where not finite)."""
        weights = obs.weights()
        cands = cands[:MAX_HYPOTHESES]
        ev = np.array([self.evidence(c, weights) for c in cands])
        w = np.exp(HYPOTHESIS_SHARPNESS * (ev - ev.max()))
        w /= w.sum()
        if cov is not None:
            cov = np.array(cov, float)
            if not np.all(np.isfinite(cov)):
                cov = None
            else:
                cov.setflags(write=False)
        out = []
        for c, wk in zip(cands, w, strict=True):
            dx, dy = c.x_m - cands[0].x_m, c.y_m - cands[0].y_m
            turn = math.degrees(wrap_pi(c.yaw_rad - cands[0].yaw_rad))
            label = (f"shift ({dx:+.2f}, {dy:+.2f}) m, turn {turn:+.0f} deg"
                     if c is not cands[0] else "best")
            out.append(Hypothesis(float(c.x_m), float(c.y_m), float(c.yaw_rad), cov,
                                  float(wk), label))
        return tuple(out)


def distinct(cands: list[Candidate]) -> list[Candidate]:
    """The candidates without those near an earlier one (0.3 m, 5 deg), the one with
    more inliers kept."""
    if not cands:
        return []
    order = sorted(range(len(cands)), key=lambda i: (-cands[i].pairs.shape[0],
                                                     cands[i].rms_m))
    p = np.array([(cands[i].x_m, cands[i].y_m, cands[i].yaw_rad) for i in order])
    d_yaw = np.abs((p[:, None, 2] - p[None, :, 2] + math.pi) % (2 * math.pi) - math.pi)
    near = ((np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1]) < 0.3)
            & (d_yaw < math.radians(5.0)))
    keep = np.ones(len(order), bool)
    for i in range(len(order)):
        if keep[i]:
            keep[i + 1:] &= ~near[i, i + 1:]
    return [cands[order[i]] for i in np.flatnonzero(keep)]
