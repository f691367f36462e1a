"""Every value a command line takes is checked once, here, before the command runs.

* **Numbers** (every ``int`` and ``float`` option): a float must be finite, and each
  numeric flag has its range in :data:`RANGES` (by flag; :data:`COMMAND_RANGES` where
  one command means something else by it). :func:`check_params` refuses a value outside
  it in one line naming the flag as typed and the range::

      ceilrun: error: --baud: expected an integer in [1, 4000000] (bit/s), found -5

* **Empty strings**: ``--view-token ''``, ``--method ''``, ``--serial ''`` (or only
  blanks) are errors (an unset shell variable, never a choice), except the flags of
  :data:`EMPTY_OK`.
* **Library names**: a library function names its parameter (``ConfigError(None,
  "start_pose", ...)``); :func:`flag_of` finds the flag of that parameter in the
  command's own parameter table (``start_pose`` -> ``--start-pose``, ``ceiling_height_m``
  -> ``--ceiling-height``: a unit suffix is dropped).
* **Usage errors** (an option that does not parse, an unknown option) are one line too
  (:func:`usage_line`), exit code 2.

A new numeric flag without a range fails ``tests/cli/test_values.py``, which walks
every command's parameters and tries NaN, infinities, negatives and huge values on each.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import typer
import typer.core

from ceilkit.runtime.errors import ConfigError


@dataclass(frozen=True)
class Range:
    """The values a numeric flag takes: ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``),
    in ``unit``."""

    lo: float
    hi: float
    lo_open: bool = False
    unit: str = ""

    def holds(self, v: float) -> bool:
        above = v > self.lo if self.lo_open else v >= self.lo
        return math.isfinite(v) and above and v <= self.hi

    def expected(self, integer: bool) -> str:
        """``an integer in [1, 255]`` / ``a number in (0, 100] m``."""
        what = "an integer" if integer else "a number"
        unit = f" {self.unit}" if self.unit else ""
        return f"{what} in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}]{unit}"


def _num(v: float) -> str:
    if isinstance(v, int) or (math.isfinite(v) and float(v).is_integer() and abs(v) < 1e15):
        return str(int(v))
    return f"{v:g}"


def _found(v: Any) -> str:
    text = _num(v) if isinstance(v, (int, float)) else repr(v)
    return text if len(text) <= 40 else f"{text[:20]}... ({len(text)} characters)"


RANGES: Mapping[str, Range] = MappingProxyType({
    # the link (ceilrun, ceilrun replay)
    "--baud": Range(1, 4_000_000, unit="bit/s"),
    "--sysid": Range(1, 255),
    "--compid": Range(0, 255),
    "--wheel-track": Range(0, 100, lo_open=True, unit="m"),
    # the run
    "--frames": Range(0, 100_000_000, unit="frames (0: until stopped)"),
    "--fsync-every": Range(0, 3600, unit="s (0: off)"),
    "--ros2-wait": Range(0, 3600, unit="s (0: do not wait)"),
    # the camera's format (ceilrun, ceilcal intrinsics, ceilcal exposure)
    "--width": Range(0, 16384, unit="px (0: the driver's)"),
    "--height": Range(0, 16384, unit="px (0: the driver's)"),
    "--fps": Range(0, 1000, unit="Hz (0: the driver's)"),
    "--exposure": Range(0, 10_000_000, lo_open=True, unit="(the driver's units)"),
    "--gain": Range(-1000, 1_000_000, unit="(the driver's units; sim: dB)"),
    # boards
    "--square": Range(0, 10, lo_open=True, unit="m"),
    "--marker": Range(0, 10, lo_open=True, unit="m"),
    # ceilcal simulate
    "--lateral": Range(-1000, 1000, unit="m"),
    "--weave": Range(0, 100, unit="m"),
    "--wobble": Range(0, 180, unit="degrees"),
    "--speed": Range(0, 100, lo_open=True, unit="m/s"),
    "--noise": Range(0, 255, unit="grey levels"),
    "--blur": Range(0, 100, unit="px"),
    "--supersample": Range(1, 16),
    "--seed": Range(0, 2**32 - 1),
    "--views": Range(5, 10_000),
    # ceilcal intrinsics
    "--min-views": Range(3, 10_000),
    "--max-views": Range(1, 10_000),
    "--every": Range(1, 1_000_000),
    # ceilcal mount
    "--max-frames": Range(1, 10_000),
    # ceilcal lightmap
    "--pose-offset-ms": Range(-3_600_000, 3_600_000, unit="ms"),
    "--ceiling-height": Range(0, 100, lo_open=True, unit="m"),
    "--cluster": Range(0, 10, lo_open=True, unit="m"),
    "--start-yaw": Range(-360, 360, unit="degrees"),
    "--anchor-frame": Range(0, 100_000_000),
    # ceilcal blockmap
    "--size": Range(0, 10, lo_open=True, unit="m"),
    # ceilcal survey
    "--readout-ms": Range(0, 1000, unit="ms (0: a global shutter)"),
    # ceilcal exposure
    "--settle": Range(0, 1000, unit="frames"),
    # ceilcal check-site
    "--step": Range(0, 100, lo_open=True, unit="m"),
    "--heading-step": Range(0, 360, lo_open=True, unit="degrees"),
    "--tol-px": Range(0, 1000, lo_open=True, unit="px"),
    "--search": Range(0, 1000, lo_open=True, unit="m"),
    "--margin": Range(0, 1000, unit="m"),
})
"""The range of each numeric flag, by flag (the same in every command that has it)."""

COMMAND_RANGES: Mapping[str, Mapping[str, Range]] = MappingProxyType({
    "simulate": MappingProxyType({
        "--frames": Range(1, 1_000_000, unit="frames"),
        "--fps": Range(0, 1000, lo_open=True, unit="Hz"),
    }),
    "exposure": MappingProxyType({"--frames": Range(1, 1000, unit="frames per setting")}),
    "lightmap": MappingProxyType({"--min-views": Range(1, 10_000, unit="frames")}),
})
"""Ranges of a flag that means something else in one command (by the command's name)."""

OWN_CHECKS = frozenset({"board", "autopilot"})
"""Commands that check their numbers themselves (``calib/board_pdf.py``,
``calib/autopilot.py``): their flags are not in :data:`RANGES`."""

EMPTY_OK = frozenset({"--fourcc", "--ros2-namespace", "--ros2-odometry"})
"""String flags for which an empty value means something (the driver's format, no
namespace, no odometry topic)."""

UNIT_SUFFIXES = ("_m", "_s", "_ms", "_deg", "_rad", "_px", "_mps", "_hz")
"""Units a library parameter's name carries that its flag does not (``wheel_track_m``
is ``--wheel-track``)."""


def range_of(command: str, flag: str) -> Range | None:
    """The range of ``flag`` in ``command`` (a subcommand's name; ``""`` for the top)."""
    if command in OWN_CHECKS:
        return None
    return COMMAND_RANGES.get(command, {}).get(flag) or RANGES.get(flag)


def flag_name(param: Any) -> str:
    """A parameter as a user types it: ``--start-pose``, or ``RECORDING`` (an argument)."""
    opts = [o for o in getattr(param, "opts", ()) if o.startswith("--")]
    if getattr(param, "param_type_name", "") == "option" and opts:
        return opts[0]
    return str(getattr(param, "metavar", None) or param.name).upper()


def numeric_kind(param: Any) -> type | None:
    """``int`` or ``float`` for a parameter that takes one number, else None (from the
    declared type: typer's annotation, or click's parameter type)."""
    desc = getattr(param, "type_descriptor", None)
    kind = getattr(desc, "annotation", None)
    if kind is None:
        name = getattr(getattr(param, "type", None), "name", "")
        kind = {"integer": int, "float": float, "integer range": int,
                "float range": float}.get(name)
    if getattr(param, "multiple", False) or getattr(param, "is_flag", False):
        return None
    return kind if kind in (int, float) else None


EMPTY_GIVEN = "ceilkit.empty_given"
"""``ctx.meta`` key: the parameters given an empty text on the command line."""


def note_empty(command: Any, ctx: Any, args: list[str]) -> None:
    """Note in ``ctx.meta`` which parameters ``args`` gives an empty (or blank) text: a
    path's ``''`` is ``Path('.')`` once converted (``--rig ''`` would read the current
    folder), so only the raw text tells. A command line that does not parse is left to
    the real parse to name."""
    try:
        opts, _, _ = command.make_parser(ctx).parse_args(args=list(args))
    except Exception:  # noqa: BLE001 (the real parse reports it, in one line)
        return
    ctx.meta[EMPTY_GIVEN] = frozenset(
        name for name, v in opts.items() if isinstance(v, str) and not v.strip())


def check_params(ctx: Any, command: str) -> None:
    """Refuse a value of ``ctx``'s parsed parameters that is out of its range, not a
    finite number, or an empty string given on the command line.

    Raises:
        ConfigError: keyed by the flag as typed (``--baud``), with the range expected.
    """
    empty_given = ctx.meta.get(EMPTY_GIVEN, frozenset())
    for param in ctx.command.params:
        value = ctx.params.get(param.name)
        flag = flag_name(param)
        empty = param.name in empty_given or (isinstance(value, str) and not value.strip())
        if empty and flag not in EMPTY_OK \
                and getattr(ctx.get_parameter_source(param.name), "name", "") == "COMMANDLINE":
            raise ConfigError(None, flag, "expected a value, found "
                              + (repr(value) if isinstance(value, str) and value
                                 else "an empty string"))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        span = range_of(command, flag)
        if span is None:
            if command not in OWN_CHECKS and not math.isfinite(value):
                raise ConfigError(None, flag, f"expected a finite number, found {_found(value)}")
            continue
        if not span.holds(value):
            raise ConfigError(None, flag, f"expected {span.expected(isinstance(value, int))}, "
                                          f"found {_found(value)}")


def flag_of(key: str, params: Iterable[Any]) -> str | None:
    """The flag (as typed) of the parameter a library names ``key``, from the command's
    own parameters: the same name, or the name without a unit suffix; None if none."""
    by_name = {p.name: p for p in params}
    for name in (key, *(key[:-len(s)] for s in UNIT_SUFFIXES if key.endswith(s))):
        if name in by_name:
            return flag_name(by_name[name])
    return None


def _usage_error_class() -> type[Exception]:
    return next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")


UsageError = _usage_error_class()
"""click's ``UsageError`` (typer's own copy of click, or click)."""


def _typed(exc: Exception) -> Any:
    """The text a user gave for a parameter that did not parse, when known."""
    cause = exc.__cause__
    try:
        return cause.errors()[0]["input"]  # type: ignore[union-attr]
    except (AttributeError, IndexError, KeyError, TypeError):
        return None


def usage_line(exc: Exception, command: str) -> str:
    """A usage error (bad option value, unknown option, missing argument) as one line,
    naming the flag and, for a number, the range expected."""
    param = getattr(exc, "param", None)
    message = " ".join(str(getattr(exc, "message", "") or exc.format_message()).split())
    message = message.removeprefix("Value error, ")   # pydantic's, in typer >= 0.29
    if type(exc).__name__ != "BadParameter":
        return " ".join(exc.format_message().split())
    if param is None:             # a command's own check: its message names the flags
        return message
    flag = flag_name(param)
    kind, span, typed = numeric_kind(param), range_of(command, flag), _typed(exc)
    if kind is not None:
        what = span.expected(kind is int) if span else \
            ("an integer" if kind is int else "a number")
        found = f", found {_found(typed)}" if typed is not None else ""
        return f"{flag}: expected {what}{found}"
    return f"{flag}: {message}"


def is_help_request(exc: Exception) -> bool:
    """A usage error that shows the help (a bare command that needs arguments)."""
    return type(exc).__name__ == "NoArgsIsHelpError"


def greedy_help_column() -> None:
    """Make ``-h``'s option tables leave their help column the width the terminal has.

    typer lays an option out in six columns (name, short name, negative name, its
    short, value type, help) and rich narrows the help column to what the others leave:
    at 100 columns ``ceilrun replay -h`` wrapped its help in 31 (11 at 80), for the one
    ``--no-progress`` and the one ``-h``. Here an option's names share one column
    (``--help, -h``; ``--progress, --no-progress``), as docs/cli.md writes them, and the
    help column takes the rest (48 at 100 columns)."""
    import typer.rich_utils as ru
    from rich.table import Table
    from rich.text import Text

    if getattr(ru.Table, "greedy_help", False):
        return

    class _GreedyTable(Table):
        greedy_help = True

        def add_row(self, *cells: Any, **kwargs: Any) -> None:
            if len(cells) >= 6:                 # [required], 4 name columns, type, help
                head, names, rest = cells[:-6], cells[-6:-2], cells[-2:]
                parts = [n for n in names if isinstance(n, Text) and n.plain]
                joined = Text(", ").join(parts) if parts else Text("")
                cells = (*head, joined, *rest)
            super().add_row(*cells, **kwargs)

    ru.Table = _GreedyTable


class CheckedCommand(typer.core.TyperCommand):
    """A subcommand whose parameters pass :func:`check_params` before it runs."""

    def format_help(self, ctx, formatter):  # type: ignore[override]
        greedy_help_column()
        return super().format_help(ctx, formatter)

    def parse_args(self, ctx, args):  # type: ignore[override]
        note_empty(self, ctx, args)
        return super().parse_args(ctx, args)

    def invoke(self, ctx):  # type: ignore[override]
        check_params(ctx, ctx.info_name or "")
        return super().invoke(ctx)


class CheckedTyper(typer.Typer):
    """A typer app whose commands are :class:`CheckedCommand` unless given a class."""

    def command(self, *args: Any, cls: Any = None, **kwargs: Any):  # type: ignore[override]
        return super().command(*args, cls=cls or CheckedCommand, **kwargs)
