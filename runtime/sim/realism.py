"""Real ceilings and real cameras on top of the ray-cast renderer: the realism knobs.

:class:`Realism` is a frozen set of knobs, every one off by default (a ``Realism()``
renders exactly what :func:`~ceilkit.runtime.sim.render.render_frame` does, bit for
bit, because :class:`~ceilkit.runtime.sim.render.SimSource` then never calls this
module). Three groups:

* **scene** (objects fixed to W, laid out once from the site and ``layout_seed``,
  :mod:`ceilkit.runtime.sim.scene`): ``pipes``, ``trays``, ``beams_m``,
  ``pendants_m``, ``fixtures_m``, ``grilles_m``, ``signs_m``, ``windows_m``,
  ``stains``, ``people``; a site lamp row with ``z`` below the ceiling is always drawn
  at its height;
* **light**: ``lamp_spread`` (unequal lamps), ``lamps_off`` (failed ones),
  ``flicker`` (modulation at twice ``mains_hz``, integrated over each row's exposure:
  banding with a rolling shutter), ``gloss`` (lamps mirrored in glossy walls, glare
  around what saturates);
* **camera**: ``motion_blur_ms`` (exposure time: the frame integrates the vehicle's
  motion over it), ``rolling_shutter_ms`` (readout from the top row to the bottom: a
  row sees the pose at its own time; the frame's stamp is the middle of the centre
  row's exposure, so the centre row sees the stamp's pose), ``auto_exposure`` (gain swings of that
  relative amplitude, period ``ae_period_s``), ``jpeg`` (quality: encoded and decoded
  as MJPEG does).

Motion blur and the rolling shutter render ``time_samples`` sub-frames (0: chosen
from the time span) along the trajectory and give each row the mean of the
sub-frames inside its exposure window (linear in time between sub-frames): one
sub-frame per 5 ms of span plus one, 2..8, unless ``time_samples`` says.

Presets are named sets of knobs: ``presets.yaml`` beside a site (the packaged
examples have one, with ``realistic``); :func:`load_preset` reads them strictly.

Example::

    real = Realism(pipes=2, motion_blur_ms=8.0, jpeg=80)
    with SimSource(rig, site, straight_drive(100), realism=real) as src: ...
    real = load_preset("configs/corridor/site.yaml", "realistic")
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import Node, load_yaml
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.shutter import row_times_s
from ceilkit.runtime.sim import render as R
from ceilkit.runtime.sim import scene as S

F32 = np.float32
PRESETS_FILE = "presets.yaml"


@dataclass(frozen=True)
class Realism:
    """The realism knobs (all off by default; see the module docstring).

    Attributes:
        pipes: pipes and ducts along x below the ceiling (count, cylinders).
        trays: cable trays along x (count, boxes).
        beams_m: spacing of beams across the corridor, m (0: none).
        pendants_m: spacing of unmapped pendant lamps hanging 0.6 m down, m.
        fixtures_m: spacing of sprinkler heads (smoke detectors every third), m.
        grilles_m: spacing of vent grilles (slatted), m.
        signs_m: spacing of exit signs (luminous, hanging), m.
        windows_m: spacing of skylights (bright ceiling panes), m.
        stains: stains per m² of ceiling.
        people: people walking along x per 12 m.
        lamp_spread: relative standard deviation of lamp and light brightness.
        lamps_off: share of lamps and lights that are off, in [0, 1].
        flicker: modulation depth of the lamps' light at twice the mains, in [0, 1].
        mains_hz: mains frequency, Hz.
        gloss: reflectance of glossy walls (lamps mirrored in them) and glare, [0, 1].
        motion_blur_ms: exposure time, ms (0: instantaneous).
        rolling_shutter_ms: readout time, top row to bottom row, ms (0: global); row
            ``v`` sees the pose at ``(v / (H - 1) - 1/2) rolling_shutter_ms`` after the
            stamp (:func:`~ceilkit.runtime.geometry.shutter.row_times_s`), the estimators'
            ``readout_ms`` option has the same meaning.
        auto_exposure: relative amplitude of auto-exposure gain swings, [0, 1).
        ae_period_s: period of the swings, s.
        jpeg: JPEG quality 1..100 (0: none).
        time_samples: sub-frames for blur and rolling shutter (0: automatic).
        layout_seed: seed of the scene's layout and the lamps' gains.
    """

    pipes: int = 0
    trays: int = 0
    beams_m: float = 0.0
    pendants_m: float = 0.0
    fixtures_m: float = 0.0
    grilles_m: float = 0.0
    signs_m: float = 0.0
    windows_m: float = 0.0
    stains: float = 0.0
    people: int = 0
    lamp_spread: float = 0.0
    lamps_off: float = 0.0
    flicker: float = 0.0
    mains_hz: float = 50.0
    gloss: float = 0.0
    motion_blur_ms: float = 0.0
    rolling_shutter_ms: float = 0.0
    auto_exposure: float = 0.0
    ae_period_s: float = 4.0
    jpeg: int = 0
    time_samples: int = 0
    layout_seed: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            want_int = f.type in ("int", int)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(float(v)) or (want_int and float(v) != int(v)):
                raise ConfigError(None, f"realism.{f.name}",
                                  f"expected {'an integer' if want_int else 'a number'}, "
                                  f"found {v!r}")
            if want_int:
                object.__setattr__(self, f.name, int(v))
            if v < 0:
                raise ConfigError(None, f"realism.{f.name}", f"expected >= 0, found {v!r}")
        for name, hi in (("lamps_off", 1.0), ("flicker", 1.0), ("gloss", 1.0),
                         ("auto_exposure", 0.99)):
            if getattr(self, name) > hi:
                raise ConfigError(None, f"realism.{name}", f"expected a number in "
                                  f"[0, {hi:g}], found {getattr(self, name)!r}")
        if self.jpeg > 100:
            raise ConfigError(None, "realism.jpeg", f"expected 0..100, found {self.jpeg}")
        if self.mains_hz <= 0 or self.ae_period_s <= 0:
            raise ConfigError(None, "realism.mains_hz", "frequencies and periods must be > 0")
        if self.time_samples == 1 or self.time_samples > 32:
            raise ConfigError(None, "realism.time_samples",
                              f"expected 0 (automatic) or 2..32, found {self.time_samples}")

    KNOBS = ("pipes", "trays", "beams_m", "pendants_m", "fixtures_m", "grilles_m", "signs_m",
             "windows_m", "stains", "people", "lamp_spread", "lamps_off", "flicker", "gloss",
             "motion_blur_ms", "rolling_shutter_ms", "auto_exposure", "jpeg")
    """The fields that turn something on (the others only parametrise them)."""

    @property
    def active(self) -> bool:
        """Any knob on."""
        return any(getattr(self, k) for k in self.KNOBS)

    @property
    def on(self) -> tuple[str, ...]:
        """The knobs that are on."""
        return tuple(k for k in self.KNOBS if getattr(self, k))

    def replace(self, **changes: Any) -> Realism:
        """A copy with some fields changed (validated again)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(changes)
        return Realism(**d)

    def only(self, knob: str) -> Realism:
        """This setting with every knob but ``knob`` off (parameters kept)."""
        if knob not in self.KNOBS:
            raise ConfigError(None, "realism", f"unknown knob {knob!r}")
        return Realism(**{f.name: getattr(self, f.name) for f in fields(self)
                          if f.name == knob or f.name not in self.KNOBS})

    def describe(self) -> str:
        """``k=v`` of every field that differs from the default."""
        d = Realism()
        return ", ".join(f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                         if getattr(self, f.name) != getattr(d, f.name)) or "off"


