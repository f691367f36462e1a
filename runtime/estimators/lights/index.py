"""Indexes of a light map whose per-frame cost does not grow with the map.

A frame sees a few dozen lights of a map that may hold 100 000. Two indexes, each
built once per map in ``O(M log M)`` time and ``O(M)`` memory, keep a frame's work to
the lights about its pose:

* :class:`LightGrid`: the lights bucketed in square cells (their sorted keys, CSR): the
  lights within ``r`` of a point are a few binary searches and contiguous slices
  (:func:`near_core`, compiled), in the map's own order. The matcher associates and
  counts the lights a pose should show against these alone (docs/methods/lights.md).
* :class:`ConstellationIndex`: geometric hashing of local constellations. Each light
  with three of its :data:`NEAR` nearest neighbours is a *quad*; its descriptor is the
  three anchor-to-neighbour distances, sorted, and the three neighbour-to-neighbour
  distances, sorted (rotation- and translation-invariant, and Lipschitz in the points:
  a point moved by ``e`` moves no entry by more than ``2 e``, so no ordering can flip
  under noise). The descriptors sit in a 6-D k-d tree (scipy's ``cKDTree``); a frame's
  quads (each reliable spot with its three nearest spots) are looked up within the
  pair-length tolerance, a Chebyshev ball. ``C(NEAR, 3)`` quads per light let up to
  ``NEAR - 3`` of a light's nearest neighbours be missing from the frame (off,
  occluded, outside the view). The chance matches grow with the map: inside a field
  of 100 000 lights 1.6 m apart (each moved by up to 0.4 m) a frame's five quads match
  about a thousand map quads within 0.1 m (a quad is not much of a key there).

Convention (SPEC §1): lights in W, metres; observed ceiling points in V.

Example::

    grid = LightGrid(lights_w, cell_m=5.0)
    ids = grid.near(x_m, y_m, 9.0)              # sorted indices into lights_w
    index = ConstellationIndex(lights_w, tol_m=0.2)
    obs_q, map_q = index.hits(q_v, anchors)     # (H, 4) observed and map quads
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.jit import arr, njit, warmer

NEAR = 5
"""A map light's quads take three of its this many nearest neighbours."""
MAX_CELLS = 1 << 40
"""The grid's cells (both axes' spans multiplied) stay below this (int64 keys)."""


class LightGrid:
    """The lights bucketed in square cells of side ``cell_m`` (only the occupied cells
    are stored: memory ``O(M)`` whatever the map's extent).

    Attributes:
        arrays: ``(keys (C,), starts (C + 1,), order (M,), lights (M, 2), geo (x0, y0,
            cell_m), dims (nx, ny))``, read-only: what :func:`near_core` reads. ``keys``
            are the occupied cells' keys ``ix ny + iy``, sorted; the lights of cell ``c``
            are ``order[starts[c]:starts[c + 1]]``, in the map's order.
    """

    def __init__(self, lights_w: np.ndarray, cell_m: float) -> None:
        L = np.asarray(lights_w, float).reshape(-1, 2)
        lo = L.min(0) if L.shape[0] else np.zeros(2)
        span = (L.max(0) - lo) if L.shape[0] else np.zeros(2)
        cell = max(float(cell_m), 1e-3)
        while (span[0] / cell + 1) * (span[1] / cell + 1) >= MAX_CELLS:
            cell *= 2.0
        nx, ny = (np.floor(span / cell).astype(np.int64) + 1).tolist()
        ix = np.floor((L[:, 0] - lo[0]) / cell).astype(np.int64)
        iy = np.floor((L[:, 1] - lo[1]) / cell).astype(np.int64)
        key = ix * ny + iy
        order = np.argsort(key, kind="stable")         # within a cell: the map's order
        ks = key[order]
        first = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]) if ks.size else np.zeros(0, int)
        self.cell_m = cell
        self.arrays = (arr(ks[first], np.int64), arr(np.r_[first, ks.size], np.int64),
                       arr(order, np.int64), arr(L, np.float64),
                       arr([lo[0], lo[1], cell], np.float64), arr([nx, ny], np.int64))

    def near(self, x_m: float, y_m: float, r_m: float) -> np.ndarray:
        """Sorted indices of the lights within ``r_m`` of ``(x_m, y_m)``."""
        return near_core(self.arrays, float(x_m), float(y_m), float(r_m))


