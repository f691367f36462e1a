"""runtime/config.py: atomic writes (never half-written, usual mode, errors name the file)."""

import os
import stat

import pytest

from ceilkit.runtime.config.yaml import atomic_write_bytes, atomic_write_text
from ceilkit.runtime.errors import ConfigError


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