_FIELDS = {f.name: f for f in fields(Realism)}


def parse_knobs(pairs: list[str] | tuple[str, ...], base: Realism = Realism(),
                key: str = "sim-fault") -> Realism:
    """``["motion_blur_ms=8", "jpeg=70"]`` on top of ``base``. Raises ConfigError
    (keyed ``key``) on a malformed pair, an unknown knob or a bad value."""
    changes: dict[str, Any] = {}
    for pair in pairs:
        name, eq, text = (p.strip() for p in pair.partition("="))
        if not eq or name not in _FIELDS:
            raise ConfigError(None, key, f"expected KNOB=VALUE with a knob of "
                              f"{', '.join(_FIELDS)}, found {pair!r}")
        try:
            v = float(text)
        except ValueError:
            raise ConfigError(None, key, f"{name}: expected a number, found {text!r}") from None
        changes[name] = int(v) if _FIELDS[name].type in ("int", int) and v == int(v) else v
    try:
        return base.replace(**changes)
    except ConfigError as exc:
        knob = (exc.key or "").partition(".")[2]
        raise ConfigError(None, key, f"{knob}: {exc.detail}" if knob else exc.detail) from None


def resolve(site_file: str | Path | None, preset: str | None = None,
            faults: list[str] | tuple[str, ...] = ()) -> Realism | None:
    """A preset (from the ``presets.yaml`` beside ``site_file``) with ``KNOB=VALUE``
    faults on top; None when neither is given."""
    if not preset and not faults:
        return None
    base = Realism()
    if preset:
        if site_file is None:
            raise ConfigError(None, "sim-preset", "a preset needs a site file beside it")
        base = load_preset(site_file, preset)
    return parse_knobs(list(faults), base)


