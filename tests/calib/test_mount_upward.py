"""Upward (lights) rig mount calibration: pan, lever arm, height from a short rendered
drive under configs/lights, motion-capture poses with a time offset, refusals."""

import math

import numpy as np
import pytest

from ceilkit.calib import workflow
from ceilkit.calib.mount_upward import (
    StampedPoses,
    calibrate_mount_upward,
    load_pose_csv,
    observe,
    rotation,
    to_mount,
)
from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.geometry.rotations import R_vehicle_cam
from ceilkit.runtime.sim.render import SimOptions, render_frame, straight_drive
from helpers import CONFIGS

SITE = CONFIGS / "lights" / "site.yaml"
CAMERA = CONFIGS / "lights" / "camera.yaml"
TRUE = Mount(math.radians(4.0), math.pi / 2, 0.0, 0.22, -0.08, 0.55)
HZ = 1200            # the continuous drive's sampling


def _dense(seed: int = 0):
    return straight_drive(20 * HZ, fps=HZ, speed_mps=0.25, x0_m=0.5, weave_m=2.0,
                          weave_period_m=4.0, yaw_wobble_rad=math.radians(20),
                          rng=np.random.default_rng(seed))


@pytest.fixture(scope="module")
def drive():
    """12 frames over a 20 s weaving drive, rendered once."""
    site = Site.load(SITE)
    base = Rig.load(CONFIGS / "lights" / "rig.yaml")
    rig = base.with_mount(TRUE)
    dense = _dense()
    ks = np.arange(7, 20 * HZ, 20 * HZ // 12)[:12]
    frames = []
    for i, k in enumerate(ks):
        img = render_frame(rig, site, *dense.pose(int(k)), SimOptions(),
                           np.random.default_rng([0, i]))
        frames.append(observe(rig, img, int(dense.t_ns[k]), f"f{i}"))
    start = base.with_mount(Mount(0.0, math.pi / 2, 0.0, 0.0, 0.0, 0.5))
    return site, start, dense, ks, frames


def test_pan_lever_arm_height_from_a_short_drive(drive):
    site, start, dense, ks, frames = drive
    exact = StampedPoses(dense.t_ns[ks], dense.x_m[ks], dense.y_m[ks], dense.yaw_rad[ks])
    res = calibrate_mount_upward(start, site, frames, exact)
    m = res.mount
    errs = {"pan": math.degrees(res.heading_rad - TRUE.pan_rad), "mx": m.x_m - TRUE.x_m,
            "my": m.y_m - TRUE.y_m, "mz": m.z_m - TRUE.z_m}
    assert abs(errs["pan"]) < 0.1
    for k in ("mx", "my", "mz"):
        assert abs(errs[k]) < 0.005
        assert abs(errs[k]) < 3 * res.sigma[k]
    assert abs(math.radians(errs["pan"])) < 3 * res.sigma["pan"]
    assert res.offset_s is None
    assert m.tilt_rad == pytest.approx(math.pi / 2)     # lean not significant: level
    assert m.swing_rad == 0.0
    assert res.rms_px < 0.5


def test_mocap_poses_at_120_hz_with_a_7_ms_offset(drive):
    site, start, dense, ks, frames = drive
    exact = calibrate_mount_upward(
        start, site, frames,
        StampedPoses(dense.t_ns[ks], dense.x_m[ks], dense.y_m[ks], dense.yaw_rad[ks]))
    lag = round(0.007 * HZ)           # 7 ms ahead: mocap stamp = frame time + 7 ms
    js = np.arange(lag, 20 * HZ, HZ // 120)
    mocap = StampedPoses(dense.t_ns[js], dense.x_m[js - lag], dense.y_m[js - lag],
                      dense.yaw_rad[js - lag])
    assert not mocap.exact(dense.t_ns[ks])
    res = calibrate_mount_upward(start, site, frames, mocap)
    assert res.offset_s == pytest.approx(0.007, abs=0.001)
    for k, a, b in (("mx", res.mount.x_m, exact.mount.x_m),
                    ("my", res.mount.y_m, exact.mount.y_m),
                    ("mz", res.mount.z_m, exact.mount.z_m)):
        assert abs(a - b) < exact.sigma[k]
    assert abs(res.heading_rad - exact.heading_rad) < exact.sigma["pan"]
    assert any("pose time offset" in line for line in res.lines())


def test_pose_table_interpolates_heading_across_the_wrap():
    t = StampedPoses(np.array([0, 10], np.int64), np.array([0.0, 1.0]), np.array([0.0, 2.0]),
                  np.radians([179.0, -179.0]))
    p = t.at(np.array([5, 20]))
    assert p[0, :2] == pytest.approx([0.5, 1.0])
    assert math.degrees(p[0, 2]) % 360 == pytest.approx(180.0)
    assert np.isnan(p[1]).all()                          # no extrapolation


def test_to_mount_keeps_the_rotation_when_leaning():
    R = rotation(0.3, 0.02, -0.01)
    m = to_mount(0.3, 0.02, -0.01, 0.0, 0.0, 0.5, level=False)
    assert R_vehicle_cam(m.pan_rad, m.tilt_rad, m.swing_rad) == pytest.approx(R, abs=1e-12)
    assert m.tilt_rad < math.pi / 2


def test_too_few_frames_is_refused(drive):
    site, start, dense, ks, frames = drive
    exact = StampedPoses(dense.t_ns[ks], dense.x_m[ks], dense.y_m[ks], dense.yaw_rad[ks])
    with pytest.raises(CalibrationError, match="frames .*Nothing written"):
        calibrate_mount_upward(start, site, frames[:3], exact)


def test_pose_csv_errors_name_the_row(tmp_path):
    p = tmp_path / "mocap.csv"
    p.write_text("t_ns,x,y,yaw_deg\n0,0,0,0\n10,1,x,0\n")
    with pytest.raises(ConfigError, match="row 3"):
        load_pose_csv(p)


def test_ceilcal_mount_on_a_lights_site_takes_the_upward_procedure(tmp_path):
    """Through the workflow: a recording with truth.csv -> rig.yaml; a recording whose
    truth rows miss the frames -> refused, nothing written."""
    site = Site.load(SITE)
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml").with_mount(TRUE)
    dense = _dense(1)
    ks = np.arange(3, 20 * HZ, 20 * HZ // 8)[:8]
    from ceilkit.runtime.sim.render import Trajectory

    tr = Trajectory(dense.t_ns[ks], dense.x_m[ks], dense.y_m[ks], dense.yaw_rad[ks])
    rec = simulate_recording(rig, site, tr, tmp_path / "rec", SimOptions(), seed=4)
    out = tmp_path / "rig.yaml"
    run = workflow.mount(rec, SITE, out, camera=CAMERA)
    got = Rig.load(out).mount
    assert got.x_m == pytest.approx(TRUE.x_m, abs=0.005)
    assert got.z_m == pytest.approx(TRUE.z_m, abs=0.005)
    assert "upward lights rig" in out.read_text()
    assert any(line.startswith("pan") for line in run.lines())
    with pytest.raises(ConfigError, match="fix"):
        workflow.mount(rec, SITE, tmp_path / "r2.yaml", camera=CAMERA, fix=["mx=0.1"])
    far = tmp_path / "far.csv"
    far.write_text("t_ns,x,y,yaw_deg\n" + "".join(
        f"{10**12 + i * 10**7},0,0,0\n" for i in range(5)))
    with pytest.raises(CalibrationError, match="Nothing written"):
        workflow.mount(rec, SITE, tmp_path / "r3.yaml", camera=CAMERA, poses=far)
    assert not (tmp_path / "r3.yaml").exists()
