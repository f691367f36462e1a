"""Mount calibration for an upward (lights) rig: pan, lean, lever arm and height.

The camera looks (nearly) straight up at spot lights whose centres the site map
gives (``lights``, SPEC §2). The vehicle's poses come from ``truth.csv`` or any pose
table (motion capture, a total station), at the frames' stamps or at their own
stamps (then interpolated, with the time offset estimated, see :class:`StampedPoses`).

Model (SPEC §1). The rotation is parametrized without the singularity of SPEC's
angles at tilt 90 deg: ``R_VC = Rz(heading) · Exp([ax, ay, 0]) · R_up`` with
``R_up = Ry(-90°) R0`` (the camera looking straight up) and ``(ax, ay)`` the lean of
the optical axis. The centre is ``(mx, my, mz)`` in V. A light at ``(Lx, Ly, H)`` in
W is seen at ``project(R_WC^T (L - c))`` with ``R_WC = Rz(yaw) R_VC`` and
``c = (x, y, 0) + Rz(yaw) (mx, my, mz)``. Residuals are pixel distances to the spot
centroids, the predicted point being the area centroid of the projected light disc
(not the projection of its centre: an off-axis disc's image is not symmetric).

The fit is Gauss-Newton/Levenberg-Marquardt (scipy) over ``(heading, ax, ay, mx, my,
mz[, offset])``, started by a search over the heading, with the spot-light
associations re-made at shrinking gates. 1 sigma: ``s^2 (J^T J)^-1`` with ``s^2`` the
residual variance per degree of freedom.

Written as SPEC's angles: tilt is the elevation of the fitted optical axis; when the
lean is within ``LEAN_SIGMAS`` of its sigma of zero (or below 0.001 deg) the mount is
written at tilt 90 deg with ``pan = heading`` and swing 0 (SPEC: at tilt 90 only
``pan + swing`` is observable, reported as pan); otherwise pan is the axis' azimuth
and swing the rest, so that ``pan + swing`` is the heading.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.features.spots import detect_spots
from ceilkit.runtime.geometry.rotations import R_vehicle_cam, rot_z

from .poses import StampedPoses, load_pose_csv

R_UP = R_vehicle_cam(0.0, math.pi / 2, 0.0)
PARAMS_UP = ("heading", "ax", "ay", "mx", "my", "mz")
# a fitted parameter whose 1 sigma exceeds this is not determined by the data: refused
MAX_SIGMA_UP = {"heading": math.radians(0.1), "lean": math.radians(0.25), "mx": 0.005,
                "my": 0.005, "mz": 0.005, "offset": 0.002}
# a fit whose residual RMS exceeds this has associated the wrong lights or has wrong poses
MAX_RMS_UP_PX = 1.0
LEAN_SIGMAS = 3.0
MIN_FRAMES = 5
DEFAULT_LIGHT_DIAMETER_M = 0.16
MAX_FIELD_DEG = 90.0    # spots at most this far off the optical axis are used
# the spot centroids may all sit this far off together, as a radial scale about the
# principal point (1 sigma, relative): vignetting and blur pull intensity-weighted
# centroids toward the image centre. Measured on rendered drives (configs/lights,
# vignetting 0.3, blur 0.8 px): the fitted height comes out 0.6 mm low at 2.45 m below
# the ceiling; with vignetting 0, 0.2 mm; a scale of 1e-4 moves it 0.6 mm. Added to the
# covariance through the parameters' sensitivity to such a scale.
SYSTEMATIC_SCALE = 1.2e-4
# ... and as a common rotation about the principal point (1 sigma, rad): on the same
# drives the heading comes out 0.0009-0.0023 deg high (3 seeds) against a statistical
# 1 sigma of 0.0007 deg
SYSTEMATIC_ROTATION = 4.0e-5
_DISC_POINTS = 24


@dataclass(frozen=True, eq=False)
class LightFrame:
    """One frame's spot centroids (distorted px, ``(N, 2)``) and its stamp."""

    t_ns: int
    spots_px: np.ndarray
    label: str = ""


