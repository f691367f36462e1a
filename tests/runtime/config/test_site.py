"""runtime/config/site.py: the SPEC §2 sections beyond corridor and lights (lamp z,
light_diameter, ignore, blocks, markers, origin): parsed, round-tripped, and a valid file
broken one field at a time, each break one line naming the file and the dotted key."""

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import (
    MIN_CEILING_CLEARANCE_M,
    Block,
    LampRow,
    MarkerPose,
    Site,
    aruco_dictionary_size,
    check_rig_site,
    points_in_polygon,
    polygon_area_m2,
    quadrilateral_problem,
)
from ceilkit.runtime.errors import ConfigError
from helpers import CONFIGS, assert_broken_field, write_text

FULL = """\
ceiling_height: 3.0
lamps:
  - {x: 0.0, y: 0.0, length: 1.2, width: 0.3, pitch: 2.4, count: 3, z: 2.7}
  - {x: 0.0, y: 2.0, length: 1.2, width: 0.3}
lights:
  - [1.2, 0.8]
  - [3.6, 0.8]
light_diameter: 0.16
ignore:
  - [[5.0, -1.0], [6.0, -1.0], [6.0, 1.0], [5.0, 1.0]]
  - [[8.0, 0.0], [9.0, 0.0], [8.5, 1.0]]
blocks:
  - {id: A, corners: [[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]], appearance: dark}
  - {id: 7, corners: [[4.0, 0.0], [4.0, 0.5], [4.5, 0.5], [4.5, 0.0]]}
markers:
  dictionary: DICT_APRILTAG_36h11
  size: 0.2
  poses:
    - {id: 7, x: 2.0, y: 0.5, yaw: 0.0}
    - {id: 586, x: 3.0, y: -0.5, yaw: 90.0, size: 0.1}
origin: {lat: 52.0, lon: 4.0, alt: 12.5, heading: 30.0}
"""


write = write_text


@pytest.fixture
def full_site(tmp_path) -> Site:
    return Site.load(write(tmp_path, FULL))


def test_every_section_parsed(full_site):
    s = full_site
    assert s.lamps[0].z_m == 2.7 and s.lamps[1].z_m is None
    assert s.lamps[0].face_z_m(3.0) == 2.7 and s.lamps[1].face_z_m(3.0) == 3.0
    assert s.light_diameter_m == 0.16
    assert len(s.ignore_m) == 2 and s.ignore_m[0].shape == (4, 2)
    assert s.ignore_m[1].shape == (3, 2)
    assert [b.id for b in s.blocks] == ["A", "7"]
    assert s.blocks[0].appearance == "dark" and s.blocks[1].appearance is None
    m = s.markers
    assert m.dictionary == "DICT_APRILTAG_36h11" and m.size_m == 0.2
    assert [p.id for p in m.poses] == [7, 586]
    assert m.poses[0].size_m == 0.2 and m.poses[1].size_m == 0.1      # default, own
    assert math.isclose(m.poses[1].yaw_rad, math.pi / 2)
    assert m.pose(586) is m.poses[1] and m.pose(3) is None
    o = s.origin
    assert (o.lat_deg, o.lon_deg, o.alt_m, o.heading_deg) == (52.0, 4.0, 12.5, 30.0)
    assert math.isclose(o.heading_rad, math.radians(30.0))
    for name in ("lamps", "lights", "ignore", "blocks", "markers", "origin"):
        assert s.has_section(name), name
    assert not s.has_section("corridor") and not s.has_section("walls")


def test_sections_absent():
    s = Site(3.0)
    assert s.light_diameter_m is None and s.ignore_m == () and s.markers is None
    assert s.origin is None
    for name in ("blocks", "markers", "ignore", "origin", "lamps"):
        assert not s.has_section(name)
    assert s.to_dict() == {"ceiling_height": 3.0}
    assert not s.ignored(np.array([[0.0, 0.0], [1.0, 1.0]])).any()


