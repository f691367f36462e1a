"""What real ceilings hold besides the site's lines and lights: objects in W.

The realism layer (:mod:`ceilkit.runtime.sim.realism`) lays these out once per site
and knob setting (seeded, fixed to the world, so a drive sees the same pipe in every
frame) and draws them over the ray-cast radiance, per pixel, with a one-footprint
linear ramp at every silhouette edge (anti-aliased, no bias), nearest last:

* :class:`PipeX`: a cylinder along x (pipes, ducts) below the ceiling, shaded by its
  normal with a specular stripe (what a lamp gives on a metal duct);
* :class:`BoxX` / :class:`BeamsY`: boxes along x (cable trays) and a periodic row of
  beams across the corridor, bottom and sides shaded apart;
* :class:`RectsZ`: periodic rows of horizontal rectangles at a height (pendant lamps,
  skylights, vent grilles with slats, hanging lamp rows of the site);
* :class:`DiscsZ`: periodic rows of discs at a height (sprinklers, smoke detectors);
* :class:`SignsX`: exit signs, luminous vertical panels facing along the corridor;
* :class:`People`: vertical cylinders (0.25 m radius, 1.75 m tall) walking along x.

Every object is ``draw(rays) -> (coverage, radiance)`` on flat pixel rays in W;
``rays`` holds the camera centre ``o`` (3,), the unit directions ``d`` (N, 3) float32 and
the angular footprint of each pixel ``ang`` (N,) (radians). Coordinates follow SPEC §1
(W: z up, the floor z = 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

F32 = np.float32


@dataclass(frozen=True, eq=False)
class Rays:
    """Pixel rays in W for one pose: centre ``o`` (3,) m, unit ``d`` (N, 3), pixel
    footprint ``ang`` (N,) rad, and the time ``t_s`` (s) the rays were taken at."""

    o: np.ndarray
    d: np.ndarray
    ang: np.ndarray
    t_s: float = 0.0


def ramp(sd: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Coverage of a signed distance (> 0 inside) over a footprint-wide ramp."""
    return np.clip(0.5 + sd / np.maximum(fp, F32(1e-6)), 0.0, 1.0).astype(F32)


def _line_sd2(o2: np.ndarray, u2: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, ...]:
    """2-D: signed penetration of the rays' lines ``o2 + t u2`` into the convex polygon
    ``pts`` (k, 2) and the ray parameter of the closest approach to its centre.

    > 0: the line crosses the polygon, by that distance to its nearest silhouette."""
    L = np.hypot(u2[:, 0], u2[:, 1])
    L = np.maximum(L, F32(1e-9))
    nx, ny = -u2[:, 1] / L, u2[:, 0] / L
    s = [(p[0] - o2[0]) * nx + (p[1] - o2[1]) * ny for p in pts]
    s = np.stack(s, axis=0)
    sd = np.minimum(s.max(axis=0), (-s).max(axis=0))
    c = pts.mean(axis=0)
    t = ((c[0] - o2[0]) * u2[:, 0] + (c[1] - o2[1]) * u2[:, 1]) / (L * L)
    return sd.astype(F32), t.astype(F32)


@dataclass(frozen=True)
class PipeX:
    """A cylinder along x: axis at ``(y, z)``, radius ``r``, base grey, highlight."""

    y: float
    z: float
    r: float
    grey: float = 110.0
    spec: float = 90.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays.o, rays.d
        uy, uz = d[:, 1], d[:, 2]
        L2 = np.maximum(uy * uy + uz * uz, F32(1e-12))
        ey, ez = F32(self.y - o[1]), F32(self.z - o[2])
        t = (ey * uy + ez * uz) / L2                      # closest approach (3-D range)
        L = np.sqrt(L2)
        s = (ey * uz - ez * uy) / L                       # signed 2-D distance to the axis
        sd = F32(self.r) - np.abs(s)
        fp = np.abs(t) * rays.ang
        cov = np.where(t > 0, ramp(sd, fp), 0.0).astype(F32)
        # surface normal at the visible point: across the pipe, -1..1 over its width
        a = np.clip(s / F32(self.r), -1.0, 1.0)
        shade = F32(self.grey) * (F32(0.55) + F32(0.45) * np.sqrt(1.0 - a * a))
        shade = shade + F32(self.spec) * np.exp(-((a - F32(0.45)) / F32(0.12)) ** 2)
        return cov, shade.astype(F32)


