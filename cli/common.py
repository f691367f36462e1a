"""What every command line shares: one place that turns ceilkit errors into one line.

A :class:`~ceilkit.runtime.errors.CeilkitError` is printed on stderr as
``ceilrun: error: <file>: <key>: <what>`` with exit code 1; anything else is a bug
and keeps its traceback.

The library names its parameters (``ConfigError(None, "method", ...)``); this is the
one place that maps them to the flags a user typed (:data:`FLAGS`,
:data:`COMMAND_FLAGS`; an estimator's ``options.NAME`` is ``--option NAME``; any other
name of one of the command's parameters is that parameter's flag), so the user reads
``ceilrun: error: --method: unknown method 'magic' (...)``. Every value typed is
checked before the command runs (ranges, finite numbers, no empty strings) and a
usage error is one line too: :mod:`ceilkit.cli.values`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import typing
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import typer
import typer.core

from ceilkit.runtime.errors import CeilkitError, ConfigError
from ceilkit.runtime.io.files import FORCE_HINT

if TYPE_CHECKING:   # the session (numba, scipy) is imported by the commands that capture
    from ceilkit.runtime.session import CaptureSettings

from .values import (
    CheckedTyper,
    UsageError,
    check_params,
    flag_of,
    greedy_help_column,
    is_help_request,
    note_empty,
    usage_line,
)

FLAGS: Mapping[str, str] = MappingProxyType({
    "method": "--method", "rig": "--rig", "site": "--site",
    "board": "--board", "square": "--square", "marker": "--marker",
    "detector": "--detector", "model": "--model", "fix_aspect_ratio": "--fix-aspect-ratio",
    "camera": "--camera", "fix": "--fix", "placements": "--placements",
    "frames": "--frames", "record": "--record", "out": "--out", "link": "--serial",
    "fsync_every_s": "--fsync-every", "force": "--force", "wait": "--wait",
    "overlays": "--overlays",
    "paper": "--paper", "link_odometry": "--link-odometry", "n": "--frames",
    "plots": "--plots",
})
"""A library parameter name -> the flag of every command that has it."""

COMMAND_FLAGS: Mapping[str, Mapping[str, str]] = MappingProxyType({
    # ceilcal simulate: SimOptions fields and the trajectory's arguments
    "simulate": MappingProxyType({
        "options.noise_sigma": "--noise", "options.blur_px": "--blur",
        "options.supersample": "--supersample", "n": "--frames", "fps": "--fps",
        "speed_mps": "--speed", "y_m": "--lateral", "weave_m": "--weave",
        "yaw_wobble_rad": "--wobble", "x_range": "--trajectory", "y_range": "--lateral",
        "trajectory": "--trajectory", "sim-preset": "--sim-preset",
        "sim-fault": "--sim-fault", "placements": "--placement", "views": "--views",
        "kind": "--kind",
    }),
    "intrinsics": MappingProxyType({"source": "FOLDER|--video|--device"}),
    # ceilcal exposure: the simulator's camera names one setting of the sweep
    "exposure": MappingProxyType({"exposure": "--exposures", "gain": "--gains"}),
    # ceilcal lightmap: KnownLights fields and the survey's arguments
    "lightmap": MappingProxyType({
        "first_m": "--known-light", "second_m": "--second-light", "yaw_deg": "--start-yaw",
        "anchor_frame": "--anchor-frame", "cluster_m": "--cluster",
        "min_views": "--min-views", "poses": "--poses",
        "ceiling_height_m": "--ceiling-height",
    }),
})
"""Names that mean another flag in one command (by the command's name)."""

ESTIMATOR_OPTIONS = "options."
"""The key prefix of an estimator option (``options.detector``): ``--option detector``
in a command that takes ``--option``."""


def as_flags(exc: ConfigError, command: str, takes_option: bool = False,
             params: Iterable[Any] = ()) -> ConfigError:
    """``exc`` re-keyed by the flag of ``command`` when it names a library parameter
    (an error about a file keeps its key: it names the file's dotted key).
    ``takes_option``: the command has ``--option KEY=VALUE`` (estimator options);
    ``params``: its parameters (a key that names one is its flag,
    :func:`~ceilkit.cli.values.flag_of`)."""
    if exc.path is not None or exc.key is None:
        return exc
    key = exc.key
    flag = COMMAND_FLAGS.get(command, {}).get(key) or flag_of(key, params) or FLAGS.get(key)
    if flag is None and takes_option and key.startswith(ESTIMATOR_OPTIONS):
        flag = f"--option {key[len(ESTIMATOR_OPTIONS):]}"
    if flag is None:
        return exc
    return ConfigError(None, flag, exc.detail)


FORCE_FLAG_HINT = "give --force to replace it"
""":data:`~ceilkit.runtime.io.recording.FORCE_HINT` as a command line says it."""
NO_FORCE_HINT = "choose another output: this command never replaces one"
""":data:`~ceilkit.runtime.io.recording.FORCE_HINT` as a command without ``--force``
says it."""


def force_hint(params: Iterable[Any]) -> str:
    """How a command with these parameters replaces an existing output: ``--force``
    (:data:`FORCE_FLAG_HINT`), ``--redo`` (``ceilcal calibrate``: its steps made again),
    or never (:data:`NO_FORCE_HINT`)."""
    opts = {o for p in params for o in getattr(p, "opts", ())}
    if "--force" in opts:
        return FORCE_FLAG_HINT
    return "give --redo to make it again" if "--redo" in opts else NO_FORCE_HINT


class TermLine:
    """A line of stderr rewritten in place (``\r``: a progress bar, a status line);
    anything else printed on stderr first ends it, so it never glues onto it."""

    def __init__(self) -> None:
        self.open = False

    def show(self, text: str) -> None:
        sys.stderr.write("\r" + text)
        sys.stderr.flush()
        self.open = True

    def clear(self) -> None:
        """Blank the line if one is showing (the cursor back at its start)."""
        if self.open:
            self.open = False
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()

    def end(self) -> None:
        """Finish the line (a newline) if one is showing."""
        if self.open:
            self.open = False
            try:
                sys.stderr.write("\n")
                sys.stderr.flush()
            except OSError:  # the terminal is gone (SIGHUP)
                pass


TERM_LINE = TermLine()
"""The one in-place line of a command's stderr."""


KEEP_WARM_UP_S = 2.0
"""A warm-up of the compiled loops that took this long (or compiled any) leaves its
last progress line on stderr; a quicker one leaves nothing."""


@contextlib.contextmanager
def warm_up_progress(prog: str) -> Iterator[None]:
    """While the block runs, the compiled loops' warm-up (:func:`ceilkit.runtime.jit.
    warm_up`) shows its progress on stderr: rewritten in place on a terminal, else a
    line once it is seen to compile or to take :data:`KEEP_WARM_UP_S`, and one when
    done; its last line stays when it compiled or took that long (a first start on a
    machine), else it is blanked."""
    from ceilkit.runtime import jit

    tty = sys.stderr.isatty()
    said = []

    def show(p: jit.WarmUpProgress) -> None:
        text = f"{prog}: {p.line()}"
        kept = p.compiled > 0 or p.elapsed_s >= KEEP_WARM_UP_S
        if tty:
            TERM_LINE.show(text.ljust(max([len(t) for t in said] + [0])))
            said.append(text)
            if not p.module:
                TERM_LINE.end() if kept else TERM_LINE.clear()
        elif kept and (not said or not p.module):
            said.append(text)
            echo_err(text)

    with jit.reporting(show):
        yield


def echo_err(msg: str) -> None:
    """``msg`` on stderr, on a line of its own; nothing when the terminal is gone (an
    ssh session that dropped: the run's files are what matters then)."""
    TERM_LINE.end()
    try:
        typer.echo(msg, err=True)
    except OSError:
        pass


INTERRUPTED_EXIT = 130
"""The exit code of a command stopped by Ctrl-C (128 + SIGINT, as a shell's): every
command but the live run (``ceilrun``), which stops cleanly and exits 0."""


def _flags_as_flags(params: list[Any]) -> list[Any]:
    """``params`` with every flag (an option that takes no value: ``--tum``,
    ``--help``) shown bare in ``--help``, not as ``--tum <bool>``."""
    for p in params:
        if getattr(p, "is_flag", False) and p.metavar is None:
            p.metavar = ""
    return params


def _lists_as_items(params: list[Any]) -> list[Any]:
    """``params`` with an argument that takes several values shown in ``--help`` by
    its items' type (``RECORDING  <path>...``), not as ``<list[Path]>``."""
    for p in params:
        desc = getattr(p, "type_descriptor", None)
        if (getattr(p, "param_type_name", "") == "argument" and p.nargs != 1
                and desc is not None and desc.is_list and "display_type_rich" not in vars(p)):
            item = typing.get_args(desc.annotation)[0]
            label = f"<{'path' if item is Path else p._bare_type(item)}>..."
            p.display_type_rich = lambda ctx, label=label: label
    return params


class _Group(typer.core.TyperGroup):
    def format_help(self, ctx, formatter):  # type: ignore[override]
        greedy_help_column()
        return super().format_help(ctx, formatter)

    def get_params(self, ctx):  # type: ignore[override]
        return _flags_as_flags(super().get_params(ctx))

    def get_command(self, ctx, cmd_name):  # type: ignore[override]
        cmd = super().get_command(ctx, cmd_name)
        if cmd is not None:
            _lists_as_items(_flags_as_flags(cmd.get_params(ctx)))
        return cmd

    def parse_args(self, ctx, args):  # type: ignore[override]
        note_empty(self, ctx, args)
        return super().parse_args(ctx, args)

    def make_context(self, info_name, args, parent=None, **extra):  # type: ignore[override]
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except UsageError as exc:   # the top's own options: one line, exit 2
            if is_help_request(exc):
                raise
            echo_err(f"{info_name}: error: {usage_line(exc, '')}")
            raise typer.Exit(2) from None

    def invoke(self, ctx):  # type: ignore[override]
        try:
            check_params(ctx, "")
            return super().invoke(ctx)
        except UsageError as exc:   # a subcommand's options: one line, exit 2
            if is_help_request(exc):
                raise
            echo_err(f"{ctx.find_root().info_name}: error: "
                     f"{usage_line(exc, ctx.invoked_subcommand or '')}")
            ctx.exit(2)
        except CeilkitError as exc:
            name = ctx.invoked_subcommand
            cmd = self.get_command(ctx, name) if name else self
            params = getattr(cmd, "params", ())
            if isinstance(exc, ConfigError):
                takes = any("--option" in p.opts for p in params)
                exc = as_flags(exc, name or "", takes, params)
            text = str(exc).replace(FORCE_HINT, force_hint(params))
            echo_err(f"{ctx.find_root().info_name}: error: {text}")
            ctx.exit(1)
        except KeyboardInterrupt:   # Ctrl-C: one line, not click's "Aborted!"
            echo_err(f"{ctx.find_root().info_name}: interrupted")
            ctx.exit(INTERRUPTED_EXIT)


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """``--option KEY=VALUE`` items as ``{KEY: VALUE}`` (values stay strings: the
    estimator's options dataclass converts them and names a bad one).

    Raises:
        ConfigError: ``--option`` for an item without ``=`` or an empty key, or a key
            given twice.
    """
    out: dict[str, Any] = {}
    for item in items or []:
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ConfigError(None, "--option", f"expected KEY=VALUE, found {item!r}")
        if key in out:
            raise ConfigError(None, "--option", f"{key} given twice")
        out[key] = value.strip()
    return out


def make_app(name: str, help: str) -> typer.Typer:
    """A typer app whose ceilkit errors become one line on stderr and exit 1.

    The app has an empty group callback from the start, so that an app with a single
    command keeps it as a subcommand (``ceilcal simulate ...``, not ``ceilcal ...``)
    however many commands register. An app that wants to run something bare (as
    ``ceilrun`` runs live) registers its own ``@app.callback(...)``, which replaces
    this one.
    """
    app = CheckedTyper(name=name, help=help, cls=_Group, no_args_is_help=False,
                      add_completion=False, pretty_exceptions_enable=False,
                      context_settings={"help_option_names": list(HELP_FLAGS)})

    @app.callback()
    def _group(version: bool = VERSION_OPTION) -> None:
        pass

    return app


HELP_FLAGS = ("-h", "--help")
"""The flags that print a command's help (every command and subcommand)."""


def _print_version(ctx: typer.Context, value: bool) -> None:
    if value:
        from ceilkit.runtime.io.provenance import VERSION

        typer.echo(f"{ctx.find_root().info_name} (ceilkit) {VERSION}")
        raise typer.Exit()


VERSION_OPTION = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                              help="Print the version and exit.")
"""``--version``: a parameter of every command line's top (``ceilrun``, ``ceilcal``)."""


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
    """:func:`ceilkit.calib.workflow.provenance_header` (imported when first used: a
    ``ceilrun`` start does not load the calibration modules)."""
    from ceilkit.calib.workflow import provenance_header as header

    return header(what, lines or ())