@dataclass(frozen=True, eq=False)
class UpwardResult:
    """The fitted mount, each parameter's 1 sigma and the report.

    ``sigma``: by name (``pan`` = the heading ``pan + swing``, ``tilt``, ``mx``, ``my``,
    ``mz``, ``offset`` in seconds when estimated), radians / metres.
    """

    mount: Mount
    sigma: dict[str, float]
    rms_px: float
    frames: int
    matches: int
    offset_s: float | None = None
    lean_rad: float = 0.0
    lean_significant: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def heading_rad(self) -> float:
        return self.mount.pan_rad + self.mount.swing_rad

    def lines(self) -> list[str]:
        m, s = self.mount, self.sigma
        out = [f"upward rig: {self.matches} light sightings in {self.frames} frames, "
               f"residual RMS {self.rms_px:.3f} px",
               f"pan   {math.degrees(self.heading_rad):9.4f} deg   +- "
               f"{math.degrees(s['pan']):.4f} deg (1 sigma; pan + swing, SPEC's heading "
               "about the vertical)",
               f"tilt  {math.degrees(m.tilt_rad):9.4f} deg   +- "
               f"{math.degrees(s['tilt']):.4f} deg (1 sigma)"
               + ("" if self.lean_significant else
                  f"; lean {math.degrees(self.lean_rad):.4f} deg is within "
                  f"{LEAN_SIGMAS:g} sigma of 0: written at 90 with swing 0"),
               f"swing {math.degrees(m.swing_rad):9.4f} deg",
               f"x     {m.x_m:9.4f} m    +- {1000 * s['mx']:.2f} mm (1 sigma)",
               f"y     {m.y_m:9.4f} m    +- {1000 * s['my']:.2f} mm (1 sigma)",
               f"z     {m.z_m:9.4f} m    +- {1000 * s['mz']:.2f} mm (1 sigma; camera "
               "height above the floor)"]
        if self.offset_s is not None:
            out.append(f"pose time offset {1000 * self.offset_s:+.3f} ms +- "
                       f"{1000 * s['offset']:.3f} ms (1 sigma; pose time = frame stamp + "
                       "offset)")
        return out + self.notes


# ------------------------------------------------------------------------------ model
def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(th) / th * K + (1 - math.cos(th)) / th ** 2 * K @ K


def rotation(heading: float, ax: float, ay: float) -> np.ndarray:
    """``R_VC = Rz(heading) Exp([ax, ay, 0]) R_up``."""
    return rot_z(heading) @ _exp_so3(np.array([ax, ay, 0.0])) @ R_UP


def to_mount(heading: float, ax: float, ay: float, mx: float, my: float, mz: float,
             level: bool) -> Mount:
    """SPEC's mount angles of the fitted rotation; ``level``: written at tilt 90."""
    mx, my, mz = float(mx), float(my), float(mz)
    if level:
        return Mount(_wrap(float(heading)), math.pi / 2, 0.0, mx, my, mz)
    R = rotation(heading, ax, ay)
    axis = R[:, 2]
    tilt = math.asin(max(-1.0, min(1.0, float(axis[2]))))
    pan = math.atan2(float(axis[1]), float(axis[0]))
    # R = Rz(pan) Ry(-tilt) R0 Rz(swing): Rz(swing) = (Rz(pan) Ry(-tilt) R0)^T R
    Rs = R_vehicle_cam(pan, tilt, 0.0).T @ R
    swing = math.atan2(float(Rs[1, 0]), float(Rs[0, 0]))
    return Mount(_wrap(pan), tilt, _wrap(swing), mx, my, mz)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _disc(radius_m: float) -> np.ndarray:
    a = np.linspace(0.0, 2 * math.pi, _DISC_POINTS, endpoint=False)
    return radius_m * np.stack([np.cos(a), np.sin(a)], axis=1)


