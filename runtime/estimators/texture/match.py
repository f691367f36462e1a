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

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.geometry.fits import fit_rigid_2d

_LSH = {"algorithm": 6, "table_number": 12, "key_size": 16, "multi_probe_level": 0}
MIN_PAIR_SEP_M = 0.08    # a two-point sample's points at least this far apart (yaw)


class DescriptorIndex:
    """The map's binary descriptors, searchable globally (LSH) or near a point."""

    def __init__(self, points_xy: np.ndarray, descriptors: np.ndarray) -> None:
        self.points_xy = np.asarray(points_xy, float)
        self.descriptors = np.ascontiguousarray(descriptors, np.uint8)
        self._lsh = cv2.flann_Index(self.descriptors, _LSH) if len(self.descriptors) else None
        self.tree = cKDTree(self.points_xy) if len(self.points_xy) else None

    def match(self, desc: np.ndarray, k: int, max_hamming: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(qi, mj, unique)``: each query descriptor's ``k`` nearest map descriptors
        (LSH) within ``max_hamming`` bits; ``unique`` marks a query's nearest pair when
        the match is distinctive (:func:`distinctive`)."""
        if self._lsh is None or len(desc) == 0:
            return _none()
        k = min(max(k, 2), len(self.descriptors))
        idx, dist = self._lsh.knnSearch(np.ascontiguousarray(desc, np.uint8), k,
                                        params={"checks": 32})
        return self._pairs(idx.reshape(len(desc), k), dist.reshape(len(desc), k),
                           max_hamming)

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
        dist, idx = cv2.batchDistance(np.ascontiguousarray(desc, np.uint8),
                                      self.descriptors[sub], -1, normType=cv2.NORM_HAMMING,
                                      K=k)
        idx = np.where(idx >= 0, sub[np.maximum(idx, 0)], -1)
        return self._pairs(idx, dist, max_hamming)

    def _pairs(self, idx: np.ndarray, dist: np.ndarray, max_hamming: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ok = (dist <= max_hamming) & (idx >= 0)
        uniq = np.zeros_like(ok)
        if idx.shape[1] >= 2:
            uniq[:, 0] = ok[:, 0] & distinctive(dist, idx, self.points_xy)
        qi, _ = np.nonzero(ok)
        return qi.astype(int), idx[ok].astype(int), uniq[ok]


RATIO = 0.8              # distinctive: nearest <= RATIO x the next place's distance
SAME_PLACE_M = 0.03      # two map features this close are one place (not a twin)


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


def _samples(q: np.ndarray, p: np.ndarray, qi: np.ndarray, tol_m: float, iters: int,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``iters`` two-point samples ``(a, b)`` of distinct query features whose
    distance the map keeps (within ``2 tol``) and at least :data:`MIN_PAIR_SEP_M`."""
    m = len(qi)
    ab = rng.integers(0, m, size=(8 * iters, 2))
    a, b = ab[:, 0], ab[:, 1]
    dq = np.hypot(*(q[a] - q[b]).T)
    dp = np.hypot(*(p[a] - p[b]).T)
    ok = (qi[a] != qi[b]) & (dq > MIN_PAIR_SEP_M) & (np.abs(dq - dp) < 2 * tol_m)
    return a[ok][:iters], b[ok][:iters]


def ransac_rigid(q: np.ndarray, p: np.ndarray, qi: np.ndarray, tol_m: float, iters: int,
                 rng: np.random.Generator, avoid: tuple[float, float, float] | None = None,
                 basin: tuple[float, float] = (0.1, math.radians(5.0))) -> RigidFit | None:
    """The pose with the most distinct query features within ``tol_m`` (two-point RANSAC
    over the correspondences ``q[k] ~ p[k]`` of query ``qi[k]``).

    Args:
        avoid: a pose whose basin (``basin``: metres, radians) is not searched (the
            runner-up's search leaves the best's out).

    Returns:
        The best :class:`RigidFit`, or None with fewer than two usable samples.
    """
    if len(qi) < 2:
        return None
    a, b = _samples(q, p, qi, tol_m, iters, rng)
    if len(a) == 0:
        return None
    zq, zp = q[:, 0] + 1j * q[:, 1], p[:, 0] + 1j * p[:, 1]
    rot = (zp[b] - zp[a]) / (zq[b] - zq[a])
    rot /= np.abs(rot)
    t = zp[a] - rot * zq[a]
    if avoid is not None:
        far = (np.abs(t - (avoid[0] + 1j * avoid[1])) > basin[0]) | \
              (np.abs(np.angle(rot * np.exp(-1j * avoid[2]))) > basin[1])
        rot, t = rot[far], t[far]
        if len(rot) == 0:
            return None
    inl = np.abs(rot[:, None] * zq[None, :] + t[:, None] - zp[None, :]) < tol_m
    counts = inl.sum(1)
    k = int(np.argmax(counts))
    pose = (float(t[k].real), float(t[k].imag), float(np.angle(rot[k])))
    return RigidFit(pose, inl[k], _distinct(qi, inl[k]))


def _distinct(qi: np.ndarray, mask: np.ndarray) -> int:
    return int(len(np.unique(qi[mask])))


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
class Refined:
    """A least-squares pose on its inliers.

    Attributes:
        pose: ``(x_m, y_m, yaw_rad)``.
        cov: ``(3, 3)`` covariance of the pose.
        used: indices of the correspondences used (one per query feature).
        rms_m: RMS residual, m.
    """

    pose: tuple[float, float, float]
    cov: np.ndarray
    used: np.ndarray
    rms_m: float


def refine(q: np.ndarray, p: np.ndarray, qi: np.ndarray | None,
           pose: tuple[float, float, float], tol_m: float, sigma_floor_m: float,
           rounds: int = 2) -> Refined | None:
    """Least squares (:func:`~ceilkit.runtime.geometry.fits.fit_rigid_2d`) on the
    correspondences within ``tol_m`` of ``pose`` (one per query feature; ``qi`` None:
    every pair is its own query feature), the inliers collected again about each new
    pose ``rounds`` times. The covariance is ``s² (JᵀJ)⁻¹`` with ``s²`` the residuals'
    variance per axis (``2n - 3`` degrees of freedom), never below ``sigma_floor_m²``.
    None with fewer than three inliers."""
    used = np.zeros(0, int)
    for _ in range(rounds):
        used = np.flatnonzero(residuals(pose, q, p) < tol_m) if qi is None else \
            one_per_query(q, p, qi, pose, tol_m)
        if len(used) < 3:
            return None
        yaw, t = fit_rigid_2d(q[used], p[used])
        pose = (float(t[0]), float(t[1]), float(yaw))
    r = residuals(pose, q[used], p[used])
    n = len(used)
    s2 = max(float(np.sum(r * r)) / max(2 * n - 3, 1), sigma_floor_m ** 2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rq = q[used] @ np.array([[c, s], [-s, c]])          # R(yaw) q
    J = np.zeros((2 * n, 3))
    J[0::2, 0] = 1.0
    J[1::2, 1] = 1.0
    J[0::2, 2] = -rq[:, 1]
    J[1::2, 2] = rq[:, 0]
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    return Refined(pose, cov, used, float(np.sqrt(np.mean(r * r))))


__all__ = ["DescriptorIndex", "distinctive", "Refined", "RigidFit", "one_per_query", "ransac_rigid",
           "refine", "residuals"]
