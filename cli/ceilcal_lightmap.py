"""`ceilcal lightmap RECORDING --out site.yaml`: survey the ceiling lights.

Thin wiring around :func:`ceilkit.calib.lightmap.survey_lights`: the recording's
frames with known poses (its ``truth.csv``, or ``--poses``) give each light's place;
the result is written as the ``lights`` section of ``--out``, keeping the other
sections of that file when it exists (else of the recording's ``site.yaml``), with a
provenance header that lists every light's uncertainty.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from ceilkit.calib.lightmap import (
    lightmap_header_lines,
    load_pose_table,
    survey_lights,
    write_site,
)
from ceilkit.runtime.recording import Recording
from ceilkit.runtime.site import Site

from .common import provenance_header


def register(app: typer.Typer) -> None:
    """Add ``lightmap`` to ``app``."""
    if app.registered_callback is None:
        @app.callback()
        def _group() -> None:
            pass

    @app.command("lightmap")
    def lightmap(
        recording: Path = typer.Argument(..., help="Recording folder (SPEC §2)."),
        out: Path = typer.Option(..., "--out", help="site.yaml to write (other sections "
                                 "kept if it exists)."),
        poses: Path = typer.Option(None, "--poses", help="Known poses: truth.csv or "
                                   "poses.csv layout (default: RECORDING/truth.csv)."),
        ceiling_height: float = typer.Option(None, "--ceiling-height",
                                             help="Ceiling height, m (default: the site's)."),
        cluster: float = typer.Option(0.15, "--cluster", help="Clustering radius, m."),
        min_views: int = typer.Option(3, "--min-views", help="Fewest frames per light."),
    ) -> None:
        """Build the `lights` of a site map from a recording with known poses."""
        rec = Recording(recording)
        table = load_pose_table(poses) if poses is not None else None
        lm = survey_lights(rec, table, ceiling_height_m=ceiling_height, cluster_m=cluster,
                           min_views=min_views)
        base = Site.load(out) if out.exists() else rec.site
        header = provenance_header("ceilcal lightmap: site map with surveyed lights",
                                   lightmap_header_lines(lm))
        write_site(lm, out, base, header, ceiling_height)
        typer.echo(f"{out}: {lm.lights_m.shape[0]} lights from {lm.frames_used} frames; "
                   f"median standard error {1e3 * float(np.median(lm.sigma_m)):.1f} mm")
