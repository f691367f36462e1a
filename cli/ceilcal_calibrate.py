"""`ceilcal calibrate`: the guided whole: intrinsics, mount, then a check replay.

Each step writes its file into ``--out`` and is skipped when that file is already
there (resume after an interruption; ``--redo`` starts over).
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib.boards import parse_board
from ceilkit.calib.intrinsics import (
    DetectionCache,
    calibrate_intrinsics,
    detect_images,
    image_files,
)
from ceilkit.runtime.config.camera import save_camera
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.replay import replay

from .ceilcal_mount import run_mount
from .common import provenance_header


def register(app: typer.Typer) -> None:
    @app.command()
    def calibrate(
        boards: Path = typer.Option(..., help="Folder of board images (step 1)."),
        board: str = typer.Option(..., help="chess:COLSxROWS or charuco:SXxSY[:DICT]."),
        square: float = typer.Option(..., help="Board square side, metres."),
        placements: Path = typer.Option(..., help="Placements file or recording with "
                                        "truth.csv (step 2)."),
        site: Path = typer.Option(..., help="site.yaml with the corridor's lines."),
        out: Path = typer.Option(Path("calibration"), help="Folder for camera.yaml, "
                                 "rig.yaml and the check."),
        model: str = typer.Option("plumb_bob", help="Lens model."),
        drive: Path = typer.Option(None, help="A straight drive for tilt and swing."),
        check: Path = typer.Option(None, help="A recording with truth.csv held back for "
                                   "the check replay (step 3)."),
        redo: bool = typer.Option(False, "--redo", help="Redo steps whose file exists."),
    ) -> None:
        """Intrinsics, then mount, then a check replay; each step resumable."""
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(out, None, f"cannot create: {exc.strerror}") from None
        cam_path, rig_path = out / "camera.yaml", out / "rig.yaml"
        if redo or not cam_path.exists():
            typer.echo("step 1/3: intrinsics")
            b = parse_board(board, square)
            files = image_files(boards)
            views = detect_images(files, b, DetectionCache(out / ".detections.npz"))
            result = calibrate_intrinsics(views, model)
            header = provenance_header("camera intrinsics by ceilcal calibrate",
                                       [f"inputs: {boards} ({len(files)} images)"]
                                       + result.report.summary_lines())
            save_camera(result.camera, cam_path, header)
            for line in result.report.summary_lines():
                typer.echo("  " + line)
        else:
            typer.echo(f"step 1/3: intrinsics: kept {cam_path} (--redo to redo)")
        if redo or not rig_path.exists():
            typer.echo("step 2/3: mount")
            for line in run_mount(placements, site, rig_path, camera_path=cam_path,
                                  drive=drive):
                typer.echo("  " + line)
        else:
            typer.echo(f"step 2/3: mount: kept {rig_path} (--redo to redo)")
        if check is None:
            typer.echo("step 3/3: check: skipped (no --check recording)")
            return
        typer.echo("step 3/3: check replay")
        res = replay(check, out / "check", rig=rig_path, site=site)
        for line in res.telemetry.summary():
            typer.echo("  " + line)
        if res.accuracy is not None:
            for line in res.accuracy.lines():
                typer.echo("  " + line)
