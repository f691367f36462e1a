"""Simulated recordings: render a trajectory through a rig in a site, with truth.

The library function behind ``ceilcal simulate``: a SPEC recording (``frames/``,
``frames.csv``, ``rig.yaml``, ``site.yaml``) plus ``truth.csv`` holding the vehicle
pose of every frame, written with :class:`ceilkit.runtime.io.recording.RecordingWriter`.

Example::

    traj = straight_drive(300, fps=30.0, speed_mps=0.5, y_m=0.05, weave_m=0.1)
    simulate_recording(rig, site, traj, "out/sim", SimOptions(noise_sigma=2.0), seed=1)
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.recording import RecordingWriter
from ceilkit.runtime.sim.render import SimOptions, SimSource, Trajectory


def _header(trajectory: Trajectory, options: SimOptions, seed: int) -> str:
    opts = ", ".join(f"{f.name}={getattr(options, f.name)!r}" for f in fields(options))
    return (f"# simulated by ceilkit.calib.simulate: {len(trajectory)} frames, seed {seed}\n"
            f"# options: {opts}\n")


def simulate_recording(rig: Rig, site: Site, trajectory: Trajectory, out_dir: str | Path,
                       options: SimOptions = SimOptions(), seed: int = 0) -> Path:
    """Render every pose of ``trajectory`` and write a recording with ``truth.csv``.

    Frame k is stamped ``trajectory.t_ns[k]`` and its noise is drawn from
    ``np.random.default_rng([seed, k])`` (as :class:`SimSource`), so the same
    arguments write the same images. Returns ``out_dir`` as a Path.

    Raises ConfigError if ``out_dir`` already holds a recording or cannot be written.
    """
    out = Path(out_dir)
    if not isinstance(options, SimOptions):
        raise ConfigError(None, "options", "expected SimOptions")
    src = SimSource(rig, site, trajectory, options, seed)
    with src, RecordingWriter(out, rig, site, truth=True,
                              header=_header(trajectory, options, seed)) as rec:
        for frame in src:
            x, y, yaw = src.pose(frame.index)
            rec.write(frame)
            rec.write_truth(frame.t_ns, x, y, yaw)
    return out


__all__ = ["simulate_recording"]
