"""The site's ceiling lines (the corridor section's ``lines_along``/``lines_across``: tile
seams, lamp rows' edges) predicted in the image from a pose near the truth, as short
pixel chords for :func:`~ceilkit.runtime.features.lines.refine_undistorted`.

A block's fix (or the tracker's prior) is a few millimetres (centimetres) off, a pixel
or two on the ceiling: measuring the known parallels where they must be costs a
fraction of a line detector over the frame. Pure math: arrays in, arrays out.

Example::

    chords = predicted_chords(geo, site.corridor, (x, y, yaw))   # (N, 4) pixels, (N,) axis
"""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.geometry.rotations import rot_z

REACH_M = 3.5        # ceiling lines looked for this far from the camera's ceiling point
STEP_M = 0.1         # sample spacing along a line on the ceiling
CHORD_SAMPLES = 11   # samples per chord (a chord spans (CHORD_SAMPLES - 1) * STEP_M)
MARGIN_PX = 8.0      # chord ends kept this far inside the frame
MAX_CHORDS = 20      # chords measured per frame (spread over the lines)


def site_lines(corridor, centre: np.ndarray, reach_m: float = REACH_M
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(point, direction)`` in W of the site's ceiling lines within ``reach_m`` of
    ``centre`` (W, ``(2,)``)."""
    out = []
    for y in corridor.lines_along_m:
        if abs(y - centre[1]) < reach_m:
            out.append((np.array([centre[0], y]), np.array([1.0, 0.0])))
    a = corridor.lines_across
    if a is not None and a.spacing_m > 0:
        k0 = math.ceil((centre[0] - reach_m - a.first_m) / a.spacing_m)
        k1 = math.floor((centre[0] + reach_m - a.first_m) / a.spacing_m)
        for k in range(k0, k1 + 1):
            out.append((np.array([a.first_m + k * a.spacing_m, centre[1]]),
                        np.array([0.0, 1.0])))
    return out


def predicted_chords(geo: PlanarGeometry, corridor, pose: np.ndarray,
                     reach_m: float = REACH_M, max_chords: int = MAX_CHORDS) -> np.ndarray:
    """Pixel chords ``(N, 4)`` along the site's ceiling lines seen from ``pose``, at most
    ``max_chords`` of them spread over the lines (one projection of every sample)."""
    x, y, yaw = (float(v) for v in pose)
    R_wc = rot_z(yaw) @ geo.R_vehicle_cam
    c = rot_z(yaw) @ geo.t_vehicle_cam + np.array([x, y, 0.0])
    axis = R_wc[:, 2]
    s = (geo.ceiling_m - c[2]) / axis[2] if axis[2] > 1e-6 else 0.0
    centre = (c + s * axis)[:2]
    lines = site_lines(corridor, centre, reach_m)
    if not lines:
        return np.zeros((0, 4))
    t = np.arange(-reach_m, reach_m + 1e-9, STEP_M)
    p0 = np.array([p for p, _ in lines])
    d = np.array([q for _, q in lines])
    pts = (p0[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 2)
    pc = (np.hstack([pts, np.full((len(pts), 1), geo.ceiling_m)]) - c) @ R_wc
    front = pc[:, 2] > 1e-6
    px = np.full((len(pts), 2), np.nan)
    if np.any(front):
        px[front] = geo.camera.distort(pc[front, :2] / pc[front, 2:3])
    inside = (front & geo.camera.in_image(px, MARGIN_PX)).reshape(len(lines), len(t))
    px = px.reshape(len(lines), len(t), 2)
    k = CHORD_SAMPLES - 1
    n = len(t) - k
    cs = np.concatenate([np.zeros((len(lines), 1), int), np.cumsum(inside, axis=1)], axis=1)
    full = (cs[:, k + 1:] - cs[:, :n]) == CHORD_SAMPLES           # (L, n) windows inside
    # non-overlapping windows: every k-th start
    full[:, np.arange(n) % k != 0] = False
    li, si = np.nonzero(full)
    if len(li) > max_chords:
        pick = np.round(np.linspace(0, len(li) - 1, max_chords)).astype(int)
        li, si = li[pick], si[pick]
    return np.hstack([px[li, si], px[li, si + k]])
