"""The calibration workflows: what each ``ceilcal`` command does, as library functions.

Each function reads its inputs, runs the calibration, writes its outputs (with a
provenance header: the time, the command line, the fit report) and returns a frozen
result whose ``lines()`` are the report the command prints; a notebook calls the same
functions. Errors name the function's parameters (``ConfigError(None, "board", ...)``);
the command line maps them to its flags (``cli/common.py``).

* :func:`intrinsics`: a camera from board images, a video or a live camera;
* :func:`mount`: a rig (the camera's mount) from measured placements in a corridor;
* :func:`lightmap`: the ``lights`` of a site map, from known poses or by chaining;
* :func:`simulate`: a simulated recording with truth;
* :func:`calibrate`: intrinsics, then mount, then a check replay, each step skipped
  when its file exists (resumable).

Example::

    board = parse_board("chess:9x6", 0.025)
    run = intrinsics(board, Path("camera.yaml"), folder=Path("shots"))
    print("\\n".join(run.lines()))
"""

from __future__ import annotations

import contextlib
import math
import os
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TextIO

import numpy as np

from ceilkit.runtime.config.camera import load_camera, save_camera
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.config.yaml import atomic_write_bytes
from ceilkit.runtime.errors import CalibrationError, ConfigError, OutputError
from ceilkit.runtime.io.capture import open_video
from ceilkit.runtime.io.outputs import FolderLock, claimed, recording_inputs
from ceilkit.runtime.io.provenance import version_line
from ceilkit.runtime.io.recording import Recording, Truth
from ceilkit.runtime.replay import ReplayResult, replay
from ceilkit.runtime.session import CaptureSettings
from ceilkit.runtime.sim.realism import resolve as resolve_realism
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from ceilkit.runtime.sim.scatter_file import SCENE_FILE, load_scene, scene_beside
from ceilkit.runtime.viz import plots as viz_plots

from .boards import Board
from .export import export_paths, write_exports
from .intrinsics import (
    PLOT_NAMES,
    DetectionCache,
    IntrinsicsResult,
    StopRule,
    calibrate_intrinsics,
    capture_views,
    check_model,
    detect_images,
    image_files,
    write_plots,
)
from .lightmap import (
    KnownLights,
    LightMap,
    chain_header_lines,
    lightmap_header_lines,
    load_pose_table,
    survey_chain,
    survey_lights,
    write_site,
)
from .mount import (
    PARAMS,
    calibrate_mount,
    calibrate_tilt_swing,
    load_drive,
    load_placements,
    unobservable,
)
from .simulate import (
    DEFAULT_PLACEMENTS,
    PLACEMENTS_FILE,
    make_trajectory,
    simulate_placements,
    simulate_recording,
)
from .simulate import simulate_boards as simulate_board_views

Progress = Callable[[int, int, str, bool], None]
"""``progress(i, n, name, found)`` after each image of a detection."""


def provenance_header(what: str, lines: Sequence[str] = (), command: str | None = None) -> str:
    """YAML comment lines naming the time, the version that wrote the file, the command
    line (``command``, default this process's ``sys.argv``) and a report."""
    command = shlex.join(sys.argv) if command is None else command
    out = [f"# {what}",
           f"# written {datetime.now(timezone.utc).isoformat(timespec='seconds')} by "
           f"{version_line()}",
           f"# command: {command}"]
    out += [f"# {line}" for line in lines]
    return "\n".join(out) + "\n"


