"""Intrinsics from the ceiling (calib/selfcal.py): a few rendered frames under the
block site's 0.6 m tiles recover the lens; drives that do not determine it refuse."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ceilkit.calib import selfcal
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

POSES = [(2.3, 0.10, 0.2), (3.1, -0.25, 0.9), (4.0, 0.2, -0.5), (4.7, -0.1, 1.3),
         (5.2, 0.25, 2.2), (2.8, -0.2, -1.1), (3.6, 0.0, 0.4), (4.4, 0.15, -2.0)]


def _frames(rig: Rig, site: Site) -> list[np.ndarray]:
    opts = SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=1)
    return [selfcal.seam_points(render_frame(rig, site, x, y, a, opts,
                                             np.random.default_rng(k)), 500, seed=k)
            for k, (x, y, a) in enumerate(POSES)]


def _solve(rig: Rig, site: Site) -> selfcal.SelfCalResult:
    size = (rig.camera.width, rig.camera.height)
    return selfcal.calibrate_from_ceiling(_frames(rig, site), size, rig,
                                          selfcal.tile_grid(site, rig))


def test_focal_and_principal_point_from_tiles():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    res = _solve(rig, site)
    K = rig.camera.K
    assert abs(res.values["f"] / K[0, 0] - 1) < 0.005
    assert abs(res.values["cx"] - K[0, 2]) < 2.0 and abs(res.values["cy"] - K[1, 2]) < 2.0
    assert abs(res.values["k1"] - rig.camera.dist[0]) < 0.01
    assert any("board" in line for line in res.lines(rig.camera))


def test_lens_without_distortion_looking_up_refuses_principal_point():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    cam = rig.camera
    flat = CameraModel.pinhole(cam.width, cam.height, cam.K[0, 0], dist=np.zeros(5))
    rig = dataclasses.replace(rig, camera=flat)
    site = Site.load(CONFIGS / "block" / "site.yaml")
    with pytest.raises(CalibrationError, match=r"does not determine c[xy].*perspective"):
        _solve(rig, site)


def test_too_few_frames_and_no_grid_refuse():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    grid = selfcal.tile_grid(site, rig)
    with pytest.raises(CalibrationError, match="frames show the tile grid"):
        selfcal.calibrate_from_ceiling([np.zeros((10, 2))] * 8, (640, 480), rig, grid)
    lights = Site.load(CONFIGS / "lights" / "site.yaml")
    with pytest.raises(ConfigError, match="corridor"):
        selfcal.tile_grid(lights, rig)


def _recording(tmp_path, rig: Rig, name: str, n: int = len(POSES)):
    from ceilkit.calib.simulate import simulate_recording
    from ceilkit.runtime.sim.render import Trajectory

    site = Site.load(CONFIGS / "block" / "site.yaml")
    p = np.array(POSES[:n])
    traj = Trajectory(np.arange(len(p), dtype=np.int64) * 33_333_333, p[:, 0], p[:, 1],
                      p[:, 2])
    return simulate_recording(rig, site, traj, tmp_path / name,
                              SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=1))


def test_from_a_recording_writes_camera_or_nothing(tmp_path):
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    out = tmp_path / "camera.yaml"
    run = selfcal.intrinsics_from_ceiling(_recording(tmp_path, rig, "drive"), out,
                                          compare=CONFIGS / "block" / "camera.yaml")
    assert out.exists() and "from the ceiling" in out.read_text()
    assert any("board" in line for line in run.lines())
    flat = CameraModel.pinhole(640, 480, 450.0, dist=np.zeros(5))
    rec = _recording(tmp_path, dataclasses.replace(rig, camera=flat), "flat", 4)
    with pytest.raises(CalibrationError, match="add perspective variety"):
        selfcal.intrinsics_from_ceiling(rec, tmp_path / "flat.yaml")
    assert not (tmp_path / "flat.yaml").exists()
