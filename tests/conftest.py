"""Shared fixtures: the example rigs and sites, a scratch folder."""

from __future__ import annotations

import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from helpers import CONFIGS


@pytest.fixture
def corridor_rig() -> Rig:
    return Rig.load(CONFIGS / "corridor" / "rig.yaml")


@pytest.fixture
def corridor_site() -> Site:
    return Site.load(CONFIGS / "corridor" / "site.yaml")


@pytest.fixture
def lights_rig() -> Rig:
    return Rig.load(CONFIGS / "lights" / "rig.yaml")


@pytest.fixture
def lights_site() -> Site:
    return Site.load(CONFIGS / "lights" / "site.yaml")