def _box_2d(o2: np.ndarray, u2: np.ndarray, lo: tuple[float, float],
            hi: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays' lines against the rectangle [lo, hi] in a 2-D section: penetration, range,
    and whether the face seen is the bottom one (the second coordinate is z)."""
    pts = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    sd, t = _line_sd2(o2, u2, pts)
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = (F32(lo[1]) - o2[1]) / u2[:, 1]
        a = o2[0] + tz * u2[:, 0]
    bottom = (a >= lo[0]) & (a <= hi[0]) & (tz > 0)
    return sd, t, bottom


@dataclass(frozen=True)
class BoxX:
    """A box along x (a cable tray): ``y`` centre, half width, z from bottom to top."""

    y: float
    half_w: float
    z_bot: float
    z_top: float
    grey: float = 95.0
    side_grey: float = 70.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays.o, rays.d
        sd, t, bottom = _box_2d(np.array([o[1], o[2]], F32), d[:, 1:3],
                                (self.y - self.half_w, self.z_bot),
                                (self.y + self.half_w, self.z_top))
        cov = np.where(t > 0, ramp(sd, np.abs(t) * rays.ang), 0.0).astype(F32)
        return cov, np.where(bottom, F32(self.grey), F32(self.side_grey)).astype(F32)


@dataclass(frozen=True)
class BeamsY:
    """Beams across (along y) every ``pitch`` m from ``x0``, between ``y_lo`` and
    ``y_hi``: half width (in x), z from bottom to top."""

    x0: float
    pitch: float
    half_w: float
    z_bot: float
    z_top: float
    y_lo: float
    y_hi: float
    grey: float = 135.0
    side_grey: float = 100.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays.o, rays.d
        with np.errstate(divide="ignore", invalid="ignore"):
            tm = (F32(0.5 * (self.z_bot + self.z_top)) - F32(o[2])) / d[:, 2]
        xm = F32(o[0]) + np.where(np.isfinite(tm), tm, 0.0) * d[:, 0]
        k = np.rint((xm - F32(self.x0)) / F32(self.pitch))
        xk = F32(self.x0) + k * F32(self.pitch)
        o2 = np.stack([np.full(d.shape[0], o[0], F32) - xk, np.full(d.shape[0], o[2], F32)])
        sd, t, bottom = _box_2d(o2, d[:, [0, 2]], (-self.half_w, self.z_bot),
                                (self.half_w, self.z_top))
        yh = F32(o[1]) + t * d[:, 1]
        sd = np.minimum(sd, np.minimum(yh - F32(self.y_lo), F32(self.y_hi) - yh))
        cov = np.where(t > 0, ramp(sd, np.abs(t) * rays.ang), 0.0).astype(F32)
        return cov, np.where(bottom, F32(self.grey), F32(self.side_grey)).astype(F32)


def _plane_hit(rays: Rays, z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Hits of the rays on the plane at height z: x, y, range t (inf: none), footprint."""
    o, d = rays.o, rays.d
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (F32(z) - F32(o[2])) / d[:, 2]
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf).astype(F32)
    tt = np.where(np.isfinite(t), t, 0.0)
    x = F32(o[0]) + tt * d[:, 0]
    y = F32(o[1]) + tt * d[:, 1]
    fp = tt * rays.ang / np.maximum(np.abs(d[:, 2]), F32(0.05))
    return x, y, t, fp


@dataclass(frozen=True)
class RectsZ:
    """Horizontal rectangles at height ``z``: centres ``x0 + k * pitch`` (k in
    ``0..count-1``, count 0: unbounded) at each y of ``ys``; half length (x), half
    width (y); ``grey``; ``slats``: a grille's slat period (m, 0: plain face)."""

    z: float
    x0: float
    pitch: float
    ys: tuple[float, ...]
    half_l: float
    half_w: float
    grey: float
    count: int = 0
    slats: float = 0.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        x, y, t, fp = _plane_hit(rays, self.z)
        dx = x - F32(self.x0)
        if self.pitch > 0:
            k = np.rint(dx / F32(self.pitch))
            if self.count > 0:
                k = np.clip(k, 0, self.count - 1)
            dx = dx - k * F32(self.pitch)
        sd = np.full(x.shape, -np.inf, F32)
        for yc in self.ys:
            sd = np.maximum(sd, np.minimum(F32(self.half_l) - np.abs(dx),
                                           F32(self.half_w) - np.abs(y - F32(yc))))
        cov = np.where(np.isfinite(t), ramp(sd, fp), 0.0).astype(F32)
        val = np.full(x.shape, self.grey, F32)
        if self.slats > 0:
            # slats across x: dark gaps half the period wide, inside a 3 cm frame
            ph = np.mod(dx, F32(self.slats)) / F32(self.slats)
            gap = ramp(F32(0.25) - np.abs(ph - F32(0.5)), fp / F32(self.slats))
            inner = sd > F32(0.03)
            val = np.where(inner, val * (1.0 - F32(0.75) * gap), val).astype(F32)
        return cov, val