def test_round_trip_every_section(tmp_path, full_site):
    full_site.save(tmp_path / "back.yaml")
    back = Site.load(tmp_path / "back.yaml")
    assert back.to_dict() == full_site.to_dict()
    text = (tmp_path / "back.yaml").read_text()
    assert "z: 2.7" in text and "light_diameter: 0.16" in text and "appearance: dark" in text
    d = back.to_dict()
    assert d["markers"]["poses"][0] == {"id": 7, "x": 2.0, "y": 0.5, "yaw": 0.0}  # no size
    assert d["markers"]["poses"][1]["size"] == 0.1
    assert d["origin"] == {"lat": 52.0, "lon": 4.0, "alt": 12.5, "heading": 30.0}
    assert "z" not in d["lamps"][1]
    for a, b in zip(back.ignore_m, full_site.ignore_m, strict=True):
        assert np.array_equal(a, b)
    for a, b in zip(back.blocks, full_site.blocks, strict=True):
        assert a.id == b.id and a.appearance == b.appearance
        assert np.array_equal(a.corners_m, b.corners_m)


def test_example_sites_load_and_round_trip(tmp_path):
    for name in ("corridor", "lights", "block"):
        site = Site.load(CONFIGS / name / "site.yaml")
        site.save(tmp_path / f"{name}.yaml")
        assert Site.load(tmp_path / f"{name}.yaml").to_dict() == site.to_dict()


def test_block_corners_normalized_counter_clockwise_from_above(full_site):
    a, b = full_site.blocks
    assert polygon_area_m2(a.corners_m) > 0 and polygon_area_m2(b.corners_m) > 0
    # A was given counter-clockwise: kept; 7 was given clockwise: reversed, corner 0 kept
    assert np.array_equal(a.corners_m, [[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]])
    assert np.array_equal(b.corners_m, [[4.0, 0.0], [4.5, 0.0], [4.5, 0.5], [4.0, 0.5]])
    built = Block("B", np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]]))
    assert np.array_equal(built.corners_m, [[0, 0], [1, 0], [1, 1], [0, 1]])
    assert not built.corners_m.flags.writeable


def test_marker_corners_follow_the_spec():
    s = 0.2
    m0 = MarkerPose(7, 2.0, 0.5, 0.0, s)
    # yaw 0: d_k = (+1,-1), (+1,+1), (-1,+1), (-1,-1) scaled by s/2
    assert np.allclose(m0.corners_m(), [[2.1, 0.4], [2.1, 0.6], [1.9, 0.6], [1.9, 0.4]])
    m90 = MarkerPose(7, 2.0, 0.5, math.pi / 2, s)
    # Rz(90) maps (a, b) to (-b, a)
    assert np.allclose(m90.corners_m(), [[2.1, 0.6], [1.9, 0.6], [1.9, 0.4], [2.1, 0.4]])
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, y, yaw, side = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3), \
            rng.uniform(0.05, 1.0)
        c = MarkerPose(0, x, y, yaw, side).corners_m()
        assert np.allclose(c.mean(axis=0), [x, y])
        assert np.allclose(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1), side)
        assert math.isclose(polygon_area_m2(c), side ** 2)      # counter-clockwise from above
        up = c[0] - c[3]                                          # bottom-left -> top-left
        assert np.allclose(up / side, [math.cos(yaw), math.sin(yaw)])


def test_markers_corners_stacked(full_site):
    corners = full_site.markers.corners_m()
    assert corners.shape == (2, 4, 2)
    assert np.allclose(corners[1], full_site.markers.poses[1].corners_m())


def test_ignored_mask(full_site):
    pts = np.array([[5.5, 0.0], [4.9, 0.0], [8.5, 0.5], [8.5, 0.99], [8.1, 0.9], [0.0, 0.0]])
    assert full_site.ignored(pts).tolist() == [True, False, True, True, False, False]
    grid = np.zeros((3, 4, 2)) + [5.5, 0.5]                       # any leading shape
    assert full_site.ignored(grid).shape == (3, 4) and full_site.ignored(grid).all()


