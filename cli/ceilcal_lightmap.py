"""`ceilcal lightmap RECORDING --out site.yaml`: survey the ceiling lights.

Parses, calls :func:`ceilkit.calib.workflow.lightmap`, prints; in one of two ways:

* **known poses** (default): the recording's ``truth.csv``, or ``--poses``, gives each
  frame's pose; :func:`~ceilkit.calib.lightmap.survey_lights` clusters the lights.
* **chaining** (``--known-light X,Y``): no pose is known; the vehicle starts under a
  light whose place was measured, and ``--second-light X,Y`` (a second measured
  light) or ``--start-yaw DEG`` (the heading in that first frame) gives the direction
  of the site's x axis; :func:`~ceilkit.calib.lightmap.survey_chain` chains the
  frames and adjusts poses and lights together.

The result is written as the ``lights`` section of ``--out``, keeping the other
sections of that file when it exists (else of the recording's ``site.yaml``), with a
provenance header that lists every light's uncertainty (SPEC's ``lights: - [x, y]``
has no place for it).
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ceilkit.calib import workflow
from ceilkit.calib.lightmap import KnownLights
from ceilkit.runtime.errors import ConfigError


def parse_xy(text: str | None, flag: str) -> tuple[float, float] | None:
    """``"X,Y"`` (metres) as a pair of floats; ConfigError naming ``flag`` otherwise."""
    if text is None:
        return None
    parts = text.replace(" ", "").split(",")
    try:
        x, y = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(None, flag, f"expected X,Y in metres, found {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)) or max(abs(x), abs(y)) > XY_LIMIT_M:
        raise ConfigError(None, flag, f"expected finite X,Y in metres, each in "
                          f"[-{XY_LIMIT_M:g}, {XY_LIMIT_M:g}], found {text!r}")
    return x, y


XY_LIMIT_M = 1e6
"""The largest |X| or |Y| of a measured light, m."""


def _known(known_light: str | None, second_light: str | None, start_yaw: float | None,
           anchor_frame: int, keep_height: bool) -> KnownLights | None:
    """The measured lights of a chaining survey from the flags, or None (known poses)."""
    first = parse_xy(known_light, "--known-light")
    second = parse_xy(second_light, "--second-light")
    if first is None:
        if second is not None or start_yaw is not None:
            raise ConfigError(None, "--known-light", "--second-light and --start-yaw "
                              "belong to a chaining survey, which needs --known-light")
        return None
    if second is None and start_yaw is None:
        raise ConfigError(None, "--second-light", "a chaining survey needs the "
                          "site's x axis: --second-light X,Y or --start-yaw DEG")
    return KnownLights(first, second, start_yaw, anchor_frame, fit_height=not keep_height)


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
                                   "poses.csv layout (default: RECORDING/truth.csv); "
                                   "at their own stamps: interpolated, their time "
                                   "offset estimated."),
        pose_offset_ms: float = typer.Option(None, "--pose-offset-ms", help="The poses' "
                                             "known time offset (pose time = frame stamp "
                                             "+ offset), ms: not estimated."),
        ceiling_height: float = typer.Option(None, "--ceiling-height",
                                             help="Ceiling height, m (default: the site's)."),
        cluster: float = typer.Option(0.15, "--cluster", help="Clustering radius, m."),
        min_views: int = typer.Option(3, "--min-views", help="Fewest frames per light."),
        known_light: str = typer.Option(None, "--known-light", help="X,Y of the light "
                                        "above the vehicle in the anchor frame: survey "
                                        "by chaining frames, no poses needed."),
        second_light: str = typer.Option(None, "--second-light", help="X,Y of a second "
                                         "measured light: fixes the x axis (and, unless "
                                         "--keep-height, the map's scale)."),
        start_yaw: float = typer.Option(None, "--start-yaw", help="Vehicle yaw in the "
                                        "anchor frame, degrees (fixes the x axis when "
                                        "there is no second light)."),
        anchor_frame: int = typer.Option(0, "--anchor-frame", help="Index of the frame "
                                         "taken under --known-light."),
        keep_height: bool = typer.Option(False, "--keep-height", help="With "
                                         "--second-light: keep the ceiling height; use "
                                         "the second light for the direction only."),
        plots: Path = typer.Option(None, "--plots",
                                   help="Folder for PNG plots (lights, 1-sigma, drive)."),
        force: bool = typer.Option(False, "--force", help="Write into an existing --out "
                                   "(its other sections kept; refused otherwise)."),
    ) -> None:
        """Build the `lights` of a site map: from known poses, or by chaining frames."""
        run = workflow.lightmap(recording, out, poses=poses, pose_offset_ms=pose_offset_ms,
                                known=_known(known_light, second_light, start_yaw,
                                             anchor_frame, keep_height),
                                ceiling_height_m=ceiling_height, cluster_m=cluster,
                                min_views=min_views, plots=plots, force=force)
        typer.echo("\n".join(run.lines()))
