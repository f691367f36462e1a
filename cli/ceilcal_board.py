"""`ceilcal board`: a printable chessboard or ChArUco board (PNG or PDF).

Parses, calls :func:`ceilkit.calib.workflow.board`, prints what it wrote.
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board
from ceilkit.cli.common import BOARD_OPTION, MARKER_OPTION, SQUARE_OPTION


def register(app: typer.Typer) -> None:
    @app.command()
    def board(
        board: str = BOARD_OPTION,
        square: float = SQUARE_OPTION,
        marker: float = MARKER_OPTION,
        dpi: float = typer.Option(300.0, "--dpi", help="Print resolution, dots per inch."),
        out: Path = typer.Option(..., "--out", help="The .png or .pdf to write."),
    ) -> None:
        """Write a board to print at 100%, its --board/--square printed on it."""
        path = workflow.board(parse_board(board, square, marker), out, dpi=dpi)
        typer.echo(f"wrote {path}")
