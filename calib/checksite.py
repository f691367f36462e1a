"""Where on a site one frame is ambiguous: ``ceilcal check-site`` (issue 36, item 4).

A pose is valid only when the frame's evidence singles it out. This module renders,
for a grid of vehicle poses over the site, what one frame sees (every site feature
projected through the rig's camera, SPEC §1), and looks for *twins*: other poses,
farther than a tolerance, that see the same picture within a pixel tolerance.

Twin candidates come from the site's self-similarities, not from brute force: for a
pose, the site's anchor points (lights, lamp centres, block centres, marker centres,
crossings of the corridor's lines) near its view give the planar motions
``p -> R(turn) p + t`` that map one anchor onto another of the same kind, for a turn
of 0, a quarter or a half (a half turn about a corridor's centre line, a shift by
the lines' spacing or the light grid's pitch, a quarter turn of a square grid). A
candidate is kept when the anchors in view land on anchors, then tested by rendering
its picture and comparing it with the pose's (every projected point within
``tol_px`` of one of the same kind, both ways; a feature seen in one picture and not
in the other is a difference, except within ``tol_px`` of the image border).

A corridor with only ``lines_along`` never shows x: the check is then made across
the corridor only (``x_unobserved``), shifts along x are not counted as twins, and
the report says so.

Pure math: a :class:`~ceilkit.runtime.config.rig.Rig` and a
:class:`~ceilkit.runtime.config.site.Site` in, frozen dataclasses out
(:func:`check_site`). :func:`check_site_files` is the edge the command calls: it
loads the files, runs the check and writes ``check-site.png`` and
``check-site.yaml``.

Example::

    check = check_site(Rig.load("rig.yaml"), Site.load("site.yaml"))
    print("\\n".join(check.lines()))          # the text report
    check.share_ambiguous                     # of the pose cells (position x heading)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import label as label_regions
from scipy.spatial import cKDTree

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import (
    MarkerPose,
    Markers,
    Site,
    check_rig_site,
    points_in_polygon,
)
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.rotations import wrap_pi

HALF_TURN = "half turn"
QUARTER_TURN = "quarter turn"
SHIFT = "shift by a pitch"
OTHER_CELL = "another cell"
KINDS = (HALF_TURN, QUARTER_TURN, SHIFT, OTHER_CELL)
"""What kind of twin: the turn between the two poses, and for no turn how far."""

UNIQUE = "unique"
AMBIGUOUS = "ambiguous"
BLIND = "blind"
UNDERDETERMINED = "underdetermined"
STATUSES = (UNIQUE, AMBIGUOUS, BLIND, UNDERDETERMINED)
"""A pose cell's verdict: singled out; has twins; sees no feature; sees too little to
fix a pose (one point alone, or parallel lines alone: a continuum of poses)."""

TURNS_RAD = (0.0, math.pi, math.pi / 2, -math.pi / 2)
DICTIONARY = "DICT_APRILTAG_36h11"
"""The dictionary of the synthetic markers when the site has none."""

_ISO, _LINE_X, _LINE_Y, _OUTLINE = 0, 1, 2, 3   # what a sampled point belongs to
_PREFILTER_M = 0.3          # an anchor in view must land this near an anchor of its class
_BORDER_RAYS = 24           # rays per image side for the view's footprint
_PREFILTER_PER_CLASS = 8    # anchors in view per class the prefilter maps
_WORLD_STRIDE = 7           # every this many points checked in the world before rendering
_MAX_MAP_ASPECT = 8.0       # a wider site's map is drawn with y stretched
_REPORT_REGIONS = 10        # regions in the text report (the YAML holds all)
_VERIFY_MAX = 400            # ambiguous poses of a region checked again with markers
_TOP_LEVEL = 62             # the level of a segment's ends (always kept)
_CLASS_GAP = 1e4            # classes kept apart in one KD-tree (a coordinate offset)


@dataclass(frozen=True)
class CheckOptions:
    """What the check covers and how strict it is.

    Attributes:
        step_m: spacing of the positions (cells of about this size over the site's box).
        heading_step_deg: spacing of the headings (90: four per position).
        tol_px: two pictures are the same when every projected point is within this
            of one of the same kind in the other (both ways).
        min_shift_m, min_turn_deg: a twin differs from the pose by more than either.
        search_m: twins are looked for within this distance of the view's centre.
        max_range_m: features farther than this from the camera are not counted (a
            tilted camera's horizon).
        margin_m: the pose box reaches this far beyond the features' box.
        twins_per_kind: stop looking for a turn's twins after this many.
        tests_per_turn: at most this many rendered tests per turn and pose.
        marker_size_m: side of the synthetic markers of the suggestion (the site's
            marker size when it has markers).
    """

    step_m: float = 0.5
    heading_step_deg: float = 90.0
    tol_px: float = 2.0
    min_shift_m: float = 0.1
    min_turn_deg: float = 2.0
    search_m: float = 6.0
    max_range_m: float = 20.0
    margin_m: float = 0.0
    twins_per_kind: int = 1
    tests_per_turn: int = 6
    marker_size_m: float = 0.2

    def __post_init__(self) -> None:
        for name in ("step_m", "heading_step_deg", "tol_px", "search_m", "max_range_m",
                     "marker_size_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(None, name, f"expected a number > 0, found {value}")
        if self.heading_step_deg > 360.0:
            raise ConfigError(None, "heading_step_deg",
                              f"expected at most 360 degrees, found {self.heading_step_deg}")
        for name in ("margin_m", "min_shift_m", "min_turn_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(None, name, f"expected a number >= 0, found {value}")
        for name in ("twins_per_kind", "tests_per_turn"):
            if getattr(self, name) < 1:
                raise ConfigError(None, name, f"expected at least 1, found {getattr(self, name)}")


@dataclass(frozen=True)
class SiteTwin:
    """Another pose that sees the same picture: ``(x_m, y_m, yaw_rad)`` and its kind."""

    x_m: float
    y_m: float
    yaw_rad: float
    kind: str


@dataclass(frozen=True)
class PoseCell:
    """One vehicle pose of the grid and its verdict (:data:`STATUSES`)."""

    x_m: float
    y_m: float
    yaw_rad: float
    status: str
    twins: tuple[SiteTwin, ...] = ()
    n_points: int = 0          # projected feature points in the picture

    @property
    def ambiguous(self) -> bool:
        return self.status == AMBIGUOUS

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(k for k in KINDS if any(t.kind == k for t in self.twins))


@dataclass(frozen=True)
class Region:
    """A connected set of positions where some heading is ambiguous, and what would
    single it out.

    Attributes:
        box_m: ``(x_min, x_max, y_min, y_max)``, the smallest rectangle of cells covering it.
        n_positions, n_poses: its positions, and its ambiguous pose cells.
        kinds: the twin kinds met in it.
        markers_m: where the check put one synthetic marker each (``(N, 2)``): the
            region's centre, or the centres of the tiles a large region is cut into.
        singled_out: of its ambiguous pose cells checked again with the markers
            (``n_checked``: all of them, or an even sample of :data:`_VERIFY_MAX`),
            how many the markers single out.
        suggestion: the sentence of the report.
    """

    box_m: tuple[float, float, float, float]
    n_positions: int
    n_poses: int
    kinds: tuple[str, ...]
    markers_m: tuple[tuple[float, float], ...]
    singled_out: int
    n_checked: int
    suggestion: str


@dataclass(frozen=True)
class SiteCheck:
    """The result of :func:`check_site`.

    Attributes:
        box_m: ``(x_min, x_max, y_min, y_max)`` of the poses' box.
        xs_m, ys_m, yaws_rad: the grid (positions at cell centres).
        cell_m: ``(dx, dy)``, the cells' size.
        cells: one per pose, ordered x, then y, then heading.
        x_unobserved: the site has corridor lines along x and nothing else.
        regions: the ambiguous regions, largest first.
        notes: what the report should say besides the figures.
    """

    options: CheckOptions
    box_m: tuple[float, float, float, float]
    xs_m: tuple[float, ...]
    ys_m: tuple[float, ...]
    yaws_rad: tuple[float, ...]
    cell_m: tuple[float, float]
    cells: tuple[PoseCell, ...]
    x_unobserved: bool
    regions: tuple[Region, ...] = ()
    notes: tuple[str, ...] = ()

    def status_grid(self) -> np.ndarray:
        """``(nx, ny, nh)`` array of status strings."""
        return np.array([c.status for c in self.cells], dtype=object).reshape(
            len(self.xs_m), len(self.ys_m), len(self.yaws_rad))

    def share(self, status: str) -> float:
        """Share of the pose cells (the site's area times the headings) with ``status``."""
        return sum(c.status == status for c in self.cells) / max(1, len(self.cells))

    @property
    def share_ambiguous(self) -> float:
        return self.share(AMBIGUOUS)

    def share_kind(self, kind: str) -> float:
        """Share of the pose cells with a twin of ``kind``."""
        return sum(kind in c.kinds for c in self.cells) / max(1, len(self.cells))

    def share_positions_ambiguous(self) -> float:
        """Share of the site's area where at least one heading is ambiguous."""
        g = self.status_grid() == AMBIGUOUS
        return float(np.any(g, axis=2).mean()) if g.size else 0.0

    def lines(self) -> list[str]:
        """The text report."""
        o = self.options
        x0, x1, y0, y1 = self.box_m
        n = len(self.cells)
        xs = "x unobserved" if self.x_unobserved else f"x {x0:.2f}..{x1:.2f} m"
        cells = (f"cells {self.cell_m[1]:.2f} m across" if self.x_unobserved else
                 f"cells {self.cell_m[0]:.2f} x {self.cell_m[1]:.2f} m")
        out = [f"site box {xs}, y {y0:.2f}..{y1:.2f} m: {len(self.xs_m)} x {len(self.ys_m)} "
               f"positions ({cells}), {len(self.yaws_rad)} headings every "
               f"{o.heading_step_deg:g} deg: {n} poses",
               f"same picture: within {o.tol_px:g} px; a twin is > {o.min_shift_m:g} m or "
               f"> {o.min_turn_deg:g} deg away, within {o.search_m:g} m"]
        out += [f"note: {t}" for t in self.notes]
        out.append(f"ambiguous: {100 * self.share_ambiguous:.1f}% of poses, "
                   f"{100 * self.share_positions_ambiguous():.1f}% of the area (some heading)")
        for k in KINDS:
            s = self.share_kind(k)
            if s > 0:
                out.append(f"  {k}: {100 * s:.1f}% of poses")
        out.append(f"unique: {100 * self.share(UNIQUE):.1f}%, sees nothing: "
                   f"{100 * self.share(BLIND):.1f}%, too little to fix a pose: "
                   f"{100 * self.share(UNDERDETERMINED):.1f}%")
        example = next((c for c in self.cells if c.ambiguous), None)
        if example is not None:
            twins = ", ".join(f"({t.x_m:.2f}, {t.y_m:.2f}, {math.degrees(t.yaw_rad):.0f} deg; "
                              f"{t.kind})" for t in example.twins[:4])
            out.append(f"for example the pose ({example.x_m:.2f}, {example.y_m:.2f}, "
                       f"{math.degrees(example.yaw_rad):.0f} deg) looks like {twins}")
        for k, r in enumerate(self.regions[:_REPORT_REGIONS]):
            bx0, bx1, by0, by1 = r.box_m
            if self.x_unobserved:
                where = f"y {by0:.2f}..{by1:.2f} m at every x ("
            else:
                where = (f"x {bx0:.2f}..{bx1:.2f}, y {by0:.2f}..{by1:.2f} m "
                         f"({bx1 - bx0:.1f} x {by1 - by0:.1f} m; ")
            out.append(f"region {k + 1}: {where}{r.n_poses} ambiguous poses; "
                       f"{', '.join(r.kinds)})")
            out.append(f"  {r.suggestion}")
        if len(self.regions) > _REPORT_REGIONS:
            out.append(f"... and {len(self.regions) - _REPORT_REGIONS} smaller regions "
                       f"(check-site.yaml lists them all)")
        return out

    def to_dict(self) -> dict[str, Any]:
        """The figures for ``check-site.yaml``."""
        o = self.options
        return {
            "options": {f.name: getattr(o, f.name) for f in dataclasses.fields(o)},
            "box": [round(float(v), 4) for v in self.box_m],
            "positions": [len(self.xs_m), len(self.ys_m)],
            "headings_deg": [round(math.degrees(a), 3) for a in self.yaws_rad],
            "poses": len(self.cells),
            "x_unobserved": self.x_unobserved,
            "notes": list(self.notes),
            "share": {"ambiguous": round(self.share_ambiguous, 4),
                      "ambiguous_area": round(self.share_positions_ambiguous(), 4),
                      "unique": round(self.share(UNIQUE), 4),
                      "blind": round(self.share(BLIND), 4),
                      "underdetermined": round(self.share(UNDERDETERMINED), 4),
                      "by_kind": {k: round(self.share_kind(k), 4) for k in KINDS}},
            "regions": [{"box": [round(float(v), 3) for v in r.box_m],
                         "positions": r.n_positions, "ambiguous_poses": r.n_poses,
                         "kinds": list(r.kinds),
                         "markers": [[round(a, 3), round(b, 3)] for a, b in r.markers_m],
                         "singled_out": r.singled_out, "checked": r.n_checked,
                         "suggestion": r.suggestion}
                        for r in self.regions],
            "ambiguous_poses": [
                {"pose": [round(c.x_m, 3), round(c.y_m, 3), round(math.degrees(c.yaw_rad), 2)],
                 "twins": [[round(t.x_m, 3), round(t.y_m, 3),
                            round(math.degrees(t.yaw_rad), 2), t.kind] for t in c.twins]}
                for c in self.cells if c.ambiguous],
        }


# -- the site's features, sampled ----------------------------------------------------------

@dataclass(frozen=True)
class Scene:
    """The site's features as labelled points in W (lines and outlines sampled).

    Attributes:
        points_w: ``(N, 3)`` points in W (z: the ceiling's, or a hanging lamp face's),
            sorted by x.
        cls: ``(N,)`` class index into ``classes`` (``line``, ``lamp``, ``light``,
            ``block:dark``, ``marker:7``, ``marker:7:c0`` ...).
        shape: ``(N,)`` what the point belongs to: an isolated point, a line along x,
            a line along y, an outline.
        level: ``(N,)`` a line's points of level >= k are spaced ``2**k`` samples
            apart: a pose keeps the coarser levels at longer range.
        anchors_w: ``(M, 2)`` anchor points, ``anchor_cls`` their classes,
            ``anchor_z_m`` their heights, ``anchor_pitch_m`` the distance to the
            nearest anchor of the same class.
        x_unobserved: corridor lines along x and nothing else.
        lines_along_only: corridor lines along x and none across (their own
            symmetries are twin candidates besides the anchors').
    """

    classes: tuple[str, ...]
    points_w: np.ndarray
    cls: np.ndarray
    shape: np.ndarray
    level: np.ndarray
    anchors_w: np.ndarray
    anchor_cls: np.ndarray
    anchor_z_m: np.ndarray
    anchor_pitch_m: np.ndarray
    box_m: tuple[float, float, float, float]
    x_unobserved: bool
    sample_m: float
    lines_along_only: bool
    notes: tuple[str, ...] = ()


class _SceneBuilder:
    def __init__(self, ds_m: float):
        self.ds = ds_m
        self.classes: list[str] = []
        self.pts: list[np.ndarray] = []
        self.cls: list[np.ndarray] = []
        self.shape: list[np.ndarray] = []
        self.level: list[np.ndarray] = []
        self.anchors: list[tuple[float, float, int]] = []

    def cid(self, name: str) -> int:
        if name not in self.classes:
            self.classes.append(name)
        return self.classes.index(name)

    def add(self, name: str, pts_xy: np.ndarray, z: float, shape: int,
            level: np.ndarray | None = None) -> None:
        pts_xy = np.asarray(pts_xy, float).reshape(-1, 2)
        self.level.append(np.full(len(pts_xy), _TOP_LEVEL) if level is None else level)
        self.pts.append(np.column_stack([pts_xy, np.full(len(pts_xy), z)]))
        self.cls.append(np.full(len(pts_xy), self.cid(name)))
        self.shape.append(np.full(len(pts_xy), shape))

    def segment(self, name: str, a: Sequence[float], b: Sequence[float], z: float,
                shape: int) -> None:
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / self.ds)) + 1)
        s = np.linspace(0.0, 1.0, n)[:, None]
        i = np.arange(n)
        level = np.full(n, _TOP_LEVEL)
        level[1:] = np.log2(i[1:] & -i[1:]).astype(int)
        level[-1] = _TOP_LEVEL
        self.add(name, a + s * (b - a), z, shape, level)

    def outline(self, name: str, corners: np.ndarray, z: float) -> None:
        c = np.asarray(corners, float)
        for k in range(len(c)):
            self.segment(name, c[k], c[(k + 1) % len(c)], z, _OUTLINE)

    def anchor(self, name: str, xy: Sequence[float], z: float) -> None:
        self.anchors.append((float(xy[0]), float(xy[1]), self.cid(name), float(z)))