def _check_writable(out: Path) -> None:
    parent = out.parent if str(out.parent) else Path(".")
    if out.is_dir():
        raise OutputError(out, "is a folder; expected a file path")
    if not parent.is_dir():
        raise OutputError(out, f"cannot write: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise OutputError(out, f"cannot write: folder {parent} is not writable")


MOUNT_PLOT = "mount_residuals.png"
LIGHTMAP_PLOT = "lightmap.png"


def _claim(out: Path, force: bool, inputs: Sequence[str | Path | None] = (),
           beside: Sequence[Path] = (), plots: Path | None = None,
           plot_names: Sequence[str] = ()) -> contextlib.AbstractContextManager[None]:
    """Claim ``out``, the files written ``beside`` it and ``plot_names`` in the ``plots``
    folder for a ``with`` block (:func:`~ceilkit.runtime.io.outputs.claimed`): refused
    when one is an input, lies in one, or exists without ``force`` (one line naming the
    file; the command line says ``give --force``); locked until the block ends (``out``
    by ``.NAME.ceilkit.lock`` beside it, ``plots`` by its folder's lock), so that a second
    run is refused at once rather than writing over the first one's file."""
    outputs = {"out": [Path(out), *beside]}
    folders = {}
    if plots is not None:
        outputs["plots"] = [Path(plots) / name for name in plot_names]
        folders["plots"] = [Path(plots)]
    return claimed(outputs, folders=folders, force=force,
                   inputs=[Path(p) for p in inputs if p is not None])


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(folder, f"cannot create: {exc.strerror}") from None


def _write_plot(folder: Path, name: str, png: bytes) -> Path:
    """``folder/name`` (the folder created if missing), written atomically."""
    _make_folder(folder)
    path = folder / name
    atomic_write_bytes(path, png)
    return path


# -- intrinsics ------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IntrinsicsRun:
    """A written camera: the fit, where it went, what it came from, the plots."""

    result: IntrinsicsResult
    camera_path: Path
    inputs: str
    plots: tuple[Path, ...] = ()

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(self.result.report.warnings)

    def lines(self) -> list[str]:
        return ([self.result.report.text(), f"wrote {self.camera_path}"]
                + [f"wrote {p}" for p in self.plots])


def intrinsics(board: Board, out: Path, *, folder: Path | None = None,
               video: Path | None = None, device: str | None = None,
               model: str = "plumb_bob", plots: Path | None = None, name: str = "camera",
               fix_aspect_ratio: bool = False, min_views: int = 5, max_views: int = 40,
               every: int = 1, cache: bool = True, progress: Progress | None = None,
               meter: TextIO | None = None,
               capture: CaptureSettings = CaptureSettings(),
               force: bool = False) -> IntrinsicsRun:
    """Calibrate a camera from ``board`` views and write ``out`` (camera.yaml).

    Exactly one source: ``folder`` (images; detections cached beside ``out`` unless
    ``cache`` is False), ``video`` (a file) or ``device`` (a live camera); a stream keeps
    the diverse views until coverage and accuracy suffice (``max_views`` at most,
    ``every`` N-th frame), drawing a coverage meter on ``meter``. ``capture``: the
    camera's format, exposure and gain for ``device`` (as ``ceilrun`` opens it).
    ``force``: replace an existing ``out`` (refused otherwise, before any work).

    Raises:
        ConfigError: ``source`` (not exactly one), ``model``, ``board`` (wrong size);
            ``out`` exists (without ``force``) or is an input.
        OutputError: ``out`` cannot be written.
        CalibrationError: no board found, too few views.
    """
    sources = [s for s in (folder, video, device) if s is not None]
    if len(sources) != 1:
        raise ConfigError(None, "source", f"give exactly one image source, found "
                          f"{len(sources)}")
    check_model(model)
    _check_writable(out)
    # beside the board images is fine: no image is replaced
    with _claim(out, force, [video], plots=plots, plot_names=PLOT_NAMES):
        if folder is not None:
            files = image_files(folder)
            det_cache = DetectionCache(out.parent / f".{out.stem}.detections.npz") if cache \
                else None
            views = detect_images(files, board, det_cache, progress)
            inputs = f"{folder} ({len(files)} images, {len(views)} with the board)"
        else:
            src = open_video(str(video) if video is not None else str(device),
                             capture.width, capture.height, capture.fps, capture.fourcc,
                             capture.exposure, capture.gain)
            stop = StopRule(max_views=max_views, min_views=max(12, min_views))
            views = capture_views(src, board, model, stop, every=every, meter=meter)
            inputs = f"{video if video is not None else f'device {device}'} ({len(views)} views)"
        result = calibrate_intrinsics(views, model, fix_aspect_ratio=fix_aspect_ratio,
                                      min_views=min_views, name=name)
        square = f", square {board.square_m:g} m"
        header = provenance_header("camera intrinsics by ceilcal intrinsics",
                                   [f"inputs: {inputs}", f"board: {board.spec}{square}"]
                                   + result.report.summary_lines())
        save_camera(result.camera, out, header)
        written = tuple(write_plots(result, plots)) if plots is not None else ()
        return IntrinsicsRun(result, out, inputs, written)


# -- mount -----------------------------------------------------------------------------
@dataclass(frozen=True)
class MountRun:
    """A written rig and the report of its fit."""

    rig_path: Path
    report: tuple[str, ...]
    plots: tuple[Path, ...] = ()
    exports: tuple[Path, ...] = ()

    def lines(self) -> list[str]:
        return [*self.report, f"wrote {self.rig_path}"] + [
            f"wrote {p}" for p in self.exports + self.plots]


def _save_rig(rig: Rig, out: Path, header: str, camera_ref: str | None) -> tuple[Path, ...]:
    """Write ``rig`` to ``out`` (naming ``camera_ref`` relative to it) and, beside it,
    the mount as a URDF joint, a ROS 2 static transform and ArduPilot VISO_POS_X/Y/Z
    (:func:`~ceilkit.calib.export.write_exports`, the same header). Returns those."""
    ref = None
    if camera_ref is not None:
        ref = os.path.relpath(Path(camera_ref).resolve(), Path(out).resolve().parent)
    rig.save(out, header, camera_ref=ref)
    return write_exports(rig.mount, out, header).paths()


def parse_fix(fix: Sequence[str]) -> dict[str, float | None]:
    """``--fix`` values: ``NAME=VALUE`` (degrees for ``pan tilt swing``, metres for
    ``mx my h``; ``h`` is the camera's distance below the ceiling) or ``NAME`` (the
    rig's value). Returns name -> value in radians / metres, or None.

    Raises:
        ConfigError: ``fix``: an unknown name or a value that is not a number.
    """
    out: dict[str, float | None] = {}
    for item in fix:
        name, sep, text = str(item).partition("=")
        name = name.strip()
        if name not in PARAMS:
            raise ConfigError(None, "fix", f"unknown parameter {name!r} "
                              f"(choose from {', '.join(PARAMS)}; NAME or NAME=VALUE)")
        if not sep:
            out[name] = None
            continue
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(None, "fix", f"{name}={text!r}: expected a number "
                              "(degrees for pan, tilt, swing; metres for mx, my, h)") from None
        if not math.isfinite(value):
            raise ConfigError(None, "fix", f"{name}={text!r}: expected a finite number")
        out[name] = math.radians(value) if name in ("pan", "tilt", "swing") else value
    return out


def _fixed_mount(base: Mount, fixes: dict[str, float | None], ceiling_m: float) -> Mount:
    """``base`` with the typed ``--fix`` values put in (``h`` as a height below the
    ceiling)."""
    names = {"pan": "pan_rad", "tilt": "tilt_rad", "swing": "swing_rad", "mx": "x_m",
             "my": "y_m"}
    kw = {names[n]: v for n, v in fixes.items() if v is not None and n in names}
    if fixes.get("h") is not None:
        kw["z_m"] = ceiling_m - float(fixes["h"])
    return replace(base, **kw)


def _fix_lines(fixes: dict[str, float | None], rig: Path | None) -> list[str]:
    out = []
    for name, value in fixes.items():
        if value is None:
            out.append(f"held by --fix: {name} at the value of {rig} (not measured here)")
        elif name in ("pan", "tilt", "swing"):
            out.append(f"held by --fix: {name} = {math.degrees(value):.4f} deg (typed, "
                       "not measured)")
        else:
            out.append(f"held by --fix: {name} = {value:.4f} m (typed, not measured)")
    return out


def _start_rig(rig: str | Path | None, camera: str | Path | None) -> tuple[Rig, str | None]:
    """The rig a mount fit starts from (``rig``, else ``camera`` on a nominal mount at
    0.5 m) and the camera file the written rig.yaml names."""
    if rig is not None:
        the_rig = Rig.load(rig)
        return the_rig, the_rig.camera_file
    return Rig(load_camera(camera), Mount(z_m=0.5)), str(camera)


def _parse_mount_fixes(fix: Sequence[str], rig: Path | None) -> dict:
    """``--fix`` parsed; a bare ``NAME`` (hold the rig's value) needs a rig."""
    fixes = parse_fix(fix)
    for name, value in fixes.items():
        if value is None and rig is None:
            raise ConfigError(None, "fix", f"--fix {name} holds the rig's value, but there "
                              f"is no --rig: give the measured value, {name}=VALUE")
    return fixes


def _require_observable(pls, fixes: dict, has_drive: bool) -> None:
    """Refuse, before any fit, a parameter the placements cannot determine and nothing
    holds (a drive gives tilt and swing)."""
    missing = dict(unobservable(pls, set(fixes)))
    if has_drive:
        missing.pop("tilt", None)
        missing.pop("swing", None)
    if missing:
        name, why = next(iter(missing.items()))
        raise CalibrationError(
            f"{name} is not observable from these placements: {why}; or measure it and "
            f"give --fix {name}=VALUE. Nothing written")


def _tilt_swing_start(the_rig: Rig, drive: Path, fixes: dict) -> tuple[Mount, str]:
    """Tilt and swing from a straight drive: the mount fit's start (pan and lateral
    offset zero unless held) and the report's line."""
    tilt, swing, rep = calibrate_tilt_swing(the_rig, load_drive(drive, the_rig.camera))
    line = (f"drive ({rep['frames']} frames): tilt {math.degrees(tilt):.4f} "
            f"+- {math.degrees(rep['sigma_tilt']):.4f} deg, swing "
            f"{math.degrees(swing):.4f} +- {math.degrees(rep['sigma_swing']):.4f} "
            f"deg, RMS {rep['rms_px']:.3f} px")
    m = the_rig.mount
    start = Mount(m.pan_rad if "pan" in fixes else 0.0, tilt, swing, m.x_m,
                  m.y_m if "my" in fixes else 0.0, m.z_m)
    return start, line


def mount(placements: Path | None, site: Path, out: Path, *, rig: Path | None = None,
          camera: Path | None = None, drive: Path | None = None,
          fix: Sequence[str] = (), max_frames: int = 8,
          plots: Path | None = None, force: bool = False, **upward) -> MountRun:
    """Fit the mount and write ``out`` (rig.yaml), by the procedure the site calls for:
    a site with ``corridor`` lines, the corridor fit below; a site with ``lights`` only
    (an upward camera), :func:`mount_upward` (``upward`` holds its own arguments).

    The corridor fit: tilt, swing, pan, offsets and the height below the ceiling from
    measured ``placements`` (a placements file or a recording with truth.csv).

    Observability first: before anything is fitted, the parameters the data cannot
    determine (:func:`~ceilkit.calib.mount.unobservable`) are refused unless held by
    ``fix``; a fit whose residuals disagree with the edge points' own noise, whose
    parameters stay undetermined, or in which a placement disagrees with the others is
    refused. Nothing is written when a fit is refused.

    Args:
        rig: a rig whose camera (and held values) to use, or
        camera: camera.yaml when there is no rig yet (one of the two).
        drive: a straight drive (recording or image folder) that gives tilt and swing.
        fix: parameters to hold: ``NAME=VALUE`` or ``NAME`` (the rig's value; needs
            ``rig``), see :func:`parse_fix`; written in the provenance header.
        max_frames: at most this many placements from a recording.
        plots: write ``mount_residuals.png`` (residual RMS per placement, px) here.
        force: replace an existing ``out`` and its exports (``rig.urdf.xml``,
            ``rig.static_tf.sh``, ``rig.viso.param``); refused otherwise, before any work.

    Raises:
        ConfigError: ``camera`` (neither a rig nor a camera), ``fix`` (unknown name, or
            no value without a rig), bad placements or site; ``out`` or an export exists
            (without ``force``), or ``out`` is an input (``--rig rig.yaml --out rig.yaml``).
        CalibrationError: a parameter that is not observable and not held; a fit that
            fails, leaves too large a residual, or whose data disagree.
    """
    if rig is None and camera is None:
        raise ConfigError(None, "camera", "give the camera (camera.yaml) or a rig")
    with _claim(out, force, [placements, site, rig, camera, drive,
                             *(v for v in upward.values() if isinstance(v, str | Path))],
                export_paths(out).paths(), plots=plots, plot_names=(MOUNT_PLOT,)):
        fixes = _parse_mount_fixes(fix, rig)
        the_site = Site.load(site)
        if the_site.corridor is None and the_site.has_lights:
            return mount_upward(placements, the_site, site, out, rig=rig, camera=camera,
                                fix=fixes, **upward)
        if upward:
            raise ConfigError(None, next(iter(upward)), "applies to an upward (lights) rig; "
                              "this site has corridor lines")
        if placements is None:
            raise ConfigError(None, "placements", "the corridor fit needs measured placements "
                              "(a placements file or a recording with truth.csv)")
        the_rig, camera_ref = _start_rig(rig, camera)
        the_rig = the_rig.with_mount(_fixed_mount(the_rig.mount, fixes,
                                                  the_site.ceiling_height_m))
        reasons = {n: (f"--fix {n} (the rig's value)" if v is None else f"--fix {n} (typed)")
                   for n, v in fixes.items()}
        pls = load_placements(placements, the_rig.camera, max_frames)
        _require_observable(pls, fixes, drive is not None)
        start, lines = None, []
        if drive is not None:
            start, line = _tilt_swing_start(the_rig, drive, fixes)
            lines.append(line)
            reasons.update(tilt="from the drive", swing="from the drive")
        res = calibrate_mount(the_rig, the_site, pls, fixed=reasons, start=start,
                              fit_height=None if "h" not in reasons else False)
        if res.outliers:
            label, rms, why = res.outliers[0]
            raise CalibrationError(
                f"placement {label} disagrees with the others: {why} (RMS {rms:.2f} px); "
                "re-measure it or leave it out. Nothing written")
        lines += res.lines() + _fix_lines(fixes, rig)
        header = provenance_header(
            "rig.yaml: the camera's mount fitted from placements",
            [f"placements: {placements} ({len(pls)})", f"site: {site}"]
            + ([f"drive: {drive}"] if drive else []) + lines)
        exports = _save_rig(the_rig.with_mount(res.mount), out, header, camera_ref)
        written = () if plots is None else (_write_plot(plots, MOUNT_PLOT,
            viz_plots.mount_png(res.per_placement_rms_px, res.rms_px,
                                [o[0] for o in res.outliers])),)
        return MountRun(Path(out), tuple(lines), written, exports)


def mount_upward(recording: Path | None, the_site: Site, site: Path, out: Path, *,
                 rig: Path | None = None, camera: Path | None = None,
                 fix: dict[str, float | None] | None = None, poses: Path | None = None,
                 max_frames: int = 120, spin: bool = False) -> MountRun:
    """Fit an upward (lights) rig's mount from a drive under the site's ``lights`` and
    write ``out`` (rig.yaml) when every parameter is determined
    (:func:`~ceilkit.calib.mount_upward.calibrate_mount_upward`).

    ``recording``: a recording (frames and, unless ``poses`` is given, ``truth.csv``
    with the vehicle's poses at the frame stamps). ``poses``: a ``t_ns,x,y,yaw_deg``
    table at its own stamps (motion capture, a total station): interpolated, and its
    time offset to the frames estimated and reported. The rig's (or nominal: tilt 90,
    at the vehicle's origin, 0.5 m up) mount is only the start of the search.
    ``spin``: the recording is a spin in place, no poses (:func:`mount_spin`).

    Raises:
        ConfigError: ``placements`` (no recording), ``fix`` (the upward fit holds
            nothing), ``poses`` / truth.csv missing or malformed.
        CalibrationError: too few frames with lights and poses, a residual or a
            parameter's 1 sigma above its limit (naming what to add); nothing written.
    """
    from .mount_upward import calibrate_mount_upward, load_light_frames, load_pose_csv

    if recording is None:
        raise ConfigError(None, "placements", "the upward (lights) fit needs a recording "
                          "of a drive under the lights")
    if spin:
        if poses is not None:
            raise ConfigError(None, "poses", "a spin in place needs no poses (give "
                              "either --spin or --poses)")
        return mount_spin(recording, the_site, site, out, rig=rig, camera=camera,
                          fix=fix or {}, max_frames=max_frames)
    if poses is None and not (Path(recording) / "truth.csv").exists():
        if fix and "my" in fix:
            return mount_drive(recording, the_site, site, out, rig=rig, camera=camera,
                               fix=fix, max_frames=max_frames)
        raise ConfigError(Path(recording) / "truth.csv", None,
                          "file not found: the upward fit needs the vehicle's poses "
                          "(truth.csv, or --poses a t_ns,x,y,yaw_deg table); with none, "
                          "a drive gives all but the lever arm's y: hold it with --fix "
                          "my=VALUE (measured, or from --spin)")
    if fix:
        raise ConfigError(None, "fix", "the upward (lights) fit with poses determines "
                          "every parameter or refuses; it holds none (--fix applies to "
                          "the corridor fit, a spin or a drive without poses)")
    the_rig, camera_ref = _start_rig(rig, camera)
    _check_writable(out)
    frames, table = load_light_frames(recording, the_rig, max_frames)
    if poses is not None:
        table = load_pose_csv(poses)
    res = calibrate_mount_upward(the_rig, the_site, frames, table,
                                 estimate_offset=None if poses is None else True)
    lines = res.lines()
    header = provenance_header(
        "rig.yaml: the camera's mount fitted from a drive (upward lights rig)",
        [f"drive: {recording} ({len(frames)} frames)", f"site: {site}"]
        + ([f"poses: {poses}"] if poses is not None else []) + lines)
    exports = _save_rig(the_rig.with_mount(res.mount), out, header, camera_ref)
    return MountRun(Path(out), tuple(lines), exports=exports)


# -- light map -------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LightmapRun:
    """A written site map with surveyed lights; ``how``: how they were surveyed."""

    lightmap: LightMap
    site_path: Path
    how: str
    plots: tuple[Path, ...] = ()

    def lines(self) -> list[str]:
        lm = self.lightmap
        return [f"{self.site_path}: {lm.lights_m.shape[0]} lights from {self.how}; median "
                f"1-sigma {1e3 * float(np.median(lm.sigma_m)):.1f} mm"] \
            + [f"wrote {p}" for p in self.plots]


def mount_spin(recording: Path, the_site: Site, site: Path, out: Path, *,
               rig: Path | None = None, camera: Path | None = None,
               fix: dict[str, float | None], max_frames: int = 120) -> MountRun:
    """Fit an upward rig's lean, lever arm and height from a spin in place under the
    site's ``lights``, no poses (:func:`~ceilkit.calib.mount_spin.calibrate_mount_spin`),
    the pan held at ``fix['pan']`` (a spin cannot determine it); write ``out``.

    Raises:
        ConfigError: ``fix``: no pan, or a parameter other than pan.
        CalibrationError: too little turn, not in place, an undetermined parameter.
    """
    from .mount_spin import calibrate_mount_spin

    if "pan" not in fix:
        raise ConfigError(None, "fix", "a spin in place does not determine the pan (the "
                          "lever arm turns with it): measure it and give --fix pan=DEG, "
                          "or --fix pan with a --rig holding it, or drive under the lights "
                          "with poses instead. Nothing written")
    the_rig, camera_ref, frames, start = _held_start(
        recording, the_site, out, rig, camera, fix, "pan", "the spin fit", max_frames)
    pan = the_rig.mount.pan_rad + the_rig.mount.swing_rad if fix["pan"] is None \
        else fix["pan"]
    res = calibrate_mount_spin(the_rig, the_site, frames, start, pan)
    return _save_held_fit(the_rig, res, out, camera_ref, "spin in place",
                          f"spin: {recording} ({len(frames)} frames placed)", site,
                          "pan", fix["pan"] is None)


def mount_drive(recording: Path, the_site: Site, site: Path, out: Path, *,
                rig: Path | None = None, camera: Path | None = None,
                fix: dict[str, float | None], max_frames: int = 120) -> MountRun:
    """Fit an upward rig's pan, lean, ``x`` and height from a drive under the site's
    ``lights`` with no poses, the wheels' no-sideways-motion tying the camera's path to
    the vehicle's (:func:`~ceilkit.calib.mount_drive.calibrate_mount_drive`), ``y`` held
    at ``fix['my']`` (a drive cannot determine it); write ``out``.

    Raises:
        ConfigError: ``fix``: a parameter other than my.
        CalibrationError: too few frames, an undetermined parameter (naming what to add).
    """
    from .mount_drive import calibrate_mount_drive

    the_rig, camera_ref, frames, start = _held_start(
        recording, the_site, out, rig, camera, fix, "my", "the drive fit", max_frames)
    my = the_rig.mount.y_m if fix["my"] is None else fix["my"]
    res = calibrate_mount_drive(the_rig, the_site, frames, start, my)
    return _save_held_fit(the_rig, res, out, camera_ref, "drive without poses",
                          f"drive: {recording} ({len(frames)} frames placed)", site, "my",
                          fix["my"] is None)


def _held_start(recording: Path, the_site: Site, out: Path, rig: Path | None,
                camera: Path | None, fix: dict[str, float | None], held: str, fit: str,
                max_frames: int):
    """For an upward fit holding ``held`` only: refuse any other ``--fix``, then the
    start rig, its camera file, and the recording's frames placed by the lights with
    their start poses (:func:`~ceilkit.calib.mount_spin.load_placed_frames`)."""
    from .mount_spin import load_placed_frames

    extra = sorted(set(fix) - {held})
    if extra:
        label = "the pan" if held == "pan" else held
        raise ConfigError(None, "fix", f"--fix {extra[0]}: {fit} determines it; "
                          f"only {label} can be held")
    the_rig, camera_ref = _start_rig(rig, camera)
    _check_writable(out)
    frames, start = load_placed_frames(Recording(recording), the_rig, the_site, max_frames)
    return the_rig, camera_ref, frames, start


def _save_held_fit(the_rig: Rig, res, out: Path, camera_ref, kind: str, source: str,
                   site: Path, held: str, from_rig: bool) -> MountRun:
    """Write an upward fit that held one parameter (``held``), saying so in the header."""
    lines = res.lines()
    how = "the rig's value" if from_rig else "typed"
    header = provenance_header(
        f"rig.yaml: the camera's mount fitted from a drive (upward lights rig, {kind})",
        [source, f"site: {site}",
         f"held: {held} (--fix {held}, {how}; not measured by this fit)"] + lines)
    exports = _save_rig(the_rig.with_mount(res.mount), out, header, camera_ref)
    return MountRun(Path(out), tuple(lines), exports=exports)


def lightmap(recording: Path, out: Path, *, poses: Path | None = None,
             known: KnownLights | None = None, ceiling_height_m: float | None = None,
             cluster_m: float = 0.15, min_views: int = 3,
             plots: Path | None = None, pose_offset_ms: float | None = None,
             force: bool = False) -> LightmapRun:
    """Survey the ceiling lights of ``recording`` and write them as the ``lights`` of
    ``out`` (site.yaml; its other sections kept when it exists, else the recording's).

    With ``known`` (lights measured in W), the frames are chained (no pose needed);
    otherwise each frame's pose comes from ``poses`` (truth.csv or poses.csv layout) or
    the recording's truth.csv; poses at their own stamps are interpolated and their
    time offset estimated unless ``pose_offset_ms`` gives it. ``plots``: write
    ``lightmap.png`` there (each light's 1σ, the drive: the poses used, or the
    recording's truth.csv). ``force``: write into an existing ``out`` (refused
    otherwise, before any work; its other sections are kept).

    Raises:
        ConfigError: ``poses`` with ``known``; bad inputs or options; ``out`` exists
            (without ``force``), is an input or lies in the recording
            (``REC/site.yaml``).
        CalibrationError: a survey that cannot be tied or solved.
    """
    with _claim(out, force, [*recording_inputs(recording), poses], plots=plots,
                plot_names=(LIGHTMAP_PLOT,)):
        rec = Recording(recording)
        base = Site.load(out) if out.exists() else rec.site
        if known is None:
            table = load_pose_table(poses) if poses is not None else None
            lm = survey_lights(rec, table, ceiling_height_m=ceiling_height_m,
                               cluster_m=cluster_m, min_views=min_views,
                               offset_s=None if pose_offset_ms is None else pose_offset_ms / 1e3)
            header = provenance_header("ceilcal lightmap: site map with surveyed lights",
                                       lightmap_header_lines(lm))
            write_site(lm, out, base, header, ceiling_height_m)
            drive = table if table is not None else rec.truth
            return LightmapRun(lm, out, f"{lm.frames_used} frames",
                               _lightmap_plot(plots, lm, drive, base))
        if poses is not None or pose_offset_ms is not None:
            raise ConfigError(None, "poses", "a chaining survey (known lights) uses no poses")
        res = survey_chain(rec, known, ceiling_height_m=ceiling_height_m, min_views=min_views)
        lm = res.lightmap
        header = provenance_header(
            "ceilcal lightmap: site map with lights surveyed by chaining frames",
            chain_header_lines(res))
        write_site(lm, out, base, header,
                   res.ceiling_height_m if res.height_fitted else ceiling_height_m)
        how = (f"{lm.frames_used} chained frames ({res.unplaced} not placed), "
               f"residual {res.rms_px:.2f} px")
        if res.height_fitted:
            how += (f"; ceiling height {res.ceiling_height_m:.4f} +- "
                    f"{res.height_sigma_m:.4f} m from the two known lights")
        return LightmapRun(lm, out, how, _lightmap_plot(plots, lm, rec.truth, base))


def _lightmap_plot(plots: Path | None, lm: LightMap, drive: Truth | None,
                   site: Site) -> tuple[Path, ...]:
    if plots is None:
        return ()
    xy = None if drive is None else np.stack([drive.x_m, drive.y_m], axis=1)
    return (_write_plot(plots, LIGHTMAP_PLOT,
                        viz_plots.lightmap_png(lm.lights_m, lm.sigma_m, lm.views, xy, site)),)


# -- simulate --------------------------------------------------------------------------
def packaged_file(name: str, example: str = "corridor") -> Path:
    """A file of a packaged example (``configs/corridor/rig.yaml``, ...)."""
    from importlib.resources import files

    return Path(str(files("ceilkit.configs") / example / name))


@dataclass(frozen=True, eq=False)
class SimulateRun:
    """A written simulated recording."""

    folder: Path
    trajectory: Trajectory
    width: int
    height: int
    seed: int
    ms_per_frame: float
    scene: str = ""         # the scatter rendered (Scatter.describe()), "" for none

    def lines(self) -> list[str]:
        t = self.trajectory
        out = [f"wrote {len(t)} frames ({self.width}x{self.height}) to {self.folder}: "
               f"x {t.x_m.min():.2f}..{t.x_m.max():.2f} m, y {t.y_m.min():.3f}.."
               f"{t.y_m.max():.3f} m, seed {self.seed}, {self.ms_per_frame:.0f} ms/frame"]
        if self.scene:
            out.append(f"scene {self.scene}, items in {self.folder / SCENE_FILE}")
        return out


def parse_placements(items: Sequence[str]) -> list[tuple[float, float]]:
    """``--placement Y,YAW`` items (metres, degrees) as ``(y_m, yaw_deg)``.

    Raises:
        ConfigError: ``placements``: an item that is not two numbers.
    """
    out = []
    for item in items:
        parts = str(item).split(",")
        try:
            y, yaw = (float(v) for v in parts)
        except ValueError:
            raise ConfigError(None, "placements", f"expected Y,YAW (m, deg), found "
                              f"{item!r}") from None
        out.append((y, yaw))
    return out


@dataclass(frozen=True)
class SimulatedFiles:
    """A written folder of simulated images (board views, placements) and their truth."""

    folder: Path
    what: str
    seed: int

    def lines(self) -> list[str]:
        return [f"wrote {self.what} to {self.folder}, seed {self.seed}"]


def simulate_boards(out: Path, board: Board, *, camera: Path | None = None,
                    rig: Path | None = None, views: int = 30, seed: int = 0,
                    noise_sigma: float = 2.0, blur_px: float = 0.7,
                    supersample: int = 2) -> SimulatedFiles:
    """Render ``views`` board views through ``camera`` (camera.yaml; default the camera
    of ``rig``, default the packaged corridor's) into ``out`` (new), with the true
    camera as ``camera_truth.yaml`` (:func:`~ceilkit.calib.simulate.simulate_boards`).

    Raises:
        ConfigError: ``views``, a bad camera or rig file, ``out`` not new.
    """
    if camera is not None:
        the_camera = load_camera(camera)
    else:
        the_camera = Rig.load(rig if rig is not None else packaged_file("rig.yaml")).camera
    if noise_sigma < 0 or blur_px < 0 or supersample < 1:
        raise ConfigError(None, "options.noise_sigma" if noise_sigma < 0 else
                          "options.blur_px" if blur_px < 0 else "options.supersample",
                          "expected noise >= 0, blur >= 0, supersample >= 1")
    marker = getattr(board, "marker_m", None)
    header = provenance_header("true camera of simulated board views by ceilcal simulate",
                               [f"board: {board.spec}, square {board.square_m:g} m"
                                + (f", marker {marker:g} m" if marker is not None else ""),
                                f"{views} views, seed {seed}"])
    folder = simulate_board_views(board, the_camera, views, out, seed, noise_sigma, blur_px,
                                  supersample, header)
    return SimulatedFiles(folder, f"{views} views of {board.spec} "
                          f"({the_camera.width}x{the_camera.height}) and camera_truth.yaml",
                          seed)


def simulate(out: Path, *, rig: Path | None = None, site: Path | None = None,
             frames: int = 300, fps: float = 30.0, trajectory: str = "drive",
             lateral_m: float = 0.0, weave_m: float = 0.0, wobble_deg: float = 0.0,
             speed_mps: float = 0.5, noise_sigma: float = 2.0, blur_px: float = 0.8,
             supersample: int = 3, clutter: bool = False, seed: int = 0,
             sim_preset: str | None = None, sim_faults: tuple[str, ...] = (),
             placements: Sequence[tuple[float, float]] | None = None,
             scene: Path | None = None) -> SimulateRun | SimulatedFiles:
    """Render a simulated recording (frames, rig, site, truth.csv) into ``out`` (new).

    ``rig`` and ``site`` default to the packaged corridor example's; ``trajectory`` is
    ``drive``, ``random`` or a truth.csv-layout file
    (:func:`~ceilkit.calib.simulate.make_trajectory`). ``sim_preset`` names a preset
    of the ``presets.yaml`` beside the site, ``sim_faults`` are ``KNOB=VALUE`` realism
    knobs on top (:func:`ceilkit.runtime.sim.realism.resolve`). Nothing is written when
    an argument is bad.

    ``placements`` (``(y_m, yaw_deg)`` each; empty: the default set): instead of a
    drive, the vehicle parked at each, with the placements file ``ceilcal mount`` reads
    (:func:`~ceilkit.calib.simulate.simulate_placements`).

    ``scene``: a scene file (a scatter of panels, vents, sprinklers, ... on the site's
    tile grid: :mod:`ceilkit.runtime.sim.scatter_file`); None: the ``scene.yaml``
    beside the site, if there is one. A drive writes its items into the recording's
    ``scene.yaml``.

    Raises:
        ConfigError: a bad value, keyed by the name of the field it sets
            (``options.noise_sigma``, ``y_m``, ...); bad rig, site or trajectory file.
    """
    the_rig = Rig.load(rig if rig is not None else packaged_file("rig.yaml"))
    site_file = site if site is not None else packaged_file("site.yaml")
    the_site = Site.load(site_file)
    realism = resolve_realism(site_file, sim_preset, tuple(sim_faults))
    scatter = scene_beside(the_site) if scene is None else load_scene(scene, the_site)
    options = SimOptions(noise_sigma=noise_sigma, blur_px=blur_px, supersample=supersample,
                         clutter=clutter, scatter=scatter)
    if placements is not None:
        if realism is not None and realism.active:
            raise ConfigError(None, "sim-preset", "applies to drives, not placements")
        header = provenance_header("simulated placements by ceilcal simulate (truth)")
        folder = simulate_placements(the_rig, the_site, placements or DEFAULT_PLACEMENTS,
                                     out, options, seed, header)
        return SimulatedFiles(folder, f"{len(placements or DEFAULT_PLACEMENTS)} "
                              f"placements and {folder / PLACEMENTS_FILE}", seed)
    traj = make_trajectory(trajectory, the_site, frames, fps, speed_mps, lateral_m, weave_m,
                           wobble_deg, np.random.default_rng(seed))
    t0 = time.perf_counter()
    folder = simulate_recording(the_rig, the_site, traj, out, options, seed, realism)
    ms = 1e3 * (time.perf_counter() - t0) / len(traj)
    return SimulateRun(folder, traj, the_rig.camera.width, the_rig.camera.height, seed, ms,
                       "" if scatter is None else scatter.describe())


# -- the guided whole ------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CalibrateRun:
    """The files of a guided calibration, the check replay (or None) and the report."""

    camera_path: Path
    rig_path: Path
    check: ReplayResult | None
    report: tuple[str, ...]

    def lines(self) -> list[str]:
        return list(self.report)


def calibrate(boards: Path, board: Board, placements: Path, site: Path, out: Path, *,
              model: str = "plumb_bob", drive: Path | None = None,
              check: Path | None = None, redo: bool = False,
              on_line: Callable[[str], None] | None = None,
              plots: Path | None = None) -> CalibrateRun:
    """Intrinsics from ``boards``, then the mount from ``placements``, then a check
    replay of ``check``; each step writes its file into ``out`` (camera.yaml, rig.yaml,
    check/) and is skipped when that file is already there, unless ``redo``.

    ``on_line`` gets each report line as the steps go (they take minutes); the result
    holds them all. ``plots``: each step that runs writes its plots there (intrinsics'
    views, coverage and distortion; the mount's residuals; the check's report.html).
    """
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        if on_line is not None:
            on_line(line)

    with FolderLock(out), _claim_step_plots(out, plots, redo,
                                            [boards, placements, site, drive, check]):
        return _calibrate_steps(boards, board, placements, site, out, model, drive, check,
                                redo, say, lines, plots)


def _claim_step_plots(out: Path, plots: Path | None, redo: bool,
                      inputs: Sequence[Path | None]) -> contextlib.AbstractContextManager:
    """The plots of the steps of :func:`calibrate` that will run (their file is missing,
    or ``redo``), claimed in ``plots`` (locked; refused there without ``redo``); the
    plots of a step kept are left as they are."""
    if plots is None:
        return contextlib.nullcontext()
    names = [*(PLOT_NAMES if redo or not (out / "camera.yaml").exists() else ()),
             *((MOUNT_PLOT,) if redo or not (out / "rig.yaml").exists() else ())]
    return claimed({"plots": [Path(plots) / n for n in names]},
                   folders={"plots": [Path(plots)]}, force=redo,
                   inputs=[Path(p) for p in inputs if p is not None])


def _calibrate_steps(boards: Path, board: Board, placements: Path, site: Path, out: Path,
                     model: str, drive: Path | None, check: Path | None, redo: bool,
                     say: Callable[[str], None], lines: list[str],
                     plots: Path | None) -> CalibrateRun:
    """The three steps of :func:`calibrate`, its folder ``out`` locked."""
    cam_path, rig_path = out / "camera.yaml", out / "rig.yaml"
    if redo or not cam_path.exists():
        say("step 1/3: intrinsics")
        files = image_files(boards)
        views = detect_images(files, board, DetectionCache(out / ".detections.npz"))
        result = calibrate_intrinsics(views, model)
        header = provenance_header("camera intrinsics by ceilcal calibrate",
                                   [f"inputs: {boards} ({len(files)} images)"]
                                   + result.report.summary_lines())
        save_camera(result.camera, cam_path, header)
        for line in result.report.summary_lines():
            say("  " + line)
        for path in write_plots(result, plots) if plots is not None else ():
            say(f"  wrote {path}")
    else:
        say(f"step 1/3: intrinsics: kept {cam_path}")
    if redo or not rig_path.exists():
        say("step 2/3: mount")
        run = mount(placements, site, rig_path, camera=cam_path, drive=drive, plots=plots,
                    force=redo)
        for line in run.report:
            say("  " + line)
        for path in run.exports + run.plots:
            say(f"  wrote {path}")
    else:
        say(f"step 2/3: mount: kept {rig_path}")
    if check is None:
        say("step 3/3: check: skipped (no check recording)")
        return CalibrateRun(cam_path, rig_path, None, tuple(lines))
    say("step 3/3: check replay")
    start = check_start_pose(check)
    if start is not None:
        say(f"  from the check drive's first truth row ({start[0]:.2f}, {start[1]:.2f}, "
            f"{math.degrees(start[2]):.1f} deg): a symmetric ceiling's twins need a start")
    # the check is this calibration's own output, made again from the files kept
    res = replay(check, out / "check", rig=rig_path, site=site, report=plots is not None,
                 start_pose=start, force=True)
    for line in res.telemetry.summary() + (res.accuracy.lines() if res.accuracy else []):
        say("  " + line)
    if res.report is not None:
        say(f"  wrote {res.report}")
    return CalibrateRun(cam_path, rig_path, res, tuple(lines))


def check_start_pose(recording: Path) -> tuple[float, float, float] | None:
    """The first row of a check recording's ``truth.csv`` as a start pose, or None: a
    check drive under a symmetric ceiling (a corridor's half turn) is singled out by
    where it starts, as a vehicle's first run is by its ``--start-pose``."""
    from ceilkit.runtime.io.tables import load_truth

    path = Path(recording) / "truth.csv"
    if Path(recording).suffix == ".mcap" or not path.exists():
        return None
    truth = load_truth(path)
    if truth is None or truth.t_ns.size == 0:
        return None
    return float(truth.x_m[0]), float(truth.y_m[0]), float(truth.yaw_rad[0])


__all__ = ["CalibrateRun", "IntrinsicsRun", "LightmapRun", "MountRun", "SimulateRun",
           "calibrate", "intrinsics", "lightmap", "mount", "packaged_file",
           "parse_placements", "provenance_header", "simulate", "simulate_boards",
           "SimulatedFiles"]
