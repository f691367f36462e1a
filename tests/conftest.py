"""Shared fixtures: the example rigs and sites, a scratch folder."""

from __future__ import annotations

import fcntl
import os

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


@pytest.fixture(scope="session", autouse=True)
def compiled_loops(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Every compiled loop (runtime/jit.py) made once, before any test: loaded from
    numba's cache, or on a fresh machine compiled here (about 45 s on a slow 2-core VM),
    so a test that starts ``ceilrun`` in a subprocess and waits for its first pose finds
    them cached rather than compiling all of them within its deadline.

    Under pytest-xdist (``-n N``) the workers take turns on a lock in the run's shared
    temporary folder: the first compiles (with its helper processes), the others then
    load its loops from the cache instead of compiling the same loops beside it."""
    import ceilkit.runtime.estimators.registry  # noqa: F401 (every method's modules)
    import ceilkit.runtime.multi  # noqa: F401
    from ceilkit.runtime import jit

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        jit.warm_up()
        return
    lock = tmp_path_factory.getbasetemp().parent / "compiled_loops.lock"
    with open(lock, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            jit.warm_up()
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
