"""`ceilcal simulate` through typer's CliRunner."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.cli import ceilcal_simulate
from ceilkit.cli.ceilcal import app
from ceilkit.cli.common import make_app
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.io.recording import TRUTH_HEADER, Recording
from helpers import CONFIGS

runner = CliRunner()


def small_rig(tmp_path, name="corridor", w=96, h=72):
    rig = Rig.load(CONFIGS / name / "rig.yaml")
    path = tmp_path / "rig.yaml"
    Rig(rig.camera.scaled(w, h), rig.mount).save(path)
    return path


def test_simulate_drive(tmp_path):
    out = tmp_path / "rec"
    res = runner.invoke(app, ["simulate", "--out", str(out), "--rig", str(small_rig(tmp_path)),
                              "--frames", "4", "--fps", "10", "--lateral", "0.1",
                              "--weave", "0.05", "--noise", "1", "--clutter", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert res.output.count("\n") == 1 and "wrote 4 frames" in res.output
    rec = Recording(out)
    assert len(rec) == 4 and rec.t_ns[1] == 100_000_000
    assert rec.truth is not None and abs(np.mean(rec.truth.y_m) - 0.1) < 0.06
    assert rec.frame(0).image.shape == (72, 96)


def test_simulate_defaults_to_packaged_corridor(tmp_path):
    out = tmp_path / "rec"
    res = runner.invoke(app, ["simulate", "--out", str(out), "--frames", "2",
                              "--supersample", "1", "--trajectory", "random"])
    assert res.exit_code == 0, res.output
    rec = Recording(out)
    assert rec.rig.camera.size == (640, 480)
    assert rec.site.corridor is not None and len(rec) == 2


def test_simulate_from_trajectory_file(tmp_path):
    traj = tmp_path / "traj.csv"
    traj.write_text(",".join(TRUTH_HEADER) + "\n0,1.0,0.0,0.0\n50000000,1.1,0.01,2.0\n")
    out = tmp_path / "rec"
    res = runner.invoke(app, ["simulate", "--out", str(out), "--rig", str(small_rig(tmp_path)),
                              "--trajectory", str(traj)])
    assert res.exit_code == 0, res.output
    rec = Recording(out)
    assert list(rec.t_ns) == [0, 50_000_000]
    assert rec.truth is not None and np.degrees(rec.truth.yaw_rad[1]) == 2.0


def test_simulate_errors(tmp_path):
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "a"),
                              "--trajectory", str(tmp_path / "none.csv")])
    assert res.exit_code == 1 and "none.csv" in res.output
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "b"), "--rig",
                              str(small_rig(tmp_path)), "--noise", "-1"])
    assert res.exit_code == 1 and "--noise" in res.output
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "c"),
                              "--rig", str(tmp_path / "missing.yaml")])
    assert res.exit_code == 1 and "missing.yaml" in res.output


@pytest.mark.parametrize("args,flag", [
    (["--noise", "-1"], "--noise"), (["--blur", "nan"], "--blur"),
    (["--supersample", "9"], "--supersample"), (["--supersample", "0"], "--supersample"),
    (["--lateral", "nan"], "--lateral"), (["--weave", "inf"], "--weave"),
    (["--wobble", "nan"], "--wobble"), (["--speed", "nan"], "--speed"),
    (["--trajectory", "random", "--lateral", "inf"], "--lateral"),
])
def test_bad_values_name_the_flag(tmp_path, args, flag):
    """One line on stderr naming the flag the user typed, not the library's field."""
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "r"), *args])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ceilcal: error: {flag}: ")
    for internal in ("options.", "noise_sigma", "blur_px", "y_m", "_rad", "speed_mps"):
        assert internal not in res.output
    assert not (tmp_path / "r").exists()


def test_single_command_app_keeps_its_subcommand(tmp_path):
    """make_app gives every app a group callback: with only `simulate` registered,
    `simulate` is still a subcommand, and a bare option is not taken as the command's."""
    one = make_app("one", "only simulate")
    ceilcal_simulate.register(one)
    res = runner.invoke(one, ["simulate", "--out", str(tmp_path / "r"), "--rig",
                              str(small_rig(tmp_path)), "--frames", "1", "--supersample", "1"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r" / "frames.csv").exists()
    res = runner.invoke(one, ["--out", str(tmp_path / "s")])
    assert res.exit_code != 0 and not (tmp_path / "s").exists()
    assert "simulate" in runner.invoke(one, ["--help"]).output


def test_simulate_boards_and_placements(tmp_path):
    from ceilkit.calib.mount import load_placements
    from ceilkit.runtime.config.camera import load_camera
    from ceilkit.runtime.io.capture import list_images

    rig = small_rig(tmp_path, w=160, h=120)
    res = runner.invoke(app, ["simulate", "--kind", "boards", "--board", "chess:5x4",
                              "--square", "0.03", "--views", "5", "--rig", str(rig),
                              "--supersample", "1", "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert len(list_images(tmp_path / "b")) == 5
    assert load_camera(tmp_path / "b" / "camera_truth.yaml").width == 160
    res = runner.invoke(app, ["simulate", "--kind", "placements", "--rig", str(rig),
                              "--placement", "0.2,0", "--placement", "-0.1,15",
                              "--supersample", "1", "--out", str(tmp_path / "p")])
    assert res.exit_code == 0, res.output
    pls = load_placements(tmp_path / "p" / "placements.yaml",
                          Rig.load(rig).camera)
    assert [p.label for p in pls] == ["p00.png", "p01.png"]
    assert np.allclose([(p.y_m, np.degrees(p.yaw_rad)) for p in pls], [(0.2, 0), (-0.1, 15)])
    assert Rig.load(tmp_path / "p" / "rig_truth.yaml").mount == Rig.load(rig).mount


@pytest.mark.parametrize("args,flag", [
    (["--kind", "boards"], "--board"),
    (["--kind", "boards", "--board", "chess:5x4", "--square", "0.03", "--views", "3"],
     "--views"),
    (["--kind", "weird"], "--kind"),
    (["--kind", "placements", "--placement", "0.1"], "--placement"),
    (["--kind", "boards", "--board", "chess:5x4", "--square", "0.03", "--noise", "-1"],
     "--noise"),
])
def test_simulate_kinds_bad_values_name_the_flag(tmp_path, args, flag):
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "x"), *args])
    assert res.exit_code == 1
    assert f"error: {flag}:" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "x").exists()


def test_simulate_placements_refuses_a_folder_with_images(tmp_path):
    rig = small_rig(tmp_path, w=96, h=72)
    args = ["simulate", "--kind", "placements", "--rig", str(rig), "--supersample", "1",
            "--placement", "0,0", "--out", str(tmp_path / "p")]
    assert runner.invoke(app, args).exit_code == 0
    res = runner.invoke(app, args)
    assert res.exit_code == 1 and "give a new folder" in res.output
