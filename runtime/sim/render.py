"""The ceiling simulator: grey frames a rig would see at a vehicle pose in a site.

Rendering is ray casting with analytic shading, so the geometry is exact (no
resampled textures): every sub-pixel's unit ray through the lens (distortion
included, :meth:`CameraModel.unproject`) is computed once per camera and
supersampling factor, turned once per mount tilt and swing, and cached (up to
:data:`GRID_CACHE_BYTES`, least recently used dropped first). Per frame the rays are turned to
the world, intersected with the ceiling plane ``z = ceiling_height`` and the
corridor walls ``y = axis +- w``, and shaded at the hit point:

* ceiling: base grey with a gentle texture fixed to the world;
* lamps (``site.lamp_rectangles()``): bright rectangles;
* seams: thin dark lines for every ``corridor.lines_along`` y and ``lines_across`` x
  that is not already a lamp edge;
* spot lights (``site.lights_m``): bright discs with a soft halo;
* blocks (dark or bright) and printed markers: :mod:`ceilkit.runtime.sim.marks`;
* walls: darker, with a vertical gradient; the floor darker still;
* clutter (optional): door frames and posters on the walls, pipes along the
  ceiling's edges (distractor lines).

Then the samples are averaged, blurred (Gaussian, ``blur_px``), vignetted, scaled by
``exposure``, given Gaussian sensor noise from the seeded rng and clipped to uint8.
Pixels whose ray the lens model does not define (beyond a fisheye's range) are black.

Convention (SPEC §1): ``R_world_cam = Rz(yaw) @ rig.mount.R_vehicle_cam``; the camera
centre is ``rig.mount.camera_position(x, y, yaw)``. Pixel (u, v) has its centre at
integer coordinates, the origin at the centre of the top-left pixel; the sub-pixel
samples for a factor ``s`` are at ``u + (k + 0.5) / s - 0.5``, k = 0..s-1.

Speed: the image is split into cells of 4x4 pixels; only cells that an edge can
cross (a feature, the ceiling-wall junction, the lens's edge) are shaded per
sub-pixel, the rest once per pixel. Shading edges are anti-aliased with a linear
ramp one sample footprint wide, which is symmetric and so adds no bias.

Example::

    rig, site = Rig.load("configs/corridor/rig.yaml"), Site.load("configs/corridor/site.yaml")
    image = render_frame(rig, site, 1.0, 0.02, math.radians(1.0),
                         rng=np.random.default_rng(0))           # (480, 640) uint8
    with SimSource(rig, site, straight_drive(100)) as src:
        for frame in src: ...
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.io.sources import Frame, SourceBase
from ceilkit.runtime.sim.marks import BLOCK_GREY as BLOCK_GREY  # re-exported
from ceilkit.runtime.sim.marks import mark_features
from ceilkit.runtime.sim.marks import ramp as _ramp
from ceilkit.runtime.sim.scatter import Scatter
from ceilkit.runtime.sim.scatter_shade import scatter_features

# Radiance of each surface, in grey levels at exposure 1 (before vignetting).
CEILING_GREY = 150.0
SEAM_GREY = 95.0
LAMP_GREY = 250.0
LIGHT_GREY = 250.0
HALO_GREY = 45.0          # default peak halo added around a spot light (SimOptions.halo)
WALL_TOP_GREY = 105.0     # wall just under the ceiling
WALL_BOTTOM_GREY = 65.0   # wall at the floor
FLOOR_GREY = 45.0
DOOR_FRAME_GREY = 30.0
DOOR_GREY = 85.0
POSTER_GREY = 200.0
PIPE_GREY = 60.0

CELL_PX = 4               # cell side in pixels
HALO_FACTOR = 3.0         # halo radius / light radius
WALL_MARGIN_M = 0.75      # derived wall half width: outermost line + this
TEXTURE_CELL_M = 0.02
TEXTURE_SIZE = 256
_DZ_MIN = 1e-3            # rays flatter than this (sine of elevation) miss the ceiling
_REPROJ_TOL_PX = 0.02


@dataclass(frozen=True)
class SimOptions:
    """How a frame is rendered.

    Attributes:
        noise_sigma: sensor noise, grey levels (Gaussian), >= 0.
        blur_px: optical blur, Gaussian sigma in pixels, >= 0 (0: none).
        exposure: gain on radiance before clipping, > 0.
        vignetting: relative fall-off at the image corner, in [0, 1).
        supersample: anti-aliasing factor s (s x s samples per pixel), 1..8.
        wall_half_width_m: corridor walls at ``y = axis +- w`` (axis: the middle of the
            corridor's lines_along); None derives w from the site (outermost line or
            lamp edge + 0.75 m); no walls when the site has no corridor.
        seam_width_m: width of a drawn ceiling line (seam), m.
        light_radius_m: radius of a spot light, m.
        clutter: door frames, posters on the walls and pipes along the ceiling's edges
            (distractor lines).
        texture: amplitude of the ceiling texture, grey levels (standard deviation).
        halo: peak glow added around a spot light, grey levels, >= 0 (0: a bare disc);
            it falls off as ``(1 - (d / 3r)^2)^2`` out to three light radii.
        scatter: what the ceiling holds besides the site's features (light panels,
            vents, hatches, patched and stained tiles, sprinklers, detectors, cables:
            :class:`~ceilkit.runtime.sim.scatter.Scatter`, a ``scene.yaml``), or None.

    Vignetting and the halo are what a real lens and lamp give, and both pull a spot's
    intensity-weighted centroid towards the image centre (see docs/simulator.md for the
    figures); set them to 0 for frames whose only centroid shift is the geometric one.
    """

    noise_sigma: float = 2.0
    blur_px: float = 0.8
    exposure: float = 1.0
    vignetting: float = 0.3
    supersample: int = 3
    wall_half_width_m: float | None = None
    seam_width_m: float = 0.012
    light_radius_m: float = 0.08
    clutter: bool = False
    texture: float = 3.0
    halo: float = HALO_GREY
    scatter: Scatter | None = None

    def __post_init__(self) -> None:
        def bad(name: str, want: str) -> ConfigError:
            return ConfigError(None, f"options.{name}",
                               f"expected {want}, found {getattr(self, name)!r}")

        for name in ("noise_sigma", "blur_px", "exposure", "vignetting", "seam_width_m",
                     "light_radius_m", "texture", "halo"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(name, "a finite number")
        if self.noise_sigma < 0:
            raise bad("noise_sigma", "a number >= 0")
        if self.blur_px < 0:
            raise bad("blur_px", "a number >= 0")
        if self.exposure <= 0:
            raise bad("exposure", "a number > 0")
        if not 0 <= self.vignetting < 1:
            raise bad("vignetting", "a number in [0, 1)")
        if self.seam_width_m <= 0:
            raise bad("seam_width_m", "a width > 0 m")
        if self.light_radius_m <= 0:
            raise bad("light_radius_m", "a radius > 0 m")
        if self.texture < 0:
            raise bad("texture", "a number >= 0")
        if self.halo < 0:
            raise bad("halo", "a number >= 0")
        if self.scatter is not None and not isinstance(self.scatter, Scatter):
            raise bad("scatter", "None or a Scatter (a scene file's items)")
        s = self.supersample
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 1 <= s <= 8:
            raise bad("supersample", "an integer in 1..8")
        w = self.wall_half_width_m
        if w is not None and (isinstance(w, bool) or not isinstance(w, (int, float))
                              or not math.isfinite(w) or w <= 0):
            raise bad("wall_half_width_m", "None or a half width > 0 m")

    def replace(self, **changes: Any) -> SimOptions:
        """A copy with some fields changed (validated again)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(changes)
        return SimOptions(**d)