def presets_path(site_file: str | Path) -> Path:
    """Where a site's presets live: ``presets.yaml`` beside its ``site.yaml``."""
    return Path(site_file).parent / PRESETS_FILE


def load_presets(path: str | Path) -> dict[str, Realism]:
    """Every preset of a ``presets.yaml`` (a mapping of names to knob mappings).
    Unknown knobs and bad values are ConfigErrors naming the file and the key."""
    root = load_yaml(path)
    if not isinstance(root.value, dict) or not root.value:
        raise root.expected("a mapping of preset names to knobs")
    out = {}
    for name in root.value:
        node = root.get(name).mapping(tuple(_FIELDS))
        out[str(name)] = _from_node(node)
    return out


def _from_node(node: Node) -> Realism:
    changes = {}
    for name in node.value:
        f = _FIELDS[name]
        child = node.get(name)
        changes[name] = (child.integer(0, 10 ** 6) if f.type in ("int", int)
                         else child.number(lo=0.0))
    try:
        return Realism(**changes)
    except ConfigError as exc:
        key = exc.key.partition(".")[2] if exc.key else None
        raise (node.get(key).error(exc.detail) if key and key in node.value
               else node.error(exc.detail)) from None


def load_preset(site_file: str | Path, name: str) -> Realism:
    """Preset ``name`` from the ``presets.yaml`` beside ``site_file``. Raises
    ConfigError when there is no such file or preset."""
    path = presets_path(site_file)
    if not path.exists():
        raise ConfigError(path, None, f"no presets file (preset {name!r} asked for)")
    presets = load_presets(path)
    if name not in presets:
        raise ConfigError(path, name, f"no such preset (choose from {', '.join(presets)})")
    return presets[name]


# --------------------------------------------------------------------------- the layout
@dataclass(frozen=True, eq=False)
class Layout:
    """The objects of a site for a realism setting, far to near (drawing order), the
    lamps' and lights' gains, and stains ``(n, 4)``: x, y, radius, depth."""

    objects: tuple[Any, ...]
    emitters: R.Emitters | None
    stains: np.ndarray


_LAYOUTS: OrderedDict[tuple, tuple[Site, Layout]] = OrderedDict()


def _extent(site: Site, options: R.SimOptions) -> tuple[float, float, float, float]:
    """x range and (axis, half width) of the region the scene is laid out in."""
    xs: list[float] = []
    for row in site.lamps:
        c = row.centres()
        xs += [float(c[0, 0]), float(c[-1, 0])]
    if site.has_lights:
        xs += [float(site.lights_m[:, 0].min()), float(site.lights_m[:, 0].max())]
    for blk in site.blocks:
        xs += [float(blk.corners_m[:, 0].min()), float(blk.corners_m[:, 0].max())]
    x0, x1 = (min(xs) - 3.0, max(xs) + 3.0) if xs else (-10.0, 30.0)
    w = R.wall_half_width(site, options)
    if w is not None and site.corridor is not None:
        return x0, x1, site.corridor.axis_y_m, w
    if site.has_lights:
        y0, y1 = float(site.lights_m[:, 1].min()), float(site.lights_m[:, 1].max())
        return x0, x1, 0.5 * (y0 + y1), 0.5 * (y1 - y0) + 1.0
    return x0, x1, 0.0, 3.0


def layout(site: Site, options: R.SimOptions, real: Realism) -> Layout:
    """The scene for ``site`` and ``real`` (cached; seeded by ``real.layout_seed``)."""
    key = (id(site), real, options.wall_half_width_m)
    got = _LAYOUTS.get(key)
    if got is not None and got[0] is site:      # the site itself kept: ids are not reused
        return got[1]
    lay = _build_layout(site, options, real)
    _LAYOUTS[key] = (site, lay)
    while len(_LAYOUTS) > 8:
        _LAYOUTS.popitem(last=False)
    return lay


