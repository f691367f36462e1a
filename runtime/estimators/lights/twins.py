"""The twins of a lights pose: the light map's own symmetries applied to a frame's poses.

A regular grid looks the same from every cell and under a half (or quarter) turn; a
pose the matcher finds has a twin for each symmetry of the map that keeps enough of its
matched lights on lights (:func:`~.matching.map_symmetries`, found once per map).
:class:`TwinJudge` moves a pose by them, verifies the moved poses against the frame
(:meth:`~.matching.PatternMatcher.twins`) and scores every candidate by the same
evidence, so that the estimator can say whether the frame singles one out
(docs/methods/lights.md, docs/methods/honesty.md). A map of more than
:data:`~.matching.SYMMETRY_MAX_LIGHTS` lights (up to :data:`PAIR_TWINS_MAX_LIGHTS`) is
not searched for its symmetries: each pose's twins are found per frame, as the
placements of pairs of its lights (:class:`PairVectors`).

Example::

    judge = TwinJudge(lights_w, matcher, extent, options)
    twins, complete = judge.twins(obs, best)
    ambiguous = any(judge.evidence(t, w) >= judge.evidence(best, w) - margin for t in twins)
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

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
from ceilkit.runtime.estimators.lights.observe import VIEW_PATCHES, Observation
from ceilkit.runtime.geometry.fits import rigid_fit_rms
from ceilkit.runtime.geometry.rotations import wrap_pi

MAX_TWIN_CHECKS = 1000  # at most this many of the map's symmetries are verified per frame
MAX_HYPOTHESES = 32  # an ambiguous frame carries at most this many poses
HYPOTHESIS_SHARPNESS = 2.0  # a hypothesis' weight goes as exp(this x its evidence score)
PAIR_TWINS_MAX_LIGHTS = 20_000
"""Maps of more lights are not searched for twins per frame (:class:`PairVectors`: its
work grows with the map, 10 ms a frame at 10 000 irregular lights, 77 ms at 100 000):
their twins are only the poses the vote verifies (docs/methods/lights.md, Known gaps)."""
TWIN_BATCH = 64  # twins are verified in batches of this many, then twice as many, ...
AXIS_TURN_MAX = math.pi / 4
"""A spot showing its lamp's axis (:data:`~.observe.AXIS_MIN_ELONGATION`) turned more
than this from the axis a pose puts the lamp at refutes that pair (:meth:`TwinJudge.
aligned`): halfway to a quarter turn. Measured over the held-out lamp drives of
``bench_heldout_lights.py`` (seeds 3, 7, 11, 13, 19; every 5th frame, 4,396 kept spots at
the true pose) the axis is at most 37 deg off (95 % within 6.5 deg)."""
DETECT_PRIOR = 3.0
"""Lights each bin of :class:`DetectionRates` counts found before the run shows any:
until then a light the frame should show is expected (after three fixes that each
missed the patch's only light, a miss there counts a quarter)."""
DETECT_MEMORY = 300.0  # lights per patch the rates remember (older ones fade)
PAIR_NEIGHBOUR = 4
"""On a map not searched for symmetries, the pairs indexed for the per-frame twin search
reach 1.5 times the median distance of a light to its this-th nearest other
(:class:`PairVectors`)."""


@dataclasses.dataclass(frozen=True, eq=False)
class DetectionRates:
    """How often the run's detector finds a map light its fixes show, patch by patch of
    the image (:data:`~.observe.VIEW_PATCHES`).

    A light far out in the view is imaged small and dim (the lens's fall-off): under a
    fisheye thresholded at a high level such lights are never found. Counted missing at
    every pose, they ranked poses by how few lights they show in view: the map's edge
    won, and the truth, whose view is full of such lights, fell out of its own list
    (held-out seed 31 ``grid1``, docs/methods/lights.md). Each fix the estimator
    publishes adds the lights it shows, found (matched, or where the frame has a region
    the checks did not keep) or missed, by their patch (:meth:`~.observe.
    VisibilityTable.patches`); a light missing where the rate is ``p`` is evidence
    ``p`` of a missing one (:meth:`TwinJudge.present`). Held by the estimator between
    frames (``LightsEstimator.forget`` empties it).

    Attributes:
        found, shown: ``(patches,)`` lights found and shown per patch (faded past
            :data:`DETECT_MEMORY`).
    """

    found: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(_PATCHES))
    shown: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(_PATCHES))

    @property
    def missed(self) -> bool:
        """Whether the run has missed a light (before that, every rate is 1)."""
        return bool(self.found.sum() < self.shown.sum())

    def added(self, found: np.ndarray, missed: np.ndarray) -> DetectionRates:
        """The rates with one fix's lights added: their patches, found and missed (-1,
        off the seen ceiling, left out)."""
        hit = _counted(found)
        shown = self.shown + hit + _counted(missed)
        fade = np.minimum(1.0, DETECT_MEMORY / np.maximum(shown, 1e-9))
        return DetectionRates((self.found + hit) * fade, shown * fade)

    @functools.cached_property
    def rates(self) -> np.ndarray:
        """``(patches,)`` the rate a light in each patch is found."""
        return (self.found + DETECT_PRIOR) / (self.shown + DETECT_PRIOR)

    def rate(self, patch: np.ndarray) -> np.ndarray:
        """``(K,)`` the rate a light in each ``patch`` is found (1 off the seen ceiling)."""
        return np.append(self.rates, 1.0)[np.asarray(patch, np.int64)]   # -1: the 1


