"""runtime/config/yaml.py: strict parsing (duplicate keys, non-UTF-8 bytes, integer ranges,
each one line naming file, line and key) and atomic writes (never half-written, usual mode,
errors name the file)."""

import os
import stat

import pytest

from ceilkit.runtime.config.camera import load_camera
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import (
    Node,
    atomic_write_bytes,
    atomic_write_text,
    load_yaml,
    parse_yaml,
)
from ceilkit.runtime.errors import ConfigError
from helpers import CONFIGS


def test_atomic_write_round_trip_and_mode(tmp_path):
    path = tmp_path / "camera.yaml"
    atomic_write_text(path, "image_width: 640\n")
    assert path.read_text() == "image_width: 640\n"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask
    atomic_write_bytes(path, b"\x00\x01")          # replaces the old file whole
    assert path.read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.yaml"]  # no temp left


def test_atomic_write_to_missing_folder_is_a_config_error(tmp_path):
    path = tmp_path / "no" / "such" / "rig.yaml"
    with pytest.raises(ConfigError, match="cannot write") as info:
        atomic_write_text(path, "x: 1\n")
    assert str(path) in str(info.value)


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "rig.yaml"
    path.write_text("old\n")

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(ConfigError, match="No space left"):
        atomic_write_text(path, "new\n")
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]   # temp removed


# -- strict parsing (issue 17) ---------------------------------------------------------


@pytest.mark.parametrize("text,key,line,first", [
    ("mount:\n  tilt: 45.0\n  tilt: 60.0\n", "mount.tilt", 3, 2),
    ("ceiling_height: 3.0\nceiling_height: 3.1\n", "ceiling_height", 2, 1),
    ("lamps:\n  - {x: 0, y: 0, x: 1}\n", "lamps[0].x", 2, 2),
    ("a: {b: 1}\na: {c: 2}\n", "a", 2, 1),
    ("1: x\n1.0: y\n", "1.0", 2, 1),                  # equal keys, as YAML compares them
])
def test_duplicate_key_names_file_line_and_key(tmp_path, text, key, line, first):
    path = tmp_path / "f.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_yaml(path)
    assert err.value.key == key
    assert str(err.value) == (f"{path}: {key}: duplicate key at line {line} "
                              f"(first given at line {first})")


def test_merge_keys_and_aliases_are_not_duplicates():
    value = parse_yaml(b"a: &x {b: 1}\nc: *x\nd: {<<: *x, b: 2}\ne: &l [*x, *x]\n")
    assert value == {"a": {"b": 1}, "c": {"b": 1}, "d": {"b": 2}, "e": [{"b": 1}, {"b": 1}]}


def test_doubled_mount_tilt_is_refused(tmp_path):
    """Issue 17: `tilt: 45.0` then `tilt: 60.0` used to give tilt 60 silently."""
    (tmp_path / "camera.yaml").write_bytes((CONFIGS / "corridor" / "camera.yaml").read_bytes())
    path = tmp_path / "rig.yaml"
    path.write_text("camera: camera.yaml\nmount:\n  tilt: 45.0\n  z: 0.8\n  tilt: 60.0\n")
    with pytest.raises(ConfigError, match=r"rig.yaml: mount.tilt: duplicate key at line 5"):
        Rig.load(path)


@pytest.mark.parametrize("loader", [load_camera, Rig.load, Site.load])
def test_latin1_comment_names_file_and_line(tmp_path, loader):
    path = tmp_path / "file.yaml"
    path.write_bytes("# ceiling height\nceiling_height: 3.0   # f\u00fcr den Flur\n"
                     .encode("latin-1"))
    with pytest.raises(ConfigError) as err:
        loader(path)
    assert str(err.value) == (f"{path}: not UTF-8 text: byte 0xfc at line 2, column 26 "
                              f"(save the file as UTF-8)")


def test_binary_file_is_a_config_error(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    with pytest.raises(ConfigError, match=r"site.yaml: not UTF-8 text: byte 0x89 at line 1"):
        Site.load(path)
    path.write_bytes(b"ceiling_height: 3.0\nlights: [[1, \x00]]\n")   # UTF-8, but not YAML
    with pytest.raises(ConfigError, match=r"site.yaml: invalid YAML at line 2, column 14: "
                                          r"special characters are not allowed \(#x0000\)"):
        Site.load(path)


def test_utf8_text_with_bom_and_crlf_loads(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_bytes("\ufeff# Fl\u00fcr\r\nceiling_height: 3.0\r\n".encode("utf-8"))
    assert Site.load(path).ceiling_height_m == 3.0


def test_invalid_yaml_names_line(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text("ceiling_height: 3.0\nlights: [[1, 2]\n")
    with pytest.raises(ConfigError, match=r"site.yaml: invalid YAML at line 3"):
        Site.load(path)


def test_integers_are_range_checked():
    assert Node(5, "f.yaml", "count").integer(1, 10) == 5
    with pytest.raises(ConfigError, match=r"f.yaml: count: expected an integer in \[1, 10\], "
                                          r"found 11"):
        Node(11, "f.yaml", "count").integer(1, 10)
    with pytest.raises(TypeError):
        Node(5, "f.yaml", "count").integer()              # bounds are required


def test_huge_integer_is_not_a_finite_number():
    with pytest.raises(ConfigError, match=r"f.yaml: x: expected a finite number"):
        Node(10 ** 400, "f.yaml", "x").number()


def test_huge_integer_in_a_file(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text("ceiling_height: 3.0\nlamps: [{x: 0, y: 0, length: 1, width: 1, "
                    "count: 100000000000000000000}]\n")
    with pytest.raises(ConfigError, match=r"lamps\[0\].count: expected an integer in "
                                          r"\[1, 100000\]"):
        Site.load(path)
