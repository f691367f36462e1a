"""What the corridor estimators compute once, when they are built: the shared
construction check and the per-rig and per-site constants.

Convention (SPEC §1): ``R_level_cam = mount.R_level_cam`` (tilt and swing; the level
frame is W's axes turned by the camera's pan), ``ceiling_above_cam_m = H - mount.z``
(the ceiling's height above the optical centre, not above the floor).

Example::

    check_setup(rig, site)                      # raises ConfigError
    setup = CorridorSetup.build(rig, site, min_elevation_rad=math.radians(3))
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import LampRow, Site, check_rig_site
from ceilkit.runtime.geometry.camera import CameraModel

LAMP_EDGE_MATCH_M = 0.01
"""A ``lines_along`` entry within this of a lamp row's long edge (``y +- width/2``) is
that edge: a step whose bright side is the lamp, seen only where the lamps are."""

MAX_MATCH_TOL_M = 0.08
"""The default 1-D association gate: a quarter of the closest ``lines_along`` spacing,
at most this."""

LAMP_LENGTH_MARGIN = (1.15, 0.1)
"""A segment on a lamp edge is at most ``1.15 length + 0.1`` m long on the ceiling."""


def check_setup(rig: Rig, site: Site) -> None:
    """The construction check both corridor estimators make beyond the base's (which
    checks the options and the `corridor` section): the camera is below the ceiling
    (:func:`~ceilkit.runtime.config.site.check_rig_site`).

    Raises:
        ConfigError: naming the site file's key.
    """
    check_rig_site(rig, site)


def default_match_tol_m(site_y: np.ndarray) -> float:
    """The association gate (m) for ``lines_along`` at ``site_y`` (J,): a quarter of
    their closest spacing, at most :data:`MAX_MATCH_TOL_M`."""
    gaps = np.diff(np.sort(np.asarray(site_y, dtype=float)))
    return min(MAX_MATCH_TOL_M, 0.25 * float(gaps.min())) if gaps.size else MAX_MATCH_TOL_M


def lamp_edge_kind(site_y: np.ndarray, row: LampRow) -> np.ndarray:
    """``(J,)``: ``+1`` where ``lines_along`` entry j is lamp row ``row``'s -y long edge
    (the lamp, bright, on its +y side), ``-1`` its +y edge, ``0`` neither (within
    :data:`LAMP_EDGE_MATCH_M`)."""
    y = np.asarray(site_y, dtype=float)
    hw = 0.5 * row.width_m
    kind = np.zeros(y.size)
    kind[np.abs(y - (row.y_m - hw)) < LAMP_EDGE_MATCH_M] = 1.0
    kind[np.abs(y - (row.y_m + hw)) < LAMP_EDGE_MATCH_M] = -1.0
    return kind


def lens_field_radius(camera: CameraModel) -> float:
    """The lens's field in normalized coordinates: the image corners' largest radius
    (undistorted), with a 2 % margin. Points beyond it are not projected."""
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    return float(np.max(np.hypot(*camera.unproject(corners).T))) * 1.02


def ceiling_rows(camera: CameraModel, R_level_cam: np.ndarray,
                 min_elevation_rad: float) -> tuple[int, int]:
    """``(v0, v1)``: the image rows where some ray rises at least ``min_elevation_rad``
    above the horizon (where the ceiling can be), with a 2-row margin."""
    u = np.linspace(-0.5, camera.width - 0.5, 41)
    v = np.arange(camera.height, dtype=float)
    uu, vv = np.meshgrid(u, v)
    xy = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
    r = np.hstack([xy, np.ones((xy.shape[0], 1))]) @ R_level_cam.T
    with np.errstate(invalid="ignore"):
        elev = r[:, 2] / np.linalg.norm(r, axis=1)
    up = np.any((elev > math.sin(min_elevation_rad)).reshape(v.size, u.size), axis=1)
    if not np.any(up):
        return 0, camera.height
    rows = np.flatnonzero(up)
    return max(0, int(rows[0]) - 2), min(camera.height, int(rows[-1]) + 3)


@dataclass(frozen=True, eq=False)
class CorridorSetup:
    """The constants of one rig on one corridor site, shared by every frame.

    Attributes:
        R_level_cam: ``(3, 3)`` the mount's tilt and swing. R_rows: its rows as float
            tuples (scalar arithmetic). R_T: its transpose, C-contiguous.
        ceiling_above_cam_m: ``H - mount.z`` (m).
        f_px: mean focal length (px). pan_rad: the mount's pan. t_vc: ``(3,)`` the
            camera's position in V (m).
        site_y: ``(J,)`` the ``lines_along`` (m). axis_y_m: their middle.
        edge_kind: ``(J,)`` ``+1``/``-1`` a lamp edge (the bright side +y/-y), 0 a seam.
        longest_m: ``(J,)`` the longest ceiling stretch a segment on line j can have
            (a lamp's length with a margin; inf for a seam).
        lamp_pitch_m: ``(J,)`` ceiling stretch that holds one lamp of line j's row
            (0 for a seam). lamp_width_m, lamp_y_m: ``(L,)`` per lamp row.
        across_spacing_m: ``lines_across`` spacing, or None.
        field_radius: :func:`lens_field_radius`. rows: :func:`ceiling_rows`.
        view_u_m: ``(S,)`` samples along W's x (m) for the in-view test.
    """

    R_level_cam: np.ndarray
    R_rows: tuple[tuple[float, float, float], ...]
    R_T: np.ndarray
    ceiling_above_cam_m: float
    f_px: float
    pan_rad: float
    t_vc: np.ndarray
    site_y: np.ndarray
    axis_y_m: float
    edge_kind: np.ndarray
    longest_m: np.ndarray
    lamp_pitch_m: np.ndarray
    lamp_width_m: np.ndarray
    lamp_y_m: np.ndarray
    across_spacing_m: float | None
    field_radius: float
    rows: tuple[int, int]
    view_u_m: np.ndarray

    @classmethod
    def build(cls, rig: Rig, site: Site, min_elevation_rad: float) -> CorridorSetup:
        """The setup of ``rig`` on ``site`` (which has a `corridor` section)."""
        cam, mount = rig.camera, rig.mount
        R = mount.R_level_cam
        site_y = np.asarray(site.corridor.lines_along_m, dtype=float)
        kind = np.zeros(site_y.size)
        longest = np.full(site_y.size, np.inf)
        pitch = np.zeros(site_y.size)
        for row in site.lamps:
            k = lamp_edge_kind(site_y, row)
            on = k != 0
            kind[on] = k[on]
            longest[on] = LAMP_LENGTH_MARGIN[0] * row.length_m + LAMP_LENGTH_MARGIN[1]
            pitch[on] = (row.pitch_m if row.count > 1 else 0.0) + row.length_m
        across = site.corridor.lines_across
        return cls(
            R_level_cam=R, R_rows=tuple(tuple(float(v) for v in row) for row in R),
            R_T=np.ascontiguousarray(R.T),
            ceiling_above_cam_m=site.ceiling_height_m - mount.z_m,
            f_px=0.5 * (cam.fx + cam.fy), pan_rad=mount.pan_rad, t_vc=mount.t_vehicle_cam,
            site_y=site_y, axis_y_m=site.corridor.axis_y_m, edge_kind=kind,
            longest_m=longest, lamp_pitch_m=pitch,
            lamp_width_m=np.array([row.width_m for row in site.lamps], dtype=float),
            lamp_y_m=np.array([row.y_m for row in site.lamps], dtype=float),
            across_spacing_m=None if across is None else across.spacing_m,
            field_radius=lens_field_radius(cam),
            rows=ceiling_rows(cam, R, min_elevation_rad),
            view_u_m=np.linspace(-30.0, 30.0, 601))


def mirror_line(setup: CorridorSetup, tol_m: float = 1e-6) -> float | None:
    """The y of the line the site is symmetric about as the corridor method sees it,
    or None: every ``lines_along`` entry has a mirror image across it of the opposite
    edge kind (a lamp's -y edge is the mirror of a +y edge), the same longest stretch
    and lamp pitch, and every lamp row a mirror row of its width. A corridor so built
    looks the same driven either way: the half turn of a pose is its twin, at the
    mirrored camera y (:func:`.hypotheses.label`)."""
    y = setup.site_y
    if y.size == 0:
        return None
    c = 0.5 * (float(y.min()) + float(y.max()))
    for j in range(y.size):
        k = np.flatnonzero(np.abs(y - (2 * c - y[j])) <= tol_m)
        if k.size != 1 or setup.edge_kind[k[0]] != -setup.edge_kind[j] or \
                setup.longest_m[k[0]] != setup.longest_m[j] or \
                setup.lamp_pitch_m[k[0]] != setup.lamp_pitch_m[j]:
            return None
    for r in range(setup.lamp_y_m.size):
        k = np.flatnonzero((np.abs(setup.lamp_y_m - (2 * c - setup.lamp_y_m[r])) <= tol_m)
                           & (np.abs(setup.lamp_width_m - setup.lamp_width_m[r]) <= tol_m))
        if k.size == 0:
            return None
    return c

