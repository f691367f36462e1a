"""runtime/config/site.py: SPEC §2 ``light_size`` and ``light_yaw`` (rectangular lights):
parsed into the Site, round-tripped, each misuse one ConfigError line naming the file
and the dotted key; the duplicate-light check by a k-d tree."""

import math

import numpy as np
import pytest

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from helpers import assert_broken_field, write_text

RECT = """\
ceiling_height: 2.8
lights:
  - [0.0, 0.0]
  - [3.05, 0.0]
  - [0.0, 3.66]
light_size: [1.2, 0.47]
light_yaw: 90.0
"""


write = write_text


def test_light_size_and_yaw_parsed(tmp_path):
    site = Site.load(write(tmp_path, RECT))
    assert site.light_size_m == (1.2, 0.47)
    assert site.light_yaw_rad == pytest.approx(math.pi / 2)
    assert site.rectangular_lights and site.light_diameter_m is None
    rects = site.light_rectangles()
    assert rects.shape == (3, 4, 2)
    # long side along +y at light_yaw 90: the first light spans x +-0.235, y +-0.6
    np.testing.assert_allclose(np.ptp(rects[0], axis=0), [0.47, 1.2], atol=1e-12)
    np.testing.assert_allclose(rects.mean(axis=1), site.lights_m, atol=1e-12)


def test_light_yaw_defaults_to_zero_and_round_lights_have_no_rectangles(tmp_path):
    site = Site.load(write(tmp_path, RECT.replace("light_yaw: 90.0\n", "")))
    assert site.light_yaw_rad == 0.0
    np.testing.assert_allclose(np.ptp(site.light_rectangles()[0], axis=0), [1.2, 0.47])
    disc = Site.load(write(tmp_path, RECT.replace("light_size: [1.2, 0.47]\nlight_yaw: 90.0\n",
                                                  "light_diameter: 0.16\n"), "disc.yaml"))
    assert disc.light_size_m is None and not disc.rectangular_lights
    assert disc.light_rectangles().shape == (0, 4, 2)
    assert "light_size" not in disc.to_dict() and "light_yaw" not in disc.to_dict()


def test_light_size_round_trip(tmp_path):
    site = Site.load(write(tmp_path, RECT))
    out = tmp_path / "again.yaml"
    site.save(out)
    again = Site.load(out)
    assert again.light_size_m == site.light_size_m
    assert again.light_yaw_rad == pytest.approx(site.light_yaw_rad, abs=1e-12)
    assert again.to_dict() == site.to_dict()
    assert site.to_dict()["light_size"] == [1.2, 0.47]
    assert site.to_dict()["light_yaw"] == 90.0


BREAKS = [
    ("light_size: [1.2, 0.47]", "light_size: [1.2, 0.0]", "light_size[1]", "(0, 1e+09]"),
    ("light_size: [1.2, 0.47]", "light_size: [-1.2, 0.47]", "light_size[0]", "(0, 1e+09]"),
    ("light_size: [1.2, 0.47]", "light_size: [.inf, 0.47]", "light_size[0]", "finite"),
    ("light_size: [1.2, 0.47]", "light_size: [1.2, .nan]", "light_size[1]", "finite"),
    ("light_size: [1.2, 0.47]", "light_size: [1.2]", "light_size", "[length, width]"),
    ("light_size: [1.2, 0.47]", "light_size: 1.2", "light_size", "[length, width]"),
    ("light_size: [1.2, 0.47]", "light_size: [0.47, 1.2]", "light_size", "length >= width"),
    ("light_size: [1.2, 0.47]", "light_size: [1.2, wide]", "light_size[1]", "finite number"),
    ("light_size: [1.2, 0.47]", "light_size: [1.2, 0.47]\nlight_diameter: 0.16",
     "light_size", "not both"),
    ("light_size: [1.2, 0.47]\n", "", "light_yaw", "needs light_size"),
    ("light_yaw: 90.0", "light_yaw: east", "light_yaw", "finite number"),
    ("light_yaw: 90.0", "light_yaw: 400.0", "light_yaw", "[-360, 360]"),
    ("light_yaw: 90.0", "light_yaws: 90.0", "light_yaws", "unknown key"),
    ("  - [0.0, 3.66]", "  - [3.05, 0.0005]", "lights[2]", "same place as lights[1]"),
]


@pytest.mark.parametrize("old,new,key,words", BREAKS)
def test_light_size_broken_one_field_at_a_time(tmp_path, old, new, key, words):
    assert old in RECT
    assert_broken_field(Site.load, write(tmp_path, RECT.replace(old, new, 1)), key, words)


def test_duplicate_check_on_a_large_map(tmp_path):
    """Thousands of lights: the k-d tree finds the one duplicate (first pair by index)."""
    g = np.stack(np.meshgrid(np.arange(60) * 1.5, np.arange(60) * 2.0), -1).reshape(-1, 2)
    g = np.vstack([g, g[1234] + [0.0002, 0.0]])
    text = "ceiling_height: 3.0\nlights:\n" + "".join(f"  - [{a}, {b}]\n" for a, b in g)
    with pytest.raises(ConfigError, match=rf"lights\[{len(g) - 1}\]: duplicate light: "
                                          r"same place as lights\[1234\]"):
        Site.load(write(tmp_path, text))