# --------------------------------------------------------------------------- ray cache
@dataclass(frozen=True, eq=False)
class _Grid:
    """Per (camera, tilt, swing, s): rays in the level frame, cell-major.

    The level frame L is W turned by ``-(yaw + pan)``: ``R_world_cam = Rz(yaw + pan) @
    R_level_cam``. ``q = (dx/dz, dy/dz)`` of a level-frame ray: its ceiling hit is
    ``h * q`` from the camera, h the ceiling's height above it.
    Sample arrays are ``(n_cells, B*B)`` float32 (B = CELL_PX * s), samples row-major
    inside a cell; pixel arrays are ``(Hp, Wp)`` (the image padded to whole cells).
    """

    s: int
    width: int
    height: int
    ncy: int
    ncx: int
    # samples, cell-major
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    qx: np.ndarray
    qy: np.ndarray
    valid: np.ndarray       # lens defines the ray (bool)
    ceil: np.ndarray        # valid and dz > _DZ_MIN (bool)
    inv_fq: np.ndarray      # 1 / footprint of a sample on the plane at h = 1
    pix: np.ndarray         # flat index of the sample's pixel in the (Hp, Wp) image
    # cells
    cq: np.ndarray          # (n, 2) centre of the cell's ceiling hits at h = 1 (nan: none)
    rq: np.ndarray          # (n,) radius around cq holding them all
    fq: np.ndarray          # (n,) largest sample footprint at h = 1
    mixed: np.ndarray       # (n,) cell holds both ceiling and other samples
    has_other: np.ndarray   # (n,) cell holds a valid sample that misses the ceiling
    # pixels (Hp, Wp)
    p_dx: np.ndarray
    p_dy: np.ndarray
    p_dz: np.ndarray
    p_valid: np.ndarray
    p_ceil: np.ndarray
    p_qx: np.ndarray
    p_qy: np.ndarray
    vig_r2: np.ndarray      # (H, W) squared radius from the principal point / corner's


_GRID_CACHE: OrderedDict[tuple, _Grid] = OrderedDict()
_RAY_CACHE: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
GRID_CACHE_BYTES = 512 * 2**20
"""The most bytes of ray grids (and of a camera's sub-pixel rays, shared by the grids
of its mount tilts) kept for reuse, least recently used dropped first (the newest
grid is kept whatever its size). A 640x480 grid at supersample 3 is about 98 MB, its
camera's rays 66 MB."""


def _grid(cam: CameraModel, R_level_cam: np.ndarray, s: int) -> _Grid:
    key = (cam, np.round(R_level_cam, 12).tobytes(), int(s))
    g = _GRID_CACHE.get(key)
    if g is not None:
        _GRID_CACHE.move_to_end(key)
        return g
    g = _build_grid(cam, R_level_cam, int(s))
    _GRID_CACHE[key] = g
    _trim_caches()
    return g


def _trim_caches() -> None:
    def nbytes(v: Any) -> int:
        arrays = v if isinstance(v, tuple) else vars(v).values()
        return sum(a.nbytes for a in arrays if isinstance(a, np.ndarray))

    total = sum(map(nbytes, _GRID_CACHE.values())) + sum(map(nbytes, _RAY_CACHE.values()))
    while total > GRID_CACHE_BYTES and (_RAY_CACHE or len(_GRID_CACHE) > 1):
        cache = _RAY_CACHE if _RAY_CACHE else _GRID_CACHE
        total -= nbytes(cache.popitem(last=False)[1])


def _to_cells(a: np.ndarray, ncy: int, ncx: int, b: int) -> np.ndarray:
    """(ncy*b, ncx*b) image layout -> (ncy*ncx, b*b) cell-major."""
    return np.ascontiguousarray(a.reshape(ncy, b, ncx, b).transpose(0, 2, 1, 3)
                                ).reshape(ncy * ncx, b * b)


