"""Upward (lights) rig mount from a spin in place (calib/mount_spin.py, `ceilcal mount
--spin`): lean, lever arm and height with no poses, the pan held and recorded as such;
refused without a pan, off the spot, or over too small a turn."""

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.mount_spin import calibrate_mount_spin, load_placed_frames
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from helpers import CONFIGS

SITE = CONFIGS / "lights" / "site.yaml"
TRUE = Mount(math.radians(4.0), math.pi / 2, 0.0, 0.22, -0.08, 0.55)
OPTS = SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=2)


def _spin(out, n=12, turn=2 * math.pi, drift_m=0.0, seed=0):
    site = Site.load(SITE)
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml").with_mount(TRUE)
    yaw = np.linspace(0.0, turn, n, endpoint=False) + 0.3
    x = 5.0 + np.linspace(0.0, drift_m, n)
    traj = Trajectory((np.arange(n) * 10**8).astype(np.int64), x, np.full(n, 0.4), yaw)
    return simulate_recording(rig, site, traj, out, OPTS, seed=seed)


@pytest.fixture(scope="module")
def spin(tmp_path_factory):
    return _spin(tmp_path_factory.mktemp("spin") / "rec")


def _start():
    return Rig.load(CONFIGS / "lights" / "rig.yaml").with_mount(
        Mount(math.radians(4.0), math.pi / 2, 0.0, 0.0, 0.0, 0.5))


def test_lever_arm_and_height_from_a_spin(spin):
    site = Site.load(SITE)
    frames, start = load_placed_frames(Recording(spin), _start(), site)
    res = calibrate_mount_spin(_start(), site, frames, start, math.radians(4.0))
    m = res.mount
    for k, a, b in (("mx", m.x_m, TRUE.x_m), ("my", m.y_m, TRUE.y_m),
                    ("mz", m.z_m, TRUE.z_m)):
        assert abs(a - b) < 0.002, k
        assert abs(a - b) < 3 * res.sigma[k], k
    assert m.pan_rad == pytest.approx(math.radians(4.0))
    assert res.centre_m == pytest.approx((5.0, 0.4), abs=0.002)
    assert res.turn_deg > 300 and res.rms_px < 0.3


def test_cli_writes_the_rig_with_the_pan_recorded_as_held(spin, tmp_path):
    rig = tmp_path / "start.yaml"
    _start().save(rig, "# start rig\n")
    out = tmp_path / "rig.yaml"
    args = ["mount", str(spin), "--site", str(SITE), "--rig", str(rig), "--out", str(out),
            "--spin"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1 and "does not determine the pan" in res.output
    assert not out.exists()
    res = CliRunner().invoke(app, args + ["--fix", "pan=4.0"])
    assert res.exit_code == 0, res.output
    got = Rig.load(out).mount
    assert got.x_m == pytest.approx(TRUE.x_m, abs=0.002)
    assert got.z_m == pytest.approx(TRUE.z_m, abs=0.002)
    assert "held: pan (--fix pan, typed" in out.read_text()
    res = CliRunner().invoke(app, args + ["--fix", "pan=4.0", "--fix", "mx=0.2", "--force"])
    assert res.exit_code == 1 and "only the pan" in res.output


def test_refuses_a_spin_off_the_spot_and_a_small_turn(tmp_path):
    site = Site.load(SITE)
    moved = _spin(tmp_path / "moved", n=8, drift_m=0.3, seed=1)
    frames, start = load_placed_frames(Recording(moved), _start(), site)
    with pytest.raises(CalibrationError, match="did not turn in place"):
        calibrate_mount_spin(_start(), site, frames, start, math.radians(4.0))
    small = _spin(tmp_path / "small", n=6, turn=math.radians(60), seed=2)
    frames, start = load_placed_frames(Recording(small), _start(), site)
    with pytest.raises(CalibrationError, match="turn a full circle"):
        calibrate_mount_spin(_start(), site, frames, start, math.radians(4.0))
