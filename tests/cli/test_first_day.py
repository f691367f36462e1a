"""What a new integrator meets first (issue 37): ``--version`` and ``-h`` everywhere,
flags shown as flags, ``ceilkit-ros2``'s own help, the warm-up command and its progress
line, the unknown-method message, a missing ``--site`` said before an existing output,
``--status`` beside ``--serial -``."""

from __future__ import annotations

import re
import sys

import pytest
import typer.main
from typer.testing import CliRunner

from ceilkit.cli import ceilrun
from ceilkit.cli.ceilcal import app as ceilcal_app
from ceilkit.cli.ceilrun import app as ceilrun_app
from ceilkit.cli.common import warm_up_progress
from ceilkit.runtime import jit
from ceilkit.runtime.io.provenance import VERSION
from helpers import FIXTURES, ROOT


@pytest.mark.parametrize("app,prog", [(ceilrun_app, "ceilrun"), (ceilcal_app, "ceilcal")])
def test_version(app, prog):
    res = CliRunner().invoke(app, ["--version"], prog_name=prog)
    assert res.exit_code == 0, res.output
    assert res.stdout == f"{prog} (ceilkit) {VERSION}\n"
    assert VERSION != "unknown"          # the installed package's version


def _subcommands():
    for prog, app in (("ceilrun", ceilrun_app), ("ceilcal", ceilcal_app)):
        yield prog, app, []
        for name in typer.main.get_command(app).commands:
            yield prog, app, [name]


@pytest.mark.parametrize("prog,app,args", list(_subcommands()),
                         ids=[" ".join([p, *a]) for p, _, a in _subcommands()])
def test_dash_h_everywhere_and_flags_shown_as_flags(prog, app, args):
    res = CliRunner().invoke(app, [*args, "-h"], prog_name=prog, terminal_width=200)
    assert res.exit_code == 0, res.output
    assert "Usage:" in res.stdout and "--help" in res.stdout
    assert "<bool>" not in res.stdout    # a flag takes no value: `--tum`, not `--tum <bool>`


def test_ceilkit_ros2_has_its_own_help_and_version(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["ceilkit-ros2", "-h"])
    ceilrun.ros2_main()
    text = capsys.readouterr().out
    assert text.startswith("Usage: ceilkit-ros2 [OPTIONS]")
    assert "ceilkit-ros2 replay RECORDING" in text and "--ros2-namespace NS" in text
    assert "--version" in text and "Run the localizer" not in text   # not ceilrun's text
    res = CliRunner().invoke(ceilrun_app, ["--ros2", "--version"], prog_name="ceilkit-ros2")
    assert res.stdout == f"ceilkit-ros2 (ceilkit) {VERSION}\n"


def test_unknown_method_lists_auto(tmp_path):
    res = CliRunner().invoke(ceilrun_app, ["replay", str(FIXTURES / "lights_rec"),
                                           "--out", str(tmp_path), "--method", "magic"])
    assert res.exit_code == 1
    assert "--method: unknown method 'magic' (choose from auto, corridor" in res.stderr


def test_a_missing_site_is_said_before_an_existing_output(tmp_path):
    (tmp_path / "poses.csv").write_text("kept\n")
    res = CliRunner().invoke(ceilrun_app, ["replay", str(FIXTURES / "lights_rec"), "--out",
                                           str(tmp_path), "--site", str(tmp_path / "no.yaml")])
    assert res.exit_code == 1
    assert res.stderr == f"ceilrun: error: {tmp_path / 'no.yaml'}: file not found\n"
    assert (tmp_path / "poses.csv").read_text() == "kept\n"


def test_status_beside_poses_on_stdout_is_whole_lines():
    res = CliRunner().invoke(ceilrun_app, ["--device", "sim:lights", "--serial", "-",
                                           "--status", "--frames", "3", "--no-realtime"])
    assert res.exit_code == 0, res.output
    assert "\r" not in res.stderr
    assert any(line.startswith("ceilrun: ") and "frame" in line
               for line in res.stderr.splitlines())
    sentences = res.stdout.splitlines()
    assert len(sentences) >= 3 and all(s.startswith("$") for s in sentences)


def test_warm_up_command():
    res = CliRunner().invoke(ceilrun_app, ["warm-up"])
    assert res.exit_code == 0, res.output
    assert "compiled loops ready" in res.stdout


def test_warm_up_progress_off_a_terminal(capsys):
    """Off a terminal: nothing for a quick load from the cache; a line once it is seen
    to compile, and the last one."""
    with warm_up_progress("ceilrun"):
        jit._report(jit.WarmUpProgress(0, 40, "ceilkit.runtime.features.lines", 0, 0.0))
        jit._report(jit.WarmUpProgress(40, 40, "", 0, 0.4))
    assert capsys.readouterr().err == ""
    with warm_up_progress("ceilrun"):
        for done in (0, 10, 20):
            jit._report(jit.WarmUpProgress(done, 40, "ceilkit.runtime.features.lines",
                                           done, 5.0 * done))
        jit._report(jit.WarmUpProgress(40, 40, "", 40, 130.0))
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "ceilrun: compiling the per-frame loops (first start on this machine; numba's "
        "cache keeps them): 10/40, features.lines, 50.0 s",
        "ceilrun: compiling the per-frame loops (first start on this machine; numba's "
        "cache keeps them): 40/40, 130.0 s"]


def test_docs_link_nothing_outside_the_repository():
    """A fresh clone holds every page a doc links to (docs/integration.md linked
    ``../shared/SPEC.md``: the contract is docs/conventions.md)."""
    for md in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        text = md.read_text()
        assert "../shared/SPEC.md" not in text, md
        for target in re.findall(r"\]\(([^)#\s]+)", text):
            if "://" in target:
                continue
            path = (md.parent / target).resolve()
            assert ROOT.resolve() in path.parents and path.exists(), f"{md}: {target}"
