"""The office scene (configs/office: a 0.6 m tile grid with the office scatter) for the
texture tests, rendered once a session: a map built from two rows of frames with truth
poses, another path's frames, and a plain tile grid's map (no scatter)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.texture import CeilingMap, build_map
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.sim.scatter_file import scene_beside
from helpers import CONFIGS

OFFICE = CONFIGS / "office"
# the map's path: two rows along x, one driven sideways, a frame every 0.5 m
MAP_POSES = [(x, y, 0.0 if y < 0 else math.pi / 2) for y in (-0.6, 0.6)
             for x in np.arange(1.0, 5.01, 0.5)]
# another path: a diagonal, headings all round
DRIVE = [(1.6 + 0.35 * k, -1.1 + 0.3 * k, -3.0 + 0.8 * k) for k in range(8)]
# the plain tile grid's map: one row, driven sideways
PLAIN_POSES = [(x, 0.0, math.pi / 2) for x in np.arange(2.0, 4.01, 0.4)]


def frames(rig: Rig, site: Site, poses, options: SimOptions, seed: int) -> list[np.ndarray]:
    """Rendered grey frames at vehicle poses ``(x, y, yaw)``, seeded per frame."""
    return [render_frame(rig, site, *p, options, np.random.default_rng([seed, k]))
            for k, p in enumerate(poses)]


@dataclass(frozen=True)
class Office:
    """The shared scene: ``sites`` maps ``scatter`` / ``plain`` to the office site
    naming that map; ``drive`` holds the frames of ``drive_poses`` (:data:`DRIVE`)."""

    rig: Rig
    sites: dict[str, Site]
    maps: dict[str, CeilingMap]
    opts: SimOptions
    plain_opts: SimOptions
    drive: list[np.ndarray]
    folder: Any
    drive_poses: tuple = tuple(DRIVE)

    def frames(self, poses, seed: int, plain: bool = False) -> list[np.ndarray]:
        """Frames of the scatter (or the plain grid) at ``poses``."""
        return frames(self.rig, self.sites["scatter"], poses,
                      self.plain_opts if plain else self.opts, seed)


@pytest.fixture(scope="session")
def office(tmp_path_factory) -> Office:
    """The rig, the sites with each map, the render options (noise 2, blur 0.8;
    supersample 1 to keep the suite short) and the drive's frames."""
    rig, site = Rig.load(OFFICE / "rig.yaml"), Site.load(OFFICE / "site.yaml")
    out = tmp_path_factory.mktemp("texture")
    opts = SimOptions(scatter=scene_beside(site), supersample=1, noise_sigma=2.0, blur_px=0.8)
    # the plain grid repeats exactly: no world-fixed texture either (the simulator's
    # smooth texture repeats only every 5.12 m, and a map can tell places by it)
    plain_opts = SimOptions(supersample=1, texture=0.0)
    maps = {"scatter": build_map(frames(rig, site, MAP_POSES, opts, 1), MAP_POSES, rig,
                                 site.ceiling_height_m),
            "plain": build_map(frames(rig, site, PLAIN_POSES, plain_opts, 2), PLAIN_POSES,
                               rig, site.ceiling_height_m)}
    sites = {}
    for name, m in maps.items():
        m.save(out / f"{name}.npz")
        sites[name] = dataclasses.replace(site, ceiling_map=str(out / f"{name}.npz"))
    return Office(rig, sites, maps, opts, plain_opts, frames(rig, site, DRIVE, opts, 3), out)
