"""The array reading of the lights method's compiled loops, kept as their oracle: the
observer's examination (:func:`ceilkit.runtime.estimators.lights.observe.examine_core`:
the spot table at each centroid, the light's centre, its ceiling point, and the size,
shape and frame checks, in numpy over all spots at once), the visibility lookup
(:func:`~ceilkit.runtime.estimators.lights.observe.locate_core`) and the pattern
matcher (:class:`ArrayMatcher`)."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.lights.matching import (
    _SAME_BIN,
    _SAME_POSE,
    MISSING_PENALTY,
    Candidate,
    PatternMatcher,
    near_pose,
)
from ceilkit.runtime.estimators.lights.observe import (
    JAC_STEP_PX,
    RIM_MARGIN_PX,
    RIM_REACH,
    SpotObserver,
    VisibilityTable,
)
from ceilkit.runtime.estimators.lights.rays import ceiling_points, interp_grid
from ceilkit.runtime.features.spots import Spots
from ceilkit.runtime.geometry.fits import fit_rigid_2d_complex


@functools.lru_cache(maxsize=32)
def _arange(n: int) -> np.ndarray:
    a = np.arange(n)
    a.setflags(write=False)
    return a


@functools.lru_cache(maxsize=32)
def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.triu_indices(n, 1)
    a.setflags(write=False)
    b.setflags(write=False)
    return a, b


def centres(centroids_px: np.ndarray, table: np.ndarray) -> np.ndarray:
    """The images of the lights' centres: the spots' centroids minus their disc's
    centroid offset (``table``: the spots' spot-table rows)."""
    off = table[:, 8:10]
    return centroids_px - np.where(np.isfinite(off), off, 0.0)


def plausible(spots: Spots, table: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Spots (among ``ok``) whose size and shape fit a light of the table's radius."""
    keep = ok.copy()
    idx = ok.nonzero()[0] if not ok.all() else slice(None)
    t = table[idx]
    a_pred = t[:, 7]
    a = spots.areas_px[idx]
    good = (a >= 0.15 * a_pred - 3) & (a <= 5.0 * a_pred + 40)
    S = spots.cov_px[idx]
    c00, c01, c11 = t[:, 4], t[:, 5], t[:, 6]
    m00 = c00 * S[:, 0, 0] + c01 * S[:, 1, 0]
    m01 = c00 * S[:, 0, 1] + c01 * S[:, 1, 1]
    m10 = c01 * S[:, 0, 0] + c11 * S[:, 1, 0]
    m11 = c01 * S[:, 0, 1] + c11 * S[:, 1, 1]
    tr = m00 + m11
    det = m00 * m11 - m01 * m10
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    root = np.sqrt(np.maximum(det, 0.0))
    good &= (lo > 0) & (lo >= 0.2 * hi) & (root > 0.05) & (root < 6.0)
    keep[idx] = good
    return keep


def uncut(observer: SpotObserver, centroids_px: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Spots whose light's disc of RIM_REACH x its radius lies inside the frame."""
    cam, r = observer.rig.camera, RIM_REACH * observer.light_radius_m
    reach_u = r * np.hypot(table[:, 0], table[:, 1]) + RIM_MARGIN_PX
    reach_v = r * np.hypot(table[:, 2], table[:, 3]) + RIM_MARGIN_PX
    u, v = centroids_px[:, 0], centroids_px[:, 1]
    return ((u - reach_u >= -0.5) & (u + reach_u <= cam.width - 0.5)
            & (v - reach_v >= -0.5) & (v + reach_v <= cam.height - 0.5))


def examine(observer: SpotObserver, spots: Spots) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(q (K, 2), ok (K,), table (K, 10))`` of detected spots, as the observer's
    compiled examination gives them."""
    table = interp_grid(observer.table, JAC_STEP_PX, spots.centroids_px)
    q, ok = ceiling_points(observer.rig, observer.ceiling_height_m,
                           centres(spots.centroids_px, table))
    ok &= np.isfinite(table[:, 0])
    if observer.light_radius_m > 0 and np.any(ok):
        ok &= plausible(spots, table, ok)
        ok &= uncut(observer, spots.centroids_px, table)
    return q, ok, table


def locate(vis: VisibilityTable, x_m: float, y_m: float, yaw_rad: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`VisibilityTable.locate`'s ``(visible (M,), cell (M,), z (M,))``: the
    lights in V as ``x + iy``, their cells of the padded table, the ``max_spots``
    nearest the nadir among those it sees (ties in map order)."""
    lights = vis.arrays[0]
    z = ((lights[:, 0] + 1j * lights[:, 1]) - complex(x_m, y_m)) * complex(
        math.cos(yaw_rad), -math.sin(yaw_rad))
    ni, nj = vis.table.shape
    i = np.rint((z.real - vis.origin_m[0]) / vis.cell_m).astype(np.intp)
    j = np.rint((z.imag - vis.origin_m[1]) / vis.cell_m).astype(np.intp)
    i = np.minimum(np.maximum(i, -1), ni) + 1
    j = np.minimum(np.maximum(j, -1), nj) + 1
    cell = i * (nj + 2) + j
    d = vis.padded[cell]
    ok = np.isfinite(d)
    if ok.sum() > vis.max_spots:
        ok[np.argsort(d, kind="stable")[vis.max_spots:]] = False
    return ok, cell, z


class ArrayMatcher(PatternMatcher):
    """The array reading of :class:`~ceilkit.runtime.estimators.lights.matching.PatternMatcher`
    (its compiled calls' oracle), on the same pair-distance hash: rotation- and
    translation-invariant matching of ceiling points to a light map. ``visible``: the
    map's :class:`VisibilityTable` (called as ``f(x, y, yaw) -> (M,) bool``) or None.
    """

    def __init__(self, lights_w: np.ndarray, gate_m: float = 0.08, max_pair_m: float = 1e9,
                 visible: Any = None) -> None:
        super().__init__(lights_w, gate_m, max_pair_m, visible)
        # the vote's per-map structures in complex form (x + iy): the lights, each
        # pair's midpoint and unit direction i -> j
        self._lights_c, _, self._pair_mid, self._pair_dir = self._map
        self._lights_row = self._lights_c[None, :]

    # -- association ------------------------------------------------------------------
    def associate(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float
                  ) -> np.ndarray:
        """``(K, 2)`` (observed, map) pairs: mutual nearest neighbours within ``gate_m``."""
        q = np.asarray(q_v, float).reshape(-1, 2)
        return self._associate(q[:, 0] + 1j * q[:, 1], complex(math.cos(yaw), math.sin(yaw)),
                               complex(t[0], t[1]), gate_m)

    def _associate(self, qc: np.ndarray, rot: complex, t: complex, gate_m: float
                   ) -> np.ndarray:
        d = np.abs((qc * rot + t)[:, None] - self._lights_row)       # (N, M) ceiling metres
        j = d.argmin(axis=1)
        ok = (d.min(axis=1) < gate_m) & (d.argmin(axis=0)[j] == _arange(j.size))
        idx = ok.nonzero()[0]
        out = np.empty((idx.size, 2), np.intp)
        out[:, 0], out[:, 1] = idx, j[idx]
        return out

    def verify(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float | None = None
               ) -> Candidate | None:
        """Associate, refit, re-associate; ``None`` with fewer than two inliers."""
        q = np.asarray(q_v, float).reshape(-1, 2)
        return self._verify(q[:, 0] + 1j * q[:, 1], yaw, complex(t[0], t[1]),
                            self.gate_m if gate_m is None else gate_m)

    def _verify(self, qc: np.ndarray, yaw: float, t: complex, gate: float
                ) -> Candidate | None:
        pairs = self._associate(qc, complex(math.cos(yaw), math.sin(yaw)), t, gate)
        if pairs.shape[0] < 2:
            return None
        rot, t = fit_rigid_2d_complex(qc[pairs[:, 0]], self._lights_c[pairs[:, 1]])
        pairs = self._associate(qc, rot, t, self.gate_m)
        if pairs.shape[0] < 2:
            return None
        res = np.abs(qc[pairs[:, 0]] * rot + t - self._lights_c[pairs[:, 1]])
        rms = math.sqrt(float((res * res).sum()) / res.size)
        yaw = math.atan2(rot.imag, rot.real)
        score = float(pairs.shape[0])
        missing = 0
        if self.visible is not None:
            vis = self.visible(t.real, t.imag, yaw).copy()
            vis[pairs[:, 1]] = False
            missing = int(vis.sum())
            score -= MISSING_PENALTY * missing
        return Candidate(float(t.real), float(t.imag), float(yaw), pairs, score, rms, missing)

    # -- global -------------------------------------------------------------------------
    def hypotheses(self, q_v: np.ndarray) -> np.ndarray:
        """``(K, 3)`` poses ``(yaw, x, y)`` voted by every observed pair x matching map pair.

        Each observed pair ``(a, b)`` and map pair ``(i, j)`` of the same length (within
        ``2 gate_m``) give two poses, one per orientation: the rotation takes ``b - a``
        onto ``j - i`` (or ``i - j``), the translation takes the midpoints together.
        """
        q = np.asarray(q_v, float).reshape(-1, 2)
        qc = q[:, 0] + 1j * q[:, 1]
        a, b = _triu(qc.size)
        if a.size == 0 or self.pair_d.size == 0:
            return np.zeros((0, 3))
        qa, qb = qc[a], qc[b]
        vq = qb - qa
        d_obs = np.abs(vq)
        tol = 2.0 * self.gate_m
        lohi = np.searchsorted(self.pair_d, np.concatenate([d_obs - tol, d_obs + tol]))
        lo, hi = lohi[:a.size], lohi[a.size:]
        cnt = hi - lo
        total = int(cnt.sum())
        if total == 0:
            return np.zeros((0, 3))
        obs_k = np.repeat(_arange(a.size), cnt)
        mp = _arange(total) + np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
        uq = np.conj(vq / np.maximum(d_obs, 1e-12))
        rot = self._pair_dir[mp] * uq[obs_k]
        rmq = rot * (0.5 * (qa + qb))[obs_k]
        mid = self._pair_mid[mp]
        yaw = np.arctan2(rot.imag, rot.real)                 # np.angle(rot)
        # the reversed orientation: rot -> -rot, yaw -> yaw + pi
        out = np.empty((2 * total, 3))
        out[:total, 0] = yaw
        out[total:, 0] = yaw - np.copysign(np.pi, yaw)
        t_fwd, t_rev = mid - rmq, mid + rmq
        out[:total, 1], out[:total, 2] = t_fwd.real, t_fwd.imag
        out[total:, 1], out[total:, 2] = t_rev.real, t_rev.imag
        return out

    def match(self, q_v: np.ndarray, order: np.ndarray | None = None) -> list[Candidate]:
        """Verified, distinct candidates for observed ceiling points ``(N, 2)``, best first.

        ``order`` ranks the observations (most reliable first); the hashing uses the
        first ``max_observed`` of them, the verification all of them.
        """
        n = q_v.shape[0]
        if n < 2 or self.lights_w.shape[0] < 2:
            return []
        use = np.arange(n) if order is None else np.asarray(order)
        use = use[:self.max_observed]
        hyp = self.hypotheses(q_v[use])
        qc = q_v[:, 0] + 1j * q_v[:, 1]
        if hyp.shape[0] == 0:
            return []
        # bin indices (3, K), rows contiguous (reductions along a row are fast)
        bins_3 = (self.yaw_bin_rad, self.pos_bin_m, self.pos_bin_m)
        kb = np.floor(hyp / bins_3).astype(np.int64).T.copy()
        kb -= kb.min(axis=1)[:, None]
        span = kb.max(axis=1) + 1
        key = (kb[0] * span[1] + kb[1]) * span[2] + kb[2]
        # the stable order of the keys from one plain sort of (key, index) packed in
        # an int64 (a stable argsort costs several times more)
        nk = key.size
        if float(span[0]) * float(span[1]) * float(span[2]) * nk < 2.0 ** 62:
            packed = np.sort(key * nk + _arange(nk))
            srt, ks = packed % nk, packed // nk
        else:   # a map too large to pack (kilometres of bins): the direct way
            srt = key.argsort(kind="stable")
            ks = key[srt]
        starts = np.concatenate([[0], np.flatnonzero(ks[1:] != ks[:-1]) + 1])
        counts = np.diff(np.concatenate([starts, [ks.size]]))
        top = (-counts).argsort(kind="stable")[:self.max_bins]
        # the bins in the order looked at, as plain ints: (first vote in srt, votes)
        bins = list(zip(starts[top].tolist(), counts[top].tolist(), strict=True))
        best = bins[0][1]
        cands: list[Candidate] = []
        for n_done, (first, count) in enumerate(bins):
            # bins far below the best cannot hold a rival of similar support; past
            # `top_bins`, only bins near the best count are looked at (a regular
            # layout spreads its votes over many equally good poses)
            if cands and count < max(3, 0.2 * best):
                break
            if n_done >= self.top_bins and count < 0.5 * best:
                break
            h = hyp[srt[first:first + count]]
            yaw = math.atan2(np.sin(h[:, 0]).sum(), np.cos(h[:, 0]).sum())
            hs = np.sort(h[:, 1:], axis=0)
            t = (0.5 * (hs[(count - 1) // 2] + hs[count // 2])).tolist()     # medians
            if any(near_pose(t[0], t[1], yaw, o, *_SAME_BIN) for o in cands):
                continue   # a neighbouring bin of a pose already verified
            c = self._verify(qc, yaw, complex(t[0], t[1]), self.gate_m)
            if c is None:
                continue
            if any(near_pose(c.x_m, c.y_m, c.yaw_rad, o, *_SAME_POSE) for o in cands):
                continue
            cands.append(c)
        cands.sort(key=lambda c: (-c.score, -c.inliers, c.rms_m))
        return cands