@njit
def near_core(grid, x, y, r):  # pragma: no cover - compiled
    """:meth:`LightGrid.near`: the sorted indices of the lights of ``grid``
    (:attr:`LightGrid.arrays`) within ``r`` of ``(x, y)``: per row of cells two binary
    searches give one contiguous run of ``order``."""
    keys, starts, order, lights, geo, dims = grid
    nx, ny = dims[0], dims[1]
    x0, y0, cell = geo[0], geo[1], geo[2]
    ix0 = max(np.int64(math.floor((x - r - x0) / cell)), 0)
    ix1 = min(np.int64(math.floor((x + r - x0) / cell)), nx - 1)
    iy0 = max(np.int64(math.floor((y - r - y0) / cell)), 0)
    iy1 = min(np.int64(math.floor((y + r - y0) / cell)), ny - 1)
    if ix0 > ix1 or iy0 > iy1:
        return np.empty(0, np.int64)
    lo = np.empty(ix1 - ix0 + 1, np.int64)
    hi = np.empty(ix1 - ix0 + 1, np.int64)
    total = 0
    for k in range(ix1 - ix0 + 1):
        row = (ix0 + k) * ny
        lo[k] = starts[np.searchsorted(keys, row + iy0)]
        hi[k] = starts[np.searchsorted(keys, row + iy1, side="right")]
        total += hi[k] - lo[k]
    out = np.empty(total, np.int64)
    n = 0
    r2 = r * r
    for k in range(lo.size):
        for s in range(lo[k], hi[k]):
            j = order[s]
            dx, dy = lights[j, 0] - x, lights[j, 1] - y
            if dx * dx + dy * dy <= r2:
                out[n] = j
                n += 1
    return np.sort(out[:n])


