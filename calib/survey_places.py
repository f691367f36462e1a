"""Places: two frames' ceiling features matched by a rigid 2-D fit, accepted only when
the fit is singled out (the survey's loop closures and keyframe links).

A frame's *place* (:func:`place_of`) is its features on the ceiling plane in its vehicle
frame V (the texture method's :func:`~ceilkit.runtime.estimators.texture.ceilmap.rectify`
and :func:`~ceilkit.runtime.estimators.texture.ceilmap.features`: ORB on the rectified
patch, metres in V). :func:`match_places` finds the motion ``z = (dx, dy, dyaw)`` of
place b in V_a (``q_a ~ Rz(dyaw) p_b + (dx, dy)``, the convention of the ceiling-plane
odometry) from descriptor matches, each point's two nearest descriptors (so that the
tile grid's repeats are all candidates, not hidden by a ratio test), by RANSAC over
two-point rigid fits, then a least-squares fit on the inliers.

The match is accepted only when the evidence singles it out: its agreeing points
(within :data:`INLIER_M`) make more separate features than a wrong motion gathers by
chance (:func:`min_inliers`; a closure also :data:`MIN_INLIERS` points), and the best
*other* motion
(RANSAC again over the matches the winner did not explain, a motion at least
:data:`DISTINCT_M` or :data:`DISTINCT_RAD` from the winner: a tile period away, a
half turn) gathers fewer than :data:`RUNNER_UP_SHARE` of the winner's inliers. A
ceiling whose features repeat with the tile grid gives a runner-up as strong as the
winner: that pair is ``ambiguous`` and no edge is made, whatever the drive's chain
suggests (a link's chain may settle it: :func:`chosen_by`). Nor may any rival motion
(:func:`_twin`: the best RANSAC motions, and the winner moved by a's own repeats)
whose like features are more than chance gives (:func:`_beyond_chance`) explain the
features it brings over a's about as well as the winner explains its own: such a pair
is a ``twin`` (a repeated pattern: the twin of larger overlap
would otherwise win), refused too.

Example::

    a, b = place_of(grey_a, rig, 2.7), place_of(grey_b, rig, 2.7)
    m = match_places(a, b, np.random.default_rng(0))
    if m.ok: m.z, m.cov, m.inliers, m.runner_up
    else: m.reason                       # "too few matches", "ambiguous", "twin"
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.special import bdtrc
from scipy.stats import f as fdist
from scipy.stats import hypergeom

from ceilkit.runtime.estimators.texture.ceilmap import features, rectify
from ceilkit.runtime.geometry.ekf import chi2_quantile
from ceilkit.runtime.geometry.fits import fit_rigid_2d

RESOLUTION_M = 0.005
"""Metres per rectified pixel of a place: the office rig's ground pixel at the image
centre (2.2 m / 450 px), so that a keypoint's pixel is a few millimetres."""
HALF_EXTENT_M = 1.2
"""Half the side of a place's patch, m (the office rig sees 1.55 x 1.17 m each side)."""
INLIER_M = 0.015          # a match agrees with a motion within this, m
MIN_INLIERS = 20
"""Fewest agreeing points of a closure (frames anywhere on the drives) beside
:func:`min_inliers`: the site's repeats beyond one view are not in the pair to test. On
the survey drive of ``bench_heldout_texture.py --seed 1`` scatter0 (light panels on a
lattice), 7 of 1000 pairs of frames 3.5 m apart or more matched at the chance minimum
alone, 3.4-5.5 m off (6-9 features, no rival in the view): at 20 points none did. A
*step* (frames a few apart in time, ``min_points=0``) needs the chance minimum only:
its wrong motion would come from a repeat within the view, which the rival test sees
(none of 1,000 step pairs more than 4 mm off, on seeds 1 and 2). Pieces of a drive
that nothing else joins may be joined below it, by matches singled out against the
whole other piece that agree (:mod:`~ceilkit.calib.survey_pieces`)."""
FALSE_MATCH_ALPHA = 1e-4
"""The chance that a wrong motion gathers :func:`min_inliers` features, per pair tried
(a survey tries a few thousand pairs: below one expected by chance, before the rival
test)."""
FEATURE_M = 2 * INLIER_M
"""Points of a place closer than this (m) are counted as one feature by
:func:`min_inliers` (ORB finds one blob at several scales: a sprinkler's 3 points
agree with a wrong motion together or not at all)."""
RUNNER_UP_SHARE = 0.5     # the runner-up's inliers, at most this share of the winner's
DISTINCT_M = 2 * INLIER_M
"""A runner-up differs from the winner by this much (m) or :data:`DISTINCT_RAD`: past
twice the inlier radius a translation shares no inlier with the winner's. (It was
0.05 m: two survey frames 49.997 mm apart matched as a standstill, 46 inliers, and the
true motion (45) was ruled the same one, so no runner-up: 50 mm off at a 1σ of
0.27 mm; issue 39. Now that pair is ``ambiguous``: ORB points along seams parallel to
the travel support a standstill.)"""
DISTINCT_RAD = math.radians(3.0)   # ... or by this turn
RANSAC_SAMPLES = 600
VAR_FLOOR_M = 0.002       # the least 1σ of one point's fit residual, m
DESCRIPTOR_MAX = 80
"""Two ORB descriptors this close (Hamming, of 256 bits) may be one feature: the
candidates' gate, and a twin's test of whether a point lands on a like feature."""
TWIN_ALPHA = 1e-2
"""A rival motion is ruled out when it explains so few of the features it brings over
a's that a rate as high as the winner's gives as few with at most this probability
(:func:`_twin`: one-sided Fisher's exact test). On ``bench_heldout_texture.py --seed 3``'s
repeated control (one tile's scatter on every tile) the twins a tile away read 0.05-1;
on the synthetic panel lattice of ``tests/calib/test_survey_pieces.py`` the rivals
that explain a lattice's corners at a piece's edge and miss its 3 scatter features
read 0.003-0.012 (at 1e-3 they stood, and the pieces were not joined). Not its nominal
rate: the winner is the best of the RANSAC motions, so its rate is biased high, and on
a synthetic tile-period scatter true twins that explain the frame as the winner does
were ruled out at this level in 6-12 % of pairs (review of stop 51); a tile-period
ceiling has many twins, so some stand (every pair of ``--seed 3``'s control was
refused), but a ceiling with a single twin would be matched a period off in about as
many pairs. A held-out rate (the winner's on points it was not chosen on) is the
next step."""
RIVAL_ALPHA = 1e-2
"""A rival motion's agreement is evidence (:func:`_beyond_chance`) when the wrong
motions tried gather as many like features by chance with at most this probability: at
most one pair in a hundred has a chance motion counted as a rival, which can only
refuse that pair (a lost closure, never a wrong one), where the 1e-4 of
:data:`FALSE_MATCH_ALPHA` guards an acceptance. (Review of stop 51: a rival was weighed
by :func:`min_inliers`' descriptor-blind chance at 1e-4, and the truth over a small
overlap was no rival.)"""
TWIN_RIVALS = 24          # the RANSAC motions, best first, that a twin test evaluates
SELF_SHIFTS = 8           # ... and a's own repeats, strongest first, moved by
SELF_KNN = 4              # each feature of a's nearest like features, for its repeats
SELF_QUERIES = 1500
"""At most this many of a's features (evenly strided) look for their like features in
the whole of a (:func:`_self_shifts`): a piece map of 20 000 points cost 3.2 s a pair
against all of itself (review of stop 51); a keyframe's 60-300 points are all asked."""
PRIOR_GATE_CHI2 = chi2_quantile(0.999, 3)
"""A prior's gate for :func:`chosen_by`: the chi-square of 3 degrees of freedom at
0.999, 16.27 (a motion as far from the prior as that is ruled out by it)."""
COVER_CELL_M = 0.1
"""The cell of a place's coverage: a point of b over a cell with a feature of a (or
beside one) is in the views' overlap, where a twin must explain it."""


