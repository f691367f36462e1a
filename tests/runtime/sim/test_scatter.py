"""The ceiling scatter (runtime/sim/scatter*.py): generated from a seed, rendered where
the scene says, read and written as scene.yaml, selected beside the site."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import AcrossLines, Corridor, Site
from ceilkit.runtime.devices import open_source
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.sim import render as sim
from ceilkit.runtime.sim.render import SimOptions, render_radiance
from ceilkit.runtime.sim.scatter import (
    KINDS,
    PRESETS,
    TILE_INSET_M,
    Scatter,
    ScatterItem,
    cable,
    generate,
)
from ceilkit.runtime.sim.scatter_file import SCENE_FILE, load_scene, save_scene, scene_beside
from helpers import CONFIGS

OFFICE = CONFIGS / "office"
CLEAN = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0, supersample=2)


@pytest.fixture(scope="module")
def rig() -> Rig:
    r = Rig.load(OFFICE / "rig.yaml")
    return Rig(r.camera.scaled(320, 240), r.mount)


@pytest.fixture(scope="module")
def site() -> Site:
    return Site.load(OFFICE / "site.yaml")


def project_world(rig: Rig, pts_w: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    R = rig.mount.R_world_cam(yaw)
    c = rig.mount.camera_position(x, y, yaw)
    return rig.camera.project((np.asarray(pts_w, float) - c) @ R)


def pixel(img: np.ndarray, uv) -> float:
    return float(img[int(round(uv[1])), int(round(uv[0]))])


# --------------------------------------------------------------------------- generation
def test_same_seed_same_scatter_other_seed_another(site):
    a = generate("office", site, 7, (-3.0, 15.0))
    b = generate("office", site, 7, (-3.0, 15.0))
    c = generate("office", site, 8, (-3.0, 15.0))
    assert a.items == b.items and len(a) > 50
    assert a.items != c.items
    pa = {(it.kind, it.x_m, it.y_m) for it in a.items}
    pc = {(it.kind, it.x_m, it.y_m) for it in c.items}
    assert len(pa & pc) < 0.5 * len(pa)          # not the same layout, reordered


def test_office_preset_holds_every_kind_at_its_scale(site):
    sc = generate("office", site, 1, (-3.0, 33.0))
    assert set(sc.counts()) == set(KINDS)
    first, sp = 0.0, 0.6
    for it in sc.items:
        if it.kind in ("vent", "hatch", "patch", "panel"):
            # fills whole tiles, inset from the seams, centred on the tile(s)
            assert min(it.length_m, it.width_m) == pytest.approx(sp - 2 * TILE_INSET_M)
            assert max(it.length_m, it.width_m) <= 2 * sp
            kx = (it.x_m - first) / (sp / 2)
            assert abs(kx - round(kx)) < 1e-6
        if it.kind == "sprinkler":
            assert it.length_m == pytest.approx(0.05)
        if it.kind == "detector":
            assert it.length_m == pytest.approx(0.12)
        if it.kind == "cable":
            assert it.length_m >= 1.5 and it.width_m < 0.015
        if it.kind == "stain":
            assert 0.02 < it.length_m <= 0.35 and it.grey > 0
    heads = np.array([[it.x_m, it.y_m] for it in sc.of_kind("sprinkler")])
    d = np.hypot(*(heads[:, None, :] - heads[None, :, :]).transpose(2, 0, 1))
    assert np.min(d[np.triu_indices(len(heads), 1)]) >= PRESETS["office"].sprinkler_gap_m


def test_scatter_is_not_periodic_on_the_tile_grid(site):
    """Shifted by any whole number of tiles, few items land on an item of their kind:
    one frame's scatter tells it from the frames a tile period away."""
    sc = generate("office", site, 3, (-3.0, 33.0))
    key = {(it.kind, round(it.x_m, 3), round(it.y_m, 3)) for it in sc.items}
    worst = 0.0
    for kx in range(-8, 9):
        for ky in range(-3, 4):
            if kx == ky == 0:
                continue
            hit = sum((it.kind, round(it.x_m + 0.6 * kx, 3), round(it.y_m + 0.6 * ky, 3))
                      in key for it in sc.items)
            worst = max(worst, hit / len(sc))
    assert worst < 0.2


def test_generate_bad_arguments(site):
    with pytest.raises(ConfigError, match="preset"):
        generate("hospital", site, 1, (0.0, 5.0))
    with pytest.raises(ConfigError, match="seed"):
        generate("office", site, -1, (0.0, 5.0))
    with pytest.raises(ConfigError, match="x_range_m"):
        generate("office", site, 1, (5.0, 0.0))
    with pytest.raises(ConfigError, match="corridor"):
        generate("office", Site(3.0, lights_m=np.array([[0.0, 0.0]])), 1, (0.0, 5.0))
    with pytest.raises(ConfigError, match="item.kind"):
        ScatterItem("lamp", 0.0, 0.0, 0.1, 0.1)
    with pytest.raises(ConfigError, match="item.points"):
        cable([[0.0, 0.0]], 0.01)
    with pytest.raises(ConfigError, match="options.scatter"):
        SimOptions(scatter="office")


