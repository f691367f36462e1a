"""cli/ceilcal.py: a command's process imports only that command's module, so that
``ceilcal board`` stays small (issue 37: 266 MB with numba and scipy, for a PDF)."""

from __future__ import annotations

import json
import subprocess
import sys

import typer

from ceilkit.cli import ceilcal

CHILD = r"""
import json, sys
sys.argv = ["ceilcal"] + sys.argv[1:]
from ceilkit.cli.ceilcal import main
try:
    main()
except SystemExit:
    pass
heavy = sorted({m.split(".")[0] for m in sys.modules} & {"numba", "scipy", "matplotlib"})
print(json.dumps(heavy))
"""


def _heavy_imports(*args: str) -> list[str]:
    proc = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True,
                          text=True, timeout=120)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_board_imports_neither_numba_nor_scipy(tmp_path):
    out = tmp_path / "board.pdf"
    assert _heavy_imports("board", "--board", "chess:9x6", "--square", "0.025",
                          "--out", str(out)) == []
    assert out.read_bytes().startswith(b"%PDF")
    assert _heavy_imports("check-site", "--help") == []


def test_a_commands_app_holds_that_command_and_the_full_app_all():
    def names(app: typer.Typer) -> list[str]:
        return list(typer.main.get_command(app).commands)

    assert names(ceilcal.build_app("board")) == ["board"]
    assert names(ceilcal.build_app("check-site")) == ["check-site"]
    assert sorted(names(ceilcal.app)) == sorted(ceilcal.COMMANDS)
    assert ceilcal.app is ceilcal.app          # built once