@dataclass(frozen=True, eq=False)
class Place:
    """A frame's features on the ceiling plane: ``points_v`` ``(N, 2)`` in V (m),
    ``descriptors`` ``(N, 32)`` uint8 (ORB)."""

    points_v: np.ndarray
    descriptors: np.ndarray


@dataclass(frozen=True, eq=False)
class PlaceMatch:
    """The result of :func:`match_places`; falsy when not accepted (``reason`` says
    why). ``z``: place b's pose in V_a (m, m, rad), ``cov`` its ``(3, 3)``
    covariance; ``inliers``: the winner's agreeing points; ``runner_up``: the best
    other motion's (0 when none); ``rms_m``: the winner's residual RMS; ``features``:
    the winner's agreeing points counted as separate features (:data:`FEATURE_M`),
    ``min_features`` the fewest that chance does not explain (:func:`min_inliers`),
    ``runner_features`` the runner-up's agreeing points as features; ``points_b``: the
    winner's agreeing points of b, ``(n, 2)`` in V_b (m). A ``twin`` refusal keeps the
    winner's ``z``, ``cov`` and ``points_b`` and gives the motions that stood beside it
    in ``twins`` (each fitted on the points it explains, as an accepted match), for a
    prior to choose among (:func:`chosen_by`)."""

    ok: bool
    reason: str
    z: np.ndarray | None = None
    cov: np.ndarray | None = None
    inliers: int = 0
    runner_up: int = 0
    rms_m: float = float("nan")
    features: int = 0
    min_features: int = 0
    runner_features: int = 0
    points_b: np.ndarray | None = None
    twins: tuple[PlaceMatch, ...] = ()

    def __bool__(self) -> bool:
        return self.ok


def place_of(grey: np.ndarray, rig, ceiling_height_m: float,
             resolution_m: float = RESOLUTION_M, half_extent_m: float = HALF_EXTENT_M
             ) -> Place:
    """The place of a grey frame (see the module docstring)."""
    patch, valid = rectify(grey, rig, ceiling_height_m, resolution_m, half_extent_m)
    q, d = features(patch, valid, resolution_m)
    return Place(np.asarray(q, float), np.asarray(d, np.uint8))


def feature_count(points: np.ndarray) -> int:
    """The separate features among ``points`` ``(N, 2)`` (m): groups of points linked
    by gaps under :data:`FEATURE_M`."""
    pts = np.unique(np.asarray(points, float).reshape(-1, 2), axis=0)
    return int(feature_labels(pts).max(initial=-1)) + 1


def feature_labels(points: np.ndarray) -> np.ndarray:
    """``(N,)`` each point's feature (:func:`feature_count`'s groups), numbered from 0."""
    pts = np.asarray(points, float).reshape(-1, 2)
    if len(pts) < 2:
        return np.arange(len(pts))
    pairs = cKDTree(pts).query_pairs(FEATURE_M, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(pts), len(pts)))
    return connected_components(graph, directed=False)[1]


@functools.lru_cache(maxsize=256)      # a keyframe's place is in several pairs
def _features(place: Place) -> int:
    """:func:`feature_count` of a place's points."""
    return feature_count(place.points_v)


@functools.lru_cache(maxsize=256)
def _labels(place: Place) -> np.ndarray:
    """:func:`feature_labels` of a place's points."""
    return feature_labels(place.points_v)