# --------------------------------------------------------------------------- rendering
ONE = {  # an item of each kind in the middle of tile (1, 0): x 0.6..1.2, y 0..0.6
    "panel": ScatterItem("panel", 0.9, 0.3, 0.584, 0.584),
    "vent": ScatterItem("vent", 0.9, 0.3, 0.584, 0.584, 90.0),
    "hatch": ScatterItem("hatch", 0.9, 0.3, 0.584, 0.584),
    "patch": ScatterItem("patch", 0.9, 0.3, 0.584, 0.584, grey=-8.0),
    "stain": ScatterItem("stain", 0.9, 0.3, 0.2, 0.1, 30.0, grey=20.0),
    "sprinkler": ScatterItem("sprinkler", 0.9, 0.3, 0.05, 0.05),
    "detector": ScatterItem("detector", 0.9, 0.3, 0.12, 0.12),
}


@pytest.mark.parametrize("kind", list(ONE))
def test_item_lands_where_the_scene_says(rig, site, kind):
    it = ONE[kind]
    pose = (0.7, 0.1, 0.3)
    plain = render_radiance(rig, site, *pose, CLEAN)
    img = render_radiance(rig, site, *pose, CLEAN.replace(scatter=Scatter((it,))))
    z = site.ceiling_height_m
    c = project_world(rig, [[it.x_m, it.y_m, z]], *pose)[0]
    assert abs(pixel(img, c) - pixel(plain, c)) > 5.0
    # outside it (30 % past its half size, along its length) the ceiling is untouched
    a = math.radians(it.yaw_deg)
    off = 0.65 * it.length_m
    o = project_world(rig, [[it.x_m + off * math.cos(a), it.y_m + off * math.sin(a), z]],
                      *pose)[0]
    assert pixel(img, o) == pytest.approx(pixel(plain, o), abs=0.5)


def test_cable_lands_on_its_points(rig, site):
    run = cable([[0.2, 0.45], [1.4, 0.45], [1.4, -0.2]], 0.01)
    pose = (0.7, 0.1, 0.3)
    plain = render_radiance(rig, site, *pose, CLEAN)
    img = render_radiance(rig, site, *pose, CLEAN.replace(scatter=Scatter((run,))))
    on = project_world(rig, [[0.8, 0.45, 2.7], [1.4, 0.15, 2.7]], *pose)
    off = project_world(rig, [[0.8, 0.35, 2.7], [1.3, 0.15, 2.7]], *pose)
    for p in on:
        assert pixel(plain, p) - pixel(img, p) > 40.0
    for p in off:
        assert pixel(img, p) == pytest.approx(pixel(plain, p), abs=0.5)


def test_generated_items_land_where_the_scene_says(rig, site):
    sc = generate("office", site, 1, (-3.0, 33.0))
    seen = 0
    for pose in ((2.0, 0.3, 0.2), (9.5, -1.1, 1.4), (17.0, 1.0, -0.6)):
        plain = render_radiance(rig, site, *pose, CLEAN)
        img = render_radiance(rig, site, *pose, CLEAN.replace(scatter=sc))
        items = [it for it in sc.items if it.kind not in ("stain", "cable")]
        uv = project_world(rig, [[it.x_m, it.y_m, 2.7] for it in items], *pose)
        inside = rig.camera.in_image(uv, 3)
        for p in uv[inside]:
            assert abs(pixel(img, p) - pixel(plain, p)) > 3.0
        seen += int(np.sum(inside))
    assert seen >= 6


def test_seams_are_where_the_corridor_lines_say(rig, site):
    """With the tiles either side replaced (patches lighter and darker), the seams are
    drawn over them, centred on the projected lines_along and lines_across."""
    items = (ScatterItem("patch", 0.9, 0.3, 0.584, 0.584, grey=10.0),
             ScatterItem("patch", 0.9, -0.3, 0.584, 0.584, grey=-10.0),
             ScatterItem("patch", 0.3, 0.3, 0.584, 0.584, grey=-10.0))
    pose = (0.7, 0.1, 0.3)
    img = render_radiance(rig, site, *pose, CLEAN.replace(scatter=Scatter(items)))
    z = site.ceiling_height_m
    # y = 0 between the upper and the lower patch; x = 0.6 between the two upper ones
    for p, step in (([0.9, 0.0, z], [0.0, 0.04, 0.0]), ([0.8, 0.0, z], [0.0, 0.04, 0.0]),
                    ([0.6, 0.4, z], [0.04, 0.0, 0.0]), ([0.6, 0.2, z], [0.04, 0.0, 0.0])):
        ends = project_world(rig, [np.subtract(p, step), np.add(p, step)], *pose)
        c = project_world(rig, [p], *pose)[0]
        ts = np.linspace(0.0, 1.0, 161)
        uv = ends[0] + ts[:, None] * (ends[1] - ends[0])
        prof = cv2.remap(img, uv[:, 0].astype(np.float32).reshape(1, -1),
                         uv[:, 1].astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR)[0]
        w = np.clip(min(prof[0], prof[-1]) - prof, 0.0, None)
        centre = (w[:, None] * uv).sum(axis=0) / w.sum()
        assert np.hypot(*(centre - c)) < 0.3
        assert prof.min() < sim.SEAM_GREY + 15


