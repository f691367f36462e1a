"""The simulator's scene file, ``scene.yaml``: a ceiling's scatter, generated or listed.

SPEC's ``site.yaml`` holds what a localization method is told about a site; what else
the simulated ceiling holds (light panels, vents, hatches, stains, sprinklers, ...:
:mod:`ceilkit.runtime.sim.scatter`) is the simulator's alone and lives beside it in
``scene.yaml``. A ``sim:`` device and ``ceilcal simulate`` render the ``scene.yaml``
beside the site (:func:`scene_beside`); ``ceilcal simulate`` writes the scatter it
rendered, item by item, into the recording's ``scene.yaml`` (the truth a survey is
scored against). Format (docs/simulator.md, "Ceilings with a scatter")::

    # both keys optional; the items are the generated ones, then the listed ones
    generate: {preset: office, seed: 1, x: [-3.0, 33.0]}   # y: [lo, hi] (default: all
                                                             # the site's lines_along)
    scatter:
      - {kind: panel, x: 0.3, y: -0.6, size: [0.584, 1.184]}   # size [length, width], m
      - {kind: vent, x: 2.1, y: 0.9, size: [0.584, 0.584], yaw: 90}   # yaw: degrees
      - {kind: patch, x: 4.5, y: -1.5, grey: -6.5}       # size defaults: DEFAULT_SIZE_M
      - {kind: stain, x: 1.2, y: 0.4, size: [0.2, 0.1], yaw: 30, grey: 18}
      - {kind: sprinkler, x: 3.3, y: 1.1}                # size: the diameter (0.05)
      - {kind: detector, x: 7.0, y: -0.8, size: 0.12}
      - {kind: cable, points: [[1.0, 0.3], [3.5, 0.3], [3.5, 1.6]], width: 0.008}

Read strictly (unknown keys, a key a kind does not take, a bad value: a ConfigError
naming the file and the dotted key).
"""

from __future__ import annotations

from pathlib import Path

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import Node, atomic_write_text, load_yaml
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.sim.scatter import (
    DEFAULT_GREY,
    DEFAULT_SIZE_M,
    DISC_KINDS,
    KINDS,
    PRESETS,
    Scatter,
    ScatterItem,
    cable,
    generate,
)

SCENE_FILE = "scene.yaml"
MAX_SIZE_M = 50.0

_KEYS = {"cable": ("kind", "points", "width"),
         "patch": ("kind", "x", "y", "size", "yaw", "grey"),
         "stain": ("kind", "x", "y", "size", "yaw", "grey")}
_PLAIN_KEYS = ("kind", "x", "y", "size", "yaw")


def load_scene(path: str | Path, site: Site | None) -> Scatter:
    """The scatter a scene file describes (``site``: its tile grid, for ``generate``).

    Raises ConfigError naming ``path`` and the key: a malformed file, an unknown preset,
    ``generate`` without a site or on a site with no tile grid."""
    root = load_yaml(path).mapping(("generate", "scatter"))
    items: list[ScatterItem] = []
    origin = str(path)
    if root.has("generate"):
        gen = root.get("generate")
        items += _generated(gen, site).items
        origin = (f"{gen.value['preset']} preset, seed {gen.value['seed']} "
                  f"({Path(path).name})")
    if root.has("scatter"):
        items += [_item(node) for node in root.get("scatter").items()]
    return Scatter(tuple(items), origin)


def _generated(gen: Node, site: Site | None) -> Scatter:
    gen.mapping(("preset", "seed", "x", "y"), ("preset", "seed", "x"))
    preset = gen.get("preset").string(tuple(PRESETS))
    seed = gen.get("seed").integer(0, 2**63 - 1)
    ranges = []
    for name in ("x", "y"):
        if name == "y" and not gen.has("y"):
            ranges.append(None)
            continue
        node = gen.get(name)
        lo, hi = node.numbers(2)
        if not lo < hi:
            raise node.error(f"expected [lo, hi] with lo < hi, found [{lo:g}, {hi:g}]")
        ranges.append((lo, hi))
    if site is None:
        raise gen.error("generating a scatter needs the site (its tile grid)")
    try:
        return generate(preset, site, seed, ranges[0], ranges[1])
    except ConfigError as exc:
        where = f"{exc.path}: {exc.key}: " if exc.path else ""
        raise gen.error(f"{where}{exc.detail}") from None


