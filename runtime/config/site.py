"""The site: what is on the ceiling, in the world frame W (SPEC §2, ``site.yaml``).

Every section is optional; which ones are present decides which estimators can run.
Lamps are rectangles whose long side runs along W's x: a row of ``count`` lamps,
the first centred at ``(x, y)``, the next ones every ``pitch`` metres along +x.

Example::

    site = Site.load("configs/block/site.yaml")      # every problem is a ConfigError
    site.blocks[0].corners_m                          # (4, 2), counter-clockwise from above
    site.ignored(np.array([[1.0, 2.0]]))              # (1,) bool: inside an ignore region?
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.config.yaml import (
    NUMBER_LIMIT,
    Node,
    atomic_write_text,
    dump_yaml,
    load_yaml,
)
from ceilkit.runtime.errors import ConfigError

SITE_KEYS = ("ceiling_height", "corridor", "lamps", "lights", "light_diameter", "light_size",
             "light_yaw", "light_sigma", "ignore", "blocks", "markers", "origin",
             "ceiling_map")
LAMP_KEYS = ("x", "y", "length", "width", "pitch", "count", "z")
BLOCK_KEYS = ("id", "corners", "appearance")
BLOCK_APPEARANCES = ("dark", "bright")
MARKER_KEYS = ("dictionary", "size", "poses")
MARKER_POSE_KEYS = ("id", "x", "y", "yaw", "size")
ORIGIN_KEYS = ("lat", "lon", "alt", "heading")

SAME_PLACE_M = 1e-3
"""Two points of the site closer than this are one point given twice: a duplicate
light, or a block corner repeated."""

MIN_AREA_M2 = 1e-6
"""Least area of a block or an ignore region (1 mm²): below it the points are (nearly)
on one line, a slip in the file rather than a shape."""

MIN_CORNER_TURN_DEG = 1.0
"""Least turn of a block's outline at each corner: a corner where the outline turns
less (or turns back by nearly 180°) is not a corner of a quadrilateral."""

MIN_CEILING_CLEARANCE_M = 0.05
"""The ceiling, and a hanging lamp's face, must be more than this above the camera's
optical centre (``mount.z``): nearer, the plane is (nearly) through the lens and no
ceiling method can work."""

YAW_LIMIT_DEG = 360.0
"""A marker's yaw and the origin's heading are read in [-360, 360] degrees."""

MARKER_CORNER_DIRECTIONS = np.array([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])
"""d_0..d_3 of SPEC §2: corner k of a marker is ``(x, y) + Rz(yaw) (s/2) d_k``, in the
order OpenCV's aruco returns corners (top-left, top-right, bottom-right, bottom-left
of the printed image)."""


@dataclass(frozen=True)
class AcrossLines:
    """Ceiling lines parallel to W's y, at ``x = first + k * spacing``."""

    first_m: float
    spacing_m: float


@dataclass(frozen=True)
class Corridor:
    """The ceiling lines the corridor method uses."""

    lines_along_m: tuple[float, ...]          # y of lines parallel to x
    lines_across: AcrossLines | None = None   # x of lines parallel to y

    @property
    def axis_y_m(self) -> float:
        """y of the corridor's centre line (middle of the along-lines)."""
        return 0.5 * (min(self.lines_along_m) + max(self.lines_along_m))


@dataclass(frozen=True)
class LampRow:
    """A row of ``count`` rectangular lamps, long side along W's x.

    ``z_m`` is the height of the lamps' face when they hang below the ceiling, None
    when they are on the ceiling (``z = ceiling_height``).
    """

    x_m: float
    y_m: float
    length_m: float
    width_m: float
    pitch_m: float = 0.0
    count: int = 1
    z_m: float | None = None

    def face_z_m(self, ceiling_height_m: float) -> float:
        """Height in W of the lamps' face: ``z_m``, or the ceiling's when None."""
        return ceiling_height_m if self.z_m is None else self.z_m

    def centres(self) -> np.ndarray:
        """``(count, 2)`` lamp centres in W."""
        k = np.arange(self.count)
        return np.stack([self.x_m + k * self.pitch_m, np.full(self.count, self.y_m)], axis=1)

    def rectangles(self) -> np.ndarray:
        """``(count, 4, 2)`` lamp corners in W, counter-clockwise from (-x, -y)."""
        hl, hw = self.length_m / 2, self.width_m / 2
        offs = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
        return self.centres()[:, None, :] + offs[None, :, :]


