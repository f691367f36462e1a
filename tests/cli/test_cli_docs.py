"""docs/cli.md stays the reference of the command lines: every command and every option
that `ceilrun` and `ceilcal` accept is documented there."""

from __future__ import annotations

import pytest
import typer
import typer.main

from ceilkit.cli.ceilcal import app as ceilcal_app
from ceilkit.cli.ceilrun import app as ceilrun_app
from helpers import ROOT

CLI_DOC = ROOT / "docs" / "cli.md"


def _commands(prog: str, app: typer.Typer):
    """``(heading, command)`` of a typer app: the app itself (when it takes options) and
    each subcommand."""
    cmd = typer.main.get_command(app)
    if any(p.param_type_name == "option" for p in cmd.params):   # more than --help
        yield prog, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield f"{prog} {name}", sub


def _sections() -> dict[str, str]:
    """docs/cli.md split at its ``## `command``` headings."""
    out, key = {}, None
    for line in CLI_DOC.read_text().splitlines():
        if line.startswith("## `") and line.rstrip().endswith("`"):
            key = line.strip()[4:-1]
            out[key] = ""
        elif key is not None:
            out[key] += line + "\n"
    return out


CASES = [(h, c) for prog, app in (("ceilrun", ceilrun_app), ("ceilcal", ceilcal_app))
         for h, c in _commands(prog, app)]


@pytest.mark.parametrize("heading,cmd", CASES, ids=[h for h, _ in CASES])
def test_every_option_is_documented(heading, cmd):
    sections = _sections()
    assert heading in sections, f"docs/cli.md has no section for `{heading}`"
    text = sections[heading]
    missing = [opt for p in cmd.params if p.param_type_name == "option"
               for opt in p.opts[:1]
               if opt not in text]
    assert not missing, f"docs/cli.md, `{heading}`: options not documented: {missing}"