def test_points_in_polygon_against_a_concave_polygon():
    u_shape = np.array([[0, 0], [3, 0], [3, 3], [2, 3], [2, 1], [1, 1], [1, 3], [0, 3]], float)
    pts = np.array([[0.5, 2.0], [1.5, 2.0], [2.5, 2.0], [1.5, 0.5], [4.0, 0.5]])
    assert points_in_polygon(pts, u_shape).tolist() == [True, False, True, True, False]


def test_aruco_dictionary_size():
    assert aruco_dictionary_size("DICT_4X4_50") == 50
    assert aruco_dictionary_size("DICT_APRILTAG_36h11") == 587
    assert aruco_dictionary_size("DICT_NOPE") is None
    assert aruco_dictionary_size("detectMarkers") is None          # in cv2.aruco, not a DICT_


@pytest.mark.parametrize("corners,words", [
    ([[0, 0], [1, 0], [1, 1], [0, 1]], None),
    ([[0, 0], [0, 1], [1, 1], [1, 0]], None),                          # clockwise: fine
    ([[0, 0], [1, 0], [0, 1], [1, 1]], "crosses itself"),               # a bow tie
    ([[0, 0], [2, 0], [0.5, 0.5], [0, 2]], "not convex"),               # a dart
    ([[0, 0], [1, 0], [2, 0], [1, 1]], "straight side"),
    ([[0, 0], [0, 0], [1, 1], [0, 1]], "same place"),
    ([[0, 0], [1, 1], [2, 2], [3, 3]], "straight side"),
    ([[0, 0], [2, 0], [1, 0.001], [0, 0.001]], "turns back"),
    ([[0, 0], [1.5e-3, 0], [2.9e-3, 5e-4], [1.4e-3, 5e-4]], "no area"),   # 0.75 mm²
])
def test_quadrilateral_problem(corners, words):
    problem = quadrilateral_problem(np.array(corners, float))
    assert (problem is None) if words is None else (words in problem), problem


