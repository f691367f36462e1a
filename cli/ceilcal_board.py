"""`ceilcal board`: a printable chessboard or ChArUco board (PNG or PDF).

Parses, calls :func:`ceilkit.calib.workflow.board`, prints what it wrote.
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board


def register(app: typer.Typer) -> None:
    @app.command()
    def board(
        board: str = typer.Option(..., "--board",
                                  help="chess:COLSxROWS (inner corners) or "
                                       "charuco:SXxSY[:DICT][:legacy] (squares)."),
        square: float = typer.Option(..., "--square", help="Square side, metres."),
        marker: float = typer.Option(None, "--marker",
                                     help="ChArUco marker side, metres (0.75 square)."),
        dpi: float = typer.Option(300.0, "--dpi", help="Print resolution, dots per inch."),
        out: Path = typer.Option(..., "--out", help="The .png or .pdf to write."),
    ) -> None:
        """Write a board to print at 100%, its --board/--square printed on it."""
        path = workflow.board(parse_board(board, square, marker), out, dpi=dpi)
        typer.echo(f"wrote {path}")
