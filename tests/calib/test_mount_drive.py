"""Upward (lights) rig mount from a drive with no poses (calib/mount_drive.py, `ceilcal
mount` on a recording without truth.csv, with --fix my): pan, lean, x and height from
the wheels' no-sideways-motion; y held and recorded as such; refusals."""

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.mount_drive import calibrate_mount_drive
from ceilkit.calib.mount_spin import load_placed_frames
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory, straight_drive
from helpers import CONFIGS

SITE = CONFIGS / "lights" / "site.yaml"
TRUE = Mount(math.radians(4.0), math.pi / 2, 0.0, 0.22, -0.08, 0.55)
OPTS = SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=2)


def _drive(out, n, step, weave_m=1.0, seed=1):
    site = Site.load(SITE)
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml").with_mount(TRUE)
    d = straight_drive(n * step, fps=30, speed_mps=0.5, x0_m=1.0, weave_m=weave_m,
                       weave_period_m=4.0, rng=np.random.default_rng(seed))
    ks = np.arange(0, n * step, step)
    traj = Trajectory(d.t_ns[ks], d.x_m[ks], d.y_m[ks], d.yaw_rad[ks])
    out = simulate_recording(rig, site, traj, out, OPTS, seed=seed)
    (out / "truth.csv").unlink()                 # no poses: only the images
    return out


def _start():
    return Rig.load(CONFIGS / "lights" / "rig.yaml").with_mount(
        Mount(0.0, math.pi / 2, 0.0, 0.0, 0.0, 0.5))


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    return _drive(tmp_path_factory.mktemp("drive") / "rec", 40, 6)


def test_pan_x_and_height_from_a_weaving_drive_without_poses(drive):
    site = Site.load(SITE)
    frames, start = load_placed_frames(Recording(drive), _start(), site)
    res = calibrate_mount_drive(_start(), site, frames, start, TRUE.y_m)
    m = res.mount
    pan_err = m.pan_rad + m.swing_rad - TRUE.pan_rad
    assert abs(math.degrees(pan_err)) < 0.1 and abs(pan_err) < 3 * res.sigma["pan"]
    for k, a, b in (("mx", m.x_m, TRUE.x_m), ("mz", m.z_m, TRUE.z_m)):
        assert abs(a - b) < 0.005 and abs(a - b) < 3 * res.sigma[k], k
    assert m.y_m == TRUE.y_m


def test_cli_needs_my_and_records_it_as_held(drive, tmp_path):
    rig = tmp_path / "start.yaml"
    _start().save(rig, "# start rig\n")
    out = tmp_path / "rig.yaml"
    args = ["mount", str(drive), "--site", str(SITE), "--rig", str(rig), "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1 and "--fix my=VALUE" in res.output and not out.exists()
    res = CliRunner().invoke(app, args + ["--fix", "my=-0.08", "--fix", "pan=4"])
    assert res.exit_code == 1 and "only my" in res.output and not out.exists()
    res = CliRunner().invoke(app, args + ["--fix", "my=-0.08"])
    assert res.exit_code == 0, res.output
    got = Rig.load(out).mount
    assert got.x_m == pytest.approx(TRUE.x_m, abs=0.005)
    assert "held: my (--fix my, typed" in out.read_text()


def test_a_straight_drive_does_not_determine_x(tmp_path):
    site = Site.load(SITE)
    rec = _drive(tmp_path / "straight", 12, 6, weave_m=0.0, seed=2)
    frames, start = load_placed_frames(Recording(rec), _start(), site)
    with pytest.raises(CalibrationError, match="mx is not determined.*turns"):
        calibrate_mount_drive(_start(), site, frames, start, TRUE.y_m)
