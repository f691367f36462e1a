"""A site of many lights: read by libyaml past FAST_YAML_BYTES with the same checks and
the same messages, its lights read at once (issue 38)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from ceilkit.runtime.config.inputs import YAML_MAX_BYTES
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import FAST_YAML_BYTES, StrictLoader, parse_yaml
from ceilkit.runtime.errors import ConfigError


def site_text(lights: np.ndarray, extra: str = "") -> str:
    return ("ceiling_height: 3.0\n" + extra + "lights:\n"
            + "".join(f"  - [{x:.4f}, {y:.4f}]\n" for x, y in lights))


def grid(n: int) -> np.ndarray:
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1)
    return g.reshape(-1, 2)[:n] * 1.6 + 0.1


def slow(text: str):
    loader = StrictLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def test_a_large_site_reads_as_the_strict_loader_reads_it(tmp_path: Path):
    text = site_text(grid(4000), "light_diameter: 0.12\n")
    assert len(text) > FAST_YAML_BYTES
    assert parse_yaml(text.encode()) == slow(text)
    p = tmp_path / "site.yaml"
    p.write_text(text)
    site = Site.load(p)
    np.testing.assert_allclose(site.lights_m, np.round(grid(4000), 4))
    assert site.light_diameter_m == 0.12


def test_a_site_of_100000_lights_is_within_the_size_cap(tmp_path: Path):
    text = site_text(grid(100000) + 1000.0)
    assert len(text.encode()) < YAML_MAX_BYTES
    p = tmp_path / "site.yaml"
    p.write_text(text)
    assert Site.load(p).lights_m.shape == (100000, 2)


def test_a_large_file_with_a_key_twice_says_so_as_a_small_one():
    text = site_text(grid(4000)) + "ceiling_height: 2.0\n"
    with pytest.raises(ConfigError) as big:
        parse_yaml(text.encode(), "site.yaml")
    with pytest.raises(ConfigError) as small:
        parse_yaml(b"ceiling_height: 3.0\nceiling_height: 2.0\n", "site.yaml")
    assert "ceiling_height" in str(big.value) and "duplicate key" in str(big.value)
    assert str(small.value).split(":")[1] == str(big.value).split(":")[1]


def test_invalid_yaml_in_a_large_file_has_the_strict_loaders_message():
    text = site_text(grid(4000)) + "  - [1.0, 2.0\n"
    with pytest.raises(ConfigError) as got:
        parse_yaml(text.encode(), "site.yaml")
    with pytest.raises(yaml.YAMLError) as want:
        slow(text)
    mark = want.value.problem_mark
    assert f"line {mark.line + 1}, column {mark.column + 1}" in str(got.value)


@pytest.mark.parametrize(("item", "message"), [
    ("[1.0, a]", r"lights\[2000\]"),
    ("[1.0, 2.0, 3.0]", r"lights\[2000\].*2 numbers"),
    ("[1.0, .inf]", r"lights\[2000\]"),
    ("[1.0, 2.0e10]", r"lights\[2000\]"),
    ("[true, 2.0]", r"lights\[2000\]"),
])
def test_a_bad_light_among_many_is_named(tmp_path: Path, item: str, message: str):
    lines = site_text(grid(4000)).splitlines()
    lines[2 + 2000] = f"  - {item}"
    p = tmp_path / "site.yaml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=message):
        Site.load(p)


def test_a_duplicate_light_among_many_is_named(tmp_path: Path):
    lights = grid(4000)
    lights[3000] = lights[12]
    p = tmp_path / "site.yaml"
    p.write_text(site_text(lights))
    with pytest.raises(ConfigError, match=r"lights\[3000\].*same place as lights\[12\]"):
        Site.load(p)
