"""Point-pattern matching of ceiling points (V) to a light map (W).

:class:`PatternMatcher` finds the rigid 2-D transforms ``p_W = R(yaw) q_V + t`` that
put the most observed ceiling points on map lights: every observed pair votes, through
the map pairs of the same length (a pair-distance hash), for a pose ``(yaw, x, y)``;
the best-voted poses are verified by association and a rigid refit
(:func:`~ceilkit.runtime.geometry.fits.fit_rigid_2d_complex`), and returned as
:class:`Candidate` values, best first. A map of many lights (more than
:data:`PAIR_VOTE_MAX_PAIRS` pairs a frame could see) votes through its constellations
instead, and is verified against the lights about each pose alone
(:mod:`~.index`): a frame's work does not grow with the map.

Convention (SPEC §1): the candidate ``(x_m, y_m, yaw_rad)`` is the vehicle pose in W:
``X_W = Rz(yaw) X_V + (x, y, 0)``.

Example::

    cands = PatternMatcher(site.lights_m, gate_m=0.1).match(q_v, order)
    best = cands[0] if cands else None          # best.x_m, best.pairs, best.score
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.estimators.lights.index import (
    ConstellationIndex,
    LightGrid,
    near_core,
    quad_poses,
)
from ceilkit.runtime.estimators.lights.observe import locate_core
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

MISSING_PENALTY = 0.5
"""A candidate's score: its inliers minus this per map light it should show but does not."""
SYMMETRY_MAX_LIGHTS = 300
"""Maps of more lights are not searched for symmetries (:func:`map_symmetries`): the
search is quadratic in the lights (a 20 x 15 grid: 1 s, 2 400 motions)."""
PAIR_VOTE_MAX_PAIRS = 20_000
"""A map with more pairs shorter than the longest a frame sees votes through its
constellations (:class:`~.index.ConstellationIndex`), not with every pair: the pair
vote's work grows with the pairs (a dense field of 1 000 lights, 75 000 pairs: 5 ms)."""
FIRST_ANCHORS = 2
"""On a map voting through its constellations, the quads of this many points (the most
reliable) vote first; the others' only when these do not settle the frame."""
SETTLED_SHARE = 0.6
"""... settled: the best pose verified explains this share of the points (and >= 4)."""
LOCAL_FROM_LIGHTS = 256
"""From this many lights a pose is verified against the lights about it alone
(:class:`~.index.LightGrid`); below, against all of them (the same result)."""
_SAME_BIN = (0.5, math.radians(8.0))    # (m, rad): a vote bin next to a verified pose
_SAME_POSE = (0.3, math.radians(5.0))   # (m, rad): a verified pose already found


class Gates(NamedTuple):
    """The gates of :func:`_verify` (m): the first association's ``first_m``, the
    second's ``second_m`` (after the rigid refit), and the view's reach ``reach_m`` (the
    lights within it of the pose are the ones read)."""

    first_m: float
    second_m: float
    reach_m: float


class VoteSettings(NamedTuple):
    """The pair vote's settings as :func:`_match` and :func:`_vote` read them (the
    :class:`PatternMatcher`'s): the association gate ``gate_m``, the bins ``yaw_bin_rad``
    and ``pos_bin_m``, ``top_bins``, ``max_bins``, ``max_observed``, the votes a bin
    needs once a candidate is found ``min_votes`` and the view's reach ``reach_m``."""

    gate_m: float
    yaw_bin_rad: float
    pos_bin_m: float
    top_bins: int
    max_bins: int
    max_observed: int
    min_votes: float
    reach_m: float


class Verified(NamedTuple):
    """What :func:`_verify` returns: ``found``, the refitted pose ``x, y, yaw``, the
    ``pairs (K, 2)`` (observed, map), the ``score``, ``rms_m`` and the lights
    ``missing``."""

    found: bool
    x: float
    y: float
    yaw: float
    pairs: np.ndarray
    score: float
    rms_m: float
    missing: int


@dataclass(frozen=True)
class Candidate:
    """A verified pose hypothesis: ``p_W = R(yaw) q_V + (x, y)``.

    Attributes:
        x_m, y_m, yaw_rad: the vehicle pose.
        pairs: ``(K, 2)`` int: observed index, map index of each inlier.
        score: inliers minus :data:`MISSING_PENALTY` per map light that should be
            seen but is not.
        rms_m: RMS of the inliers' ceiling distances.
        missing: map lights that should be seen from this pose but matched nothing.
        present: map lights it should show that matched nothing but lie where the frame
            has a region the checks did not keep (not in ``missing``:
            :meth:`~.twins.TwinJudge.present`).
        unseen: of ``missing``, how many the run's detector would have missed anyway
            (each missing light's miss rate where the frame shows it:
            :class:`~.twins.DetectionRates`); no evidence against the pose.
    """

    x_m: float
    y_m: float
    yaw_rad: float
    pairs: np.ndarray
    score: float
    rms_m: float
    missing: int = 0
    present: int = 0
    unseen: float = 0.0

    @property
    def inliers(self) -> int:
        return int(self.pairs.shape[0])

    def same_pose(self, other: Candidate, pos_m: float, yaw_rad: float) -> bool:
        return near_pose(self.x_m, self.y_m, self.yaw_rad, other, pos_m, yaw_rad)


