"""Global localization from ceiling spot lights: rays, point-pattern matching, pose.

One frame of spot lights gives the vehicle's full pose ``(x, y, yaw)`` in W with no
prior (after Roh et al., ASCC 2011; see ``docs/methods/lights.md``).

Convention (SPEC §1): ``X_W = Rz(yaw) X_V + (x, y, 0)``; the camera is mounted by
``X_V = R_vehicle_cam X_C + t_vehicle_cam``, so ``R_world_cam = Rz(yaw) R_vehicle_cam``.
Every light centre lies on the ceiling plane ``z = H`` (``site.ceiling_height``).

Pipeline per frame:

1. :func:`~ceilkit.runtime.features.spots.detect_spots` finds the lights' centroids (distorted px).
2. :func:`ceiling_points` turns each centroid into a point on the ceiling in the
   *vehicle* frame: the ray ``R_vehicle_cam @ unproject(px)`` from the optical centre
   up to ``z = H``. The yaw only turns about the vertical, so these points are known
   without the pose: they are the map seen from the vehicle.
3. :class:`PatternMatcher` finds the rigid 2-D transform ``p_W = R(yaw) q_V + t`` that
   puts the most observed points on map lights: every observed pair votes, through
   the map pairs of the same length, for a pose ``(yaw, x, y)``; the best-voted
   poses are verified by counting inliers (and map lights that should be seen but are
   not), refined, and ranked. When the runner-up is a genuinely different pose with
   nearly the same support (a regular grid), the frame is ``ambiguous``.
4. :func:`refine_pose_ceiling` minimizes the pixel residuals (Gauss-Newton over
   ``x, y, yaw``), linearized at the observations through each spot's pixel Jacobian:
   the same pose as :func:`refine_pose`, which reprojects through the distorted lens
   at every step (kept as the reference); the covariance is ``s² (JᵀJ)⁻¹`` with ``s``
   the pixel residual.

Example::

    est = LightsEstimator(rig, site).estimate(grey, t_ns)
    if est:
        print(est.x_m, est.y_m, est.yaw_deg, est.quality)
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Estimate, Failure, PoseEstimate
from ceilkit.runtime.features.spots import SpotParams, Spots, detect_spots
from ceilkit.runtime.geometry.rotations import wrap_pi

NAME = "lights"
_JAC_STEP_PX = 8  # node spacing of the pixel-Jacobian table


# ------------------------------------------------------------------------ geometry
@functools.lru_cache(maxsize=64)
def _mount_arrays(mount: Mount) -> tuple[np.ndarray, np.ndarray]:
    """``(R_vehicle_cam, t_vehicle_cam)`` of a mount, computed once (read-only)."""
    R, t = mount.R_vehicle_cam, mount.t_vehicle_cam
    R.setflags(write=False)
    t.setflags(write=False)
    return R, t


def ceiling_points(rig: Rig, ceiling_height_m: float, points_px: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Ceiling points in the vehicle frame of image points.

    Args:
        rig: camera and mount.
        ceiling_height_m: ``H``, the ceiling's height above the floor (W's z).
        points_px: ``(N, 2)`` distorted pixels.

    Returns:
        ``(q_V (N, 2), ok (N,))``: ``(x, y)`` in V (metres) of the ray's meeting with
        ``z = H``; ``ok`` is False where the ray does not rise (NaN there).
    """
    px = np.asarray(points_px, float).reshape(-1, 2)
    if px.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    xy = rig.camera.unproject(px)
    rays_c = np.ones((xy.shape[0], 3))
    rays_c[:, :2] = xy
    R_vc, t_vc = _mount_arrays(rig.mount)
    rays_v = rays_c @ R_vc.T
    dz = ceiling_height_m - rig.mount.z_m
    ok = rays_v[:, 2] > 1e-6 * np.sqrt((rays_v * rays_v).sum(axis=1))       # |ray|
    s = np.where(ok, dz / np.where(ok, rays_v[:, 2], 1.0), np.nan)
    q = t_vc[None, :2] + s[:, None] * rays_v[:, :2]
    return q, ok


def project_lights(rig: Rig, ceiling_height_m: float, lights_w: np.ndarray, x_m: float,
                   y_m: float, yaw_rad: float) -> np.ndarray:
    """Pixels ``(N, 2)`` of ceiling lights ``(N, 2)`` (W) seen from a vehicle pose.

    NaN where a light is behind the camera.
    """
    L = np.asarray(lights_w, float).reshape(-1, 2)
    return _project_poses(rig, ceiling_height_m, L, np.array([[x_m, y_m, yaw_rad]]))[0]


def _project_poses(rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                   poses: np.ndarray) -> np.ndarray:
    """``(P, N, 2)`` pixels of ``N`` lights from ``P`` poses ``(x, y, yaw)``, one call."""
    L = np.asarray(lights_w, float).reshape(-1, 2)
    n = L.shape[0]
    poses = np.asarray(poses, float).reshape(-1, 3)
    R_vc, t_vc = _mount_arrays(rig.mount)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    # light minus camera centre, in the vehicle-level frame of each pose: Rz(-yaw) (P - c_w)
    dx = L[None, :, 0] - poses[:, None, 0]
    dy = L[None, :, 1] - poses[:, None, 1]
    lx = c[:, None] * dx + s[:, None] * dy - t_vc[0]
    ly = -s[:, None] * dx + c[:, None] * dy - t_vc[1]
    lz = np.full_like(lx, ceiling_height_m - t_vc[2])
    P_v = np.stack([lx, ly, lz], axis=-1).reshape(-1, 3)
    return rig.camera.project(P_v @ R_vc).reshape(poses.shape[0], n, 2)


