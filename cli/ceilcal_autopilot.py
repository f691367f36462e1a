"""`ceilcal autopilot`: an ArduPilot or PX4 parameter file for external navigation."""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib.autopilot import (
    DEFAULT_DELAY_MS,
    TARGETS,
    autopilot_params,
    parse_autopilot_at,
    write_params,
)
from ceilkit.runtime.config.rig import Rig

from .common import provenance_header


def run_autopilot(rig_path: Path, target: str, out: Path, autopilot_at: str | None = None,
                  corridor: bool = False, delay_ms: float = DEFAULT_DELAY_MS) -> list[str]:
    """Write the parameter file ``out``; returns the report lines."""
    rig = Rig.load(rig_path)
    at = parse_autopilot_at(autopilot_at)
    params = autopilot_params(rig.mount, target, autopilot_V_m=at, corridor=corridor,
                              delay_ms=delay_ms)
    lines = [f"rig: {rig_path} (mount x {rig.mount.x_m:.4f}, y {rig.mount.y_m:.4f}, "
             f"z {rig.mount.z_m:.4f} m)",
             f"autopilot at {at[0]:.4f}, {at[1]:.4f}, {at[2]:.4f} m in V"
             + ("; corridor site (no x)" if corridor else "")]
    header = provenance_header(f"{target} parameters written by ceilcal autopilot", lines)
    write_params(out, params, target, header)
    return lines + [f"{len(params)} parameters"]


def register(app: typer.Typer) -> None:
    @app.command()
    def autopilot(
        rig: Path = typer.Option(..., help="The calibrated rig.yaml (its mount)."),
        for_: str = typer.Option(..., "--for", help=f"The autopilot: {' or '.join(TARGETS)}."),
        out: Path = typer.Option(..., help="The parameter file to write (.param for "
                                 "ArduPilot, .params for PX4)."),
        autopilot_at: str = typer.Option(None, help="X,Y,Z: the autopilot (its IMU) in V, "
                                         "m; default V's origin."),
        corridor: bool = typer.Option(False, help="The site gives no x (corridor "
                                      "method): ArduPilot fuses the heading only."),
        delay_ms: float = typer.Option(DEFAULT_DELAY_MS, help="Capture-to-arrival latency, "
                                       "ms (poses.csv latency_ms)."),
    ) -> None:
        """Autopilot settings for the mavlink-odometry stream, from the rig."""
        for line in run_autopilot(rig, for_, out, autopilot_at, corridor, delay_ms):
            typer.echo(line)
        typer.echo(f"wrote {out}")