def min_inliers(a: Place, b: Place, alpha: float = FALSE_MATCH_ALPHA, *,
                samples: int = RANSAC_SAMPLES, area_m2: float | None = None) -> int:
    """The fewest separate features (:func:`feature_count`) of b that must agree with a
    motion before chance is ruled out, at false-match probability ``alpha``.

    Under a wrong motion a feature of b lands within :data:`INLIER_M` of one of a's
    ``F_a`` features with probability at most ``p = F_a pi r^2 / A`` (``A``: the area
    of the convex hull of a's points, m²; as if any of a's features could be its match,
    whatever the descriptors say: the tile grid's corners and a ceiling's identical
    sprinklers do look alike). A RANSAC hypothesis explains its two sample features,
    and each of the other ``F_b - 2`` by chance: the minimum is the least ``n`` with
    ``RANSAC_SAMPLES * P(Binomial(F_b - 2, p) >= n - 2) <= alpha``. The office drive's
    frames (64-123 ORB points in 18-36 features) need 8-9; a frame whose features
    cover more of the ceiling needs more (a wrong motion meets more by chance). On the
    survey drive of ``bench_heldout_texture.py --seed 2`` scatter0 (docs/survey.md) the
    best motion between frames 3.5 m apart or more (1,000 pairs) never passed it, and
    297 of 384 consecutive pairs did, none more than 2.6 mm off. ``samples``: the
    hypotheses tried (:data:`RANSAC_SAMPLES`); ``area_m2``: the area a's features cover
    when not their hull (a piece of a drive: :mod:`~ceilkit.calib.survey_pieces`).
    Returns a number above ``F_b`` when no count could rule chance out."""
    fa, fb = _features(a), _features(b)
    if len(a.points_v) < 3 or fb < 3:
        return fb + 1
    return _chance_need(fb, _chance_p(a, fa, area_m2), samples, alpha)


def _chance_p(a: Place, fa: int, area_m2: float | None) -> float:
    """The chance that a wrong motion brings one feature of b onto one of a's ``fa``
    (:func:`min_inliers`)."""
    area = area_m2 if area_m2 is not None else \
        cv2.contourArea(cv2.convexHull(a.points_v.astype(np.float32)))
    return min(1.0, fa * math.pi * INLIER_M ** 2 / max(area, 1e-12))


def _chance_need(fb: int, p: float, samples: int, alpha: float) -> int:
    """The least count of ``fb`` features that ``samples`` wrong motions, each bringing a
    feature on one of a's with probability ``p``, reach with at most ``alpha``
    (:func:`min_inliers`); ``fb + 1`` when none."""
    if fb < 3:
        return fb + 1
    n = np.arange(3, fb + 1)
    tail = samples * bdtrc(n - 3, fb - 2, p)      # P(X > n - 3)
    ok = np.flatnonzero(tail <= alpha)
    return int(n[ok[0]]) if ok.size else fb + 1


