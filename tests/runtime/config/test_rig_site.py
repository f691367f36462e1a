import math

import numpy as np
import pytest

from ceilkit.runtime.config.camera import save_camera
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import ConfigError
from helpers import CONFIGS


def test_example_configs_load(corridor_rig, corridor_site, lights_rig, lights_site):
    assert corridor_rig.camera.size == (640, 480)
    assert math.isclose(corridor_rig.mount.tilt_rad, math.radians(45))
    assert corridor_site.corridor.lines_along_m == (-0.45, -0.15, 0.15, 0.45)
    assert corridor_site.lamp_rectangles().shape == (60, 4, 2)
    assert lights_site.lights_m.shape == (40, 2)
    assert Site.load(CONFIGS / "block" / "site.yaml").blocks[0].id == "A"
    check_rig_site(corridor_rig, corridor_site)


def test_camera_position_and_rotation():
    m = Mount(pan_rad=0.0, tilt_rad=math.pi / 2, swing_rad=0.0, x_m=0.3, y_m=0.1, z_m=0.8)
    c = m.camera_position(1.0, 2.0, math.pi / 2)
    assert np.allclose(c, [1.0 - 0.1, 2.0 + 0.3, 0.8])
    assert np.allclose(m.R_world_cam(0.0) @ [0, 0, 1], [0, 0, 1])


def test_rig_round_trip_inline_and_by_reference(tmp_path, corridor_rig):
    corridor_rig.save(tmp_path / "rig.yaml")
    back = Rig.load(tmp_path / "rig.yaml")
    assert back.mount == corridor_rig.mount
    assert np.array_equal(back.camera.K, corridor_rig.camera.K)
    save_camera(corridor_rig.camera, tmp_path / "cam.yaml")
    corridor_rig.save(tmp_path / "rig2.yaml", camera_ref="cam.yaml")
    assert Rig.load(tmp_path / "rig2.yaml").camera_file == str(tmp_path / "cam.yaml")


def test_site_round_trip(tmp_path, corridor_site, lights_site):
    for site in (corridor_site, lights_site):
        site.save(tmp_path / "site.yaml")
        back = Site.load(tmp_path / "site.yaml")
        assert back.to_dict() == site.to_dict()


RIG = "camera: {cam}\nmount: {{pan: 0.0, tilt: 45.0, swing: 0.0, x: 0.3, y: 0.0, z: 0.8}}\n"


@pytest.mark.parametrize("old,new,key,words", [
    ("tilt: 45.0", "tilt: 120.0", "mount.tilt", "[0, 90]"),
    ("tilt: 45.0", "tilt: -5", "mount.tilt", "[0, 90]"),
    ("z: 0.8", "z: 0.0", "mount.z", "(0, 100]"),
    ("pan: 0.0", "pan: left", "mount.pan", "number"),
    ("swing: 0.0,", "swing: 0.0, roll: 1,", "mount.roll", "unknown key"),
    ("z: 0.8", "zz: 0.8", "mount.zz", "unknown key"),
])
def test_bad_rig_files(tmp_path, old, new, key, words):
    cam = tmp_path / "camera.yaml"
    (CONFIGS / "corridor" / "camera.yaml").read_bytes()
    cam.write_bytes((CONFIGS / "corridor" / "camera.yaml").read_bytes())
    path = tmp_path / "rig.yaml"
    path.write_text(RIG.format(cam="camera.yaml").replace(old, new))
    with pytest.raises(ConfigError) as err:
        Rig.load(path)
    assert str(path) in str(err.value) and key in str(err.value) and words in str(err.value)


def test_rig_missing_camera_file(tmp_path):
    (tmp_path / "rig.yaml").write_text(RIG.format(cam="nowhere.yaml"))
    with pytest.raises(ConfigError, match=r"rig.yaml: camera: camera file .*nowhere.yaml"):
        Rig.load(tmp_path / "rig.yaml")


@pytest.mark.parametrize("text,key,words", [
    ("ceiling_height: -1\n", "ceiling_height", "(0, 1000]"),
    ("ceiling_height: 3\nwalls: 2\n", "walls", "unknown key"),
    ("ceiling_height: 3\ncorridor: {lines_along: []}\n", "corridor.lines_along", "at least one"),
    ("ceiling_height: 3\ncorridor: {lines_along: [0.1, 0.1]}\n", "corridor.lines_along",
     "same y"),
    ("ceiling_height: 3\ncorridor: {lines_along: [0], lines_across: {spacing: 0}}\n",
     "corridor.lines_across.spacing", "(0, 1e+09]"),
    ("ceiling_height: 3\nlights: [[1, 2], [3]]\n", "lights[1]", "2 numbers"),
    ("ceiling_height: 3\nlights: [[1, 2], [3, 4], [1, 2]]\n", "lights[2]", "duplicate light"),
    ("ceiling_height: 3\nlights: []\n", "lights", "at least one light"),
    ("ceiling_height: 3\nlamps: [{x: 0, y: 0, length: 1.2, width: 0.3, pitch: 1.0, count: 3}]\n",
     "lamps[0].pitch", "overlap"),
    ("ceiling_height: 3\nblocks: [{id: A, corners: [[0, 0], [1, 0], [1, 1]]}]\n",
     "blocks[0].corners", "4 corners"),
])
def test_bad_site_files(tmp_path, text, key, words):
    path = tmp_path / "site.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        Site.load(path)
    msg = str(err.value)
    assert str(path) in msg and key in msg and words in msg, msg


def test_ceiling_below_camera(tmp_path, corridor_rig):
    (tmp_path / "site.yaml").write_text("ceiling_height: 0.5\n")
    with pytest.raises(ConfigError, match="site.yaml: ceiling_height: the ceiling"):
        check_rig_site(corridor_rig, Site.load(tmp_path / "site.yaml"))