@dataclass(frozen=True)
class Block:
    """A reference block (Xu et al.): a known convex quadrilateral on the ceiling.

    Attributes:
        id: the block's name in the site file (text).
        corners_m: ``(4, 2)`` corners (x, y) in W, in order around the block and
            counter-clockwise seen from above (W's +z; positive shoelace area), that
            is clockwise as the camera sees it from below. Corner 0 is the file's
            first corner; corners given clockwise are reversed to 0, 3, 2, 1.
        appearance: ``dark`` or ``bright`` against the ceiling around it, None if
            not given.
    """

    id: str
    corners_m: np.ndarray
    appearance: str | None = None

    def __post_init__(self) -> None:
        corners = np.array(self.corners_m, dtype=float).reshape(4, 2)
        if polygon_area_m2(corners) < 0:
            corners = corners[[0, 3, 2, 1]]
        corners.setflags(write=False)
        object.__setattr__(self, "corners_m", corners)


@dataclass(frozen=True)
class MarkerPose:
    """One printed square marker: its id in the dictionary, centre, yaw and side.

    Attributes:
        id: the marker's id in the site's aruco dictionary.
        x_m, y_m: the marker's centre in W.
        yaw_rad: rotation about W's z (counter-clockwise from above); at 0 the printed
            image's "up" points along +x.
        size_m: side of the black square (the site's default when the file gives
            none for this marker).
    """

    id: int
    x_m: float
    y_m: float
    yaw_rad: float
    size_m: float

    def corners_m(self) -> np.ndarray:
        """``(4, 2)`` corners in W, SPEC §2: corner k = ``(x, y) + Rz(yaw) (s/2) d_k``,
        in the order OpenCV's aruco returns them.

        >>> MarkerPose(7, 2.0, 0.5, 0.0, 0.2).corners_m()[0]     # top-left
        array([2.1, 0.4])
        """
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        R = np.array([[c, -s], [s, c]])
        return np.array([self.x_m, self.y_m]) + (0.5 * self.size_m) * MARKER_CORNER_DIRECTIONS @ R.T


@dataclass(frozen=True)
class Markers:
    """Printed square fiducials on the ceiling, all from one aruco dictionary.

    ``dictionary`` is a ``cv2.aruco`` predefined dictionary name (``DICT_4X4_50``,
    ``DICT_APRILTAG_36h11``, ...), ``size_m`` the default side of the black square.
    """

    dictionary: str
    size_m: float
    poses: tuple[MarkerPose, ...]

    def pose(self, marker_id: int) -> MarkerPose | None:
        """The pose of marker ``marker_id``, None if the site does not hold it."""
        return next((p for p in self.poses if p.id == marker_id), None)

    def corners_m(self) -> np.ndarray:
        """``(N, 4, 2)`` every marker's corners in W, in the order of ``poses``."""
        return np.array([p.corners_m() for p in self.poses]).reshape(-1, 4, 2)