def pixel_scale(rig: Rig, ceiling_height_m: float, q_v: np.ndarray) -> np.ndarray:
    """``(N, 2, 2)`` Jacobians d(pixel)/d(ceiling point in V, metres) at points ``q_v``."""
    q = np.asarray(q_v, float).reshape(-1, 2)
    n = q.shape[0]
    if n == 0:
        return np.zeros((0, 2, 2))
    eps = 1e-3
    pts = np.concatenate([q, q + [eps, 0.0], q + [0.0, eps]])
    px = project_lights(rig, ceiling_height_m, pts, 0.0, 0.0, 0.0)
    J = np.stack([(px[n:2 * n] - px[:n]) / eps, (px[2 * n:] - px[:n]) / eps], axis=2)
    return J


def jacobian_grid(rig: Rig, ceiling_height_m: float, step_px: int = 16) -> np.ndarray:
    """``(GH, GW, 2, 2)`` d(pixel)/d(ceiling point in V) on the pixel grid
    ``u = i step_px``, ``v = j step_px`` (the last node past the image edge); NaN where a
    pixel's ray does not rise. Read with :func:`interp_grid`."""
    cam = rig.camera
    us = np.arange(0, cam.width - 1 + step_px, step_px, dtype=float)
    vs = np.arange(0, cam.height - 1 + step_px, step_px, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    q, ok = ceiling_points(rig, ceiling_height_m, np.stack([uu.ravel(), vv.ravel()], 1))
    J = np.full((q.shape[0], 2, 2), np.nan)
    if np.any(ok):
        J[ok] = pixel_scale(rig, ceiling_height_m, q[ok])
    return J.reshape(vs.size, us.size, 2, 2)


def interp_grid(grid: np.ndarray, step_px: int, points_px: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a per-node table ``(GH, GW, ...)`` (nodes every
    ``step_px`` pixels from pixel 0) at pixels ``(N, 2)``; returns ``(N, ...)``."""
    px = np.asarray(points_px, float).reshape(-1, 2)
    gh, gw = grid.shape[:2]
    f = np.minimum(np.maximum(px / step_px, 0.0), (gw - 1.0, gh - 1.0))   # (u, v) in nodes
    i = np.minimum(f.astype(np.intp), (gw - 2, gh - 2))
    ab = f - i
    extra = (slice(None),) + (None,) * (grid.ndim - 2)
    a, b = ab[:, 0][extra], ab[:, 1][extra]
    # the four corners of each point's cell in one gather: (N, 4, ...)
    node = i[:, 1] * gw + i[:, 0]
    c = grid.reshape((gh * gw,) + grid.shape[2:])[node[:, None] + (0, 1, gw, gw + 1)]
    ua = 1 - a
    return (1 - b) * (ua * c[:, 0] + a * c[:, 1]) + b * (ua * c[:, 2] + a * c[:, 3])


def fit_rigid_2d(q: np.ndarray, p: np.ndarray, w: np.ndarray | None = None
                 ) -> tuple[float, np.ndarray]:
    """Least-squares ``(yaw, t)`` with ``p ≈ R(yaw) q + t`` for point pairs ``(N, 2)``.

    The scale is known (metres on both sides), so this is the rigid case of the
    paper's similarity fit (Eq. 15 with ``s = 1``): closed form, N >= 2.
    """
    w = np.ones(q.shape[0]) if w is None else np.asarray(w, float)
    W = w.sum()
    qm = (w[:, None] * q).sum(0) / W
    pm = (w[:, None] * p).sum(0) / W
    a, b = q - qm, p - pm
    s_cos = (w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])).sum()
    s_sin = (w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])).sum()
    yaw = math.atan2(s_sin, s_cos)
    c, s = math.cos(yaw), math.sin(yaw)
    t = pm - np.array([c * qm[0] - s * qm[1], s * qm[0] + c * qm[1]])
    return yaw, t


# ------------------------------------------------------------------------ matching
@functools.lru_cache(maxsize=32)
def _arange(n: int) -> np.ndarray:
    """``np.arange(n)``, computed once per ``n`` (read-only)."""
    a = np.arange(n)
    a.setflags(write=False)
    return a


@functools.lru_cache(maxsize=32)
def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)``, computed once per ``n`` (read-only)."""
    a, b = np.triu_indices(n, 1)
    a.setflags(write=False)
    b.setflags(write=False)
    return a, b


@dataclass(frozen=True)
class Candidate:
    """A verified pose hypothesis: ``p_W = R(yaw) q_V + (x, y)``.

    Attributes:
        x_m, y_m, yaw_rad: the vehicle pose.
        pairs: ``(K, 2)`` int: observed index, map index of each inlier.
        score: inliers minus half the map lights that should be seen but are not.
        rms_m: RMS of the inliers' ceiling distances.
        missing: map lights that should be seen from this pose but matched nothing.
    """

    x_m: float
    y_m: float
    yaw_rad: float
    pairs: np.ndarray
    score: float
    rms_m: float
    missing: int = 0

    @property
    def inliers(self) -> int:
        return int(self.pairs.shape[0])

    def same_pose(self, other: Candidate, pos_m: float, yaw_rad: float) -> bool:
        return _near(self.x_m, self.y_m, self.yaw_rad, other, pos_m, yaw_rad)


def _near(x_m: float, y_m: float, yaw_rad: float, other: Candidate, pos_m: float,
          max_yaw_rad: float) -> bool:
    """Whether the pose ``(x_m, y_m, yaw_rad)`` is within ``pos_m`` and ``max_yaw_rad``
    of ``other`` (:meth:`Candidate.same_pose` without building a candidate)."""
    return (math.hypot(x_m - other.x_m, y_m - other.y_m) < pos_m
            and abs(wrap_pi(yaw_rad - other.yaw_rad)) < max_yaw_rad)


class PatternMatcher:
    """Rotation- and translation-invariant matching of ceiling points to a light map.

    Built once per map: every map pair shorter than ``max_pair_m`` with its length,
    sorted (a pair-distance hash). ``match`` returns verified candidates, best first.

    Args:
        lights_w: ``(M, 2)`` map light centres in W.
        gate_m: largest distance of an inlier from its map light (ceiling metres).
        max_pair_m: longest pair that can be seen in one frame.
        visible: optional ``f(x, y, yaw) -> (M,) bool``: map lights the camera should see
            from a pose (used to penalize poses whose visible lights are not observed).
    """

    def __init__(self, lights_w: np.ndarray, gate_m: float = 0.08, max_pair_m: float = 1e9,
                 visible: Any = None, max_observed: int = 7, top_bins: int = 8,
                 max_bins: int = 48,
                 yaw_bin_rad: float = math.radians(4.0), pos_bin_m: float = 0.3):
        self.lights_w = np.asarray(lights_w, float).reshape(-1, 2)
        m = self.lights_w.shape[0]
        self.gate_m = gate_m
        self.visible = visible
        self.max_observed = max_observed
        self.top_bins = top_bins
        self.max_bins = max(top_bins, max_bins)
        self.yaw_bin = yaw_bin_rad
        self.pos_bin = pos_bin_m
        i, j = np.triu_indices(m, 1)
        d = np.linalg.norm(self.lights_w[i] - self.lights_w[j], axis=1)
        keep = d <= max_pair_m
        order = np.argsort(d[keep])
        self.pair_i = i[keep][order]
        self.pair_j = j[keep][order]
        self.pair_d = d[keep][order]
        # per-map structures of the vote, in complex form (x + iy): each pair's midpoint
        # and unit direction i -> j
        self._lc = self.lights_w[:, 0] + 1j * self.lights_w[:, 1]
        vp = self._lc[self.pair_j] - self._lc[self.pair_i]
        self._pair_mid = 0.5 * (self._lc[self.pair_i] + self._lc[self.pair_j])
        self._pair_dir = vp / np.maximum(np.abs(vp), 1e-12)
        self._lc_row = self._lc[None, :]

    # -- association ------------------------------------------------------------------
    def associate(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float
                  ) -> np.ndarray:
        """``(K, 2)`` (observed, map) pairs: mutual nearest neighbours within ``gate_m``."""
        q = np.asarray(q_v, float).reshape(-1, 2)
        return self._associate(q[:, 0] + 1j * q[:, 1], complex(math.cos(yaw), math.sin(yaw)),
                               complex(t[0], t[1]), gate_m)

    def _associate(self, qc: np.ndarray, rot: complex, t: complex, gate_m: float
                   ) -> np.ndarray:
        d = np.abs((qc * rot + t)[:, None] - self._lc_row)       # (N, M) ceiling metres
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
        # the rigid fit (fit_rigid_2d) in complex form: rot = phase of sum conj(a) b
        qa, pb = qc[pairs[:, 0]], self._lc[pairs[:, 1]]
        n = pairs.shape[0]
        qm, pm = qa.sum() / n, pb.sum() / n                 # the means
        sc = complex((np.conj(qa - qm) * (pb - pm)).sum())
        rot = sc / abs(sc) if abs(sc) > 0 else 1.0 + 0j
        t = complex(pm - rot * qm)
        pairs = self._associate(qc, rot, t, self.gate_m)
        if pairs.shape[0] < 2:
            return None
        res = np.abs(qc[pairs[:, 0]] * rot + t - self._lc[pairs[:, 1]])
        rms = math.sqrt(float((res * res).sum()) / res.size)
        yaw = math.atan2(rot.imag, rot.real)
        score = float(pairs.shape[0])
        missing = 0
        if self.visible is not None:
            vis = self.visible(t.real, t.imag, yaw)
            vis[pairs[:, 1]] = False
            missing = int(vis.sum())
            score -= 0.5 * missing
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
        kb = np.floor(hyp / (self.yaw_bin, self.pos_bin, self.pos_bin)).astype(np.int64).T.copy()
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
            if any(_near(t[0], t[1], yaw, o, 0.5, math.radians(8.0)) for o in cands):
                continue   # a neighbouring bin of a pose already verified
            c = self._verify(qc, yaw, complex(t[0], t[1]), self.gate_m)
            if c is None:
                continue
            if any(_near(c.x_m, c.y_m, c.yaw_rad, o, 0.3, math.radians(5.0)) for o in cands):
                continue
            cands.append(c)
        cands.sort(key=lambda c: (-c.score, -c.inliers, c.rms_m))
        return cands


# ------------------------------------------------------------------------ refinement
@dataclass(frozen=True)
class Refined:
    """Gauss-Newton result: the pose, its covariance and the pixel residuals."""

    x_m: float
    y_m: float
    yaw_rad: float
    cov: np.ndarray
    residuals_px: np.ndarray  # (K,) norms
    pairs: np.ndarray


def refine_pose(rig: Rig, ceiling_height_m: float, points_px: np.ndarray,
                lights_w: np.ndarray, x_m: float, y_m: float, yaw_rad: float,
                iterations: int = 3, sigma_floor_px: float = 0.1) -> tuple[
                    float, float, float, np.ndarray, np.ndarray]:
    """Minimize the reprojection error of matched lights over ``(x, y, yaw)``.

    Args:
        points_px: ``(K, 2)`` observed centroids (distorted pixels).
        lights_w: ``(K, 2)`` their map lights in W.
        x_m, y_m, yaw_rad: the starting pose.
        sigma_floor_px: least pixel noise assumed in the covariance.

    Returns:
        ``(x, y, yaw, cov (3, 3), residual norms (K,) px)``. The covariance is
        ``s² (JᵀJ)⁻¹``, ``s² = max(SSR / (2K - 3), sigma_floor²)``.
    """
    p = np.array([x_m, y_m, yaw_rad], float)
    obs = np.asarray(points_px, float).reshape(-1, 2)
    L = np.asarray(lights_w, float).reshape(-1, 2)
    k = obs.shape[0]
    eps = np.array([1e-5, 1e-5, 1e-6])

    def jac(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals at q and their forward-difference Jacobian, in one projection."""
        poses = np.repeat(q[None, :], 4, axis=0)
        poses[1:] += np.diag(eps)
        px = _project_poses(rig, ceiling_height_m, L, poses)
        r0 = (px[0] - obs).ravel()
        Jq = np.stack([((px[a + 1] - obs).ravel() - r0) / eps[a] for a in range(3)], axis=1)
        return r0, Jq

    r, J = jac(p)
    for _ in range(iterations):
        if not np.all(np.isfinite(J)) or not np.all(np.isfinite(r)):
            break
        try:
            step = -np.linalg.solve(J.T @ J + 1e-9 * np.eye(3), J.T @ r)
        except np.linalg.LinAlgError:
            break
        r_new, J_new = jac(p + step)
        if not np.all(np.isfinite(r_new)) or r_new @ r_new > r @ r:
            break
        p, r, J = p + step, r_new, J_new
        if np.abs(step[:2]).max() < 1e-5 and abs(step[2]) < 1e-6:
            break
    dof = 2 * k - 3
    s2 = max(float(r @ r) / dof if dof > 0 else 0.0, sigma_floor_px ** 2)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    norms = np.linalg.norm(r.reshape(-1, 2), axis=1)
    return float(p[0]), float(p[1]), float(wrap_pi(p[2])), cov, norms


def refine_pose_ceiling(q_v: np.ndarray, jac_px: np.ndarray, lights_w: np.ndarray,
                        x_m: float, y_m: float, yaw_rad: float, iterations: int = 3,
                        sigma_floor_px: float = 0.1) -> tuple[
                            float, float, float, np.ndarray, np.ndarray]:
    """:func:`refine_pose` linearized at the observations: no projection per step.

    The pixel residual of light ``i`` is ``J_i (q̂_i - q_i)``, with ``q_i`` the observed
    ceiling point in V, ``q̂_i = Rz(-yaw) (L_i - t)`` the map light seen from the pose and
    ``J_i`` d(pixel)/d(ceiling point) at the observation (:func:`pixel_scale`). It differs
    from the reprojection error only at second order in the residual (sub-millimetre
    here), so both give the same pose; this one costs a few 3x3 solves.

    Args:
        q_v: ``(K, 2)`` observed ceiling points in V (metres).
        jac_px: ``(K, 2, 2)`` pixel Jacobians at those points (px per metre).
        lights_w: ``(K, 2)`` their map lights in W.
        x_m, y_m, yaw_rad: the starting pose.

    Returns:
        As :func:`refine_pose`: ``(x, y, yaw, cov (3, 3), residual norms (K,) px)``.
    """
    q = np.asarray(q_v, float).reshape(-1, 2)
    J = np.asarray(jac_px, float).reshape(-1, 2, 2)
    L = np.asarray(lights_w, float).reshape(-1, 2)
    k = q.shape[0]
    D = np.empty((k, 2, 3))          # d q̂ / d(x, y, yaw) of every light

    def resid(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(2k,)`` px (light by light, u then v) and their Jacobian
        ``(2k, 3)`` at a pose."""
        c, s = math.cos(yaw), math.sin(yaw)
        qh = (L - (x, y)) @ np.array([[c, -s], [s, c]])      # q̂ = Rz(-yaw) (L - t)
        r = (J @ (qh - q)[:, :, None]).reshape(-1)
        # A = J @ d q̂ / d(x, y, yaw), d q̂ / d(x, y, yaw) = [[-c, -s, q̂y], [s, -c, -q̂x]]
        D[:, :, :2] = ((-c, -s), (s, -c))
        D[:, 0, 2] = qh[:, 1]
        D[:, 1, 2] = -qh[:, 0]
        return r, (J @ D).reshape(-1, 3)

    p = (float(x_m), float(y_m), float(yaw_rad))
    r, A = resid(*p)
    ssr = float(r @ r)
    for _ in range(iterations):
        if not (math.isfinite(ssr) and np.isfinite(A).all()):
            break
        step = _solve3(A.T @ A, A.T @ r, 1e-9)
        if step is None:
            break
        p_new = (p[0] - step[0], p[1] - step[1], p[2] - step[2])
        r_new, A_new = resid(*p_new)
        ssr_new = float(r_new @ r_new)
        if not math.isfinite(ssr_new) or ssr_new > ssr:
            break
        p, r, A, ssr = p_new, r_new, A_new, ssr_new
        if max(abs(step[0]), abs(step[1])) < 1e-5 and abs(step[2]) < 1e-6:
            break
    dof = 2 * k - 3
    s2 = max(ssr / dof if dof > 0 else 0.0, sigma_floor_px ** 2)
    try:
        cov = s2 * np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    rr = r.reshape(-1, 2)
    norms = np.sqrt(rr[:, 0] ** 2 + rr[:, 1] ** 2)
    return p[0], p[1], float(wrap_pi(p[2])), cov, norms


def _solve3(N: np.ndarray, g: np.ndarray, ridge: float) -> tuple[float, float, float] | None:
    """``(N + ridge I)⁻¹ g`` for a symmetric ``(3, 3)`` ``N`` and ``g`` ``(3,)`` by Cholesky,
    in plain floats (a 3x3 system costs less than the call to a general solver);
    ``None`` if the matrix is not positive definite."""
    (a, b, c), (_, d, e), (_, _, f) = N.tolist()
    a, d, f = a + ridge, d + ridge, f + ridge
    g0, g1, g2 = g.tolist()
    if not a > 0:
        return None
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    t = d - l10 * l10
    if not t > 0:
        return None
    l11 = math.sqrt(t)
    l21 = (e - l20 * l10) / l11
    t = f - l20 * l20 - l21 * l21
    if not t > 0:
        return None
    l22 = math.sqrt(t)
    z0 = g0 / l00
    z1 = (g1 - l10 * z0) / l11
    z2 = (g2 - l20 * z0 - l21 * z1) / l22
    x2 = z2 / l22
    x1 = (z1 - l21 * x2) / l11
    x0 = (z0 - l10 * x1 - l20 * x2) / l00
    return x0, x1, x2


# ------------------------------------------------------------------------ estimator
class LightsEstimator:
    """Full vehicle pose from one frame of ceiling spot lights, with no prior.

    Args:
        rig: camera and mount (any tilt whose view reaches the ceiling).
        site: needs ``lights`` (and ``ceiling_height``).
        light_radius_m: radius of a light's bright disc; predicts each spot's area and
            shape at its place in the image (0 turns these checks off).
        gate_m: largest ceiling distance of a matched light from its map position.
        ambiguity_margin: a different pose whose score is within this of the best makes
            the frame ``ambiguous`` (score: inliers - 0.5 x lights missed).
        min_inliers: fewest matched lights for a pose without a prior (>= 3).
        max_residual_px: a matched light with a larger reprojection residual is dropped.
        spot_params: :class:`~ceilkit.runtime.features.spots.SpotParams` (defaults if ``None``).
        prior_gate_m: association gate around a prior pose (default: 0.4 x the closest
            light spacing, at most 1 m).
        max_view_angle_deg: spots seen further than this from the vertical are ignored
            (tiny, poorly resolved, and the edge of a fisheye image circle).
        max_spots: examine at most this many candidate regions, nearest the nadir first.

    Raises:
        ConfigError: no lights in the site, an impossible option, or a ceiling below
            the camera.
    """

    name = NAME

    def __init__(self, rig: Rig, site: Site, light_radius_m: float = 0.08,
                 gate_m: float = 0.1, ambiguity_margin: float = 1.0, min_inliers: int = 3,
                 max_residual_px: float = 3.0, spot_params: SpotParams | None = None,
                 prior_gate_m: float | None = None, max_view_angle_deg: float = 75.0,
                 max_spots: int = 12):
        if not site.has_lights:
            raise ConfigError(site.source, "lights",
                              "the lights method needs at least one light in the site map")
        check_rig_site(rig, site)
        if min_inliers < 3:
            raise ConfigError(None, "min_inliers", f"expected >= 3, found {min_inliers}")
        if gate_m <= 0 or light_radius_m < 0:
            raise ConfigError(None, "gate_m", "expected gate_m > 0 and light_radius_m >= 0")
        self.rig, self.site = rig, site
        self.height_m = site.ceiling_height_m
        self.lights_w = np.asarray(site.lights_m, float)
        self._lights_c = self.lights_w[:, 0] + 1j * self.lights_w[:, 1]     # x + iy
        self.light_radius_m = light_radius_m
        self.gate_m = gate_m
        self.ambiguity_margin = ambiguity_margin
        self.min_inliers = min_inliers
        self.max_residual_px = max_residual_px
        self.spot_params = spot_params or SpotParams()
        spacing = _min_spacing(self.lights_w)
        if spacing < 1e-3:
            raise ConfigError(site.source, "lights",
                              "duplicate light: two lights at the same place")
        self.prior_gate_m = (prior_gate_m if prior_gate_m is not None
                             else max(gate_m, min(1.0, 0.4 * spacing)))
        self.max_spots = max_spots
        self.valid_mask = view_mask(rig, math.radians(max_view_angle_deg))
        R, _ = _mount_arrays(rig.mount)
        up = R.T @ np.array([0.0, 0.0, 1.0])   # the vertical seen from the camera
        nadir = rig.camera.project(up[None]) if up[2] > 1e-6 else np.full((1, 2), np.nan)
        self.nadir_px = ((float(nadir[0, 0]), float(nadir[0, 1]))
                         if np.all(np.isfinite(nadir)) else (rig.camera.cx, rig.camera.cy))
        self._t_vc = _mount_arrays(rig.mount)[1]
        self._table = self._spot_table()
        self._build_visibility(math.radians(max_view_angle_deg))
        self.matcher = PatternMatcher(self.lights_w, gate_m, self._max_pair_m(),
                                      visible=self._visible)

    def _build_visibility(self, max_angle_rad: float) -> None:
        """A table over the ceiling in V: the pixel distance from the nadir of a light
        there, ``inf`` where the detector cannot report it (outside the image by 12 px,
        or outside the view mask). Makes :meth:`_visible` a lookup, not a projection.

        The table covers the ceiling seen by the view mask (from its pixels every 8 px),
        in at most 200 x 200 cells."""
        cam = self.rig.camera
        uu, vv = np.meshgrid(np.arange(0, cam.width, 8.0), np.arange(0, cam.height, 8.0))
        grid_px = np.stack([uu.ravel(), vv.ravel()], 1)
        inside = self.valid_mask[grid_px[:, 1].astype(int), grid_px[:, 0].astype(int)] > 0
        q, ok = ceiling_points(self.rig, self.height_m, grid_px[inside])
        if not np.any(ok):
            q, ok = np.zeros((1, 2)), np.ones(1, bool)
        lo, hi = q[ok].min(0) - 0.5, q[ok].max(0) + 0.5
        cell = max(0.01, float((hi - lo).max()) / 200)
        n = np.ceil((hi - lo) / cell).astype(int) + 1
        self._vis_origin, self._vis_cell = lo, cell
        gi, gj = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
        g = lo[None, :] + cell * np.stack([gi.ravel(), gj.ravel()], 1)
        px = project_lights(self.rig, self.height_m, g, 0.0, 0.0, 0.0)
        ok = np.isfinite(px[:, 0])
        ok[ok] = cam.in_image(px[ok], margin_px=12.0)
        idx = np.nonzero(ok)[0]
        uv = np.round(px[idx]).astype(int)
        ok[idx[self.valid_mask[uv[:, 1], uv[:, 0]] == 0]] = False
        d = np.hypot(px[:, 0] - self.nadir_px[0], px[:, 1] - self.nadir_px[1])
        self._vis_table = np.where(ok, d, np.inf).astype(np.float32).reshape(n[0], n[1])
        # the same, with a border of inf cells: a clipped index off the table lands there
        self._vis_padded = np.pad(self._vis_table, 1, constant_values=np.inf).ravel()

    def _max_pair_m(self) -> float:
        cam = self.rig.camera
        w, h = cam.width, cam.height
        t = np.linspace(0, 1, 24)
        border = np.concatenate([np.stack([t * (w - 1), np.zeros_like(t)], 1),
                                 np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
                                 np.stack([np.zeros_like(t), t * (h - 1)], 1),
                                 np.stack([np.full_like(t, w - 1), t * (h - 1)], 1)])
        q, ok = ceiling_points(self.rig, self.height_m, border)
        if not np.all(ok):
            return 1e9
        return float(np.linalg.norm(q[:, None] - q[None], axis=2).max()) + 2 * self.gate_m

    def _visible(self, x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
        """``(M,)`` map lights the detector should report from a pose: inside the image
        (by 12 px) and the view mask, and among the ``max_spots`` nearest the nadir
        (a lookup in the table of :meth:`_build_visibility`)."""
        # the lights in V, x + iy: Rz(-yaw) (L - t)
        z = (self._lights_c - complex(x_m, y_m)) * complex(math.cos(yaw_rad),
                                                           -math.sin(yaw_rad))
        ni, nj = self._vis_table.shape
        i = np.rint((z.real - self._vis_origin[0]) / self._vis_cell).astype(np.intp)
        j = np.rint((z.imag - self._vis_origin[1]) / self._vis_cell).astype(np.intp)
        # cells of the padded table (a border of inf): off the table is not visible
        i = np.minimum(np.maximum(i, -1), ni) + 1
        j = np.minimum(np.maximum(j, -1), nj) + 1
        d = self._vis_padded[i * (nj + 2) + j]
        ok = np.isfinite(d)
        if ok.sum() > self.max_spots:
            ok[np.argsort(d, kind="stable")[self.max_spots:]] = False
        return ok

    # -- spots ------------------------------------------------------------------------
    def spots_and_points(self, image: np.ndarray) -> tuple[Spots, np.ndarray, np.ndarray]:
        """Detected spots (after the per-place size and shape checks), their ceiling
        points in V ``(N, 2)`` and a reliability order (nearest the nadir first)."""
        spots, q, order, _ = self._observe(image)
        return spots, q, order

    def _observe(self, image: np.ndarray
                 ) -> tuple[Spots, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`spots_and_points` plus each spot's pixel Jacobian ``(N, 2, 2)``."""
        spots = detect_spots(image, self.spot_params, self.valid_mask, self.nadir_px,
                             self.max_spots)
        if len(spots) == 0:
            return spots, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 2, 2))
        q, ok = ceiling_points(self.rig, self.height_m, spots.centroids_px)
        table = interp_grid(self._table, _JAC_STEP_PX, spots.centroids_px)
        ok &= np.isfinite(table[:, 0])
        if self.light_radius_m > 0 and np.any(ok):
            ok &= self._plausible(spots, table, ok)
        J = table[:, :4].reshape(-1, 2, 2)
        if not ok.all():
            spots, q, J = spots.select(ok), q[ok], J[ok]
        rng = np.hypot(q[:, 0] - self._t_vc[0], q[:, 1] - self._t_vc[1])
        return spots, q, rng.argsort(kind="stable"), J

    def _plausible(self, spots: Spots, table: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Spots whose size and shape fit a light of ``light_radius_m`` at their place.

        The predicted spot is the light's disc through the local Jacobian ``J`` of the
        ceiling-to-pixel map: area ``pi r² |det J|``, second moments
        ``C = r²/4 J Jᵀ + 0.8 I`` (+ blur). The observed moments ``S``, whitened by the
        predicted ones (the eigenvalues of ``C⁻¹ S``), must be round (ratio >= 0.2) and
        of a plausible size. ``table`` rows are the spots' :meth:`_spot_table` entries.
        """
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

    def _spot_table(self) -> np.ndarray:
        """``(GH, GW, 8)`` per-node table (nodes every ``_JAC_STEP_PX`` px): the pixel
        Jacobian ``J`` (4, row-major), ``C⁻¹`` of the predicted spot moments (00, 01,
        11) and the predicted area (see :meth:`_plausible`); NaN where no ray rises."""
        J = jacobian_grid(self.rig, self.height_m, _JAC_STEP_PX)
        gh, gw = J.shape[:2]
        J = J.reshape(-1, 2, 2)
        fin = np.all(np.isfinite(J), axis=(1, 2))
        Jf = np.where(fin[:, None, None], J, 1.0)
        r2 = self.light_radius_m ** 2
        C = 0.25 * r2 * np.einsum("nij,nkj->nik", Jf, Jf) + 0.8 * np.eye(2)
        Ci = np.linalg.inv(C)
        a_pred = math.pi * r2 * np.abs(np.linalg.det(Jf))
        out = np.concatenate([J.reshape(-1, 4), Ci[:, 0, 0:1], Ci[:, 0, 1:2], Ci[:, 1, 1:2],
                              a_pred[:, None]], axis=1)
        out[~fin] = np.nan
        return out.reshape(gh, gw, 8)

    # -- main -------------------------------------------------------------------------
    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> Estimate:
        """The vehicle pose in W from one frame (see the module doc).

        Args:
            image: ``(H, W)`` grey or ``(H, W, 3)`` BGR frame as captured.
            t_ns: capture time, integer nanoseconds.
            prior: a predicted pose (tracking); used for a fast local association and to
                pick among symmetric solutions, never to make up a pose.

        Returns:
            :class:`PoseEstimate` (``lateral_m`` None) or :class:`Failure` with reason
            ``bad_image``, ``no_lights``, ``too_few_lights``, ``no_match`` or ``ambiguous``.
        """
        t0 = time.perf_counter()
        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.size == 0 or img.shape[:2] != (
                self.rig.camera.height, self.rig.camera.width):
            return Failure(t_ns, NAME, "bad_image",
                           f"expected a {self.rig.camera.width}x{self.rig.camera.height} "
                           f"frame, found shape {img.shape}")
        spots, q, order, jac = self._observe(img)
        diag: dict[str, Any] = {"spots": len(spots), "candidates": spots.n_candidates}
        if len(spots) == 0:
            return Failure(t_ns, NAME, "no_lights", "no light found in the frame", diag)
        if len(spots) < 2:
            return Failure(t_ns, NAME, "too_few_lights",
                           f"{len(spots)} light found, a pose needs 2 with a prior, "
                           f"{self.min_inliers} without", diag)
        cand: Candidate | None = None
        runner: Candidate | None = None
        mode = "global"
        if prior is not None and prior.x_m is not None and prior.y_m is not None:
            c = self.matcher.verify(q, prior.yaw_rad, _t_from_pose(prior), self.prior_gate_m)
            # the prior is trusted only when most spots, and most lights the pose
            # should see, match: a stale prior must not pull a local false match
            if (c is not None and c.inliers >= max(2, math.ceil(0.6 * len(spots)))
                    and c.missing <= max(1, c.inliers // 2)):
                cand, mode = c, "tracked"
        if cand is None:
            if len(spots) < self.min_inliers:
                return Failure(t_ns, NAME, "too_few_lights",
                               f"{len(spots)} lights found, a global fix needs "
                               f"{self.min_inliers}", diag)
            cands = [c for c in self.matcher.match(q, order)
                     if c.inliers >= self.min_inliers]
            diag["hypotheses"] = len(cands)
            if not cands:
                return Failure(t_ns, NAME, "no_match",
                               f"{len(spots)} lights match no place of the map", diag)
            cand = cands[0]
            rivals = [c for c in cands[1:]
                      if c.score >= cand.score - self.ambiguity_margin]
            if rivals and prior is not None and prior.x_m is not None:
                near = [c for c in [cand] + rivals if c.same_pose(
                    _cand_from_prior(prior), 1.0, math.radians(20.0))]
                if len(near) == 1:
                    cand, rivals, mode = near[0], [], "prior_resolved"
            if rivals:
                r = rivals[0]
                diag["runner_up"] = (r.x_m, r.y_m, math.degrees(r.yaw_rad), r.inliers)
                return Failure(t_ns, NAME, "ambiguous",
                               f"{len(rivals) + 1} poses fit {cand.inliers} lights equally "
                               f"well (e.g. ({cand.x_m:.2f}, {cand.y_m:.2f}) and "
                               f"({r.x_m:.2f}, {r.y_m:.2f})): a symmetric layout", diag)
            runner = cands[1] if len(cands) > 1 else None
        pairs = cand.pairs
        x, y, yaw, cov, res = refine_pose_ceiling(q[pairs[:, 0]], jac[pairs[:, 0]],
                                                  self.lights_w[pairs[:, 1]],
                                                  cand.x_m, cand.y_m, cand.yaw_rad)
        bad = res > max(self.max_residual_px, 4.0 * _median(res))
        if bad.any() and pairs.shape[0] - int(bad.sum()) >= 2:
            pairs = pairs[~bad]
            x, y, yaw, cov, res = refine_pose_ceiling(q[pairs[:, 0]], jac[pairs[:, 0]],
                                                      self.lights_w[pairs[:, 1]], x, y, yaw)
        k = pairs.shape[0]
        min_k = 2 if mode == "tracked" else self.min_inliers
        if k < min_k or not np.all(np.isfinite(cov)):
            return Failure(t_ns, NAME, "no_match",
                           f"only {k} lights fit after refinement", diag)
        rms = math.sqrt(float((res * res).sum()) / res.size)
        quality = _quality(k, rms, cand, runner, mode)
        diag.update({"inliers": k, "matched_lights": tuple(pairs[:, 1].tolist()),
                     "rms_px": rms, "mode": mode, "score": cand.score,
                     "runner_up_score": None if runner is None else runner.score,
                     "ms": 1e3 * (time.perf_counter() - t0)})
        return PoseEstimate(t_ns, NAME, x, y, yaw, quality, None, cov, diag)


def _quality(k: int, rms_px: float, best: Candidate, runner: Candidate | None,
             mode: str) -> float:
    """Confidence in [0, 1]: more lights, smaller residuals, a clear margin."""
    q_n = 1.0 - math.exp(-(k - 2) / 2.5)
    q_res = math.exp(-0.5 * (rms_px / 1.5) ** 2)
    # lights the pose says should be seen but were not (off, occluded, or a wrong pose)
    q_vis = (best.inliers / (best.inliers + best.missing)) ** 2
    if mode == "tracked":
        q_sep = 0.9
    else:
        rival = runner.score if runner is not None else 2.0
        q_sep = 1.0 - math.exp(-max(best.score - rival, 0.0) / 1.5)
    return float(min(1.0, max(0.0, q_n * q_res * q_sep * q_vis)))


def _median(x: np.ndarray) -> float:
    """``np.median`` of a short 1-D array, the same number for less overhead."""
    s = np.sort(x)
    n = s.size
    return float(s[n // 2]) if n % 2 else float((s[n // 2 - 1] + s[n // 2]) / 2)


def _t_from_pose(pose: PoseEstimate) -> np.ndarray:
    return np.array([float(pose.x_m), float(pose.y_m)])


def _cand_from_prior(pose: PoseEstimate) -> Candidate:
    return Candidate(float(pose.x_m), float(pose.y_m), pose.yaw_rad,
                     np.zeros((0, 2), int), 0.0, 0.0)


def view_mask(rig: Rig, max_angle_rad: float) -> np.ndarray:
    """``(H, W)`` uint8: 255 where a pixel's ray rises within ``max_angle_rad`` of the
    vertical (computed on a 4x coarser grid, then enlarged)."""
    cam = rig.camera
    step = 4
    us = np.arange(0, cam.width, step) + (step - 1) / 2
    vs = np.arange(0, cam.height, step) + (step - 1) / 2
    uu, vv = np.meshgrid(us, vs)
    rays = np.hstack([cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1)),
                      np.ones((uu.size, 1))]) @ rig.mount.R_vehicle_cam.T
    cos_up = rays[:, 2] / np.linalg.norm(rays, axis=1)
    ok = np.isfinite(cos_up) & (cos_up > math.cos(max_angle_rad))
    small = np.where(ok, 255, 0).astype(np.uint8).reshape(uu.shape)
    big = cv2.resize(small, (us.size * step, vs.size * step), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(big[:cam.height, :cam.width])


def _min_spacing(lights_w: np.ndarray) -> float:
    if lights_w.shape[0] < 2:
        return math.inf
    d = np.linalg.norm(lights_w[:, None] - lights_w[None], axis=2)
    d[np.diag_indices_from(d)] = np.inf
    return float(d.min())


__all__ = ["Candidate", "LightsEstimator", "PatternMatcher", "ceiling_points", "fit_rigid_2d",
           "interp_grid", "jacobian_grid", "pixel_scale", "project_lights", "refine_pose",
           "refine_pose_ceiling", "view_mask"]