def _polygon_centroids(p: np.ndarray) -> np.ndarray:
    """Area centroids of polygons ``(N, K, 2)``."""
    x, y = p[..., 0], p[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * y1 - x1 * y
    area = cr.sum(axis=1)
    safe = np.where(np.abs(area) > 1e-12, area, 1.0)
    cx = ((x + x1) * cr).sum(axis=1) / (3 * safe)
    cy = ((y + y1) * cr).sum(axis=1) / (3 * safe)
    out = np.stack([cx, cy], axis=1)
    bad = np.abs(area) <= 1e-12
    out[bad] = p[bad].mean(axis=1)
    return out


def predict_px(rig: Rig, ceiling_m: float, lights_w: np.ndarray, poses: np.ndarray,
               R_vc: np.ndarray, t_vc: np.ndarray, radius_m: float) -> np.ndarray:
    """Predicted spot centroids ``(N, 2)`` px of lights ``(N, 2)`` seen from vehicle
    poses ``(N, 3)`` (one per light); NaN where behind the camera."""
    n = lights_w.shape[0]
    if n == 0:
        return np.zeros((0, 2))
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    Rz = np.zeros((n, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    R_wc = Rz @ R_vc                                   # (n, 3, 3)
    cen = np.einsum("nij,j->ni", Rz, t_vc)
    cen[:, :2] += poses[:, :2]
    ring = _disc(radius_m)                             # (K, 2)
    pts = np.empty((n, ring.shape[0], 3))
    pts[..., :2] = lights_w[:, None, :] + ring[None]
    pts[..., 2] = ceiling_m
    d = pts - cen[:, None, :]
    pc = np.einsum("nji,nkj->nki", R_wc, d)           # R_wc^T d
    behind = (pc[..., 2] <= 1e-6).any(axis=1)
    pc[..., 2] = np.where(pc[..., 2] > 1e-6, pc[..., 2], 1.0)
    px = rig.camera.project(pc.reshape(-1, 3)).reshape(n, -1, 2)
    out = _polygon_centroids(px)
    out[behind] = np.nan
    return out


# ------------------------------------------------------------------------------ data
def observe(rig: Rig, image: np.ndarray, t_ns: int, label: str = "") -> LightFrame:
    """A frame's spot centroids (:func:`~ceilkit.runtime.features.spots.detect_spots`)."""
    spots = detect_spots(image)
    return LightFrame(int(t_ns), np.asarray(spots.centroids_px, float).reshape(-1, 2), label)


def load_light_frames(source, rig: Rig, max_frames: int = 120
                      ) -> tuple[list[LightFrame], StampedPoses | None]:
    """Spot frames of a recording (at most ``max_frames``, spread evenly) and its
    ``truth.csv`` as a pose table (None when it has none)."""
    from pathlib import Path

    from ceilkit.runtime.io.recording import Recording

    source = Path(source)
    if not (source / "frames.csv").exists():
        raise ConfigError(source / "frames.csv", None, "file not found: the upward mount "
                          "fit reads a recording (frames.csv, frames/, truth.csv)")
    rec = Recording(source)
    ks = list(range(len(rec)))
    if max_frames and len(ks) > max_frames:
        ks = [ks[int(i)] for i in np.linspace(0, len(ks) - 1, max_frames).round()]
    frames = []
    for k in ks:
        f = rec.frame(k)
        frames.append(observe(rig, f.image, f.t_ns, f"frame {f.index}"))
    table = StampedPoses.from_truth(rec.truth) if rec.truth is not None else None
    return frames, table


class _Fit:
    def __init__(self, rig: Rig, site: Site, frames: Sequence[LightFrame], poses: StampedPoses,
                 fit_offset: bool, radius_m: float):
        self.rig, self.H = rig, float(site.ceiling_height_m)
        self.lights = np.asarray(site.lights_m, float).reshape(-1, 2)
        self.frames = list(frames)
        self.poses = poses
        self.fit_offset = fit_offset
        self.radius = radius_m
        self.t = np.array([f.t_ns for f in self.frames], np.int64)
        self.max_angle: float | None = None
        self.assoc: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # frame, light, px

    def frame_poses(self, offset_s: float) -> np.ndarray:
        return self.poses.at(self.t, offset_s * 1e9)

    def all_predictions(self, theta: np.ndarray) -> list[np.ndarray]:
        """Per frame, ``(L, 2)`` predicted px of every light (NaN: behind / no pose)."""
        R_vc = rotation(*theta[:3])
        t_vc = theta[3:6]
        poses = self.frame_poses(theta[6] if self.fit_offset else 0.0)
        L = self.lights.shape[0]
        out = []
        for k in range(len(self.frames)):
            if not np.all(np.isfinite(poses[k])):
                out.append(np.full((L, 2), np.nan))
                continue
            pk = np.repeat(poses[k][None], L, axis=0)
            out.append(predict_px(self.rig, self.H, self.lights, pk, R_vc, t_vc,
                                  self.radius))
        return out

    def associate(self, theta: np.ndarray, gate_px: float) -> int:
        preds = self.all_predictions(theta)
        fk, lk, px = [], [], []
        cam = self.rig.camera
        for k, (f, pr) in enumerate(zip(self.frames, preds, strict=True)):
            if f.spots_px.shape[0] == 0:
                continue
            ok = np.isfinite(pr[:, 0]) & cam.in_image(np.nan_to_num(pr, nan=-1e9))
            idx = np.flatnonzero(ok)
            if idx.size == 0:
                continue
            spots = f.spots_px
            if self.max_angle is not None:
                xy = cam.unproject(spots)
                spots = spots[np.arctan(np.hypot(xy[:, 0], xy[:, 1])) <= self.max_angle]
                if spots.shape[0] == 0:
                    continue
            d = np.linalg.norm(spots[:, None, :] - pr[idx][None], axis=2)
            j = np.argmin(d, axis=1)
            best = d[np.arange(d.shape[0]), j]
            # one light per spot and one spot per light, both nearest, within the gate
            back = np.argmin(d, axis=0)
            for i in range(d.shape[0]):
                if best[i] < gate_px and back[j[i]] == i:
                    fk.append(k)
                    lk.append(int(idx[j[i]]))
                    px.append(spots[i])
        self.assoc = (np.array(fk, int), np.array(lk, int), np.array(px).reshape(-1, 2))
        return len(fk)

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        fk, lk, px = self.assoc
        R_vc = rotation(*theta[:3])
        poses = self.frame_poses(theta[6] if self.fit_offset else 0.0)[fk]
        pr = predict_px(self.rig, self.H, self.lights[lk], poses, R_vc, theta[3:6],
                        self.radius)
        r = (pr - px).ravel()
        return np.where(np.isfinite(r), r, 50.0)


def _search_heading(fit: _Fit, theta: np.ndarray, gate_px: float) -> np.ndarray:
    """The heading (every 2 deg) that associates the most spots, then the least cost."""
    best, best_key = theta, (-1, 0.0)
    for h in np.radians(np.arange(-180.0, 180.0, 2.0)):
        th = theta.copy()
        th[0] = h
        n = fit.associate(th, gate_px)
        if n == 0:
            continue
        r = fit.residuals(th)
        key = (n, -float(np.sum(np.minimum(r * r, gate_px ** 2))))
        if key > best_key:
            best, best_key = th, key
    return best


def covariance(J: np.ndarray, s2: float, px: np.ndarray, rig: Rig,
               px_scale: float = 1.0) -> np.ndarray:
    """The parameters' covariance: the residuals' scatter ``s2`` through ``J``, plus a
    common radial scale and a rotation of the centroids about the principal point
    (:data:`SYSTEMATIC_SCALE`, :data:`SYSTEMATIC_ROTATION`) through the sensitivity
    ``d theta = -(J^T J)^-1 J^T dr``. The first ``2 len(px)`` rows of ``J`` are the
    pixel residuals divided by ``px_scale``; any further rows (other residuals) see no
    systematic shift."""
    JtJ_inv = np.linalg.pinv(J.T @ J)
    cov = s2 * JtJ_inv
    c = np.array([rig.camera.cx, rig.camera.cy])
    pad = np.zeros(J.shape[0] - 2 * px.shape[0])
    for dr in ((-(px - c) * SYSTEMATIC_SCALE).ravel(),          # r = pred - obs
               (-np.stack([-(px - c)[:, 1], (px - c)[:, 0]], axis=1)
                * SYSTEMATIC_ROTATION).ravel()):
        g = -JtJ_inv @ (J.T @ np.r_[dr / px_scale, pad])
        cov = cov + np.outer(g, g)
    return cov


def lean_of(ax: float, ay: float, cov2: np.ndarray) -> tuple[float, float, bool]:
    """The lean from the vertical (rad), the 1 sigma of its magnitude (along its
    direction, so of tilt = 90 deg - lean) and whether it is significant."""
    lean = math.hypot(ax, ay)
    if lean > 1e-12:
        u = np.array([ax, ay]) / lean
        s_lean = math.sqrt(max(float(u @ cov2 @ u), 0.0))
    else:
        s_lean = math.sqrt(max(0.5 * (cov2[0, 0] + cov2[1, 1]), 0.0))
    return lean, s_lean, lean > max(LEAN_SIGMAS * s_lean, math.radians(0.001))


def refuse_undetermined(limits: Sequence[tuple[str, float, float, str]]) -> None:
    """Raise CalibrationError for the first ``(name, sigma, limit, what to add)`` whose
    sigma is above its limit (radians for pan and tilt, seconds for offset, else m)."""
    for name, s, lim, what in limits:
        if not s <= lim:
            unit = (f"{math.degrees(s):.3f} deg (limit {math.degrees(lim):.3f})"
                    if name in ("pan", "tilt") else f"{1000 * s:.2f} mm (limit "
                    f"{1000 * lim:.1f})" if name != "offset" else
                    f"{1000 * s:.2f} ms (limit {1000 * lim:.1f})")
            raise CalibrationError(
                f"{name} is not determined by this drive: 1 sigma {unit}; add {what}, or "
                f"measure it and give --fix. Nothing written")


def calibrate_mount_upward(rig: Rig, site: Site, frames: Sequence[LightFrame],
                           poses: StampedPoses, *, estimate_offset: bool | None = None,
                           light_diameter_m: float | None = None,
                           max_field_deg: float = MAX_FIELD_DEG) -> UpwardResult:
    """Fit the upward mount from spot frames and the vehicle's poses.

    ``estimate_offset``: fit the time offset of ``poses`` to the frame stamps (None:
    when the stamps are not rows of the table, i.e. poses at their own stamps).
    Observability first: refuses (CalibrationError, naming what to add) too few frames
    with lights, a residual RMS above :data:`MAX_RMS_UP_PX`, and any parameter whose
    1 sigma exceeds :data:`MAX_SIGMA_UP`.
    """
    if not site.has_lights:
        raise ConfigError(None, "site", "the upward mount fit needs the site's lights")
    t = np.array([f.t_ns for f in frames], np.int64)
    if estimate_offset is None:
        estimate_offset = not poses.exact(t)
    usable = [f for f in frames if f.spots_px.shape[0] >= 1]
    diam = light_diameter_m or site.light_diameter_m or DEFAULT_LIGHT_DIAMETER_M
    fit = _Fit(rig, site, usable, poses, estimate_offset, 0.5 * diam)
    fit.max_angle = math.radians(max_field_deg)
    have_pose = np.all(np.isfinite(fit.frame_poses(0.0)), axis=1)
    if int(have_pose.sum()) < MIN_FRAMES:
        raise CalibrationError(
            f"only {int(have_pose.sum())} frames with spot lights have a vehicle pose "
            f"(at least {MIN_FRAMES}): add truth.csv / pose rows covering the drive, or a "
            "longer drive under the lights. Nothing written")
    m0 = rig.mount
    theta = np.array([m0.pan_rad + m0.swing_rad, 0.0, 0.0, m0.x_m, m0.y_m, m0.z_m]
                     + ([0.0] if estimate_offset else []))
    theta = _search_heading(fit, theta, 60.0)
    for gate in (60.0, 20.0, 8.0, 4.0, 3.0):
        n = fit.associate(theta, gate)
        if n < 3 * len(theta):
            break
        theta = least_squares(fit.residuals, theta, method="lm",
                              x_scale=np.r_[0.01, 0.01, 0.01, 0.01, 0.01, 0.01,
                                            [0.001] * (len(theta) - 6)]).x
    n = fit.associate(theta, 3.0)
    frames_used = len(set(fit.assoc[0].tolist()))
    if n < 3 * len(theta) or frames_used < MIN_FRAMES:
        raise CalibrationError(
            f"only {n} light sightings in {frames_used} frames matched the site's lights "
            f"(at least {MIN_FRAMES} frames): drive longer under the lights, check "
            "site.yaml's lights and the poses. Nothing written")
    sol = least_squares(fit.residuals, theta, method="lm")
    theta = sol.x
    r = fit.residuals(theta)
    dof = max(r.size - theta.size, 1)
    s2 = float(r @ r) / dof
    rms = math.sqrt(float(np.mean(r * r)))
    if rms > MAX_RMS_UP_PX:
        raise CalibrationError(
            f"the fit leaves {rms:.2f} px RMS (refused above {MAX_RMS_UP_PX:g} px): the "
            "poses, the site's lights or the camera disagree with the images; check them. "
            "Nothing written")
    cov = covariance(sol.jac, s2, fit.assoc[2], rig)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    lean, s_lean, significant = lean_of(theta[1], theta[2], cov[1:3, 1:3])
    mount = to_mount(*theta[:6], level=not significant)
    sigma = {"pan": float(sd[0]), "tilt": s_lean, "mx": float(sd[3]), "my": float(sd[4]),
             "mz": float(sd[5])}
    if estimate_offset:
        sigma["offset"] = float(sd[6])
    limits = [("pan", sigma["pan"], MAX_SIGMA_UP["heading"], "more turns under the lights"),
              ("tilt", s_lean, MAX_SIGMA_UP["lean"], "frames with lights near the image "
               "edges"),
              ("mx", sigma["mx"], MAX_SIGMA_UP["mx"], "a drive with more headings"),
              ("my", sigma["my"], MAX_SIGMA_UP["my"], "a drive with more headings"),
              ("z", sigma["mz"], MAX_SIGMA_UP["mz"], "frames that see more lights at once")]
    if estimate_offset:
        limits.append(("offset", sigma["offset"], MAX_SIGMA_UP["offset"],
                       "a drive whose speed and turn rate vary"))
    refuse_undetermined(limits)
    return UpwardResult(mount, sigma, rms, frames_used, n,
                        float(theta[6]) if estimate_offset else None, lean, significant)


__all__ = ["LightFrame", "StampedPoses", "UpwardResult", "calibrate_mount_upward",
           "load_light_frames", "load_pose_csv", "observe", "predict_px", "rotation",
           "to_mount"]
