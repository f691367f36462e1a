"""Global localization from ceiling spot lights: rays, point-pattern matching, pose.

One frame of spot lights gives the vehicle's full pose ``(x, y, yaw)`` in W with no
prior (after Roh et al., ASCC 2011; see ``docs/methods/lights.md``).

Convention (SPEC §1): ``X_W = Rz(yaw) X_V + (x, y, 0)``; the camera is mounted by
``X_V = R_vehicle_cam X_C + t_vehicle_cam``, so ``R_world_cam = Rz(yaw) R_vehicle_cam``.
Every light centre lies on the ceiling plane ``z = H`` (``site.ceiling_height``).

Pipeline per frame:

1. :func:`~ceilkit.runtime.spots.detect_spots` finds the lights' centroids (distorted px).
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
4. :func:`refine_pose` minimizes the reprojection error in pixels (Gauss-Newton over
   ``x, y, yaw`` through the distorted projection); the covariance is
   ``s² (JᵀJ)⁻¹`` with ``s`` the pixel residual.

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

from .errors import ConfigError
from .estimate import Estimate, Failure, PoseEstimate
from .geometry import wrap_pi
from .rig import Mount, Rig
from .site import Site, check_rig_site
from .spots import SpotParams, Spots, detect_spots

NAME = "lights"


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
    rays_c = np.hstack([xy, np.ones((xy.shape[0], 1))])
    R_vc, t_vc = _mount_arrays(rig.mount)
    rays_v = rays_c @ R_vc.T
    dz = ceiling_height_m - rig.mount.z_m
    ok = rays_v[:, 2] > 1e-6 * np.linalg.norm(rays_v, axis=1)
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


def _transform(q: np.ndarray, yaw: float, t: np.ndarray) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([c * q[:, 0] - s * q[:, 1] + t[0], s * q[:, 0] + c * q[:, 1] + t[1]], 1)


# ------------------------------------------------------------------------ matching
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
        return (math.hypot(self.x_m - other.x_m, self.y_m - other.y_m) < pos_m
                and abs(wrap_pi(self.yaw_rad - other.yaw_rad)) < yaw_rad)


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

    # -- association ------------------------------------------------------------------
    def associate(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float
                  ) -> np.ndarray:
        """``(K, 2)`` (observed, map) pairs: mutual nearest neighbours within ``gate_m``."""
        pw = _transform(q_v, yaw, t)
        d2 = ((pw[:, None, :] - self.lights_w[None, :, :]) ** 2).sum(-1)
        j = np.argmin(d2, axis=1)
        dj = d2[np.arange(len(j)), j]
        i_back = np.argmin(d2, axis=0)
        ok = (dj < gate_m ** 2) & (i_back[j] == np.arange(len(j)))
        return np.stack([np.nonzero(ok)[0], j[ok]], axis=1)

    def verify(self, q_v: np.ndarray, yaw: float, t: np.ndarray, gate_m: float | None = None
               ) -> Candidate | None:
        """Associate, refit, re-associate; ``None`` with fewer than two inliers."""
        gate = self.gate_m if gate_m is None else gate_m
        pairs = self.associate(q_v, yaw, t, gate)
        if pairs.shape[0] < 2:
            return None
        yaw, t = fit_rigid_2d(q_v[pairs[:, 0]], self.lights_w[pairs[:, 1]])
        pairs = self.associate(q_v, yaw, t, self.gate_m)
        if pairs.shape[0] < 2:
            return None
        res = _transform(q_v[pairs[:, 0]], yaw, t) - self.lights_w[pairs[:, 1]]
        rms = float(np.sqrt((res ** 2).sum(1).mean()))
        score = float(pairs.shape[0])
        missing = 0
        if self.visible is not None:
            vis = self.visible(float(t[0]), float(t[1]), yaw)
            vis[pairs[:, 1]] = False
            missing = int(vis.sum())
            score -= 0.5 * missing
        return Candidate(float(t[0]), float(t[1]), float(wrap_pi(yaw)), pairs, score, rms,
                         missing)

    # -- global -------------------------------------------------------------------------
    def hypotheses(self, q_v: np.ndarray) -> np.ndarray:
        """``(K, 3)`` poses ``(yaw, x, y)`` voted by every observed pair x matching map pair."""
        n = q_v.shape[0]
        a, b = np.triu_indices(n, 1)
        if a.size == 0 or self.pair_d.size == 0:
            return np.zeros((0, 3))
        d_obs = np.linalg.norm(q_v[a] - q_v[b], axis=1)
        tol = 2.0 * self.gate_m
        lo = np.searchsorted(self.pair_d, d_obs - tol)
        hi = np.searchsorted(self.pair_d, d_obs + tol)
        cnt = hi - lo
        if cnt.sum() == 0:
            return np.zeros((0, 3))
        obs_k = np.repeat(np.arange(a.size), cnt)
        offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        mp = np.repeat(lo, cnt) + offs
        qa, qb = q_v[a[obs_k]], q_v[b[obs_k]]
        pa, pb = self.lights_w[self.pair_i[mp]], self.lights_w[self.pair_j[mp]]
        # both orientations of each map pair
        qa2, qb2 = np.concatenate([qa, qa]), np.concatenate([qb, qb])
        pa2, pb2 = np.concatenate([pa, pb]), np.concatenate([pb, pa])
        vq, vp = qb2 - qa2, pb2 - pa2
        yaw = np.arctan2(vp[:, 1], vp[:, 0]) - np.arctan2(vq[:, 1], vq[:, 0])
        c, s = np.cos(yaw), np.sin(yaw)
        mq, mpt = 0.5 * (qa2 + qb2), 0.5 * (pa2 + pb2)
        tx = mpt[:, 0] - (c * mq[:, 0] - s * mq[:, 1])
        ty = mpt[:, 1] - (s * mq[:, 0] + c * mq[:, 1])
        return np.stack([(yaw + np.pi) % (2 * np.pi) - np.pi, tx, ty], axis=1)

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
        if hyp.shape[0] == 0:
            return []
        ky = np.floor(hyp[:, 0] / self.yaw_bin).astype(np.int64)
        kx = np.floor(hyp[:, 1] / self.pos_bin).astype(np.int64)
        kz = np.floor(hyp[:, 2] / self.pos_bin).astype(np.int64)
        key = ((ky - ky.min()) * (kx.max() - kx.min() + 1) + (kx - kx.min())) \
            * (kz.max() - kz.min() + 1) + (kz - kz.min())
        srt = np.argsort(key, kind="stable")
        ks = key[srt]
        starts = np.concatenate([[0], np.nonzero(np.diff(ks))[0] + 1])
        counts = np.diff(np.concatenate([starts, [ks.size]]))
        top = np.argsort(-counts, kind="stable")[:self.max_bins]
        cands: list[Candidate] = []
        for n_done, k in enumerate(top):
            # bins far below the best cannot hold a rival of similar support; past
            # `top_bins`, only bins near the best count are looked at (a regular
            # layout spreads its votes over many equally good poses)
            if cands and counts[k] < max(3, 0.2 * counts[top[0]]):
                break
            if n_done >= self.top_bins and counts[k] < 0.5 * counts[top[0]]:
                break
            h = hyp[srt[starts[k]:starts[k] + counts[k]]]
            yaw = math.atan2(np.sin(h[:, 0]).mean(), np.cos(h[:, 0]).mean())
            t = np.array([np.median(h[:, 1]), np.median(h[:, 2])])
            seed = Candidate(float(t[0]), float(t[1]), yaw, np.zeros((0, 2), int), 0.0, 0.0)
            if any(seed.same_pose(o, 0.5, math.radians(8.0)) for o in cands):
                continue   # a neighbouring bin of a pose already verified
            c = self.verify(q_v, yaw, t)
            if c is None:
                continue
            if any(c.same_pose(o, 0.3, math.radians(5.0)) for o in cands):
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
        spot_params: :class:`~ceilkit.runtime.spots.SpotParams` (defaults if ``None``).
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
        self.matcher = PatternMatcher(self.lights_w, gate_m, self._max_pair_m(),
                                      visible=self._visible)

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
        (by 12 px) and the view mask, and among the ``max_spots`` nearest the nadir."""
        px = project_lights(self.rig, self.height_m, self.lights_w, x_m, y_m, yaw_rad)
        ok = np.isfinite(px[:, 0])
        ok[ok] = self.rig.camera.in_image(px[ok], margin_px=12.0)
        idx = np.nonzero(ok)[0]
        if idx.size:
            uv = np.round(px[idx]).astype(int)
            inside = self.valid_mask[uv[:, 1], uv[:, 0]] > 0
            ok[idx[~inside]] = False
            idx = idx[inside]
        if idx.size > self.max_spots:
            d = np.hypot(px[idx, 0] - self.nadir_px[0], px[idx, 1] - self.nadir_px[1])
            ok[idx[np.argsort(d)[self.max_spots:]]] = False
        return ok

    # -- spots ------------------------------------------------------------------------
    def spots_and_points(self, image: np.ndarray) -> tuple[Spots, np.ndarray, np.ndarray]:
        """Detected spots (after the per-place size and shape checks), their ceiling
        points in V ``(N, 2)`` and a reliability order (nearest the nadir first)."""
        spots = detect_spots(image, self.spot_params, self.valid_mask, self.nadir_px,
                             self.max_spots)
        if len(spots) == 0:
            return spots, np.zeros((0, 2)), np.zeros(0, int)
        q, ok = ceiling_points(self.rig, self.height_m, spots.centroids_px)
        if self.light_radius_m > 0 and np.any(ok):
            ok &= self._plausible(spots, q, ok)
        spots = spots.select(ok)
        q = q[ok]
        rng = np.linalg.norm(q - _mount_arrays(self.rig.mount)[1][None, :2], axis=1)
        return spots, q, np.argsort(rng, kind="stable")

    def _plausible(self, spots: Spots, q: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Spots whose size and shape fit a light of ``light_radius_m`` at their place.

        The predicted spot is the light's disc through the local Jacobian ``J`` of the
        ceiling-to-pixel map: area ``pi r² |det J|``, second moments
        ``r²/4 J Jᵀ`` (+ blur). The observed moments, whitened by the predicted ones,
        must be round (eigenvalue ratio >= 0.2) and of a plausible size.
        """
        keep = ok.copy()
        idx = np.nonzero(ok)[0]
        J = pixel_scale(self.rig, self.height_m, q[idx])
        r2 = self.light_radius_m ** 2
        fin = np.all(np.isfinite(J), axis=(1, 2))
        J = np.where(fin[:, None, None], J, 1.0)
        a_pred = math.pi * r2 * np.abs(np.linalg.det(J))
        a = spots.areas_px[idx]
        good = fin & (a >= 0.15 * a_pred - 3) & (a <= 5.0 * a_pred + 40)
        C = 0.25 * r2 * np.einsum("nij,nkj->nik", J, J) + 0.8 * np.eye(2)
        Ci = np.linalg.inv(C)
        M = np.einsum("nij,njk->nik", Ci, spots.cov_px[idx])  # similar to the whitened
        tr = M[:, 0, 0] + M[:, 1, 1]
        det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
        disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
        lo, hi = tr / 2 - disc, tr / 2 + disc
        good &= (lo > 0) & (lo >= 0.2 * hi) & (np.sqrt(np.maximum(det, 0)) > 0.05) \
            & (np.sqrt(np.maximum(det, 0)) < 6.0)
        keep[idx] = good
        return keep

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
        spots, q, order = self.spots_and_points(img)
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
        x, y, yaw, cov, res = refine_pose(self.rig, self.height_m,
                                          spots.centroids_px[pairs[:, 0]],
                                          self.lights_w[pairs[:, 1]],
                                          cand.x_m, cand.y_m, cand.yaw_rad)
        bad = res > max(self.max_residual_px, 4.0 * float(np.median(res)))
        if np.any(bad) and pairs.shape[0] - int(bad.sum()) >= 2:
            pairs = pairs[~bad]
            x, y, yaw, cov, res = refine_pose(self.rig, self.height_m,
                                              spots.centroids_px[pairs[:, 0]],
                                              self.lights_w[pairs[:, 1]], x, y, yaw)
        k = pairs.shape[0]
        min_k = 2 if mode == "tracked" else self.min_inliers
        if k < min_k or not np.all(np.isfinite(cov)):
            return Failure(t_ns, NAME, "no_match",
                           f"only {k} lights fit after refinement", diag)
        rms = float(np.sqrt(np.mean(res ** 2)))
        quality = _quality(k, rms, cand, runner, mode)
        diag.update({"inliers": k, "matched_lights": tuple(int(j) for j in pairs[:, 1]),
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


__all__ = ["Candidate", "LightsEstimator", "PatternMatcher", "ceiling_points", "view_mask",
           "fit_rigid_2d", "pixel_scale", "project_lights", "refine_pose"]
