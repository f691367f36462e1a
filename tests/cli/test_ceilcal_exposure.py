"""`ceilcal exposure` wiring and `ceilrun --capture`."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app
from ceilkit.cli.common import capture_settings
from ceilkit.runtime.config.capture import load_capture


def test_exposure_writes_the_capture_file_ceilrun_reads(tmp_path):
    out = tmp_path / "capture.yaml"
    res = CliRunner().invoke(app, ["exposure", "--device", "sim:lights", "--exposures",
                                   "50,100,200", "--gains", "0", "--settle", "0",
                                   "--frames", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "best for lights: exposure 100, gain 0" in res.stdout
    assert load_capture(out).exposure == 100.0
    settings = capture_settings(out, 640, 0, 0.0, "", None, None)
    assert (settings.width, settings.exposure, settings.gain) == (640, 100.0, 0.0)
    mine = capture_settings(out, 0, 0, 0.0, "", 30.0, None)
    assert (mine.exposure, mine.gain) == (30.0, 0.0)      # the command line wins


def test_bad_lists_are_one_line(tmp_path):
    res = CliRunner().invoke(app, ["exposure", "--device", "sim:lights", "--exposures",
                                   "10,fast", "--out", str(tmp_path / "c.yaml")])
    assert res.exit_code == 1
    assert "exposures" in res.output and "Traceback" not in res.output
    assert not Path(tmp_path / "c.yaml").exists()
