"""The mount of an upward (lights) rig from a drive under the site's lights with no
poses: the light map places the camera, the vehicle's wheels constrain the motion.

A wheeled vehicle does not move sideways (a differential or Ackermann drive about its
rear axle, the point the mount is measured from): between two frames its origin moves
along its heading (the chord of a constant-curvature arc points along the mean of the
two headings). With every frame's vehicle pose unknown, that constraint is what ties
the camera's path to the vehicle's and makes the mount observable:

* the camera's lateral velocity in V is ``w * mx`` (w the turn rate): turns give ``mx``;
* a wrong pan tilts every straight stretch sideways: straight stretches give the pan;
* the camera's forward velocity is ``v - w * my`` with the speed ``v`` unknown: a drive
  alone does not determine ``my``; hold it (``--fix my=VALUE``: measured, or from a spin
  in place, :mod:`ceilkit.calib.mount_spin`), recorded as held.

The fit is the upward fit's (:mod:`ceilkit.calib.mount_upward`: spot centroids
against the site's lights, in pixels, over their measured scatter) with every frame's
pose among the unknowns, plus one residual per consecutive pair of frames: the
sideways step over its 1 sigma (:data:`SLIP_FLOOR_M` plus a slip angle, measured from
the fit's own steps, times the step's length). Lean, pan, ``mx`` and the height come with their
1 sigma; each is refused (naming what to add) when the drive does not determine it.

Example::

    frames, start = load_placed_frames(Recording("drive1"), start_rig, site)   # poses to start
    res = calibrate_mount_drive(start_rig, site, frames, start, my_m=0.0)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError

from .mount_spin import PosedFit
from .mount_upward import (
    DEFAULT_LIGHT_DIAMETER_M,
    MAX_FIELD_DEG,
    MAX_RMS_UP_PX,
    MAX_SIGMA_UP,
    MIN_FRAMES,
    LightFrame,
    covariance,
    lean_of,
    refuse_undetermined,
    to_mount,
)

# the vehicle's sideways step between two frames has a 1 sigma of SLIP_FLOOR_M plus a
# slip angle (wheel slip, a path whose curvature changes between frames) times the
# step's length; the angle is measured from the fit's own steps (as the pixel scatter
# is), starting at SLIP_ANGLE_START
SLIP_FLOOR_M = 2e-4
SLIP_ANGLE_START = 0.01
# consecutive frames further apart than this many median frame gaps are not tied
MAX_GAP_FACTOR = 3.0


@dataclass(frozen=True, eq=False)
class DriveResult:
    """The mount from a drive without poses, each fitted parameter's 1 sigma (``pan``,
    ``tilt``, ``mx``, ``mz``; rad / m), the pixel residual and the sideways steps'."""

    mount: Mount
    sigma: dict[str, float]
    rms_px: float
    slip_angle_rad: float
    frames_used: int
    sightings: int

    def lines(self) -> list[str]:
        m, s = self.mount, self.sigma
        return [f"drive, no poses: {self.frames_used} frames, {self.sightings} light "
                f"sightings; residual {self.rms_px:.3f} px RMS, sideways steps "
                f"{math.degrees(self.slip_angle_rad):.3f} deg RMS of their length",
                f"pan {math.degrees(m.pan_rad + m.swing_rad):.4f} deg +- "
                f"{math.degrees(s['pan']):.4f}, tilt {math.degrees(m.tilt_rad):.4f} deg +- "
                f"{math.degrees(s['tilt']):.4f}",
                f"x {m.x_m:.4f} m +- {s['mx']:.4f}, z {m.z_m:.4f} m +- {s['mz']:.4f} "
                f"(1 sigma); y {m.y_m:.4f} m as given (--fix my: a drive does not "
                "determine it)"]


