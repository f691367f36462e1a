"""Observability first: each calibration refuses what its data cannot determine, and a
refusal writes nothing (issue 13's reproduced defects)."""

import csv
import math
import shutil

import cv2
import numpy as np
import pytest

from ceilkit.calib import workflow
from ceilkit.calib.boards import ChessBoard, look_at_pose, render_board
from ceilkit.calib.mount import Placement, calibrate_mount, placement_from_image
from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, Trajectory, render_frame, straight_drive
from helpers import CONFIGS

SITE = CONFIGS / "corridor" / "site.yaml"
CAMERA = CONFIGS / "corridor" / "camera.yaml"


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    """A 10-frame straight drive, one placement, five placements (rendered once)."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(SITE)
    base = tmp_path_factory.mktemp("corridor")
    simulate_recording(rig, site, straight_drive(10, 30.0, 1.0), base / "drive", SimOptions(),
                       seed=1)
    one = Trajectory(np.array([0], np.int64), np.array([1.0]), np.array([0.05]),
                     np.array([0.0]))
    simulate_recording(rig, site, one, base / "one", SimOptions(), seed=2)
    five = Trajectory(np.arange(5, dtype=np.int64) * 10**8,
                      np.array([0.5, 3.1, 5.3, 7.9, 10.2]),
                      np.array([0.0, 0.3, -0.3, 0.1, -0.1]),
                      np.radians([0.0, 0.0, 0.0, 10.0, -12.0]))
    simulate_recording(rig, site, five, base / "five", SimOptions(), seed=3)
    return rig, site, base


def test_an_unobserved_forward_offset_is_refused_not_written(corridor, tmp_path):
    """The issue's `mount --drive REC` plus one placement: x was written as 0.0 while
    the report said "not observable"; now it is refused unless typed with --fix."""
    _, _, base = corridor
    out = tmp_path / "rig.yaml"
    with pytest.raises(CalibrationError, match=r"mx is not observable.*--fix mx=VALUE"):
        workflow.mount(base / "one", SITE, out, camera=CAMERA, drive=base / "drive")
    assert not out.exists()
    run = workflow.mount(base / "one", SITE, out, camera=CAMERA, drive=base / "drive",
                         fix=["mx=0.30"])
    text = out.read_text()
    assert "held by --fix: mx = 0.3000 m (typed, not measured)" in text
    assert Rig.load(out).mount.x_m == pytest.approx(0.30)
    assert any("held: from the drive" in line for line in run.lines())


def test_fix_needs_a_value_without_a_rig_and_a_known_name(corridor, tmp_path):
    _, _, base = corridor
    with pytest.raises(ConfigError, match="no --rig: give the measured value, mx=VALUE"):
        workflow.mount(base / "one", SITE, tmp_path / "r.yaml", camera=CAMERA, fix=["mx"])
    with pytest.raises(ConfigError, match="unknown parameter 'q'"):
        workflow.mount(base / "one", SITE, tmp_path / "r.yaml", camera=CAMERA, fix=["q=1"])
    with pytest.raises(ConfigError, match="expected a number"):
        workflow.mount(base / "one", SITE, tmp_path / "r.yaml", camera=CAMERA,
                       fix=["mx=abc"])
    assert not list(tmp_path.iterdir())


def test_placements_shifted_together_are_refused(corridor, tmp_path):
    """Every measured y +1 m (the issue: RMS 0.968 px slipped under the 1 px refusal and
    wrote y = -0.945 m): refused, nothing written."""
    _, _, base = corridor
    rec = tmp_path / "shifted"
    shutil.copytree(base / "five", rec)
    rows = list(csv.reader(open(rec / "truth.csv")))
    with open(rec / "truth.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([rows[0]] + [[r[0], r[1], f"{float(r[2]) + 1.0:.6f}", r[3]]
                                              for r in rows[1:]])
    out = tmp_path / "rig.yaml"
    with pytest.raises(CalibrationError, match="disagree|chi-square"):
        workflow.mount(rec, SITE, out, camera=CAMERA)
    assert not out.exists()
    run = workflow.mount(base / "five", SITE, out, camera=CAMERA)   # the true ones: fine
    assert "chi-square" in "\n".join(run.lines())


def test_residuals_against_the_edge_noise_catch_a_small_common_shift():
    """Placements all 10 cm off: under 1 px RMS, but 4 times the edge points' scatter."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(SITE)
    places = [(0.0, 0.0), (0.3, 0.0), (-0.3, 0.0), (0.1, 10.0), (-0.1, -12.0)]
    pls = []
    for k, ((y, yaw), x) in enumerate(zip(places, (3.0, 11.0, 19.0, 27.0, 35.0),
                                          strict=True)):
        img = render_frame(rig, site, x, y, math.radians(yaw), SimOptions(),
                           np.random.default_rng([7, k]))
        pls.append(placement_from_image(rig.camera, img, y, math.radians(yaw), f"p{k}"))
    blank = rig.with_mount(Mount(z_m=0.5))
    good = calibrate_mount(blank, site, pls)
    assert good.chi2_per_dof < 2.0
    shifted = [Placement(p.segments_n, p.y_m + 0.1, p.yaw_rad, p.label, p.weights,
                         p.noise_px) for p in pls]
    with pytest.raises(CalibrationError, match="chi-square"):
        calibrate_mount(blank, site, shifted)