def _lateral(rng: np.random.Generator, axis: float, w: float, n: int, margin: float,
             avoid: float) -> list[float]:
    """n lateral positions within the walls, away from the middle band ``avoid``."""
    out = []
    for _ in range(n):
        side = rng.choice([-1.0, 1.0])
        out.append(axis + side * rng.uniform(min(avoid, w - margin), w - margin))
    return out


def _build_layout(site: Site, options: R.SimOptions, real: Realism) -> Layout:
    rng = np.random.default_rng([20261202, real.layout_seed])
    H = site.ceiling_height_m
    x0, x1, axis, w = _extent(site, options)
    band = 0.0
    for row in site.lamps:
        band = max(band, abs(row.y_m - axis) + row.width_m / 2 + 0.1)
    objs: list[tuple[float, Any]] = []          # (z for ordering, object)
    # ceiling-plane decorations first (farthest)
    if real.windows_m:
        objs.append((H, S.RectsZ(H - 1e-3, x0 + rng.uniform(0, real.windows_m),
                                 real.windows_m, (axis + (band + 0.45 if band else 1.5),),
                                 0.6, 0.35, 255.0)))
    if real.grilles_m:
        objs.append((H, S.RectsZ(H - 2e-3, x0 + rng.uniform(0, real.grilles_m),
                                 real.grilles_m, (axis - (band + 0.35 if band else 1.0),),
                                 0.3, 0.3, 175.0, slats=0.025)))
    if real.fixtures_m:
        ys = tuple(_lateral(rng, axis, w, 2, 0.25, band + 0.05))
        objs.append((H, S.DiscsZ(H - 0.03, x0 + rng.uniform(0, real.fixtures_m),
                                 real.fixtures_m, ys, 0.025, 70.0, ring_grey=190.0)))
        objs.append((H, S.DiscsZ(H - 0.05, x0 + rng.uniform(0, 3 * real.fixtures_m),
                                 3 * real.fixtures_m, (axis + 0.5 * (band or 1.0),), 0.065,
                                 215.0, ring_grey=185.0)))
    for row in site.lamps:                     # the site's hanging lamps, at their height
        if row.z_m is not None and row.z_m < H - 1e-9:
            objs.append((row.z_m, S.RectsZ(row.z_m, row.x_m, row.pitch_m if row.count > 1
                                           else 0.0, (row.y_m,), row.length_m / 2,
                                           row.width_m / 2, R.LAMP_GREY, count=row.count)))
    if real.beams_m:
        objs.append((H - 0.1, S.BeamsY(x0 + rng.uniform(0, real.beams_m), real.beams_m, 0.12,
                                       H - 0.35, H, axis - w, axis + w)))
    for _ in range(real.trays):
        y = _lateral(rng, axis, w, 1, 0.35, band + 0.2)[0]
        zb = H - rng.uniform(0.3, 0.5)
        objs.append((zb, S.BoxX(y, 0.15, zb, zb + 0.08)))
    for i in range(real.pipes):
        r = rng.uniform(0.1, 0.2) if i % 3 == 2 else rng.uniform(0.025, 0.06)   # a duct
        y = _lateral(rng, axis, w, 1, r + 0.1, band + r)[0]
        z = H - r - rng.uniform(0.05, 0.35)
        objs.append((z, S.PipeX(y, z, r, grey=rng.uniform(90, 140))))
    if real.signs_m:
        objs.append((H - 0.3, S.SignsX(x0 + rng.uniform(0, real.signs_m), real.signs_m,
                                       axis + 0.4 * w, 0.17, H - 0.42, H - 0.22)))
    if real.pendants_m:
        y = _lateral(rng, axis, w, 1, 0.4, band + 0.2)[0]
        objs.append((H - 0.6, S.RectsZ(H - 0.6, x0 + rng.uniform(0, real.pendants_m),
                                       real.pendants_m, (y,), 0.3, 0.08, 245.0)))
    if real.people:
        n = real.people
        ys = tuple(float(v) for v in rng.uniform(axis - w + 0.3, axis + w - 0.3, n))
        x0s = tuple(float(v) for v in rng.uniform(0, 12.0, n))
        sp = tuple(float(v) for v in rng.choice([-1, 1], n) * rng.uniform(0.8, 1.5, n))
        objs.append((0.0, S.People(ys, x0s, sp)))
    objs.sort(key=lambda zo: -zo[0])
    stains = np.zeros((0, 4))
    if real.stains:
        area = (x1 - x0) * 2 * w
        n = int(rng.poisson(real.stains * area))
        stains = np.stack([rng.uniform(x0, x1, n), rng.uniform(axis - w, axis + w, n),
                           rng.uniform(0.05, 0.3, n), rng.uniform(0.1, 0.35, n)], axis=1)
    return Layout(tuple(o for _, o in objs), _emitters(site, real, rng), stains)