_PATCHES = VIEW_PATCHES[0] * VIEW_PATCHES[1]


def _counted(patch: np.ndarray) -> np.ndarray:
    patch = np.asarray(patch, np.int64)
    return np.bincount(patch[patch >= 0], minlength=_PATCHES).astype(float)


class PairVectors:
    """The map's short pairs as vectors, for a per-frame twin search on a map too large
    to search for its symmetries once (more than :data:`~.matching.SYMMETRY_MAX_LIGHTS`
    lights).

    Every pair ``i < j`` of lights at most ``reach_m`` apart is kept with its vector
    ``L_j - L_i`` (W, m) in a 2-D k-d tree; ``reach_m`` is 1.5 times the median distance
    of a light to its :data:`PAIR_NEIGHBOUR`-th nearest other, plus ``2 gate_m``
    (``O(M)`` pairs: 8 per light on the held-out grid of two lights per 0.5 m tile,
    4.7 on an irregular field 1.6 m apart).
    :meth:`placements` finds every placement of two matched lights on the map, at
    each quarter turn: a pose's twins, complete whenever the two lie at most
    ``reach_m - 2 gate_m`` apart (every placement's pair is then indexed).
    """

    def __init__(self, lights_w: np.ndarray, gate_m: float) -> None:
        L = np.asarray(lights_w, float).reshape(-1, 2)
        self.lights, self.tol_m = L, 2.0 * gate_m
        tree = self.light_tree = cKDTree(L)
        k = min(PAIR_NEIGHBOUR, L.shape[0] - 1)
        d4 = float(np.median(tree.query(L, k=k + 1)[0][:, k])) if k > 0 else 0.0
        self.reach_m = 1.5 * d4 + self.tol_m
        pp = tree.query_pairs(self.reach_m, output_type="ndarray").reshape(-1, 2)
        self.pairs = pp.astype(np.int64)
        self.tree = cKDTree(L[pp[:, 1]] - L[pp[:, 0]]) if pp.shape[0] else None

    def placements(self, a: int, b: int) -> np.ndarray | None:
        """``(K, 3)`` rows ``(turn, tx, ty)``: the rigid motions ``p -> Rz(turn) p + t``
        (``turn`` a quarter turn) that take lights ``a`` and ``b`` onto two lights of the
        map (within ``2 gate_m`` of their vector), the identity among them; ``None``
        when ``a`` and ``b`` lie too far apart for every placement to be indexed."""
        pa, pb = self.lights[a], self.lights[b]
        v = pb - pa
        if self.tree is None or math.hypot(*v) > self.reach_m - self.tol_m:
            return None
        mid = 0.5 * (pa + pb)
        rows = []
        for k in range(4):
            turn = 0.5 * math.pi * k
            c, s = round(math.cos(turn)), round(math.sin(turn))
            vk = np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])
            mk = np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1]])
            for sign in (1.0, -1.0):          # a pair is indexed once, i < j
                hit = np.asarray(self.tree.query_ball_point(sign * vk, self.tol_m), np.int64)
                if hit.size == 0:
                    continue
                ij = self.pairs[hit]
                mids = 0.5 * (self.lights[ij[:, 0]] + self.lights[ij[:, 1]])
                t = mids - mk
                rows.append(np.column_stack([np.full(hit.size, turn), t]))
        return np.concatenate(rows) if rows else np.zeros((0, 3))

    def motions(self, ids: np.ndarray, need: int) -> tuple[np.ndarray, bool]:
        """``(K, 3)`` rows ``(turn, tx, ty)``, nearest first, that hold every
        quarter-turn motion keeping at least ``need`` of the lights ``ids`` on lights
        (:meth:`keeping` picks those out); and whether they hold all of them.

        The lights are paired, nearest pairs first and each light once; a motion that
        keeps ``need`` of ``n`` lights keeps both lights of one of any ``n - need + 1``
        such pairs, so the placements of that many pairs (:meth:`placements`) hold
        every such motion. Not all when fewer pairs lie within the indexed reach."""
        n = ids.size
        if need > n:
            return np.zeros((0, 3)), True
        seeds = self._seed_pairs(ids)
        want = n - need + 1
        found = [r for a, b in seeds[:want]
                 if (r := self.placements(a, b)) is not None and r.shape[0]]
        if not found:
            return np.zeros((0, 3)), want <= len(seeds)
        rows = np.concatenate(found)
        # one motion per cluster (several pairs find the same one)
        cell = np.round(rows[:, 1:] / self.tol_m).astype(np.int64)
        cell -= cell.min(axis=0)
        key = ((np.round(rows[:, 0] / (0.5 * math.pi)).astype(np.int64) * (cell[:, 0].max() + 1)
                + cell[:, 0]) * (cell[:, 1].max() + 1) + cell[:, 1])
        rows = rows[np.sort(np.unique(key, return_index=True)[1])]
        return rows[np.argsort(np.hypot(rows[:, 1], rows[:, 2]), kind="stable")], \
            want <= len(seeds)

    def keeping(self, rows: np.ndarray, ids: np.ndarray, need: int) -> np.ndarray:
        """The motions of ``rows`` that put at least ``need`` of the lights ``ids`` within
        ``gate_m`` of a light (as :func:`~.matching.symmetry_table`), in their order."""
        hits = np.zeros(rows.shape[0], np.int64)
        c, s = np.cos(rows[:, 0]), np.sin(rows[:, 0])
        for left, p in zip(range(ids.size - 1, -1, -1), self.lights[ids], strict=True):
            moved = np.column_stack([c * p[0] - s * p[1], s * p[0] + c * p[1]]) + rows[:, 1:]
            d, _ = self.light_tree.query(moved, distance_upper_bound=0.5 * self.tol_m)
            hits += np.isfinite(d)
            ok = hits + left >= need          # the others cannot make up the rest
            rows, hits, c, s = rows[ok], hits[ok], c[ok], s[ok]
        return rows

    def _seed_pairs(self, ids: np.ndarray) -> list[tuple[int, int]]:
        """The lights ``ids`` paired, nearest first, each light at most once, the pairs
        within ``reach_m - 2 gate_m`` (:meth:`placements` finds all their placements)."""
        p = self.lights[ids]
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
        iu = np.triu_indices(ids.size, 1)
        order = np.argsort(d[iu], kind="stable")
        used = np.zeros(ids.size, bool)
        out = []
        for k in order:
            i, j = iu[0][k], iu[1][k]
            if d[i, j] > self.reach_m - self.tol_m:
                break
            if not used[i] and not used[j]:
                used[i] = used[j] = True
                out.append((int(ids[i]), int(ids[j])))
        return out


