"""The mount of an upward (lights) rig from a spin in place: no poses needed.

The vehicle turns on the spot under the site's ``lights`` (a differential drive about
its origin, the point the mount is measured from). The vehicle pose of frame k is then
``(cx, cy, yaw_k)`` with one unknown centre and an unknown heading per frame, and the
camera centre draws a circle about the centre whose radius and phase are the lever arm
``(mx, my)``. The fit is the upward fit's (:mod:`ceilkit.calib.mount_upward`: spot
centroids against the site's lights, in pixels) with the poses replaced by that model:
unknowns lean (ax, ay), lever arm and height (mx, my, mz), the centre and every yaw.

Observability: a spin determines the lever arm's length and its direction seen from the
camera, not the pan: turning every yaw by d and the pan by -d (and the lever arm with
it) predicts the same images (the planar hand-eye degeneracy). The pan must be given
(``--fix pan=DEG``, measured, or from a drive with poses, :func:`calibrate_mount_upward`)
and is recorded as given. A spin that is not in place (the centre wanders) leaves a
residual that refuses the fit; one of too few headings leaves a lever arm whose 1 sigma
refuses it.

Example::

    frames, yaws = load_placed_frames(Recording("spin1"), start_rig, site)
    res = calibrate_mount_spin(start_rig, site, frames, yaws, pan_rad=math.radians(4.0))
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.estimators.lights import LightsEstimator

from .mount_upward import (
    DEFAULT_LIGHT_DIAMETER_M,
    MAX_FIELD_DEG,
    MAX_RMS_UP_PX,
    MAX_SIGMA_UP,
    MIN_FRAMES,
    LightFrame,
    _Fit,
    covariance,
    lean_of,
    observe,
    predict_px,
    refuse_undetermined,
    rotation,
    to_mount,
)

# the fewest degrees a spin must turn through (in total, over its frames)
MIN_TURN_DEG = 90.0
# the centroid noise the start poses are checked against (px): a start mount whose
# lever arm or height is decimetres off misfits the lights by pixels
START_NOISE_PX = 10.0
# the false-refusal rate of the in-place test
IN_PLACE_ALPHA = 1e-3


@dataclass(frozen=True, eq=False)
class SpinResult:
    """The mount from a spin, each fitted parameter's 1 sigma (``tilt``, ``mx``, ``my``,
    ``mz``; rad / m), the residual, the spin's centre in W and the turn covered."""

    mount: Mount
    sigma: dict[str, float]
    rms_px: float
    frames_used: int
    sightings: int
    centre_m: tuple[float, float]
    turn_deg: float
    pan_rad: float

    def lines(self) -> list[str]:
        m, s = self.mount, self.sigma
        return [f"spin in place: {self.frames_used} frames, {self.sightings} light "
                f"sightings, {self.turn_deg:.0f} deg turned about ({self.centre_m[0]:.3f}, "
                f"{self.centre_m[1]:.3f}) m; residual {self.rms_px:.3f} px RMS",
                f"pan {math.degrees(self.pan_rad):.4f} deg as given (--fix pan: a spin "
                "does not determine it)",
                f"tilt {math.degrees(m.tilt_rad):.4f} deg +- "
                f"{math.degrees(s['tilt']):.4f}",
                f"x {m.x_m:.4f} m +- {s['mx']:.4f}, y {m.y_m:.4f} m +- {s['my']:.4f}, "
                f"z {m.z_m:.4f} m +- {s['mz']:.4f} (1 sigma)"]


