"""`ceilcal intrinsics`: camera intrinsics from board images, with uncertainty.

    ceilcal intrinsics (FOLDER | --video FILE | --device DEV) --board chess:9x6 \\
        --square 0.025 [--model plumb_bob|rational_polynomial|equidistant] \\
        --out camera.yaml [--plots DIR] \\
        [--width W --height H --fps F --fourcc MJPG --exposure E --gain G --capture FILE]
    ceilcal intrinsics --ceiling RECORDING [--compare camera.yaml] --out camera.yaml

Parses, calls :func:`ceilkit.calib.workflow.intrinsics`, prints: the report (with its
warnings) goes to stdout, progress to stderr, the camera to ``--out`` (atomically, with
a provenance header). The warnings are said again on stderr when stdout is not the
terminal stderr shows (a file, a pipe), so that a person watching reads each once.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import typer

from ceilkit.calib import selfcal, workflow
from ceilkit.calib.boards import parse_board
from ceilkit.cli.common import (
    BOARD_OPTION,
    CAPTURE_OPTION,
    EXPOSURE_OPTION,
    FOURCC_OPTION,
    FPS_OPTION,
    GAIN_OPTION,
    HEIGHT_OPTION,
    MARKER_OPTION,
    SQUARE_OPTION,
    TERM_LINE,
    WIDTH_OPTION,
    capture_settings,
)


def _progress(i: int, n: int, fname: str, found: bool) -> None:
    # the one in-place line: an error printed meanwhile starts on a line of its own
    TERM_LINE.show(f"detecting {i + 1}/{n} {fname[:30]:30s}")
    if i + 1 == n:
        TERM_LINE.end()


class _MeterLine:
    """The coverage meter's stream (``\\r`` + a line, rewritten; ``\\n`` at the end) as the
    one in-place line, so that an error while capturing starts on a line of its own."""

    def write(self, text: str) -> None:
        if text.startswith("\r"):
            TERM_LINE.show(text[1:])
        elif text == "\n":
            TERM_LINE.end()
        else:
            TERM_LINE.end()
            sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def same_terminal() -> bool:
    """Whether stdout and stderr are one terminal (whatever is in the report on stdout
    has then been read there)."""
    try:
        return (sys.stdout.isatty() and sys.stderr.isatty() and os.fstat(
            sys.stdout.fileno()).st_rdev == os.fstat(sys.stderr.fileno()).st_rdev)
    except (OSError, ValueError, AttributeError):   # a stream without a descriptor
        return False


def register(app: typer.Typer) -> None:
    """Add ``intrinsics`` to ``app``."""

    @app.command("intrinsics")
    def intrinsics(
        folder: Path = typer.Argument(None, help="Folder of board images."),
        video: Path = typer.Option(None, "--video", help="A video file of the board."),
        device: str = typer.Option(None, "--device",
                                   help="A live camera: index (0) or path (/dev/video0)."),
        board: str = typer.Option(None, "--board", help=BOARD_OPTION.help),
        square: float = typer.Option(None, "--square", help=SQUARE_OPTION.help),
        ceiling: Path = typer.Option(None, "--ceiling", help="A drive recording under a "
                                     "tiled ceiling: no board (docs/calibration.md)."),
        compare: Path = typer.Option(None, "--compare",
                                     help="--ceiling: a board camera.yaml to compare."),
        marker: float = MARKER_OPTION,
        legacy: bool = typer.Option(False, "--legacy",
                                    help="ChArUco layout of boards made before OpenCV 4.6."),
        detector: str = typer.Option("auto", "--detector",
                                     help="Chessboard detector: auto, classic or sb."),
        model: str = typer.Option("plumb_bob", "--model",
                                  help="plumb_bob, rational_polynomial or equidistant."),
        out: Path = typer.Option(..., "--out", help="camera.yaml to write."),
        plots: Path = typer.Option(None, "--plots", help="Folder for PNG plots."),
        name: str = typer.Option("camera", "--name", help="camera_name in the file."),
        fix_aspect_ratio: bool = typer.Option(False, "--fix-aspect-ratio",
                                              help="Solve one focal length (fx = fy)."),
        min_views: int = typer.Option(5, "--min-views", help="Fewest views to solve."),
        max_views: int = typer.Option(40, "--max-views",
                                      help="Live/video: stop after this many views."),
        every: int = typer.Option(1, "--every", help="Live/video: look at 1 frame in N."),
        no_cache: bool = typer.Option(False, "--no-cache",
                                      help="Detect again; do not read or write the cache."),
        width: int = WIDTH_OPTION,
        height: int = HEIGHT_OPTION,
        fps: float = FPS_OPTION,
        fourcc: str = FOURCC_OPTION,
        exposure: float = EXPOSURE_OPTION,
        gain: float = GAIN_OPTION,
        capture: Path = CAPTURE_OPTION,
        force: bool = typer.Option(False, "--force", help="Replace an existing --out "
                                   "(refused otherwise)."),
    ) -> None:
        """Calibrate the camera's intrinsics from views of a board (or the ceiling)."""
        if ceiling is not None:
            if folder is not None or video is not None or device is not None or board:
                raise typer.BadParameter("--ceiling reads a drive: give no FOLDER, "
                                         "--video, --device or --board with it")
            run = selfcal.intrinsics_from_ceiling(ceiling, out, compare=compare, name=name,
                                                  force=force)
            typer.echo("\n".join(run.lines()))
            return
        if board is None or square is None:
            raise typer.BadParameter("--board and --square are required (or --ceiling "
                                     "RECORDING)")
        run = workflow.intrinsics(
            parse_board(board, square, marker, legacy, detector), out, folder=folder,
            video=video, device=device, model=model, plots=plots, name=name,
            fix_aspect_ratio=fix_aspect_ratio, min_views=min_views, max_views=max_views,
            every=every, cache=not no_cache, progress=_progress, meter=_MeterLine(),
            capture=capture_settings(capture, width, height, fps, fourcc, exposure, gain),
            force=force)
        typer.echo("\n".join(run.lines()))
        if not same_terminal():     # on a terminal the report said them
            for w in run.warnings:
                typer.echo(f"ceilcal: warning: {w}", err=True)