def _item(node: Node) -> ScatterItem:
    node.mapping(("kind", "x", "y", "size", "yaw", "grey", "points", "width"), ("kind",))
    kind = node.get("kind").string(KINDS)
    node.mapping(_KEYS.get(kind, _PLAIN_KEYS), ("kind", "points") if kind == "cable"
                 else ("kind", "x", "y"))
    if kind == "cable":
        pts = [p.numbers(2) for p in node.get("points").items()]
        if len(pts) < 2:
            raise node.get("points").error(f"expected two points or more, found {len(pts)}")
        width = node.get("width", DEFAULT_SIZE_M["cable"][1]).number(0.0, 1.0, lo_open=True)
        return cable(pts, width)
    size = node.get("size", DEFAULT_SIZE_M[kind][0] if kind in DISC_KINDS
                    else list(DEFAULT_SIZE_M[kind]))
    if kind in DISC_KINDS or isinstance(size.value, (int, float)):
        length = width = size.number(0.0, MAX_SIZE_M, lo_open=True,
                                     what=" (a diameter or side, m)")
    else:
        length, width = size.numbers(2, 1e-6, MAX_SIZE_M)
    grey = 0.0
    if kind in DEFAULT_GREY:
        g = node.get("grey", DEFAULT_GREY[kind])
        grey = g.number(0.0, 255.0, lo_open=True) if kind == "stain" else g.number(-100, 100)
    return ScatterItem(kind, node.get("x").number(), node.get("y").number(), length, width,
                       node.get("yaw", 0.0).number(-360.0, 360.0), grey)


def _num(v: float) -> str:
    return repr(float(v))


def item_line(it: ScatterItem) -> str:
    """One item as a flow mapping in the scene file's format (values round-trip)."""
    if it.kind == "cable":
        pts = ", ".join(f"[{_num(x)}, {_num(y)}]" for x, y in it.points_m)
        return f"{{kind: cable, points: [{pts}], width: {_num(it.width_m)}}}"
    parts = [f"kind: {it.kind}", f"x: {_num(it.x_m)}", f"y: {_num(it.y_m)}"]
    if it.kind in DISC_KINDS:
        parts.append(f"size: {_num(it.length_m)}")
    else:
        parts.append(f"size: [{_num(it.length_m)}, {_num(it.width_m)}]")
    if it.yaw_deg != 0.0:
        parts.append(f"yaw: {_num(it.yaw_deg)}")
    if it.kind in DEFAULT_GREY:
        parts.append(f"grey: {_num(it.grey)}")
    return "{" + ", ".join(parts) + "}"


def save_scene(scatter: Scatter, path: str | Path, header: str = "") -> Path:
    """Write ``scatter`` item by item (the listed form: no ``generate``) after
    ``header`` and a comment line with its origin and counts; returns the path."""
    lines = [f"# {scatter.describe()}", "scatter:"]
    lines += [f"  - {item_line(it)}" for it in scatter.items]
    if not scatter.items:
        lines[-1] = "scatter: []"
    atomic_write_text(path, header + "\n".join(lines) + "\n")
    return Path(path)


def scene_beside(site: Site) -> Scatter | None:
    """The scatter of the ``scene.yaml`` beside ``site``'s file (None: no such file, or
    a site not read from a file)."""
    if not site.source:
        return None
    path = Path(site.source).parent / SCENE_FILE
    return load_scene(path, site) if path.is_file() else None


__all__ = ["SCENE_FILE", "item_line", "load_scene", "save_scene", "scene_beside"]
