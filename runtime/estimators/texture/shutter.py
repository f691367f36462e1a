"""The ``texture`` method under a rolling shutter: each feature's place on the ceiling
plane put back to the frame's stamp (docs/methods/texture.md, "Rolling shutter").

A rolling-shutter camera exposes row ``v`` at ``tau(v)`` after the stamp
(:func:`~ceilkit.runtime.geometry.shutter.row_times_s`). A feature the rectified patch
places at ``q`` (m, in V) was seen from the vehicle's pose at ``t + tau``; at constant
velocity ``(vx, vy, w)`` (W) that pose is the stamp's moved by ``(vx tau, vy tau, w tau)``,
so the same ceiling point in the stamp's V is

    q' = R(w tau) q + R(-yaw) (vx, vy) tau

(``yaw`` the vehicle's heading in W). The velocity is the prior's
(:func:`~ceilkit.runtime.estimators.rows.row_motion`); without one it is taken as zero
with the ``unknown_*`` sigmas. Either way the fit's covariance grows by what one sigma
of each velocity component moves the pose (:func:`widened`), as in the other methods.

Example::

    ro = Readout.of(rig, 2.7, options, prior)          # None for a global shutter
    tau = ro.times(q_v)                                # (N,) s, each feature's row time
    q_v = ro.unrolled(q_v, tau, yaw)                   # in the stamp's V
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.rows import ShutterOptions, row_motion
from ceilkit.runtime.estimators.texture.match import MapFit
from ceilkit.runtime.geometry.ceiling import on_ceiling, project_px
from ceilkit.runtime.geometry.shutter import row_times_s


@dataclass(frozen=True, eq=False)
class Readout:
    """One frame's row model: where the rig images a ceiling point of V, the readout
    time and the motion the rows are corrected with.

    Attributes:
        rig: the rig (``camera``, ``mount``); ``ceiling_m``: the ceiling's height, m.
        readout_s: top row to bottom row, s (> 0).
        velocity: ``(vx m/s, vy m/s, yaw rate rad/s)`` in W (zero when unknown).
        sigma: their 1-sigma (the ``unknown_*`` options' when unknown).
    """

    rig: Any
    ceiling_m: float
    readout_s: float
    velocity: tuple[float, float, float]
    sigma: tuple[float, float, float]

    @classmethod
    def of(cls, rig: Any, ceiling_m: float, options: ShutterOptions,
           prior: PoseEstimate | None) -> Readout | None:
        """The model for a frame with this prior, or None for a global shutter
        (``readout_ms`` 0)."""
        motion = row_motion(options, prior)
        if motion is None:
            return None
        return cls(rig, float(ceiling_m), options.readout_ms / 1e3, *motion)

    def times(self, q_v: np.ndarray) -> np.ndarray:
        """``(N,)`` the row time of features at ceiling points ``q_v`` ``(N, 2)`` of V
        (as the rectified patch placed them), s after the stamp; 0 for a point the
        lens does not image (none the patch holds)."""
        if len(q_v) == 0:
            return np.zeros(0)
        cam, mount = self.rig.camera, self.rig.mount
        px = project_px(cam, np.asarray(mount.R_vehicle_cam, float),
                        np.asarray(mount.t_vehicle_cam, float),
                        on_ceiling(np.asarray(q_v, float), self.ceiling_m), np.zeros((1, 3)))[0]
        tau = row_times_s(px[:, 1], cam.height, self.readout_s)
        return np.where(np.isfinite(tau), tau, 0.0)

    def unrolled(self, q_v: np.ndarray, tau: np.ndarray, yaw: float | None,
                 velocity: tuple[float, float, float] | None = None) -> np.ndarray:
        """``(N, 2)`` features ``q_v`` seen at row times ``tau`` put in the stamp's V
        (the module's ``q'``) at ``velocity`` (default this frame's). ``yaw`` None:
        the turn only (the translation needs the heading; its share, ``|v| tau``, is
        6 mm at 0.5 m/s and a 25 ms readout)."""
        vx, vy, w = self.velocity if velocity is None else velocity
        a = w * tau
        c, s = np.cos(a), np.sin(a)
        q = np.asarray(q_v, float)
        out = np.column_stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]])
        if yaw is not None and (vx or vy):
            cy, sy = math.cos(yaw), math.sin(yaw)
            out[:, 0] += (cy * vx + sy * vy) * tau
            out[:, 1] += (-sy * vx + cy * vy) * tau
        return out


def widened(fit: MapFit, ro: Readout, q_raw: np.ndarray, tau: np.ndarray) -> MapFit:
    """``fit`` (on the pairs ``used`` of features ``q_raw`` as observed, ``tau`` their
    row times) with its covariance grown by the velocity's uncertainty: for each
    component moved by its sigma, the move of the rigid least squares' pose (to first
    order: ``d = (JᵀJ)⁻¹ Jᵀ e``, ``e`` the inliers' moves in W: ``(σ tau, 0)``,
    ``(0, σ tau)`` and ``σ tau perp(R q)``), its outer product added."""
    used = fit.used
    if len(used) < 3:
        return fit
    t = tau[used]
    yaw = fit.pose[2]
    q = ro.unrolled(q_raw[used], t, yaw)
    c, s = math.cos(yaw), math.sin(yaw)
    rx, ry = c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]
    n = float(len(used))
    jtj = np.array([[n, 0.0, -ry.sum()], [0.0, n, rx.sum()],
                    [-ry.sum(), rx.sum(), float(np.sum(rx * rx + ry * ry))]])
    sx, sy, sw = ro.sigma
    # Jᵀe for each component's moves e (columns): rows x, y, yaw (J_i = [I | perp(Rq_i)])
    jte = np.array([[sx * t.sum(), 0.0, -sw * np.sum(t * ry)],
                    [0.0, sy * t.sum(), sw * np.sum(t * rx)],
                    [-sx * np.sum(t * ry), sy * np.sum(t * rx),
                     sw * np.sum(t * (rx * rx + ry * ry))]])
    try:
        d = np.linalg.solve(jtj, jte)
    except np.linalg.LinAlgError:
        return fit
    return dataclasses.replace(fit, cov=np.array(fit.cov, float) + d @ d.T)


__all__ = ["Readout", "widened"]
