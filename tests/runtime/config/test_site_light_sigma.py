"""runtime/config/site.py: ``light_sigma`` (ceilkit's extension of SPEC §2: each light's
position 1σ per axis, what ``ceilcal survey`` writes): one number or one per light,
round-tripped; each misuse one ConfigError line naming the file and the dotted key."""

import numpy as np
import pytest

from ceilkit.runtime.config.site import Site
from helpers import assert_broken_field, write_text

SITE = """\
ceiling_height: 2.8
lights:
  - [0.0, 0.0]
  - [3.05, 0.0]
  - [0.0, 3.66]
"""


def test_light_sigma_per_light_and_for_all(tmp_path):
    one = Site.load(write_text(tmp_path, SITE + "light_sigma: [0.001, 0.002, 0.0015]\n"))
    np.testing.assert_array_equal(one.light_sigma_m, [0.001, 0.002, 0.0015])
    every = Site.load(write_text(tmp_path, SITE + "light_sigma: 0.002\n", "all.yaml"))
    np.testing.assert_array_equal(every.light_sigma_m, [0.002] * 3)
    assert Site.load(write_text(tmp_path, SITE, "none.yaml")).light_sigma_m is None


def test_light_sigma_round_trip(tmp_path):
    site = Site.load(write_text(tmp_path, SITE + "light_sigma: [0.001, 0.002, 0.0015]\n"))
    site.save(tmp_path / "again.yaml")
    again = Site.load(tmp_path / "again.yaml")
    np.testing.assert_array_equal(again.light_sigma_m, site.light_sigma_m)
    assert again.to_dict() == site.to_dict()
    assert "light_sigma" not in Site.load(write_text(tmp_path, SITE, "b.yaml")).to_dict()


@pytest.mark.parametrize("text, key, words", [
    ("light_sigma: [0.001, 0.002]\n", "light_sigma", "one 1-sigma per light (3"),
    ("light_sigma: [0.001, -0.002, 0.001]\n", "light_sigma[1]", "expected a number in [0,"),
    ("light_sigma: fine\n", "light_sigma", "a finite number"),
])
def test_light_sigma_misuse(tmp_path, text, key, words):
    assert_broken_field(Site.load, write_text(tmp_path, SITE + text), key, words)


def test_light_sigma_needs_lights(tmp_path):
    path = write_text(tmp_path, "ceiling_height: 2.8\nlight_sigma: 0.001\n")
    assert_broken_field(Site.load, path, "light_sigma", "needs lights")