class TwinJudge:
    """The map's symmetries and the evidence that tells a pose from its twins.

    Args:
        lights_w: ``(N, 2)`` the map's lights in W (m).
        matcher: the estimator's :class:`~.matching.PatternMatcher`.
        extent: the site's extent (a pose outside it is not possible).
        options: the estimator's options (``twins``, ``gate_m``, ``min_inliers``,
            ``site_margin_m``).
        present_m: how near a light's ceiling point a region the observer did not keep
            shows it there (:meth:`present`; 0: never).
    """

    def __init__(self, lights_w: np.ndarray, matcher: PatternMatcher, extent: SiteExtent,
                 options: Any, present_m: float = 0.0,
                 light_yaw_rad: float | None = None) -> None:
        o = options
        self.matcher, self.extent, self.options = matcher, extent, o
        self.present_m = present_m
        self.light_yaw_rad = light_yaw_rad    # rectangular lamps' long side in W (aligned)
        sym = (map_symmetries(lights_w, o.gate_m, o.min_inliers) if o.twins
               else np.zeros((0, 3)))
        # a larger map: each pose's twins searched per frame (PairVectors)
        m = lights_w.shape[0]
        self.pair_vectors = (PairVectors(lights_w, o.gate_m) if o.twins
                             and SYMMETRY_MAX_LIGHTS < m <= PAIR_TWINS_MAX_LIGHTS else None)
        self.searched = bool(o.twins and m <= PAIR_TWINS_MAX_LIGHTS)
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

    def present(self, obs: Observation, c: Candidate) -> Candidate:
        """``c`` with the map lights it should show that matched no spot but lie where
        the frame has a region the observer examined and did not keep (within
        ``present_m`` of its ceiling point: :attr:`~.observe.Observation.rejected_v`)
        no longer counted missing. Such a light is there, only not measurable: a lamp
        bloomed into an oval no rectangle fits, a light cut by the lens's edge. Counted
        missing, they ranked a pose by how few lights it predicts in view: under a
        183 deg fisheye with bloomed lamps (held-out ``lamps1`` of seed 7) only slivers
        at the rim were kept, every pose inside the grid had a dozen lights missing, a
        pose at the map's edge three cells away few, and it came out singled out (a
        complete list of four poses, all 12-15 m off, which ``auto`` then published).
        A light where the frame is dark stays missing (a lamp that is off). Such lights
        are no evidence against a pose, nor is a pose that shows more of them than it
        measures explained (the estimator's ``misfit``). Pairs whose lamp is seen
        turned are dropped first (:meth:`aligned`)."""
        c = self.aligned(obs, c)
        if c.missing == 0:
            return c
        z, there = self._missing(obs, c)
        if z.size == 0:
            return c
        n = int(np.count_nonzero(there))
        unseen = 0.0
        if obs.detect is not None and self.matcher.visible is not None:
            # of the lights missing, those the run's detector would miss anyway
            unseen = self.matcher.visible.unseen(z[~there] if n else z, obs.detect.rates)
        if n == 0 and unseen == 0.0:
            return c
        return Candidate(c.x_m, c.y_m, c.yaw_rad, c.pairs,
                         c.score + MISSING_PENALTY * (n + unseen), c.rms_m, c.missing - n,
                         n, unseen)

    def _missing(self, obs: Observation, c: Candidate) -> tuple[np.ndarray, np.ndarray]:
        """The lights ``c`` shows that matched no spot (V, ``x + iy``) and which of them
        lie where the frame has a region the checks did not keep (:meth:`present`)."""
        rv = obs.rejected_v
        if (rv is None or rv.size == 0 or self.present_m <= 0) and obs.detect is None:
            return np.zeros(0, np.complex128), np.zeros(0, bool)
        z = self.matcher.unmatched_seen(c)
        if z.size == 0 or rv is None or rv.size == 0 or self.present_m <= 0:
            return z, np.zeros(z.size, bool)
        return z, np.abs(z[:, None] - rv[None, :]).min(axis=1) <= self.present_m

    def detections(self, obs: Observation, c: Candidate) -> tuple[np.ndarray, np.ndarray]:
        """The image patches (:meth:`~.observe.VisibilityTable.patches`) of the lights the
        pose ``c`` shows, found (matched, or where the frame has a region the checks did
        not keep) and missed: what a published fix teaches :class:`DetectionRates`."""
        table = self.matcher.visible
        found = table.patches(obs.q_v[c.pairs[:, 0], 0] + 1j * obs.q_v[c.pairs[:, 0], 1])
        if c.missing + c.present == 0:
            return found, np.zeros(0, np.int64)
        z = self.matcher.unmatched_seen(dataclasses.replace(c, missing=c.missing + c.present))
        rv = obs.rejected_v
        there = (np.abs(z[:, None] - rv[None, :]).min(axis=1) <= self.present_m
                 if z.size and rv is not None and rv.size and self.present_m > 0
                 else np.zeros(z.size, bool))
        return np.concatenate([found, table.patches(z[there])]), table.patches(z[~there])

    def aligned(self, obs: Observation, c: Candidate) -> Candidate:
        """``c`` without the pairs whose spot shows its rectangular lamp's long side
        (:attr:`~.observe.Observation.axis_v`) more than :data:`AXIS_TURN_MAX` from the
        side the pose puts it at (the site's ``light_yaw`` less the pose's yaw), each
        such light counted missing: the frame shows a lamp there turned, not the one the
        map has. A grid of oblong lamps pitched alike both ways looks the same under a
        quarter turn by its points, never by its lamps. Itself for round lights, or
        when no spot shows its axis."""
        if self.light_yaw_rad is None or obs.axis_v is None or c.inliers == 0:
            return c
        a = obs.axis_v[c.pairs[:, 0]]
        d = np.abs(np.mod(a - (self.light_yaw_rad - c.yaw_rad) + 0.5 * math.pi, math.pi)
                   - 0.5 * math.pi)
        bad = np.isfinite(d) & (d > AXIS_TURN_MAX)
        n = int(bad.sum())
        if n == 0:
            return c
        pairs = c.pairs[~bad]
        out = dataclasses.replace(c, pairs=pairs, missing=c.missing + n,
                                  score=c.score - n * (1.0 + MISSING_PENALTY))
        # the pose refitted on the pairs left (a turned region, often two lamps merged
        # or a fixture, pulled it: a prior's region judges this pose)
        return self.refitted(obs, out)

    def refitted(self, obs: Observation, c: Candidate) -> Candidate:
        """``c`` with its pose the rigid fit of its own pairs (at least 2; else ``c``):
        the association's pose is fitted before its last re-association (on a frame of
        bloomed lamps 3.7 cm from where its final pairs put it, 0.2 cm from the truth)."""
        if c.inliers < 2:
            return c
        yaw, t, rms = rigid_fit_rms(obs.q_v[c.pairs[:, 0]], self.matcher.lights_w[c.pairs[:, 1]])
        return dataclasses.replace(c, x_m=float(t[0]), y_m=float(t[1]), yaw_rad=yaw,
                                   rms_m=rms)

    @staticmethod
    def evidence(c: Candidate, weights: np.ndarray) -> float:
        """A candidate's score with each spot at its weight (:meth:`Observation.weights`):
        the weighted spots it explains less :data:`~.matching.MISSING_PENALTY` per map
        light it should show that matched nothing."""
        return float(weights[c.pairs[:, 0]].sum()) - MISSING_PENALTY * (c.missing - c.unseen)

    def twins(self, obs: Observation, best: Candidate) -> tuple[list[Candidate], bool]:
        """The best pose moved by each motion of the map (on a regular grid the other
        cells and the turned placements, which a vote may leave unverified) that keeps
        enough of its matched lights on lights to come within the margin of it (at least
        ``min_inliers``, and with the spots it leaves unexplained its evidence less
        ``ambiguity_margin``), verified (:meth:`PatternMatcher.twins`); and whether
        they were all checked. The motions: the map's symmetries, found once, or on a
        map too large for that search those that put best's lights on lights, found per
        frame (:meth:`PairVectors.motions`); at most :data:`MAX_TWIN_CHECKS`."""
        # a twin explains at most the best's spots it keeps on lights and the spots the
        # best leaves unexplained: one that cannot come within the margin of the best
        # is no rival, and is not verified (most partial symmetries of an irregular map)
        reach = self.evidence(best, obs.weights()) - self.options.ambiguity_margin
        need = max(self.options.min_inliers,
                   math.ceil(reach - (len(obs.spots) - best.inliers) - 1e-9))
        keep = None
        if self.pair_vectors is not None:
            ids = np.unique(best.pairs[:, 1])
            sym, complete = self.pair_vectors.motions(ids, need)

            def keep(rows: np.ndarray) -> np.ndarray:
                return self.pair_vectors.keeping(rows, ids, need)
        else:
            if self.symmetries.shape[0] == 0:
                return [], self.searched
            kept = self.lights[:, best.pairs[:, 1]].sum(axis=1)
            sym = self.symmetries[kept >= need]
            complete = self.searched
        twins, stopped = self._verified(obs, best, sym, keep)
        return twins, complete and not stopped

    def _verified(self, obs: Observation, best: Candidate, sym: np.ndarray,
                  keep: Any = None) -> tuple[list[Candidate], bool]:
        """``best`` moved by each motion of ``sym`` (:func:`~.matching.twin_poses`; those
        ``keep`` keeps when given), verified (:meth:`PatternMatcher.twins`), nearest
        first in batches of :data:`TWIN_BATCH`, then twice as many, ...; and whether the
        search stopped before the end: past :data:`MAX_TWIN_CHECKS` motions, or once two
        distinct possible poses lie within ``ambiguity_margin`` of the best found (the
        frame then singles none out whatever the other motions would show; a regular
        grid has hundreds of twins, each verification some 0.1 ms)."""
        weights, out, start, size, checked = obs.weights(), [], 0, TWIN_BATCH, 0
        margin = self.options.ambiguity_margin
        if keep is None:             # the map's symmetries: all at once, as found
            size = MAX_TWIN_CHECKS
        while start < sym.shape[0]:
            batch = sym[start:start + size]
            start, size = start + size, 2 * size
            batch = batch if keep is None else keep(batch)
            checked += batch.shape[0]
            if checked > MAX_TWIN_CHECKS:
                return out, True
            if batch.shape[0] == 0:
                continue
            out += [self.present(obs, c) for c in self.matcher.twins(
                obs.q_v, twin_poses(batch, best.x_m, best.y_m, best.yaw_rad),
                2.0 * self.options.gate_m, self.options.min_inliers)]
            ev = [self.evidence(c, weights) for c in distinct([best] + out)
                  if self.possible(c)]
            if start < sym.shape[0] and sum(e >= max(ev) - margin for e in ev) >= 2:
                return out, True
        return out, False

    def ranked(self, obs: Observation, cands: list[Candidate], weights: np.ndarray
               ) -> tuple[list[Candidate], bool]:
        """Every placement of the best candidate's spots on the map's lights (its twins,
        with the matcher's ``cands``), distinct, the possible ones ranked by evidence,
        and whether every twin was checked. Empty when only a pose outside the site
        (which its model check would refuse) explains the frame best, by more than
        ``ambiguity_margin``."""
        every, complete = self._every(obs, cands, weights)
        ev = [self.evidence(c, weights) for c in every]          # each scored once
        ok = [self.possible(c) for c in every]
        out_e = max((e for e, o in zip(ev, ok, strict=True) if not o), default=-math.inf)
        in_e = max((e for e, o in zip(ev, ok, strict=True) if o), default=-math.inf)
        if not any(ok) or out_e > in_e + self.options.ambiguity_margin:
            return [], complete
        order = sorted((i for i in range(len(every)) if ok[i]),
                       key=lambda i: (-ev[i], -every[i].inliers, every[i].rms_m))
        return [every[i] for i in order], complete


    def _every(self, obs: Observation, cands: list[Candidate], weights: np.ndarray
               ) -> tuple[list[Candidate], bool]:
        """``cands`` with the twins of the first, distinct, those of ``min_inliers``;
        and whether every twin was checked. Where the twins are placements of two
        lights found per frame (:meth:`PairVectors.motions`) and one explains spots the
        first did not, that one's twins are added too (a pose the vote missed, whose
        own twins need keep few of the first's lights)."""
        twins, complete = self.twins(obs, cands[0])
        every = distinct(cands + twins)
        if self.pair_vectors is not None and every:
            top = max(every, key=lambda c: self.evidence(c, weights))
            if np.setdiff1d(top.pairs[:, 0], cands[0].pairs[:, 0]).size:
                more, done = self.twins(obs, top)
                every, complete = distinct(every + more), complete and done
        return [c for c in every if c.inliers >= self.options.min_inliers], complete

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
