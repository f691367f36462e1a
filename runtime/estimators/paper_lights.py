"""The paper's ceiling-lights pipeline, as literally as its text allows (a baseline).

Roh, Sung, Kang, Chung, "Point pattern matching based visual global localization
using ceiling lights", ASCC 2011. Steps (Fig. 1 of the paper):

1. **Thresholding** (§II.A): Niblack over 64 x 64 sub-images (§IV), ``T = mean + k std``.
2. **Identification** (§II.B): each candidate's perception index
   ``L = (I_o - I_b) A^0.33 / (1.97 I_b^0.72)`` (Eq. 6, object and dilated-ring means,
   Eqs. 7-9); ``L >= min_level`` is a light. Its position is the region's centroid.
3. **Undistortion of the positions only** (§III.1, Eqs. 10-12), then Eq. 14:
   ``Q_real = K⁻¹ q Z`` with ``Z`` the camera-to-ceiling height: the camera is taken to
   look straight up (only the mount's in-plane rotation and offset are applied).
4. **Point pattern matching** (§III.2, after Chang et al. 1997): every model pair and
   every observed pair vote for a scale and a rotation ``(s, θ)``; the peak's pairs
   vote for a translation; correspondences are the nearest map lights.
5. **Least squares** (§III.3, Eq. 15): the similarity ``(t_x, t_y, s, θ)`` from the
   matched pairs; the vehicle pose is its rotation and translation.

Where the text is silent (``k``, the index threshold, bin sizes, the scale range) the
choices are named options. No ambiguity test, no refinement in pixels, no quality
model beyond the share of observed lights that matched: those are what ``lights``
adds (``docs/methods/lights.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import (
    Estimate,
    Estimator,
    EstimatorOptions,
    PoseEstimate,
)
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.spots import SpotParams, regions_to_spots, tile_niblack_mask
from ceilkit.runtime.geometry.fits import fit_similarity_2d
from ceilkit.runtime.geometry.rotations import wrap_pi

NAME = "paper-lights"


@dataclass(frozen=True)
class PaperLightsOptions(EstimatorOptions):
    """What a user may set for ``paper-lights`` (the choices the paper leaves open).

    Attributes:
        min_contrast: the shared blank-frame check (0: off; a blank frame is then
            ``no_lights``).
        k: Niblack's weight on the tile's standard deviation.
        tile_px: Niblack sub-image size (the paper: 64).
        min_level: least perception index of a light.
        max_spots: the paper's "maximum 11 spot lighting target model".
        scale_min, scale_max: the similarity scales the matching accepts.
        gate_m: correspondence distance after the transform.
        angle_bin_deg, scale_bin, pos_bin_m: the vote bins of rotation, scale, translation.
    """

    min_contrast: float = 0.0
    k: float = 2.5
    tile_px: int = 64
    min_level: float = 1.0
    max_spots: int = 11
    scale_min: float = 0.85
    scale_max: float = 1.15
    gate_m: float = 0.15
    angle_bin_deg: float = 2.0
    scale_bin: float = 0.02
    pos_bin_m: float = 0.2


class PaperLightsEstimator(Estimator):
    """The paper's pipeline on the Estimator contract.

    Args:
        rig, site: the site needs ``lights``.
        options: :class:`PaperLightsOptions`, a mapping of them, or ``None``.
    """

    name = NAME
    Options: ClassVar[type[EstimatorOptions]] = PaperLightsOptions
    site_sections = ("lights",)

    def __init__(self, rig: Rig, site: Site,
                 options: PaperLightsOptions | Mapping[str, Any] | None = None) -> None:
        if not site.has_lights:
            raise ConfigError(site.source, "lights",
                              "the paper-lights method needs at least one light in the map")
        super().__init__(rig, site, options)
        check_rig_site(rig, site)
        o = self.options
        self.params = SpotParams(min_area_px=1, max_area_px=100_000, min_level=o.min_level,
                                 min_relative_contrast=0.0, min_axis_ratio=0.0,
                                 max_spots=o.max_spots)
        self.angle_bin_rad = math.radians(o.angle_bin_deg)
        lights = np.asarray(site.lights_m, float)
        self.lights_w = lights[~site.ignored(lights)]    # SPEC §2: ignore regions unused
        if self.lights_w.shape[0] == 0:
            raise ConfigError(site.source, "ignore", "every light of the map lies in an "
                              "ignore region: paper-lights has nothing to use")
        self.pair_i, self.pair_j = np.triu_indices(self.lights_w.shape[0], 1)
        # camera (x, y) -> vehicle (x, y) for a camera looking up
        self.R2_vehicle_cam = rig.mount.R_vehicle_cam[:2, :2]
        self.cam_to_ceiling_m = site.ceiling_height_m - rig.mount.z_m

    def observed_points(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(centroids_px (N, 2), Q_real in V (N, 2))`` of the identified lights."""
        grey = to_grey(np.asarray(image))
        mask = tile_niblack_mask(grey, self.options.tile_px, self.options.k)
        # the paper's steps: every region measured, a light cut by the frame's edge too
        spots = regions_to_spots(grey, mask, self.params, weighted=False,
                                 rethreshold=False, relative=False, drop_cut=False)
        if len(spots) == 0:
            return np.zeros((0, 2)), np.zeros((0, 2))
        xy = self.rig.camera.unproject(spots.centroids_px)      # Eqs. 10-12 inverted
        q_cam = xy * self.cam_to_ceiling_m                         # Eq. 14
        q_v = q_cam @ self.R2_vehicle_cam.T + self.rig.mount.t_vehicle_cam[None, :2]
        return spots.centroids_px, q_v

    def _match(self, q: np.ndarray) -> np.ndarray:
        """``(K, 2)`` (observed, map) correspondences by pair voting (Chang et al.)."""
        a, b = np.triu_indices(q.shape[0], 1)
        vq = q[b] - q[a]
        vp = self.lights_w[self.pair_j] - self.lights_w[self.pair_i]
        dq = np.linalg.norm(vq, axis=1)
        dp = np.linalg.norm(vp, axis=1)
        aq = np.arctan2(vq[:, 1], vq[:, 0])
        ap = np.arctan2(vp[:, 1], vp[:, 0])
        s = dp[None, :] / np.maximum(dq[:, None], 1e-9)                 # (Pq, Pm)
        th = wrap_pi(ap[None, :] - aq[:, None])
        # both orientations of each map pair
        s = np.concatenate([s, s], axis=1)
        th = np.concatenate([th, wrap_pi(th + math.pi)], axis=1)
        oq = np.repeat(np.arange(a.size)[:, None], s.shape[1], axis=1)
        om = np.tile(np.concatenate([np.arange(vp.shape[0]), -1 - np.arange(vp.shape[0])]),
                     (a.size, 1))
        ok = (s >= self.options.scale_min) & (s <= self.options.scale_max)
        if not np.any(ok):
            return np.zeros((0, 2), int)
        s, th, oq, om = s[ok], th[ok], oq[ok], om[ok]
        ks = np.floor(s / self.options.scale_bin).astype(np.int64)
        kt = np.floor((th + math.pi) / self.angle_bin_rad).astype(np.int64)
        key = ks * 10_000 + kt
        vals, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        sel = inv.ravel() == int(np.argmax(cnt))
        s0 = float(np.median(s[sel]))
        t_peak = math.atan2(np.sin(th[sel]).mean(), np.cos(th[sel]).mean())
        # pairs have no direction: the peak at θ has a twin at θ + π; the translation
        # votes decide between them
        best = None
        for t0 in (t_peak, wrap_pi(t_peak + math.pi)):
            near = np.abs(wrap_pi(th - t0)) < self.angle_bin_rad
            near &= np.abs(s - s0) < self.options.scale_bin
            c, n = math.cos(t0), math.sin(t0)
            qa = q[a[oq[near]]]
            mi = om[near]
            m = np.abs(mi) - (mi < 0)
            pa = np.where((mi >= 0)[:, None], self.lights_w[self.pair_i[m]],
                          self.lights_w[self.pair_j[m]])
            t = pa - s0 * np.stack([c * qa[:, 0] - n * qa[:, 1],
                                    n * qa[:, 0] + c * qa[:, 1]], 1)
            kx = np.floor(t[:, 0] / self.options.pos_bin_m).astype(np.int64)
            ky = np.floor(t[:, 1] / self.options.pos_bin_m).astype(np.int64)
            _, tinv, tcnt = np.unique(kx * 100_000 + ky, return_inverse=True,
                                      return_counts=True)
            k = int(np.argmax(tcnt))
            if best is None or tcnt[k] > best[0]:
                best = (int(tcnt[k]), t0, np.median(t[tinv.ravel() == k], axis=0))
        _, t0, tt = best
        c, n = math.cos(t0), math.sin(t0)
        pw = s0 * np.stack([c * q[:, 0] - n * q[:, 1], c * q[:, 1] + n * q[:, 0]], 1) + tt
        d = np.linalg.norm(pw[:, None] - self.lights_w[None], axis=2)
        j = np.argmin(d, axis=1)
        good = d[np.arange(len(j)), j] < self.options.gate_m
        return np.stack([np.nonzero(good)[0], j[good]], axis=1)

    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        """The vehicle pose from a checked frame (``prior`` is ignored: the paper uses
        none). Failures: ``no_lights``, ``too_few_lights``, ``no_match``."""
        px, q = self.observed_points(grey)
        diag: dict[str, Any] = {"spots": int(q.shape[0])}
        if q.shape[0] == 0:
            return self.fail(t_ns, "no_lights", "no light found in the frame", **diag)
        if q.shape[0] < 3:
            return self.fail(t_ns, "too_few_lights", f"{q.shape[0]} lights found", **diag)
        pairs = self._match(q)
        if pairs.shape[0] < 3 or len(set(pairs[:, 1].tolist())) < 3:
            return self.fail(t_ns, "no_match", "fewer than 3 lights matched", **diag)
        s, theta, t = fit_similarity_2d(q[pairs[:, 0]], self.lights_w[pairs[:, 1]])
        res = (s * (q[pairs[:, 0]] @ np.array([[math.cos(theta), math.sin(theta)],
                                               [-math.sin(theta), math.cos(theta)]]))
               + t - self.lights_w[pairs[:, 1]])
        rms = float(np.sqrt((res ** 2).sum(1).mean()))
        diag.update({"inliers": int(pairs.shape[0]), "scale": s, "rms_m": rms})
        quality = float(pairs.shape[0] / q.shape[0])
        return PoseEstimate(t_ns, NAME, float(t[0]), float(t[1]), float(wrap_pi(theta)),
                            quality, None, None, diag)


__all__ = ["PaperLightsEstimator", "PaperLightsOptions"]
