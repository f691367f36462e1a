"""What an ordinary drop-tile ceiling holds: an irregular scatter of items, as data.

A building's ceiling is a grid of tiles (SPEC §2 ``corridor.lines_along`` and
``lines_across`` give its seams) with what the building needs scattered over it:
light panels in some tiles, vent grilles, access hatches, patched tiles, stains,
sprinkler heads, smoke detectors and cable runs. None of it is in ``site.yaml`` (SPEC
defines no key for it): it is the simulator's *scene*, a :class:`Scatter` of
:class:`ScatterItem` in W, read from a ``scene.yaml``
(:mod:`ceilkit.runtime.sim.scatter_file`) and rendered by
:mod:`ceilkit.runtime.sim.render` when ``SimOptions.scatter`` holds it. Every item
is its own truth (kind, centre, size, yaw), so a map surveyed from frames can be scored
against it.

:func:`generate` lays a scatter out on a site's tile grid from a preset
(:data:`PRESETS`: ``office``, ``sparse``) and a seed: the same arguments give the same
items, to 0.1 mm (every value is rounded as the scene file writes it, so a scene
written and read back renders the same frames).

Kinds and sizes (``length`` along ``yaw`` from +x, ``width`` across):

============  ====================================================================
``panel``     a light panel filling one tile or two (lit face, metal frame); an
              emitter (what the realism layer's flicker modulates)
``vent``      a grille filling a tile: a light frame and dark slats along ``yaw``
``hatch``     an access hatch filling a tile: a darker frame round a plain face
``patch``     a replaced tile, ``grey`` levels lighter (> 0) or darker than the rest
``stain``     a soft blotch, an ellipse ``length x width``, ``grey`` levels deep
``sprinkler`` a disc of ``length`` diameter (about 5 cm): chrome ring, dark centre
``detector``  a smoke detector, a white disc (about 12 cm) with a groove and a dot
``cable``     a thin dark line along ``points`` (a polyline in W), ``width`` wide
============  ====================================================================

Example::

    site = Site.load("configs/office/site.yaml")
    scatter = generate("office", site, seed=1, x_range_m=(-3.0, 33.0))
    image = render_frame(rig, site, 2.0, 0.3, 0.1, SimOptions(scatter=scatter))
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError

KINDS = ("panel", "vent", "hatch", "patch", "stain", "sprinkler", "detector", "cable")
TILE_KINDS = ("panel", "vent", "hatch", "patch")   # items that fill a tile of the grid
DISC_KINDS = ("sprinkler", "detector")

DEFAULT_SIZE_M = {"panel": (0.6, 0.6), "vent": (0.6, 0.6), "hatch": (0.6, 0.6),
                  "patch": (0.6, 0.6), "stain": (0.2, 0.12), "sprinkler": (0.05, 0.05),
                  "detector": (0.12, 0.12), "cable": (0.0, 0.008)}
"""``(length, width)`` of a kind when a scene file leaves them out (a cable's length
comes from its points)."""

DEFAULT_GREY = {"patch": 8.0, "stain": 20.0}
"""A patch's grey offset and a stain's depth when a scene file leaves ``grey`` out."""

TILE_INSET_M = 0.008
"""A tile-filling item is this much smaller than its tile on every side, so the seam
(T-bar) round it stays visible."""

ROUND_M = 1e-4          # positions and sizes are kept to 0.1 mm
ROUND_DEG = 1e-2
ROUND_GREY = 0.1


def _r(v: float, step: float) -> float:
    return float(round(round(v / step) * step, 6))


@dataclass(frozen=True)
class ScatterItem:
    """One item on the ceiling plane ``z = ceiling_height`` (SPEC §1 W).

    Attributes:
        kind: one of :data:`KINDS`.
        x_m, y_m: its centre in W (a cable: the middle of its points' bounding box).
        length_m, width_m: its size along ``yaw_deg`` and across, m (a disc: the
            diameter twice; a cable: its length along the points, and its line width).
        yaw_deg: direction of its length from +x of W, degrees counter-clockwise.
        grey: a patch's grey offset (grey levels, + lighter) or a stain's depth (> 0);
            0 for the other kinds.
        points_m: a cable's polyline in W, ``((x, y), ...)``, at least two points.
    """

    kind: str
    x_m: float
    y_m: float
    length_m: float
    width_m: float
    yaw_deg: float = 0.0
    grey: float = 0.0
    points_m: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(None, "item.kind",
                              f"expected one of {', '.join(KINDS)}, found {self.kind!r}")
        for name in ("x_m", "y_m", "length_m", "width_m", "yaw_deg", "grey"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(None, f"item.{name}", f"expected a finite number, found {v!r}")
        if self.width_m <= 0 or (self.kind != "cable" and self.length_m <= 0):
            raise ConfigError(None, "item.size", f"{self.kind}: expected sizes > 0 m, found "
                              f"{self.length_m:g} x {self.width_m:g}")
        if (self.kind == "cable") != bool(self.points_m) or \
                (self.kind == "cable" and len(self.points_m) < 2):
            raise ConfigError(None, "item.points",
                              "a cable needs at least two points, other kinds none")

    @property
    def radius_m(self) -> float:
        """Radius of a circle about ``(x_m, y_m)`` holding the whole item."""
        if self.kind == "cable":
            p = np.asarray(self.points_m, float)
            return float(np.max(np.hypot(p[:, 0] - self.x_m, p[:, 1] - self.y_m))
                         + 0.5 * self.width_m)
        if self.kind in DISC_KINDS:
            return 0.5 * self.length_m
        return 0.5 * math.hypot(self.length_m, self.width_m)


def cable(points_m, width_m: float) -> ScatterItem:
    """A cable item along ``points_m`` (``(n >= 2, 2)``, W), its centre and length
    derived from the points."""
    p = np.asarray(points_m, float)
    if p.ndim != 2 or p.shape[0] < 2 or p.shape[1] != 2 or not np.all(np.isfinite(p)):
        raise ConfigError(None, "item.points", "expected at least two finite [x, y] points")
    ctr = 0.5 * (p.min(axis=0) + p.max(axis=0))
    length = float(np.sum(np.hypot(*np.diff(p, axis=0).T)))
    return ScatterItem("cable", _r(ctr[0], ROUND_M), _r(ctr[1], ROUND_M),
                       _r(length, ROUND_M), float(width_m),
                       points_m=tuple((float(x), float(y)) for x, y in p))


@dataclass(frozen=True, eq=False)
class Scatter:
    """The items on a simulated ceiling, in drawing order, and where they came from.

    ``origin``: how they were made (``office preset, seed 1``; a scene file's path);
    shown in recordings' headers. ``centres_m`` ``(n, 2)`` and ``radii_m`` ``(n,)``
    (the circle holding each item) are for culling.
    """

    items: tuple[ScatterItem, ...]
    origin: str = ""
    centres_m: np.ndarray = field(init=False, repr=False)
    radii_m: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        items = tuple(self.items)
        if not all(isinstance(it, ScatterItem) for it in items):
            raise ConfigError(None, "scatter.items", "expected ScatterItem values")
        object.__setattr__(self, "items", items)
        c = np.array([[it.x_m, it.y_m] for it in items], float).reshape(-1, 2)
        object.__setattr__(self, "centres_m", c)
        object.__setattr__(self, "radii_m", np.array([it.radius_m for it in items], float))

    def __len__(self) -> int:
        return len(self.items)

    def __repr__(self) -> str:
        return f"Scatter({self.origin or 'listed'}: {len(self.items)} items)"

    def counts(self) -> dict[str, int]:
        """Items per kind, in :data:`KINDS` order (kinds with none left out)."""
        c = Counter(it.kind for it in self.items)
        return {k: c[k] for k in KINDS if c[k]}

    def of_kind(self, kind: str) -> tuple[ScatterItem, ...]:
        return tuple(it for it in self.items if it.kind == kind)

    def x_range_m(self) -> tuple[float, float] | None:
        """The x extent of the items (None: no items)."""
        if not self.items:
            return None
        lo = self.centres_m[:, 0] - self.radii_m
        hi = self.centres_m[:, 0] + self.radii_m
        return float(lo.min()), float(hi.max())

    def describe(self) -> str:
        """One line: origin and the count of each kind."""
        kinds = ", ".join(f"{n} {k}" for k, n in self.counts().items()) or "no items"
        return f"{self.origin or 'listed'}: {kinds}"


# --------------------------------------------------------------------------- presets
@dataclass(frozen=True)
class ScatterPreset:
    """How :func:`generate` fills a tile grid (densities per m² of ceiling).

    Light panels sit on a lattice every ``panel_pitch_tiles`` (x, y) tiles, each moved
    by one tile with probability ``panel_shift``, left out with ``panel_missing``, and
    two tiles long with ``panel_double``: the near-regular layout of real offices, made
    irregular by the rest. Sprinklers keep ``sprinkler_gap_m`` apart and detectors
    ``detector_gap_m``; stains come in clusters of one to three blotches.
    """

    name: str
    panel_pitch_tiles: tuple[int, int] = (4, 3)
    panel_shift: float = 0.35
    panel_missing: float = 0.1
    panel_double: float = 0.5
    vents_per_m2: float = 0.08
    hatches_per_m2: float = 0.025
    patch_share: float = 0.07
    stains_per_m2: float = 0.25
    sprinklers_per_m2: float = 1.0 / 9.0
    sprinkler_gap_m: float = 1.5
    detectors_per_m2: float = 1.0 / 40.0
    detector_gap_m: float = 3.0
    cables_per_m2: float = 1.0 / 40.0


PRESETS: dict[str, ScatterPreset] = {
    # an office floor: panels every 2.4 x 1.8 m, a vent every 12 m², hatches, patched
    # and stained tiles, sprinklers every ~9 m², a smoke detector every ~40 m², cables
    "office": ScatterPreset("office"),
    # a plain ceiling with little on it: sparse panels, few fixtures, faint stains
    "sparse": ScatterPreset("sparse", panel_pitch_tiles=(6, 5), panel_missing=0.3,
                            vents_per_m2=0.02, hatches_per_m2=0.01, patch_share=0.02,
                            stains_per_m2=0.05, sprinklers_per_m2=1.0 / 12.0,
                            detectors_per_m2=1.0 / 60.0, cables_per_m2=0.0),
}
"""The scatter presets a ``scene.yaml`` (``generate: {preset: NAME, ...}``) can name."""


# --------------------------------------------------------------------------- generation
_FREE, _PANEL, _VENT, _HATCH, _PATCH = 0, 1, 2, 3, 4
_CODE = {"panel": _PANEL, "vent": _VENT, "hatch": _HATCH, "patch": _PATCH}


def tile_grid(site: Site, x_range_m: tuple[float, float],
              y_range_m: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The tile grid's seams inside the ranges: ``(xs, ys)``, the x of the across lines
    (``lines_across``) in ``x_range_m`` and the y of the ``lines_along`` in
    ``y_range_m`` (None: all of them), both sorted; tile ``(i, j)`` spans
    ``[xs[i], xs[i+1]] x [ys[j], ys[j+1]]``.

    Raises ConfigError (keyed ``corridor`` of the site's file) when the site has no tile
    grid (two lines along and lines across), or keyed ``x_range_m`` / ``y_range_m`` when
    a range is empty or holds no tile."""
    cor = site.corridor
    if cor is None or cor.lines_across is None or len(cor.lines_along_m) < 2:
        raise ConfigError(site.source, "corridor", "a scatter is laid on the site's tile "
                          "grid: expected lines_along (two or more) and lines_across")
    for name, r in (("x_range_m", x_range_m), ("y_range_m", y_range_m)):
        if r is not None and not (len(r) == 2 and all(math.isfinite(v) for v in r)
                                  and r[0] < r[1]):
            raise ConfigError(None, name, f"expected [lo, hi] with lo < hi, found {r!r}")
    first, sp = cor.lines_across.first_m, cor.lines_across.spacing_m
    k0 = math.ceil((x_range_m[0] - first) / sp - 1e-9)
    k1 = math.floor((x_range_m[1] - first) / sp + 1e-9)
    xs = first + sp * np.arange(k0, k1 + 1, dtype=float)
    ys = np.array(sorted(cor.lines_along_m), float)
    if y_range_m is not None:
        ys = ys[(ys >= y_range_m[0] - 1e-9) & (ys <= y_range_m[1] + 1e-9)]
    if xs.size < 2:
        raise ConfigError(None, "x_range_m", f"{x_range_m!r} holds no whole tile")
    if ys.size < 2:
        raise ConfigError(None, "y_range_m", f"{y_range_m!r} holds no whole tile")
    return xs, ys


def generate(preset: str | ScatterPreset, site: Site, seed: int,
             x_range_m: tuple[float, float],
             y_range_m: tuple[float, float] | None = None) -> Scatter:
    """A scatter laid out by ``preset`` (a name of :data:`PRESETS` or a
    :class:`ScatterPreset`) on ``site``'s tile grid (:func:`tile_grid`) over the ranges,
    drawn from ``np.random.default_rng(seed)``: deterministic from its arguments.

    Raises ConfigError: ``preset`` unknown, ``seed`` not an integer >= 0, no tile grid.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ConfigError(None, "preset", f"expected one of {', '.join(PRESETS)}, "
                              f"found {preset!r}")
        preset = PRESETS[preset]
    if not isinstance(preset, ScatterPreset):
        raise ConfigError(None, "preset", "expected a preset name or a ScatterPreset")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(None, "seed", f"expected an integer >= 0, found {seed!r}")
    xs, ys = tile_grid(site, x_range_m, y_range_m)
    rng = np.random.default_rng(int(seed))
    occ = np.full((xs.size - 1, ys.size - 1), _FREE, np.int8)
    area = float((xs[-1] - xs[0]) * (ys[-1] - ys[0]))
    p = preset
    items = _panels(p, xs, ys, occ, rng)
    items += _fill_tiles("vent", rng.poisson(p.vents_per_m2 * area), xs, ys, occ, rng)
    items += _fill_tiles("hatch", rng.poisson(p.hatches_per_m2 * area), xs, ys, occ, rng)
    items += _patches(p.patch_share, xs, ys, occ, rng)
    items += _stains(rng.poisson(p.stains_per_m2 * area), xs, ys, occ, rng)
    sprinklers = _points("sprinkler", rng.poisson(p.sprinklers_per_m2 * area),
                         p.sprinkler_gap_m, [], xs, ys, occ, rng)
    detectors = _points("detector", rng.poisson(p.detectors_per_m2 * area),
                        p.detector_gap_m, sprinklers, xs, ys, occ, rng)
    items += sprinklers + detectors
    items += _cables(rng.poisson(p.cables_per_m2 * area), xs, ys, rng)
    return Scatter(tuple(items), f"{p.name} preset, seed {int(seed)}")


def _tile_item(kind: str, xs: np.ndarray, ys: np.ndarray, i0: int, i1: int, j0: int,
               j1: int, yaw_deg: float = 0.0, grey: float = 0.0) -> ScatterItem:
    """An item filling tiles ``i0..i1 x j0..j1`` (inclusive), inset by
    :data:`TILE_INSET_M`; ``yaw_deg`` 0 or 90 (its length along x or y)."""
    lx = xs[i1 + 1] - xs[i0] - 2 * TILE_INSET_M
    ly = ys[j1 + 1] - ys[j0] - 2 * TILE_INSET_M
    length, width = (lx, ly) if yaw_deg == 0.0 else (ly, lx)
    return ScatterItem(kind, _r(0.5 * (xs[i0] + xs[i1 + 1]), ROUND_M),
                       _r(0.5 * (ys[j0] + ys[j1 + 1]), ROUND_M), _r(length, ROUND_M),
                       _r(width, ROUND_M), yaw_deg, _r(grey, ROUND_GREY))


def _panels(p: ScatterPreset, xs: np.ndarray, ys: np.ndarray, occ: np.ndarray,
            rng: np.random.Generator) -> list[ScatterItem]:
    """Light panels on a lattice of tiles, each moved, left out or doubled at random."""
    nx, ny = occ.shape
    px, py = p.panel_pitch_tiles
    out = []
    for i in range(int(rng.integers(px)), nx, px):
        for j in range(int(rng.integers(py)), ny, py):
            u = rng.random(4)
            if u[0] < p.panel_missing:
                continue
            di, dj = 0, 0
            if u[1] < p.panel_shift:
                di, dj = ((1, 0), (-1, 0), (0, 1), (0, -1))[int(rng.integers(4))]
            a, b = i + di, j + dj
            double = u[2] < p.panel_double
            i1 = a + 1 if double and u[3] < 0.5 else a
            j1 = b + 1 if double and u[3] >= 0.5 else b
            if not (0 <= a and i1 < nx and 0 <= b and j1 < ny) or \
                    np.any(occ[a:i1 + 1, b:j1 + 1] != _FREE):
                continue
            occ[a:i1 + 1, b:j1 + 1] = _PANEL
            out.append(_tile_item("panel", xs, ys, a, i1, b, j1))
    return out


def _fill_tiles(kind: str, n: int, xs: np.ndarray, ys: np.ndarray, occ: np.ndarray,
                rng: np.random.Generator) -> list[ScatterItem]:
    """``n`` items of a tile kind in free tiles chosen at random (a vent's slats along
    x or y at random)."""
    free = np.argwhere(occ == _FREE)
    out = []
    for i, j in free[rng.permutation(len(free))[:n]]:
        occ[i, j] = _CODE[kind]
        yaw = 90.0 if kind == "vent" and rng.random() < 0.5 else 0.0
        out.append(_tile_item(kind, xs, ys, int(i), int(i), int(j), int(j), yaw))
    return out


def _patches(share: float, xs: np.ndarray, ys: np.ndarray, occ: np.ndarray,
             rng: np.random.Generator) -> list[ScatterItem]:
    """Each free tile replaced with probability ``share``: 4 to 12 grey levels lighter
    or darker."""
    out = []
    for i, j in np.argwhere(occ == _FREE):
        u = rng.random(3)
        if u[0] >= share:
            continue
        occ[i, j] = _PATCH
        grey = (4.0 + 8.0 * u[1]) * (1.0 if u[2] < 0.5 else -1.0)
        out.append(_tile_item("patch", xs, ys, int(i), int(i), int(j), int(j), grey=grey))
    return out


def _tile_at(xs: np.ndarray, ys: np.ndarray, x: float, y: float) -> tuple[int, int]:
    return (int(np.clip(np.searchsorted(xs, x) - 1, 0, xs.size - 2)),
            int(np.clip(np.searchsorted(ys, y) - 1, 0, ys.size - 2)))


def _stains(n: int, xs: np.ndarray, ys: np.ndarray, occ: np.ndarray,
            rng: np.random.Generator) -> list[ScatterItem]:
    """``n`` stains, each a cluster of one to three soft blotches (6 to 35 cm, 8 to 28
    grey levels deep), on plain or patched tiles."""
    out = []
    for _ in range(n):
        for _try in range(20):
            cx, cy = rng.uniform(xs[0], xs[-1]), rng.uniform(ys[0], ys[-1])
            if occ[_tile_at(xs, ys, cx, cy)] in (_FREE, _PATCH):
                break
        else:
            continue
        size = rng.uniform(0.06, 0.35)
        for _b in range(int(rng.integers(1, 4))):
            length = size * rng.uniform(0.5, 1.0)
            ox, oy = rng.normal(0.0, 0.25 * size, 2)
            out.append(ScatterItem(
                "stain", _r(cx + ox, ROUND_M), _r(cy + oy, ROUND_M), _r(length, ROUND_M),
                _r(length * rng.uniform(0.4, 0.9), ROUND_M),
                _r(rng.uniform(0.0, 180.0), ROUND_DEG), _r(rng.uniform(8.0, 28.0),
                                                           ROUND_GREY)))
    return out


def _points(kind: str, n: int, gap_m: float, others: list[ScatterItem], xs: np.ndarray,
            ys: np.ndarray, occ: np.ndarray, rng: np.random.Generator) -> list[ScatterItem]:
    """``n`` discs of ``kind`` at random in plain or patched tiles, at least 8 cm inside
    the tile, ``gap_m`` from each other and 0.5 m from ``others`` (fewer when no room
    is found in ``20 n`` tries)."""
    d = DEFAULT_SIZE_M[kind][0]
    placed: list[tuple[float, float]] = []
    near = [(it.x_m, it.y_m) for it in others]
    for _ in range(20 * n):
        if len(placed) >= n:
            break
        x, y = rng.uniform(xs[0], xs[-1]), rng.uniform(ys[0], ys[-1])
        i, j = _tile_at(xs, ys, x, y)
        inner = min(x - xs[i], xs[i + 1] - x, y - ys[j], ys[j + 1] - y)
        if occ[i, j] not in (_FREE, _PATCH) or inner < 0.08:
            continue
        if any(math.hypot(x - a, y - b) < gap_m for a, b in placed) or \
                any(math.hypot(x - a, y - b) < 0.5 for a, b in near):
            continue
        placed.append((_r(x, ROUND_M), _r(y, ROUND_M)))
    return [ScatterItem(kind, x, y, d, d) for x, y in placed]


def _cables(n: int, xs: np.ndarray, ys: np.ndarray,
            rng: np.random.Generator) -> list[ScatterItem]:
    """``n`` cable runs of 1.5 to 4 m along x or y, half of them with a right-angle
    bend, sagging a little between their points, 6 to 12 mm wide."""
    out = []
    dirs = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    for _ in range(n):
        p0 = np.array([rng.uniform(xs[0], xs[-1]), rng.uniform(ys[0], ys[-1])])
        d = dirs[int(rng.integers(4))]
        total = rng.uniform(1.5, 4.0)
        pts = [p0]
        if rng.random() < 0.5:
            a = total * rng.uniform(0.3, 0.7)
            pts.append(pts[-1] + a * d)
            d = np.array([-d[1], d[0]]) * (1.0 if rng.random() < 0.5 else -1.0)
            total -= a
        end = pts[-1] + total * d
        mid = 0.5 * (pts[-1] + end) + rng.normal(0.0, 0.02, 2)
        pts += [mid, end]
        pts = [(_r(x, ROUND_M), _r(y, ROUND_M)) for x, y in pts]
        out.append(cable(pts, _r(rng.uniform(0.006, 0.012), ROUND_M)))
    return out


__all__ = ["DEFAULT_GREY", "DEFAULT_SIZE_M", "DISC_KINDS", "KINDS", "PRESETS", "Scatter",
           "ScatterItem", "ScatterPreset", "TILE_KINDS", "cable", "generate", "tile_grid"]