@dataclass(frozen=True)
class SiteOrigin:
    """Where W lies on the Earth (for GPS-style outputs).

    Attributes:
        lat_deg, lon_deg: W's origin, degrees (WGS84).
        alt_m: its altitude, m.
        heading_deg: heading of W's +x, degrees clockwise from true north.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    heading_deg: float

    @property
    def heading_rad(self) -> float:
        return math.radians(self.heading_deg)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Site:
    """Everything on the ceiling, in W; each section empty or None when absent.

    ``ignore_m`` holds the regions no method should use, each an ``(N, 2)`` polygon
    in W (N >= 3), as :meth:`ignored` tests them.

    ``light_size_m`` (SPEC §2 ``light_size``): ``(length, width)`` of lights that are
    rectangles (panels, troffers), whose centres are ``lights_m``; ``light_yaw_rad``
    the direction of their long side from W's +x (``light_yaw``, 0 when not given).
    None (and 0) for round lights; ``light_size_m`` and ``light_diameter_m`` are never
    both set.

    ``ceiling_map`` (ceilkit's extension of SPEC §2, ``ceiling_map: FILE``): the path of
    the site's ceiling map (the ``texture`` method's; relative paths in the file are
    resolved against the site file's folder), or None.

    ``light_sigma_m`` (ceilkit's extension of SPEC §2, ``light_sigma``): ``(N,)`` the 1σ
    per axis of each light's position in ``lights_m`` (a surveyed map's own error:
    ``ceilcal survey`` writes it), or None: the lights are exact.
    """

    ceiling_height_m: float
    corridor: Corridor | None = None
    lamps: tuple[LampRow, ...] = ()
    lights_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    blocks: tuple[Block, ...] = ()
    light_diameter_m: float | None = None
    ignore_m: tuple[np.ndarray, ...] = ()
    markers: Markers | None = None
    origin: SiteOrigin | None = None
    source: str | None = None
    light_size_m: tuple[float, float] | None = None
    light_yaw_rad: float = 0.0
    ceiling_map: str | None = None
    light_sigma_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "ignore_m", tuple(_readonly(p) for p in self.ignore_m))
        if self.light_sigma_m is not None:
            sig = _readonly(np.asarray(self.light_sigma_m, float).reshape(-1))
            if sig.shape[0] != self.lights_m.shape[0]:
                raise ValueError(f"light_sigma_m holds {sig.shape[0]} values for "
                                 f"{self.lights_m.shape[0]} lights")
            object.__setattr__(self, "light_sigma_m", sig)
        if self.light_size_m is not None:
            object.__setattr__(self, "light_size_m",
                               (float(self.light_size_m[0]), float(self.light_size_m[1])))

    @property
    def rectangular_lights(self) -> bool:
        """Whether the lights are rectangles (``light_size`` given)."""
        return self.light_size_m is not None

    def light_rectangles(self) -> np.ndarray:
        """``(N, 4, 2)`` every light's corners in W (``light_size`` and ``light_yaw``),
        counter-clockwise from the (-long, -short) corner; ``(0, 4, 2)`` for round
        lights."""
        if self.light_size_m is None or not self.has_lights:
            return np.zeros((0, 4, 2))
        hl, hw = 0.5 * self.light_size_m[0], 0.5 * self.light_size_m[1]
        c, s = math.cos(self.light_yaw_rad), math.sin(self.light_yaw_rad)
        offs = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]]) @ np.array([[c, s],
                                                                                   [-s, c]])
        return self.lights_m[:, None, :] + offs[None]

    def has_section(self, name: str) -> bool:
        """Whether the site holds section ``name`` (``corridor``, ``lamps``, ``lights``,
        ``blocks``, ``markers``, ``ignore``, ``origin``), non-empty: the estimators that
        need it can run. Any other name is False."""
        present = {"corridor": self.corridor is not None, "lamps": bool(self.lamps),
                   "lights": self.has_lights, "blocks": bool(self.blocks),
                   "markers": self.markers is not None and bool(self.markers.poses),
                   "ignore": bool(self.ignore_m), "origin": self.origin is not None,
                   "ceiling_map": self.ceiling_map is not None}
        return present.get(name, False)

    @property
    def has_lights(self) -> bool:
        return self.lights_m.shape[0] > 0

    def lamp_rectangles(self) -> np.ndarray:
        """``(N, 4, 2)`` every lamp's corners in W."""
        if not self.lamps:
            return np.zeros((0, 4, 2))
        return np.concatenate([row.rectangles() for row in self.lamps], axis=0)

    def ignored(self, points_w: np.ndarray) -> np.ndarray:
        """Which points lie in an ``ignore`` region.

        Args:
            points_w: ``(..., 2)`` points (x, y) in W.

        Returns:
            ``(...)`` bool, True inside any region (even-odd rule; a point exactly on a
            region's edge may fall either way). All False when there is none.
        """
        pts = np.asarray(points_w, dtype=float)
        mask = np.zeros(pts.shape[:-1], dtype=bool)
        for polygon in self.ignore_m:
            mask |= points_in_polygon(pts, polygon)
        return mask

    def touches_ignored(self, corners_w: np.ndarray) -> bool:
        """Whether a quad ``(4, 2)`` (a block's or a marker's corners, W) reaches into an
        ``ignore`` region: a corner, the centre or a side's midpoint inside one."""
        if not self.ignore_m:
            return False
        c = np.asarray(corners_w, float).reshape(-1, 2)
        probe = np.concatenate([c, c.mean(axis=0, keepdims=True),
                                0.5 * (c + c[np.arange(1, len(c) + 1) % len(c)])])
        return bool(self.ignored(probe).any())

    def without_ignored(self) -> Site:
        """This site without the blocks and markers that reach into an ``ignore`` region
        (SPEC §2: regions no method should use); itself when it has no region."""
        if not self.ignore_m:
            return self
        blocks = tuple(b for b in self.blocks if not self.touches_ignored(b.corners_m))
        markers = self.markers
        if markers is not None:
            markers = dataclasses.replace(markers, poses=tuple(
                m for m in markers.poses if not self.touches_ignored(m.corners_m())))
        return dataclasses.replace(self, blocks=blocks, markers=markers)

    def to_dict(self) -> dict[str, Any]:
        """The ``site.yaml`` mapping; :meth:`from_node` of it gives this site back."""
        d: dict[str, Any] = {"ceiling_height": float(self.ceiling_height_m)}
        if self.corridor is not None:
            c: dict[str, Any] = {"lines_along": [float(v) for v in self.corridor.lines_along_m]}
            if self.corridor.lines_across is not None:
                c["lines_across"] = {"first": float(self.corridor.lines_across.first_m),
                                     "spacing": float(self.corridor.lines_across.spacing_m)}
            d["corridor"] = c
        if self.lamps:
            d["lamps"] = [_lamp_dict(r) for r in self.lamps]
        if self.has_lights:
            d["lights"] = [[float(a), float(b)] for a, b in self.lights_m]
        if self.light_sigma_m is not None:
            d["light_sigma"] = [float(v) for v in self.light_sigma_m]
        if self.light_diameter_m is not None:
            d["light_diameter"] = float(self.light_diameter_m)
        if self.light_size_m is not None:
            d["light_size"] = [float(v) for v in self.light_size_m]
            d["light_yaw"] = round(math.degrees(self.light_yaw_rad), 9)
        if self.ignore_m:
            d["ignore"] = [_points_list(p) for p in self.ignore_m]
        if self.blocks:
            d["blocks"] = [_block_dict(b) for b in self.blocks]
        if self.markers is not None:
            d["markers"] = _markers_dict(self.markers)
        if self.ceiling_map is not None:
            d["ceiling_map"] = str(self.ceiling_map)
        if self.origin is not None:
            o = self.origin
            d["origin"] = {"lat": float(o.lat_deg), "lon": float(o.lon_deg),
                           "alt": float(o.alt_m), "heading": float(o.heading_deg)}
        return d

    def save(self, path: str | Path, header: str = "") -> None:
        atomic_write_text(path, dump_yaml(self.to_dict(), header))

    @classmethod
    def load(cls, path: str | Path) -> Site:
        return cls.from_node(load_yaml(path), str(path))

    @classmethod
    def from_node(cls, node: Node, source: str | None = None) -> Site:
        """The site a ``site.yaml`` mapping describes, checked whole.

        Raises:
            ConfigError: naming the file and the dotted key of the first problem.
        """
        node.mapping(SITE_KEYS, required=("ceiling_height",))
        height = node.get("ceiling_height").number(0.0, 1000.0, lo_open=True, what=" m")
        corridor = _corridor(node.get("corridor")) if node.has("corridor") else None
        lamps = (tuple(_lamp(ln, height) for ln in node.get("lamps").items())
                 if node.has("lamps") else ())
        lights = _lights(node.get("lights")) if node.has("lights") else np.zeros((0, 2))
        diameter = (node.get("light_diameter").number(0.0, None, lo_open=True, what=" m")
                    if node.has("light_diameter") else None)
        size, light_yaw = _light_size(node)
        ignore = _ignore(node.get("ignore")) if node.has("ignore") else ()
        blocks = _blocks(node.get("blocks")) if node.has("blocks") else ()
        markers = _markers(node.get("markers")) if node.has("markers") else None
        origin = _origin(node.get("origin")) if node.has("origin") else None
        source = source or (str(node.path) if node.path else None)
        cmap = _ceiling_map(node.get("ceiling_map"), source) if node.has("ceiling_map") else None
        return cls(height, corridor, lamps, lights, blocks, diameter, ignore, markers, origin,
                   source, size, light_yaw, cmap, _light_sigma(node, lights.shape[0]))


# -- polygons (pure) ------------------------------------------------------------------

def polygon_area_m2(points_m: np.ndarray) -> float:
    """Signed (shoelace) area of an ``(N, 2)`` polygon: > 0 counter-clockwise from above."""
    x, y = points_m[:, 0], points_m[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def points_in_polygon(points_m: np.ndarray, polygon_m: np.ndarray) -> np.ndarray:
    """``(...)`` bool: which of the ``(..., 2)`` points lie inside the ``(N, 2)`` polygon
    (even-odd rule, by a ray along +x)."""
    x, y = points_m[..., 0, None], points_m[..., 1, None]
    x0, y0 = polygon_m[:, 0], polygon_m[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(crosses & (x < x_cross), axis=-1) % 2 == 1


def quadrilateral_problem(corners_m: np.ndarray) -> str | None:
    """Why four corners (in order around, either way) are not a simple convex
    quadrilateral, or None when they are."""
    edges = np.roll(corners_m, -1, axis=0) - corners_m
    lengths = np.linalg.norm(edges, axis=1)
    for k in range(4):
        if lengths[k] < SAME_PLACE_M:
            return f"corners {k} and {(k + 1) % 4} are at the same place"
    nxt = np.roll(edges, -1, axis=0)
    sines = (edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]) / (lengths * np.roll(lengths, -1))
    if np.min(np.abs(sines)) < math.sin(math.radians(MIN_CORNER_TURN_DEG)):
        k = (int(np.argmin(np.abs(sines))) + 1) % 4
        return f"corner {k} lies on a straight side or turns back (not a quadrilateral)"
    if np.all(sines > 0) or np.all(sines < 0):
        if abs(polygon_area_m2(corners_m)) < MIN_AREA_M2:
            return "the corners enclose no area"
        return None
    if (_segments_cross(corners_m[0], corners_m[1], corners_m[2], corners_m[3])
            or _segments_cross(corners_m[1], corners_m[2], corners_m[3], corners_m[0])):
        return "the outline crosses itself (corners not in order around the block)"
    return "not convex"


def _segments_cross(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> bool:
    """Whether segments ab and cd cross at a point inside both."""
    def side(p, q, r):
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])
    return side(a, b, c) * side(a, b, d) < 0 and side(c, d, a) * side(c, d, b) < 0


# -- sections: file -> dataclasses ----------------------------------------------------

def _ceiling_map(node: Node, source: str | None) -> str:
    """``ceiling_map: FILE``: the map's path, resolved against the site file's folder;
    the file must exist (its contents are read by the ``texture`` method)."""
    text = node.string()
    path = Path(text)
    if not path.is_absolute() and source is not None:
        path = Path(source).parent / path
    if not path.is_file():
        raise node.error(f"no such file {str(path)!r}")
    return str(path)


def _corridor(node: Node) -> Corridor:
    cn = node.mapping(("lines_along", "lines_across"), required=("lines_along",))
    an = cn.get("lines_along")
    along = an.numbers()
    if not along:
        raise an.error("expected at least one line")
    if len(set(along)) != len(along):
        raise an.error("two lines at the same y")
    across = None
    if cn.has("lines_across"):
        xn = cn.get("lines_across").mapping(("first", "spacing"), required=("spacing",))
        across = AcrossLines(xn.get("first", 0.0).number(),
                             xn.get("spacing").number(0.0, None, lo_open=True, what=" m"))
    return Corridor(tuple(sorted(along)), across)


def _lamp(ln: Node, ceiling_height_m: float) -> LampRow:
    ln.mapping(LAMP_KEYS, required=("x", "y", "length", "width"))
    count = ln.get("count", 1).integer(1, 100_000)
    pitch = ln.get("pitch", 0.0).number(0.0, None, what=" m")
    length = ln.get("length").number(0.0, None, lo_open=True, what=" m")
    if count > 1 and pitch < length:
        raise ln.get("pitch").error(
            f"lamps overlap: pitch {pitch:g} m is shorter than length {length:g} m")
    z = (ln.get("z").number(0.0, ceiling_height_m, lo_open=True,
                            what=" m (above the floor, at most ceiling_height)")
         if ln.has("z") else None)
    return LampRow(ln.get("x").number(), ln.get("y").number(), length,
                   ln.get("width").number(0.0, None, lo_open=True, what=" m"), pitch, count, z)


def _lights(ln: Node) -> np.ndarray:
    lights = _plain_lights(ln.value)
    if lights is None:       # not a plain list of pairs of numbers: each item says why
        lights = np.array([n.numbers(2) for n in ln.items()], dtype=float).reshape(-1, 2)
    if lights.shape[0] == 0:
        raise ln.error("expected at least one light (or leave the section out)")
    if lights.shape[0] > 1:
        # pairs closer than SAME_PLACE_M by a k-d tree (a map of thousands of lights
        # would make an all-pairs matrix of millions of entries)
        close = cKDTree(lights).query_pairs(SAME_PLACE_M, output_type="ndarray")
        if close.shape[0]:
            lo, hi = (int(v) for v in close[np.lexsort((close[:, 1], close[:, 0]))[0]])
            raise ConfigError(ln.path, f"{ln.key}[{hi}]",
                              f"duplicate light: same place as {ln.key}[{lo}]")
    return lights


def _light_sigma(node: Node, n: int) -> np.ndarray | None:
    """``(n,)`` of ``light_sigma`` (one number for every light, or one per light in the
    order of ``lights``; metres, per axis, >= 0), or None when absent."""
    if not node.has("light_sigma"):
        return None
    sn = node.get("light_sigma")
    if n == 0:
        raise sn.error("light_sigma needs lights (the 1-sigma of their positions)")
    if not isinstance(sn.value, list):
        return np.full(n, sn.number(0.0, None, what=" m"))
    if len(sn.value) != n:
        raise sn.expected(f"one 1-sigma per light ({n}, in the order of lights) or one "
                          "number for all")
    return np.array([v.number(0.0, None, what=" m") for v in sn.items()])


def _plain_lights(value: object) -> np.ndarray | None:
    """``(N, 2)`` of a list of ``[x, y]`` finite numbers within ``NUMBER_LIMIT`` (what
    ``Node.numbers(2)`` accepts, read at once: a site of 100 000 lights), or None
    when any item is not (the items are then read one by one, for the message)."""
    if not isinstance(value, list) or not all(
            type(v) is list and len(v) == 2 and type(v[0]) in (int, float)
            and type(v[1]) in (int, float) for v in value):
        return None
    try:
        out = np.array(value, dtype=float).reshape(-1, 2)
    except OverflowError:
        return None
    ok = np.isfinite(out).all() and (np.abs(out) <= NUMBER_LIMIT).all()
    return out if ok else None


def _light_size(node: Node) -> tuple[tuple[float, float] | None, float]:
    """``(light_size (length, width) or None, light_yaw in rad)`` of a site mapping:
    ``light_size`` positive finite lengths (length >= width), never with
    ``light_diameter``; ``light_yaw`` only with ``light_size``."""
    if not node.has("light_size"):
        if node.has("light_yaw"):
            raise node.get("light_yaw").error(
                "light_yaw needs light_size (the direction of a rectangle's long side)")
        return None, 0.0
    sn = node.get("light_size")
    if node.has("light_diameter"):
        raise sn.error("give light_size (rectangular lights) or light_diameter (round "
                       "lights), not both")
    if not isinstance(sn.value, list) or len(sn.value) != 2:
        raise sn.expected("[length, width] of the lights' lit face, m")
    length, width = (n.number(0.0, None, lo_open=True, what=" m") for n in sn.items())
    if width > length:
        raise sn.error(f"expected [length, width] with length >= width, found "
                       f"[{length:g}, {width:g}] (light_yaw gives the long side's direction)")
    yaw = (node.get("light_yaw").number(-YAW_LIMIT_DEG, YAW_LIMIT_DEG, what=" degrees")
           if node.has("light_yaw") else 0.0)
    return (length, width), math.radians(yaw)


def _points(node: Node, what: str) -> np.ndarray:
    """``(N, 2)`` from a list of ``[x, y]``."""
    if not isinstance(node.value, list):
        raise node.expected(f"a list of {what}")
    return np.array([p.numbers(2) for p in node.items()], dtype=float).reshape(-1, 2)


def _ignore(node: Node) -> tuple[np.ndarray, ...]:
    polygons = []
    for pn in node.items():
        polygon = _points(pn, "[x, y] points")
        if polygon.shape[0] < 3:
            raise pn.error(f"expected a polygon of at least 3 [x, y] points, "
                           f"found {polygon.shape[0]}")
        if abs(polygon_area_m2(polygon)) < MIN_AREA_M2:
            raise pn.error("the polygon encloses no area")
        polygons.append(polygon)
    if not polygons:
        raise node.error("expected at least one polygon (or leave the section out)")
    return tuple(polygons)


def _scalar_id(node: Node) -> str:
    if isinstance(node.value, bool) or not isinstance(node.value, (str, int, float)):
        raise node.expected("a name or a number")
    return str(node.value)


def _blocks(node: Node) -> tuple[Block, ...]:
    blocks: list[Block] = []
    for bn in node.items():
        bn.mapping(BLOCK_KEYS, required=("id", "corners"))
        bid = _scalar_id(bn.get("id"))
        if any(b.id == bid for b in blocks):
            raise bn.get("id").error(f"duplicate block id {bid!r}")
        cn = bn.get("corners")
        corners = _points(cn, "4 [x, y] corners")
        if corners.shape[0] != 4:
            raise cn.error(f"expected 4 corners, found {corners.shape[0]}")
        problem = quadrilateral_problem(corners)
        if problem:
            raise cn.error(f"expected a convex quadrilateral, corners in order around "
                           f"it: {problem}")
        appearance = (bn.get("appearance").string(BLOCK_APPEARANCES)
                      if bn.has("appearance") else None)
        blocks.append(Block(bid, corners, appearance))
    return tuple(blocks)


def aruco_dictionary_size(name: str) -> int | None:
    """How many markers the ``cv2.aruco`` predefined dictionary ``name`` holds, None
    when ``name`` is not one."""
    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if isinstance(value, bool) or not isinstance(value, int):
        return None
    return int(cv2.aruco.getPredefinedDictionary(value).bytesList.shape[0])


def _markers(node: Node) -> Markers:
    node.mapping(MARKER_KEYS, required=("dictionary", "size", "poses"))
    dn = node.get("dictionary")
    dictionary = dn.string()
    n_ids = aruco_dictionary_size(dictionary)
    if n_ids is None:
        known = sorted(n for n in dir(cv2.aruco) if aruco_dictionary_size(n) is not None)
        raise dn.error(f"expected an OpenCV aruco dictionary ({', '.join(known)}), "
                       f"found {dictionary!r}")
    size = node.get("size").number(0.0, None, lo_open=True, what=" m")
    poses: list[MarkerPose] = []
    pn = node.get("poses")
    for mn in pn.items():
        mn.mapping(MARKER_POSE_KEYS, required=("id", "x", "y", "yaw"))
        mid = mn.get("id").integer(0, n_ids - 1)
        if any(p.id == mid for p in poses):
            raise mn.get("id").error(f"duplicate marker id {mid}")
        yaw = mn.get("yaw").number(-YAW_LIMIT_DEG, YAW_LIMIT_DEG, what=" degrees")
        poses.append(MarkerPose(mid, mn.get("x").number(), mn.get("y").number(),
                                math.radians(yaw),
                                mn.get("size", size).number(0.0, None, lo_open=True,
                                                            what=" m")))
    if not poses:
        raise pn.error("expected at least one marker (or leave the section out)")
    return Markers(dictionary, size, tuple(poses))


def _origin(node: Node) -> SiteOrigin:
    node.mapping(ORIGIN_KEYS, required=ORIGIN_KEYS)
    return SiteOrigin(node.get("lat").number(-90.0, 90.0, what=" degrees"),
                      node.get("lon").number(-180.0, 180.0, what=" degrees"),
                      node.get("alt").number(what=" m"),
                      node.get("heading").number(-YAW_LIMIT_DEG, YAW_LIMIT_DEG,
                                                 what=" degrees"))


# -- sections: dataclasses -> file ----------------------------------------------------

def _points_list(points_m: np.ndarray) -> list[list[float]]:
    return [[float(a), float(b)] for a, b in points_m]


def _lamp_dict(r: LampRow) -> dict[str, Any]:
    d: dict[str, Any] = {"x": r.x_m, "y": r.y_m, "length": r.length_m, "width": r.width_m,
                         "pitch": r.pitch_m, "count": r.count}
    if r.z_m is not None:
        d["z"] = float(r.z_m)
    return d


def _block_dict(b: Block) -> dict[str, Any]:
    d: dict[str, Any] = {"id": b.id, "corners": _points_list(b.corners_m)}
    if b.appearance is not None:
        d["appearance"] = b.appearance
    return d


def _markers_dict(m: Markers) -> dict[str, Any]:
    poses = []
    for p in m.poses:
        d: dict[str, Any] = {"id": int(p.id), "x": float(p.x_m), "y": float(p.y_m),
                             "yaw": round(math.degrees(p.yaw_rad), 9)}
        if p.size_m != m.size_m:
            d["size"] = float(p.size_m)
        poses.append(d)
    return {"dictionary": m.dictionary, "size": float(m.size_m), "poses": poses}


def check_rig_site(rig: Any, site: Site) -> None:
    """Raise a ConfigError if the rig does not fit the site: the ceiling, and the face
    of every lamp row that hangs below it, must be more than
    :data:`MIN_CEILING_CLEARANCE_M` above the camera (``mount.z``)."""
    camera_z_m = rig.mount.z_m
    rig_name = rig.source or "the rig"
    if site.ceiling_height_m <= camera_z_m + MIN_CEILING_CLEARANCE_M:
        raise ConfigError(site.source, "ceiling_height",
                          f"the ceiling ({site.ceiling_height_m:g} m) must be above the "
                          f"camera (mount.z = {camera_z_m:g} m in {rig_name}) by more than "
                          f"{MIN_CEILING_CLEARANCE_M:g} m")
    for i, row in enumerate(site.lamps):
        if row.z_m is not None and row.z_m <= camera_z_m + MIN_CEILING_CLEARANCE_M:
            raise ConfigError(site.source, f"lamps[{i}].z",
                              f"the lamps' face ({row.z_m:g} m) must be above the camera "
                              f"(mount.z = {camera_z_m:g} m in {rig_name}) by more than "
                              f"{MIN_CEILING_CLEARANCE_M:g} m")