class PosedFit(_Fit):
    """The upward fit with the vehicle poses among the unknowns: a subclass maps its
    parameters ``p`` to ``(theta, poses)`` in :meth:`split` (``theta`` = heading, ax,
    ay, mx, my, mz as :func:`~ceilkit.calib.mount_upward.rotation` and
    :func:`~ceilkit.calib.mount_upward.predict_px` take them; ``poses`` ``(K, 3)``)."""

    GATES = (30.0, 10.0, 5.0, 3.0)   # the association gates, px, shrinking

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def least_squares(self, p: np.ndarray, final: bool):
        """One solve from ``p`` (``final``: the last one, the covariance's)."""
        return least_squares(self.residuals, p, method="lm",
                             **({} if final else {"x_scale": 0.01}))

    def remeasure(self, p: np.ndarray) -> None:
        """Re-measure the residuals' scales after a solve (none here)."""

    def solve(self, p: np.ndarray, advice: str) -> tuple[np.ndarray, object, int]:
        """Associate at :attr:`GATES` and refit; the last solution and its sightings.
        ``advice``: where the sightings were too few and what to do, for the error."""
        sol = None
        for gate in self.GATES:
            n = self.associate(p, gate)
            if n < p.size:
                break
            sol = self.least_squares(p, final=False)
            p = sol.x
            self.remeasure(p)
        n = self.associate(p, self.GATES[-1])
        if sol is None or n < p.size:
            raise CalibrationError(
                f"only {n} light sightings matched the site's lights {advice} under more "
                "lights, check site.yaml's lights and the camera. Nothing written")
        sol = self.least_squares(p, final=True)
        return sol.x, sol, n

    def all_predictions(self, p: np.ndarray) -> list[np.ndarray]:
        theta, poses = self.split(p)
        R_vc, L = rotation(*theta[:3]), self.lights.shape[0]
        return [predict_px(self.rig, self.H, self.lights, np.repeat(pk[None], L, axis=0),
                           R_vc, theta[3:6], self.radius) for pk in poses]

    def pixel_residuals(self, p: np.ndarray) -> np.ndarray:
        fk, lk, px = self.assoc
        theta, poses = self.split(p)
        pr = predict_px(self.rig, self.H, self.lights[lk], poses[fk], rotation(*theta[:3]),
                        theta[3:6], self.radius)
        r = (pr - px).ravel()
        return np.where(np.isfinite(r), r, 50.0)


class _SpinFit(PosedFit):
    """Parameters ``p = (ax, ay, mx, my, mz, cx, cy, yaw_1 .. yaw_K)``, the heading held
    at ``pan``: one centre for every frame."""

    def __init__(self, rig: Rig, site: Site, frames: Sequence[LightFrame], pan: float,
                 radius_m: float):
        super().__init__(rig, site, frames, None, False, radius_m)
        self.site, self.pan = site, pan

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = len(self.frames)
        poses = np.column_stack([np.full(k, p[5]), np.full(k, p[6]), p[7:]])
        return np.r_[self.pan, p[:5]], poses

    def residuals(self, p: np.ndarray) -> np.ndarray:
        return self.pixel_residuals(p)


class _FreeFit(_SpinFit):
    """The same sightings with the mount held and every frame's pose free
    (``p = (x_k, y_k, yaw_k)`` per frame): the model a spin in place is nested in."""

    def __init__(self, spin: _SpinFit, p_spin: np.ndarray):
        super().__init__(spin.rig, spin.site, spin.frames, spin.pan, spin.radius)
        self.max_angle = spin.max_angle
        self.theta = np.r_[spin.pan, p_spin[:5]]
        self.assoc = spin.assoc

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.theta, p.reshape(-1, 3)


def in_place_test(fit: _SpinFit, p: np.ndarray) -> tuple[float, float]:
    """Did the vehicle turn in place? The F statistic of the spin model (one centre)
    against every frame's own position (the mount held), and its limit at
    :data:`IN_PLACE_ALPHA`: independent of the centroids' noise level."""
    from scipy.stats import f as f_dist

    free = _FreeFit(fit, p)
    _, poses = fit.split(p)
    r_spin = fit.residuals(p)
    r_free = least_squares(free.residuals, poses.ravel(), method="lm").fun
    rss_s, rss_f = float(r_spin @ r_spin), float(r_free @ r_free)
    extra = 2 * len(fit.frames) - 2
    dof = max(r_free.size - 3 * len(fit.frames) - 5, 1)
    F = ((rss_s - rss_f) / extra) / max(rss_f / dof, 1e-300)
    return F, float(f_dist.ppf(1.0 - IN_PLACE_ALPHA, extra, dof))


def load_placed_frames(recording, rig: Rig, site: Site, max_frames: int = 120
                       ) -> tuple[list[LightFrame], np.ndarray]:
    """A recording's spot frames (a spin, a drive) and each frame's starting vehicle pose
    ``(K, 3)`` from the lights method with ``rig`` (frames it cannot place are left
    out: their heading would have no start). The start rig is only approximate (its
    lever arm and height are what the fit finds), so the method's misfit checks are
    relaxed by :data:`START_NOISE_PX`: these poses only start the fit."""
    est = LightsEstimator(rig, site, {"noise_px": START_NOISE_PX,
                                      "max_residual_px": 3 * START_NOISE_PX})
    ks = list(range(len(recording)))
    if max_frames and len(ks) > max_frames:
        ks = [ks[int(i)] for i in np.linspace(0, len(ks) - 1, max_frames).round()]
    frames, poses = [], []
    for k in ks:
        f = recording.frame(k)
        e = est.estimate(f.image, f.t_ns)
        if not e.ok or e.x_m is None or e.y_m is None:
            continue
        frames.append(observe(rig, f.image, f.t_ns, f"frame {f.index}"))
        poses.append((e.x_m, e.y_m, e.yaw_rad))
    return frames, np.array(poses, float).reshape(-1, 3)