def near_pose(x_m: float, y_m: float, yaw_rad: float, other: Candidate, pos_m: float,
              max_yaw_rad: float) -> bool:
    """Whether the pose ``(x_m, y_m, yaw_rad)`` is within ``pos_m`` and ``max_yaw_rad``
    of ``other`` (:meth:`Candidate.same_pose` without building a candidate)."""
    return (math.hypot(x_m - other.x_m, y_m - other.y_m) < pos_m
            and abs(wrap_pi(yaw_rad - other.yaw_rad)) < max_yaw_rad)


class PatternMatcher:
    """Rotation- and translation-invariant matching of ceiling points to a light map.

    Built once per map (a k-d tree, ``O(M log M)``): every map pair shorter than
    ``max_pair_m`` with its length, sorted (a pair-distance hash), when there are at
    most :data:`PAIR_VOTE_MAX_PAIRS`; else the map's constellations
    (:class:`~.index.ConstellationIndex`), whose matches vote instead. From
    ``index_from`` lights the lights are bucketed (:class:`~.index.LightGrid`) and a
    pose is verified against those about it alone, so neither path's work per frame
    grows with the map. ``match`` returns verified candidates, best first. The vote,
    its bins and the verification of each are one compiled call (:func:`_match`,
    :func:`_vote`); the array reading they stand for is kept with the tests.

    Args:
        lights_w: ``(M, 2)`` map light centres in W.
        gate_m: largest distance of an inlier from its map light (ceiling metres).
        max_pair_m: longest pair that can be seen in one frame.
        visible: optional :class:`~.observe.VisibilityTable` of the same lights: the
            map lights the camera should see from a pose (poses whose visible lights
            are not observed are penalized).
        index_from: bucket the lights from this many (:data:`LOCAL_FROM_LIGHTS`).
    """

    def __init__(self, lights_w: np.ndarray, gate_m: float = 0.08, max_pair_m: float = 1e9,
                 visible: Any = None, max_observed: int = 7, top_bins: int = 8,
                 max_bins: int = 48,
                 yaw_bin_rad: float = math.radians(4.0), pos_bin_m: float = 0.3,
                 index_from: int = LOCAL_FROM_LIGHTS):
        self.lights_w = np.asarray(lights_w, float).reshape(-1, 2)
        m = self.lights_w.shape[0]
        self.gate_m = gate_m
        self.visible = visible
        self.max_observed = max_observed
        self.top_bins = top_bins
        self.max_bins = max(top_bins, max_bins)
        self.yaw_bin_rad = yaw_bin_rad
        self.pos_bin_m = pos_bin_m
        tree = cKDTree(self.lights_w) if m else None
        n_pairs = _pairs_within(self.lights_w, tree, max_pair_m)
        # a map of few pairs votes with every pair (the pair-distance hash); a larger
        # one through its constellations (index.py): its per-frame cost does not grow
        i, j = np.zeros((2, 0), np.int64)
        self.index = None
        if n_pairs <= PAIR_VOTE_MAX_PAIRS:
            # the pairs within max_pair_m, in np.triu_indices order (a k-d tree, not
            # all pairs: the same table)
            if m >= 2:
                pp = tree.query_pairs(max_pair_m * (1 + 1e-9) + 1e-9, output_type="ndarray")
                pp = pp[np.lexsort((pp[:, 1], pp[:, 0]))]
                i, j = pp[:, 0].astype(np.int64), pp[:, 1].astype(np.int64)
        else:
            self.index = ConstellationIndex(self.lights_w, gate_m)
        d = np.linalg.norm(self.lights_w[i] - self.lights_w[j], axis=1)
        keep = d <= max_pair_m
        order = np.argsort(d[keep])
        self.pair_i = i[keep][order]
        self.pair_j = j[keep][order]
        self.pair_d = d[keep][order]
        # per-map structures of the vote, in complex form (x + iy): each pair's midpoint
        # and unit direction i -> j
        lights_c = self.lights_w[:, 0] + 1j * self.lights_w[:, 1]
        vp = lights_c[self.pair_j] - lights_c[self.pair_i]
        pair_dir = vp / np.maximum(np.abs(vp), 1e-12)
        pair_mid = 0.5 * (lights_c[self.pair_i] + lights_c[self.pair_j])
        if visible is None:   # no table (its NI < 0 skips the lookup): nothing is missing
            vis = (arr(self.lights_w, np.float64), arr(np.full(1, np.inf), np.float32),
                   arr([0.0, 0.0, 1.0], np.float64), arr([-1, -1, 0], np.int64))
            reach = 0.0
        else:
            vis = visible.arrays
            reach = view_reach_m(visible)
        # what the compiled calls read (read-only)
        self._map = (arr(lights_c, np.complex128), arr(self.pair_d, np.float64),
                     arr(pair_mid, np.complex128), arr(pair_dir, np.complex128))
        self._vis = vis
        self._grid = _grid_arrays(self.lights_w, m >= index_from, reach, max_pair_m)
        self._params = VoteSettings(float(gate_m), float(self.yaw_bin_rad),
                                    float(self.pos_bin_m), int(self.top_bins),
                                    int(self.max_bins), int(self.max_observed), 3.0,
                                    float(reach))
        # the constellations' votes: a quad is strong evidence, a bin of 2 is a rival
        self._hash_params = self._params._replace(min_votes=2.0)

    # -- association ------------------------------------------------------------------
    def associate(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float
                  ) -> np.ndarray:
        """``(K, 2)`` (observed, map) pairs: mutual nearest neighbours within ``gate_m``."""
        return _associate(_complex(q_v), complex(math.cos(yaw), math.sin(yaw)),
                          complex(t[0], t[1]), self._map[0], float(gate_m))

    def verify(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float | None = None
               ) -> Candidate | None:
        """Associate within ``gate_m`` (default: the matcher's gate), refit the rigid
        transform, re-associate within the matcher's gate; ``None`` with fewer than two
        inliers. Its score counts the map lights the pose should show but that matched
        nothing (``visible``)."""
        gates = Gates(float(self.gate_m if gate_m is None else gate_m), float(self.gate_m),
                      self._params.reach_m)
        out = _verify(_complex(q_v), float(yaw), complex(t[0], t[1]), gates,
                      self._map[0], self._vis, self._grid)
        if not out.found:
            return None
        return Candidate(out.x, out.y, out.yaw, out.pairs, out.score, out.rms_m,
                         out.missing)

    def unmatched_seen(self, c: Candidate) -> np.ndarray:
        """``(K,)`` the map lights (in V, ``x + iy``) the pose ``c`` should show that
        matched none of its spots: what its ``missing`` counts (:func:`_unmatched_seen`)."""
        if self._vis[3][0] < 0 or c.missing == 0:
            return np.zeros(0, np.complex128)
        return _unmatched_seen(arr([c.x_m, c.y_m, c.yaw_rad], np.float64),
                               arr(c.pairs[:, 1], np.int64), self._map[0], self._vis,
                               self._grid, float(self._params.reach_m))

    def twins(self, q_v: np.ndarray, starts: np.ndarray, gate_m: float,
              min_inliers: int) -> list[Candidate]:
        """The poses ``starts (K, 3)`` ``(x, y, yaw)`` verified (:meth:`verify`, first
        association within ``gate_m``), those with at least ``min_inliers`` inliers, a
        pose near one found before dropped (0.3 m, 5 deg). One compiled call
        (:func:`_twins`)."""
        starts = np.asarray(starts, float).reshape(-1, 3)
        if starts.shape[0] == 0 or self.lights_w.shape[0] == 0:
            return []
        gates = Gates(float(gate_m), float(self.gate_m), self._params.reach_m)
        poses, pairs, offsets = _twins(_complex(q_v), arr(starts, np.float64), gates,
                                       int(min_inliers), self._map[0], self._vis,
                                       self._grid)
        return [Candidate(p[0], p[1], p[2], pairs[a:b], p[3], p[4], int(p[5]))
                for p, a, b in zip(poses.tolist(), offsets[:-1].tolist(),
                                   offsets[1:].tolist(), strict=True)]

    # -- global -------------------------------------------------------------------------
    def hypotheses(self, q_v: np.ndarray) -> np.ndarray:
        """``(K, 3)`` poses ``(yaw, x, y)`` voted by every observed pair x matching map pair.

        Each observed pair ``(a, b)`` and map pair ``(i, j)`` of the same length (within
        ``2 gate_m``) give two poses, one per orientation: the rotation takes ``b - a``
        onto ``j - i`` (or ``i - j``), the translation takes the midpoints together.
        """
        return _hypotheses(_complex(q_v), *self._map[1:], 2.0 * self.gate_m)

    def match(self, q_v: np.ndarray, order: np.ndarray | None = None) -> list[Candidate]:
        """Verified, distinct candidates for observed ceiling points ``(N, 2)``, best first.

        ``order`` ranks the observations (most reliable first); the hashing uses the
        first ``max_observed`` of them, the verification all of them.

        The poses :meth:`hypotheses` votes for are binned (:attr:`yaw_bin_rad`,
        :attr:`pos_bin_m`); the bins are looked at by their votes, most first (ties in
        the order of their cells, yaw first). On a map voting through its
        constellations each matched quad is one vote (ties: the best-fitting quad
        first), and a bin needs 2 votes, not 3, to be looked at once a candidate is
        found. A bin's pose is its votes' circular mean yaw and
        median position, verified (:meth:`verify`) unless a candidate already lies near
        it; a verified pose near an earlier one is dropped. Bins far below the best
        cannot hold a rival of similar support: the search stops at the first bin with
        fewer than ``max(3, 0.2 best)`` votes once a candidate is found, and past
        ``top_bins`` at the first with fewer than half the best (a regular layout spreads
        its votes over many equally good poses).
        """
        n = q_v.shape[0]
        if n < 2 or self.lights_w.shape[0] < 2:
            return []
        use = np.arange(n) if order is None else np.asarray(order)
        qc = _complex(q_v)
        if self.index is not None:
            return self._match_constellations(q_v, qc, use)
        poses, pairs, offsets = _match(qc, arr(use, np.int64), self._map, self._params,
                                       self._vis, self._grid)
        cands = _candidates(poses, pairs, offsets)
        cands.sort(key=lambda c: (-c.score, -c.inliers, c.rms_m))
        return cands

    def _match_constellations(self, q_v: np.ndarray, qc: np.ndarray, use: np.ndarray
                              ) -> list[Candidate]:
        """:meth:`match` on a map voting through its constellations: the quads of the
        first :data:`FIRST_ANCHORS` points of ``use`` vote
        (:meth:`~.index.ConstellationIndex.hits`, :func:`~.index.quad_poses`,
        :func:`_vote`); when the best pose they verify does
        not explain :data:`SETTLED_SHARE` of the points, the quads of the others up to
        ``max_observed`` vote with them."""
        settle = max(4, math.ceil(SETTLED_SHARE * qc.size))
        hyp = np.zeros((0, 4))
        cands: list[Candidate] = []
        for lo, hi in ((0, FIRST_ANCHORS), (FIRST_ANCHORS, self.max_observed)):
            if lo >= min(hi, use.size):
                break
            obs, maps = self.index.hits(q_v, use[lo:hi])
            hyp = np.concatenate([hyp, quad_poses(qc, arr(obs, np.int64),
                                                  arr(maps, np.int64), self._map[0])])
            cands = _candidates(*_vote(qc, arr(hyp[:, :3], np.float64),
                                       arr(hyp[:, 3], np.float64), self._map[0],
                                       self._hash_params, self._vis, self._grid))
            cands.sort(key=lambda c: (-c.score, -c.inliers, c.rms_m))
            if cands and cands[0].inliers >= settle:
                break
        return cands


