"""`ceilcal intrinsics`: camera intrinsics from board images, with uncertainty.

    ceilcal intrinsics (FOLDER | --video FILE | --device DEV) --board chess:9x6 \\
        --square 0.025 [--model plumb_bob|rational_polynomial|equidistant] \\
        --out camera.yaml [--plots DIR]

Thin wiring over :mod:`ceilkit.calib.intrinsics`: the report goes to stdout, progress
and warnings to stderr, the camera to ``--out`` (atomically, with a provenance header).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import typer

from ceilkit.calib.boards import parse_board
from ceilkit.calib.intrinsics import (
    DetectionCache,
    StopRule,
    calibrate_intrinsics,
    capture_views,
    detect_images,
    image_files,
    write_plots,
)
from ceilkit.runtime.config.camera import save_camera
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import DISTORTION_MODELS
from ceilkit.runtime.io.capture import open_video

from .common import provenance_header


def _check_writable(out: Path) -> None:
    parent = out.parent if str(out.parent) else Path(".")
    if out.is_dir():
        raise ConfigError(out, None, "is a folder; expected a camera.yaml path")
    if not parent.is_dir():
        raise ConfigError(out, None, f"cannot write: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise ConfigError(out, None, f"cannot write: folder {parent} is not writable")


def register(app: typer.Typer) -> None:
    """Add ``intrinsics`` to ``app``."""

    @app.command("intrinsics")
    def intrinsics(
        folder: Path = typer.Argument(None, help="Folder of board images."),
        video: Path = typer.Option(None, "--video", help="A video file of the board."),
        device: str = typer.Option(None, "--device",
                                   help="A live camera: index (0) or path (/dev/video0)."),
        board: str = typer.Option(..., "--board",
                                  help="chess:COLSxROWS (inner corners) or "
                                       "charuco:SXxSY[:DICT][:legacy] (squares)."),
        square: float = typer.Option(..., "--square", help="Square side, metres."),
        marker: float = typer.Option(None, "--marker",
                                     help="ChArUco marker side, metres (0.75 square)."),
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
    ) -> None:
        """Calibrate the camera's intrinsics from views of a board."""
        sources = [s for s in (folder, video, device) if s is not None]
        if len(sources) != 1:
            raise ConfigError(None, "FOLDER|--video|--device",
                              f"give exactly one image source, found {len(sources)}")
        if model not in DISTORTION_MODELS:
            raise ConfigError(None, "--model", f"expected one of {', '.join(DISTORTION_MODELS)}"
                              f", found {model!r}")
        b = parse_board(board, square, marker, legacy, detector)
        _check_writable(out)
        if folder is not None:
            files = image_files(folder)
            cache = None if no_cache else DetectionCache(
                out.parent / f".{out.stem}.detections.npz")

            def progress(i: int, n: int, fname: str, found: bool) -> None:
                typer.echo(f"\rdetecting {i + 1}/{n} {fname[:30]:30s}", err=True, nl=False)

            views = detect_images(files, b, cache, progress)
            typer.echo("", err=True)
            inputs = f"{folder} ({len(files)} images, {len(views)} with the board)"
        else:
            src = open_video(str(video) if video is not None else device)
            stop = StopRule(max_views=max_views, min_views=max(12, min_views))
            views = capture_views(src, b, model, stop, every=every, meter=sys.stderr)
            inputs = f"{video if video is not None else 'device ' + device} ({len(views)} views)"
        result = calibrate_intrinsics(views, model, fix_aspect_ratio=fix_aspect_ratio,
                                      min_views=min_views, name=name)
        rep = result.report
        header = provenance_header(
            "camera intrinsics by ceilcal intrinsics",
            [f"inputs: {inputs}", f"board: {b.spec}, square {square:g} m"] + rep.summary_lines())
        save_camera(result.camera, out, header)
        typer.echo(rep.text())
        typer.echo(f"wrote {out}")
        if plots is not None:
            for p in write_plots(result, plots):
                typer.echo(f"wrote {p}")
        for w in rep.warnings:
            typer.echo(f"ceilcal: warning: {w}", err=True)
