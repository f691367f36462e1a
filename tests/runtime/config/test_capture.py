"""capture.yaml: strict loading, round trip."""

from __future__ import annotations

import pytest

from ceilkit.runtime.config.capture import CaptureFile, load_capture, save_capture
from ceilkit.runtime.errors import ConfigError


def test_round_trip_with_a_header(tmp_path):
    p = save_capture(CaptureFile(120.0, 6.0), tmp_path / "capture.yaml", ["sweep table"])
    assert p.read_text().startswith("# sweep table\n")
    assert load_capture(p) == CaptureFile(120.0, 6.0)
    save_capture(CaptureFile(exposure=80.0), p)
    assert load_capture(p) == CaptureFile(80.0, None)


@pytest.mark.parametrize("text,key", [
    ("exposure: 0\n", "exposure"), ("exposure: -3\n", "exposure"),
    ("gain: fast\n", "gain"), ("exposure: 10\nshutter: 3\n", "shutter"),
    ("exposure: .nan\n", "exposure")])
def test_bad_files_name_the_key(tmp_path, text, key):
    p = tmp_path / "capture.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_capture(p)
    assert e.value.key == key and str(e.value.path) == str(p)
