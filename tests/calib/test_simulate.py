"""simulate_recording: a SPEC recording with truth that Recording reads back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, SimSource, straight_drive


def test_simulate_recording_round_trip(tmp_path, corridor_rig, corridor_site):
    rig = Rig(corridor_rig.camera.scaled(96, 72), corridor_rig.mount)
    traj = straight_drive(5, fps=15.0, speed_mps=0.8, y_m=0.04, weave_m=0.05,
                          yaw_wobble_rad=math.radians(1.0))
    opts = SimOptions(noise_sigma=1.5)
    out = simulate_recording(rig, corridor_site, traj, tmp_path / "rec", opts, seed=7)
    assert out == tmp_path / "rec"
    rec = Recording(out)
    assert len(rec) == 5
    np.testing.assert_array_equal(rec.t_ns, traj.t_ns)
    assert rec.truth is not None
    np.testing.assert_array_equal(rec.truth.t_ns, traj.t_ns)
    np.testing.assert_allclose(rec.truth.x_m, traj.x_m, atol=1e-6)
    np.testing.assert_allclose(rec.truth.y_m, traj.y_m, atol=1e-6)
    np.testing.assert_allclose(rec.truth.yaw_rad, traj.yaw_rad, atol=1e-7)
    assert rec.rig.camera.size == (96, 72)
    assert rec.rig.mount.tilt_rad == pytest.approx(rig.mount.tilt_rad)
    assert rec.site.to_dict() == corridor_site.to_dict()
    src = SimSource(rig, corridor_site, traj, opts, seed=7)
    for k, frame in enumerate(rec):
        assert frame.image.dtype == np.uint8 and frame.image.shape == (72, 96)
        np.testing.assert_array_equal(frame.image, src.render(k).image)
    assert "seed 7" in (out / "rig.yaml").read_text()


def test_simulate_recording_refuses_an_existing_recording(tmp_path, corridor_rig,
                                                          corridor_site):
    rig = Rig(corridor_rig.camera.scaled(64, 48), corridor_rig.mount)
    traj = straight_drive(2)
    simulate_recording(rig, corridor_site, traj, tmp_path / "rec")
    with pytest.raises(ConfigError, match="already"):
        simulate_recording(rig, corridor_site, traj, tmp_path / "rec")


def test_simulate_boards_charuco_views_are_detected(tmp_path):
    """ChArUco views through a chosen lens: every view is found by the detector that
    `ceilcal intrinsics` runs."""
    from ceilkit.calib.boards import parse_board
    from ceilkit.calib.intrinsics import detect_images, image_files
    from ceilkit.calib.simulate import simulate_boards
    from ceilkit.runtime.config.camera import load_camera
    from ceilkit.runtime.config.rig import Rig
    from helpers import CONFIGS

    cam = Rig.load(CONFIGS / "corridor" / "rig.yaml").camera.scaled(320, 240)
    board = parse_board("charuco:5x4", 0.04)
    out = simulate_boards(board, cam, 5, tmp_path / "b", seed=2, supersample=1)
    views = detect_images(image_files(out), board)
    assert len(views) == 5
    assert load_camera(out / "camera_truth.yaml").fx == cam.fx


def test_simulated_scatter_is_written_beside_the_recording(tmp_path):
    """A drive under a scatter (the office example's scene.yaml, found beside its site)
    writes every item into the recording's scene.yaml, which renders the same frames."""
    from ceilkit.calib import workflow
    from ceilkit.runtime.config.site import Site
    from ceilkit.runtime.sim.scatter_file import load_scene, scene_beside
    from helpers import CONFIGS

    office = CONFIGS / "office"
    full = Rig.load(office / "rig.yaml")
    rig = Rig(full.camera.scaled(96, 72), full.mount)
    rig.save(tmp_path / "rig.yaml")
    run = workflow.simulate(tmp_path / "rec", rig=tmp_path / "rig.yaml",
                            site=office / "site.yaml", frames=3, lateral_m=0.3, seed=2)
    assert "scene office preset, seed 1" in "\n".join(run.lines())
    site = Site.load(office / "site.yaml")
    back = load_scene(tmp_path / "rec" / "scene.yaml", site)
    assert back.items == scene_beside(site).items
    rec = Recording(tmp_path / "rec")
    src = SimSource(rig, site, run.trajectory, SimOptions(scatter=back), seed=2)
    for k, frame in enumerate(rec):
        np.testing.assert_array_equal(frame.image, src.render(k).image)