BREAKS = [
    # lamps' z
    ("count: 3, z: 2.7", "count: 3, z: 3.5", "lamps[0].z", "at most ceiling_height"),
    ("count: 3, z: 2.7", "count: 3, z: 0", "lamps[0].z", "(0, 3]"),
    ("count: 3, z: 2.7", "count: 3, z: high", "lamps[0].z", "finite number"),
    ("count: 3, z: 2.7", "count: 3, zz: 2.7", "lamps[0].zz", "unknown key"),
    # light_diameter
    ("light_diameter: 0.16", "light_diameter: 0", "light_diameter", "(0, 1e+09]"),
    ("light_diameter: 0.16", "light_diameter: -0.1", "light_diameter", "(0, 1e+09]"),
    ("light_diameter: 0.16", "light_diameter: [0.16]", "light_diameter", "finite number"),
    ("light_diameter: 0.16", "light_diameters: 0.16", "light_diameters", "unknown key"),
    # ignore
    ("[[8.0, 0.0], [9.0, 0.0], [8.5, 1.0]]", "[[8.0, 0.0], [9.0, 0.0]]", "ignore[1]",
     "at least 3"),
    ("[[8.0, 0.0], [9.0, 0.0], [8.5, 1.0]]", "[[8.0, 0.0], [9.0, 0.0], [10.0, 0.0]]",
     "ignore[1]", "no area"),
    ("[[8.0, 0.0], [9.0, 0.0], [8.5, 1.0]]", "[[8.0, 0.0], [9.0], [8.5, 1.0]]", "ignore[1][1]",
     "2 numbers"),
    ("[[8.0, 0.0], [9.0, 0.0], [8.5, 1.0]]", "{x: 1}", "ignore[1]", "a list of"),
    # blocks
    ("{id: A, corners", "{corners", "blocks[0].id", "missing required key"),
    ("{id: 7, corners", "{id: A, corners", "blocks[1].id", "duplicate block id 'A'"),
    ("{id: 7, corners", "{id: [7], corners", "blocks[1].id", "a name or a number"),
    ("[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]",
     "[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2]]", "blocks[0].corners", "4 corners"),
    ("[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]",
     "[[2.0, -0.2], [2.6, -0.2], [2.1, -0.1], [2.0, 0.2]]", "blocks[0].corners",
     "not convex"),
    ("[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]",
     "[[2.0, -0.2], [2.6, 0.2], [2.6, -0.2], [2.0, 0.2]]", "blocks[0].corners",
     "crosses itself"),
    ("[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]",
     "[[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0]]", "blocks[0].corners[3]", "2 numbers"),
    ("appearance: dark", "appearance: grey", "blocks[0].appearance", "dark, bright"),
    ("appearance: dark", "colour: dark", "blocks[0].colour", "unknown key"),
    # markers
    ("dictionary: DICT_APRILTAG_36h11", "dictionary: DICT_APRILTAG_99h99",
     "markers.dictionary", "expected an OpenCV aruco dictionary"),
    ("dictionary: DICT_APRILTAG_36h11", "dictionary: 36", "markers.dictionary", "a string"),
    ("  dictionary: DICT_APRILTAG_36h11\n", "", "markers.dictionary", "missing required key"),
    ("size: 0.2", "size: 0", "markers.size", "(0, 1e+09]"),
    ("  size: 0.2\n", "", "markers.size", "missing required key"),
    ("yaw: 90.0, size: 0.1", "yaw: 90.0, size: 0", "markers.poses[1].size", "(0, 1e+09]"),
    ("yaw: 90.0, size: 0.1", "yaw: 90.0, size: -1", "markers.poses[1].size", "(0, 1e+09]"),
    ("{id: 586, x", "{id: 587, x", "markers.poses[1].id", "[0, 586]"),
    ("{id: 586, x", "{id: -1, x", "markers.poses[1].id", "[0, 586]"),
    ("{id: 586, x", "{id: 7, x", "markers.poses[1].id", "duplicate marker id 7"),
    ("{id: 586, x", "{id: 5.5, x", "markers.poses[1].id", "an integer"),
    ("yaw: 90.0,", "yaw: 400.0,", "markers.poses[1].yaw", "[-360, 360]"),
    ("x: 3.0, y: -0.5, yaw: 90.0", "x: 3.0, y: -0.5", "markers.poses[1].yaw",
     "missing required key"),
    ("yaw: 0.0}", "yaw: 0.0, roll: 0}", "markers.poses[0].roll", "unknown key"),
    ("  poses:\n    - {id: 7, x: 2.0, y: 0.5, yaw: 0.0}\n"
     "    - {id: 586, x: 3.0, y: -0.5, yaw: 90.0, size: 0.1}\n",
     "  poses: []\n", "markers.poses", "at least one marker"),
    # origin
    ("lat: 52.0", "lat: 91.0", "origin.lat", "[-90, 90]"),
    ("lon: 4.0", "lon: -181.0", "origin.lon", "[-180, 180]"),
    ("alt: 12.5, ", "", "origin.alt", "missing required key"),
    ("heading: 30.0", "heading: north", "origin.heading", "finite number"),
    ("heading: 30.0", "heading: 30.0, datum: WGS84", "origin.datum", "unknown key"),
]


@pytest.mark.parametrize("old,new,key,words", BREAKS)
def test_full_site_broken_one_field_at_a_time(tmp_path, old, new, key, words):
    assert old in FULL
    assert_broken_field(Site.load, write(tmp_path, FULL.replace(old, new, 1)), key, words)