class _DriveFit(PosedFit):
    """Parameters ``p = (heading, ax, ay, mx, mz, x_1, y_1, yaw_1, ...)``, ``my`` held."""

    def __init__(self, rig: Rig, site: Site, frames: Sequence[LightFrame], my: float,
                 radius_m: float):
        super().__init__(rig, site, frames, None, False, radius_m)
        self.my = my
        self.sigma_px = 0.2
        self.slip_angle = SLIP_ANGLE_START
        self.pairs = _pairs(self.t)

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.r_[p[:4], self.my, p[4]], p[5:].reshape(-1, 3)

    GATES = (30.0, 10.0, 5.0, 3.0, 3.0)   # the last twice: the scales settle

    def least_squares(self, p: np.ndarray, final: bool):
        """A sparse solve: each frame's pose touches its own sightings and steps."""
        return least_squares(self.residuals, p, method="trf", jac_sparsity=self.sparsity(),
                             x_scale="jac")

    def steps(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each tied pair's sideways step of the vehicle's origin and the step's
        length, metres."""
        _, poses = self.split(p)
        a, b = poses[self.pairs[:, 0]], poses[self.pairs[:, 1]]
        mid = a[:, 2] + 0.5 * np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))
        d = b[:, :2] - a[:, :2]
        return -np.sin(mid) * d[:, 0] + np.cos(mid) * d[:, 1], np.hypot(d[:, 0], d[:, 1])

    def slips(self, p: np.ndarray) -> np.ndarray:
        """The sideways steps over their 1 sigma."""
        side, length = self.steps(p)
        return side / (SLIP_FLOOR_M + self.slip_angle * length)

    def remeasure(self, p: np.ndarray) -> None:
        """The pixel scatter and the slip angle from the fit's own residuals."""
        self.sigma_px = max(math.sqrt(float(np.mean(self.pixel_residuals(p) ** 2))), 0.02)
        side, length = self.steps(p)
        moving = length > 10 * SLIP_FLOOR_M
        if np.any(moving):
            self.slip_angle = max(math.sqrt(float(np.mean(
                (side[moving] / length[moving]) ** 2))), 1e-4)

    def residuals(self, p: np.ndarray) -> np.ndarray:
        """Pixels over their scatter, then the sideways steps over theirs."""
        return np.r_[self.pixel_residuals(p) / self.sigma_px, self.slips(p)]

    def sparsity(self) -> lil_matrix:
        fk = self.assoc[0]
        n_px, n_par = 2 * fk.size, 5 + 3 * len(self.frames)
        S = lil_matrix((n_px + self.pairs.shape[0], n_par), dtype=int)
        S[:n_px, :5] = 1
        for j, k in enumerate(np.repeat(fk, 2)):
            S[j, 5 + 3 * k:8 + 3 * k] = 1
        for i, (a, b) in enumerate(self.pairs):
            S[n_px + i, 5 + 3 * a:8 + 3 * a] = 1
            S[n_px + i, 5 + 3 * b:8 + 3 * b] = 1
        return S


def _pairs(t_ns: np.ndarray) -> np.ndarray:
    """``(M, 2)`` consecutive frames close enough in time to be tied."""
    if t_ns.size < 2:
        return np.zeros((0, 2), int)
    gap = np.diff(t_ns.astype(float))
    ok = gap <= MAX_GAP_FACTOR * float(np.median(gap))
    k = np.flatnonzero(ok)
    return np.stack([k, k + 1], axis=1)


def calibrate_mount_drive(rig: Rig, site: Site, frames: Sequence[LightFrame],
                          start_poses: np.ndarray, my_m: float, *,
                          light_diameter_m: float | None = None) -> DriveResult:
    """Fit pan, lean, ``mx`` and the height of an upward rig from a drive under the
    lights with no poses, ``my`` held at ``my_m`` (see the module doc).

    ``start_poses``: ``(K, 3)`` each frame's vehicle pose with ``rig``
    (:func:`~ceilkit.calib.mount_spin.load_placed_frames`); frames in time order.

    Raises:
        ConfigError: the site has no lights; frames and poses of different lengths.
        CalibrationError: too few frames, a residual above :data:`MAX_RMS_UP_PX`, a
            parameter whose 1 sigma is above its limit (naming what to add).
    """
    if not site.has_lights:
        raise ConfigError(None, "site", "the drive fit needs the site's lights")
    P = np.asarray(start_poses, float).reshape(-1, 3)
    if P.shape[0] != len(frames):
        raise ConfigError(None, "start_poses", f"expected {len(frames)} poses, found "
                          f"{P.shape[0]}")
    if len(frames) < MIN_FRAMES:
        raise CalibrationError(f"only {len(frames)} frames placed by the lights (at least "
                               f"{MIN_FRAMES}): drive longer under the lights. Nothing "
                               "written")
    diam = light_diameter_m or site.light_diameter_m or DEFAULT_LIGHT_DIAMETER_M
    fit = _DriveFit(rig, site, frames, my_m, 0.5 * diam)
    fit.max_angle = math.radians(MAX_FIELD_DEG)
    m0 = rig.mount
    p = np.r_[m0.pan_rad + m0.swing_rad, 0.0, 0.0, m0.x_m, m0.z_m, P.ravel()]
    p, sol, n = fit.solve(p, "over the drive: drive")
    r_px = fit.pixel_residuals(p)
    rms = math.sqrt(float(np.mean(r_px * r_px)))
    if rms > MAX_RMS_UP_PX:
        raise CalibrationError(
            f"the drive fit leaves {rms:.2f} px RMS (refused above {MAX_RMS_UP_PX:g} px): "
            "the site's lights or the camera disagree with the images. Nothing written")
    r = fit.residuals(p)
    s2 = float(r @ r) / max(r.size - p.size, 1)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    cov = covariance(J, s2, fit.assoc[2], rig, px_scale=fit.sigma_px)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    lean, s_lean, significant = lean_of(p[1], p[2], cov[1:3, 1:3])
    sigma = {"pan": float(sd[0]), "tilt": s_lean, "mx": float(sd[3]), "mz": float(sd[4])}
    refuse_undetermined([
        ("pan", sigma["pan"], MAX_SIGMA_UP["heading"], "longer straight stretches"),
        ("tilt", s_lean, MAX_SIGMA_UP["lean"], "frames with lights near the image edges"),
        ("mx", sigma["mx"], MAX_SIGMA_UP["mx"], "more and sharper turns"),
        ("z", sigma["mz"], MAX_SIGMA_UP["mz"], "frames that see more lights at once")])
    mount = to_mount(p[0], p[1], p[2], p[3], my_m, p[4], level=not significant)
    return DriveResult(mount, sigma, rms, fit.slip_angle, len(set(fit.assoc[0].tolist())),
                       n)


__all__ = ["DriveResult", "calibrate_mount_drive"]