def _unit_rays(cam: CameraModel, u: np.ndarray, v: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(rays (N, 3), ok (N,))`` of the pixels ``u x v`` (row-major, N = v.size *
    u.size): :meth:`CameraModel.unit_rays` (the same numbers: its arithmetic in its
    order, without its masks when every pixel is inside the image); a pixel outside
    the image has the ray 0, one the lens does not define the optical axis."""
    iu = (u >= -0.5) & (u <= cam.width - 0.5)
    iv = (v >= -0.5) & (v <= cam.height - 0.5)
    uu, vv = np.meshgrid(u, v)
    px = np.stack([uu.ravel(), vv.ravel()], axis=1)
    whole = bool(iu.all() and iv.all())
    inside = None if whole else (iv[:, None] & iu[None, :]).ravel()
    pin = px if whole else px[inside]
    xy = cam.unproject(pin)
    if cam.is_distorted:
        good = cam.reprojects(pin, xy, _REPROJ_TOL_PX)
    else:           # a linear lens's inverse reprojects within 1e-9 px wherever finite
        good = np.isfinite(xy).all(axis=1)
    x = np.where(good, xy[:, 0], 0.0)
    y = np.where(good, xy[:, 1], 0.0)
    n = np.sqrt((x * x + y * y) + 1.0)         # np.linalg.norm of (x, y, 1)
    rays = np.zeros((px.shape[0], 3))
    if whole:
        rays[:, 0], rays[:, 1], rays[:, 2] = x / n, y / n, 1.0 / n
        return rays, good
    rays[inside] = np.stack([x / n, y / n, 1.0 / n], axis=1)
    ok = inside.copy()
    ok[inside] = good
    return rays, ok


def _level_rays(cam: CameraModel, R_lc: np.ndarray, s: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``dx, dy, dz, ok`` ``(Hs, Ws)``: the unit rays of the sub-pixel samples
    (factor ``s``, the image padded to whole cells) in the level frame. Their rays in
    the camera frame are kept for the next mount of the same camera."""
    b = CELL_PX * s
    hs, ws = -(-cam.height // CELL_PX) * b, -(-cam.width // CELL_PX) * b
    key = (cam, s)
    hit = _RAY_CACHE.get(key)
    if hit is None:
        hit = _unit_rays(cam, (np.arange(ws) + 0.5) / s - 0.5, (np.arange(hs) + 0.5) / s - 0.5)
        _RAY_CACHE[key] = hit
    _RAY_CACHE.move_to_end(key)
    rays, ok = hit
    d = rays @ np.asarray(R_lc, float).T
    return d[:, 0].reshape(hs, ws), d[:, 1].reshape(hs, ws), d[:, 2].reshape(hs, ws), \
        ok.reshape(hs, ws)


def _footprint(qx: np.ndarray, qy: np.ndarray, ceil: np.ndarray) -> np.ndarray:
    """Footprint of each sample on the plane at unit height: the longer of its two
    steps; a sample beside a non-ceiling one (no gradient) takes the largest."""
    gi = np.hypot(np.gradient(qx, axis=0), np.gradient(qy, axis=0))
    gj = np.hypot(np.gradient(qx, axis=1), np.gradient(qy, axis=1))
    fq = np.fmax(gi, gj)
    fq = np.where(np.isfinite(fq) & (fq > 0), fq, np.nan)
    fill = np.nanmax(fq) if np.any(np.isfinite(fq)) else 1.0
    return np.where(ceil & np.isnan(fq), fill, fq)


def _cell_bounds(cqx: np.ndarray, cqy: np.ndarray, cceil: np.ndarray, cfq: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell: ``cq (n, 2)`` the centre of its ceiling hits at h = 1, ``rq (n,)`` a
    radius around it holding them all, ``fq (n,)`` its largest footprint (NaN: none)."""
    n = cqx.shape[0]
    any_ceil = cceil.any(axis=1)
    cq = np.full((n, 2), np.nan)
    rq = np.full(n, np.nan)
    fqc = np.full(n, np.nan)
    if np.any(any_ceil):
        sx, sy, sc = cqx[any_ceil], cqy[any_ceil], cceil[any_ceil]
        lo_x = np.where(sc, sx, np.inf).min(axis=1)
        hi_x = np.where(sc, sx, -np.inf).max(axis=1)
        lo_y = np.where(sc, sy, np.inf).min(axis=1)
        hi_y = np.where(sc, sy, -np.inf).max(axis=1)
        mx, my = 0.5 * (lo_x + hi_x), 0.5 * (lo_y + hi_y)
        r = np.where(sc, np.hypot(sx - mx[:, None], sy - my[:, None]), 0.0).max(axis=1)
        cq[any_ceil] = np.stack([mx, my], axis=1)
        rq[any_ceil] = r * (1 + 1e-6) + 1e-9
        fqc[any_ceil] = np.where(sc, cfq[any_ceil], 0.0).max(axis=1)
    return cq, rq, fqc


def _build_grid(cam: CameraModel, R_lc: np.ndarray, s: int) -> _Grid:
    W, H = cam.width, cam.height
    ncx, ncy = -(-W // CELL_PX), -(-H // CELL_PX)
    b = CELL_PX * s
    hs, ws = ncy * b, ncx * b
    dx, dy, dz, ok = _level_rays(cam, R_lc, s)
    ceil = ok & (dz > _DZ_MIN)
    with np.errstate(divide="ignore", invalid="ignore"):
        qx = np.where(ceil, dx / dz, np.nan)
        qy = np.where(ceil, dy / dz, np.nan)
    fq = _footprint(qx, qy, ceil)

    def cells(a: np.ndarray) -> np.ndarray:
        return _to_cells(a, ncy, ncx, b)

    cqx, cqy, cceil, cok, cfq = cells(qx), cells(qy), cells(ceil), cells(ok), cells(fq)
    cq, rq, fqc = _cell_bounds(cqx, cqy, cceil, cfq)
    any_ceil = cceil.any(axis=1)
    mixed = any_ceil & ~cceil.all(axis=1)
    has_other = (cok & ~cceil).any(axis=1)
    # pixel index of each sample in the padded (Hp, Wp) image
    pi = (np.arange(hs) // s)[:, None] * (ncx * CELL_PX) + (np.arange(ws) // s)[None, :]
    # pixel centres: for an odd s the middle samples (u + (k + 0.5) / s - 0.5 = u
    # exactly at k = (s - 1) / 2), else their own rays
    hp, wp = ncy * CELL_PX, ncx * CELL_PX
    if s % 2:
        mid = slice(s // 2, None, s)
        pdx, pdy, pdz = dx[mid, mid], dy[mid, mid], dz[mid, mid]
        pok = np.ascontiguousarray(ok[mid, mid])
    else:
        prays, pok = _unit_rays(cam, np.arange(wp, dtype=float), np.arange(hp, dtype=float))
        pd = prays @ np.asarray(R_lc, float).T
        pdx, pdy, pdz = (pd[:, k].reshape(hp, wp) for k in range(3))
        pok = pok.reshape(hp, wp)
    pceil = pok & (pdz > _DZ_MIN)
    with np.errstate(divide="ignore", invalid="ignore"):
        pqx = np.where(pceil, pdx / pdz, 0.0)
        pqy = np.where(pceil, pdy / pdz, 0.0)
    cu, cv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    corners = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]])
    rc2 = np.max((corners[:, 0] - cam.cx) ** 2 + (corners[:, 1] - cam.cy) ** 2)
    vig = ((cu - cam.cx) ** 2 + (cv - cam.cy) ** 2) / rc2

    f32 = np.float32
    with np.errstate(invalid="ignore"):     # q is finite on the ceiling, NaN off it
        fx, fy = np.where(ceil, qx, 0.0).astype(f32), np.where(ceil, qy, 0.0).astype(f32)
    return _Grid(
        s=s, width=W, height=H, ncy=ncy, ncx=ncx,       # (cast, then reordered to cells)
        dx=cells(dx.astype(f32)), dy=cells(dy.astype(f32)), dz=cells(dz.astype(f32)),
        qx=cells(fx), qy=cells(fy), valid=cok, ceil=cceil,
        inv_fq=np.where(cceil, 1.0 / np.where(cceil, cfq, 1.0), 0.0).astype(f32),
        pix=cells(pi).astype(np.int64),
        cq=cq, rq=rq, fq=fqc, mixed=mixed | (cok.any(axis=1) & ~cok.all(axis=1)),
        has_other=has_other,
        p_dx=pdx.astype(f32), p_dy=pdy.astype(f32), p_dz=pdz.astype(f32),
        p_valid=pok, p_ceil=pceil, p_qx=pqx.astype(f32), p_qy=pqy.astype(f32),
        vig_r2=vig.astype(f32),
    )


# --------------------------------------------------------------------------- texture
_TEXTURE: np.ndarray | None = None


def _texture_tile() -> np.ndarray:
    """A fixed, periodic, smooth noise tile of unit standard deviation."""
    global _TEXTURE
    if _TEXTURE is None:
        rng = np.random.default_rng(20240611)
        t = rng.standard_normal((TEXTURE_SIZE, TEXTURE_SIZE)).astype(np.float32)
        big = np.tile(t, (3, 3))
        big = cv2.GaussianBlur(big, (0, 0), 2.0)
        t = big[TEXTURE_SIZE:2 * TEXTURE_SIZE, TEXTURE_SIZE:2 * TEXTURE_SIZE]
        t = (t - t.mean()) / t.std()
        _TEXTURE = np.ascontiguousarray(t, dtype=np.float32)
    return _TEXTURE


# --------------------------------------------------------------------------- the scene
def wall_half_width(site: Site, options: SimOptions = SimOptions()) -> float | None:
    """Half width w of the corridor (walls at ``y = axis +- w``), or None: no walls.

    ``options.wall_half_width_m`` if given; else, for a site with a corridor, the
    outermost line or lamp edge from the axis plus 0.75 m.
    """
    if site.corridor is None:
        return None
    if options.wall_half_width_m is not None:
        return float(options.wall_half_width_m)
    axis = site.corridor.axis_y_m
    ext = max(abs(y - axis) for y in site.corridor.lines_along_m)
    for row in site.lamps:
        ext = max(ext, abs(row.y_m - axis) + row.width_m / 2)
    for blk in site.blocks:
        ext = max(ext, float(np.max(np.abs(blk.corners_m[:, 1] - axis))))
    return ext + WALL_MARGIN_M


def _is_lamp_long_edge(site: Site, y: float, tol: float = 1e-6) -> bool:
    return any(abs(y - (r.y_m + sgn * r.width_m / 2)) < tol
               for r in site.lamps for sgn in (-1, 1))


def _lamp_edge_across_indices(site: Site, first: float, spacing: float) -> np.ndarray:
    """Indices k of across lines ``first + k * spacing`` that are lamp short edges."""
    ks: set[int] = set()
    for r in site.lamps:
        xs = r.centres()[:, 0]
        for e in np.concatenate([xs - r.length_m / 2, xs + r.length_m / 2]):
            k = round((e - first) / spacing)
            if abs(first + k * spacing - e) < 1e-6:
                ks.add(int(k))
    return np.array(sorted(ks), dtype=np.int64)


class _Frame:
    """Per-frame quantities: pose, rotation, offsets, walls."""

    def __init__(self, rig: Rig, site: Site, x_m: float, y_m: float, yaw_rad: float,
                 options: SimOptions):
        a = yaw_rad + rig.mount.pan_rad
        self.ca, self.sa = math.cos(a), math.sin(a)
        c = rig.mount.camera_position(x_m, y_m, yaw_rad)
        self.cx, self.cy, self.cz = float(c[0]), float(c[1]), float(c[2])
        self.h = site.ceiling_height_m - self.cz
        if self.h <= 0.05:
            raise ConfigError(site.source, "ceiling_height",
                              f"the ceiling ({site.ceiling_height_m:g} m) must be above the "
                              f"camera ({self.cz:g} m)")
        self.ceiling_m = site.ceiling_height_m
        w = wall_half_width(site, options)
        self.walls = False
        self.axis_r = 0.0
        self.w = math.inf
        if w is not None and site.corridor is not None:
            axis = site.corridor.axis_y_m
            if abs(self.cy - axis) < w:          # camera between the walls
                self.walls = True
                self.axis_r = axis - self.cy
                self.w = w

    def xy(self, qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ceiling hit relative to the camera, ``(x - cx, y - cy)``, m."""
        h = self.h
        xr = (h * self.ca) * qx - (h * self.sa) * qy
        yr = (h * self.sa) * qx + (h * self.ca) * qy
        return xr, yr


def _wall_shade(fr: _Frame, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray,
                clutter: bool) -> np.ndarray:
    """Radiance of rays that miss the ceiling (walls, floor); flat arrays."""
    out = np.full(dx.shape, FLOOR_GREY, dtype=np.float32)
    if not fr.walls:
        return out
    dwx = fr.ca * dx - fr.sa * dy
    dwy = fr.sa * dx + fr.ca * dy
    side = np.where(dwy >= 0, 1.0, -1.0).astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (fr.axis_r + side * fr.w) / dwy
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    z = fr.cz + t * dz
    on = np.isfinite(t) & (z >= 0)
    zc = np.clip(z, 0.0, fr.ceiling_m)
    g = WALL_BOTTOM_GREY + (WALL_TOP_GREY - WALL_BOTTOM_GREY) * zc / fr.ceiling_m
    out = np.where(on, g, out).astype(np.float32)
    if clutter:
        xw = fr.cx + np.where(on, t * dwx, 0.0)      # absolute x along the wall
        off = np.where(side > 0, 0.0, 3.75)
        # doors: 0.9 m wide, 2.1 m high, every 7.5 m, with a dark 7 cm frame
        u = np.mod(xw - 3.0 - off, 7.5) - 0.45 - 0.07
        inner = (np.abs(u) < 0.45) & (z < 2.1)
        outer = (np.abs(u) < 0.52) & (z < 2.17)
        out = np.where(on & outer, DOOR_FRAME_GREY, out)
        out = np.where(on & inner, DOOR_GREY, out)
        # posters: 0.6 x 0.8 m between the doors
        pu = np.mod(xw - 6.75 - off, 7.5) - 0.3
        poster = (np.abs(pu) < 0.3) & (z > 1.2) & (z < 2.0)
        out = np.where(on & poster, POSTER_GREY, out)
        # skirting board
        out = np.where(on & (z < 0.1), DOOR_FRAME_GREY + 20.0, out)
    return out.astype(np.float32)


@dataclass
class _Feature:
    """A ceiling feature: the cells it may touch and how to shade its samples.

    ``emitter``: it is a lamp or a light (what flickers); :func:`render_radiance` can
    give the emitters' share of the radiance apart (``split=True``).
    ``edges``: the cells an edge of it can cross (None: all its cells); the others are
    shaded once per pixel when no other feature needs them per sub-pixel (the inside
    of a large tile-filling item, a soft stain).
    """

    cells: np.ndarray            # (n_cells,) bool
    shade: Any                   # (xr, yr, inv_fp, value) -> value
    emitter: bool = False        # shade(..., em=share) -> (value, emitted share) too
    edges: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Emitters:
    """Per-lamp and per-light brightness (the simulator's realism layer sets it).

    A gain g gives radiance ``OFF_GREY + g * (full - OFF_GREY)``: 1 is the nominal lamp
    or light (``LAMP_GREY``, ``LIGHT_GREY`` and the halo), 0 a failed one (a dull
    diffuser, no halo).

    Attributes:
        lamp_gain: one ``(count,)`` array per ``site.lamps`` row.
        light_gain: ``(n_lights,)`` for ``site.lights_m``.
    """

    lamp_gain: tuple[np.ndarray, ...] = ()
    light_gain: np.ndarray | None = None


OFF_GREY = 172.0          # a lamp or light that is off: its diffuser, lit by the others


def _features(site: Site, fr: _Frame, options: SimOptions, cxr: np.ndarray,
              cyr: np.ndarray, reach: np.ndarray,
              emitters: Emitters | None = None) -> list[_Feature]:
    """Every ceiling feature with the cells it can touch, in drawing order (the
    scatter's tile fills, seams along, seams across, blocks and markers, the scatter's
    fixtures, lamps, lights, the scatter's light panels).

    ``cxr, cyr``: cell centres relative to the camera; ``reach``: cell radius plus a
    footprint (nan for cells without ceiling samples, which never match). Lamp rows
    with a ``z`` below the ceiling are left to the realism layer (drawn at their
    height).
    """
    with np.errstate(invalid="ignore"):
        scat = None
        if options.scatter is not None:
            scat = scatter_features(options.scatter, fr.cx, fr.cy, cxr, cyr, reach)
        feats = [] if scat is None else [_Feature(c, f, edges=e) for c, f, e in scat.fills]
        feats += _along_features(site, fr, options, cyr, reach)
        feats += _across_features(site, fr, options, cxr, reach)
        feats += [_Feature(c, f) for c, f in mark_features(site, fr.cx, fr.cy, cxr, cyr,
                                                           reach)]
        if scat is not None:
            feats += [_Feature(c, f, edges=e) for c, f, e in scat.fixtures]
        feats += _lamp_features(site, fr, cxr, cyr, reach, emitters)
        feats += _light_features(site, fr, options, cxr, cyr, reach, emitters)
        if scat is not None:
            feats += [_Feature(c, f, True, e) for c, f, e in scat.panels]
    return feats


def _along_features(site: Site, fr: _Frame, options: SimOptions, cyr: np.ndarray,
                    reach: np.ndarray) -> list[_Feature]:
    """Seams along x (``lines_along`` that are not lamp edges), then clutter pipes."""
    hw_seam = options.seam_width_m / 2
    along: list[tuple[float, float, float]] = []
    if site.corridor is not None:
        along += [(y, hw_seam, SEAM_GREY) for y in site.corridor.lines_along_m
                  if not _is_lamp_long_edge(site, y)]
    if options.clutter and fr.walls:
        axis = fr.axis_r + fr.cy
        for sgn in (-1.0, 1.0):
            along.append((axis + sgn * (fr.w - 0.12), 0.03, PIPE_GREY))
            along.append((axis + sgn * (fr.w - 0.30), 0.05, PIPE_GREY + 60.0))
    feats = []
    for y, hw, grey in along:
        yr0 = y - fr.cy

        def shade_along(xr, yr, inv_fp, val, yr0=yr0, hw=hw, grey=grey):
            cov = _ramp(hw - np.abs(yr - yr0), inv_fp)
            return val + cov * (grey - val)

        feats.append(_Feature(np.abs(cyr - yr0) < reach + hw, shade_along))
    return feats


def _across_features(site: Site, fr: _Frame, options: SimOptions, cxr: np.ndarray,
                     reach: np.ndarray) -> list[_Feature]:
    """Seams across (``x = first + k * spacing``), lamp edges left out."""
    if site.corridor is None or site.corridor.lines_across is None:
        return []
    hw_seam = options.seam_width_m / 2
    first = site.corridor.lines_across.first_m
    sp = site.corridor.lines_across.spacing_m
    skip = _lamp_edge_across_indices(site, first, sp)
    x0r = first - fr.cx
    kc = np.rint((cxr - x0r) / sp)
    dn = np.abs(cxr - x0r - kc * sp)
    near = (dn < reach + hw_seam) | (reach + hw_seam > sp / 2)
    if skip.size and np.any(near):
        # a cell whose only nearby line is a lamp edge needs nothing
        wide = reach + hw_seam > sp / 2
        near &= wide | ~np.isin(np.nan_to_num(kc).astype(np.int64), skip)

    def shade_across(xr, yr, inv_fp, val, x0r=x0r, sp=sp, skip=skip):
        k = np.rint((xr - x0r) / sp)
        cov = _ramp(hw_seam - np.abs(xr - x0r - k * sp), inv_fp)
        if skip.size:
            cov = np.where(np.isin(k.astype(np.int64), skip), 0.0, cov)
        return val + cov * (SEAM_GREY - val)

    return [_Feature(near, shade_across)]


def _lamp_features(site: Site, fr: _Frame, cxr: np.ndarray, cyr: np.ndarray,
                   reach: np.ndarray, emitters: Emitters | None) -> list[_Feature]:
    """Lamps on the ceiling: rows of bright rectangles (per-lamp gains if given)."""
    feats = []
    for i, row in enumerate(site.lamps):
        if row.z_m is not None and row.z_m < site.ceiling_height_m - 1e-9:
            continue                              # hangs below: drawn at its height
        hl, hwl = row.length_m / 2, row.width_m / 2
        x0r, y0r = row.x_m - fr.cx, row.y_m - fr.cy
        pitch = row.pitch_m if row.count > 1 else 0.0
        cells = np.abs(cyr - y0r) < reach + hwl
        if pitch > 0:
            kl = np.ceil((cxr - reach - hl - x0r) / pitch)
            ku = np.floor((cxr + reach + hl - x0r) / pitch)
            cells &= (np.maximum(kl, 0) <= np.minimum(ku, row.count - 1))
        else:
            cells &= np.abs(cxr - x0r) < reach + hl
        gain = None
        if emitters is not None and i < len(emitters.lamp_gain):
            gain = np.asarray(emitters.lamp_gain[i], np.float32)

        def shade_lamp(xr, yr, inv_fp, val, em=None, x0r=x0r, y0r=y0r, hl=hl, hwl=hwl,
                       pitch=pitch, count=row.count, gain=gain):
            dx = xr - x0r
            k = np.clip(np.rint(dx / pitch), 0, count - 1) if pitch > 0 else None
            if k is not None:
                dx = dx - k * pitch
            sd = np.minimum(hl - np.abs(dx), hwl - np.abs(yr - y0r))
            grey = LAMP_GREY
            if gain is not None:
                g = gain[k.astype(np.int64)] if k is not None else gain[0]
                grey = np.float32(OFF_GREY) + g * np.float32(LAMP_GREY - OFF_GREY)
            cov = _ramp(sd, inv_fp)
            if em is None:
                return val + cov * (grey - val)
            return val + cov * (grey - val), em + cov * (grey - em)

        feats.append(_Feature(cells, shade_lamp, emitter=True))
    return feats


def _light_features(site: Site, fr: _Frame, options: SimOptions, cxr: np.ndarray,
                    cyr: np.ndarray, reach: np.ndarray,
                    emitters: Emitters | None) -> list[_Feature]:
    """Spot lights: discs with a halo (per-light gains if given); with the site's
    ``light_size`` lit rectangles (``light_yaw``), with the same halo about their long
    axis (:func:`_rect_distances`)."""
    if not site.has_lights:
        return []
    rect = site.light_size_m
    if rect is None:
        rl = options.light_radius_m
        seg = 0.0
    else:
        rl = 0.5 * rect[1]                      # the halo's radius unit: half the width
        seg = 0.5 * (rect[0] - rect[1])         # half the long axis' core segment
    ca, sa = math.cos(site.light_yaw_rad), math.sin(site.light_yaw_rad)
    halo = np.float32(options.halo)
    rh = HALO_FACTOR * rl if options.halo > 0 else rl
    if rect is not None:                        # the reach of a lit rectangle or its halo
        rh = max(rh + seg, 0.5 * math.hypot(*rect))
    lr = site.lights_m - np.array([fr.cx, fr.cy])
    gains = None if emitters is None else emitters.light_gain
    # coarse cull: lights within reach of any ceiling cell
    ok = np.isfinite(reach)
    if not np.any(ok):
        return []
    ex, ey, er = cxr[ok], cyr[ok], reach[ok]
    lo_x, hi_x = np.min(ex - er), np.max(ex + er)
    lo_y, hi_y = np.min(ey - er), np.max(ey + er)
    keep = ((lr[:, 0] > lo_x - rh) & (lr[:, 0] < hi_x + rh)
            & (lr[:, 1] > lo_y - rh) & (lr[:, 1] < hi_y + rh))
    feats = []
    for i in np.flatnonzero(keep):
        lx, ly = lr[i]
        cells = np.hypot(cxr - lx, cyr - ly) < reach + rh
        if not np.any(cells):
            continue
        if gains is None:
            grey, hl = LIGHT_GREY, halo
        else:
            g = float(gains[i])
            grey, hl = OFF_GREY + g * (LIGHT_GREY - OFF_GREY), np.float32(g * halo)

        def shade_light(xr, yr, inv_fp, val, em=None, lx=lx, ly=ly, grey=grey, hl=hl):
            if rect is None:
                d = np.hypot(xr - lx, yr - ly)
                inside = rl - d
                d_halo, r_halo = d, rh
            else:
                inside, d_halo = _rect_distances(xr - lx, yr - ly, ca, sa, rect, seg)
                r_halo = HALO_FACTOR * rl
            if hl > 0:
                g = np.clip(1.0 - (d_halo / r_halo) ** 2, 0.0, 1.0)
                val = val + hl * g * g
                if em is not None:
                    em = em + hl * g * g
            cov = _ramp(inside, inv_fp)
            if em is None:
                return val + cov * (grey - val)
            return val + cov * (grey - val), em + cov * (grey - em)

        feats.append(_Feature(cells, shade_light, emitter=True))
    return feats


def _rect_distances(dx: np.ndarray, dy: np.ndarray, ca: float, sa: float,
                    size: tuple[float, float], seg: float) -> tuple[np.ndarray, np.ndarray]:
    """``(inside, d_halo)`` of ceiling samples ``(dx, dy)`` from a rectangular light's
    centre (long side along ``(ca, sa)``, ``size`` its length and width): the signed
    distance inside the rectangle (> 0 inside; what a disc's ``r - d`` is) and the
    distance from the core segment of its long axis (half length ``seg``: length minus
    width over 2), which the halo falls off with as a disc's from its centre (a disc is
    the case of a segment of length 0)."""
    a = np.abs(dx * ca + dy * sa)               # along the long side
    b = np.abs(-dx * sa + dy * ca)              # across it
    inside = np.minimum(0.5 * size[0] - a, 0.5 * size[1] - b)
    return inside, np.hypot(np.maximum(a - seg, 0.0), b)


# --------------------------------------------------------------------------- rendering
def _check_pose(x_m: float, y_m: float, yaw_rad: float) -> None:
    for name, v in (("x_m", x_m), ("y_m", y_m), ("yaw_rad", yaw_rad)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                or not math.isfinite(float(v)):
            raise ConfigError(None, name, f"expected a finite number, found {v!r}")


def render_radiance(rig: Rig, site: Site, x_m: float, y_m: float, yaw_rad: float,
                    options: SimOptions = SimOptions(), *, emitters: Emitters | None = None,
                    split: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The noise-free radiance ``(H, W)`` float32 (grey levels), before blur,
    vignetting, exposure and noise: the supersampled average of every pixel.

    ``emitters``: per-lamp and per-light gains (None: all nominal). ``split``: return
    ``(radiance, emitted)`` where ``emitted`` is the lamps' and lights' share of it
    (what a flickering supply modulates).
    """
    _check_pose(x_m, y_m, yaw_rad)
    g = _grid(rig.camera, rig.mount.R_level_cam, options.supersample)
    fr = _Frame(rig, site, float(x_m), float(y_m), float(yaw_rad), options)
    hp, wp = g.ncy * CELL_PX, g.ncx * CELL_PX

    # -- per pixel: base radiance (ceiling + texture, walls, floor, black) -------------
    pxr, pyr = fr.xy(g.p_qx, g.p_qy)
    tex = np.zeros((hp, wp), np.float32)
    if options.texture > 0:
        period = TEXTURE_SIZE * TEXTURE_CELL_M
        mx = (np.mod(pxr + np.float32(math.fmod(fr.cx, period)), period) / TEXTURE_CELL_M)
        my = (np.mod(pyr + np.float32(math.fmod(fr.cy, period)), period) / TEXTURE_CELL_M)
        tex = cv2.remap(_texture_tile(), mx.astype(np.float32), my.astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        tex *= np.float32(options.texture)
    img = _base(fr, options, g.p_valid, g.p_ceil, pxr, pyr, g.p_dx, g.p_dy, g.p_dz,
                tex).reshape(hp, wp)

    # -- cells an edge can cross ----------------------------------------------------------
    cxr, cyr = fr.xy(g.cq[:, 0], g.cq[:, 1])
    reach = fr.h * (g.rq + g.fq)
    active = g.mixed.copy()
    if fr.walls:
        with np.errstate(invalid="ignore"):
            dy = np.abs(cyr - fr.axis_r)
            active |= (dy + reach > fr.w) & (dy - reach < fr.w)
            if options.clutter:
                # wall cells: shade per sub-pixel only where the per-pixel image has an
                # edge (door frames, posters) within a pixel of the cell
                k3 = np.ones((3, 3), np.uint8)
                edge = cv2.dilate(img, k3) - cv2.erode(img, k3) > 1.0
                edge = edge.reshape(g.ncy, CELL_PX, g.ncx, CELL_PX).any(axis=(1, 3)).ravel()
                active |= edge & (g.has_other | (dy + reach > fr.w))
    feats = _features(site, fr, options, cxr, cyr, reach, emitters)
    for f in feats:
        active |= f.cells if f.edges is None else f.edges
    emitted = np.zeros((hp, wp), np.float32) if split else None
    _shade_inner(g, fr, feats, active, pxr, pyr, img, emitted)
    _shade_active(g, fr, options, feats, active, tex, img, emitted)
    img = np.ascontiguousarray(img[:g.height, :g.width])
    if split:
        return img, np.ascontiguousarray(emitted[:g.height, :g.width])
    return img


def _shade_inner(g: _Grid, fr: _Frame, feats: list[_Feature], active: np.ndarray,
                 pxr: np.ndarray, pyr: np.ndarray, img: np.ndarray,
                 emitted: np.ndarray | None) -> None:
    """Shade per pixel, in place, the cells of features with ``edges`` that no edge
    crosses and no feature needs per sub-pixel (``active``): there every sample of a
    pixel has the same value, or one varying smoothly (a stain)."""
    wp = g.ncx * CELL_PX
    k = np.arange(CELL_PX)
    for f in feats:
        if f.edges is None:
            continue
        idx = np.flatnonzero(f.cells & ~active)
        if not idx.size:
            continue
        flat = (((idx // g.ncx) * CELL_PX)[:, None, None] + k[None, :, None]) * wp \
            + ((idx % g.ncx) * CELL_PX)[:, None, None] + k[None, None, :]
        flat = flat.ravel()
        xr, yr = pxr.ravel()[flat], pyr.ravel()[flat]
        inside = g.p_ceil.ravel()[flat]
        if fr.walls:
            inside &= np.abs(yr - fr.axis_r) < fr.w
        inv_fp = np.repeat((1.0 / (fr.h * g.fq[idx])).astype(np.float32), CELL_PX ** 2)
        old = img.ravel()[flat]
        if f.emitter and emitted is not None:
            new, e_new = f.shade(xr, yr, inv_fp, old, em=emitted.ravel()[flat])
            emitted.ravel()[flat] = np.where(inside, e_new, emitted.ravel()[flat])
        else:
            new = f.shade(xr, yr, inv_fp, old)
        img.ravel()[flat] = np.where(inside, new, old)


def _shade_active(g: _Grid, fr: _Frame, options: SimOptions, feats: list[_Feature],
                  active: np.ndarray, tex: np.ndarray, img: np.ndarray,
                  emitted: np.ndarray | None) -> None:
    """Shade the active cells per sub-pixel and write their pixel means into ``img``
    (and the emitters' share into ``emitted`` when given), in place."""
    idx = np.flatnonzero(active)
    if not idx.size:
        return
    amap = np.full(active.size, -1, dtype=np.int64)
    amap[idx] = np.arange(idx.size)
    xr, yr = fr.xy(g.qx[idx], g.qy[idx])
    ceil = g.ceil[idx]
    val = _base(fr, options, g.valid[idx], ceil, xr, yr, g.dx[idx], g.dy[idx],
                g.dz[idx], tex.ravel()[g.pix[idx]])
    em = np.zeros_like(val) if emitted is not None else None
    inside = ceil
    if fr.walls:
        inside = ceil & (np.abs(yr - fr.axis_r) < fr.w)
    inv_fp = np.where(inside, g.inv_fq[idx] * np.float32(1.0 / fr.h), 0.0
                      ).astype(np.float32)
    for f in feats:
        pos = amap[np.flatnonzero(f.cells & active)]
        m = inside[pos]
        if not np.any(m):
            continue
        old = val[pos]
        if em is not None:
            # the emitters' share: replaced where a feature covers it (emitters are
            # drawn last, so other features only ever cover the ceiling's texture)
            e_old = em[pos]
            if f.emitter:
                new, e_new = f.shade(xr[pos], yr[pos], inv_fp[pos], old, em=e_old)
                em[pos] = np.where(m, e_new, e_old)
            else:
                new = f.shade(xr[pos], yr[pos], inv_fp[pos], old)
        else:
            new = f.shade(xr[pos], yr[pos], inv_fp[pos], old)
        val[pos] = np.where(m, new, old)
    s = g.s
    img4 = img.reshape(g.ncy, CELL_PX, g.ncx, CELL_PX)
    img4[idx // g.ncx, :, idx % g.ncx, :] = val.reshape(idx.size, CELL_PX, s, CELL_PX,
                                                        s).mean(axis=(2, 4))
    if em is not None:
        e4 = emitted.reshape(g.ncy, CELL_PX, g.ncx, CELL_PX)
        e4[idx // g.ncx, :, idx % g.ncx, :] = em.reshape(idx.size, CELL_PX, s, CELL_PX,
                                                         s).mean(axis=(2, 4))


def _base(fr: _Frame, options: SimOptions, valid: np.ndarray, ceil: np.ndarray,
          xr: np.ndarray, yr: np.ndarray, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray,
          tex: np.ndarray) -> np.ndarray:
    """Radiance without ceiling features: ceiling + texture inside the walls, else
    walls/floor; black where the lens is undefined. Any array shape; float32."""
    val = (CEILING_GREY + tex).astype(np.float32)
    other = valid & ~ceil
    if fr.walls:
        other |= ceil & (np.abs(yr - fr.axis_r) >= fr.w)
    if np.any(other):
        val[other] = _wall_shade(fr, dx[other], dy[other], dz[other], options.clutter)
    val[~valid] = 0.0
    return val


def render_frame(rig: Rig, site: Site, x_m: float, y_m: float, yaw_rad: float,
                 options: SimOptions = SimOptions(),
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """The grey frame ``(H, W)`` uint8 the rig sees at vehicle pose ``(x_m, y_m, yaw_rad)``.

    Radiance (see :func:`render_radiance`), Gaussian blur ``options.blur_px``, vignetting
    ``1 - vignetting * (r / r_corner)^2`` about the principal point, gain
    ``options.exposure``, Gaussian noise ``options.noise_sigma`` drawn from ``rng``
    (None: ``np.random.default_rng(0)``), rounded and clipped to 0..255.

    A site lamp row with ``z`` below the ceiling is drawn at that height (by
    :func:`ceilkit.runtime.sim.realism.render_real`, all knobs off).

    Raises ConfigError for a bad pose (not finite) or a ceiling not above the camera.
    """
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise ConfigError(None, "rng", f"expected a numpy Generator, found {type(rng).__name__}")
    if _hanging_rows(site):       # lamps below the ceiling: drawn at their height
        from ceilkit.runtime.sim.realism import Realism, render_real

        _check_pose(x_m, y_m, yaw_rad)
        pose = (float(x_m), float(y_m), float(yaw_rad))
        return render_real(rig, site, lambda t: pose, 0, options, Realism(), rng)
    img = render_radiance(rig, site, x_m, y_m, yaw_rad, options)
    return finish_frame(rig, img, options, rng)


def _hanging_rows(site: Site) -> bool:
    return any(r.z_m is not None and r.z_m < site.ceiling_height_m - 1e-9 for r in site.lamps)


def finish_frame(rig: Rig, radiance: np.ndarray, options: SimOptions = SimOptions(),
                 rng: np.random.Generator | None = None,
                 gain_rows: np.ndarray | None = None) -> np.ndarray:
    """Radiance ``(H, W)`` float32 to the uint8 frame: blur, vignetting, exposure
    (times ``gain_rows`` ``(H,)``, a per-row gain, if given), noise, rounding."""
    img = radiance
    if options.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), options.blur_px, borderType=cv2.BORDER_REPLICATE)
    g = _grid(rig.camera, rig.mount.R_level_cam, options.supersample)
    gain = np.float32(options.exposure) * (1.0 - np.float32(options.vignetting) * g.vig_r2)
    if gain_rows is not None:
        gain = gain * np.asarray(gain_rows, np.float32)[:, None]
    img = img * gain
    if options.noise_sigma > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(options.noise_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- trajectories
@dataclass(frozen=True, eq=False)
class Trajectory:
    """Vehicle poses over time: ``t_ns`` (N,) int64 increasing, ``x_m``, ``y_m``,
    ``yaw_rad`` (N,) float (SPEC §1 vehicle pose in W)."""

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns)
        if t.ndim != 1 or t.size == 0:
            raise ConfigError(None, "trajectory.t_ns", "expected a non-empty 1-D array")
        if not np.issubdtype(t.dtype, np.integer):
            raise ConfigError(None, "trajectory.t_ns", f"expected integers, found {t.dtype}")
        object.__setattr__(self, "t_ns", t.astype(np.int64))
        for name in ("x_m", "y_m", "yaw_rad"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != t.shape:
                raise ConfigError(None, f"trajectory.{name}",
                                  f"expected {t.size} values, found shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ConfigError(None, f"trajectory.{name}", "expected finite numbers")
            object.__setattr__(self, name, a)
        if t.size > 1 and np.any(np.diff(self.t_ns) <= 0):
            k = int(np.argmax(np.diff(self.t_ns) <= 0)) + 1
            raise ConfigError(None, f"trajectory.t_ns[{k}]", "stamps must increase")

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def pose(self, k: int) -> tuple[float, float, float]:
        """``(x_m, y_m, yaw_rad)`` of pose k."""
        return float(self.x_m[k]), float(self.y_m[k]), float(self.yaw_rad[k])

    def pose_at(self, t_ns: float) -> tuple[float, float, float]:
        """``(x_m, y_m, yaw_rad)`` at any time: linear between poses, extended past the
        ends along the first or last step (a single pose: that pose)."""
        t = self.t_ns
        if t.size == 1:
            return self.pose(0)
        k = int(np.clip(np.searchsorted(t, t_ns, side="right") - 1, 0, t.size - 2))
        a = (float(t_ns) - float(t[k])) / float(t[k + 1] - t[k])
        return tuple(float(v[k] + a * (v[k + 1] - v[k]))
                     for v in (self.x_m, self.y_m, self.yaw_rad))


MAX_SIM_FRAMES = 1_000_000
"""The most frames a simulated trajectory holds (its arrays are made whole: 10^6
frames are some 40 MB; more is refused, not a MemoryError)."""


def _stamps(n: int, fps: float) -> np.ndarray:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not \
            1 <= n <= MAX_SIM_FRAMES:
        raise ConfigError(None, "n", f"expected a frame count in [1, {MAX_SIM_FRAMES}] (a "
                          f"simulated drive), found {n!r}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ConfigError(None, "fps", f"expected a frame rate > 0, found {fps!r}")
    return np.rint(np.arange(n) * (1e9 / fps)).astype(np.int64)


def straight_drive(n: int, fps: float = 30.0, speed_mps: float = 0.5, x0_m: float = 0.0,
                   y_m: float = 0.0, yaw_rad: float = 0.0, weave_m: float = 0.0,
                   yaw_wobble_rad: float = 0.0, rng: np.random.Generator | None = None,
                   weave_period_m: float = 6.0, wobble_period_s: float = 2.3,
                   length_m: float | None = None) -> Trajectory:
    """A drive along heading ``yaw_rad`` from ``(x0_m, y_m)`` at ``speed_mps``.

    ``weave_m``: amplitude of a sideways sine (period ``weave_period_m`` of travel),
    the heading following the path's tangent; ``yaw_wobble_rad``: amplitude of an extra
    heading sine (period ``wobble_period_s``) on top, as a vehicle that crabs. ``rng``
    draws the two phases (None: both 0). Frame k is at ``t = k / fps`` s.

    ``length_m``: a drive that would go further than this shuttles instead, between its
    start and ``length_m`` along its heading (the heading kept: it backs up), slowing to
    a stop at each end (``length_m / 2 * (1 - cos(s / (length_m / 2)))`` along the
    heading after ``s`` m of travel), so it stays on a map of that length.
    """
    t_ns = _stamps(n, fps)
    for name, v in (("speed_mps", speed_mps), ("x0_m", x0_m), ("y_m", y_m),
                    ("yaw_rad", yaw_rad), ("weave_m", weave_m),
                    ("yaw_wobble_rad", yaw_wobble_rad)):
        if not math.isfinite(v):
            raise ConfigError(None, name, f"expected a finite number, found {v!r}")
    if weave_period_m <= 0 or wobble_period_s <= 0:
        raise ConfigError(None, "weave_period_m", "periods must be > 0")
    ph1, ph2 = (0.0, 0.0) if rng is None else tuple(rng.uniform(0, 2 * math.pi, 2))
    t = t_ns / 1e9
    s = speed_mps * t
    if length_m is not None and length_m > 0 and s[-1] > length_m:
        s = 0.5 * length_m * (1.0 - np.cos(s / (0.5 * length_m)))
    k = 2 * math.pi / weave_period_m
    lat = weave_m * np.sin(k * s + ph1)
    slope = weave_m * k * np.cos(k * s + ph1)
    c, sn = math.cos(yaw_rad), math.sin(yaw_rad)
    x = x0_m + s * c - lat * sn
    y = y_m + s * sn + lat * c
    yaw = (yaw_rad + np.arctan(slope)
           + yaw_wobble_rad * np.sin(2 * math.pi * t / wobble_period_s + ph2))
    return Trajectory(t_ns, x, y, yaw)


def random_poses(n: int, x_range: tuple[float, float], y_range: tuple[float, float],
                 yaw_range: tuple[float, float], rng: np.random.Generator,
                 fps: float = 30.0) -> Trajectory:
    """n poses drawn uniformly from the ranges (m, m, rad), stamped at ``fps``."""
    t_ns = _stamps(n, fps)
    if not isinstance(rng, np.random.Generator):
        raise ConfigError(None, "rng", "expected a numpy Generator")
    out = []
    for name, r in (("x_range", x_range), ("y_range", y_range), ("yaw_range", yaw_range)):
        try:
            lo, hi = (float(v) for v in r)
        except (TypeError, ValueError):
            raise ConfigError(None, name, f"expected (lo, hi), found {r!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ConfigError(None, name, f"expected finite lo <= hi, found {r!r}")
        out.append(rng.uniform(lo, hi, n))
    return Trajectory(t_ns, out[0], out[1], out[2])


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory in the ``truth.csv`` layout (``t_ns,x,y,yaw_deg``, SPEC §2)."""
    from ceilkit.runtime.io.recording import load_truth

    tr = load_truth(path)
    if tr.t_ns.size == 0:
        raise ConfigError(path, None, "no poses in the file")
    if tr.t_ns.size > 1 and np.any(np.diff(tr.t_ns) <= 0):
        raise ConfigError(path, "t_ns", "two rows share a stamp")
    return Trajectory(tr.t_ns, tr.x_m, tr.y_m, tr.yaw_rad)


# --------------------------------------------------------------------------- source
class SimSource(SourceBase):
    """A frame source rendering ``trajectory`` (one frame per pose, stamped with it).

    Frame k's noise comes from ``np.random.default_rng([seed, k])``, so a frame does
    not depend on which frames were read before it.

    ``pace``: called as ``pace(seconds)`` to wait (``threading.Event.wait``: a stop
    cuts it short) until a frame is due by its stamp on ``clock``, counted from the
    first frame read: the frames come in real time, as a camera's would (never faster;
    a frame that renders late comes late). ``None``: as fast as they render.
    """

    live = False  # stamped from the trajectory, not at grab
    dropped = 0

    def __init__(self, rig: Rig, site: Site, trajectory: Trajectory,
                 options: SimOptions = SimOptions(), seed: int = 0, realism: Any = None,
                 pace: Callable[[float], object] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        from ceilkit.runtime.sim.realism import Realism

        if realism is not None and not isinstance(realism, Realism):
            raise ConfigError(None, "realism", "expected a Realism (or None)")
        self.realism = None if realism is None or not realism.active else realism
        if not isinstance(trajectory, Trajectory):
            raise ConfigError(None, "trajectory", "expected a Trajectory")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(None, "seed", f"expected an integer >= 0, found {seed!r}")
        self.rig, self.site, self.trajectory = rig, site, trajectory
        self.options, self.seed = options, int(seed)
        self._k = 0
        self.pace, self.clock = pace, clock
        self._started: float | None = None

    def __len__(self) -> int:
        return len(self.trajectory)

    def pose(self, k: int) -> tuple[float, float, float]:
        """``(x_m, y_m, yaw_rad)`` of frame k."""
        return self.trajectory.pose(k)

    def render(self, k: int) -> Frame:
        """Frame k (any order)."""
        rng = np.random.default_rng([self.seed, k])
        if self.realism is not None:
            from ceilkit.runtime.sim.realism import render_real

            img = render_real(self.rig, self.site, self.trajectory.pose_at,
                              int(self.trajectory.t_ns[k]), self.options, self.realism, rng)
            return Frame(img, int(self.trajectory.t_ns[k]), k)
        x, y, yaw = self.pose(k)
        img = render_frame(self.rig, self.site, x, y, yaw, self.options, rng)
        return Frame(img, int(self.trajectory.t_ns[k]), k)

    def read(self) -> Frame | None:
        if self._k >= len(self.trajectory):
            return None
        f = self.render(self._k)
        if self.pace is not None:
            if self._started is None:
                self._started = self.clock()
            due = self._started + (f.t_ns - int(self.trajectory.t_ns[0])) / 1e9
            wait = due - self.clock()
            if wait > 0:
                self.pace(wait)
        self._k += 1
        return f


__all__ = ["SimOptions", "Emitters", "finish_frame", "render_frame", "render_radiance",
           "Trajectory", "straight_drive", "random_poses", "load_trajectory", "SimSource",
           "wall_half_width"]
