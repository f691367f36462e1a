"""``-h`` on an ordinary terminal: the help column keeps the width the names leave."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app as ceilcal_app
from ceilkit.cli.ceilrun import app as ceilrun_app


@pytest.mark.parametrize("app,args", [(ceilrun_app, ["replay", "-h"]), (ceilrun_app, ["-h"]),
                                      (ceilcal_app, ["calibrate", "-h"])])
def test_help_column_is_wide_at_100_columns(monkeypatch, app, args):
    """An option's names share one column (``--help, -h``), so at 100 columns the help
    starts before column 50 (it was 66 for ``ceilrun replay``: a 31-column help)."""
    monkeypatch.setenv("COLUMNS", "100")          # what rich reads
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rows = [ln for ln in res.stdout.splitlines() if "--help" in ln]
    assert rows and "--help, -h " in rows[0]
    start = rows[0].index("Show this message")
    assert start < 50, rows[0]


def test_a_negative_flag_is_named_beside_its_flag(monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    res = CliRunner().invoke(ceilrun_app, ["replay", "-h"])
    row = next(ln for ln in res.stdout.splitlines() if "--no-progress" in ln)
    assert "--progress, --no-progress" in row
    assert "Replace an existing poses.csv (refused otherwise)." in res.stdout   # one line
