"""The estimators by name, and which one a site calls for.

A table of classes (each on :class:`~ceilkit.runtime.estimators.base.Estimator`): adding
a method is its module or folder, one line in :data:`ESTIMATORS`, its docs and its tests.

Example::

    est = make_estimator("corridor", rig, site, {"detector": "lsd"})
    est = make_estimator(None, rig, site)          # the site's default method
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Estimator
from ceilkit.runtime.estimators.block.estimator import BlockEstimator
from ceilkit.runtime.estimators.corridor.estimator import CorridorEstimator
from ceilkit.runtime.estimators.lights.estimator import LightsEstimator
from ceilkit.runtime.estimators.paper_block import PaperBlockEstimator
from ceilkit.runtime.estimators.paper_corridor import PaperCorridorEstimator
from ceilkit.runtime.estimators.paper_lights import PaperLightsEstimator
from ceilkit.runtime.estimators.texture.estimator import TextureEstimator

ESTIMATORS: Mapping[str, type[Estimator]] = {
    cls.name: cls for cls in (CorridorEstimator, PaperCorridorEstimator,
                              LightsEstimator, PaperLightsEstimator, BlockEstimator,
                              PaperBlockEstimator, TextureEstimator)
}
"""Every estimator by its name (the ``--method`` values)."""

METHOD_NAMES = tuple(ESTIMATORS)

DEFAULT_ORDER = ("lights", "corridor")
"""The methods a site calls for, best first: a global fix before a partial one."""


AUTO = "auto"
"""``--method auto``: every method the site supports, fused (``runtime/multi.py``)."""

FUSED_METHODS = ("lights", "block", "texture", "corridor")
"""The methods ``auto`` runs where the site supports them (the paper baselines are not)."""


def site_methods(site: Site) -> tuple[str, ...]:
    """The methods of :data:`FUSED_METHODS` that ``site`` supports, best first."""
    return tuple(n for n in FUSED_METHODS if _supports(ESTIMATORS[n], site))


def default_method(site: Site) -> str:
    """The method a site calls for: the first of :data:`DEFAULT_ORDER` it supports."""
    for name in DEFAULT_ORDER:
        if _supports(ESTIMATORS[name], site):
            return name
    raise ConfigError(site.source, None,
                      "the site has neither `lights` nor `corridor`: no method can run")


def _supports(cls: type, site: Site) -> bool:
    if issubclass(cls, Estimator):
        return cls.supports(site)
    return site.has_section(cls.name)  # not yet on the contract (transition)


def make_estimator(name: str | None, rig: Rig, site: Site,
                   options: Mapping[str, Any] | None = None) -> Estimator:
    """Build the estimator ``name`` (or the site's default) for a rig and a site.

    Raises:
        ConfigError: ``method`` for an unknown name, the site's section it lacks, or
            ``options.NAME`` for a bad option.
    """
    name = name or default_method(site)
    if name not in ESTIMATORS:
        raise ConfigError(None, "method",
                          f"unknown method {name!r} (choose from "
                          f"{', '.join((AUTO, *ESTIMATORS))}; {AUTO}: every method the "
                          f"site supports, fused)")
    cls = ESTIMATORS[name]
    if issubclass(cls, Estimator):
        return cls(rig, site, cls.Options.from_mapping(options))
    return cls(rig, site, **dict(options or {}))  # not yet on the contract (transition)
