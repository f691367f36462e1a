"""The site: what is on the ceiling, in the world frame W (SPEC §2, ``site.yaml``).

Every section is optional; which ones are present decides which estimators can run.
Lamps are rectangles whose long side runs along W's x: a row of ``count`` lamps,
the first centred at ``(x, y)``, the next ones every ``pitch`` metres along +x.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ceilkit.runtime.config.yaml import Node, atomic_write_text, dump_yaml, load_yaml
from ceilkit.runtime.errors import ConfigError

SITE_KEYS = ("ceiling_height", "corridor", "lamps", "lights", "blocks")
LAMP_KEYS = ("x", "y", "length", "width", "pitch", "count")


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
    x_m: float
    y_m: float
    length_m: float
    width_m: float
    pitch_m: float = 0.0
    count: int = 1

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
    id: str
    corners_m: np.ndarray  # (4, 2) x, y in W


@dataclass(frozen=True)
class Site:
    ceiling_height_m: float
    corridor: Corridor | None = None
    lamps: tuple[LampRow, ...] = ()
    lights_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    blocks: tuple[Block, ...] = ()
    source: str | None = None

    def has_section(self, name: str) -> bool:
        """Whether the site holds section ``name`` (``corridor``, ``lights``, ``blocks``),
        non-empty: the estimators that need it can run."""
        present = {"corridor": self.corridor is not None, "lights": self.has_lights,
                   "blocks": bool(self.blocks)}
        return present.get(name, False)

    @property
    def has_lights(self) -> bool:
        return self.lights_m.shape[0] > 0

    def lamp_rectangles(self) -> np.ndarray:
        """``(N, 4, 2)`` every lamp's corners in W."""
        if not self.lamps:
            return np.zeros((0, 4, 2))
        return np.concatenate([row.rectangles() for row in self.lamps], axis=0)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"ceiling_height": float(self.ceiling_height_m)}
        if self.corridor is not None:
            c: dict[str, Any] = {"lines_along": [float(v) for v in self.corridor.lines_along_m]}
            if self.corridor.lines_across is not None:
                c["lines_across"] = {"first": float(self.corridor.lines_across.first_m),
                                     "spacing": float(self.corridor.lines_across.spacing_m)}
            d["corridor"] = c
        if self.lamps:
            d["lamps"] = [{"x": r.x_m, "y": r.y_m, "length": r.length_m, "width": r.width_m,
                           "pitch": r.pitch_m, "count": r.count} for r in self.lamps]
        if self.has_lights:
            d["lights"] = [[float(a), float(b)] for a, b in self.lights_m]
        if self.blocks:
            d["blocks"] = [{"id": b.id, "corners": [[float(a), float(c)] for a, c in
                                                    b.corners_m]} for b in self.blocks]
        return d

    def save(self, path: str | Path, header: str = "") -> None:
        atomic_write_text(path, dump_yaml(self.to_dict(), header))

    @classmethod
    def load(cls, path: str | Path) -> Site:
        return cls.from_node(load_yaml(path), str(path))

    @classmethod
    def from_node(cls, node: Node, source: str | None = None) -> Site:
        node.mapping(SITE_KEYS, required=("ceiling_height",))
        height = node.get("ceiling_height").number(0.0, 1000.0, lo_open=True, what=" m")
        corridor = None
        if node.has("corridor"):
            cn = node.get("corridor").mapping(("lines_along", "lines_across"),
                                              required=("lines_along",))
            an = cn.get("lines_along")
            along = an.numbers()
            if not along:
                raise an.error("expected at least one line")
            if len(set(along)) != len(along):
                raise an.error("two lines at the same y")
            across = None
            if cn.has("lines_across"):
                xn = cn.get("lines_across").mapping(("first", "spacing"),
                                                    required=("spacing",))
                across = AcrossLines(xn.get("first", 0.0).number(),
                                     xn.get("spacing").number(0.0, None, lo_open=True,
                                                              what=" m"))
            corridor = Corridor(tuple(sorted(along)), across)
        lamps = []
        if node.has("lamps"):
            for ln in node.get("lamps").items():
                ln.mapping(LAMP_KEYS, required=("x", "y", "length", "width"))
                count = ln.get("count", 1).integer(1, 100_000)
                pitch = ln.get("pitch", 0.0).number(0.0, None, what=" m")
                length = ln.get("length").number(0.0, None, lo_open=True, what=" m")
                if count > 1 and pitch < length:
                    raise ln.get("pitch").error(
                        f"lamps overlap: pitch {pitch:g} m is shorter than length {length:g} m")
                lamps.append(LampRow(ln.get("x").number(), ln.get("y").number(), length,
                                     ln.get("width").number(0.0, None, lo_open=True,
                                                            what=" m"), pitch, count))
        lights = np.zeros((0, 2))
        if node.has("lights"):
            ln = node.get("lights")
            pts = [n.numbers(2) for n in ln.items()]
            lights = np.array(pts, dtype=float).reshape(-1, 2)
            if lights.shape[0] == 0:
                raise ln.error("expected at least one light (or leave the section out)")
            d = np.linalg.norm(lights[:, None] - lights[None], axis=2)
            d[np.diag_indices_from(d)] = np.inf
            i, j = np.unravel_index(np.argmin(d), d.shape)
            if d[i, j] < 1e-3:
                raise ConfigError(source or node.path, f"{ln.key}[{max(i, j)}]",
                                  f"duplicate light: same place as {ln.key}[{min(i, j)}]")
        blocks = []
        if node.has("blocks"):
            seen: set[str] = set()
            for bn in node.get("blocks").items():
                bn.mapping(("id", "corners"), required=("id", "corners"))
                bid = str(bn.get("id").value)
                if bid in seen:
                    raise bn.get("id").error(f"duplicate block id {bid!r}")
                seen.add(bid)
                cn = bn.get("corners")
                corners = [c.numbers(2) for c in cn.items()]
                if len(corners) != 4:
                    raise cn.error(f"expected 4 corners, found {len(corners)}")
                blocks.append(Block(bid, np.array(corners, dtype=float)))
        return cls(height, corridor, tuple(lamps), lights, tuple(blocks),
                   source or (str(node.path) if node.path else None))


def check_rig_site(rig: Any, site: Site) -> None:
    """Raise a ConfigError if the camera is not below the ceiling."""
    if site.ceiling_height_m <= rig.mount.z_m + 0.05:
        raise ConfigError(site.source, "ceiling_height",
                          f"the ceiling ({site.ceiling_height_m:g} m) must be above the "
                          f"camera (mount.z = {rig.mount.z_m:g} m in {rig.source or 'the rig'})")
