"""Pieces of a survey joined by closures singled out against the whole other piece.

A drive whose chain broke leaves *pieces*: segments (:mod:`~ceilkit.calib.survey_chain`)
that no link, gap or closure ties together. A closure between two keyframes needs
:data:`~ceilkit.calib.survey_places.MIN_INLIERS` points because a repeat of the ceiling
beyond one view (light panels on a lattice) cannot be seen within the pair. Here a
keyframe of one piece is matched instead against the *whole other piece*: every
keyframe of it put in the piece's frame (its first frame's V) by its chain, their
features merged (:func:`~ceilkit.runtime.estimators.texture.ceilmap.merge_features`),
so that the rival motion is searched over every place of the piece (each point's
:data:`PIECE_KNN` nearest descriptors, :data:`PIECE_SAMPLES` hypotheses), and the
chance minimum (:func:`~ceilkit.calib.survey_places.min_inliers`) counts the piece's
features over the area its views cover. Such a match may still be a repeat of the
piece outside it, so two pieces are joined only when closures from two keyframes or
more agree on where one piece lies in the other, within their 1σ (a chi-square test,
the chains' drift between the keyframes included), and the separate features they
agree on together reach a closure's floor (``MIN_INLIERS``) and the chance minimum of
all their keyframes' features. Two such sets that share no closure join nothing
(``ambiguous``). The joins are links of kind ``piece``.

Example::

    links, refused = piece_closures(segments, keys_of, places, offset, links, rng)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.texture.ceilmap import merge_features

from .survey_chain import Segment
from .survey_graph import compose, relative
from .survey_places import (
    MIN_INLIERS,
    RESOLUTION_M,
    Place,
    feature_count,
    match_places,
    min_inliers,
)

PIECE_KNN = 4
"""Candidates per point in the piece (a feature seen from several keyframes keeps up to
four descriptors: two would often both be the same feature, hiding its repeats)."""
PIECE_SAMPLES = 3000
"""RANSAC hypotheses per piece match (the piece's candidates are mostly other places);
the chance minimum counts them."""
AGREE_CHI2 = 16.27
"""Two closures agree when their difference's chi-square (3 degrees of freedom) is
under this: 0.1 % of agreeing closures would be refused."""
CELL_M = 0.1              # the raster cell that measures a piece's covered area, m


@dataclass(frozen=True, eq=False)
class PieceMap:
    """A piece's features in its frame: ``place`` (merged over its keyframes),
    ``area_m2`` the area its keyframes' views cover."""

    place: Place
    area_m2: float


@dataclass(frozen=True, eq=False)
class _Closure:
    """A keyframe ``a`` (position in its segment) of one piece placed in the other's
    frame: ``z`` (m, m, rad), ``cov``; ``points``: its agreeing points in its own
    piece's frame (m); ``near``: the other piece's keyframe nearest to it; ``inliers``,
    ``runner_up``: the match's support; ``seen``: all its points in its piece's frame."""

    a: int
    z: np.ndarray
    cov: np.ndarray
    points: np.ndarray
    near: int
    inliers: int
    runner_up: int
    seen: np.ndarray


def _in_frame(pose: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points ``(N, 2)`` in the V of ``pose`` put in the frame ``pose`` is given in."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pts @ np.array([[c, s], [-s, c]]) + pose[:2]


def piece_map(seg: Segment, keys: np.ndarray, places: Sequence[Place]) -> PieceMap:
    """The features of a segment's keyframes (positions ``keys``, their ``places``)
    in the segment's frame, merged, and the area their views cover (m²)."""
    pts = [_in_frame(seg.chain[k], pl.points_v) for k, pl in zip(keys, places, strict=True)]
    allp = np.concatenate(pts) if pts else np.zeros((0, 2))
    desc = np.concatenate([pl.descriptors for pl in places]) if places else \
        np.zeros((0, 32), np.uint8)
    views = np.repeat(np.arange(len(pts)), [len(p) for p in pts])
    q, d, _ = merge_features(allp, desc, views, RESOLUTION_M, min_views=1)
    if len(allp) < 3:
        return PieceMap(Place(q, d), 0.0)
    lo = allp.min(0)
    shape = tuple(int(v) + 1 for v in np.ceil((allp.max(0) - lo) / CELL_M))[::-1]
    grid = np.zeros(shape, np.uint8)
    for p in pts:
        if len(p) >= 3:
            hull = cv2.convexHull(np.round((p - lo) / CELL_M).astype(np.int32))
            cv2.fillConvexPoly(grid, hull, 1)
    return PieceMap(Place(q, d), float(np.count_nonzero(grid)) * CELL_M ** 2)


def _chain_cov(seg: Segment, i: int, j: int) -> np.ndarray:
    """The covariance of the chain's motion between positions ``i`` and ``j`` (its steps
    composed, independent), in the earlier one's V."""
    i, j = min(i, j), max(i, j)
    pose, cov = np.zeros(3), np.zeros((3, 3))
    for e in seg.steps[i:j]:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        zx, zy = e.z[0], e.z[1]
        j1 = np.array([[1, 0, -s * zx - c * zy], [0, 1, c * zx - s * zy], [0, 0, 1.0]])
        j2 = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        cov = j1 @ cov @ j1.T + j2 @ e.cov @ j2.T
        pose = compose(pose, e.z)
    return cov


def _rotated(cov: np.ndarray, yaw: float) -> np.ndarray:
    """A pose covariance given in a frame turned by ``yaw``, in the outer frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return r @ cov @ r.T


def agree(ci: _Closure, cj: _Closure, seg: Segment, other: Segment) -> bool:
    """Whether closure ``cj`` is where closure ``ci`` and the chains put it, within the
    1σ of both, the chain's drift between their keyframes in ``seg`` and between the
    keyframes of ``other`` they fell near (chi-square under :data:`AGREE_CHI2`)."""
    d = relative(seg.chain[ci.a], seg.chain[cj.a])
    pred = compose(ci.z, d)
    c, s = math.cos(ci.z[2]), math.sin(ci.z[2])
    jp = np.array([[1, 0, -s * d[0] - c * d[1]], [0, 1, c * d[0] - s * d[1]], [0, 0, 1.0]])
    first = ci.a if ci.a <= cj.a else cj.a
    drift = _rotated(_chain_cov(seg, ci.a, cj.a), ci.z[2] + seg.chain[first, 2]
                     - seg.chain[ci.a, 2])
    there = _rotated(_chain_cov(other, ci.near, cj.near),
                     other.chain[min(ci.near, cj.near), 2])
    cov = cj.cov + jp @ ci.cov @ jp.T + drift + there
    e = cj.z - pred
    e[2] = math.remainder(e[2], 2 * math.pi)
    return float(e @ np.linalg.solve(cov + np.eye(3) * 1e-12, e)) < AGREE_CHI2


def _beyond_chance(group: list[_Closure], pm: PieceMap) -> bool:
    """Whether a set of agreeing closures from two keyframes or more is more than chance
    and the site's repeats explain: the separate features they agree on, together
    (each feature counted once, however many keyframes saw it), are at least
    :data:`~ceilkit.calib.survey_places.MIN_INLIERS` (a closure's floor) and at least
    what chance gives a wrong motion of all their keyframes' features together
    (:func:`~ceilkit.calib.survey_places.min_inliers` against the piece)."""
    if len({c.a for c in group}) < 2:
        return False
    agreed = feature_count(np.concatenate([c.points for c in group]))
    union = Place(np.concatenate([c.seen for c in group]), np.zeros((0, 32), np.uint8))
    need = min_inliers(pm.place, union, samples=PIECE_SAMPLES, area_m2=pm.area_m2)
    return agreed >= max(MIN_INLIERS, need)


def _closures(seg: Segment, keys: np.ndarray, places: Sequence[Place], target: Segment,
              target_keys: np.ndarray, pm: PieceMap, rng: np.random.Generator
              ) -> list[_Closure]:
    """Each keyframe of ``seg`` matched against the piece map of ``target``: the ones
    singled out against the whole piece."""
    out = []
    tk = target.chain[target_keys, :2]
    for k, pl in zip(keys, places, strict=True):
        m = match_places(pm.place, pl, rng, min_points=0, knn=PIECE_KNN,
                         samples=PIECE_SAMPLES, area_m2=pm.area_m2)
        if not m:
            continue
        near = int(target_keys[np.argmin(np.hypot(*(tk - m.z[:2]).T))])
        out.append(_Closure(int(k), m.z, m.cov, _in_frame(seg.chain[k], m.points_b), near,
                            m.inliers, m.runner_up, _in_frame(seg.chain[k], pl.points_v)))
    return out


def join(closures: list[_Closure], seg: Segment, other: Segment, pm: PieceMap
         ) -> tuple[list[_Closure], str]:
    """The closures that join two pieces (empty, with the reason, when none may): the
    largest set agreeing with one closure that is beyond chance together
    (:func:`_beyond_chance`), unless another such set shares none of it
    (``ambiguous``)."""
    sets = []
    for ci in closures:
        group = [cj for cj in closures if cj is ci or agree(ci, cj, seg, other)]
        if _beyond_chance(group, pm):
            sets.append(group)
    if not sets:
        return [], "too few agreeing features" if closures else "no closure"
    best = max(sets, key=len)
    for g in sets:
        if not any(x in best for x in g):
            return [], "ambiguous"
    return best, ""


def piece_closures(segments: Sequence[Segment], keys_of: Sequence[np.ndarray],
                   places: dict[int, Place], offset: np.ndarray, links: Sequence,
                   rng: np.random.Generator) -> tuple[list[tuple], dict[str, int]]:
    """Joins between the pieces that ``links`` (anything with node numbers ``a``, ``b``)
    leave apart: for each two, the keyframes of the one with fewer matched against the
    other's piece map (module docstring). ``keys_of``: each segment's keyframe
    positions; ``places``: keyframes' places by node (``offset[s]`` + position).

    Returns ``(node a, node b, z, cov, inliers, runner_up)`` per closure (b's pose in
    V_a) and the refused joins by reason (``piece: <reason>``)."""
    seg_of = np.repeat(np.arange(len(segments)), [len(s.frames) for s in segments])
    comp = list(range(len(segments)))

    def root(s: int) -> int:
        while comp[s] != s:
            s = comp[s]
        return s

    for lk in links:
        comp[root(int(seg_of[lk.a]))] = root(int(seg_of[lk.b]))
    out, refused, maps = [], {}, {}
    for s in range(len(segments)):
        for t in range(s + 1, len(segments)):
            if root(s) == root(t) or min(len(keys_of[s]), len(keys_of[t])) < 2:
                continue
            q, m = (s, t) if len(keys_of[s]) <= len(keys_of[t]) else (t, s)
            if m not in maps:
                maps[m] = piece_map(segments[m], keys_of[m], [
                    places[int(offset[m] + k)] for k in keys_of[m]])
            got = _closures(segments[q], keys_of[q],
                            [places[int(offset[q] + k)] for k in keys_of[q]],
                            segments[m], keys_of[m], maps[m], rng)
            chosen, why = join(got, segments[q], segments[m], maps[m])
            if not chosen:
                refused[f"piece: {why}"] = refused.get(f"piece: {why}", 0) + 1
                continue
            comp[root(q)] = root(m)
            for c in chosen:
                base = segments[m].chain[c.near]
                out.append((int(offset[m] + c.near), int(offset[q] + c.a),
                            relative(base, c.z), _rotated(c.cov, -base[2]), c.inliers,
                            c.runner_up))
    return out, refused