@dataclass(frozen=True)
class DiscsZ:
    """Discs at height ``z``: centres ``x0 + k * pitch`` at each y of ``ys``; radius
    ``r``; ``grey``, with a darker ring (``ring_grey``) in the outer third."""

    z: float
    x0: float
    pitch: float
    ys: tuple[float, ...]
    r: float
    grey: float
    ring_grey: float | None = None

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        x, y, t, fp = _plane_hit(rays, self.z)
        dx = x - F32(self.x0)
        dx = dx - np.rint(dx / F32(self.pitch)) * F32(self.pitch)
        dist = np.full(x.shape, np.inf, F32)
        for yc in self.ys:
            dist = np.minimum(dist, np.hypot(dx, y - F32(yc)))
        cov = np.where(np.isfinite(t), ramp(F32(self.r) - dist, fp), 0.0).astype(F32)
        val = np.full(x.shape, self.grey, F32)
        if self.ring_grey is not None:
            val = np.where(dist > F32(self.r * 0.66), F32(self.ring_grey), val)
        return cov, val.astype(F32)


@dataclass(frozen=True)
class SignsX:
    """Exit signs: luminous vertical panels in the planes ``x = x0 + k * pitch``,
    ``y`` centre, half width (y), from ``z_lo`` to ``z_hi``."""

    x0: float
    pitch: float
    y: float
    half_w: float
    z_lo: float
    z_hi: float
    grey: float = 235.0
    reach_m: float = 15.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays.o, rays.d
        n = d.shape[0]
        cov = np.zeros(n, F32)
        k0 = math.ceil((o[0] - self.reach_m - self.x0) / self.pitch)
        k1 = math.floor((o[0] + self.reach_m - self.x0) / self.pitch)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(k0, k1 + 1):
                t = (F32(self.x0 + k * self.pitch - o[0])) / d[:, 0]
                ok = np.isfinite(t) & (t > 0)
                tt = np.where(ok, t, 0.0)
                yy = F32(o[1]) + tt * d[:, 1] - F32(self.y)
                zz = F32(o[2]) + tt * d[:, 2]
                sd = np.minimum(F32(self.half_w) - np.abs(yy),
                                np.minimum(zz - F32(self.z_lo), F32(self.z_hi) - zz))
                fp = tt * rays.ang / np.maximum(np.abs(d[:, 0]), F32(0.05))
                cov = np.maximum(cov, np.where(ok, ramp(sd, fp), 0.0))
        return cov.astype(F32), np.full(n, self.grey, F32)


@dataclass(frozen=True)
class People:
    """People walking along x: vertical cylinders of radius ``r`` from the floor to
    ``height``; person i at ``y_i``, ``x_i(t) = x0_i + v_i t``, repeated every
    ``period`` m of x (so a drive meets them again)."""

    ys: tuple[float, ...]
    x0s: tuple[float, ...]
    speeds: tuple[float, ...]
    period: float = 12.0
    r: float = 0.25
    height: float = 1.75
    grey: float = 60.0

    def draw(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays.o, rays.d
        n = d.shape[0]
        # the part of each ray below the head: from the camera to z = height (or floor)
        with np.errstate(divide="ignore", invalid="ignore"):
            ze = np.where(d[:, 2] > 0, F32(self.height), F32(0.0))
            te = (ze - F32(o[2])) / d[:, 2]
        te = np.where(np.isfinite(te) & (te > 0), te, F32(0.0)).astype(F32)
        te = np.minimum(te, F32(30.0))
        cov = np.zeros(n, F32)
        for y, x0, v in zip(self.ys, self.x0s, self.speeds, strict=True):
            px = x0 + v * rays.t_s
            # the copy of this person nearest the camera (within half a period)
            px += self.period * round((o[0] - px) / self.period)
            ax, ay = F32(px - o[0]), F32(y - o[1])
            ux, uy = d[:, 0], d[:, 1]
            L2 = np.maximum(ux * ux + uy * uy, F32(1e-12))
            t = np.clip((ax * ux + ay * uy) / L2, 0.0, te)
            dist = np.hypot(ux * t - ax, uy * t - ay)
            cov = np.maximum(cov, ramp(F32(self.r) - dist, t * rays.ang))
        return cov.astype(F32), np.full(n, self.grey, F32)


__all__ = ["Rays", "PipeX", "BoxX", "BeamsY", "RectsZ", "DiscsZ", "SignsX", "People",
           "ramp"]