def _emitters(site: Site, real: Realism, rng: np.random.Generator) -> R.Emitters | None:
    if not (real.lamp_spread or real.lamps_off):
        return None

    def gains(n: int) -> np.ndarray:
        g = np.clip(1.0 + real.lamp_spread * rng.standard_normal(n), 0.3, 1.3)
        return np.where(rng.uniform(size=n) < real.lamps_off, 0.0, g).astype(F32)

    lamp = tuple(gains(row.count) for row in site.lamps)
    light = gains(len(site.lights_m)) if site.has_lights else None
    return R.Emitters(lamp, light)


# --------------------------------------------------------------------------- per pixel
_PIX: dict[int, tuple[Any, np.ndarray, np.ndarray, np.ndarray]] = {}


def _pixel_rays(g: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a ray grid: which pixels the lens defines (flat bool), their level-frame
    unit rays ``(N, 3)`` float32 and angular footprints ``(N,)`` (the larger of the
    two steps to the next pixel), rad. Cached for the last grid."""
    got = _PIX.get(id(g))
    if got is not None and got[0] is g:
        return got[1], got[2], got[3]
    d = np.stack([g.p_dx, g.p_dy, g.p_dz], axis=-1).astype(np.float64)
    gu = np.linalg.norm(np.gradient(d, axis=1), axis=-1)
    gv = np.linalg.norm(np.gradient(d, axis=0), axis=-1)
    a = np.nan_to_num(np.fmax(gu, gv), nan=0.0)
    a = np.where(a > 0, a, np.median(a[a > 0]) if np.any(a > 0) else 1e-3)
    ok = g.p_valid.ravel()
    lev = np.ascontiguousarray(d.reshape(-1, 3)[ok], dtype=F32)
    ang = np.ascontiguousarray(a.ravel()[ok], dtype=F32)
    _PIX.clear()
    _PIX[id(g)] = (g, ok, lev, ang)
    return ok, lev, ang


def _world_rays(rig: Rig, pose: tuple[float, float, float], options: R.SimOptions,
                t_s: float) -> tuple[S.Rays, Any, np.ndarray]:
    g = R._grid(rig.camera, rig.mount.R_level_cam, options.supersample)
    ok, lev, ang = _pixel_rays(g)
    x, y, yaw = pose
    a = yaw + rig.mount.pan_rad
    c, s = math.cos(a), math.sin(a)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], F32)
    o = np.asarray(rig.mount.camera_position(x, y, yaw), float)
    return S.Rays(o, lev @ Rz.T, ang, t_s), g, ok


def _overlay(img: np.ndarray, rig: Rig, site: Site, pose: tuple[float, float, float],
             t_s: float, options: R.SimOptions, real: Realism, lay: Layout) -> np.ndarray:
    """Draw the layout's objects, stains and glossy-wall reflections over ``img``."""
    return _overlay_split(img, None, rig, site, pose, t_s, options, real, lay)[0]


def _overlay_split(img: np.ndarray, em: np.ndarray | None, rig: Rig, site: Site,
                   pose: tuple[float, float, float], t_s: float, options: R.SimOptions,
                   real: Realism, lay: Layout) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`_overlay`, and the lamps' emission ``em`` (the part that flickers) hidden
    where an object below the ceiling covers it (a person walking under the camera
    hides the lamps' flicker too, not only their light)."""
    if not (lay.objects or lay.stains.size or real.gloss):
        return img, em
    rays, g, ok = _world_rays(rig, pose, options, t_s)
    hp, wp = g.ncy * R.CELL_PX, g.ncx * R.CELL_PX
    H, W = img.shape
    full = np.zeros((hp, wp), F32)
    full[:H, :W] = img
    v = full.ravel()[ok]
    if lay.stains.size:
        v = _stain(v, rays, site, lay.stains)
    if real.gloss:
        v = _wall_gloss(v, rays, site, options, real.gloss)
    keep = np.ones_like(v) if em is not None and lay.objects else None
    for obj in lay.objects:
        cov, val = obj.draw(rays)
        v = v + cov * (val - v)
        if keep is not None:
            keep = keep * (1.0 - cov)
    out = full.ravel().copy()
    out[ok] = v
    img = np.ascontiguousarray(out.reshape(hp, wp)[:H, :W])
    if keep is None:
        return img, em
    clear = np.ones((hp, wp), F32).ravel()
    clear[ok] = keep
    return img, (em * clear.reshape(hp, wp)[:H, :W]).astype(F32)


def _stain(v: np.ndarray, rays: S.Rays, site: Site, stains: np.ndarray) -> np.ndarray:
    """Darken the ceiling under soft stains (a smooth bump of each one's depth)."""
    x, y, t, _ = S._plane_hit(rays, site.ceiling_height_m)
    near = np.hypot(stains[:, 0] - rays.o[0], stains[:, 1] - rays.o[1]) < 15.0
    f = np.ones_like(v)
    for sx, sy, r, depth in stains[near]:
        d2 = ((x - F32(sx)) ** 2 + (y - F32(sy)) ** 2) / F32(r * r)
        f *= 1.0 - F32(depth) * np.exp(-d2 * F32(2.0))
    return np.where(np.isfinite(t), v * f, v).astype(F32)


def _wall_gloss(v: np.ndarray, rays: S.Rays, site: Site, options: R.SimOptions,
                gloss: float) -> np.ndarray:
    """Lamps (and lights) mirrored in glossy corridor walls: a ray that meets a wall
    below the ceiling is reflected and looked up on the ceiling."""
    w = R.wall_half_width(site, options)
    if w is None or site.corridor is None or not site.lamps:
        return v
    o, d = rays.o, rays.d
    axis = site.corridor.axis_y_m
    side = np.where(d[:, 1] >= 0, 1.0, -1.0).astype(F32)
    with np.errstate(divide="ignore", invalid="ignore"):
        tw = (F32(axis) + side * F32(w) - F32(o[1])) / d[:, 1]
        tc = (F32(site.ceiling_height_m) - F32(o[2])) / d[:, 2]
    hit = np.isfinite(tw) & (tw > 0) & np.isfinite(tc) & (tc > tw) & (d[:, 2] > 0)
    tcc = np.where(hit, tc, 0.0)
    xc = F32(o[0]) + tcc * d[:, 0]
    yc = 2 * (F32(axis) + side * F32(w)) - (F32(o[1]) + tcc * d[:, 1])
    fp = tcc * rays.ang / np.maximum(d[:, 2], F32(0.05))
    cov = np.zeros_like(v)
    for row in site.lamps:
        dx = xc - F32(row.x_m)
        if row.count > 1:
            dx = dx - np.clip(np.rint(dx / F32(row.pitch_m)), 0, row.count - 1) * F32(row.pitch_m)
        sd = np.minimum(F32(row.length_m / 2) - np.abs(dx),
                        F32(row.width_m / 2) - np.abs(yc - F32(row.y_m)))
        cov = np.maximum(cov, S.ramp(sd, fp))
    cov = np.where(hit, cov, 0.0)
    return (v + F32(gloss) * cov * (F32(R.LAMP_GREY) - v)).astype(F32)


# --------------------------------------------------------------------------- in time
def _time_offsets(real: Realism) -> np.ndarray:
    """Sub-frame times (s) relative to the frame's stamp, from the top row's exposure
    start to the bottom row's exposure end: the stamp is the middle of the centre row's
    exposure (docs/conventions.md), so they run from ``-span/2`` to ``+span/2``."""
    span = (real.motion_blur_ms + real.rolling_shutter_ms) / 1e3
    if span <= 0:
        return np.zeros(1)
    k = real.time_samples or int(np.clip(math.ceil(span / 5e-3) + 1, 2, 8))
    return np.linspace(-0.5 * span, 0.5 * span, k)


def _row_weights(real: Realism, taus: np.ndarray, rows: int) -> np.ndarray:
    """(rows, K): each row's mean over its exposure window of the sub-frames, linear
    in time between them."""
    k = taus.size
    if k == 1:
        return np.ones((rows, 1))
    ro, te = real.rolling_shutter_ms / 1e3, real.motion_blur_ms / 1e3
    # each row's exposure start after the first sub-frame (geometry.shutter's row times)
    start = row_times_s(np.arange(rows), rows, ro) - 0.5 * te - taus[0]
    m = 16 if te > 0 else 1
    pts = start[:, None] + (np.arange(m) + 0.5) / m * te          # (rows, m)
    pos = np.clip(pts / (taus[-1] - taus[0]) * (k - 1), 0, k - 1)
    lo = np.minimum(np.floor(pos).astype(int), k - 2)
    fr = pos - lo
    w = np.zeros((rows, k))
    r = np.repeat(np.arange(rows)[:, None], m, axis=1)
    np.add.at(w, (r, lo), (1 - fr) / m)
    np.add.at(w, (r, lo + 1), fr / m)
    return w


def _flicker_rows(real: Realism, t0_s: float, rows: int) -> np.ndarray:
    """(rows,) relative brightness of the lamps seen by each row: 1 + m * the mean of
    cos(2 pi 2 f t) over the row's exposure window (2 ms when exposure is 0)."""
    om = 2 * math.pi * 2 * real.mains_hz
    te = real.motion_blur_ms / 1e3 or 2e-3
    ro = real.rolling_shutter_ms / 1e3
    # each row's exposure start; the centre row's exposure is centred on the stamp
    a = t0_s + row_times_s(np.arange(rows), rows, ro) - 0.5 * te
    mean = (np.sin(om * (a + te)) - np.sin(om * a)) / (om * te)
    return 1.0 + real.flicker * mean


def render_real(rig: Rig, site: Site, pose_at: Callable[[float], tuple[float, float, float]],
                t_ns: int, options: R.SimOptions = R.SimOptions(),
                real: Realism = Realism(), rng: np.random.Generator | None = None
                ) -> np.ndarray:
    """The uint8 frame at stamp ``t_ns`` with the realism knobs, ``pose_at(t_ns)``
    giving the vehicle pose at any time (:meth:`Trajectory.pose_at`).

    Order: sub-frames along the trajectory (motion blur, rolling shutter), each the
    ray-cast radiance (lamp gains) with the scene drawn over it; rows combined; lamp
    flicker per row; glare; then blur, vignetting, exposure (auto-exposure swing),
    noise (:func:`~ceilkit.runtime.sim.render.finish_frame`); JPEG last.
    """
    lay = layout(site, options, real)
    taus = _time_offsets(real)
    H = rig.camera.height
    t0 = t_ns / 1e9
    split = real.flicker > 0
    acc = emit = None
    wts = _row_weights(real, taus, H)
    for j, tau in enumerate(taus):
        pose = pose_at(t_ns + tau * 1e9)
        out = R.render_radiance(rig, site, *pose, options, emitters=lay.emitters,
                                split=split)
        img, em = out if split else (out, None)
        img, em = _overlay_split(img, em, rig, site, pose, t0 + tau, options, real, lay)
        wj = wts[:, j:j + 1].astype(F32)
        acc = img * wj if acc is None else acc + img * wj
        if em is not None:
            emit = em * wj if emit is None else emit + em * wj
    if emit is not None:
        acc = acc + emit * (_flicker_rows(real, t0, H).astype(F32)[:, None] - 1.0)
    if real.gloss:
        glare = cv2.GaussianBlur(np.clip(acc - 235.0, 0, None), (0, 0), 12.0)
        acc = acc + F32(12.0 * real.gloss) * glare
    opts = options
    if real.auto_exposure:
        ph = 2 * math.pi * t0 / real.ae_period_s
        swing = math.sin(ph) + 0.35 * math.sin(3.1 * ph + 1.0)
        opts = options.replace(exposure=options.exposure * (1.0 + real.auto_exposure * swing
                                                            / 1.35))
    frame = R.finish_frame(rig, acc.astype(F32), opts, rng)
    if real.jpeg:
        ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(real.jpeg)])
        frame = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return frame


__all__ = ["Realism", "Layout", "layout", "parse_knobs", "resolve", "load_preset", "load_presets",
           "presets_path", "render_real", "PRESETS_FILE"]
