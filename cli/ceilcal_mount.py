"""`ceilcal mount`: the rig's tilt, swing, pan and offsets from corridor images.

Parses, calls :func:`ceilkit.calib.workflow.mount`, prints its report.
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib import workflow


def register(app: typer.Typer) -> None:
    @app.command()
    def mount(
        placements: Path = typer.Argument(..., help="A placements file (YAML: image, y, "
                                          "yaw per placement) or a recording with "
                                          "truth.csv; for an upward lights rig, a drive "
                                          "under the site's lights."),
        site: Path = typer.Option(..., help="site.yaml with the corridor's lines."),
        out: Path = typer.Option(Path("rig.yaml"), help="The rig file to write."),
        rig: Path = typer.Option(None, help="A rig whose camera (and held values) to use."),
        camera: Path = typer.Option(None, help="camera.yaml, when there is no rig yet."),
        drive: Path = typer.Option(None, help="A straight drive (recording or image "
                                   "folder) for tilt and swing, nothing measured."),
        fix: list[str] = typer.Option(None, help="Hold a parameter the data cannot "
                                      "determine: NAME=VALUE (pan tilt swing in deg, mx my "
                                      "h in m; h below the ceiling) or NAME (the --rig's "
                                      "value); recorded in the header; repeatable."),
        max_frames: int = typer.Option(8, help="At most this many placements from a "
                                       "recording."),
        plots: Path = typer.Option(None, "--plots",
                                   help="Folder for PNG plots (residual per placement)."),
        poses: Path = typer.Option(None, help="Upward (lights) rig: vehicle poses at "
                                   "their own stamps (t_ns,x,y,yaw_deg; motion capture), "
                                   "interpolated, their time offset estimated."),
        spin: bool = typer.Option(False, "--spin", help="Upward (lights) rig: the "
                                  "recording is a spin in place, no poses; needs --fix "
                                  "pan (a spin does not determine it)."),
        force: bool = typer.Option(False, "--force", help="Replace an existing --out and "
                                   "its exports beside it (refused otherwise)."),
    ) -> None:
        """Fit tilt, swing, pan and the offsets (and the height below the ceiling)."""
        upward = {"poses": poses} if poses is not None else {}
        if spin:
            upward["spin"] = True
        run = workflow.mount(placements, site, out, rig=rig, camera=camera, drive=drive,
                             fix=fix or (), max_frames=max_frames, plots=plots,
                             force=force, **upward)
        typer.echo("\n".join(run.lines()))