def _candidates(poses: np.ndarray, pairs: np.ndarray, offsets: np.ndarray
                ) -> list[Candidate]:
    """The candidates of a compiled call's ``(poses, pairs, offsets)`` (:func:`_match`)."""
    return [Candidate(p[0], p[1], p[2], pairs[a:b], p[3], p[4], int(p[5]))
            for p, a, b in zip(poses.tolist(), offsets[:-1].tolist(), offsets[1:].tolist(),
                               strict=True)]


def _complex(q_v: np.ndarray) -> np.ndarray:
    """Points ``(N, 2)`` as ``x + iy`` (read-only, as a compiled call takes them)."""
    q = np.asarray(q_v, float).reshape(-1, 2)
    return arr(q[:, 0] + 1j * q[:, 1], np.complex128)


@njit
def _associate(qc, rot, t, lights_c, gate):  # pragma: no cover - compiled
    """``(K, 2)`` (observed, map) pairs of points ``qc`` moved by ``rot q + t``: mutual
    nearest neighbours (the first of equal distances) within ``gate``. Distances are
    compared squared (no square root), the few within a relative ``1e-12`` of each
    other by their ``abs`` (:func:`_closer`): the pairs of the ``abs`` distances, the
    same bit for bit (tests/lights_reference.py holds that reading), in a third of
    the time (``hypot`` was 480 of a verification's 12 x 40)."""
    n, m = qc.size, lights_c.size
    out = np.empty((n, 2), np.int64)
    if m == 0:
        return out[:0].copy()
    p = np.empty(n, np.complex128)
    d2 = np.empty((n, m))
    for i in range(n):
        p[i] = qc[i] * rot + t
        for j in range(m):
            e = p[i] - lights_c[j]
            d2[i, j] = e.real * e.real + e.imag * e.imag
    k = 0
    for i in range(n):
        if not (math.isfinite(p[i].real) and math.isfinite(p[i].imag)):
            continue                       # every distance NaN: np.argmin's first, no pair
        j = 0
        for c in range(1, m):
            if _closer(p[i], lights_c[c], d2[i, c], p[i], lights_c[j], d2[i, j]):
                j = c
        if not abs(p[i] - lights_c[j]) < gate:
            continue
        best = 0
        for r in range(1, n):
            if _closer(p[r], lights_c[j], d2[r, j], p[best], lights_c[j], d2[best, j]):
                best = r
        if best == i:
            out[k, 0], out[k, 1] = i, j
            k += 1
    return out[:k].copy()


