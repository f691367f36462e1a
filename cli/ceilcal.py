"""``ceilcal``: calibrate a rig, survey a site, simulate recordings."""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.runtime.errors import ConfigError

from . import (
    ceilcal_board,
    ceilcal_calibrate,
    ceilcal_exposure,
    ceilcal_intrinsics,
    ceilcal_lightmap,
    ceilcal_mount,
    ceilcal_simulate,
)
from .common import make_app, quiet_opencv

app = make_app("ceilcal", "Calibrate a ceiling-vision rig: intrinsics, mount, light map; "
               "simulate recordings.")

for _module in (ceilcal_simulate, ceilcal_intrinsics, ceilcal_mount, ceilcal_lightmap,
                ceilcal_calibrate, ceilcal_board, ceilcal_exposure):
    _module.register(app)

from . import ceilcal_autopilot  # noqa: E402 - registered after the calibration commands

ceilcal_autopilot.register(app)


CHECK_SITE_FLAGS = {"step_m": "--step", "heading_step_deg": "--heading-step",
                    "tol_px": "--tol-px", "search_m": "--search", "margin_m": "--margin"}


@app.command("check-site")
def check_site(
    rig: Path = typer.Option(..., help="The rig.yaml (camera and mount)."),
    site: Path = typer.Option(..., help="The site.yaml to check."),
    out: Path = typer.Option(None, help="Folder for check-site.png (the map) and "
                             "check-site.yaml (the figures); existing files are not "
                             "overwritten without --force."),
    step: float = typer.Option(0.5, help="Spacing of the checked positions, m."),
    heading_step: float = typer.Option(90.0, help="Spacing of the checked headings, "
                                       "degrees."),
    tol_px: float = typer.Option(2.0, help="Two pictures are the same within this many "
                                 "pixels."),
    search: float = typer.Option(6.0, help="Look for twins this far, m."),
    margin: float = typer.Option(0.0, help="Check this far beyond the features' box, m."),
    force: bool = typer.Option(False, "--force", help="Replace an existing check-site.png "
                               "and check-site.yaml in --out (refused otherwise)."),
) -> None:
    """Where on the site one frame is ambiguous, with which twins, and what would
    single it out."""
    from ceilkit.calib.checksite import CheckOptions, check_site_files

    try:
        options = CheckOptions(step_m=step, heading_step_deg=heading_step, tol_px=tol_px,
                               search_m=search, margin_m=margin)
    except ConfigError as exc:        # the options' names -> this command's flags
        raise ConfigError(None, CHECK_SITE_FLAGS.get(exc.key or "", exc.key),
                          exc.detail) from None
    result = check_site_files(rig, site, out, options, force)
    typer.echo("\n".join(result.lines()))
    if out is not None:
        typer.echo(f"wrote {out / 'check-site.png'}, {out / 'check-site.yaml'}")


def main() -> None:
    quiet_opencv()
    app(prog_name="ceilcal")


if __name__ == "__main__":
    main()
