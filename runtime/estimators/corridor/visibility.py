"""Which ``lines_along`` a camera sees: for the absence test of the association
(:func:`lines_in_view`) and for benchmarks and tests (:func:`visible_along_lines`).

Convention (SPEC §1): the ceiling line ``y = y_j`` at ``z = H`` is projected through
the rig at the pose; a lamp edge exists only where its lamps are.

Example::

    seen = visible_along_lines(rig, site, x_m, y_m, yaw_rad, min_length_px=25.6)
"""

from __future__ import annotations

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.corridor.setup import (
    CorridorSetup,
    lamp_edge_kind,
    lens_field_radius,
)
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import rot_z

IN_VIEW_LENGTHS = 3.0
"""A line is clearly in view with a visible stretch of this many ``min_length_px``."""


def _longest_run_px(cam: CameraModel, R_cw: np.ndarray, C: np.ndarray, r_max: float,
                    xs: np.ndarray, y_m: float, H: float) -> float:
    """The longest run (px) of consecutive visible samples of the ceiling points
    ``(xs, y_m, H)`` for a camera at ``C`` (W) with ``R_cw`` (W to camera); -inf when
    no two consecutive samples are visible."""
    P = np.stack([xs, np.full_like(xs, y_m), np.full_like(xs, H)], axis=1)
    Pc = (P - C) @ R_cw.T
    z = Pc[:, 2]
    ok = z > 1e-6
    xy = np.where(ok[:, None], Pc[:, :2] / np.where(ok, z, 1.0)[:, None], 0.0)
    ok &= np.hypot(xy[:, 0], xy[:, 1]) <= r_max
    px = np.full((xs.size, 2), np.nan)
    if np.any(ok):
        px[ok] = cam.distort(xy[ok])
    ok &= np.isfinite(px[:, 0]) & cam.in_image(np.nan_to_num(px, nan=-1e9))
    if np.count_nonzero(ok) < 2:
        return -np.inf
    seg = np.hypot(*np.diff(px, axis=0).T)
    both = ok[1:] & ok[:-1]
    run = np.cumsum(~both)          # runs of consecutive visible samples
    return float(np.bincount(run[both], seg[both]).max()) if np.any(both) else -np.inf


def visible_along_lines(rig: Rig, site: Site, x_m: float, y_m: float, yaw_rad: float,
                        min_length_px: float, step_m: float = 0.01,
                        reach_m: float = 40.0) -> np.ndarray:
    """Which ``lines_along`` a vehicle pose sees: ``(J,)`` bool, True where the line
    has a visible stretch at least ``min_length_px`` long in the image.

    The line ``y = y_j`` on the ceiling is sampled every ``step_m`` within ``reach_m``
    of the camera (a lamp edge only where its lamps are), projected through the rig at
    the pose (SPEC §1), and its longest run of consecutive samples inside the image
    (and inside the lens's field, the image corners' radius) is measured in pixels.
    For benchmarks and tests: "frames with two or more forward lines in view".
    """
    cam, mount = rig.camera, rig.mount
    r_max = lens_field_radius(cam)
    R_cw = mount.R_world_cam(yaw_rad).T
    C = mount.camera_position(x_m, y_m, yaw_rad)
    H = site.ceiling_height_m
    ys = np.asarray(site.corridor.lines_along_m, dtype=float)
    on_lamp = [lamp_edge_kind(ys, row) != 0 for row in site.lamps]
    out = np.zeros(ys.size, bool)
    for j, yj in enumerate(ys):
        pieces = []
        for row, on in zip(site.lamps, on_lamp, strict=True):
            if on[j]:
                for cx in row.centres()[:, 0]:
                    if abs(cx - C[0]) < reach_m:
                        pieces.append((cx - 0.5 * row.length_m, cx + 0.5 * row.length_m))
        if not pieces and not any(on[j] for on in on_lamp):
            pieces = [(C[0] - reach_m, C[0] + reach_m)]
        for x0, x1 in pieces:
            xs = np.arange(x0, x1 + 1e-9, step_m)
            if _longest_run_px(cam, R_cw, C, r_max, xs, yj, H) >= min_length_px:
                out[j] = True
                break
    return out


def lines_in_view(setup: CorridorSetup, cam: CameraModel, min_length_px: float,
                  psi_rad: float, camera_y_m: tuple[float, ...]) -> np.ndarray:
    """``(C, J)``: the site's ``lines_along`` clearly in view for camera pan ``psi_rad``
    and each camera y in ``camera_y_m`` (C,): a visible stretch of at least
    :data:`IN_VIEW_LENGTHS` ``min_length_px``, and for a lamp edge at least a lamp
    pitch of ceiling (so a lamp is in it)."""
    u = setup.view_u_m                                       # (S,) m along W's x
    R_cw = setup.R_level_cam.T @ rot_z(-psi_rad)
    J = setup.site_y.size
    dy = (setup.site_y[None, :] - np.asarray(camera_y_m, dtype=float)[:, None]).reshape(-1, 1)
    h = setup.ceiling_above_cam_m
    # the ceiling points (u, y_j - c_y, h) in the camera frame, per coordinate (C J, S)
    d0, d1, d2 = (u * R[0] + (dy * R[1] + h * R[2]) for R in R_cw)
    front = d2 > 1e-6
    z = np.where(front, d2, 1.0)
    x, y = d0 / z, d1 / z
    front &= np.hypot(x, y) <= setup.field_radius
    px = cam.distort(np.stack([x.ravel(), y.ravel()], axis=1)).reshape(*x.shape, 2)
    vis = front & cam.in_image(px.reshape(-1, 2), 2.0).reshape(x.shape)
    step = np.hypot(*np.diff(px, axis=1).transpose(2, 0, 1))
    both = vis[:, 1:] & vis[:, :-1]
    length_px = np.sum(np.where(both, step, 0.0), axis=1).reshape(-1, J)
    stretch_m = (np.sum(both, axis=1) * (u[1] - u[0])).reshape(-1, J)
    return (length_px >= IN_VIEW_LENGTHS * min_length_px) & (stretch_m >= setup.lamp_pitch_m)