@njit
def _closer(a, la, a2, b, lb, b2):  # pragma: no cover - compiled
    """Whether ``abs(a - la) < abs(b - lb)``, given the squares ``a2``, ``b2`` of the
    two distances: decided by them unless they lie within a relative ``1e-12`` (or one
    is NaN), where ``abs`` decides (rounding moves a square by ~1e-16 relative)."""
    if a2 < b2 * (1.0 - 1e-12):
        return True
    if a2 > b2 * (1.0 + 1e-12):
        return False
    return abs(a - la) < abs(b - lb)


def view_reach_m(visible: Any) -> float:
    """How far (m, in V) from the vehicle a light the table ``visible``
    (:class:`~.observe.VisibilityTable`) reports can lie: its farthest corner."""
    ni, nj = visible.table.shape
    lo = np.asarray(visible.origin_m, float) - visible.cell_m
    hi = lo + visible.cell_m * np.array([ni + 1, nj + 1])
    return float(max(math.hypot(x, y) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])))


def _pairs_within(lights_w: np.ndarray, tree: cKDTree | None, r_m: float) -> int:
    """The pairs of lights at most ``r_m`` apart: counted for up to 2 000 lights, else
    estimated from every ``M // 2000``-th light's neighbours (a k-d tree; an exact count
    would cost as many steps as there are pairs, 25 million for 100 000 lights)."""
    m = lights_w.shape[0]
    if m < 2 or tree is None:
        return 0
    step = max(1, m // 2000)
    n = tree.query_ball_point(lights_w[::step], r_m, return_length=True)
    return int(((np.sum(n) - n.size) * (m / n.size)) // 2)


def _grid_arrays(lights_w: np.ndarray, bucketed: bool, reach_m: float,
                 max_pair_m: float) -> tuple:
    """:attr:`~.index.LightGrid.arrays` of the lights in cells of half the view's
    reach (at least 1 m), or, when not ``bucketed``, of no cell (:func:`_local`: every
    light)."""
    if bucketed:
        scale = reach_m if reach_m > 0 else min(max_pair_m, 50.0)
        return LightGrid(lights_w, max(1.0, 0.5 * scale)).arrays
    return (arr(np.zeros(0), np.int64), arr(np.zeros(1), np.int64), arr(np.zeros(0), np.int64),
            arr(np.zeros((0, 2)), np.float64), arr([0.0, 0.0, 1.0], np.float64),
            arr([0, 0], np.int64))


@njit
def _local(grid, m, t, r):  # pragma: no cover - compiled
    """The sorted indices of the lights within ``r`` of ``t`` (x + iy) in ``grid``
    (:func:`~.index.near_core`), or all ``m`` when the lights are not bucketed."""
    if grid[0].size == 0:
        return np.arange(m)
    return near_core(grid, t.real, t.imag, r)


@njit
def _unmatched_seen(pose, matched, lights_c, vis, grid, reach):  # pragma: no cover
    """:meth:`PatternMatcher.unmatched_seen`: the lights within ``reach`` of ``pose``
    ``(x, y, yaw)`` that :func:`~.observe.locate_core` says it shows, less the map
    lights ``matched``, in V as ``x + iy`` (the count :func:`_verify` calls missing)."""
    vis_lights, padded, geo, ints = vis
    t = complex(pose[0], pose[1])
    local = _local(grid, lights_c.size, t, reach + 1e-6)
    seen, _, zr, zi = locate_core(pose[0], pose[1], pose[2], vis_lights[local], padded,
                                  geo, ints)
    for j in matched:
        k = np.searchsorted(local, j)
        if k < local.size and local[k] == j:
            seen[k] = False
    out = np.empty(int(seen.sum()), np.complex128)
    n = 0
    for k in range(seen.size):
        if seen[k]:
            out[n] = complex(zr[k], zi[k])
            n += 1
    return out


@njit
def _verify(qc, yaw, t, gates, lights_c, vis, grid):  # pragma: no cover - compiled
    """:meth:`PatternMatcher.verify` in a compiled call: ``(found, x, y, yaw, pairs (K,
    2), score, rms_m, missing)``; the rigid refit is
    :func:`~ceilkit.runtime.geometry.fits.fit_rigid_2d_complex`'s, the lights a pose
    should show :func:`~.observe.locate_core`'s. ``gates`` (:class:`Gates`): the first
    association's gate, the second's, and the view's reach (m): each association and
    the count of lights missed read only the lights within reach of the pose
    (:func:`_local`; the same pairs and count as all of them, in the map's order).
    Returns a :class:`Verified`."""
    gate, gate_m, reach = gates
    vis_lights, padded, geo, ints = vis
    none = np.empty((0, 2), np.int64)
    q_max = 0.0
    for i in range(qc.size):
        q_max = max(q_max, abs(qc[i]))
    r = max(reach, q_max + max(gate, gate_m)) + 1e-6
    local = _local(grid, lights_c.size, t, r)
    pairs = _associate(qc, complex(math.cos(yaw), math.sin(yaw)), t, lights_c[local], gate)
    k = pairs.shape[0]
    if k < 2:
        return Verified(False, 0.0, 0.0, 0.0, none, 0.0, 0.0, 0)
    qm, pm = 0j, 0j
    for r_ in range(k):
        qm += qc[pairs[r_, 0]]
        pm += lights_c[local[pairs[r_, 1]]]
    qm, pm = qm / k, pm / k
    sc = 0j
    for r_ in range(k):
        sc += (qc[pairs[r_, 0]] - qm).conjugate() * (lights_c[local[pairs[r_, 1]]] - pm)
    rot = sc / abs(sc) if abs(sc) > 0 else 1.0 + 0j
    t = pm - rot * qm
    local = _local(grid, lights_c.size, t, r)
    pairs = _associate(qc, rot, t, lights_c[local], gate_m)
    k = pairs.shape[0]
    if k < 2:
        return Verified(False, 0.0, 0.0, 0.0, none, 0.0, 0.0, 0)
    ss = 0.0
    for r_ in range(k):
        e = abs(qc[pairs[r_, 0]] * rot + t - lights_c[local[pairs[r_, 1]]])
        ss += e * e
    yaw = math.atan2(rot.imag, rot.real)
    missing = 0
    if ints[0] >= 0:
        seen = locate_core(t.real, t.imag, yaw, vis_lights[local], padded, geo, ints)[0]
        for r_ in range(k):
            seen[pairs[r_, 1]] = False
        for j in range(seen.size):
            missing += seen[j]
    for r_ in range(k):
        pairs[r_, 1] = local[pairs[r_, 1]]
    score = k - MISSING_PENALTY * missing
    return Verified(True, t.real, t.imag, yaw, pairs, score, math.sqrt(ss / k), missing)


@njit
def _hypotheses(qc, pair_d, pair_mid, pair_dir, tol):  # pragma: no cover - compiled
    """:meth:`PatternMatcher.hypotheses` of points ``qc``: the poses of the observed
    pairs in ``np.triu_indices`` order, each with its map pairs within ``tol`` in length
    order, the reversed orientations after all the forward ones."""
    n = qc.size
    n_pairs = n * (n - 1) // 2
    lo = np.empty(n_pairs, np.int64)
    hi = np.empty(n_pairs, np.int64)
    total = 0
    k = 0
    for a in range(n):
        for b in range(a + 1, n):
            d = abs(qc[b] - qc[a])
            lo[k] = np.searchsorted(pair_d, d - tol)
            hi[k] = np.searchsorted(pair_d, d + tol)
            total += hi[k] - lo[k]
            k += 1
    out = np.empty((2 * total, 3))
    r = 0
    k = 0
    for a in range(n):
        for b in range(a + 1, n):
            vq = qc[b] - qc[a]
            uq = (vq / max(abs(vq), 1e-12)).conjugate()
            mid_q = 0.5 * (qc[a] + qc[b])
            for mp in range(lo[k], hi[k]):
                rot = pair_dir[mp] * uq
                rmq = rot * mid_q
                yaw = math.atan2(rot.imag, rot.real)
                out[r, 0] = yaw
                out[total + r, 0] = yaw - math.copysign(math.pi, yaw)
                fwd, rev = pair_mid[mp] - rmq, pair_mid[mp] + rmq
                out[r, 1], out[r, 2] = fwd.real, fwd.imag
                out[total + r, 1], out[total + r, 2] = rev.real, rev.imag
                r += 1
            k += 1
    return out


@njit
def _match(qc, use, maps, params, vis, grid):  # pragma: no cover - compiled
    """:meth:`PatternMatcher.match` before the candidates are made and sorted:
    ``(poses (C, 6), pairs (P, 2), offsets (C + 1,))``, a candidate's row ``(x, y,
    yaw, score, rms_m, missing)``, its pairs ``pairs[offsets[c]:offsets[c + 1]]``, in the
    order found: the pair vote (:func:`_hypotheses`) of the ``max_observed`` first
    points of ``use``, binned and verified (:func:`_vote`). ``maps``: the matcher's
    lights, pair lengths, midpoints and directions; ``params``: its
    :class:`VoteSettings`."""
    lights_c, pair_d, pair_mid, pair_dir = maps
    hyp = _hypotheses(qc[use[:params.max_observed]], pair_d, pair_mid, pair_dir,
                      2.0 * params.gate_m)
    return _vote(qc, hyp, np.zeros(hyp.shape[0]), lights_c, params, vis, grid)


@njit
def _vote(qc, hyp, rank, lights_c, params, vis, grid):  # pragma: no cover - compiled
    """The poses ``hyp (K, 3)`` ``(yaw, x, y)`` binned, and the bins verified by their
    votes, most first (ties: the smallest ``rank (K,)`` of a bin's votes, then the order
    of their cells), as :meth:`PatternMatcher.match` says (``params``: the
    :class:`VoteSettings`): :func:`_match`'s output."""
    yaw_bin, pos_bin = params.yaw_bin_rad, params.pos_bin_m
    top_bins, max_bins = params.top_bins, params.max_bins
    min_votes = params.min_votes
    gates = Gates(params.gate_m, params.gate_m, params.reach_m)
    poses = np.empty((max_bins, 6))
    offsets = np.zeros(max_bins + 1, np.int64)
    all_pairs = np.empty((max_bins * qc.size, 2), np.int64)
    nk = hyp.shape[0]
    if nk == 0:
        return poses[:0], all_pairs[:0], offsets[:1]
    # bins: (yaw, x, y) cells; each pose's cell as one key, its votes in a stable order
    kb = np.empty((nk, 3), np.int64)
    size = (yaw_bin, pos_bin, pos_bin)
    for r in range(nk):
        for c in range(3):
            kb[r, c] = np.int64(math.floor(hyp[r, c] / size[c]))
    low = np.empty(3, np.int64)
    span = np.empty(3, np.int64)
    for c in range(3):
        low[c] = kb[:, c].min()
        span[c] = kb[:, c].max() - low[c] + 1
    key = np.empty(nk, np.int64)
    for r in range(nk):
        key[r] = ((kb[r, 0] - low[0]) * span[1] + kb[r, 1] - low[1]) * span[2] \
            + kb[r, 2] - low[2]
    srt = np.argsort(key, kind="mergesort")
    starts = np.empty(nk, np.int64)
    counts = np.empty(nk, np.int64)
    nb = 0
    for r in range(nk):
        if r == 0 or key[srt[r]] != key[srt[r - 1]]:
            starts[nb] = r
            nb += 1
    tie = np.empty(nb)
    for b in range(nb):
        counts[b] = (starts[b + 1] if b + 1 < nb else nk) - starts[b]
        low_rank = np.inf
        for r in range(starts[b], starts[b] + counts[b]):
            low_rank = min(low_rank, rank[srt[r]])
        tie[b] = low_rank / (1.0 + low_rank)        # in [0, 1): orders equal counts
    top = np.argsort(tie - counts[:nb], kind="mergesort")[:max_bins]
    best = counts[top[0]]
    n_cand = 0
    for n_done in range(top.size):
        first, count = starts[top[n_done]], counts[top[n_done]]
        if n_cand and count < max(min_votes, 0.2 * best):
            break
        if n_done >= top_bins and count < 0.5 * best:
            break
        s, c, xs, ys = 0.0, 0.0, np.empty(count), np.empty(count)
        for r in range(count):
            h = srt[first + r]
            s += math.sin(hyp[h, 0])
            c += math.cos(hyp[h, 0])
            xs[r], ys[r] = hyp[h, 1], hyp[h, 2]
        yaw = math.atan2(s, c)
        xs.sort()
        ys.sort()
        tx = 0.5 * (xs[(count - 1) // 2] + xs[count // 2])          # medians
        ty = 0.5 * (ys[(count - 1) // 2] + ys[count // 2])
        if _near_any(tx, ty, yaw, poses, n_cand, _SAME_BIN[0], _SAME_BIN[1]):
            continue   # a neighbouring bin of a pose already verified
        found, x, y, yaw, pairs, score, rms, missing = _verify(
            qc, yaw, complex(tx, ty), gates, lights_c, vis, grid)
        if not found or _near_any(x, y, yaw, poses, n_cand, _SAME_POSE[0], _SAME_POSE[1]):
            continue
        n_cand = _store(poses, all_pairs, offsets, n_cand, (x, y, yaw, score, rms, missing),
                        pairs)
    return poses[:n_cand].copy(), all_pairs[:offsets[n_cand]].copy(), \
        offsets[:n_cand + 1].copy()


@njit
def _store(poses, all_pairs, offsets, n_cand, row, pairs):  # pragma: no cover - compiled
    """Candidate ``n_cand`` written: its ``row`` ``(x, y, yaw, score, rms, missing)``
    into ``poses``, its ``pairs`` ``(K, 2)`` after the previous ones in ``all_pairs``
    (``offsets`` updated); returns ``n_cand + 1``."""
    poses[n_cand, 0], poses[n_cand, 1], poses[n_cand, 2] = row[0], row[1], row[2]
    poses[n_cand, 3], poses[n_cand, 4], poses[n_cand, 5] = row[3], row[4], row[5]
    k = pairs.shape[0]
    all_pairs[offsets[n_cand]:offsets[n_cand] + k] = pairs
    offsets[n_cand + 1] = offsets[n_cand] + k
    return n_cand + 1


@njit
def _twins(qc, starts, gates, min_inliers, lights_c, vis, grid
           ):  # pragma: no cover - compiled
    """:meth:`PatternMatcher.twins` in a compiled call: ``(poses (C, 6), pairs (P, 2),
    offsets (C + 1,))`` as :func:`_match` gives them."""
    cap = max(1, starts.shape[0])
    poses = np.empty((cap, 6))
    offsets = np.zeros(cap + 1, np.int64)
    all_pairs = np.empty((cap * max(qc.size, 1), 2), np.int64)
    n_cand = 0
    for r in range(starts.shape[0]):
        found, x, y, yaw_v, pairs, score, rms, missing = _verify(
            qc, starts[r, 2], complex(starts[r, 0], starts[r, 1]), gates, lights_c, vis,
            grid)
        if not found or pairs.shape[0] < min_inliers:
            continue
        if _near_any(x, y, yaw_v, poses, n_cand, _SAME_POSE[0], _SAME_POSE[1]):
            continue
        n_cand = _store(poses, all_pairs, offsets, n_cand,
                        (x, y, yaw_v, score, rms, missing), pairs)
    return poses[:n_cand].copy(), all_pairs[:offsets[n_cand]].copy(), \
        offsets[:n_cand + 1].copy()


def map_symmetries(lights_w: np.ndarray, gate_m: float, min_lights: int,
                   turns: int = 4, max_lights: int = SYMMETRY_MAX_LIGHTS) -> np.ndarray:
    """``(K, 3)`` rows ``(turn, tx, ty)``: the rigid motions ``p -> Rz(turn) p + t``,
    ``turn`` a multiple of a quarter turn (``k < turns``), that put at least
    ``min_lights`` of the map's lights on lights of the map (within ``gate_m``), the
    identity left out: a regular grid's cells and half (or quarter) turns, and the
    chance coincidences of a few lights of an irregular map. A pose ``(x, y, yaw)``
    matched to the map has a twin ``(Rz(turn) (x, y) + t, yaw + turn)`` for each
    (:func:`twin_poses`).

    Every light taken onto every light gives a translation per turn; the translations
    are binned at ``2 gate_m`` on four grids half a bin apart (a cluster narrower than
    ``gate_m`` lies whole in a bin of one of them), and a bin holding ``min_lights``
    of them is one motion (their mean), a motion found twice kept once. Maps of more
    than ``max_lights`` lights are not searched (``(0, 3)``: their twins are only the
    ones the vote verifies).
    """
    L = np.asarray(lights_w, float).reshape(-1, 2)
    m = L.shape[0]
    if m < max(2, min_lights) or m > max_lights:
        return np.zeros((0, 3))
    size = 2.0 * gate_m
    rows: list[np.ndarray] = []
    for k in range(turns):
        turn = 0.5 * math.pi * k
        c, s = math.cos(turn), math.sin(turn)
        RL = L @ np.array([[c, s], [-s, c]])
        t = (L[None, :, :] - RL[:, None, :]).reshape(-1, 2)
        means: list[np.ndarray] = []
        for sx, sy in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
            kx = np.floor(t[:, 0] / size + sx).astype(np.int64)
            ky = np.floor(t[:, 1] / size + sy).astype(np.int64)
            key = (kx - kx.min()) * (int(ky.max() - ky.min()) + 1) + (ky - ky.min())
            order = np.argsort(key, kind="stable")
            ks = key[order]
            starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
            counts = np.diff(np.r_[starts, ks.size])
            sums = np.add.reduceat(t[order], starts, axis=0)
            good = counts >= min_lights
            means.append(sums[good] / counts[good, None])
        tt = np.concatenate(means)
        if k == 0:
            tt = tt[np.hypot(tt[:, 0], tt[:, 1]) >= gate_m]        # the identity
        if tt.shape[0] == 0:
            continue
        # one motion per cluster of means (the four grids find most twice or more)
        keep = np.ones(tt.shape[0], bool)
        for i, j in sorted(cKDTree(tt).query_pairs(gate_m)):
            if keep[i]:
                keep[j] = False
        tt = tt[keep]
        rows.append(np.column_stack([np.full(tt.shape[0], turn), tt]))
    return np.concatenate(rows) if rows else np.zeros((0, 3))


def symmetry_table(lights_w: np.ndarray, symmetries: np.ndarray, gate_m: float
                   ) -> np.ndarray:
    """``(K, M)`` bool: which map lights each symmetry (:func:`map_symmetries`) puts on
    a light of the map (within ``gate_m``). A pose's twin under symmetry ``k`` can
    explain the spots the pose matched to lights ``i`` only where ``table[k, i]``."""
    L = np.asarray(lights_w, float).reshape(-1, 2)
    out = np.zeros((symmetries.shape[0], L.shape[0]), bool)
    if out.size == 0:
        return out
    tree = cKDTree(L)
    for k, (turn, tx, ty) in enumerate(symmetries):
        c, s = math.cos(turn), math.sin(turn)
        d, _ = tree.query(L @ np.array([[c, s], [-s, c]]) + (tx, ty),
                          distance_upper_bound=gate_m)
        out[k] = np.isfinite(d)
    return out


def twin_poses(symmetries: np.ndarray, x_m: float, y_m: float, yaw_rad: float
               ) -> np.ndarray:
    """``(K, 3)`` the twins ``(x, y, yaw)`` of a pose under the map's symmetries
    (:func:`map_symmetries`): ``(Rz(turn) (x, y) + t, yaw + turn)``."""
    turn = symmetries[:, 0]
    c, s = np.cos(turn), np.sin(turn)
    return np.stack([c * x_m - s * y_m + symmetries[:, 1], s * x_m + c * y_m + symmetries[:, 2],
                     yaw_rad + turn], axis=1)


@njit
def _near_any(x, y, yaw, poses, n, pos_m, max_yaw):  # pragma: no cover - compiled
    """Whether ``(x, y, yaw)`` lies within ``pos_m`` and ``max_yaw`` of one of the first
    ``n`` rows of ``poses`` (:func:`near_pose`)."""
    for c in range(n):
        d_yaw = (yaw - poses[c, 2] + math.pi) % (2.0 * math.pi) - math.pi
        if math.hypot(x - poses[c, 0], y - poses[c, 1]) < pos_m and abs(d_yaw) < max_yaw:
            return True
    return False


@warmer
def _warm() -> None:
    q = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.5]])
    m = PatternMatcher(q, 0.1)        # (with a visibility table: the same types)
    m.match(q)
    m.verify(q, 0.0, np.zeros(2))
    m.twins(q, np.zeros((1, 3)), 0.2, 3)
    m.associate(q, 0.0, np.zeros(2), 0.1)
    _unmatched_seen(arr(np.zeros(3), np.float64), arr(np.zeros(1), np.int64), m._map[0],
                    m._vis, m._grid, 1.0)
    # the constellations' vote takes its poses from Python (read-only arrays)
    _vote(_complex(q), arr(np.zeros((1, 3)), np.float64), arr(np.zeros(1), np.float64),
          m._map[0], m._hash_params, m._vis, m._grid)


__all__ = ["FIRST_ANCHORS", "LOCAL_FROM_LIGHTS", "MISSING_PENALTY", "PAIR_VOTE_MAX_PAIRS",
           "SETTLED_SHARE", "Candidate", "PatternMatcher", "map_symmetries", "near_pose",
           "symmetry_table", "twin_poses", "view_reach_m"]
