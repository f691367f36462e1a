"""`ceilcal intrinsics` through typer's CliRunner on rendered board images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.boards import ChessBoard, render_views
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.camera import load_camera
from ceilkit.runtime.geometry.camera import CameraModel

CAM = CameraModel(640, 480, np.array([[500.0, 0, 322.3], [0, 502.0, 236.8], [0, 0, 1]]),
                  [-0.25, 0.08, 0.001, -0.0008, 0.0], "plumb_bob")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("shots")
    for i, (img, _, _) in enumerate(render_views(ChessBoard(9, 6, 0.03), CAM, 12,
                                                 np.random.default_rng(7), noise_sigma=1.0)):
        cv2.imwrite(str(d / f"v{i:02d}.png"), img)
    return d


def test_writes_camera_with_provenance_and_plots(folder, tmp_path):
    out = tmp_path / "camera.yaml"
    r = CliRunner().invoke(app, ["intrinsics", str(folder), "--board", "chess:9x6",
                                 "--square", "0.03", "--out", str(out),
                                 "--plots", str(tmp_path / "plots")])
    assert r.exit_code == 0, r.output
    text = out.read_text()
    assert "# command:" in text and "RMS" in text and "1 sigma" in text
    cam = load_camera(out)
    assert abs(cam.fx / CAM.fx - 1) < 0.005
    assert (tmp_path / "plots" / "distortion.png").is_file()
    assert (tmp_path / ".camera.detections.npz").is_file()


@pytest.fixture(scope="module")
def few(folder, tmp_path_factory):
    """Five of the images: enough for the wrong-size errors (a failed search for a board
    costs 0.2-1.5 s per image)."""
    d = tmp_path_factory.mktemp("few")
    for f in sorted(folder.glob("*.png"))[:5]:
        (d / f.name).write_bytes(f.read_bytes())
    return d


def test_wrong_board_size_suggests_the_right_one(few, tmp_path):
    r = CliRunner().invoke(app, ["intrinsics", str(few), "--board", "chess:8x6",
                                 "--square", "0.03", "--out", str(tmp_path / "c.yaml")])
    assert r.exit_code == 1
    assert "error: --board: " in r.output and "did you mean chess:9x6?" in r.output


def test_size_matching_part_of_the_board_is_caught(few, tmp_path):
    """chess:7x4 is found inside the 9x6 board (by the sb detector) in some views: the
    corners beyond the detected grid give it away, and the neighbouring sizes are tried."""
    r = CliRunner().invoke(app, ["intrinsics", str(few), "--board", "chess:7x4",
                                 "--detector", "sb", "--square", "0.03", "--out",
                                 str(tmp_path / "c.yaml")])
    assert r.exit_code == 1
    assert "--board" in r.output and "matches only part of the board" in r.output
    assert "did you mean chess:9x6?" in r.output
    assert not (tmp_path / "c.yaml").exists()


def test_unwritable_output_writes_nothing(folder, tmp_path):
    out = tmp_path / "missing" / "camera.yaml"
    r = CliRunner().invoke(app, ["intrinsics", str(folder), "--board", "chess:9x6",
                                 "--square", "0.03", "--out", str(out)])
    assert r.exit_code == 1 and "cannot write" in r.output
    assert not out.parent.exists()


def test_needs_exactly_one_source(tmp_path):
    r = CliRunner().invoke(app, ["intrinsics", "--board", "chess:9x6", "--square", "0.03",
                                 "--out", str(tmp_path / "c.yaml")])
    assert r.exit_code == 1 and "exactly one image source" in r.output


def test_device_takes_ceilruns_camera_settings(tmp_path, monkeypatch):
    """--device opens the camera with the format, exposure and gain options ceilrun
    has; a capture file fills the exposure and gain not given."""
    from ceilkit.calib import workflow
    from ceilkit.runtime.config.capture import CaptureFile, save_capture
    from ceilkit.runtime.errors import CaptureError

    seen = []

    def fake_open(device, *args):
        seen.append((device, *args))
        raise CaptureError(f"{device}: fake camera")

    monkeypatch.setattr(workflow, "open_video", fake_open)
    save_capture(CaptureFile(exposure=120.0, gain=3.0), tmp_path / "capture.yaml")
    out = tmp_path / "camera.yaml"
    base = ["intrinsics", "--device", "/dev/video7", "--board", "chess:9x6", "--square",
            "0.03", "--out", str(out)]
    r = CliRunner().invoke(app, base + ["--width", "1280", "--height", "720", "--fps", "60",
                                        "--pixel-format", "MJPG", "--exposure", "50",
                                        "--gain", "2"])
    assert r.exit_code == 1 and "fake camera" in r.output
    assert seen[-1] == ("/dev/video7", 1280, 720, 60.0, "MJPG", 50.0, 2.0)
    r = CliRunner().invoke(app, base + ["--fourcc", "YUYV", "--capture",
                                        str(tmp_path / "capture.yaml"), "--gain", "1"])
    assert seen[-1] == ("/dev/video7", 0, 0, 0.0, "YUYV", 120.0, 1.0)
    assert not out.exists()