def _turn_deg(yaw: np.ndarray) -> float:
    """Degrees the headings cover (their unwrapped range, in frame order)."""
    u = np.unwrap(yaw)
    return float(np.degrees(u.max() - u.min())) if u.size else 0.0


def calibrate_mount_spin(rig: Rig, site: Site, frames: Sequence[LightFrame],
                         start_poses: np.ndarray, pan_rad: float, *,
                         light_diameter_m: float | None = None) -> SpinResult:
    """Fit lean, lever arm and height of an upward rig from a spin in place, the pan
    held at ``pan_rad`` (see the module doc).

    ``start_poses``: ``(K, 3)`` each frame's vehicle pose with ``rig`` (:func:`load_placed_frames`):
    the centre starts at their mean, each yaw at its own.

    Raises:
        ConfigError: the site has no lights; frames and poses of different lengths.
        CalibrationError: too few frames or too little turn, a residual above
            :data:`MAX_RMS_UP_PX` (not a spin in place, or a wrong map or camera), a
            parameter whose 1 sigma is above its limit. Nothing is written by callers.
    """
    if not site.has_lights:
        raise ConfigError(None, "site", "the spin fit needs the site's lights")
    P = np.asarray(start_poses, float).reshape(-1, 3)
    if P.shape[0] != len(frames):
        raise ConfigError(None, "start_poses", f"expected {len(frames)} poses, found "
                          f"{P.shape[0]}")
    turn = _turn_deg(P[:, 2])
    if len(frames) < MIN_FRAMES or turn < MIN_TURN_DEG:
        raise CalibrationError(
            f"the spin has {len(frames)} frames placed by the lights over {turn:.0f} deg "
            f"(at least {MIN_FRAMES} frames over {MIN_TURN_DEG:.0f} deg): turn a full "
            "circle on the spot under the lights. Nothing written")
    diam = light_diameter_m or site.light_diameter_m or DEFAULT_LIGHT_DIAMETER_M
    fit = _SpinFit(rig, site, frames, pan_rad, 0.5 * diam)
    fit.max_angle = math.radians(MAX_FIELD_DEG)
    m0 = rig.mount
    # the lights placed the vehicle as if the lever arm were the start's: the centre is
    # the mean of those places over the turn
    p = np.r_[0.0, 0.0, m0.x_m, m0.y_m, m0.z_m, P[:, 0].mean(), P[:, 1].mean(), P[:, 2]]
    p, sol, n = fit.solve(p, "in the spin: spin")
    r = fit.residuals(p)
    rms = math.sqrt(float(np.mean(r * r)))
    if rms > MAX_RMS_UP_PX:
        raise CalibrationError(
            f"the spin fit leaves {rms:.2f} px RMS (refused above {MAX_RMS_UP_PX:g} px): "
            "the vehicle did not turn in place (its origin moved), or the site's lights "
            "or the camera disagree with the images. Nothing written")
    F, F_lim = in_place_test(fit, p)
    if F > F_lim:
        raise CalibrationError(
            f"the vehicle did not turn in place: one centre explains the frames worse "
            f"than each frame's own position (F {F:.1f} above {F_lim:.1f}); spin on the "
            "spot (a differential drive about its origin). Nothing written")
    cov = covariance(sol.jac, float(r @ r) / max(r.size - p.size, 1), fit.assoc[2], rig)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    lean, s_lean, significant = lean_of(p[0], p[1], cov[0:2, 0:2])
    sigma = {"tilt": s_lean, "mx": float(sd[2]), "my": float(sd[3]), "mz": float(sd[4])}
    refuse_undetermined([
        ("tilt", s_lean, MAX_SIGMA_UP["lean"], "frames with lights near the image edges"),
        ("mx", sigma["mx"], MAX_SIGMA_UP["mx"], "a wider turn (a full circle)"),
        ("my", sigma["my"], MAX_SIGMA_UP["my"], "a wider turn (a full circle)"),
        ("z", sigma["mz"], MAX_SIGMA_UP["mz"], "frames that see more lights at once")])
    mount = to_mount(pan_rad, p[0], p[1], p[2], p[3], p[4], level=not significant)
    return SpinResult(mount, sigma, rms, len(set(fit.assoc[0].tolist())), n,
                      (float(p[5]), float(p[6])), _turn_deg(p[7:]), pan_rad)


__all__ = ["MIN_TURN_DEG", "SpinResult", "calibrate_mount_spin", "load_placed_frames"]
