"""Pieces of a survey joined by closures singled out against the whole other piece.

A drive whose chain broke leaves *segments* (:mod:`~ceilkit.calib.survey_chain`); a
*piece* is a connected component of them under every accepted link (the chain's steps,
gap matches, loop and drive closures, and the joins made here): :func:`pieces` puts
each piece's frames in one frame (its first node's V) along a spanning tree of those
links, with each frame's pose covariance along it. A closure between two keyframes
needs :data:`~ceilkit.calib.survey_places.MIN_INLIERS` points because a repeat of the
ceiling beyond one view (light panels on a lattice) cannot be seen within the pair.
Here a keyframe of one piece is matched instead against the *whole other piece*: its
keyframes' features merged in its frame
(:func:`~ceilkit.runtime.estimators.texture.ceilmap.merge_features`), so that the rival
motion is searched over every place of the piece (each point's :data:`PIECE_KNN`
nearest descriptors, :data:`PIECE_SAMPLES` hypotheses), and the chance minimum
(:func:`~ceilkit.calib.survey_places.min_inliers`) counts the piece's features over the
area its views cover. Such a match may still be a repeat of the piece outside it, so
two pieces are joined only when closures from two keyframes or more agree on where one
piece lies in the other, within their 1σ (a chi-square test, both pieces' drift
between the keyframes included), and the separate features they agree on together
reach a closure's floor (``MIN_INLIERS``) and the chance minimum of all their
keyframes' features. Two such sets that share no closure join nothing (``ambiguous``).
The joins are links of kind ``piece``; a pair refused is tried again once either piece
has grown by a join. A piece of one keyframe is never joined (one match cannot be
checked by a second): it is said so (``piece apart: one keyframe``).

Example::

    links, refused = piece_closures(segments, keys_of, places, offset, links, rng)
"""

from __future__ import annotations

import itertools
import math
from collections import deque
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
class Piece:
    """Segments tied by accepted links, in one frame (its first node's V).

    Attributes:
        segments: the segments' numbers.
        nodes: ``(n,)`` the graph nodes of their frames.
        poses: ``(n, 3)`` each node's pose in the piece's frame (m, m, rad).
        cov: ``(n, 3, 3)`` its covariance there (the spanning tree's motions composed,
            independent; the first node's is zero).
        parent: ``(n,)`` each node's parent in the spanning tree (position in ``nodes``;
            -1 at the first node); ``depth``: ``(n,)`` its steps from the first node.
        keys: positions in ``nodes`` of the keyframes.
    """

    segments: tuple[int, ...]
    nodes: np.ndarray
    poses: np.ndarray
    cov: np.ndarray
    parent: np.ndarray
    depth: np.ndarray
    keys: np.ndarray


@dataclass(frozen=True, eq=False)
class PieceMap:
    """A piece's features in its frame: ``place`` (merged over its keyframes),
    ``area_m2`` the area its keyframes' views cover."""

    place: Place
    area_m2: float


@dataclass(frozen=True, eq=False)
class _Closure:
    """A keyframe ``a`` (position in its piece) of one piece placed in the other's
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


def _rotated(cov: np.ndarray, yaw: float) -> np.ndarray:
    """A pose covariance given in a frame turned by ``yaw``, in the outer frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return r @ cov @ r.T


