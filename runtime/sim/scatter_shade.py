"""How the renderer shades a :class:`~ceilkit.runtime.sim.scatter.Scatter`.

:func:`scatter_features` gives :mod:`ceilkit.runtime.sim.render` the cells each item
within reach of the frame can touch and how to shade a sample there (as
:mod:`ceilkit.runtime.sim.marks` does for blocks and markers), in three layers drawn in
this order around the site's own features:

* ``fills`` (before the seams): patched tiles, hatches, vents, stains: what replaces
  or marks a tile, with the T-bar seams drawn over its edges;
* ``fixtures`` (after the seams and markers, before the lamps): sprinklers, smoke
  detectors, cable runs;
* ``panels`` (last, with the site's lamps and lights): light panels, emitters.

Every hard edge is a linear ramp one sample footprint wide on its signed distance (no
bias); a stain is soft (``(1 - q)^2`` inside the ellipse ``q = 1``) and a vent's slats
fade to their mean where a footprint spans a slat period (no aliasing).

Radiance at exposure 1 (the ceiling is 150, ``render.CEILING_GREY``): see the
``*_GREY`` constants.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.sim.marks import ramp
from ceilkit.runtime.sim.scatter import Scatter, ScatterItem

PANEL_GREY = 245.0          # a lit panel's diffuser
PANEL_FRAME_GREY = 200.0    # its metal frame
PANEL_FRAME_M = 0.025
VENT_GREY = 185.0           # a grille's painted frame and slats
VENT_GAP_GREY = 55.0        # the dark gaps between its slats
VENT_FRAME_M = 0.03
VENT_SLAT_M = 0.025         # slat period
HATCH_GREY = 142.0          # an access hatch's face
HATCH_FRAME_GREY = 90.0     # its darker frame
HATCH_FRAME_M = 0.02
SPRINKLER_GREY = 205.0      # the chrome escutcheon
SPRINKLER_CORE_GREY = 70.0  # the deflector and frame seen from below (inner 45 %)
DETECTOR_GREY = 222.0       # a smoke detector's white body
DETECTOR_GROOVE_GREY = 170.0
DETECTOR_LED_GREY = 80.0
CABLE_GREY = 50.0

Shade = Callable[..., np.ndarray]


@dataclass(frozen=True)
class ScatterFeatures:
    """``(cells, shade, edges)`` per item in reach, by layer (see the module
    docstring): ``cells`` ``(n_cells,)`` bool, ``shade(xr, yr, inv_fp, value) ->
    value`` (a panel's also takes ``em=``, the emitters' share, and returns ``(value,
    em)``), ``edges`` the cells an edge of the item can cross (None: all its cells;
    empty for a stain, which has none): the renderer shades the rest per pixel."""

    fills: list[tuple[np.ndarray, Shade, np.ndarray | None]]
    fixtures: list[tuple[np.ndarray, Shade, np.ndarray | None]]
    panels: list[tuple[np.ndarray, Shade, np.ndarray | None]]


_EDGES_M = {"panel": (0.0, PANEL_FRAME_M), "hatch": (0.0, HATCH_FRAME_M), "patch": (0.0,),
            "stain": ()}
"""Signed distances inside a tile item's rectangle where its shade has an edge (a vent:
everywhere, its slats)."""


def scatter_features(scatter: Scatter, cam_x_m: float, cam_y_m: float, cxr: np.ndarray,
                     cyr: np.ndarray, reach: np.ndarray) -> ScatterFeatures:
    """The features of the items of ``scatter`` that a frame can see.

    Args:
        scatter: the items.
        cam_x_m, cam_y_m: the camera centre in W.
        cxr, cyr: ``(n_cells,)`` cell centres on the ceiling relative to the camera, m.
        reach: ``(n_cells,)`` cell radius plus a footprint, m (NaN: no ceiling samples).
    """
    out = ScatterFeatures([], [], [])
    ok = np.isfinite(reach)
    if not len(scatter) or not np.any(ok):
        return out
    ex, ey, er = cxr[ok], cyr[ok], reach[ok]
    lo_x, hi_x = np.min(ex - er), np.max(ex + er)
    lo_y, hi_y = np.min(ey - er), np.max(ey + er)
    c = scatter.centres_m - np.array([cam_x_m, cam_y_m])
    r = scatter.radii_m
    keep = ((c[:, 0] + r > lo_x) & (c[:, 0] - r < hi_x)
            & (c[:, 1] + r > lo_y) & (c[:, 1] - r < hi_y))
    for k in np.flatnonzero(keep):
        it = scatter.items[k]
        x0r, y0r = float(c[k, 0]), float(c[k, 1])
        edges = None
        with np.errstate(invalid="ignore"):
            if it.kind == "cable":
                pts = np.asarray(it.points_m, float) - np.array([cam_x_m, cam_y_m])
                cells = _polyline_dist(cxr, cyr, pts) < reach + 0.5 * it.width_m
                layer, shade = out.fixtures, _cable_shade(pts, 0.5 * it.width_m)
            elif it.kind in ("sprinkler", "detector"):
                cells = np.hypot(cxr - x0r, cyr - y0r) < reach + 0.5 * it.length_m
                layer, shade = out.fixtures, _disc_shade(it, x0r, y0r)
            else:
                sd, _, _ = _rect_sd(it, x0r, y0r, cxr, cyr)
                cells = sd > -reach
                if it.kind in _EDGES_M:
                    edges = np.zeros(cells.shape, bool)
                    for e in _EDGES_M[it.kind]:
                        edges |= np.abs(sd - e) < reach
                layer = out.panels if it.kind == "panel" else out.fills
                shade = _TILE_SHADES[it.kind](it, x0r, y0r)
            cells = cells & ok
        if np.any(cells):
            layer.append((cells, shade, None if edges is None else edges & cells))
    return out


def _local(xr: np.ndarray, yr: np.ndarray, x0r: float, y0r: float,
           yaw_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates along and across an item's length (its centre at ``x0r, y0r``)."""
    dx, dy = xr - x0r, yr - y0r
    if yaw_deg == 0.0:
        return dx, dy
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return c * dx + s * dy, -s * dx + c * dy


