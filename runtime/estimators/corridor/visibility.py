"""Which ``lines_along`` a camera sees: for the absence test of the association
(:func:`lines_in_view`) and for benchmarks and tests (:func:`visible_along_lines`).

Convention (SPEC §1): the ceiling line ``y = y_j`` at ``z = H`` is projected through
the rig at the pose; a lamp edge exists only where its lamps are.

Example::

    seen = visible_along_lines(rig, site, x_m, y_m, yaw_rad, min_length_px=25.6)
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.corridor.setup import (
    CorridorSetup,
    lamp_edge_kind,
    lens_field_radius,
)
from ceilkit.runtime.geometry.camera import CameraModel, distort_points
from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.jit import arr, njit, warmer

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


class ViewSetup(NamedTuple):
    """What :func:`view_core` needs of a rig on a site: the samples ``u_m (S,)`` along
    W's x (m), the mount's ``R_level_cam (3, 3)``, the site's ``site_y (J,)`` and
    ``lamp_pitch_m (J,)``, the ceiling's height above the camera ``h_m``, the lens's
    field radius (normalized), the lens ``code`` and ``lens (13,)``
    (:attr:`~ceilkit.runtime.geometry.camera.CameraModel.lens`), the image's usable
    box ``box (4,)`` (px: left, right, top, bottom, 2 px inside the border) and the
    stretch a line clearly in view needs ``min_px`` (px)."""

    u_m: np.ndarray
    R_level_cam: np.ndarray
    site_y: np.ndarray
    lamp_pitch_m: np.ndarray
    h_m: float
    field_radius: float
    code: int
    lens: np.ndarray
    box: np.ndarray
    min_px: float


@functools.lru_cache(maxsize=8)
def view_setup(setup: CorridorSetup, cam: CameraModel, min_length_px: float) -> ViewSetup:
    """:class:`ViewSetup` of ``setup`` seen through ``cam`` (one per estimator: cached
    on the objects themselves, which are compared by identity)."""
    f, m = np.float64, IN_VIEW_MARGIN_PX
    code, lens = cam.lens
    box = np.array([-0.5 + m, cam.width - 0.5 - m, -0.5 + m, cam.height - 0.5 - m])
    return ViewSetup(arr(setup.view_u_m, f), arr(setup.R_level_cam, f), arr(setup.site_y, f),
                     arr(setup.lamp_pitch_m, f), float(setup.ceiling_above_cam_m),
                     float(setup.field_radius), int(code), arr(lens, f), arr(box, f),
                     float(IN_VIEW_LENGTHS * min_length_px))


IN_VIEW_MARGIN_PX = 2.0
"""A sample of a line is in the image when it lies this far inside its border (px)."""


def lines_in_view(setup: CorridorSetup, cam: CameraModel, min_length_px: float,
                  psi_rad: float, camera_y_m: tuple[float, ...]) -> np.ndarray:
    """``(C, J)``: the site's ``lines_along`` clearly in view for camera pan ``psi_rad``
    and each camera y in ``camera_y_m`` (C,): a visible stretch of at least
    :data:`IN_VIEW_LENGTHS` ``min_length_px``, and for a lamp edge at least a lamp
    pitch of ceiling (so a lamp is in it). Each line is sampled at ``setup.view_u_m``
    along W's x, the samples in front of the camera and inside the lens's field
    projected (SPEC §1) and kept :data:`IN_VIEW_MARGIN_PX` inside the image; the
    stretch is the summed pixel length (and ceiling length) between consecutive kept
    samples. One compiled call (:func:`view_core`)."""
    R_cw = setup.R_level_cam.T @ rot_z(-psi_rad)
    out = np.empty((len(camera_y_m), setup.site_y.size), np.bool_)
    view_core(view_setup(setup, cam, float(min_length_px)), arr(R_cw, np.float64),
              arr(np.asarray(camera_y_m, dtype=float), np.float64), out)
    return out


@njit
def view_core(vs, R_cw, camera_y, out):  # pragma: no cover - compiled
    """:func:`lines_in_view` into ``out (C, J)`` for ``vs`` (:class:`ViewSetup`), the
    rotation ``R_cw (3, 3)`` from the level frame turned by the pan to the camera, and
    camera y ``camera_y (C,)``. Only the samples about the stretch of the line in front
    of the camera and inside the lens's field are looked at (:func:`_field_span`: the
    others fail those tests; each sample looked at is tested as the array reading
    tests it)."""
    u = vs.u_m
    du = u[1] - u[0]
    one, px = np.empty((1, 2)), np.empty((1, 2))
    for c in range(camera_y.size):
        for j in range(vs.site_y.size):
            dy = vs.site_y[j] - camera_y[c]
            b0 = dy * R_cw[0, 1] + vs.h_m * R_cw[0, 2]
            b1 = dy * R_cw[1, 1] + vs.h_m * R_cw[1, 2]
            b2 = dy * R_cw[2, 1] + vs.h_m * R_cw[2, 2]
            lo, hi = _field_span((R_cw[0, 0], R_cw[1, 0], R_cw[2, 0]), (b0, b1, b2),
                                 vs.field_radius, u)
            length, n_both = 0.0, 0
            prev, px0, px1 = False, 0.0, 0.0
            for i in range(lo, hi):
                d0 = u[i] * R_cw[0, 0] + b0
                d1 = u[i] * R_cw[1, 0] + b1
                d2 = u[i] * R_cw[2, 0] + b2
                vis = False
                if d2 > 1e-6:
                    x, y = d0 / d2, d1 / d2
                    if math.hypot(x, y) <= vs.field_radius:
                        one[0, 0], one[0, 1] = x, y
                        distort_points(one, vs.code, vs.lens, px)
                        vis = (vs.box[0] <= px[0, 0] <= vs.box[1]
                               and vs.box[2] <= px[0, 1] <= vs.box[3])
                if vis and prev:
                    length += math.hypot(px[0, 0] - px0, px[0, 1] - px1)
                    n_both += 1
                if vis:
                    px0, px1 = px[0, 0], px[0, 1]
                prev = vis
            out[c, j] = length >= vs.min_px and n_both * du >= vs.lamp_pitch_m[j]


@njit
def _field_span(a, b, rf, u):  # pragma: no cover - compiled
    """``(lo, hi)``: the indices ``[lo, hi)`` of the evenly spaced samples ``u (S,)``
    that can hold the points ``d = a u + b`` (camera frame; ``a, b``: 3-tuples) in
    front of the camera (``d_2 > 0``) and inside the field ``|d_01| <= rf d_2``: the
    roots of those conditions, widened by two samples (the tests themselves are made
    per sample)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    u0, du, n = u[0], u[1] - u[0], u.size
    lo_u, hi_u = -math.inf, math.inf
    if a2 > 0:
        lo_u = -b2 / a2
    elif a2 < 0:
        hi_u = -b2 / a2
    elif b2 <= 0:
        return 0, 0
    qa = a0 * a0 + a1 * a1 - rf * rf * a2 * a2
    qb = 2.0 * (a0 * b0 + a1 * b1 - rf * rf * a2 * b2)
    qc = b0 * b0 + b1 * b1 - rf * rf * b2 * b2
    if qa > 1e-12:                  # inside the field between the roots
        disc = qb * qb - 4.0 * qa * qc
        if disc < 0:
            return 0, 0
        r = math.sqrt(disc)
        lo_u = max(lo_u, (-qb - r) / (2.0 * qa))
        hi_u = min(hi_u, (-qb + r) / (2.0 * qa))
    if lo_u > hi_u:
        return 0, 0
    lo = 0 if lo_u == -math.inf else int(max(0.0, min(float(n), math.floor((lo_u - u0) / du) - 2)))
    hi = n if hi_u == math.inf else int(max(0.0, min(float(n), math.ceil((hi_u - u0) / du) + 3)))
    return lo, hi


@warmer
def _warm() -> None:
    f = np.float64
    lens = np.zeros(13)
    lens[:4] = 400.0, 400.0, 320.0, 240.0
    vs = ViewSetup(arr(np.linspace(-1.0, 1.0, 5), f), arr(np.eye(3), f),
                   arr(np.array([0.0, 0.5]), f), arr(np.zeros(2), f), 2.0, 2.0, 0,
                   arr(lens, f), arr(np.array([1.5, 637.5, 1.5, 477.5]), f), 30.0)
    view_core(vs, arr(np.eye(3), f), arr(np.zeros(1), f), np.empty((1, 2), np.bool_))
