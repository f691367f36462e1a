"""`ceilcal mount`: the rig's tilt, swing, pan and offsets from corridor images."""

from __future__ import annotations

import math
import os
from pathlib import Path

import typer

from ceilkit.calib.mount import (
    PARAMS,
    calibrate_mount,
    calibrate_tilt_swing,
    load_drive,
    load_placements,
)
from ceilkit.runtime.config.camera import load_camera
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError

from .common import provenance_header


def run_mount(placements: Path, site_path: Path, out: Path, rig_path: Path | None = None,
              camera_path: Path | None = None, drive: Path | None = None,
              fix: list[str] | None = None, max_frames: int = 8) -> list[str]:
    """Calibrate and write ``out`` (rig.yaml); returns the report lines."""
    if rig_path is None and camera_path is None:
        raise ConfigError(None, "--camera", "give the camera (camera.yaml) or a --rig")
    if rig_path is not None:
        rig = Rig.load(rig_path)
        camera_ref = rig.camera_file
    else:
        rig = Rig(load_camera(camera_path), Mount(z_m=0.5))
        camera_ref = str(camera_path)
    site = Site.load(site_path)
    fixed = list(fix or [])
    for name in fixed:
        if name not in PARAMS:
            raise ConfigError(None, "--fix", f"unknown parameter {name!r} "
                              f"(choose from {', '.join(PARAMS)})")
    pls = load_placements(placements, rig.camera, max_frames)
    start = None
    lines: list[str] = []
    if drive is not None:
        tilt, swing, rep = calibrate_tilt_swing(rig, load_drive(drive, rig.camera))
        lines.append(f"drive ({rep['frames']} frames): tilt {math.degrees(tilt):.4f} "
                     f"+- {math.degrees(rep['sigma_tilt']):.4f} deg, swing "
                     f"{math.degrees(swing):.4f} +- {math.degrees(rep['sigma_swing']):.4f} "
                     f"deg, RMS {rep['rms_px']:.3f} px")
        start = Mount(0.0, tilt, swing, rig.mount.x_m, 0.0, rig.mount.z_m)
        fixed += ["tilt", "swing"]
    res = calibrate_mount(rig, site, pls, fixed=fixed, start=start,
                          fit_height=None if "h" not in fixed else False)
    lines += res.lines()
    new = rig.with_mount(res.mount)
    header = provenance_header(
        "rig.yaml written by ceilcal mount",
        [f"placements: {placements} ({len(pls)})", f"site: {site_path}"]
        + ([f"drive: {drive}"] if drive else []) + lines)
    ref = None
    if camera_ref is not None:
        ref = os.path.relpath(Path(camera_ref).resolve(), Path(out).resolve().parent)
    new.save(out, header, camera_ref=ref)
    return lines


def register(app: typer.Typer) -> None:
    @app.command()
    def mount(
        placements: Path = typer.Argument(..., help="A placements file (YAML: image, y, "
                                          "yaw per placement) or a recording with "
                                          "truth.csv."),
        site: Path = typer.Option(..., help="site.yaml with the corridor's lines."),
        out: Path = typer.Option(Path("rig.yaml"), help="The rig file to write."),
        rig: Path = typer.Option(None, help="A rig whose camera (and held values) to use."),
        camera: Path = typer.Option(None, help="camera.yaml, when there is no rig yet."),
        drive: Path = typer.Option(None, help="A straight drive (recording or image "
                                   "folder) for tilt and swing, nothing measured."),
        fix: list[str] = typer.Option(None, help="Hold a parameter at the rig's value "
                                      "(pan tilt swing mx my h); repeatable."),
        max_frames: int = typer.Option(8, help="At most this many placements from a "
                                       "recording."),
    ) -> None:
        """Fit tilt, swing, pan and the offsets (and the height below the ceiling)."""
        for line in run_mount(placements, site, out, rig, camera, drive, fix, max_frames):
            typer.echo(line)
        typer.echo(f"wrote {out}")
