"""`ceilcal autopilot`: an ArduPilot or PX4 parameter file for external navigation."""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib.autopilot import (
    ARDUPILOT_FIRMWARES,
    DEFAULT_DELAY_MS,
    TARGETS,
    autopilot_params,
    default_param_path,
    parse_autopilot_at,
    purpose_lines,
    resolve_target,
    write_params,
)
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.io.outputs import claimed

from .common import provenance_header


def run_autopilot(rig_path: Path, target: str | None, out: Path | None,
                  autopilot_at: str | None = None, corridor: bool = False,
                  delay_ms: float = DEFAULT_DELAY_MS, firmware: str | None = None,
                  force: bool = False) -> tuple[Path, list[str]]:
    """Write the parameter file (``out``, or beside the rig named by its purpose);
    returns its path and the report lines. Every value is checked, and an existing
    file refused without ``force``, before anything is written."""
    target, firmware = resolve_target(target, firmware)
    at = parse_autopilot_at(autopilot_at)
    rig = Rig.load(rig_path)
    params = autopilot_params(rig.mount, target, firmware, autopilot_V_m=at,
                              corridor=corridor, delay_ms=delay_ms)
    out = default_param_path(rig_path, target, firmware) if out is None else out
    lines = [f"rig: {rig_path} (mount x {rig.mount.x_m:.4f}, y {rig.mount.y_m:.4f}, "
             f"z {rig.mount.z_m:.4f} m)",
             f"autopilot at {at[0]:.4f}, {at[1]:.4f}, {at[2]:.4f} m in V"
             + ("; corridor site (no x)" if corridor else "")]
    what, *more = purpose_lines(target, firmware)
    with claimed({"out": [out]}, inputs=[rig_path], force=force):  # locked while written
        write_params(out, params, target, provenance_header(what, more + lines))
    return out, lines + [f"{len(params)} parameters for {firmware or target}"]


def register(app: typer.Typer) -> None:
    @app.command()
    def autopilot(
        rig: Path = typer.Option(..., help="The calibrated rig.yaml (its mount)."),
        for_: str = typer.Option(None, "--for", help=f"The autopilot: {' or '.join(TARGETS)} "
                                 "(implied by --firmware)."),
        firmware: str = typer.Option(None, "--firmware", help="ArduPilot's release: "
                                     f"{', '.join(ARDUPILOT_FIRMWARES)} (its parameter "
                                     "names differ)."),
        out: Path = typer.Option(None, help="The parameter file to write (default: beside "
                                 "the rig, RIG.ardupilot-4.6.param or RIG.px4.params)."),
        autopilot_at: str = typer.Option(None, help="X,Y,Z: the autopilot (its IMU) in V, "
                                         "m; default V's origin."),
        corridor: bool = typer.Option(False, help="The site gives no x (corridor "
                                      "method): ArduPilot fuses the heading only."),
        delay_ms: float = typer.Option(DEFAULT_DELAY_MS, help="Capture-to-arrival latency, "
                                       "ms, 0-250 (poses.csv latency_ms)."),
        force: bool = typer.Option(False, "--force", help="Replace an existing --out."),
    ) -> None:
        """Autopilot settings for the mavlink-odometry stream, from the rig."""
        path, lines = run_autopilot(rig, for_, out, autopilot_at, corridor, delay_ms,
                                    firmware, force)
        for line in lines:
            typer.echo(line)
        typer.echo(f"wrote {path}")
