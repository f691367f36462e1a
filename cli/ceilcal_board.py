"""`ceilcal board`: a printable chessboard or ChArUco board, a vector PDF at true scale.

Parses, calls :func:`ceilkit.calib.board_pdf.write_board_pdf`, prints what it wrote.
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib.board_pdf import DEFAULT_PAPER, PAPERS, write_board_pdf
from ceilkit.calib.boards import parse_board
from ceilkit.cli.common import BOARD_OPTION, MARKER_OPTION, SQUARE_OPTION


def register(app: typer.Typer) -> None:
    @app.command()
    def board(
        board: str = BOARD_OPTION,
        square: float = SQUARE_OPTION,
        marker: float = MARKER_OPTION,
        paper: str = typer.Option(DEFAULT_PAPER, "--paper",
                                  help=f"Paper size: {', '.join(PAPERS)}."),
        out: Path = typer.Option(..., "--out", help="The .pdf to write."),
        force: bool = typer.Option(False, "--force", help="Replace an existing --out."),
    ) -> None:
        """Write a board as a PDF to print at 100%, its --board/--square printed on it."""
        page = write_board_pdf(parse_board(board, square, marker), out, paper, force)
        x0, y0, x1, y1 = page.squares_mm
        typer.echo(f"wrote {out}: {page.paper}{' landscape' if page.landscape else ''}, "
                   f"squares {x1 - x0:.1f} x {y1 - y0:.1f} mm, square "
                   f"{1000 * square:g} mm at 100 % scale")
