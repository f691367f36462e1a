"""Simulated recordings: render a trajectory through a rig in a site, with truth.

The library function behind ``ceilcal simulate``: a SPEC recording (``frames/``,
``frames.csv``, ``rig.yaml``, ``site.yaml``) plus ``truth.csv`` holding the vehicle
pose of every frame, written with :class:`ceilkit.runtime.io.recording.RecordingWriter`.

Example::

    traj = straight_drive(300, fps=30.0, speed_mps=0.5, y_m=0.05, weave_m=0.1)
    simulate_recording(rig, site, traj, "out/sim", SimOptions(noise_sigma=2.0), seed=1)

:func:`make_trajectory` gives the trajectories ``ceilcal simulate`` offers by name
(``drive``, ``random``) or reads one from a ``truth.csv``-layout file.
"""

from __future__ import annotations

import math
from dataclasses import fields
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.recording import RecordingWriter
from ceilkit.runtime.sim.realism import Realism
from ceilkit.runtime.sim.render import (
    SimOptions,
    SimSource,
    Trajectory,
    load_trajectory,
    random_poses,
    straight_drive,
)


def site_x_range(site: Site) -> tuple[float, float]:
    """The x extent (m) of what a site has on its ceiling: lamps, lights, blocks
    (``(0, 10)`` when it has none of them)."""
    xs: list[float] = []
    for row in site.lamps:
        xs += [float(row.centres()[0, 0]), float(row.centres()[-1, 0])]
    if site.has_lights:
        xs += [float(site.lights_m[:, 0].min()), float(site.lights_m[:, 0].max())]
    for blk in site.blocks:
        xs += [float(blk.corners_m[:, 0].min()), float(blk.corners_m[:, 0].max())]
    return (min(xs), max(xs)) if xs else (0.0, 10.0)


def make_trajectory(kind: str, site: Site, frames: int, fps: float, speed_mps: float,
                    lateral_m: float, weave_m: float, wobble_deg: float,
                    rng: np.random.Generator) -> Trajectory:
    """``drive``: a straight drive along +x at ``lateral_m``; ``random``: poses spread
    over the site (x over its lamps/lights/blocks, y within 0.3 m of ``lateral_m`` in a
    corridor or over the lights, yaw within +-15 deg in a corridor, any otherwise);
    anything else is a ``truth.csv``-layout file.

    Raises:
        ConfigError: a bad value (keyed by the argument's name: ``y_m``, ``fps``, ...),
            or a trajectory file that is missing or malformed.
    """
    if kind == "drive":
        return straight_drive(frames, fps, speed_mps, y_m=lateral_m, weave_m=weave_m,
                              yaw_wobble_rad=math.radians(wobble_deg), rng=rng)
    if kind == "random":
        xr = site_x_range(site)
        if site.corridor is not None or not site.has_lights:
            yr = (lateral_m - 0.3, lateral_m + 0.3)
            yaw = (-math.radians(15), math.radians(15))
        else:
            yr = (float(site.lights_m[:, 1].min()), float(site.lights_m[:, 1].max()))
            yaw = (-math.pi, math.pi)
        return random_poses(frames, xr, yr, yaw, rng, fps)
    path = Path(kind)
    if not path.exists():
        raise ConfigError(path, None, "file not found (a trajectory is drive, random or a "
                          "truth.csv-layout file)")
    return load_trajectory(path)


def _header(trajectory: Trajectory, options: SimOptions, seed: int,
            realism: Realism | None = None) -> str:
    opts = ", ".join(f"{f.name}={getattr(options, f.name)!r}" for f in fields(options))
    real = f"# realism: {realism.describe()}\n" if realism is not None else ""
    return (f"# simulated by ceilkit.calib.simulate: {len(trajectory)} frames, seed {seed}\n"
            f"# options: {opts}\n{real}")


def simulate_recording(rig: Rig, site: Site, trajectory: Trajectory, out_dir: str | Path,
                       options: SimOptions = SimOptions(), seed: int = 0,
                       realism: Realism | None = None) -> Path:
    """Render every pose of ``trajectory`` and write a recording with ``truth.csv``.

    ``realism``: the realism knobs (:mod:`ceilkit.runtime.sim.realism`), None: off.

    Frame k is stamped ``trajectory.t_ns[k]`` and its noise is drawn from
    ``np.random.default_rng([seed, k])`` (as :class:`SimSource`), so the same
    arguments write the same images. Returns ``out_dir`` as a Path.

    Raises ConfigError if ``out_dir`` already holds a recording or cannot be written.
    """
    out = Path(out_dir)
    if not isinstance(options, SimOptions):
        raise ConfigError(None, "options", "expected SimOptions")
    src = SimSource(rig, site, trajectory, options, seed, realism=realism)
    with src, RecordingWriter(out, rig, site, truth=True,
                              header=_header(trajectory, options, seed, realism)) as rec:
        for frame in src:
            x, y, yaw = src.pose(frame.index)
            rec.write(frame)
            rec.write_truth(frame.t_ns, x, y, yaw)
    return out


__all__ = ["make_trajectory", "simulate_recording", "site_x_range"]
