"""`ceilcal survey RIG RECORDING... --out SITE_DIR`: a site's map from drives with no
external poses.

Parses, calls :func:`ceilkit.calib.survey_files.survey_site`, prints what it wrote
(docs/survey.md). The library is imported when the command runs, not when the program
is built (``ceilcal survey --help`` loads neither numba nor scipy).
"""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add ``survey`` to ``app``."""
    @app.command("survey")
    def survey(
        rig: Path = typer.Argument(..., metavar="RIG", help="The rig.yaml (camera and "
                                   "mount)."),
        recordings: list[Path] = typer.Argument(..., metavar="RECORDING", help="Recording "
                                                "folders (SPEC §2) of drives under the "
                                                "site; several merge into one map."),
        out: Path = typer.Option(..., "--out", help="Folder to write: site.yaml, "
                                 "ceiling_map.npz, poses.csv, survey.md, survey.png."),
        site: Path = typer.Option(None, "--site", help="A site.yaml of what is known "
                                  "(its sections are kept, its ceiling height used)."),
        start_pose: str = typer.Option(None, "--start-pose", metavar="X,Y,YAW",
                                       help="X,Y,YAW (m, m, "
                                       "degrees): the first drive's first frame in W "
                                       "(default 0,0,0)."),
        anchor_marker: list[str] = typer.Option(None, "--anchor-marker",
                                                metavar="ID,X,Y,YAW[,SIZE]", help="ID,X,Y,"
                                                "YAW[,SIZE] (m, m, degrees, m): a marker "
                                                "of known pose anchors the survey "
                                                "(repeatable; beside --site's markers)."),
        marker_dictionary: str = typer.Option(None, "--marker-dictionary", metavar="DICT",
                                              help="The "
                                              "markers' aruco dictionary when --site has "
                                              "none (default DICT_APRILTAG_36h11)."),
        anchor_geodetic: str = typer.Option(None, "--anchor-geodetic",
                                            metavar="LAT,LON,HEADING", help="LAT,LON,"
                                            "HEADING (degrees; heading clockwise from "
                                            "north): the first frame on the Earth."),
        ceiling_height: float = typer.Option(None, "--ceiling-height", help="Ceiling "
                                             "height, m (default: --site's, else the "
                                             "first recording's site.yaml)."),
        readout_ms: float = typer.Option(0.0, "--readout-ms", help="The camera's "
                                         "rolling-shutter readout, top row to bottom, ms "
                                         "(0: a global shutter)."),
        force: bool = typer.Option(False, "--force", help="Replace existing outputs in "
                                   "--out (refused otherwise)."),
    ) -> None:
        """Map a site from drives with no external poses; writes its site and map.

        Chained frames, loop closures and a pose graph give the site file and its
        ceiling map (docs/survey.md)."""
        from ceilkit.calib.survey import SurveyOptions
        from ceilkit.calib.survey_files import parse_anchors, survey_site

        anchors = parse_anchors(start_pose, anchor_marker or [], marker_dictionary,
                                anchor_geodetic, site)
        run = survey_site(rig, recordings, out, site=site, anchors=anchors,
                          ceiling_height_m=ceiling_height, force=force,
                          options=SurveyOptions(readout_ms=readout_ms))
        typer.echo("\n".join(run.lines()))