def test_panels_are_emitters(rig, site):
    sc = Scatter((ONE["panel"], ONE["patch"].__class__("patch", 0.3, 0.3, 0.584, 0.584,
                                                       grey=5.0)))
    pose = (0.7, 0.1, 0.3)
    img, em = render_radiance(rig, site, *pose, CLEAN.replace(scatter=sc), split=True)
    c = project_world(rig, [[0.9, 0.3, 2.7], [0.3, 0.3, 2.7]], *pose)
    assert pixel(em, c[0]) == pytest.approx(pixel(img, c[0])) and pixel(img, c[0]) > 240
    assert pixel(em, c[1]) == 0.0


# --------------------------------------------------------------------------- scene file
def test_scene_file_round_trip(tmp_path, site):
    sc = generate("office", site, 5, (-1.2, 8.0))
    path = save_scene(sc, tmp_path / SCENE_FILE, "# a test\n")
    back = load_scene(path, site)
    assert back.items == sc.items
    assert path.read_text().startswith("# a test\n# office preset, seed 5")


def test_scene_file_generates_and_lists(tmp_path, site):
    path = tmp_path / SCENE_FILE
    path.write_text("generate: {preset: office, seed: 2, x: [0.0, 6.0], y: [-1.2, 1.2]}\n"
                    "scatter:\n"
                    "  - {kind: sprinkler, x: 0.3, y: 0.3}\n"
                    "  - {kind: stain, x: 1.0, y: 0.2, size: [0.3, 0.1], yaw: 20}\n"
                    "  - {kind: cable, points: [[0, 0.1], [2, 0.1]]}\n")
    sc = load_scene(path, site)
    gen = generate("office", site, 2, (0.0, 6.0), (-1.2, 1.2))
    assert sc.items[:len(gen)] == gen.items
    extra = sc.items[len(gen):]
    assert [it.kind for it in extra] == ["sprinkler", "stain", "cable"]
    assert extra[0].length_m == 0.05 and extra[1].grey == 20.0 and extra[2].length_m == 2.0
    assert all(abs(it.y_m) <= 1.2 + 0.3 for it in gen.items if it.kind != "cable")


@pytest.mark.parametrize("text, key", [
    ("generate: {preset: hospital, seed: 1, x: [0, 5]}\n", "generate.preset"),
    ("generate: {preset: office, seed: 1, x: [5, 0]}\n", "generate.x"),
    ("generate: {preset: office, x: [0, 5]}\n", "generate.seed"),
    ("lights: []\n", "lights"),
    ("scatter:\n  - {kind: lamp, x: 0, y: 0}\n", "scatter[0].kind"),
    ("scatter:\n  - {kind: sprinkler, x: 0, y: 0, grey: 3}\n", "scatter[0].grey"),
    ("scatter:\n  - {kind: vent, x: 0}\n", "scatter[0].y"),
    ("scatter:\n  - {kind: vent, x: 0, y: 0, size: [0.6, -1]}\n", "scatter[0].size[1]"),
    ("scatter:\n  - {kind: cable, points: [[0, 0]]}\n", "scatter[0].points"),
    ("scatter:\n  - {kind: stain, x: 0, y: 0, grey: -5}\n", "scatter[0].grey"),
])
def test_scene_file_errors_name_the_file_and_key(tmp_path, site, text, key):
    path = tmp_path / SCENE_FILE
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_scene(path, site)
    assert exc.value.path == str(path) and exc.value.key == key, str(exc.value)


def test_generate_needs_a_tile_grid(tmp_path):
    path = tmp_path / SCENE_FILE
    path.write_text("generate: {preset: office, seed: 1, x: [0, 5]}\n")
    bare = Site(3.0, corridor=Corridor((0.0,), AcrossLines(0.0, 0.6)))
    with pytest.raises(ConfigError) as exc:
        load_scene(path, bare)
    assert exc.value.key == "generate" and "lines_along" in str(exc.value)
    with pytest.raises(ConfigError, match="needs the site"):
        load_scene(path, None)


# --------------------------------------------------------------------------- selection
def test_the_scene_beside_the_site_is_rendered(site, tmp_path):
    sc = scene_beside(site)
    assert sc is not None and sc.items == generate("office", site, 1, (-3.0, 33.0)).items
    assert scene_beside(Site.load(CONFIGS / "corridor" / "site.yaml")) is None
    src = open_source("sim:office", Rig.load(OFFICE / "rig.yaml"), site, frames=3)
    assert src.options.scatter is not None and src.options.scatter.items == sc.items
    # a site file elsewhere with no scene.yaml beside it: no scatter
    (tmp_path / "site.yaml").write_text((OFFICE / "site.yaml").read_text())
    other = Site.load(tmp_path / "site.yaml")
    assert open_source("sim:office", Rig.load(OFFICE / "rig.yaml"), other,
                       frames=3).options.scatter is None
