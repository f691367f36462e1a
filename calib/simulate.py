"""Simulated recordings, board views and placements, each with its truth.

The library function behind ``ceilcal simulate``: a SPEC recording (``frames/``,
``frames.csv``, ``rig.yaml``, ``site.yaml``) plus ``truth.csv`` holding the vehicle
pose of every frame, written with :class:`ceilkit.runtime.io.recording.RecordingWriter`.

Example::

    traj = straight_drive(300, fps=30.0, speed_mps=0.5, y_m=0.05, weave_m=0.1)
    simulate_recording(rig, site, traj, "out/sim", SimOptions(noise_sigma=2.0), seed=1)

:func:`simulate_boards` renders board views through a camera (for ``ceilcal
intrinsics``), :func:`simulate_placements` the vehicle parked at measured placements
with their placements file (for ``ceilcal mount``).

:func:`make_trajectory` gives the trajectories ``ceilcal simulate`` offers by name
(``drive``, ``random``) or reads one from a ``truth.csv``-layout file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.camera import save_camera
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import atomic_write_bytes
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.io.capture import list_images
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
from ceilkit.runtime.sim.scatter_file import SCENE_FILE, save_scene

from .boards import Board, render_views

PLACEMENTS_FILE = "placements.yaml"


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
    With ``options.scatter`` the recording also holds ``scene.yaml``: every item of
    the scatter rendered (:func:`~ceilkit.runtime.sim.scatter_file.save_scene`), the
    truth a map surveyed from it is scored against.

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
    if options.scatter is not None:
        save_scene(options.scatter, out / SCENE_FILE,
                   "# the simulator scene of this recording (truth; docs/simulator.md)\n")
    return out


DEFAULT_PLACEMENTS: tuple[tuple[float, float], ...] = (
    (0.0, 0.0), (0.25, 0.0), (-0.25, 0.0), (0.1, 12.0), (-0.1, -12.0))
"""``(y_m, yaw_deg)`` of the placements ``ceilcal simulate --kind placements`` renders by
default: three lateral positions and two turned by 12 deg (one turned placement makes
the forward offset observable, docs/calibration.md)."""


def _new_folder(out: Path) -> None:
    """``out`` created; refused when it already holds images, a placements file or a
    recording (``frames.csv``)."""
    if out.exists() and (not out.is_dir() or list_images(out)
                         or (out / PLACEMENTS_FILE).exists() or (out / "frames.csv").exists()):
        raise ConfigError(out, None, "already holds images, a placements file or a "
                          "recording, or is a file; give a new folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(out, None, f"cannot create: {exc.strerror}") from None


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ConfigError(path, None, "cannot encode the image")
    atomic_write_bytes(path, buf.tobytes())


def simulate_boards(board: Board, camera: CameraModel, n_views: int, out_dir: str | Path,
                    seed: int = 0, noise_sigma: float = 2.0, blur_px: float = 0.7,
                    supersample: int = 2, header: str = "") -> Path:
    """Render ``n_views`` views of ``board`` through ``camera`` into ``out_dir`` (new):
    ``view_00.png ...`` (what ``ceilcal intrinsics FOLDER`` reads) and the true camera
    as ``camera_truth.yaml`` (after ``header``).

    The views spread the board over the image and tilt it by up to 40 deg in every
    direction (:func:`~ceilkit.calib.boards.render_views`, every corner in view), from
    ``np.random.default_rng(seed)``. Returns ``out_dir`` as a Path.

    Raises:
        ConfigError: ``views`` (< 5: too few for intrinsics), ``out_dir`` not new.
    """
    if n_views < 5:
        raise ConfigError(None, "views", f"expected at least 5 views, found {n_views}")
    out = Path(out_dir)
    views = render_views(board, camera, n_views, np.random.default_rng(seed),
                         noise_sigma=noise_sigma, blur_sigma_px=blur_px,
                         supersample=supersample)
    _new_folder(out)
    for k, (image, _, _) in enumerate(views):
        _write_png(out / f"view_{k:02d}.png", image)
    save_camera(camera, out / "camera_truth.yaml", header)
    return out


def placement_poses(site: Site, placements: Sequence[tuple[float, float]]) -> Trajectory:
    """The vehicle poses of ``placements`` (``(y_m, yaw_deg)`` each): spread evenly in x
    over the middle half of what the site has on its ceiling, stamped 1 s apart."""
    x0, x1 = site_x_range(site)
    n = len(placements)
    xs = x0 + (x1 - x0) * (0.25 + 0.5 * (np.arange(n) + 0.5) / n)
    ys = np.array([float(y) for y, _ in placements])
    yaws = np.radians([float(a) for _, a in placements])
    return Trajectory(np.arange(n, dtype=np.int64) * 1_000_000_000, xs, ys, yaws)


def simulate_placements(rig: Rig, site: Site, placements: Sequence[tuple[float, float]],
                        out_dir: str | Path, options: SimOptions = SimOptions(),
                        seed: int = 0, header: str = "") -> Path:
    """Render the vehicle parked at each of ``placements`` (``(y_m, yaw_deg)``,
    :func:`placement_poses`) into ``out_dir`` (new): ``p00.png ...``, the placements
    file ``placements.yaml`` (image, y, yaw per placement, as ``ceilcal mount`` reads
    it; the x of each in a comment), the site as ``site.yaml`` and the true rig as
    ``rig_truth.yaml`` (camera inline), each after ``header``.

    Raises:
        ConfigError: ``placements`` (none, or a y or yaw out of range), ``out_dir`` not new.
    """
    if not placements:
        raise ConfigError(None, "placements", "expected at least one placement")
    for y, yaw in placements:
        if not (abs(y) <= 100 and abs(yaw) <= 180):
            raise ConfigError(None, "placements", f"y {y} m, yaw {yaw} deg: expected "
                              "|y| <= 100 m and |yaw| <= 180 deg")
    out = Path(out_dir)
    traj = placement_poses(site, placements)
    src = SimSource(rig, site, traj, options, seed)
    _new_folder(out)
    rows = []
    with src:
        for frame in src:
            name = f"p{frame.index:02d}.png"
            _write_png(out / name, frame.image)
            x, y, yaw = src.pose(frame.index)
            rows.append(f"  - {{image: {name}, y: {y:.4f}, yaw: {math.degrees(yaw):.4f}}}"
                        f"   # x {x:.3f} m")
    atomic_write_bytes(out / PLACEMENTS_FILE,
                       (header + "placements:\n" + "\n".join(rows) + "\n").encode())
    site.save(out / "site.yaml", header)
    rig.save(out / "rig_truth.yaml", header)
    return out


__all__ = ["DEFAULT_PLACEMENTS", "PLACEMENTS_FILE", "make_trajectory", "placement_poses",
           "simulate_boards", "simulate_placements", "simulate_recording", "site_x_range"]
