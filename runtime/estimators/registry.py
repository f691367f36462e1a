"""The estimators by name, and which one a site calls for.

Every estimator is built as ``Cls(rig, site, **options)`` and called per frame::

    est = estimator.estimate(image, t_ns, prior=None)   # -> PoseEstimate | Failure

``image`` is the frame as captured (grey or BGR); ``prior`` is the tracker's
predicted pose for this frame, if any (estimators may use it to resolve
ambiguities or to speed up association, never to fabricate a pose).
"""

from __future__ import annotations

import importlib
from typing import Any, Protocol

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate


class Estimator(Protocol):
    name: str

    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> Estimate:
        ...


# name -> (module, class, what the site must hold)
_METHODS: dict[str, tuple[str, str, str]] = {
    "corridor": ("corridor.estimator", "CorridorEstimator", "corridor"),
    "paper-corridor": ("paper_corridor", "PaperCorridorEstimator", "corridor"),
    "lights": ("lights.estimator", "LightsEstimator", "lights"),
    "paper-lights": ("paper_lights", "PaperLightsEstimator", "lights"),
}

METHOD_NAMES = tuple(_METHODS)


def _site_has(site: Site, section: str) -> bool:
    if section == "corridor":
        return site.corridor is not None
    if section == "lights":
        return site.has_lights
    return False


def default_method(site: Site) -> str:
    """The method a site calls for: lights (global) when it has lights, else corridor."""
    if site.has_lights:
        return "lights"
    if site.corridor is not None:
        return "corridor"
    raise ConfigError(site.source, None,
                      "the site has neither `lights` nor `corridor`: no method can run")


def make_estimator(name: str | None, rig: Rig, site: Site, **options: Any) -> Estimator:
    """Build the estimator ``name`` (or the site's default) for a rig and a site."""
    name = name or default_method(site)
    if name not in _METHODS:
        raise ConfigError(None, "--method",
                          f"unknown method {name!r} (choose from {', '.join(_METHODS)})")
    module, cls, section = _METHODS[name]
    if not _site_has(site, section):
        raise ConfigError(site.source, section,
                          f"method {name!r} needs a `{section}` section in the site file")
    mod = importlib.import_module(f"{__package__}.{module}")
    return getattr(mod, cls)(rig, site, **options)