def _lever(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How an error of pose ``a`` (x, y, yaw in a frame) moves pose ``b`` reached from
    it by a fixed motion: ``(3, 3)``."""
    return np.array([[1.0, 0, -(b[1] - a[1])], [0, 1.0, b[0] - a[0]], [0, 0, 1.0]])


def _inverse(z: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motion back (``a`` in V_b from ``b`` in V_a) and its covariance."""
    c, s = math.cos(z[2]), math.sin(z[2])
    jac = np.array([[-c, -s, s * z[0] - c * z[1]], [s, -c, c * z[0] + s * z[1]],
                    [0, 0, -1.0]])
    return relative(z, np.zeros(3)), jac @ cov @ jac.T


def _roots(n: int, pairs: Sequence[tuple[int, int]]) -> np.ndarray:
    """``(n,)`` each item's component under the ``pairs`` (its smallest member)."""
    comp = list(range(n))

    def root(s: int) -> int:
        while comp[s] != s:
            s = comp[s]
        return s

    for a, b in pairs:
        ra, rb = root(a), root(b)
        comp[max(ra, rb)] = min(ra, rb)
    return np.array([root(s) for s in range(n)], int)


def _edges(segs: Sequence[int], segments: Sequence[Segment], offset: np.ndarray,
           links: Sequence[tuple]) -> tuple[np.ndarray, list[list[tuple]]]:
    """The nodes of ``segs`` and each one's measured motions to others
    ``(position, z, cov)`` (both ways: a motion and its inverse)."""
    nodes = np.concatenate([offset[s] + np.arange(len(segments[s].frames)) for s in segs])
    where = {int(n): i for i, n in enumerate(nodes)}
    adj: list[list[tuple]] = [[] for _ in nodes]
    motions = [(int(offset[s] + e.i), int(offset[s] + e.j), e.z, e.cov)
               for s in segs for e in segments[s].steps]
    motions += [lk for lk in links if int(lk[0]) in where and int(lk[1]) in where]
    for a, b, z, cov in motions:
        ia, ib = where[int(a)], where[int(b)]
        adj[ia].append((ib, np.asarray(z, float), np.asarray(cov, float)))
        adj[ib].append((ia, *_inverse(np.asarray(z, float), np.asarray(cov, float))))
    return nodes, adj


def _piece(segs: Sequence[int], segments: Sequence[Segment], offset: np.ndarray,
           keys_of: Sequence[np.ndarray], links: Sequence[tuple]) -> Piece:
    """One piece (:class:`Piece`): a breadth-first spanning tree of its motions from
    its first node, the poses and covariances composed along it."""
    nodes, adj = _edges(segs, segments, offset, links)
    n = len(nodes)
    poses, cov = np.zeros((n, 3)), np.zeros((n, 3, 3))
    parent, depth = np.full(n, -1), np.zeros(n, int)
    seen = np.zeros(n, bool)
    seen[0] = True
    todo = deque([0])
    while todo:
        i = todo.popleft()
        for j, z, c in adj[i]:
            if seen[j]:
                continue
            seen[j], parent[j], depth[j] = True, i, depth[i] + 1
            poses[j] = compose(poses[i], z)
            lev = _lever(poses[i], poses[j])
            cov[j] = lev @ cov[i] @ lev.T + _rotated(c, poses[i, 2])
            todo.append(j)
    where = {int(v): i for i, v in enumerate(nodes)}
    keys = np.array(sorted(where[int(offset[s] + k)] for s in segs for k in keys_of[s]), int)
    return Piece(tuple(int(s) for s in segs), nodes, poses, cov, parent, depth, keys)


def pieces(segments: Sequence[Segment], offset: np.ndarray, keys_of: Sequence[np.ndarray],
           links: Sequence[tuple]) -> list[Piece]:
    """The pieces (connected components of segments under ``links``: ``(node a, node
    b, z, cov)``, b's pose in V_a), each in its frame; in the order of their first
    segment. ``keys_of``: each segment's keyframe positions; ``offset``: each
    segment's first node."""
    seg_of = np.repeat(np.arange(len(segments)), [len(s.frames) for s in segments])
    comp = _roots(len(segments), [(int(seg_of[lk[0]]), int(seg_of[lk[1]])) for lk in links])
    return [_piece(np.flatnonzero(comp == r), segments, offset, keys_of, links)
            for r in np.unique(comp)]


def between(piece: Piece, i: int, j: int) -> np.ndarray:
    """The covariance of node ``j``'s pose relative to node ``i``'s (positions in the
    piece), in the piece's frame: the tree's motions from their common ancestor to
    each, independent."""
    a, b = i, j
    while a != b:
        if piece.depth[a] >= piece.depth[b]:
            a = int(piece.parent[a])
        else:
            b = int(piece.parent[b])
    p = piece.poses

    def own(x: int) -> np.ndarray:       # what the branch from the ancestor adds to x
        lev = _lever(p[a], p[x])
        return piece.cov[x] - lev @ piece.cov[a] @ lev.T

    lev = _lever(p[i], p[j])
    return own(j) + lev @ own(i) @ lev.T


def piece_map(piece: Piece, places: Sequence[Place]) -> PieceMap:
    """The features of a piece's keyframes (their ``places``, in the order of
    ``piece.keys``) in the piece's frame, merged, and the area their views cover
    (m²)."""
    pts = [_in_frame(piece.poses[k], pl.points_v)
           for k, pl in zip(piece.keys, places, strict=True)]
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


def agree(ci: _Closure, cj: _Closure, mine: Piece, other: Piece) -> bool:
    """Whether closure ``cj`` is where closure ``ci`` and the pieces put it, within the
    1σ of both, the drift of ``mine`` between their keyframes and of ``other``
    between the keyframes they fell near (chi-square under :data:`AGREE_CHI2`)."""
    d = relative(mine.poses[ci.a], mine.poses[cj.a])
    pred = compose(ci.z, d)
    c, s = math.cos(ci.z[2]), math.sin(ci.z[2])
    jp = np.array([[1, 0, -s * d[0] - c * d[1]], [0, 1, c * d[0] - s * d[1]], [0, 0, 1.0]])
    drift = _rotated(between(mine, ci.a, cj.a), ci.z[2] - mine.poses[ci.a, 2])
    cov = cj.cov + jp @ ci.cov @ jp.T + drift + between(other, ci.near, cj.near)
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


def _closures(mine: Piece, places: Sequence[Place], other: Piece, pm: PieceMap,
              rng: np.random.Generator) -> list[_Closure]:
    """Each keyframe of ``mine`` (its ``places``, in the order of its keys) matched
    against the piece map of ``other``: the ones singled out against the whole piece."""
    out = []
    tk = other.poses[other.keys, :2]
    for k, pl in zip(mine.keys, places, strict=True):
        m = match_places(pm.place, pl, rng, min_points=0, knn=PIECE_KNN,
                         samples=PIECE_SAMPLES, area_m2=pm.area_m2)
        if not m:
            continue
        near = int(other.keys[np.argmin(np.hypot(*(tk - m.z[:2]).T))])
        out.append(_Closure(int(k), m.z, m.cov, _in_frame(mine.poses[k], m.points_b), near,
                            m.inliers, m.runner_up, _in_frame(mine.poses[k], pl.points_v)))
    return out


def join(closures: list[_Closure], mine: Piece, other: Piece, pm: PieceMap
         ) -> tuple[list[_Closure], str]:
    """The closures that join two pieces (empty, with the reason, when none may): the
    largest set agreeing with one closure that is beyond chance together
    (:func:`_beyond_chance`), unless another such set shares none of it
    (``ambiguous``)."""
    sets = []
    for ci in closures:
        group = [cj for cj in closures if cj is ci or agree(ci, cj, mine, other)]
        if _beyond_chance(group, pm):
            sets.append(group)
    if not sets:
        return [], "too few agreeing features" if closures else "no closure"
    best = max(sets, key=len)
    for g in sets:
        if not any(x in best for x in g):
            return [], "ambiguous"
    return best, ""


def _try(q: Piece, m: Piece, places: dict[int, Place], pm: PieceMap,
         rng: np.random.Generator) -> tuple[list[tuple], str]:
    """Piece ``q``'s keyframes (``places`` by node) against the map ``pm`` of piece
    ``m``: the joins ``(node a, node b, z, cov, inliers, runner_up)`` (b's pose in
    V_a), or the reason none was made."""
    got = _closures(q, [places[int(q.nodes[k])] for k in q.keys], m, pm, rng)
    chosen, why = join(got, q, m, pm)
    out = []
    for c in chosen:
        base = m.poses[c.near]
        out.append((int(m.nodes[c.near]), int(q.nodes[c.a]), relative(base, c.z),
                    _rotated(c.cov, -base[2]), c.inliers, c.runner_up))
    return out, why


def piece_closures(segments: Sequence[Segment], keys_of: Sequence[np.ndarray],
                   places: dict[int, Place], offset: np.ndarray, links: Sequence,
                   rng: np.random.Generator) -> tuple[list[tuple], dict[str, int]]:
    """Joins between the pieces that ``links`` (anything with node numbers ``a``, ``b``,
    ``z`` and ``cov``) leave apart: for each two, the keyframes of the one with fewer
    matched against the other's piece map (module docstring), again once either has
    grown by a join. ``keys_of``: each segment's keyframe positions; ``places``:
    keyframes' places by node (``offset[s]`` + position).

    Returns ``(node a, node b, z, cov, inliers, runner_up)`` per closure (b's pose in
    V_a) and the refused joins by reason (``piece: <reason>`` per pair tried;
    ``piece apart: <reason>`` per piece left apart from segment 0's at the end:
    ``one keyframe``, or ``no checked join``)."""
    known = [(lk.a, lk.b, lk.z, lk.cov) for lk in links]
    out, refused, maps, tried = [], {}, {}, set()
    grew = True
    while grew:
        grew = False
        ps = pieces(segments, offset, keys_of, known + [j[:4] for j in out])
        for a, b in itertools.combinations(ps, 2):
            q, m = (a, b) if len(a.keys) <= len(b.keys) else (b, a)
            if len(q.keys) < 2 or (q.segments, m.segments) in tried:
                continue
            tried.add((q.segments, m.segments))
            if m.segments not in maps:
                maps[m.segments] = piece_map(m, [places[int(m.nodes[k])] for k in m.keys])
            got, why = _try(q, m, places, maps[m.segments], rng)
            if not got:
                refused[f"piece: {why}"] = refused.get(f"piece: {why}", 0) + 1
                continue
            out += got
            grew = True
            break
    for p in ps[1:]:                   # ps[0] holds segment 0 (the anchor's)
        why = "piece apart: " + ("one keyframe" if len(p.keys) < 2 else "no checked join")
        refused[why] = refused.get(why, 0) + 1
    return out, refused