def _rect_sd(it: ScatterItem, x0r: float, y0r: float, xr: np.ndarray,
             yr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance inside the item's rectangle, and the local coordinates."""
    a, b = _local(xr, yr, x0r, y0r, it.yaw_deg)
    sd = np.minimum(0.5 * it.length_m - np.abs(a), 0.5 * it.width_m - np.abs(b))
    return sd, a, b


def _framed(grey: float, frame_grey: float, frame_m: float):
    """A rectangle of ``grey`` inside a ``frame_m`` frame of ``frame_grey`` (a hatch)."""
    def make(it: ScatterItem, x0r: float, y0r: float) -> Shade:
        def shade(xr, yr, inv_fp, val):
            sd, _, _ = _rect_sd(it, x0r, y0r, xr, yr)
            val = val + ramp(sd, inv_fp) * (frame_grey - val)
            return val + ramp(sd - frame_m, inv_fp) * (grey - val)
        return shade
    return make


def _panel(it: ScatterItem, x0r: float, y0r: float) -> Shade:
    def shade(xr, yr, inv_fp, val, em=None):
        sd, _, _ = _rect_sd(it, x0r, y0r, xr, yr)
        c_all, c_face = ramp(sd, inv_fp), ramp(sd - PANEL_FRAME_M, inv_fp)
        val = val + c_all * (PANEL_FRAME_GREY - val)
        val = val + c_face * (PANEL_GREY - val)
        if em is None:
            return val
        em = em - c_all * em                         # the frame does not emit
        return val, em + c_face * (PANEL_GREY - em)
    return shade


def _vent(it: ScatterItem, x0r: float, y0r: float) -> Shade:
    def shade(xr, yr, inv_fp, val):
        sd, _, b = _rect_sd(it, x0r, y0r, xr, yr)
        # slats along the length: dark gaps half the period wide, across it
        ph = np.mod(b, VENT_SLAT_M) - 0.5 * VENT_SLAT_M
        gap = ramp(0.25 * VENT_SLAT_M - np.abs(ph), inv_fp)
        fade = np.clip(2.0 / (inv_fp * VENT_SLAT_M + 1e-9) - 0.5, 0.0, 1.0)
        gap = gap + fade * (0.5 - gap)
        inner = VENT_GREY + gap * (VENT_GAP_GREY - VENT_GREY)
        val = val + ramp(sd, inv_fp) * (VENT_GREY - val)
        return val + ramp(sd - VENT_FRAME_M, inv_fp) * (inner - val)
    return shade


def _patch(it: ScatterItem, x0r: float, y0r: float) -> Shade:
    def shade(xr, yr, inv_fp, val):
        sd, _, _ = _rect_sd(it, x0r, y0r, xr, yr)
        return val + ramp(sd, inv_fp) * np.float32(it.grey)
    return shade


def _stain(it: ScatterItem, x0r: float, y0r: float) -> Shade:
    def shade(xr, yr, inv_fp, val):
        a, b = _local(xr, yr, x0r, y0r, it.yaw_deg)
        q = (a / (0.5 * it.length_m)) ** 2 + (b / (0.5 * it.width_m)) ** 2
        f = np.clip(1.0 - q, 0.0, 1.0)
        return val - np.float32(it.grey) * f * f
    return shade


_TILE_SHADES = {"panel": _panel, "vent": _vent, "patch": _patch, "stain": _stain,
                "hatch": _framed(HATCH_GREY, HATCH_FRAME_GREY, HATCH_FRAME_M)}


def _disc_shade(it: ScatterItem, x0r: float, y0r: float) -> Shade:
    r = 0.5 * it.length_m

    def shade(xr, yr, inv_fp, val):
        d = np.hypot(xr - x0r, yr - y0r)
        if it.kind == "sprinkler":
            val = val + ramp(r - d, inv_fp) * (SPRINKLER_GREY - val)
            return val + ramp(0.45 * r - d, inv_fp) * (SPRINKLER_CORE_GREY - val)
        val = val + ramp(r - d, inv_fp) * (DETECTOR_GREY - val)
        val = val + ramp(0.05 * r - np.abs(d - 0.67 * r), inv_fp) * (
            DETECTOR_GROOVE_GREY - val)
        return val + ramp(0.12 * r - d, inv_fp) * (DETECTOR_LED_GREY - val)
    return shade


def _polyline_dist(x: np.ndarray, y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance from points ``(x, y)`` to the polyline ``pts`` ``(n, 2)``."""
    dist = np.full(np.shape(x), np.inf, dtype=np.result_type(x, np.float32))
    p = np.asarray(pts, float).tolist()
    for (x1, y1), (x2, y2) in zip(p[:-1], p[1:], strict=True):
        ex, ey = x2 - x1, y2 - y1
        ll = max(ex * ex + ey * ey, 1e-18)
        t = np.clip(((x - x1) * ex + (y - y1) * ey) / ll, 0.0, 1.0)
        dist = np.minimum(dist, np.hypot(x - x1 - t * ex, y - y1 - t * ey))
    return dist


def _cable_shade(pts: np.ndarray, half_w: float) -> Shade:
    def shade(xr, yr, inv_fp, val):
        cov = ramp(half_w - _polyline_dist(xr, yr, pts), inv_fp)
        return val + cov * (CABLE_GREY - val)
    return shade


__all__ = ["ScatterFeatures", "scatter_features"]
