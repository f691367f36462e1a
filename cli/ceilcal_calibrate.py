"""`ceilcal calibrate`: the guided whole: intrinsics, mount, then a check replay.

Each step writes its file into ``--out`` and is skipped when that file is already
there (resume after an interruption; ``--redo`` starts over). Parses, calls
:func:`ceilkit.calib.workflow.calibrate`, which prints each step's lines as it goes.
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board


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
        plots: Path = typer.Option(None, "--plots",
                                   help="Folder for every step's PNG plots (and report.html)."),
    ) -> None:
        """Intrinsics, then mount, then a check replay; each step resumable."""
        workflow.calibrate(boards, parse_board(board, square), placements, site, out,
                           model=model, drive=drive, check=check, redo=redo,
                           on_line=typer.echo, plots=plots)
