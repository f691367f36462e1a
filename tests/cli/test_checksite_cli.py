"""`ceilcal check-site`: the report on stdout, the map and the figures with --out, and
no output overwritten."""

from __future__ import annotations

import yaml
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app
from helpers import CONFIGS

SITE = """\
ceiling_height: 2.8
corridor:
  lines_along: [-0.45, -0.15, 0.15, 0.45]
lamps:
  - {x: 0.0, y: 0.0, length: 1.2, width: 0.3, pitch: 2.4, count: 4}
"""


def test_check_site_writes_the_map_and_figures_and_refuses_to_overwrite(tmp_path):
    site = tmp_path / "site.yaml"
    site.write_text(SITE)
    out = tmp_path / "check"
    args = ["check-site", "--rig", str(CONFIGS / "block" / "rig.yaml"), "--site", str(site),
            "--step", "1.0", "--search", "8", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "ambiguous:" in res.output and "half turn" in res.output
    assert "region 1:" in res.output and "would single it out" in res.output
    png = (out / "check-site.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    figures = yaml.safe_load((out / "check-site.yaml").read_text())
    assert figures["share"]["ambiguous"] > 0.5
    assert figures["share"]["by_kind"]["half turn"] > 0.5
    assert figures["regions"] and figures["regions"][0]["markers"]
    assert (out / "check-site.yaml").read_text().startswith("# ceilcal check-site")
    before = png
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1
    assert "check-site.png: already there; nothing was overwritten" in res.output
    assert (out / "check-site.png").read_bytes() == before


def test_check_site_reports_on_stdout_and_names_a_bad_flag(tmp_path):
    args = ["check-site", "--rig", str(CONFIGS / "lights" / "rig.yaml"),
            "--site", str(CONFIGS / "lights" / "site.yaml"), "--step", "4"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "ambiguous: 0.0% of poses" in res.output
    res = CliRunner().invoke(app, args[:-1] + ["0"])
    assert res.exit_code == 1 and "--step: expected a number in (0, 100] m, found 0" in res.output