# The board options that `ceilcal board` and `ceilcal intrinsics` share.
BOARD_OPTION = typer.Option(..., "--board", help="chess:COLSxROWS (inner corners) or "
                                                 "charuco:SXxSY[:DICT][:legacy] (squares).")
SQUARE_OPTION = typer.Option(..., "--square", help="Square side, metres.")
MARKER_OPTION = typer.Option(None, "--marker",
                             help="ChArUco marker side, metres (0.75 square).")


# The camera-format options that `ceilrun` (live), `ceilcal intrinsics --device` and
# `ceilcal exposure` share: one definition each (runtime.session.CaptureSettings).
WIDTH_OPTION = typer.Option(0, "--width", help="Capture width (0: driver default).")
HEIGHT_OPTION = typer.Option(0, "--height", help="Capture height.")
FPS_OPTION = typer.Option(0.0, "--fps", help="Capture rate.")
FOURCC_OPTION = typer.Option("", "--fourcc", "--pixel-format",
                             help="Pixel format, e.g. MJPG or YUYV.")
EXPOSURE_OPTION = typer.Option(None, "--exposure",
                               help="Manual exposure (turns auto-exposure off).")
GAIN_OPTION = typer.Option(None, "--gain", help="Manual gain.")
CAPTURE_OPTION = typer.Option(None, "--capture", help="capture.yaml (ceilcal exposure): "
                              "its exposure and gain, unless given here.")


def capture_settings(path: Path | None, width: int, height: int, fps: float, fourcc: str,
                     exposure: float | None, gain: float | None) -> CaptureSettings:
    """The camera settings of the options above, with the capture file's (``path``,
    written by ``ceilcal exposure``) exposure and gain where not given."""
    from ceilkit.runtime.session import CaptureSettings

    settings = CaptureSettings(width, height, fps, fourcc, exposure, gain)
    if path is None:
        return settings
    from ceilkit.runtime.config.capture import load_capture

    cap = load_capture(path)
    return dataclasses.replace(
        settings, exposure=cap.exposure if settings.exposure is None else settings.exposure,
        gain=cap.gain if settings.gain is None else settings.gain)
