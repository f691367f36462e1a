"""`ceilcal simulate`: render a simulated recording (frames + truth) for a rig and site."""

from __future__ import annotations

import math
import time
from importlib.resources import files
from pathlib import Path

import numpy as np
import typer

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.sim.render import (
    SimOptions,
    Trajectory,
    load_trajectory,
    random_poses,
    straight_drive,
)


def default_config(name: str) -> Path:
    """A file of the packaged ``configs/corridor`` example."""
    return Path(str(files("ceilkit.configs") / "corridor" / name))


def _site_x_range(site: Site) -> tuple[float, float]:
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
    anything else is a ``truth.csv``-layout file."""
    if kind == "drive":
        return straight_drive(frames, fps, speed_mps, y_m=lateral_m, weave_m=weave_m,
                              yaw_wobble_rad=math.radians(wobble_deg), rng=rng)
    if kind == "random":
        xr = _site_x_range(site)
        if site.corridor is not None or not site.has_lights:
            yr = (lateral_m - 0.3, lateral_m + 0.3)
            yaw = (-math.radians(15), math.radians(15))
        else:
            yr = (float(site.lights_m[:, 1].min()), float(site.lights_m[:, 1].max()))
            yaw = (-math.pi, math.pi)
        return random_poses(frames, xr, yr, yaw, rng, fps)
    path = Path(kind)
    if not path.exists():
        raise ConfigError(path, None, "--trajectory: expected drive, random or a "
                          "truth.csv-layout file; file not found")
    return load_trajectory(path)


# internal names (SimOptions fields, trajectory arguments) -> the flag a user typed
FLAGS = {
    "options.noise_sigma": "--noise", "options.blur_px": "--blur",
    "options.supersample": "--supersample", "n": "--frames", "fps": "--fps",
    "speed_mps": "--speed", "y_m": "--lateral", "weave_m": "--weave",
    "yaw_wobble_rad": "--wobble", "x_range": "--trajectory", "y_range": "--lateral",
}


def _as_flag(exc: ConfigError) -> ConfigError:
    """``exc`` re-keyed by the command-line flag when it names an internal argument."""
    if exc.path is None and exc.key in FLAGS:
        return ConfigError(None, FLAGS[exc.key], exc.detail)
    return exc


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to ``app`` (made by :func:`ceilkit.cli.common.make_app`, whose
    group callback keeps it a subcommand)."""
    @app.command("simulate")
    def simulate(
        out: Path = typer.Option(..., "--out", help="Recording folder to write (new)."),
        rig: Path = typer.Option(None, "--rig", help="rig.yaml (default: packaged corridor)."),
        site: Path = typer.Option(None, "--site",
                                  help="site.yaml (default: packaged corridor)."),
        frames: int = typer.Option(300, "--frames", min=1, help="Number of frames."),
        fps: float = typer.Option(30.0, "--fps", min=0.001, help="Frame rate, Hz."),
        trajectory: str = typer.Option("drive", "--trajectory",
                                       help="drive, random, or a truth.csv-layout file."),
        lateral: float = typer.Option(0.0, "--lateral", help="y of the drive, m."),
        weave: float = typer.Option(0.0, "--weave", help="Sideways weave amplitude, m."),
        wobble: float = typer.Option(0.0, "--wobble", help="Heading wobble amplitude, deg."),
        speed: float = typer.Option(0.5, "--speed", help="Drive speed, m/s."),
        noise: float = typer.Option(2.0, "--noise", help="Sensor noise sigma, grey levels."),
        blur: float = typer.Option(0.8, "--blur", help="Optical blur sigma, px."),
        supersample: int = typer.Option(3, "--supersample", help="Anti-aliasing factor."),
        clutter: bool = typer.Option(False, "--clutter", help="Add distractor lines."),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed for noise and trajectory."),
    ) -> None:
        """Render a simulated recording (frames, rig, site and truth.csv)."""
        rig_path = rig if rig is not None else default_config("rig.yaml")
        site_path = site if site is not None else default_config("site.yaml")
        the_rig, the_site = Rig.load(rig_path), Site.load(site_path)
        try:
            options = SimOptions(noise_sigma=noise, blur_px=blur, supersample=supersample,
                                 clutter=clutter)
            traj = make_trajectory(trajectory, the_site, frames, fps, speed, lateral, weave,
                                   wobble, np.random.default_rng(seed))
        except ConfigError as exc:
            raise _as_flag(exc) from None
        t0 = time.perf_counter()
        folder = simulate_recording(the_rig, the_site, traj, out, options, seed)
        ms = 1e3 * (time.perf_counter() - t0) / len(traj)
        typer.echo(f"wrote {len(traj)} frames ({the_rig.camera.width}x"
                   f"{the_rig.camera.height}) to {folder}: x {traj.x_m.min():.2f}.."
                   f"{traj.x_m.max():.2f} m, y {traj.y_m.min():.3f}..{traj.y_m.max():.3f} m, "
                   f"seed {seed}, {ms:.0f} ms/frame")
