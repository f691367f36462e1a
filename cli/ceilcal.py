"""``ceilcal``: calibrate a rig, survey a site, simulate recordings.

A command's process imports only that command's module (:func:`build_app`): the board
needs neither numba nor scipy, so ``ceilcal board`` starts in a quarter of the memory
of the whole program. ``app`` (for tests and ``CliRunner``) holds every command.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import typer

from ceilkit.runtime.errors import ConfigError

from .common import HELP_FLAGS, make_app, quiet_opencv

HELP = "Calibrate a ceiling-vision rig: intrinsics, mount, light map; simulate recordings."
COMMANDS = {"simulate": "ceilcal_simulate", "intrinsics": "ceilcal_intrinsics",
            "mount": "ceilcal_mount", "lightmap": "ceilcal_lightmap",
            "calibrate": "ceilcal_calibrate", "board": "ceilcal_board",
            "exposure": "ceilcal_exposure", "autopilot": "ceilcal_autopilot",
            "survey": "ceilcal_survey", "blockmap": "ceilcal_blockmap",
            "check-site": None}
"""Each command and the module under ``ceilkit.cli`` that registers it, in the order
``--help`` lists them (``None``: defined here)."""


def build_app(command: str | None = None) -> typer.Typer:
    """The ``ceilcal`` program with every command, or with ``command`` alone (one of
    :data:`COMMANDS`: only its module is imported)."""
    app = make_app("ceilcal", HELP)
    for name, module in COMMANDS.items():
        if command is not None and name != command:
            continue
        if module is None:
            app.command(name)(check_site)
        else:
            importlib.import_module(f"{__package__}.{module}").register(app)
    return app


CHECK_SITE_FLAGS = {"step_m": "--step", "heading_step_deg": "--heading-step",
                    "tol_px": "--tol-px", "search_m": "--search", "margin_m": "--margin"}


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
    """Where on the site one frame is ambiguous, and what would single it out.

    For each ambiguous pose, its twins; for each ambiguous region, the markers (or
    asymmetric features) that would tell them apart."""
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


_APP: list[typer.Typer] = []


def __getattr__(name: str) -> typer.Typer:
    """``app``: the program with every command, built on first use."""
    if name != "app":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if not _APP:
        _APP.append(build_app())
    return _APP[0]


def main() -> None:
    """The ``ceilcal`` entry point: builds only the command the arguments name (none
    for ``--version`` alone, every command for ``--help`` or a name it does not know)."""
    quiet_opencv()
    args = sys.argv[1:]
    words = [a for a in args if not a.startswith("-")][:1]
    command = words[0] if words and words[0] in COMMANDS else None
    if not words and "--version" in args and not set(HELP_FLAGS) & set(args):
        command = ""                # the version needs no command's imports
    build_app(command)(prog_name="ceilcal")


if __name__ == "__main__":
    main()