def _candidates(a: Place, b: Place, k: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(q_a (M, 2), p_b (M, 2))``: for every point of b its ``k`` nearest descriptors
    in a (Hamming)."""
    if len(a.descriptors) < k or len(b.descriptors) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(b.descriptors, a.descriptors, k=k)
    pairs = [(m.trainIdx, m.queryIdx) for ms in knn for m in ms
             if m.distance <= DESCRIPTOR_MAX]
    if not pairs:
        return np.zeros((0, 2)), np.zeros((0, 2))
    ia, ib = np.array(pairs).T
    return a.points_v[ia], b.points_v[ib]


def _hypotheses(q: np.ndarray, p: np.ndarray, rng: np.random.Generator,
                samples: int = RANSAC_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Two-point rigid motions ``(K,)`` yaw and ``(K, 2)`` t from ``samples`` random
    pairs of matches, those whose lengths agree."""
    m = len(q)
    i = rng.integers(0, m, samples)
    j = rng.integers(0, m, samples)
    dq, dp = q[j] - q[i], p[j] - p[i]
    lq, lp = np.hypot(*dq.T), np.hypot(*dp.T)
    ok = (i != j) & (lp > 0.1) & (np.abs(lq - lp) < 2 * INLIER_M)
    yaw = np.arctan2(dq[ok, 1], dq[ok, 0]) - np.arctan2(dp[ok, 1], dp[ok, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    pi = p[i[ok]]
    t = q[i[ok]] - np.stack([c * pi[:, 0] - s * pi[:, 1], s * pi[:, 0] + c * pi[:, 1]], 1)
    return yaw, t


def _inliers(q: np.ndarray, p: np.ndarray, yaw: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(K, M)`` bool: which matches each motion explains within :data:`INLIER_M`."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    rx = c * p[None, :, 0] - s * p[None, :, 1] + t[:, None, 0] - q[None, :, 0]
    ry = s * p[None, :, 0] + c * p[None, :, 1] + t[:, None, 1] - q[None, :, 1]
    return rx * rx + ry * ry <= INLIER_M ** 2


def _count(mask: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(K,)`` the points of b each motion explains, a point once however many of its
    candidates agree (rows of ``mask`` ``(K, M)`` over the candidates, ``p`` their
    points of b). (Until 2026-12-07 a point counted only when its *first* candidate
    agreed: a point whose second-nearest descriptor was the right feature was not an
    inlier, and on a repeated scatter, every candidate a copy, the truth's count was
    chance's.)"""
    key = np.round(p[:, 0] * 1e5) * 1e6 + np.round(p[:, 1] * 1e5)
    _, inverse = np.unique(key, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(inverse[order]) != 0])
    if mask.shape[1] == 0:
        return np.zeros(len(mask), int)
    return np.count_nonzero(np.logical_or.reduceat(mask[:, order], starts, axis=1), axis=1)


def _best(q: np.ndarray, p: np.ndarray, rng: np.random.Generator,
          samples: int = RANSAC_SAMPLES
          ) -> tuple[float, np.ndarray, np.ndarray, int, tuple] | None:
    """The RANSAC winner: ``(yaw, t, inlier mask, count, every hypothesis as
    (yaws, ts, counts))``, or None."""
    if len(q) < 2:
        return None
    yaw, t = _hypotheses(q, p, rng, samples)
    if yaw.size == 0:
        return None
    mask = _inliers(q, p, yaw, t)
    n = _count(mask, p)
    k = int(np.argmax(n))
    return float(yaw[k]), t[k], mask[k], int(n[k]), (yaw, t, n)


def _refine(q: np.ndarray, p: np.ndarray, yaw: float, t: np.ndarray
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least squares on the inliers, twice: ``(yaw, t, inlier mask)``."""
    keep = _inliers(q, p, np.array([yaw]), t[None])[0]
    for _ in range(2):
        if np.count_nonzero(keep) < 3:
            break
        yaw, t = fit_rigid_2d(p[keep], q[keep])
        keep = _inliers(q, p, np.array([yaw]), np.asarray(t)[None])[0]
    return float(yaw), np.asarray(t, float), keep


def _covariance(q: np.ndarray, p: np.ndarray, yaw: float, t: np.ndarray
                ) -> tuple[np.ndarray, float]:
    """The fit's covariance ``s² (JᵀJ)⁻¹`` (as the odometry's, s floored at
    :data:`VAR_FLOOR_M`) and its residual RMS, m."""
    c, s = math.cos(yaw), math.sin(yaw)
    rp = p @ np.array([[c, s], [-s, c]])
    r = q - (rp + t)
    n = len(q)
    s2 = max(float(np.sum(r * r)) / max(2 * n - 3, 1), VAR_FLOOR_M ** 2)
    J = np.zeros((2 * n, 3))
    J[0::2, 0] = 1.0
    J[1::2, 1] = 1.0
    J[0::2, 2] = -rp[:, 1]
    J[1::2, 2] = rp[:, 0]
    return s2 * np.linalg.inv(J.T @ J), float(np.sqrt(np.mean(np.sum(r * r, 1))))


@dataclass(frozen=True, eq=False)
class _Cover:
    """What a twin test needs of place a: its points' k-d tree, its descriptors' bits,
    and the cells its features cover (:data:`COVER_CELL_M`, each grown by one)."""

    tree: cKDTree
    bits: np.ndarray
    origin: np.ndarray
    cells: np.ndarray
    hull: np.ndarray

    @classmethod
    @functools.lru_cache(maxsize=32)   # noqa: B019 - places are few and kept by the survey
    def of(cls, a: Place) -> _Cover:
        ij = np.floor(a.points_v / COVER_CELL_M).astype(int)
        origin = ij.min(0) - 1
        cells = np.zeros(tuple(ij.max(0) - origin + 2), bool)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                cells[ij[:, 0] - origin[0] + di, ij[:, 1] - origin[1] + dj] = True
        hull = cv2.convexHull(a.points_v.astype(np.float32), clockwise=False)
        return cls(cKDTree(a.points_v), np.unpackbits(a.descriptors, axis=1), origin,
                   cells, hull.reshape(-1, 2).astype(float))

    def seen(self, x: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which points ``x`` ``(N, 2)`` (V_a, m) lie in a's view (the
        hull of its points)."""
        if len(self.hull) < 3:
            return np.zeros(len(x), bool)
        e = np.roll(self.hull, -1, axis=0) - self.hull
        r = x[:, None, :] - self.hull[None]
        return np.all(e[None, :, 0] * r[..., 1] - e[None, :, 1] * r[..., 0] >= 0, axis=1)

    def over(self, x: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which points ``x`` ``(N, 2)`` (V_a, m) lie over a's features."""
        ij = np.floor(x / COVER_CELL_M).astype(int) - self.origin
        inside = np.all((ij >= 0) & (ij < self.cells.shape), axis=1)
        out = np.zeros(len(x), bool)
        out[inside] = self.cells[ij[inside, 0], ij[inside, 1]]
        return out

    def explained(self, x: np.ndarray, bits_b: np.ndarray) -> np.ndarray:
        """``(N,)`` for each point ``x`` (V_a, m), with descriptor bits ``bits_b``
        ``(N, 256)``, the nearest feature of a within :data:`INLIER_M` that looks alike
        (:data:`DESCRIPTOR_MAX`), -1 where none."""
        _, idx = self.tree.query(x, k=4, distance_upper_bound=INLIER_M)
        near = idx < len(self.bits)
        out = np.full(len(x), -1)
        rows, cols = np.nonzero(near)
        if rows.size:
            d = np.count_nonzero(self.bits[idx[rows, cols]] != bits_b[rows], axis=1)
            like = d <= DESCRIPTOR_MAX
            # the first (nearest) like one: rows come in order, their columns by distance
            first = np.unique(rows[like], return_index=True)[1]
            out[rows[like][first]] = idx[rows[like], cols[like]][first]
        return out


@functools.lru_cache(maxsize=32)       # a place (by identity) is matched many times
def _self_shifts(a: Place, limit: int = SELF_SHIFTS) -> np.ndarray:
    """``(K, 2)`` a's repeats: the displacements (V_a, m) from each feature of a to its
    :data:`SELF_KNN` nearest descriptors (within :data:`DESCRIPTOR_MAX`) past
    :data:`DISTINCT_M` that most pairs share, at least three, strongest first (a
    tile-period scatter's period, a grid's pitch)."""
    if len(a.points_v) < SELF_KNN + 1:
        return np.zeros((0, 2))
    query = np.arange(0, len(a.points_v), -(-len(a.points_v) // SELF_QUERIES))
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a.descriptors[query], a.descriptors,
                                                   k=SELF_KNN + 1)
    pairs = np.array([(query[m.queryIdx], m.trainIdx) for ms in knn for m in ms
                      if m.distance <= DESCRIPTOR_MAX and query[m.queryIdx] != m.trainIdx],
                     int).reshape(-1, 2)
    v = a.points_v[pairs[:, 1]] - a.points_v[pairs[:, 0]]
    v = v[np.hypot(*v.T) > DISTINCT_M]
    v = np.concatenate([v, -v])
    if not len(v):
        return np.zeros((0, 2))
    key, count = np.unique(np.round(v / (2 * INLIER_M)).astype(int), axis=0,
                           return_counts=True)
    best = np.argsort(-count, kind="stable")[:limit]
    best = best[count[best] >= 3]
    return key[best] * (2 * INLIER_M)


def _rivals(hypotheses: tuple, yaw: float, t: np.ndarray, a: Place
            ) -> tuple[np.ndarray, np.ndarray, int]:
    """The motions a twin test weighs against the winner ``(yaw, t)``, ``(yaws (R,),
    ts (R, 2), tries)``: the winner moved by each of a's own repeats
    (:func:`_self_shifts`), and the best :data:`TWIN_RIVALS` of the winner's RANSAC
    motions (``hypotheses``: ``(yaws, ts, counts)``) distinct from it, the strongest of
    each cell of :data:`DISTINCT_M` x :data:`DISTINCT_RAD`. ``tries``: the distinct
    motions they were chosen from (the cells of every hypothesis, and a's repeats), the
    draws a rival's agreement is the best of (:func:`_beyond_chance`)."""
    shifts = _self_shifts(a)
    yaws, ts, counts = hypotheses
    cell_all = np.c_[np.floor(ts / DISTINCT_M),
                     np.floor(np.mod(yaws, 2 * math.pi) / DISTINCT_RAD)]
    tries = len(np.unique(cell_all, axis=0)) + len(shifts)
    dyaw = np.abs((yaws - yaw + math.pi) % (2 * math.pi) - math.pi)
    far = (dyaw > DISTINCT_RAD) | (np.hypot(*(ts - t).T) > DISTINCT_M)
    yaws, ts, counts, cell = yaws[far], ts[far], counts[far], cell_all[far]
    order = np.lexsort((-counts, *cell.T[::-1]))      # by cell, strongest first in each
    first = order[np.r_[True, np.any(np.diff(cell[order], axis=0) != 0, axis=1)]] \
        if len(order) else order
    top = first[np.argsort(-counts[first], kind="stable")[:TWIN_RIVALS]]
    return (np.r_[np.full(len(shifts), yaw), yaws[top]],
            np.r_[t + shifts.reshape(-1, 2), ts[top].reshape(-1, 2)], tries)


def _twin(a: Place, b: Place, hypotheses: tuple, yaw: float, t: np.ndarray, samples: int,
          area_m2: float | None) -> tuple[int, int, list[PlaceMatch]]:
    """The rivals that the pair does not rule out: ``(the strongest's explained
    features, its explained points, every standing rival fitted as a match)``,
    ``(0, 0, [])`` when every rival is ruled out or is no rival.

    Each motion is weighed by the features of b it brings over a's (:class:`_Cover`)
    and how many of those land on a like feature of a. A rival *stands* (the pair is a
    ``twin``) when its agreement is evidence and the pair does not rule it out:

    * *evidence* (:func:`_beyond_chance`): its like features are more than the wrong
      motions tried gather by chance at :data:`RIVAL_ALPHA`, each feature at its own
      chance (how many of a's features look like it), two given to the motion (drawn
      to explain them). Three of three alike over a 0.3 m overlap, each at 1.9e-4 (its
      one like feature of a in 3.7 m²), 6 distinct motions tried: 1.1e-3, evidence. A
      motion that brings 1-2 features, or explains only the two it was drawn on, is
      evidence of nothing: no rival, whatever else;
    * *ruled out* (:func:`_rate_below`, one-sided Fisher's exact test at
      :data:`TWIN_ALPHA`): its rate over the features it brings over a's is below the
      winner's (0 of 8 against 30 of 32 reads 5.9e-7; 3 of 3 and 6 of 8 read 1 and
      0.17: not). A rival whose agreement beats chance only through the descriptors
      (fewer than :func:`min_inliers`' descriptor-blind count over its overlap: a
      few like features) is weighed as well on every feature it brings into a's view
      (the hull of a's points; not for a piece, ``area_m2``, whose hull is not its
      views): a light panel turned about itself explains its own corners and leaves
      the rest of the view unexplained (ruled out), the truth over a narrow overlap
      brings only what it explains (not).

    Too small an overlap to beat chance is not ruled out: until 2026-12-07 (review of
    stop 51) a rival had to beat the descriptor-blind chance (every feature of a a
    possible match, 600 draws, 1e-4), a bound made to be safe for *accepting* a match,
    so the truth a period away over 0.3-0.4 m (3 of 3, 4 of 4) was set aside and the
    copy of larger overlap accepted 3 m off. A repeat of the ceiling explains its
    overlap as well as the truth does, whatever the views' overlap: the runner-up of
    :func:`match_places` (counted on the matches the winner left) does not see it when
    the descriptors' nearest candidates all point at one copy."""
    cover = _Cover.of(a)
    bits_b = np.unpackbits(b.descriptors, axis=1)
    label = _labels(b)
    yaws, ts, tries = _rivals(hypotheses, yaw, t, a)
    over, on, seen = _weigh(cover, b.points_v, bits_b, np.r_[yaw, yaws],
                            np.r_[t[None], ts])
    f_over, f_hit = _seen(over, label), _seen(on >= 0, label)
    n_over, n_hit, f_seen = f_over.sum(1), f_hit.sum(1), _seen(seen, label)
    rate, blind = _alike_rates(a, b, area_m2), _chance_p(a, _features(a), area_m2)
    own = _own_pairs(on, label, _labels(a))
    own[0] = f_hit[0]
    shared = f_hit & ~own
    view = (own.sum(1), (f_seen & ~shared).sum(1) + _missed(
        a, b, np.r_[yaw, yaws], np.r_[t[None], ts])) if area_m2 is None else None
    win = _fit_on(a.points_v, b.points_v, on[0], yaw, t)
    best, standing = (0, 0), []
    for r in range(1, len(over)):
        if not _beyond_chance(f_over[r], f_hit[r], rate, tries) or \
                _rate_below(n_hit, n_over, r):
            continue
        fit = _fit_on(a.points_v, b.points_v, on[r], yaws[r - 1], ts[r - 1])
        if n_hit[r] < max(3, _chance_need(int(n_over[r]), blind, samples,
                                          FALSE_MATCH_ALPHA)) and (
                _set_aside(f_over[r] & ~shared[r], own[r], rate, tries, view, r)
                or _rougher(fit, int(n_hit[r]), win, int(n_hit[0]))):
            continue        # the winner's own pairs, its view unexplained, or loose
        best = max(best, (int(n_hit[r]), int(np.count_nonzero(on[r] >= 0))))
        if all(_apart(fit.z, o) for o in [np.array([t[0], t[1], yaw]),
                                          *(f.z for f in standing)]):
            standing.append(fit)           # the same twin reached twice counts once
    return best[0], best[1], standing


def _set_aside(over: np.ndarray, own: np.ndarray, rate: np.ndarray, tries: int,
               view: tuple | None, r: int) -> bool:
    """Whether rival ``r``, whose like features are evidence only at their own chance
    (fewer than :func:`min_inliers`' descriptor-blind count), is no twin:

    * *the winner's own match*: its like features beyond those it lands on the same
      feature of a as the winner does (``own`` ``(F_b,)``, of ``over``, the features it
      brings over a's less those shared) are no evidence (:func:`_beyond_chance`). A
      motion 0.02-0.06 m or 2-4 deg from the winner, outside the 3 cm x 3 deg of
      :func:`_apart`, keeps 4-6 of the winner's pairs (the points of a feature along a
      seam or a panel's edge still within :data:`INLIER_M` of its own match) and brings
      no pair of its own: 0 of 7 is evidence of nothing, and a shared pair says the same
      of both motions (it cannot tell them apart). A twin a period off pairs each
      feature it explains with another copy: every pair its own, nothing set aside;
    * *its view unexplained* (``view``: ``(hits (R,), of (R,))``, :func:`_rate_below`
      at :data:`TWIN_ALPHA`): weighed on every place of the shared view, the features
      of b it brings into a's view (the hull of a's points) less those it shares with
      the winner, and the features of a it brings into b's view with no feature of b
      near (:func:`_missed`; such a place holds no feature of b, so it is not counted
      twice). A half turn about a panel explaining 4 of the 6 features of b it brings
      into a's view also brings 8-12 features of a into b's where b shows nothing: 4 of
      16 against the winner's 11 of 12 reads 6.0e-4 (4 of 6 alone 0.25: not ruled
      out). ``None`` for a piece (``area_m2``), whose hull is not its views.

    Weighing only the features a holds once (a tile's or a panel's corners explained
    by every motion mapping the tiles onto themselves) was tried and not kept: on
    ``bench_heldout_texture --seed 1`` scatter0 the rivals' 4-5 like features each have
    2-14 look-alikes in a, and so do most of the winner's, leaving 0-7 features to
    weigh (office 60 m: 148 -> 139 closures)."""
    if not _beyond_chance(over, own, rate, tries):
        return True
    return view is not None and _rate_below(view[0], view[1], r)


def _rougher(fit: PlaceMatch, f: int, win: PlaceMatch, f_win: int) -> bool:
    """Whether a rival's like features (``fit``: fitted on them, ``f`` features) land
    on a's farther than the winner's (``win``, ``f_win``) do: its residual variance
    above the winner's with less than :data:`TWIN_ALPHA` (one-sided F test). Each
    variance is ``n rms^2 / (2n - 3)`` over its ``n`` points (3 of the 2n coordinates
    fitted), its degrees of freedom ``2f - 3`` over features (the points of one
    feature move together: fewer than the points', the test the weaker). A like
    feature of a wrong motion lands anywhere within :data:`INLIER_M` (1.5 cm: an RMS
    of 1.06 cm over the disc), the truth's and a twin's within the points' noise
    (synthetic pairs: 1 mm; the survey's winners on ``bench_heldout_texture --seed 1``
    scatter0: 2.6-6.0 mm RMS over 21-58 points, a blob's points spread): 4 features at
    9.1 mm against 9 at 4.2 mm read F = 7.1 on (5, 15), 1.4e-3 (set aside); at 6.6 mm
    against 10 at 5.3 mm, F = 2.3, 0.09 (not). The truth over a narrow overlap (3 features at the
    points' noise) reads F near 1: not. A rival's residual is after its own fit (3
    of its few coordinates), so this sets few aside: 2 of the 71 rivals it weighed on
    scatter0, 3 closures of 151 on the office drive."""
    d1, d2 = 2 * f - 3, 2 * f_win - 3
    n1, n2 = fit.inliers, win.inliers
    if d1 < 1 or d2 < 1 or n2 < 2 or not (fit.rms_m > 0 and win.rms_m > 0):
        return False
    v1 = n1 * fit.rms_m ** 2 / (2 * n1 - 3)
    v2 = n2 * win.rms_m ** 2 / (2 * n2 - 3)
    return bool(fdist.sf(v1 / v2, d1, d2) < TWIN_ALPHA)


def _own_pairs(on: np.ndarray, label_b: np.ndarray, label_a: np.ndarray) -> np.ndarray:
    """``(R, F_b)`` bool: which features of b each motion pairs (``on`` ``(R, N)``, the
    point of a each point of b lands on, -1 none) with a like feature of a that motion
    0 (the winner) does not pair it with."""
    fa = int(label_a.max(initial=-1)) + 2
    key = np.where(on >= 0, label_b[None] * fa + label_a[np.maximum(on, 0)], -1)
    mine = (on >= 0) & ~np.isin(key, key[0][on[0] >= 0])
    return _seen(mine, label_b)


def _missed(a: Place, b: Place, yaws: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """``(R,)`` under each motion ``(yaws (R,), ts (R, 2))`` (V_b to V_a), the features
    of a it brings into b's view (the hull of b's points, :meth:`_Cover.seen`) with no
    feature of b near (not :meth:`_Cover.over` b's): places b should show and does
    not."""
    cover, label = _Cover.of(b), _labels(a)
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    dx = a.points_v[None, :, 0] - ts[:, None, 0]
    dy = a.points_v[None, :, 1] - ts[:, None, 1]
    x = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=2).reshape(-1, 2)
    near = cover.over(x).reshape(len(yaws), -1)
    seen = cover.seen(x).reshape(len(yaws), -1)
    return (_seen(seen, label) & ~_seen(near, label)).sum(1)


def _rate_below(hit: np.ndarray, of: np.ndarray, r: int) -> bool:
    """Whether motion ``r`` explains ``hit[r]`` of ``of[r]`` features at a rate below
    the winner's (``hit[0]`` of ``of[0]``): a rate as high gives as few with less than
    :data:`TWIN_ALPHA` (one-sided Fisher's exact test)."""
    return bool(hypergeom.cdf(hit[r], of[0] + of[r], hit[0] + hit[r], of[r]) < TWIN_ALPHA)


def _beyond_chance(over: np.ndarray, hit: np.ndarray, rate: np.ndarray, tries: int
                   ) -> bool:
    """Whether a rival's like features (``hit`` ``(F_b,)`` bool, of the features it
    brings over a's, ``over``) are evidence: more than ``tries`` wrong motions gather by
    chance at :data:`RIVAL_ALPHA`, each feature landing on a like feature of a with its
    ``rate`` (:func:`_alike_rates`).

    A RANSAC motion explains the two features it was drawn on (a repeat, the winner's
    agreeing features moved with it), so two are given to it: the two of its hits with
    the *least* chance (the reading that leaves the least evidence). The other ``k``
    hits of its ``n`` features are weighed against ``Binomial(n, p)``, ``p`` their mean
    rate, whose tail beyond the mean bounds the tail of the features' own rates
    (Hoeffding 1956); evidence when ``tries * P(X >= k) <= RIVAL_ALPHA``."""
    k = int(np.count_nonzero(hit)) - 2
    if k < 1:
        return False
    drawn = np.flatnonzero(hit)[np.argsort(rate[hit], kind="stable")[:2]]
    rest = over.copy()
    rest[drawn] = False
    n = int(np.count_nonzero(rest))
    return tries * float(bdtrc(k - 1, n, rate[rest].mean())) <= RIVAL_ALPHA


def _alike_rates(a: Place, b: Place, area_m2: float | None) -> np.ndarray:
    """``(F_b,)`` for each feature of b (:func:`feature_labels`) the chance that a wrong
    motion brings it within :data:`INLIER_M` of a feature of a that looks like it
    (:data:`DESCRIPTOR_MAX`): ``m pi r^2 / A``, ``m`` the features of a with a point
    like one of its points, ``A`` as :func:`min_inliers`' (a's hull, or ``area_m2``). A
    distinctive feature has ``m`` 1 (its own match) or 0; a tile corner, every corner
    of a."""
    la, lb = _labels(a), _labels(b)
    fa = int(la.max(initial=-1)) + 1
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).radiusMatch(b.descriptors, a.descriptors,
                                                      DESCRIPTOR_MAX + 0.5)
    pairs = np.array([(m.queryIdx, m.trainIdx) for ms in knn for m in ms],
                     int).reshape(-1, 2)
    like = np.unique(lb[pairs[:, 0]] * max(fa, 1) + la[pairs[:, 1]])
    m = np.bincount(like // max(fa, 1), minlength=int(lb.max(initial=-1)) + 1)
    return np.minimum(1.0, m * _chance_p(a, 1, area_m2))


def _apart(z_a: np.ndarray, z_b: np.ndarray) -> bool:
    """Whether two motions (m, m, rad) are two (:data:`DISTINCT_M`,
    :data:`DISTINCT_RAD`)."""
    dyaw = abs((z_a[2] - z_b[2] + math.pi) % (2 * math.pi) - math.pi)
    return dyaw > DISTINCT_RAD or float(np.hypot(*(z_a[:2] - z_b[:2]))) > DISTINCT_M


def _weigh(cover: _Cover, pb: np.ndarray, bits_b: np.ndarray, yaws: np.ndarray,
           ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Under each motion ``(yaws (R,), ts (R, 2))``, which points of b lie over a's
    features, ``(R, N)`` bool, the like feature of a each of those lands on,
    ``(R, N)`` (-1 none; :meth:`_Cover.explained`), and which lie in a's view
    (over a's features or in its hull, :meth:`_Cover.seen`), ``(R, N)`` bool."""
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x = np.stack([c * pb[None, :, 0] - s * pb[None, :, 1] + ts[:, None, 0],
                  s * pb[None, :, 0] + c * pb[None, :, 1] + ts[:, None, 1]], axis=2)
    flat = x.reshape(-1, 2)
    over = cover.over(flat).reshape(len(yaws), -1)
    on = np.full(flat.shape[0], -1)
    sel = over.ravel()
    on[sel] = cover.explained(flat[sel], np.tile(bits_b, (len(yaws), 1))[sel])
    return over, on.reshape(len(yaws), -1), (over.ravel() | cover.seen(flat)).reshape(
        len(yaws), -1)


def _seen(mask: np.ndarray, label: np.ndarray) -> np.ndarray:
    """``(R, F)`` bool: which separate features (``label``: each point's,
    :func:`feature_labels`) have a point in each row of ``mask`` ``(R, N)``."""
    n = int(label.max(initial=-1)) + 1
    seen = np.zeros((len(mask), max(n, 1)), bool)
    r, i = np.nonzero(mask)
    seen[r, label[i]] = True
    return seen


def _fit_on(qa: np.ndarray, pb: np.ndarray, on: np.ndarray, yaw: float, t: np.ndarray
            ) -> PlaceMatch:
    """A standing twin as an accepted match: the points of b it explains fitted to the
    like features of a they land on (``on``: a's point per point of b, -1 none)."""
    sel = on >= 0
    if np.count_nonzero(sel) >= 3:
        yaw, t = fit_rigid_2d(pb[sel], qa[on[sel]])
        t = np.asarray(t, float)
    cov, rms = _covariance(qa[on[sel]], pb[sel], float(yaw), t)
    return PlaceMatch(True, "", np.array([t[0], t[1], float(yaw)]), cov,
                      int(np.count_nonzero(sel)), rms_m=rms,
                      features=feature_count(pb[sel]), points_b=pb[sel])


def match_places(a: Place, b: Place, rng: np.random.Generator,
                 min_points: int = MIN_INLIERS, *, knn: int = 2,
                 samples: int = RANSAC_SAMPLES, area_m2: float | None = None
                 ) -> PlaceMatch:
    """Place b's pose in V_a, accepted only when singled out (module docstring), with at
    least ``min_points`` agreeing points (:data:`MIN_INLIERS`: a closure; 0: a step).
    ``knn``: candidates in a per point of b; ``samples``: RANSAC hypotheses, for the
    winner and for the runner-up; ``area_m2``: as :func:`min_inliers` (a's features
    spread over many views: a piece of a drive, :mod:`~ceilkit.calib.survey_pieces`)."""
    q, p = _candidates(a, b, knn)
    need = min_inliers(a, b, samples=samples, area_m2=area_m2)
    win = _best(q, p, rng, samples)
    if win is None or win[3] < max(need, min_points):   # points >= features
        return PlaceMatch(False, "too few matches", inliers=0 if win is None else win[3],
                          min_features=need)
    yaw, t, keep = _refine(q, p, win[0], win[1])
    n, nf = int(_count(keep[None], p)[0]), feature_count(p[keep])
    if nf < need or n < min_points:
        return PlaceMatch(False, "too few matches", inliers=n, features=nf,
                          min_features=need)
    rest = ~keep
    other = _best(q[rest], p[rest], rng, samples)
    runner = runner_f = 0
    if other is not None:
        if _apart(np.r_[other[1], other[0]], np.r_[t, yaw]):
            runner, runner_f = other[3], feature_count(p[rest][other[2]])
    if runner >= RUNNER_UP_SHARE * n:
        return PlaceMatch(False, "ambiguous", inliers=n, runner_up=runner, features=nf,
                          min_features=need, runner_features=runner_f)
    twin_f, twin, twins = _twin(a, b, win[4], yaw, t, samples, area_m2)
    cov, rms = _covariance(q[keep], p[keep], yaw, t)
    if twin_f:
        return PlaceMatch(False, "twin", np.array([t[0], t[1], yaw]), cov, n, twin, rms,
                          nf, need, twin_f, p[keep], tuple(twins))
    return PlaceMatch(True, "", np.array([t[0], t[1], yaw]), cov, n, runner, rms, nf, need,
                      runner_f, p[keep])


def chosen_by(m: PlaceMatch, prior: np.ndarray, prior_cov: np.ndarray,
              gate: float = PRIOR_GATE_CHI2) -> PlaceMatch:
    """A ``twin`` refusal accepted when a prior on the motion (the chain of the
    odometry between the two frames: a measurement, with its covariance) singles out
    one of the winner and its standing twins: that one within ``gate`` (squared
    Mahalanobis distance under the prior's covariance plus the motion's), every other
    beyond it. The one chosen is returned as the match (its own fit; ``runner_up``
    the winner's strongest twin, as refused). Any other match is returned as it is."""
    if m.ok or m.reason != "twin" or m.z is None or m.cov is None:
        return m

    def d2(c: PlaceMatch) -> float:
        e = np.asarray(c.z, float) - prior
        e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
        return float(e @ np.linalg.solve(np.asarray(prior_cov, float) + c.cov, e))

    winner = dataclasses.replace(m, ok=True, reason="", twins=())
    inside = [c for c in (winner, *m.twins) if d2(c) <= gate]
    if len(inside) != 1:
        return m
    return dataclasses.replace(inside[0], runner_up=m.runner_up,
                               runner_features=m.runner_features,
                               min_features=m.min_features)