def test_block_and_marker_breaks_the_issue_names(tmp_path):
    """Issue 11's bad inputs: a block that is not convex, a marker size of 0, an unknown
    dictionary; each one line naming file and key."""
    base = "ceiling_height: 3.0\n"
    cases = [
        ("blocks: [{id: A, corners: [[0, 0], [2, 0], [0.5, 0.5], [0, 2]]}]\n",
         "blocks[0].corners: expected a convex quadrilateral, corners in order around it: "
         "not convex"),
        ("blocks: [{id: A, corners: [[0, 0], [1, 1], [1, 0], [0, 1]]}]\n",
         "blocks[0].corners: expected a convex quadrilateral, corners in order around it: "
         "the outline crosses itself (corners not in order around the block)"),
        ("markers: {dictionary: DICT_4X4_50, size: 0, poses: [{id: 1, x: 0, y: 0, yaw: 0}]}\n",
         "markers.size: expected a number in (0, 1e+09] m, found 0"),
        ("markers: {dictionary: DICT_9X9_5, size: 0.1, poses: [{id: 1, x: 0, y: 0, yaw: 0}]}\n",
         "markers.dictionary: expected an OpenCV aruco dictionary ("),
    ]
    for text, message in cases:
        path = write(tmp_path, base + text)
        with pytest.raises(ConfigError) as err:
            Site.load(path)
        assert str(err.value).startswith(f"{path}: {message}"), str(err.value)


def test_marker_ids_bounded_by_the_dictionary(tmp_path):
    text = "ceiling_height: 3.0\nmarkers: {dictionary: DICT_4X4_50, size: 0.1, poses: [%s]}\n"
    ok = Site.load(write(tmp_path, text % "{id: 49, x: 0, y: 0, yaw: 0}"))
    assert ok.markers.poses[0].id == 49
    with pytest.raises(ConfigError, match=r"markers.poses\[0\].id: expected an integer in "
                                          r"\[0, 49\], found 50"):
        Site.load(write(tmp_path, text % "{id: 50, x: 0, y: 0, yaw: 0}"))


def test_site_arrays_are_read_only(full_site):
    with pytest.raises(ValueError):
        full_site.ignore_m[0][0, 0] = 1.0
    with pytest.raises(ValueError):
        full_site.blocks[0].corners_m[0, 0] = 1.0


def rig_at(z_m: float) -> Rig:
    cam = Rig.load(CONFIGS / "corridor" / "rig.yaml").camera
    return Rig(cam, Mount(tilt_rad=math.pi / 2, z_m=z_m), "rig.yaml")


def test_rig_site_clearance_is_the_named_tolerance():
    site = Site(3.0, source="site.yaml")
    check_rig_site(rig_at(3.0 - MIN_CEILING_CLEARANCE_M - 1e-6), site)
    with pytest.raises(ConfigError, match=r"site.yaml: ceiling_height: the ceiling \(3 m\) "
                                          r"must be above the camera \(mount.z = 2.95 m in "
                                          r"rig.yaml\) by more than 0.05 m"):
        check_rig_site(rig_at(3.0 - MIN_CEILING_CLEARANCE_M), site)


def test_hanging_lamp_must_be_above_the_camera():
    site = Site(3.0, lamps=(LampRow(0.0, 0.0, 1.2, 0.3), LampRow(0.0, 2.0, 1.2, 0.3, z_m=2.0)),
                source="site.yaml")
    check_rig_site(rig_at(1.9), site)
    with pytest.raises(ConfigError, match=r"site.yaml: lamps\[1\].z: the lamps' face \(2 m\) "
                                          r"must be above the camera"):
        check_rig_site(rig_at(1.96), site)


def test_config_reference_example_loads(tmp_path):
    """docs/config.md's complete site.yaml example is a valid site with every section."""
    text = (CONFIGS.parent / "docs" / "config.md").read_text(encoding="utf-8")
    section = text[text.index("## site.yaml"):]
    lines = section.split("\n")
    start = lines.index("    ceiling_height: 3.0")
    example = []
    for line in lines[start:]:
        if not line.startswith("    "):
            break
        example.append(line[4:])
    site = Site.load(write(tmp_path, "\n".join(example) + "\n"))
    for name in ("corridor", "lamps", "lights", "ignore", "blocks", "markers", "origin"):
        assert site.has_section(name), name
    assert site.light_diameter_m == 0.16 and site.lamps[1].z_m == 2.6
