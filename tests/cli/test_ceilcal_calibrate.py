"""A whole `ceilcal calibrate` on simulated data, then a replay on its rig: no rig value
is typed in (the camera comes from rendered boards, the mount from placements)."""

import math

import cv2
import numpy as np
from typer.testing import CliRunner

from ceilkit.calib.boards import parse_board, render_views
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.cli.ceilrun import app as ceilrun
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.sim.render import SimOptions, Trajectory, straight_drive
from helpers import CONFIGS, replay_errors


def test_calibrate_then_replay(tmp_path, corridor_rig, corridor_site):
    rng = np.random.default_rng(5)
    board = parse_board("chess:9x6", 0.04)
    boards = tmp_path / "boards"
    boards.mkdir()
    for k, (img, _, _) in enumerate(render_views(board, corridor_rig.camera, 14, rng)):
        cv2.imwrite(str(boards / f"b{k:02d}.png"), img)
    traj = Trajectory(np.arange(5, dtype=np.int64) * 10**8,
                      np.array([0.5, 3.1, 5.3, 7.9, 10.2]),
                      np.array([0.0, 0.3, -0.3, 0.1, -0.1]), np.radians([0, 0, 0, 10, -12]))
    simulate_recording(corridor_rig, corridor_site, traj, tmp_path / "pl", SimOptions(), seed=4)
    check = straight_drive(30, fps=10, speed_mps=0.8, y_m=0.1, weave_m=0.2,
                           yaw_wobble_rad=math.radians(5), rng=rng)
    simulate_recording(corridor_rig, corridor_site, check, tmp_path / "check", SimOptions(),
                       seed=6)
    args = ["calibrate", "--boards", str(boards), "--board", "chess:9x6", "--square", "0.04",
            "--placements", str(tmp_path / "pl"), "--site",
            str(CONFIGS / "corridor" / "site.yaml"), "--out", str(tmp_path / "cal"),
            "--check", str(tmp_path / "check")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "step 3/3" in res.output and "heading" in res.output
    rig = Rig.load(tmp_path / "cal" / "rig.yaml")
    assert abs(rig.camera.fx - corridor_rig.camera.fx) / corridor_rig.camera.fx < 0.002
    assert abs(math.degrees(rig.mount.tilt_rad - corridor_rig.mount.tilt_rad)) < 0.1
    # then `ceilrun replay` with the calibrated rig meets the foundation's targets
    # (the packaged corridor is symmetric about its centre line: the drive's start
    # singles its heading out)
    x0, y0, yaw0 = check.pose(0)
    res = CliRunner().invoke(ceilrun, ["replay", str(tmp_path / "check"), "--out",
                                       str(tmp_path / "replay"), "--rig",
                                       str(tmp_path / "cal" / "rig.yaml"), "--start-pose",
                                       f"{x0},{y0},{math.degrees(yaw0)}"])
    assert res.exit_code == 0, res.output
    dh, dy = replay_errors(tmp_path / "check", tmp_path / "replay" / "poses.csv")
    assert dh.size == dy.size == 30
    assert np.median(dh) <= 0.05 and np.percentile(dh, 95) <= 0.15
    assert np.median(dy) <= 0.005 and np.percentile(dy, 95) <= 0.015
    # resumable: a second run keeps both files
    res2 = CliRunner().invoke(app, args)
    assert res2.exit_code == 0 and "kept" in res2.output
