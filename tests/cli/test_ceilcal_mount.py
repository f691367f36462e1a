"""`ceilcal mount` on a simulated recording of five measured placements."""

import math

import numpy as np
from typer.testing import CliRunner

from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from helpers import CONFIGS


def test_mount_from_simulated_placements(tmp_path, corridor_rig, corridor_site):
    ys = [0.0, 0.3, -0.3, 0.1, -0.1]
    yaws = np.radians([0.0, 0.0, 0.0, 10.0, -12.0])
    traj = Trajectory(np.arange(5, dtype=np.int64) * 10**8,
                      np.array([0.5, 3.1, 5.3, 7.9, 10.2]), np.array(ys), yaws)
    simulate_recording(corridor_rig, corridor_site, traj, tmp_path / "pl", SimOptions(), seed=3)
    out = tmp_path / "rig.yaml"
    res = CliRunner().invoke(app, ["mount", str(tmp_path / "pl"), "--site",
                                   str(CONFIGS / "corridor" / "site.yaml"), "--camera",
                                   str(CONFIGS / "corridor" / "camera.yaml"), "--out",
                                   str(out)])
    assert res.exit_code == 0, res.output
    assert "residual RMS" in res.output
    got = Rig.load(out)
    truth = corridor_rig.mount
    # the targets: angles within 0.1 deg, lateral offset within 5 mm
    for name in ("tilt_rad", "swing_rad", "pan_rad"):
        assert abs(math.degrees(getattr(got.mount, name) - getattr(truth, name))) < 0.1
    assert abs(got.mount.y_m - truth.y_m) < 0.005
    assert out.read_text().startswith("# rig.yaml: the camera's mount fitted from placements")


def test_mount_bad_inputs(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["mount", str(tmp_path / "none"), "--site",
                              str(CONFIGS / "corridor" / "site.yaml")])
    assert res.exit_code == 1 and "--camera" in res.output
    (tmp_path / "pl.yaml").write_text("placements:\n  - {image: a.png, y: 0, yaw: 0, z: 1}\n")
    res = runner.invoke(app, ["mount", str(tmp_path / "pl.yaml"), "--site",
                              str(CONFIGS / "corridor" / "site.yaml"), "--camera",
                              str(CONFIGS / "corridor" / "camera.yaml")])
    assert res.exit_code == 1 and "placements[0].z: unknown key" in res.output
    assert not (tmp_path / "rig.yaml").exists()
