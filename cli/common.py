"""What every command line shares: one place that turns ceilkit errors into one line.

A :class:`~ceilkit.runtime.errors.CeilkitError` is printed on stderr as
``ceilrun: error: <file>: <key>: <what>`` with exit code 1; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

import shlex
import sys
from datetime import datetime, timezone

import typer
import typer.core

from ceilkit.runtime.errors import CeilkitError


class _Group(typer.core.TyperGroup):
    def invoke(self, ctx):  # type: ignore[override]
        try:
            return super().invoke(ctx)
        except CeilkitError as exc:
            typer.echo(f"{ctx.find_root().info_name}: error: {exc}", err=True)
            ctx.exit(1)


def make_app(name: str, help: str) -> typer.Typer:
    """A typer app whose ceilkit errors become one line on stderr and exit 1.

    The app has an empty group callback from the start, so that an app with a single
    command keeps it as a subcommand (``ceilcal simulate ...``, not ``ceilcal ...``)
    however many commands register. An app that wants to run something bare (as
    ``ceilrun`` runs live) registers its own ``@app.callback(...)``, which replaces
    this one.
    """
    app = typer.Typer(name=name, help=help, cls=_Group, no_args_is_help=False,
                      add_completion=False, pretty_exceptions_enable=False)

    @app.callback()
    def _group() -> None:
        pass

    return app


def quiet_opencv() -> None:
    """Keep OpenCV's own warnings (``[ WARN:0@0.250] global cap.cpp ...``) off the
    console: the command says what went wrong in its own line. Called by the console
    scripts only; a program that imports ceilkit keeps its OpenCV settings."""
    try:
        import cv2.utils.logging as cv_logging

        cv_logging.setLogLevel(cv_logging.LOG_LEVEL_ERROR)
    except (ImportError, AttributeError):  # an OpenCV build without the logging API
        pass


def provenance_header(what: str, lines: list[str] | None = None) -> str:
    """YAML comment lines naming the time, the command line and a report."""
    out = [f"# {what}",
           f"# written {datetime.now(timezone.utc).isoformat(timespec='seconds')}",
           f"# command: {shlex.join(sys.argv)}"]
    out += [f"# {line}" for line in (lines or [])]
    return "\n".join(out) + "\n"