def _rect(cx: float, cy: float, length: float, width: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    offs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
    return np.array([cx, cy]) + offs @ np.array([[c, s], [-s, c]])


def _discrete_box(site: Site) -> np.ndarray | None:
    """``(K, 2)`` every point of the site's discrete features, None when there is none."""
    parts = [site.lamp_rectangles().reshape(-1, 2), np.asarray(site.lights_m).reshape(-1, 2)]
    parts += [b.corners_m for b in site.blocks]
    if site.markers is not None:
        parts += [m.corners_m() for m in site.markers.poses]
    pts = np.concatenate(parts, axis=0) if parts else np.zeros((0, 2))
    return pts if len(pts) else None


def site_box(site: Site, margin_m: float = 0.0) -> tuple[tuple[float, float, float, float], bool]:
    """The box the site's features span, and whether x is unobserved (corridor lines
    along x and nothing else). Raises a ConfigError for a site with no feature."""
    pts = _discrete_box(site)
    corridor = site.corridor
    x_unobserved = pts is None and corridor is not None and corridor.lines_across is None
    xs, ys = [], []
    if pts is not None:
        xs += [pts[:, 0].min(), pts[:, 0].max()]
        ys += [pts[:, 1].min(), pts[:, 1].max()]
    if corridor is not None:
        ys += [min(corridor.lines_along_m), max(corridor.lines_along_m)]
        if pts is None and corridor.lines_across is not None:
            a = corridor.lines_across
            length = max(4 * a.spacing_m, ys[1] - ys[0])
            xs += [a.first_m, a.first_m + math.ceil(length / a.spacing_m) * a.spacing_m]
    if not ys:
        raise ConfigError(site.source, None, "the site holds no feature to check")
    if x_unobserved:
        xs = [0.0, 0.0]
    return (min(xs) - margin_m, max(xs) + margin_m, min(ys) - margin_m,
            max(ys) + margin_m), x_unobserved


def build_scene(site: Site, ds_m: float, reach_m: float, margin_m: float = 0.0) -> Scene:
    """The site's features sampled every ``ds_m`` metres; endless lines are drawn
    ``reach_m`` beyond the poses' box."""
    box, x_unobserved = site_box(site, margin_m)
    b = _SceneBuilder(ds_m)
    H = site.ceiling_height_m
    notes = []
    xa, xb = box[0] - reach_m, box[1] + reach_m
    corridor = site.corridor
    if corridor is not None:
        ya, yb = min(corridor.lines_along_m), max(corridor.lines_along_m)
        for y in corridor.lines_along_m:
            b.segment("line", (xa, y), (xb, y), H, _LINE_X)
        if corridor.lines_across is not None:
            a = corridor.lines_across
            k0 = math.floor((xa - a.first_m) / a.spacing_m)
            k1 = math.ceil((xb - a.first_m) / a.spacing_m)
            for k in range(k0, k1 + 1):
                x = a.first_m + k * a.spacing_m
                b.segment("line", (x, ya), (x, yb), H, _LINE_Y)
                for y in corridor.lines_along_m:
                    b.anchor("crossing", (x, y), H)
        if _discrete_box(site) is None and corridor.lines_across is not None:
            notes.append(f"the lines repeat without end along x: checked over x "
                         f"{box[0]:.2f}..{box[1]:.2f} m")
        if x_unobserved:
            notes.append("the site has corridor lines along x only: x is never observed "
                         "(the corridor method gives heading and lateral position); shifts "
                         "along x are not counted as twins, the check runs across the corridor")
    for row in site.lamps:
        z = row.face_z_m(H)
        for rect, centre in zip(row.rectangles(), row.centres(), strict=True):
            b.outline("lamp", rect, z)
            b.anchor("lamp", centre, z)
    size = getattr(site, "light_size_m", None)
    light_yaw = float(getattr(site, "light_yaw_rad", 0.0) or 0.0)   # SPEC §2 light_yaw
    for xy in np.asarray(site.lights_m).reshape(-1, 2):
        if size is not None:
            b.outline("light", _rect(xy[0], xy[1], size[0], size[1], light_yaw), H)
        else:
            b.add("light", xy[None], H, _ISO)
        b.anchor("light", xy, H)
    for blk in site.blocks:
        name = f"block:{blk.appearance or 'plain'}"
        b.outline(name, blk.corners_m, H)
        b.anchor(name, blk.corners_m.mean(axis=0), H)
    if site.markers is not None:
        for m in site.markers.poses:
            corners = m.corners_m()
            b.outline(f"marker:{m.id}", corners, H)
            b.add(f"marker:{m.id}:c0", corners[:1], H, _ISO)
            b.anchor(f"marker:{m.id}", (m.x_m, m.y_m), H)
    anchors = np.array(b.anchors, float).reshape(-1, 4)
    if site.ignore_m:
        anchors = anchors[~site.ignored(anchors[:, :2])]
    pitch = np.full(len(anchors), np.inf)
    for c in np.unique(anchors[:, 2]) if len(anchors) else ():
        sel = np.flatnonzero(anchors[:, 2] == c)
        if len(sel) > 1:
            d, _ = cKDTree(anchors[sel, :2]).query(anchors[sel, :2], k=2)
            pitch[sel] = d[:, 1]
    pts = np.concatenate(b.pts, axis=0) if b.pts else np.zeros((0, 3))
    cls = np.concatenate(b.cls).astype(int) if b.cls else np.zeros(0, int)
    shape = np.concatenate(b.shape).astype(int) if b.shape else np.zeros(0, int)
    level = np.concatenate(b.level).astype(int) if b.level else np.zeros(0, int)
    if site.ignore_m:                  # what no method uses is not seen either
        kept = ~site.ignored(pts[:, :2])
        pts, cls, shape, level = pts[kept], cls[kept], shape[kept], level[kept]
    order = np.argsort(pts[:, 0], kind="stable")       # by x: a pose selects a slab
    return Scene(tuple(b.classes), pts[order], cls[order], shape[order], level[order],
                 anchors[:, :2].copy(), anchors[:, 2].astype(int),
                 anchors[:, 3].copy(), pitch, box, x_unobserved, ds_m,
                 corridor is not None and corridor.lines_across is None, tuple(notes))


# -- what one frame sees -----------------------------------------------------------------

@dataclass(frozen=True)
class View:
    """The camera's view of the ceiling, in V: a disc holding its footprint."""

    centre_v: np.ndarray     # (2,) the footprint's centre in V
    radius_m: float
    inner_radius_m: float    # the largest disc about V's origin the camera sees whole
    px_per_m: float          # the most pixels a metre of the ceiling spans


def camera_view(rig: Rig, heights_m: Sequence[float], max_range_m: float) -> View:
    """Where the camera's image border meets the ceiling planes ``heights_m``."""
    cam, mount = rig.camera, rig.mount
    w, h = cam.width, cam.height
    t = np.linspace(0.0, 1.0, _BORDER_RAYS)
    border = np.concatenate([np.column_stack([t * (w - 1), np.zeros_like(t)]),
                             np.column_stack([np.full_like(t, w - 1), t * (h - 1)]),
                             np.column_stack([(1 - t) * (w - 1), np.full_like(t, h - 1)]),
                             np.column_stack([np.zeros_like(t), (1 - t) * (h - 1)])])
    centre_px = np.array([[cam.cx, cam.cy]])
    rays_c, ok = cam.unit_rays(np.concatenate([border, centre_px]), 0.5)
    rays_v = rays_c @ mount.R_vehicle_cam.T
    foot = []
    for H in heights_m:
        dz = H - mount.z_m
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(rays_v[:, 2] > 1e-9, dz / rays_v[:, 2], np.inf)
        s = np.minimum(s, max_range_m)
        foot.append(mount.t_vehicle_cam[:2] + s[:, None] * rays_v[:, :2])
    pts = np.concatenate(foot)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    radius = float(np.max(np.linalg.norm(pts - centre, axis=1)))
    # the disc about V's origin inside every plane's footprint (0 when it is not seen)
    inner = math.inf
    for f in foot:
        poly = f[:-1]
        if not points_in_polygon(np.zeros((1, 2)), poly)[0]:
            inner = 0.0
            break
        inner = min(inner, float(np.min(np.linalg.norm(poly, axis=1))))
    dz_min = min(heights_m) - mount.z_m
    return View(centre, radius, 0.0 if not math.isfinite(inner) else inner,
                max(cam.fx, cam.fy) / dz_min * 1.2)


@dataclass
class Picture:
    """What one pose sees: projected points and their classes; ``inner`` marks those
    not within ``tol_px`` of the image border (they must be matched)."""

    px: np.ndarray
    cls: np.ndarray
    shape: np.ndarray
    inner: np.ndarray
    index: np.ndarray          # the points' indices in the scene
    range_m: np.ndarray        # their distance from the camera
    _tree: Any = None

    def tree(self) -> cKDTree:
        """A KD-tree of the points, classes kept apart (built once)."""
        if self._tree is None:
            self._tree = cKDTree(np.column_stack([self.px, self.cls * _CLASS_GAP]))
        return self._tree

    @property
    def n(self) -> int:
        return int(self.px.shape[0])


class Renderer:
    """Renders pictures of a scene through a rig; compares them."""

    def __init__(self, rig: Rig, scene: Scene, view: View, options: CheckOptions):
        self.rig, self.scene, self.view, self.o = rig, scene, view, options
        self.R_vc = rig.mount.R_vehicle_cam
        self.t_vc = rig.mount.t_vehicle_cam
        self.ds = scene.sample_m
        self.near_m = min(float(np.min(scene.points_w[:, 2])) if len(scene.points_w) else
                          math.inf, math.inf) - rig.mount.z_m
        self.select_r = view.radius_m + 2 * options.tol_px / view.px_per_m + 0.05

    def footprint_centre(self, x: float, y: float, yaw: float) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        v = self.view.centre_v
        return np.array([x + c * v[0] - s * v[1], y + s * v[0] + c * v[1]])

    def render(self, x: float, y: float, yaw: float) -> Picture:
        sc = self.scene
        fc = self.footprint_centre(x, y, yaw)
        r = self.select_r
        lo, hi = np.searchsorted(sc.points_w[:, 0], (fc[0] - r, fc[0] + r))
        slab = sc.points_w[lo:hi]
        d2 = (slab[:, 0] - fc[0]) ** 2 + (slab[:, 1] - fc[1]) ** 2
        sel = lo + np.flatnonzero(d2 <= r * r)
        c, s = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        R_wc = Rz @ self.R_vc
        cam_w = Rz @ self.t_vc + np.array([x, y, 0.0])
        # a metre spans fewer pixels farther away: sample spacing may grow with range
        pw = sc.points_w[sel]
        rng = np.sqrt((pw[:, 0] - cam_w[0]) ** 2 + (pw[:, 1] - cam_w[1]) ** 2
                      + (pw[:, 2] - cam_w[2]) ** 2)
        need = np.floor(np.log2(np.maximum(rng / self.near_m, 1.0))).astype(int)
        sel = sel[sc.level[sel] >= need]
        pw = sc.points_w[sel]
        pc = (pw - cam_w) @ R_wc
        front = (pc[:, 2] > 1e-6) & (np.linalg.norm(pc, axis=1) <= self.o.max_range_m)
        sel, pc = sel[front], pc[front]
        px = self.rig.camera.project(pc)
        ok = self.rig.camera.in_image(px) & np.all(np.isfinite(px), axis=1)
        sel, px, pc = sel[ok], px[ok], pc[ok]
        # one point per class and half-tolerance pixel cell (far lines crowd together)
        cell = np.floor(px / (0.5 * self.o.tol_px)).astype(np.int64) + 2
        key = (sc.cls[sel].astype(np.int64) * 1_000_003 + cell[:, 0]) * 1_000_003 + cell[:, 1]
        _, first = np.unique(key, return_index=True)
        sel, px, pc = sel[first], px[first], pc[first]
        inner = self.rig.camera.in_image(px, self.o.tol_px)
        return Picture(px, sc.cls[sel], sc.shape[sel], inner, sel, np.linalg.norm(pc, axis=1))

    def anchors_in_view(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Indices of the scene's anchors inside the image (by ``4 tol_px``), on the
        ceiling plane."""
        sc = self.scene
        if len(sc.anchors_w) == 0:
            return np.zeros(0, int)
        fc = self.footprint_centre(x, y, yaw)
        near = np.flatnonzero(np.linalg.norm(sc.anchors_w - fc, axis=1) <= self.select_r)
        c, s = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pw = np.column_stack([sc.anchors_w[near], sc.anchor_z_m[near]])
        pc = (pw - (Rz @ self.t_vc + np.array([x, y, 0.0]))) @ (Rz @ self.R_vc)
        front = (pc[:, 2] > 1e-6) & (np.linalg.norm(pc, axis=1) <= self.o.max_range_m)
        near, pc = near[front], pc[front]
        px = self.rig.camera.project(pc)
        ok = self.rig.camera.in_image(px, 4 * self.o.tol_px) & np.all(np.isfinite(px), axis=1)
        return near[ok]

    def same(self, a: Picture, b: Picture) -> bool:
        """Whether two pictures are the same within ``tol_px`` (every inner point of
        each has a point of its class in the other). A sample of ``a``'s points is
        tried first."""
        if a.n == 0 or b.n == 0:
            return not a.inner.any() and not b.inner.any()
        tol = self.o.tol_px
        for p, q, stride in ((a, b, _WORLD_STRIDE), (a, b, 1), (b, a, 1)):
            idx = np.flatnonzero(p.inner)[::stride]
            if len(idx) == 0:
                continue
            d, _ = q.tree().query(np.column_stack([p.px[idx], p.cls[idx] * _CLASS_GAP]),
                                  distance_upper_bound=tol)
            if not np.all(np.isfinite(d)):
                return False
        return True


def _status_of(pic: Picture, x_unobserved: bool) -> str | None:
    """BLIND or UNDERDETERMINED for a picture that cannot fix a pose, else None."""
    if pic.n == 0:
        return BLIND
    shapes = set(pic.shape.tolist())
    if _OUTLINE in shapes:
        return None
    lines = shapes & {_LINE_X, _LINE_Y}
    n_iso = int(np.count_nonzero(pic.shape == _ISO))
    if x_unobserved:
        return None
    if n_iso == 0 and len(lines) < 2:
        return UNDERDETERMINED
    if n_iso == 1 and not lines:
        return UNDERDETERMINED
    return None


# -- twins --------------------------------------------------------------------------------

def _rot2(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _kind(turn: float, shift_m: float, pitch_m: float) -> str:
    if abs(abs(turn) - math.pi) < 1e-6:
        return HALF_TURN
    if abs(abs(turn) - math.pi / 2) < 1e-6:
        return QUARTER_TURN
    return SHIFT if shift_m <= 1.5 * pitch_m + 1e-6 else OTHER_CELL


class TwinFinder:
    """Twin candidates of a pose from the scene's self-similarities, each tested by
    rendering."""

    def __init__(self, renderer: Renderer):
        self.r = renderer
        sc = renderer.scene
        self.sc = sc
        self.trees = {c: cKDTree(sc.anchors_w[sc.anchor_cls == c])
                      for c in np.unique(sc.anchor_cls)}
        self.f_min = min(renderer.rig.camera.fx, renderer.rig.camera.fy)
        self.world_tree = cKDTree(np.column_stack([sc.points_w[:, :2], sc.points_w[:, 2]
                                                   + sc.cls * _CLASS_GAP]))
        # lines along x and none across: their own symmetries are candidates too
        self.along_y = (np.unique(sc.points_w[sc.shape == _LINE_X, 1])
                        if sc.lines_along_only else None)

    def far_enough(self, p: np.ndarray, yaw: float, q: np.ndarray, yaw2: float) -> bool:
        o = self.r.o
        d = abs(q[1] - p[1]) if self.sc.x_unobserved else float(np.linalg.norm(q - p))
        return d > o.min_shift_m or abs(wrap_pi(yaw2 - yaw)) > math.radians(o.min_turn_deg)

    def _lines_only(self, x: float, y: float, yaw: float, turns: Sequence[float]
                    ) -> Iterator[tuple[float, np.ndarray, float]]:
        """The corridor's lines along x map onto themselves by a shift across (x kept),
        or a half turn about the middle of two of them (about the view's centre)."""
        # x unobserved: the twin's x is the pose's (any x sees the same endless lines)
        fx = x if self.sc.x_unobserved else self.r.footprint_centre(x, y, yaw)[0]
        ys = self.along_y
        for turn in turns:
            if turn not in (0.0, math.pi):
                continue
            for yi in ys:
                for yj in ys:
                    q = (np.array([x, y + yj - yi]) if turn == 0.0 else
                         np.array([2 * fx - x, yi + yj - y]))
                    yield turn, q, math.inf

    def candidates(self, x: float, y: float, yaw: float, turns: Sequence[float]
                   ) -> Iterator[tuple[float, np.ndarray, float]]:
        """``(turn, twin position, pitch)`` of the pose, per turn nearest first: the
        motions mapping the anchor nearest the view's centre onto another of its class,
        kept when the anchors in view land on anchors of their class (the rarest
        classes first: a marker in view rejects every candidate but itself)."""
        sc = self.sc
        if self.along_y is not None:       # after the anchors' (they cover a grid's lines)
            tail = self._lines_only(x, y, yaw, turns)
        else:
            tail = iter(())
        if sc.x_unobserved or len(sc.anchors_w) == 0:
            yield from tail
            return
        p = np.array([x, y])
        fc = self.r.footprint_centre(x, y, yaw)
        ia = int(np.argmin(np.linalg.norm(sc.anchors_w - fc, axis=1)))
        a, ca, pitch = sc.anchors_w[ia], sc.anchor_cls[ia], sc.anchor_pitch_m[ia]
        tree = self.trees[ca]
        bs = np.asarray(tree.data[tree.query_ball_point(a, self.r.o.search_m)],
                        float).reshape(-1, 2)
        bs = bs[np.argsort(np.linalg.norm(bs - a, axis=1), kind="stable")]
        seen = self.r.anchors_in_view(x, y, yaw)
        groups = []
        for c in np.unique(sc.anchor_cls[seen]) if len(seen) else ():
            mine = seen[sc.anchor_cls[seen] == c]
            mine = mine[np.argsort(np.linalg.norm(sc.anchors_w[mine] - fc, axis=1))]
            groups.append((self.trees[c].n, c, sc.anchors_w[mine[:_PREFILTER_PER_CLASS]]))
        groups.sort(key=lambda g: g[0])
        # the pitch of the coarsest repeating feature in view names a shift's kind
        pitches = [float(sc.anchor_pitch_m[seen][sc.anchor_cls[seen] == c].max())
                   for _, c, _ in groups]
        pitches = [v for v in pitches if math.isfinite(v)]
        if pitches:
            pitch = max(pitches)
        for turn in turns:
            R = _rot2(turn)
            ts = bs - R @ a                                    # (B, 2)
            keep = np.ones(len(ts), bool)
            for _, c, pts in groups:
                pts = pts @ R.T
                mapped = (ts[keep, None, :] + pts[None]).reshape(-1, 2)
                d, _ = self.trees[c].query(mapped, distance_upper_bound=_PREFILTER_M)
                ok = np.all(np.isfinite(d).reshape(-1, len(pts)), axis=1)
                keep[np.flatnonzero(keep)[~ok]] = False
                if not keep.any():
                    break
            qs = ts[keep] + R @ p
            for q in qs[np.argsort(np.linalg.norm(qs - p, axis=1), kind="stable")]:
                yield turn, q, pitch
        yield from tail

    def world_match(self, pic: Picture, p: np.ndarray, yaw: float, q: np.ndarray,
                    turn: float) -> bool:
        """A cheap test before rendering: a sample of the points the pose sees, moved
        by the motion from the pose to ``q``, lies on features of their class (within
        a loose world tolerance that grows with range)."""
        idx = np.flatnonzero(pic.inner)[::_WORLD_STRIDE]
        if len(idx) == 0:
            return True
        R = _rot2(turn)
        t = q - R @ p
        pw = self.sc.points_w[pic.index[idx]]
        moved = np.column_stack([pw[:, :2] @ R.T + t, pw[:, 2] + pic.cls[idx] * _CLASS_GAP])
        tol = 3 * self.r.o.tol_px * pic.range_m[idx] / self.f_min + 2 * self.r.ds + 0.01
        d, _ = self.world_tree.query(moved, distance_upper_bound=float(tol.max()))
        return bool(np.all(d <= tol))

    def twins(self, x: float, y: float, yaw: float, pic: Picture) -> tuple[SiteTwin, ...]:
        o = self.r.o
        p = np.array([x, y])
        found: list[SiteTwin] = []
        turns = (0.0, math.pi) if self.sc.x_unobserved else TURNS_RAD
        tested = dict.fromkeys(turns, 0)
        hits = dict.fromkeys(turns, 0)
        done: list[np.ndarray] = []
        for turn, q, pitch in self.candidates(x, y, yaw, turns):
            yaw2 = wrap_pi(yaw + turn)
            if tested[turn] >= o.tests_per_turn or hits[turn] >= o.twins_per_kind:
                continue
            if not self.far_enough(p, yaw, q, yaw2):
                continue
            qa = np.array([q[0], q[1], yaw2])
            if any(np.linalg.norm(qa[:2] - s[:2]) < 1e-6 and abs(s[2] - yaw2) < 1e-6
                   for s in done):
                continue
            done.append(qa)
            tested[turn] += 1
            if not self.sc.x_unobserved and not self.world_match(pic, p, yaw, q, turn):
                continue
            if self.r.same(pic, self.r.render(q[0], q[1], yaw2)):
                hits[turn] += 1
                found.append(SiteTwin(float(q[0]), float(q[1]), yaw2,
                                  _kind(turn, float(np.linalg.norm(q - p)), pitch)))
        return tuple(found)


# -- the check ----------------------------------------------------------------------------

def _grid(lo: float, hi: float, step: float) -> tuple[np.ndarray, float]:
    n = max(1, int(math.ceil((hi - lo) / step - 1e-9)))
    size = (hi - lo) / n if hi > lo else step
    return lo + size * (np.arange(n) + 0.5) if hi > lo else np.array([lo]), size


def _heights(site: Site) -> list[float]:
    return sorted({site.ceiling_height_m} | {r.face_z_m(site.ceiling_height_m)
                                             for r in site.lamps})


def _prepare(rig: Rig, site: Site, options: CheckOptions) -> tuple[Renderer, TwinFinder]:
    view = camera_view(rig, _heights(site), options.max_range_m)
    ds = options.tol_px / view.px_per_m
    reach = view.radius_m + 2 * abs(view.centre_v).max() + options.search_m + 1.0
    scene = build_scene(site, ds, reach, options.margin_m)
    renderer = Renderer(rig, scene, view, options)
    return renderer, TwinFinder(renderer)


def _check_poses(finder: TwinFinder, poses: Sequence[tuple[float, float, float]]
                 ) -> list[PoseCell]:
    r = finder.r
    out = []
    for x, y, yaw in poses:
        pic = r.render(x, y, yaw)
        status = _status_of(pic, r.scene.x_unobserved)
        twins: tuple[SiteTwin, ...] = ()
        if status is None:
            twins = finder.twins(x, y, yaw, pic)
            status = AMBIGUOUS if twins else UNIQUE
        out.append(PoseCell(float(x), float(y), float(yaw), status, twins, pic.n))
    return out


def check_site(rig: Rig, site: Site, options: CheckOptions = CheckOptions(), *,
               suggest: bool = True) -> SiteCheck:
    """Where on ``site`` one frame of ``rig`` is ambiguous, with which twins, and (with
    ``suggest``) what would single each ambiguous region out.

    Raises:
        ConfigError: the rig does not fit the site, the site holds no feature, or an
            option is out of range.
    """
    check_rig_site(rig, site)
    site = site.without_ignored()
    renderer, finder = _prepare(rig, site, options)
    scene = renderer.scene
    box = scene.box_m
    xs, dx = _grid(box[0], box[1], options.step_m)
    ys, dy = _grid(box[2], box[3], options.step_m)
    n_h = max(1, int(round(360.0 / options.heading_step_deg)))
    yaws = np.array([wrap_pi(k * 2 * math.pi / n_h) for k in range(n_h)])
    poses = [(x, y, a) for x in xs for y in ys for a in yaws]
    cells = _check_poses(finder, poses)
    notes = list(scene.notes)
    if scene.x_unobserved:
        dx = 0.0
    result = SiteCheck(options, box, tuple(float(v) for v in xs), tuple(float(v) for v in ys),
                       tuple(float(a) for a in yaws), (dx, dy), tuple(cells),
                       scene.x_unobserved, (), tuple(notes))
    if not suggest:
        return result
    regions = _regions(result, rig, site, renderer.view)
    return dataclasses.replace(result, regions=tuple(regions))


# -- what would break it ------------------------------------------------------------------

def _marker_tile_m(view: View, marker_size_m: float) -> float:
    """The side of a square in which one marker is seen from every position at every
    heading (the camera sees a disc about the vehicle); 0 when there is none."""
    r = view.inner_radius_m - marker_size_m / math.sqrt(2)
    return max(0.0, math.sqrt(2) * r)


def with_markers(site: Site, centres_m: Sequence[tuple[float, float]], size_m: float
                 ) -> Site:
    """``site`` with one synthetic marker (a new id, yaw 0) at each centre."""
    markers = site.markers
    base = markers.poses if markers is not None else ()
    first = 1 + max((p.id for p in base), default=-1)
    size = markers.size_m if markers is not None else size_m
    poses = base + tuple(MarkerPose(first + k, float(x), float(y), 0.0, size)
                         for k, (x, y) in enumerate(centres_m))
    dictionary = markers.dictionary if markers is not None else DICTIONARY
    return dataclasses.replace(site, markers=Markers(dictionary, size, poses))


def _regions(check: SiteCheck, rig: Rig, site: Site, view: View) -> list[Region]:
    grid = check.status_grid() == AMBIGUOUS
    pos = np.any(grid, axis=2)
    if not pos.any():
        return []
    labels, n = label_regions(pos)
    xs, ys = np.array(check.xs_m), np.array(check.ys_m)
    dx, dy = check.cell_m
    o = check.options
    size = site.markers.size_m if site.markers is not None else o.marker_size_m
    tile = _marker_tile_m(view, size)
    cells = np.array(check.cells, dtype=object).reshape(grid.shape)
    out = []
    for k in range(1, n + 1):
        ii, jj = np.nonzero(labels == k)
        box = (float(xs[ii].min() - dx / 2), float(xs[ii].max() + dx / 2),
               float(ys[jj].min() - dy / 2), float(ys[jj].max() + dy / 2))
        amb = [c for i, j in zip(ii, jj, strict=True) for c in cells[i, j] if c.ambiguous]
        kinds = tuple(kd for kd in KINDS if any(kd in c.kinds for c in amb))
        w, h = box[1] - box[0], box[3] - box[2]
        if tile > 0:
            nx, ny = max(1, math.ceil(w / tile - 1e-9)), max(1, math.ceil(h / tile - 1e-9))
        else:   # the camera does not see above the vehicle: one marker per view's width
            span = max(view.radius_m, o.step_m)
            nx, ny = max(1, math.ceil(w / span - 1e-9)), max(1, math.ceil(h / span - 1e-9))
        tx, ty = w / nx, h / ny
        centres = [(box[0] + tx * (a + 0.5), box[2] + ty * (b + 0.5))
                   for a in range(nx) for b in range(ny)]
        # keep the tiles that hold an ambiguous position
        amb_xy = np.array([[c.x_m, c.y_m] for c in amb])
        centres = [cxy for cxy in centres
                   if np.any((np.abs(amb_xy[:, 0] - cxy[0]) <= tx / 2 + 1e-9)
                             & (np.abs(amb_xy[:, 1] - cxy[1]) <= ty / 2 + 1e-9))]
        if check.x_unobserved:    # a marker every tile along the endless corridor
            span = tile if tile > 0 else max(view.radius_m, o.step_m)
            reach = math.ceil((view.radius_m + abs(float(view.centre_v[0]))) / span)
            centres = [(k * span, c[1]) for c in centres for k in range(-reach, reach + 1)]
        _, finder = _prepare(rig, with_markers(site, centres, size), o)
        sample = amb if len(amb) <= _VERIFY_MAX else \
            [amb[int(i)] for i in np.linspace(0, len(amb) - 1, _VERIFY_MAX)]
        again = _check_poses(finder, [(c.x_m, c.y_m, c.yaw_rad) for c in sample])
        singled = sum(c.status == UNIQUE for c in again)
        what = "one marker (or any asymmetric feature)"
        if check.x_unobserved:
            text = (f"{what} every {span:.1f} m along the corridor, at y "
                    f"{', '.join(sorted({f'{c[1]:.2f}' for c in centres}))}, would single "
                    f"it out")
        elif len(centres) == 1:
            # anywhere: seen from every position of the region wherever it is put
            anywhere = tile > 0 and math.hypot(w, h) <= view.inner_radius_m - size / math.sqrt(2)
            where = "anywhere in this region" if anywhere else \
                f"at its centre ({centres[0][0]:.2f}, {centres[0][1]:.2f})"
            text = f"{what} {where} would single it out"
        else:
            text = (f"{len(centres)} markers (or asymmetric features), one in each "
                    f"{tx:.1f} x {ty:.1f} m tile of it, would single it out")
        if tile <= 0:
            text += " (the camera does not see above the vehicle: a marker is seen only " \
                    "from the poses that face it)"
        of = (f"{singled} of {len(amb)} ambiguous poses" if len(sample) == len(amb) else
              f"{singled} of {len(sample)} ambiguous poses (an even sample of {len(amb)})")
        at = "at the region's centre" if len(centres) == 1 else "at the tiles' centres"
        text += f"; checked with synthetic markers {at}: {of} singled out"
        out.append(Region(box, int(len(ii)), len(amb), kinds,
                          tuple((float(a), float(b)) for a, b in centres), singled,
                          len(sample), text))
    out.sort(key=lambda r: -r.n_positions)
    return out


# -- files: what the command calls ----------------------------------------------------------

OUTPUT_FILES = ("check-site.png", "check-site.yaml")


def map_png(check: SiteCheck, site: Site) -> bytes:
    """The site map with its features and the ambiguous cells coloured by kind."""
    from ceilkit.runtime.viz.plots import draw_site, figure_png, pyplot

    plt = pyplot()
    x0, x1, y0, y1 = check.box_m
    if check.x_unobserved:    # one column stands for every x: draw it as a band
        reach = max([3.0] + [abs(m[0]) + 1.0 for r in check.regions for m in r.markers_m])
        x0, x1 = -reach, reach
    w = max(x1 - x0, 1.0)
    h = max(y1 - y0, 1.0)
    stretch = w / h > _MAX_MAP_ASPECT      # a long corridor: y drawn stretched
    fig, ax = plt.subplots(figsize=(12.0, 4.0 if stretch else
                                    min(10.0, max(3.0, 12.0 * h / w + 1.5))))
    colours = {HALF_TURN: "tab:red", QUARTER_TURN: "tab:orange", SHIFT: "tab:blue",
               OTHER_CELL: "tab:purple", BLIND: "0.85", UNDERDETERMINED: "0.7"}
    dx, dy = check.cell_m
    if check.x_unobserved:
        dx = x1 - x0
    grid = np.array(check.cells, dtype=object).reshape(len(check.xs_m), len(check.ys_m),
                                                       len(check.yaws_rad))
    used = set()
    for i, x in enumerate(check.xs_m):
        for j, y in enumerate(check.ys_m):
            cs = grid[i, j]
            amb = [c for c in cs if c.ambiguous]
            if amb:
                kind = next(k for k in KINDS if any(k in c.kinds for c in amb))
                alpha = 0.25 + 0.5 * len(amb) / len(cs)
            elif all(c.status == BLIND for c in cs):
                kind, alpha = BLIND, 0.6
            elif any(c.status in (BLIND, UNDERDETERMINED) for c in cs):
                kind, alpha = UNDERDETERMINED, 0.5
            else:
                continue
            ax.add_patch(plt.Rectangle((x - dx / 2, y - dy / 2), dx, dy, color=colours[kind],
                                       alpha=alpha, lw=0,
                                       label=None if kind in used else kind))
            used.add(kind)
    draw_site(ax, site)
    corridor = site.corridor
    if corridor is not None and corridor.lines_across is not None:
        a = corridor.lines_across
        ya, yb = min(corridor.lines_along_m), max(corridor.lines_along_m)
        k0 = math.floor((x0 - 0.5 - a.first_m) / a.spacing_m)
        k1 = math.ceil((x1 + 0.5 - a.first_m) / a.spacing_m)
        for k in range(k0, k1 + 1):
            xk = a.first_m + k * a.spacing_m
            ax.plot([xk, xk], [ya, yb], color="0.75", lw=0.6)
    for k, r in enumerate(check.regions):
        bx0, bx1, by0, by1 = r.box_m
        if check.x_unobserved:
            bx0, bx1 = x0, x1
        ax.add_patch(plt.Rectangle((bx0, by0), bx1 - bx0, by1 - by0, fill=False,
                                   ec="black", lw=1, ls="--"))
        if r.markers_m:
            m = np.array(r.markers_m)
            ax.scatter(m[:, 0], m[:, 1], marker="s", s=18, color="green",
                       label="suggested marker" if k == 0 else None)
    pad = 0.5
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("auto" if stretch else "equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m, stretched)" if stretch else "y (m)")
    ax.set_title(f"check-site: {100 * check.share_ambiguous:.0f}% of poses ambiguous "
                 f"(colour: twin kind; darker: more headings)"
                 + ("; x unobserved: every x alike" if check.x_unobserved else ""))
    ax.legend(loc="upper right", fontsize=7)
    return figure_png(fig)


def check_site_files(rig_path: str | Path, site_path: str | Path, out: str | Path | None = None,
                     options: CheckOptions = CheckOptions(), force: bool = False) -> SiteCheck:
    """Load the rig and the site, check, and with ``out`` write ``check-site.png`` and
    ``check-site.yaml`` there (the folder made if missing, locked while written:
    :func:`~ceilkit.runtime.io.outputs.claim_outputs`).

    Raises:
        ConfigError: a bad file or option; an output file that exists without
            ``force`` (nothing is overwritten), or that is the rig or the site.
        OutputError: an output that cannot be written; another run writing ``out``.
    """
    import contextlib

    from ceilkit.runtime.config.yaml import atomic_write_bytes, atomic_write_text, dump_yaml
    from ceilkit.runtime.errors import OutputError
    from ceilkit.runtime.io.outputs import claim_outputs

    rig, site = Rig.load(rig_path), Site.load(site_path)
    if out is None:
        return check_site(rig, site, options)
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise OutputError(folder, "is a file; expected a folder")
    paths = [folder / n for n in OUTPUT_FILES]
    with contextlib.ExitStack() as locked:
        claim_outputs({"out": paths}, folders={"out": [folder]},
                      inputs=[rig_path, site_path], force=force, stack=locked)
        check = check_site(rig, site, options)
        from ceilkit.calib.workflow import provenance_header

        header = provenance_header("ceilcal check-site",
                                   [f"rig: {rig_path}", f"site: {site_path}"])
        atomic_write_bytes(paths[0], map_png(check, site))
        atomic_write_text(paths[1], dump_yaml(check.to_dict(), header))
    return check


__all__ = ["CheckOptions", "PoseCell", "Region", "SiteCheck", "SiteTwin", "check_site",
           "check_site_files", "map_png", "with_markers", "KINDS", "STATUSES"]