class ConstellationIndex:
    """Geometric hashing of every light with three of its :data:`NEAR` nearest
    neighbours (the module doc).

    Args:
        lights_w: ``(M, 2)`` the map's lights in W (m), ``M >= 4``.
        tol_m: how far a frame's distance may lie from the map's (the matcher's
            ``gate_m``: the anchors are the spots nearest the nadir, the best measured).

    Attributes:
        quads: ``(Q, 4)`` int: anchor, then three neighbours, nearest the anchor first.
        tree: the ``cKDTree`` of their ``(Q, 6)`` descriptors (:func:`descriptors`).
    """

    def __init__(self, lights_w: np.ndarray, tol_m: float) -> None:
        L = np.asarray(lights_w, float).reshape(-1, 2)
        self.tol_m = float(tol_m)
        near = min(NEAR, L.shape[0] - 1)
        _, nb = cKDTree(L).query(L, near + 1)
        combos = list(itertools.combinations(range(1, near + 1), 3))
        m = L.shape[0]
        self.quads = np.empty((len(combos) * m, 4), np.int32)
        desc = np.empty((len(combos) * m, 6))
        for k, combo in enumerate(combos):        # one combination at a time: O(M) extra
            rows = slice(k * m, (k + 1) * m)
            self.quads[rows, 0] = np.arange(m)
            self.quads[rows, 1:] = nb[:, combo]
            desc[rows] = descriptors(L, self.quads[rows])
        self.tree = cKDTree(desc, balanced_tree=False, compact_nodes=False)

    def hits(self, q_v: np.ndarray, anchors: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """``(observed (H, 4), map (H, 4))`` quads whose descriptors lie within
        ``tol_m`` of each other (every distance): each anchor spot with its three
        nearest spots (of all ``q_v``), against every map quad."""
        q = np.asarray(q_v, float).reshape(-1, 2)
        anchors = np.asarray(anchors, np.int64)
        if q.shape[0] < 4 or anchors.size == 0:
            return np.zeros((0, 4), np.int64), np.zeros((0, 4), np.int64)
        d = np.hypot(q[anchors, None, 0] - q[None, :, 0], q[anchors, None, 1] - q[None, :, 1])
        d[np.arange(anchors.size), anchors] = np.inf
        nb = np.argsort(d, axis=1, kind="stable")[:, :3]
        obs = np.column_stack([anchors, nb])
        found = self.tree.query_ball_point(descriptors(q, obs), self.tol_m, p=np.inf)
        counts = np.array([len(f) for f in found], np.int64)
        if counts.sum() == 0:
            return np.zeros((0, 4), np.int64), np.zeros((0, 4), np.int64)
        ids = np.concatenate([np.asarray(f, np.int64) for f in found])
        return np.repeat(obs, counts, axis=0), self.quads[ids].astype(np.int64)


def descriptors(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """``(Q, 6)`` the quads' descriptors: the anchor's distances to its three
    neighbours, sorted, then the neighbours' three mutual distances, sorted (m)."""
    p = np.asarray(points, float)
    a, b, c, e = (p[quads[:, k]] for k in range(4))

    def dist(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.hypot(u[:, 0] - v[:, 0], u[:, 1] - v[:, 1])

    r = np.sort(np.column_stack([dist(a, b), dist(a, c), dist(a, e)]), axis=1)
    s = np.sort(np.column_stack([dist(b, c), dist(b, e), dist(c, e)]), axis=1)
    return np.concatenate([r, s], axis=1)


@njit
def quad_poses(qc, obs, maps, lights_c):  # pragma: no cover - compiled
    """``(H, 4)`` rows ``(yaw, x, y, rms_m)``: the rigid motion taking each observed
    quad ``qc[obs[h]]`` onto its map quad ``lights_c[maps[h]]``, the anchors paired and
    the neighbours in the order (of the six) that fits best (the descriptor does not
    say which neighbour is which)."""
    h_n = obs.shape[0]
    out = np.empty((h_n, 4))
    perms = np.array([[1, 2, 3], [1, 3, 2], [2, 1, 3], [2, 3, 1], [3, 1, 2], [3, 2, 1]])
    qs = np.empty(4, np.complex128)
    ps = np.empty(4, np.complex128)
    for h in range(h_n):
        best = np.inf
        for p in range(6):
            qs[0], ps[0] = qc[obs[h, 0]], lights_c[maps[h, 0]]
            for k in range(3):
                qs[k + 1] = qc[obs[h, k + 1]]
                ps[k + 1] = lights_c[maps[h, perms[p, k]]]
            qm, pm = qs.mean(), ps.mean()
            sc = 0j
            for k in range(4):
                sc += (qs[k] - qm).conjugate() * (ps[k] - pm)
            rot = sc / abs(sc) if abs(sc) > 0 else 1.0 + 0j
            t = pm - rot * qm
            ss = 0.0
            for k in range(4):
                e = abs(qs[k] * rot + t - ps[k])
                ss += e * e
            if ss < best:
                best = ss
                out[h, 0] = math.atan2(rot.imag, rot.real)
                out[h, 1], out[h, 2] = t.real, t.imag
                out[h, 3] = math.sqrt(ss / 4.0)
    return out


@warmer
def _warm() -> None:
    L = np.array([[0.0, 0.0], [1.0, 0.1], [0.2, 1.3], [1.4, 1.6], [2.9, 0.4]])
    LightGrid(L, 1.0).near(0.5, 0.5, 1.0)
    c = arr(L[:, 0] + 1j * L[:, 1], np.complex128)
    q = arr(np.array([[0, 1, 2, 3]]), np.int64)
    quad_poses(c, q, q, c)


__all__ = ["NEAR", "ConstellationIndex", "LightGrid", "descriptors", "near_core",
           "quad_poses"]
