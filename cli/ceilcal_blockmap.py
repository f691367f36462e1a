"""`ceilcal blockmap RECORDING --out site.yaml`: the markers' map from a drive of known
poses.

Parses, calls :func:`ceilkit.calib.blockmap.blockmap`, prints what it wrote and, on
stderr, one line per marker refused (seen in too few frames, sightings that disagree,
a side off the given one). The library is imported when the command runs, not when
the program is built.
"""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add ``blockmap`` to ``app``."""
    @app.command("blockmap")
    def blockmap(
        recording: Path = typer.Argument(..., help="Recording folder (SPEC §2) of a drive "
                                         "under the markers."),
        out: Path = typer.Option(..., "--out", help="site.yaml to write: its `markers` "
                                 "(other sections kept from it with --force, else from "
                                 "the recording's site.yaml)."),
        rig: Path = typer.Option(None, "--rig", help="The rig.yaml (default: the "
                                 "recording's)."),
        poses: Path = typer.Option(None, "--poses", help="Known poses: truth.csv or "
                                   "poses.csv layout (default: RECORDING/truth.csv), "
                                   "interpolated at the frames' stamps."),
        pose_offset_ms: float = typer.Option(None, "--pose-offset-ms", help="The poses' "
                                             "time offset (pose time = frame stamp + "
                                             "offset), ms (default 0)."),
        dictionary: str = typer.Option(None, "--dictionary", help="The markers' aruco "
                                       "dictionary (default: the site's, else "
                                       "DICT_APRILTAG_36h11)."),
        size: float = typer.Option(None, "--size", help="The printed side of the black "
                                   "square, m: checked within 5% and written (default: "
                                   "each marker's measured side)."),
        ceiling_height: float = typer.Option(None, "--ceiling-height",
                                             help="Ceiling height, m (default: the site's)."),
        force: bool = typer.Option(False, "--force", help="Write into an existing --out "
                                   "(its other sections kept; refused otherwise)."),
    ) -> None:
        """Build the `markers` of a site map from a drive of known poses.

        Every marker seen in 3 frames or more, placed by least squares with its
        covariance."""
        from ceilkit.calib.blockmap import blockmap as run_blockmap

        run = run_blockmap(recording, out, rig=rig, poses=poses,
                           pose_offset_ms=pose_offset_ms, dictionary=dictionary,
                           size_m=size, ceiling_height_m=ceiling_height, force=force)
        for line in run.refusals():
            typer.echo(f"ceilcal: refused: {line}", err=True)
        typer.echo("\n".join(run.lines()))