# -- intrinsics -------------------------------------------------------------------------
CAM = CameraModel(640, 480, np.array([[535.0, 0, 320.0], [0, 535.0, 240.0], [0, 0, 1]]),
                  [-0.2, 0.05, 0.0, 0.0, 0.0], "plumb_bob")
BOARD = ChessBoard(9, 6, 0.025)


def _write_views(folder, poses):
    folder.mkdir()
    for k, (tilt, tdir, off) in enumerate(poses):
        rvec, t = look_at_pose(BOARD, 0.45, tilt, tdir, 5.0 * k, off)
        img, _, _ = render_board(BOARD, CAM, rvec, t, np.random.default_rng(k))
        cv2.imwrite(str(folder / f"v{k:02d}.png"), img)


def test_copies_of_one_board_image_are_refused(tmp_path):
    """Eight copies of one image wrote fx 918 / fy 827 (truth 535): now refused."""
    _write_views(tmp_path / "one", [(30.0, 20.0, (0.0, 0.0))])
    for k in range(1, 8):
        shutil.copy(tmp_path / "one" / "v00.png", tmp_path / "one" / f"copy{k}.png")
    out = tmp_path / "camera.yaml"
    with pytest.raises(CalibrationError, match=r"only 1 distinct views among 8.*add views"):
        workflow.intrinsics(BOARD, out, folder=tmp_path / "one", cache=False)
    assert not out.exists()


def test_tilts_about_one_axis_only_are_refused(tmp_path):
    poses = [(t, 0.0, (dx, 0.0)) for t, dx in ((0.0, -0.05), (25.0, 0.05), (35.0, 0.0),
                                               (20.0, -0.03), (30.0, 0.04), (5.0, 0.0))]
    _write_views(tmp_path / "axis", poses)
    out = tmp_path / "camera.yaml"
    with pytest.raises(CalibrationError, match="tilt variety.*top and bottom"):
        workflow.intrinsics(BOARD, out, folder=tmp_path / "axis", cache=False)
    assert not out.exists()
    _write_views(tmp_path / "flat", [(2.0, 0.0, (dx, dy)) for dx in (-0.05, 0.05)
                                     for dy in (-0.03, 0.03)] + [(3.0, 90.0, (0.0, 0.0))])
    with pytest.raises(CalibrationError, match="too little tilt variety: 0 of 5"):
        workflow.intrinsics(BOARD, out, folder=tmp_path / "flat", cache=False)
    assert not out.exists()


# -- light map --------------------------------------------------------------------------
def test_lightmap_refuses_rectangular_lamps(corridor, tmp_path):
    """The corridor's 1.2 x 0.3 m lamps wrote three invented lights: now refused."""
    _, _, base = corridor
    out = tmp_path / "site.yaml"
    with pytest.raises(CalibrationError, match="not spot lights.*corridor method"):
        workflow.lightmap(base / "drive", out)
    assert not out.exists()
