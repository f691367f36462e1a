"""Matching a frame's ceiling features to the ceiling map, and the rigid fits they
support: the ``texture`` method's stages between the features and the pose.

Convention: ``q`` are a frame's features in V, ``p`` the map's in W (metres); a fit is
the vehicle pose ``(x, y, yaw)`` with ``p ≈ R(yaw) q + (x, y)`` (SPEC §1), scale fixed
(the plane is metric). Correspondences are index pairs ``(qi, mj)``: each query
feature may have several candidates (its nearest map descriptors), so a repeated
ceiling (a tile grid's seam crossings) gives each twin pose its own consistent subset.

* :class:`DescriptorIndex`: the map's descriptors in an LSH index (FLANN), whose
  query cost grows with the bucket sizes, not the map's area; and a brute-force
  match against the features near a prior (:meth:`DescriptorIndex.near`).
* :func:`ransac_rigid`: two-point samples, pre-checked by the distance they keep, the
  hypothesis with the most query features within ``tol_m``.
* :func:`refine`: least squares on the inliers (one per query feature, the nearest),
  with the covariance ``s² (JᵀJ)⁻¹`` of the fit.

Example::

    index = DescriptorIndex(cmap.points_xy, cmap.descriptors)
    qi, mj, unique = index.match(desc, k=2, max_hamming=64)
    best = ransac_rigid(q[qi], cmap.points_xy[mj], qi, 0.03, 200, rng)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.features.bits import popcount
from ceilkit.runtime.jit import arr, njit, warmer

LSH_TABLES = 16          # hash tables of the descriptor index ...
LSH_KEY_BITS = 16        # ... each keyed by this many of the descriptor's bits
LSH_SEED = 0             # the bits each table reads: drawn from this seed
MIN_PAIR_SEP_M = 0.08    # a two-point sample's points at least this far apart (yaw)
RATIO = 0.8              # distinctive: nearest <= RATIO x the next place's distance
SAME_PLACE_M = 0.03      # two map features this close are one place (not a twin)
REPEAT_ROWS = 128        # DescriptorIndex.repeats: the nearest rows a feature reads ...
REPEAT_MAX = 32          # ... and the most-supported shifts it returns at most
REPEAT_PLACES = 16       # ... or, not exact, the nearest places the global index gives


class DescriptorIndex:
    """The map's binary descriptors, searchable globally (LSH) or near a point.

    The global index is locality-sensitive hashing of the binary descriptors (as
    FLANN's LSH, one probe a table): :data:`LSH_TABLES` tables, each keyed by
    :data:`LSH_KEY_BITS` of the descriptor's bits drawn once (:data:`LSH_SEED`), each
    a sorted array of the map's features by key (a bucket is a slice). A query reads
    its bucket in each table and measures the Hamming distance to the features there
    only (:func:`_lsh_knn`): its cost grows with the buckets' fill, not the map's area.
    A descriptor within ``h`` bits of the query shares a table's key with probability
    ``(1 - h / 256)^16``: 27 % a table at 20 bits, 99.4 % that some table of 16 holds
    it.

    A map feature may hold several descriptors (rows at one point: the feature as
    views unlike each other saw it, :func:`.ceilmap.build_map`); a query's ``k``
    nearest are then ``k`` places, each at its nearest descriptor (:func:`_by_place`),
    so that the ratio test (:func:`distinctive`) weighs the feature against another
    place, never against itself. The global search keeps its list by place as it reads
    the buckets (:func:`_lsh_knn`): on bench_texture's 1,000 m² map (37,980 rows of
    16,837 features) 0.28 ms a frame's 400 queries against 0.77 ms for the nearest
    ``k x`` (most rows a place) rows sorted first and then grouped, the same answer.
    """

    def __init__(self, points_xy: np.ndarray, descriptors: np.ndarray) -> None:
        self.points_xy = np.asarray(points_xy, float)
        self.descriptors = np.ascontiguousarray(descriptors, np.uint8)
        self.tree = cKDTree(self.points_xy) if len(self.points_xy) else None
        self.place, self.rows_per_place = places(self.points_xy)
        self.key_bits = arr(key_bits(self.descriptors), np.int64)
        self._words = arr(_as_words(self.descriptors), np.uint64)
        self._order, self._starts = _lsh_build(self.descriptors, self.key_bits)

    def match(self, desc: np.ndarray, k: int, max_hamming: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(qi, mj, unique)``: each query descriptor's ``k`` nearest map descriptors
        (LSH) within ``max_hamming`` bits; ``unique`` marks a query's nearest pair when
        the match is distinctive (:func:`distinctive`)."""
        if len(self.descriptors) == 0 or len(desc) == 0:
            return _none()
        k = min(max(k, 2), len(self.descriptors))
        desc = np.ascontiguousarray(desc, np.uint8)
        idx, dist = _lsh_knn(arr(desc, np.uint8), arr(_as_words(desc), np.uint64),
                             LshTables(self._words, self.key_bits, self._order, self._starts),
                             self.place, k)
        return self._pairs(idx, dist, max_hamming)

    def near(self, desc: np.ndarray, xy: tuple[float, float], radius_m: float, k: int,
             max_hamming: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`match`, against the map features within ``radius_m`` of ``xy``
        only (brute force over them: the cost of the neighbourhood, not of the map)."""
        if self.tree is None or len(desc) == 0:
            return _none()
        sub = np.asarray(self.tree.query_ball_point(xy, radius_m), int)
        if len(sub) == 0:
            return _none()
        k = min(max(k, 2), len(sub))
        idx, dist = _rows_knn(arr(_as_words(desc), np.uint64), self._words, arr(sub, np.int64),
                              min(k * self.rows_per_place, len(sub)))
        return self._pairs(*_by_place(idx, dist, self.place, k), max_hamming)

    def alike(self, desc: np.ndarray, max_hamming: int, rows: int = 64
              ) -> tuple[np.ndarray, np.ndarray, bool]:
        """``(qi, mj, complete)``: for each query descriptor, every place of the map
        whose nearest descriptor is as near as a match the ratio test cannot tell from
        the query's nearest (within its distance / :data:`RATIO` and ``max_hamming``
        bits), each at that descriptor; brute force over the whole map (exact: no LSH
        miss), the nearest ``rows`` rows a query. ``complete`` is False when some
        query's ``rows``-th row is still that near (its list may miss places)."""
        n = len(self.descriptors)
        if n == 0 or len(desc) == 0:
            return *_none()[:2], True
        kk = min(rows, n)
        idx, dist = _rows_knn(arr(_as_words(desc), np.uint64), self._words,
                              arr(np.arange(n), np.int64), kk)
        bound = np.minimum(dist[:, :1] / RATIO, max_hamming)
        complete = kk == n or bool(np.all(dist[:, -1:] > bound))
        idx, dist = _by_place(idx, dist, self.place, kk)
        qi, col = np.nonzero((idx >= 0) & (dist <= bound))
        return qi.astype(int), idx[qi, col].astype(int), complete

    def repeats(self, mj: np.ndarray, max_hamming: int, least: int = 2,
                rows: int = REPEAT_ROWS, exact: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        """``(shifts (K, 2), support (K,))``: the translations of the map (m, in W)
        under which its features ``mj`` recur, most supported first: another place of
        the map within ``max_hamming`` bits of a feature's descriptor (no ratio test),
        past :data:`SAME_PLACE_M` from it, at that displacement (votes in cells of
        :data:`SAME_PLACE_M`, each counted in its cell and the eight beside it, the
        shift the mean of the votes there); ``support``: how many of ``mj``'s places
        recur so, ``least`` at the fewest. Brute force over the whole map, the nearest
        ``rows`` rows a feature (``exact``), or the global index's nearest
        :data:`REPEAT_PLACES` places (LSH: its cost does not grow with the map): the
        map's own repeats about a pose, which the frame's matches need not show (a
        repeated item surveyed from other views carries other descriptors)."""
        mj = np.unique(self.place[np.asarray(mj, np.int64)])
        n = len(self.descriptors)
        if n < 2 or len(mj) == 0:
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        words = arr(self._words[mj], np.uint64)       # read-only: one type a loop
        if exact:
            idx, dist = _rows_knn(words, self._words, arr(np.arange(n), np.int64),
                                  min(rows, n))
        else:
            idx, dist = _lsh_knn(arr(self.descriptors[mj], np.uint8), words,
                                 LshTables(self._words, self.key_bits, self._order,
                                           self._starts), self.place, min(REPEAT_PLACES, n))
        qi, col = np.nonzero((idx >= 0) & (dist <= max_hamming))
        d = self.points_xy[idx[qi, col]] - self.points_xy[mj[qi]]
        far = np.hypot(*d.T) > SAME_PLACE_M
        qi, d = qi[far], d[far]
        if not len(d):
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        return _vote_shifts(qi, d, least)

    def _pairs(self, idx: np.ndarray, dist: np.ndarray, max_hamming: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ok = (dist <= max_hamming) & (idx >= 0)
        uniq = np.zeros_like(ok)
        if idx.shape[1] >= 2:
            uniq[:, 0] = ok[:, 0] & distinctive(dist, idx, self.points_xy)
        qi, _ = np.nonzero(ok)
        return qi.astype(int), idx[ok].astype(int), uniq[ok]


def _vote_shifts(who: np.ndarray, d: np.ndarray, least: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`DescriptorIndex.repeats`' vote: displacements ``d (V, 2)`` of the
    features ``who (V,)``; ``(shifts (K, 2), support (K,))``: for each cell of
    :data:`SAME_PLACE_M` the distinct features with a vote in it or beside it, those of
    ``least`` or more, most first, no two kept within two cells of each other (at most
    :data:`REPEAT_MAX`), each shift the mean of the votes about its cell. The cells
    whose 3 x 3 block holds ``least`` votes of distinct features per cell are counted
    exactly, the others never reach it (a map that does not repeat costs one sort)."""
    cell = np.round(d / SAME_PLACE_M).astype(np.int64)
    span = int(np.abs(cell).max()) + 2
    side = 2 * span + 1
    code = (cell[:, 0] + span) * side + cell[:, 1] + span
    n_who = int(who.max()) + 1
    ucode, count = np.unique(np.unique(code * n_who + who) // n_who, return_counts=True)
    block = np.zeros(len(ucode), np.int64)
    for off in (a * side + b for a in (-1, 0, 1) for b in (-1, 0, 1)):
        i = np.minimum(np.searchsorted(ucode, ucode + off), len(ucode) - 1)
        block += np.where(ucode[i] == ucode + off, count[i], 0)
    cand = ucode[block >= max(least, 2)]
    at = np.c_[cand // side - span, cand % side - span]
    support = np.array([len(np.unique(who[np.max(np.abs(cell - c), axis=1) <= 1]))
                        for c in at], np.int64)
    kept: list[int] = []
    for k in np.argsort(-support, kind="stable"):
        if support[k] < max(least, 2) or len(kept) == REPEAT_MAX:
            break
        if all(np.max(np.abs(at[k] - at[m])) > 2 for m in kept):
            kept.append(int(k))
    shifts = np.array([d[np.max(np.abs(cell - at[k]), axis=1) <= 1].mean(axis=0)
                       for k in kept]).reshape(-1, 2)
    return shifts, support[kept].astype(np.int64)


def places(points_xy: np.ndarray) -> tuple[np.ndarray, int]:
    """``(place (N,), most)``: for each row of ``points_xy`` the first row at the very
    same point (a map feature's several descriptors share its point), and the most rows
    one point has (1: every row a place of its own)."""
    pts = np.asarray(points_xy, float).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, np.int64), 1
    _, first, inverse, counts = np.unique(pts, axis=0, return_index=True,
                                          return_inverse=True, return_counts=True)
    return arr(first[inverse.ravel()], np.int64), int(counts.max())


@njit
def _by_place(idx, dist, place, k):  # pragma: no cover - compiled
    """``(idx (Q, k), dist (Q, k))`` from nearest-first ``(Q, K)`` candidates: the
    first ``k`` distinct places (:func:`places`), each at its nearest row (-1 and the
    last column's distance where fewer)."""
    q, kk = idx.shape
    out_i = np.full((q, k), -1, np.int64)
    out_d = np.empty((q, k), np.int64)
    for i in range(q):
        n = 0
        for c in range(kk):
            j = idx[i, c]
            if j < 0 or n == k:
                break
            seen = False
            for m in range(n):
                seen = seen or place[out_i[i, m]] == place[j]
            if not seen:
                out_i[i, n], out_d[i, n] = j, dist[i, c]
                n += 1
        for m in range(n, k):
            out_d[i, m] = dist[i, kk - 1] if kk else 0
    return out_i, out_d




def distinctive(dist: np.ndarray, idx: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """``(Q,)``: whether each query's nearest map descriptor (column 0 of ``(Q, k)``
    Hamming distances and map indices, nearest first) singles out one place of the
    map: its distance at most :data:`RATIO` times the second's (Lowe's ratio test), or
    the second at the same place (within :data:`SAME_PLACE_M`). A tile grid's seam
    crossing, or a repeated scatter's item, matches its twins alike: not distinctive.
    (The index is approximate: a twin it misses can make a match look distinctive.)"""
    d0, d1 = dist[:, 0].astype(float), dist[:, 1].astype(float)
    a, b = points_xy[np.maximum(idx[:, 0], 0)], points_xy[np.maximum(idx[:, 1], 0)]
    same = np.hypot(*(a - b).T) < SAME_PLACE_M
    return (d0 <= RATIO * d1) | same | (idx[:, 1] < 0)


def _none() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool)


@dataclass(frozen=True, eq=False)
class RigidFit:
    """A vehicle pose one subset of the correspondences supports.

    Attributes:
        pose: ``(x_m, y_m, yaw_rad)`` in W.
        inliers: ``(M,)`` bool over the correspondences: within the tolerance.
        count: distinct query features among the inliers.
    """

    pose: tuple[float, float, float]
    inliers: np.ndarray
    count: int


def residuals(pose: tuple[float, float, float], q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(M,)`` distances ``|R(yaw) q + (x, y) - p|`` of pairs ``(M, 2)``, m."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.hypot(c * q[:, 0] - s * q[:, 1] + x - p[:, 0],
                    s * q[:, 0] + c * q[:, 1] + y - p[:, 1])


BASIN = (0.1, math.radians(5.0))
"""A pose's RANSAC basin (m, rad): :func:`ransac_rigid` searches a runner-up outside
the best's; two poses within it are one hypothesis."""


def ransac_rigid(q: np.ndarray, p: np.ndarray, qi: np.ndarray, tol_m: float, iters: int,
                 rng: np.random.Generator, avoid: tuple[float, float, float] | None = None,
                 basin: tuple[float, float] = BASIN,
                 exhaustive: bool = False) -> RigidFit | None:
    """The pose with the most distinct query features within ``tol_m`` (two-point RANSAC
    over the correspondences ``q[k] ~ p[k]`` of query ``qi[k]``).

    Up to ``iters`` two-point samples ``(a, b)`` of distinct query features whose
    distance the map keeps (within ``2 tol``) and at least :data:`MIN_PAIR_SEP_M`, from
    ``8 iters`` drawn; each gives the pose mapping ``q[a], q[b]`` onto ``p[a], p[b]``'s
    direction; the one with the most correspondences within ``tol_m`` wins (the first
    such). One compiled loop (:func:`_ransac`) over the draws.

    Args:
        avoid: a pose whose basin (``basin``: metres, radians) is not searched (the
            runner-up's search leaves the best's out).
        exhaustive: every pair of correspondences is a sample (``iters`` and ``rng``
            unused): the pose the most support among those two samples give, for
            certain (for a few dozen correspondences: a pose's twins, ``estimator._twins``).

    Returns:
        The best :class:`RigidFit`, or None with fewer than two usable samples.
    """
    if len(qi) < 2:
        return None
    if exhaustive:
        ab = np.stack(np.triu_indices(len(qi), 1), axis=1)
        iters = len(ab)
    else:
        ab = rng.integers(0, len(qi), size=(8 * iters, 2))
    ax, ay, ayaw = avoid if avoid is not None else (0.0, 0.0, 0.0)
    found, x, y, yaw, inl, count = _ransac(
        Pairs(arr(q, np.float64), arr(p, np.float64), arr(qi, np.int64)), ab,
        Sampling(float(tol_m), int(iters), MIN_PAIR_SEP_M),
        Avoid(avoid is not None, float(ax), float(ay), float(ayaw), float(basin[0]),
              float(basin[1])))
    if not found:
        return None
    return RigidFit((x, y, yaw), inl, count)


class Pairs(NamedTuple):
    """Correspondences as the compiled loops take them: ``q (M, 2)`` in V ~ ``p (M, 2)``
    in W (m), of query features ``qi (M,)``."""

    q: np.ndarray
    p: np.ndarray
    qi: np.ndarray


class Sampling(NamedTuple):
    """:func:`ransac_rigid`'s settings: the inlier tolerance ``tol`` (m), the samples
    ``iters`` and their points' least separation ``min_sep`` (m)."""

    tol: float
    iters: int
    min_sep: float


class Avoid(NamedTuple):
    """A pose whose basin the runner-up's search leaves out (``on``: one is given):
    ``(x, y, yaw)`` and the basin's ``metres`` and ``radians``."""

    on: bool
    x: float
    y: float
    yaw: float
    metres: float
    radians: float


@njit
def _ransac(pairs, ab, sampling, avoid):  # pragma: no cover - compiled
    """:func:`ransac_rigid`'s loop over the drawn index pairs ``ab (S, 2)``: ``(found,
    x, y, yaw, inliers (M,) bool, distinct query features among them)``."""
    q, p, qi = pairs.q, pairs.p, pairs.qi
    tol, iters, min_sep = sampling.tol, sampling.iters, sampling.min_sep
    m = len(qi)
    tol2 = tol * tol
    best, bx, by, byaw, used = -1, 0.0, 0.0, 0.0, 0
    for s in range(len(ab)):
        if used == iters:
            break
        a, b = ab[s, 0], ab[s, 1]
        qx, qy = q[b, 0] - q[a, 0], q[b, 1] - q[a, 1]
        px, py = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1]
        dq, dp = math.hypot(qx, qy), math.hypot(px, py)
        if qi[a] == qi[b] or not dq > min_sep or not abs(dq - dp) < 2 * tol:
            continue
        used += 1
        yaw = math.atan2(qx * py - qy * px, qx * px + qy * py)
        c, sn = math.cos(yaw), math.sin(yaw)
        tx = p[a, 0] - (c * q[a, 0] - sn * q[a, 1])
        ty = p[a, 1] - (sn * q[a, 0] + c * q[a, 1])
        if avoid.on and math.hypot(tx - avoid.x, ty - avoid.y) <= avoid.metres and \
                abs(math.atan2(math.sin(yaw - avoid.yaw), math.cos(yaw - avoid.yaw))) \
                <= avoid.radians:
            continue
        count = 0
        for k in range(m):
            ex = c * q[k, 0] - sn * q[k, 1] + tx - p[k, 0]
            ey = sn * q[k, 0] + c * q[k, 1] + ty - p[k, 1]
            count += ex * ex + ey * ey < tol2
        if count > best:
            best, bx, by, byaw = count, tx, ty, yaw
    inl = np.zeros(m, np.bool_)
    if best < 0:
        return False, 0.0, 0.0, 0.0, inl, 0
    c, sn = math.cos(byaw), math.sin(byaw)
    seen = np.zeros(qi.max() + 1, np.bool_)
    distinct = 0
    for k in range(m):
        ex = c * q[k, 0] - sn * q[k, 1] + bx - p[k, 0]
        ey = sn * q[k, 0] + c * q[k, 1] + by - p[k, 1]
        if ex * ex + ey * ey < tol2:
            inl[k] = True
            if not seen[qi[k]]:
                seen[qi[k]] = True
                distinct += 1
    return True, bx, by, byaw, inl, distinct


def one_per_query(q: np.ndarray, p: np.ndarray, qi: np.ndarray, pose: tuple[float, float, float],
                  tol_m: float) -> np.ndarray:
    """Indices of the correspondences within ``tol_m`` of ``pose``, the nearest one per
    query feature."""
    r = residuals(pose, q, p)
    idx = np.flatnonzero(r < tol_m)
    if len(idx) == 0:
        return idx
    order = idx[np.lexsort((r[idx], qi[idx]))]
    first = np.r_[True, qi[order][1:] != qi[order][:-1]]
    return order[first]


@dataclass(frozen=True, eq=False)
class MapFit:
    """A least-squares pose on its inliers.

    Attributes:
        pose: ``(x_m, y_m, yaw_rad)``.
        cov: ``(3, 3)`` covariance of the pose.
        used: indices of the correspondences used (one per query feature).
        rms_m: RMS residual, m.
        velocity, velocity_sigma: ``(vx m/s, vy m/s, yaw rate rad/s)`` in W and their
            1-sigma when the fit estimated the velocity from the frame's rows
            (:func:`.shutter.joint_fit`); None otherwise.
    """

    pose: tuple[float, float, float]
    cov: np.ndarray
    used: np.ndarray
    rms_m: float
    velocity: tuple[float, float, float] | None = None
    velocity_sigma: tuple[float, ...] | None = None


def refine(q: np.ndarray, p: np.ndarray, qi: np.ndarray | None,
           pose: tuple[float, float, float], tol_m: float, sigma_floor_m: float,
           rounds: int = 2) -> MapFit | None:
    """Least squares (:func:`~ceilkit.runtime.geometry.fits.fit_rigid_2d`) on the
    correspondences within ``tol_m`` of ``pose`` (one per query feature, the nearest;
    ``qi`` None: every pair is its own query feature), the inliers collected again
    about each new pose ``rounds`` times. The covariance is ``s² (JᵀJ)⁻¹`` with ``s²``
    the residuals' variance per axis (``2n - 3`` degrees of freedom), never below
    ``sigma_floor_m²``. None with fewer than three inliers. One compiled loop
    (:func:`_refine`)."""
    has_qi = qi is not None
    qi = arr(qi if has_qi else np.zeros(len(q), np.int64), np.int64)
    good, x, y, yaw, cov, used, rms = _refine(
        Pairs(arr(q, np.float64), arr(p, np.float64), qi), has_qi,
        (float(pose[0]), float(pose[1]), float(pose[2])),
        Fitting(float(tol_m), float(sigma_floor_m), int(rounds)))
    return MapFit((x, y, yaw), cov, used, rms) if good else None


class Fitting(NamedTuple):
    """:func:`refine`'s settings: the inlier tolerance ``tol`` and the covariance's
    floor ``sigma_floor`` (m), the ``rounds`` of collecting the inliers again."""

    tol: float
    sigma_floor: float
    rounds: int


@njit
def _refine(pairs, has_qi, pose, fitting):  # pragma: no cover - compiled
    """:func:`refine` from ``pose (x, y, yaw)``: ``(good, x, y, yaw, cov (3, 3), used
    (indices), rms_m)``; ``has_qi`` False: every pair is its own query feature."""
    q, p, qi = pairs.q, pairs.p, pairs.qi
    x, y, yaw = pose
    tol, sigma_floor = fitting.tol, fitting.sigma_floor
    used = np.zeros(0, np.int64)
    for _ in range(fitting.rounds):
        r = _residuals(q, p, x, y, yaw)
        used = _one_per_query(r, qi, tol) if has_qi else np.flatnonzero(r < tol)
        if len(used) < 3:
            return False, x, y, yaw, np.zeros((3, 3)), used, 0.0
        mask = np.zeros(len(q), np.bool_)
        mask[used] = True
        x, y, yaw = _rigid(q, p, mask)
    c, s = math.cos(yaw), math.sin(yaw)
    n = len(used)
    ss = sx = sy = srr = 0.0
    for k in used:
        rx, ry = c * q[k, 0] - s * q[k, 1], s * q[k, 0] + c * q[k, 1]
        ex, ey = rx + x - p[k, 0], ry + y - p[k, 1]
        ss += ex * ex + ey * ey
        sx += rx
        sy += ry
        srr += rx * rx + ry * ry
    s2 = max(ss / max(2 * n - 3, 1), sigma_floor * sigma_floor)
    jtj = np.array([[n, 0.0, -sy], [0.0, n, sx], [-sy, sx, srr]])
    if not abs(np.linalg.det(jtj)) > 1e-12:
        return False, x, y, yaw, np.zeros((3, 3)), used, 0.0
    return True, x, y, yaw, s2 * np.linalg.inv(jtj), used, math.sqrt(ss / n)


@njit
def _one_per_query(r, qi, tol):  # pragma: no cover - compiled
    """:func:`one_per_query` on the residuals ``r``: the nearest pair within ``tol`` of
    each query feature (the first on a tie), in the order of ``qi``'s values."""
    top = qi.max() + 1 if len(qi) else 0
    best = np.full(top, -1, np.int64)
    for k in range(len(r)):
        if r[k] < tol and (best[qi[k]] < 0 or r[k] < r[best[qi[k]]]):
            best[qi[k]] = k
    return best[best >= 0]


@njit
def _rigid(q, p, mask):  # pragma: no cover - compiled
    """:func:`~ceilkit.runtime.geometry.fits.fit_rigid_2d` of the pairs ``mask`` holds:
    ``(x, y, yaw)`` with ``p ≈ R(yaw) q + (x, y)``."""
    m = qx = qy = px = py = 0.0
    for k in range(len(q)):
        if mask[k]:
            m += 1.0
            qx += q[k, 0]
            qy += q[k, 1]
            px += p[k, 0]
            py += p[k, 1]
    qx, qy, px, py = qx / m, qy / m, px / m, py / m
    sc = sn = 0.0
    for k in range(len(q)):
        if mask[k]:
            ax, ay, bx, by = q[k, 0] - qx, q[k, 1] - qy, p[k, 0] - px, p[k, 1] - py
            sc += ax * bx + ay * by
            sn += ax * by - ay * bx
    yaw = math.atan2(sn, sc)
    c, s = math.cos(yaw), math.sin(yaw)
    return px - (c * qx - s * qy), py - (s * qx + c * qy), yaw


@njit
def _residuals(q, p, x, y, yaw):  # pragma: no cover - compiled
    """``(N,)`` distances ``|R(yaw) q + (x, y) - p|``, m (:func:`residuals`)."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.empty(len(q))
    for k in range(len(q)):
        out[k] = math.hypot(c * q[k, 0] - s * q[k, 1] + x - p[k, 0],
                            s * q[k, 0] + c * q[k, 1] + y - p[k, 1])
    return out


def key_bits(descriptors: np.ndarray, tables: int = LSH_TABLES, bits: int = LSH_KEY_BITS,
             seed: int = LSH_SEED) -> np.ndarray:
    """``(tables, bits)``: the descriptor bits (bit ``b`` is bit ``b % 8`` of byte
    ``b // 8``) each LSH table is keyed by: the ``tables x bits`` bits whose share of
    ones over the map's descriptors is nearest one half (a bit set in nearly every
    descriptor or in none fills one bucket and empties the other), no bit twice,
    dealt to the tables at random (``seed``)."""
    d = np.asarray(descriptors, np.uint8)
    n_bits = 8 * d.shape[1]
    want = min(tables * bits, n_bits)
    ones = np.unpackbits(d, axis=1, bitorder="little").mean(0) if len(d) else \
        np.full(n_bits, 0.5)
    chosen = np.argsort(np.abs(ones - 0.5), kind="stable")[:want]
    chosen = np.random.default_rng(seed).permutation(chosen)
    if want < tables * bits:            # a short descriptor: tables share bits
        chosen = np.resize(chosen, tables * bits)
    return chosen.reshape(tables, bits).astype(np.int64)


def _as_words(desc: np.ndarray) -> np.ndarray:
    """``(N, ceil(D / 8))`` uint64: each descriptor's bytes as words (zero-padded)."""
    d = np.ascontiguousarray(desc, np.uint8)
    if d.shape[1] % 8:
        d = np.ascontiguousarray(np.pad(d, ((0, 0), (0, -d.shape[1] % 8))))
    return d.view(np.uint64).reshape(len(d), d.shape[1] // 8)


def _lsh_build(desc: np.ndarray, key_bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order (T, N), starts (T, 2^K + 1))``: each table's features sorted by key,
    and where each key's bucket starts in that order."""
    keys = _lsh_keys(arr(desc, np.uint8), key_bits)
    order = np.argsort(keys, axis=1, kind="stable")
    n_keys = 1 << key_bits.shape[1]
    starts = np.stack([np.searchsorted(np.take_along_axis(keys[t:t + 1], order[t:t + 1], 1)[0],
                                       np.arange(n_keys + 1)) for t in range(len(keys))])
    return arr(order.astype(np.int32), np.int32), arr(starts.astype(np.int32), np.int32)


@njit
def _lsh_keys(desc, key_bits):  # pragma: no cover - compiled
    """``(T, N)``: each descriptor's key in each table (its bits ``key_bits[t]``, bit
    ``b`` being bit ``b % 8`` of byte ``b // 8``)."""
    out = np.zeros((key_bits.shape[0], desc.shape[0]), np.int64)
    for t in range(key_bits.shape[0]):
        for i in range(desc.shape[0]):
            key = 0
            for j in range(key_bits.shape[1]):
                b = key_bits[t, j]
                key = (key << 1) | ((desc[i, b >> 3] >> (b & 7)) & 1)
            out[t, i] = key
    return out


@njit
def _rows_knn(qwords, words, rows, kk):  # pragma: no cover - compiled
    """``(idx (Q, kk), dist (Q, kk))``: each query's ``kk`` nearest of the map's ``rows``
    (Hamming distance of the descriptors as words, :func:`_as_words`), nearest first,
    ties in ``rows``' order: ``cv2.batchDistance``'s K nearest, the same lists, at about
    half its time (a frame's 97 queries against a window's 373 rows, K 8: 0.19 against
    0.35 ms)."""
    q, nw = qwords.shape
    idx = np.full((q, kk), -1, np.int64)
    dist = np.full((q, kk), 8 * 8 * nw + 1, np.int64)
    for i in range(q):
        for r in range(rows.shape[0]):
            j = rows[r]
            d = 0
            for w in range(nw):
                d += popcount(qwords[i, w] ^ words[j, w])
            if d >= dist[i, kk - 1]:
                continue
            s = kk - 1
            while s > 0 and dist[i, s - 1] > d:
                idx[i, s], dist[i, s] = idx[i, s - 1], dist[i, s - 1]
                s -= 1
            idx[i, s], dist[i, s] = j, d
    return idx, dist


class LshTables(NamedTuple):
    """The global index as the compiled loop takes it: the map's descriptors as words
    ``words (N, W)`` uint64, each table's key bits ``key_bits (T, K)``, its features
    sorted by key ``order (T, N)`` and where each key's bucket starts ``starts (T,
    2^K + 1)`` (:func:`_lsh_build`)."""

    words: np.ndarray
    key_bits: np.ndarray
    order: np.ndarray
    starts: np.ndarray


@njit
def _lsh_knn(desc, words, tables, place, k):  # pragma: no cover - compiled
    """``(idx (Q, k), dist (Q, k))``: each query's ``k`` nearest places (:func:`places`)
    among the map descriptors sharing its bucket in some table, each at its nearest
    descriptor, nearest first (ties by index; -1 and a distance past every descriptor's
    where fewer places share one): what :func:`_by_place` makes of the nearest rows.

    One pass over the buckets, the list kept by place: a row no nearer than the
    ``k``-th place is passed over after its distance, a nearer one moves its place up
    (or takes the last place's slot), so a row met in several tables needs no mark."""
    q, nw = words.shape
    map_words, order, starts = tables.words, tables.order, tables.starts
    idx = np.full((q, k), -1, np.int64)
    dist = np.full((q, k), 8 * 8 * nw + 1, np.int64)
    at = np.full((q, k), -1, np.int64)          # the listed places
    keys = _lsh_keys(desc, tables.key_bits)
    for i in range(q):
        for t in range(keys.shape[0]):
            key = keys[t, i]
            for r in range(starts[t, key], starts[t, key + 1]):
                j = order[t, r]
                d = 0
                for w in range(nw):
                    d += popcount(words[i, w] ^ map_words[j, w])
                if d > dist[i, k - 1] or (d == dist[i, k - 1] and 0 <= idx[i, k - 1] < j):
                    continue
                end = k - 1                     # the slot the row frees: its place's ...
                for m in range(k):
                    if at[i, m] == place[j]:
                        end = m
                        break
                if at[i, end] == place[j] and (dist[i, end] < d or
                                               (dist[i, end] == d and idx[i, end] <= j)):
                    continue                    # ... unless its place has a nearer row
                s = end
                while s > 0 and (dist[i, s - 1] > d or (dist[i, s - 1] == d
                                                         and idx[i, s - 1] > j)):
                    s -= 1
                for m in range(end, s, -1):
                    idx[i, m], dist[i, m], at[i, m] = idx[i, m - 1], dist[i, m - 1], at[i, m - 1]
                idx[i, s], dist[i, s], at[i, s] = j, d, place[j]
    return idx, dist


@warmer
def _warm() -> None:
    d = np.arange(64, dtype=np.uint8).reshape(2, 32)
    index = DescriptorIndex(np.zeros((2, 2)), d)
    index.match(d, 2, 64)
    index.near(d, (0.0, 0.0), 1.0, 2, 64)
    q = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    ransac_rigid(q, q, np.arange(3), 0.03, 4, np.random.default_rng(0), (0.0, 0.0, 0.0))
    refine(q, q, np.arange(3), (0.0, 0.0, 0.0), 0.03, 0.001)
    refine(q, q, None, (0.0, 0.0, 0.0), 0.03, 0.001, 1)


__all__ = ["DescriptorIndex", "distinctive", "MapFit", "RigidFit", "one_per_query", "places",
           "ransac_rigid", "refine", "residuals"]
