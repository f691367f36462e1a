"""docs/tour.md's simulated track, small: `ceilcal simulate` boards, placements and a
drive -> `ceilcal calibrate` (intrinsics, mount) -> `ceilrun replay` with the calibrated
rig, all through the command lines (no rig value typed in, no Python rendering)."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app as ceilcal
from ceilkit.cli.ceilrun import app as ceilrun
from ceilkit.runtime.config.camera import load_camera
from ceilkit.runtime.config.rig import Rig
from helpers import replay_errors


def _ok(app, args):
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return res.output


def test_the_simulated_track_meets_the_targets(tmp_path):
    boards, pl, drive, cal = (tmp_path / n for n in ("boards", "placements", "drive", "cal"))
    _ok(ceilcal, ["simulate", "--kind", "boards", "--board", "chess:9x6", "--square",
                  "0.025", "--views", "20", "--supersample", "2", "--out", str(boards),
                  "--seed", "1"])
    _ok(ceilcal, ["simulate", "--kind", "placements", "--out", str(pl), "--seed", "2"])
    out = _ok(ceilcal, ["calibrate", "--boards", str(boards), "--board", "chess:9x6",
                        "--square", "0.025", "--placements", str(pl / "placements.yaml"),
                        "--site", str(pl / "site.yaml"), "--out", str(cal)])
    assert "step 2/3: mount" in out
    truth_cam = load_camera(boards / "camera_truth.yaml")
    rig = Rig.load(cal / "rig.yaml")
    truth = Rig.load(pl / "rig_truth.yaml")
    assert abs(rig.camera.fx / truth_cam.fx - 1) < 0.005
    assert abs(np.degrees(rig.mount.tilt_rad - truth.mount.tilt_rad)) < 0.2
    assert abs(rig.mount.x_m - truth.mount.x_m) < 0.01
    assert (cal / "rig.urdf.xml").is_file() and (cal / "rig.viso.param").is_file()
    _ok(ceilcal, ["simulate", "--out", str(drive), "--frames", "20", "--lateral", "0.1",
                  "--weave", "0.05", "--wobble", "2", "--seed", "3"])
    # the corridor is symmetric about its centre line: the drive's start singles it out
    _ok(ceilrun, ["replay", str(drive), "--rig", str(cal / "rig.yaml"), "--out",
                  str(tmp_path / "replay"), "--start-pose", "0,0.1,0"])
    dh, dy = replay_errors(drive, tmp_path / "replay" / "poses.csv")
    assert dh.size == dy.size == 20
    assert np.median(dh) <= 0.05 and np.median(dy) <= 0.005
