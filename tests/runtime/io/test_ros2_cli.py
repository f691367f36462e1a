"""``ceilrun replay --ros2`` as a user runs it (the CLI in a subprocess), to a real rclpy
subscriber in another process started first: every pose of a 100-frame replay arrives,
in order, with its stamp; ``camera_info`` is the rig's camera and a site point taken
through the received pose, the mount and ``camera_info`` lands where ceilkit's own
camera model puts it; the overlay arrives as JPEG. ``/tf`` and ``/tf_static`` are
checked the same way when ``tf2_msgs`` is installed (a ROS 2 installation; the PyPI
wheels have no ``tf2_msgs``: then the MCAP's /tf is, tests/runtime/io/test_ros2_views.py).

Five runs of five: ``benchmarks/bench_ros2_replay.py``. ROS_LOCALHOST_ONLY=1 and a
domain of its own."""

from __future__ import annotations

import csv
import math
import os

import cv2
import numpy as np
import pytest
from ros2_listen import pingpong_recording, replay_to_listener, ros_env

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.io import ros2_msgs as msgs

pytest.importorskip("rclpy", reason="the ros2 extra is not installed (pip install "
                    "'ceilkit[ros2]'; .ci/run installs it)")
pytest.importorskip("sensor_msgs.msg", reason="the ros2 extra is not installed")


def project_with_camera_info(info: dict, p_cam: np.ndarray) -> np.ndarray:
    """Pixels of camera-frame points through a received ``camera_info`` alone (OpenCV's
    models of ROS's distortion names)."""
    K = np.array(info["k"]).reshape(3, 3)
    D = np.array(info["d"], float)
    obj = p_cam.reshape(-1, 1, 3).astype(float)
    if info["model"] == "equidistant":
        px, _ = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), K, D)
    else:
        px, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, D)
    return px.reshape(-1, 2)


def site_point_in_camera(pose: tuple[float, float, float], R_vc: np.ndarray,
                         t_vc: np.ndarray, X_w: np.ndarray) -> np.ndarray:
    """``X_C`` of a point in W for a vehicle at ``pose``: ``X_V = Rz(yaw)ᵀ (X_W - (x, y,
    0))``, ``X_C = R_VCᵀ (X_V - t_VC)`` (SPEC §1)."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    X_v = Rz.T @ (X_w - np.array([x, y, 0.0]))
    return R_vc.T @ (X_v - t_vc)


def test_every_pose_of_a_100_frame_cli_replay_arrives_with_camera_info(tmp_path):
    rec = pingpong_recording(tmp_path / "rec", 100)
    got, cli, _ = replay_to_listener(rec, tmp_path / "out", ros_env(150 + os.getpid() % 50),
                                     "--ros2-param", "image_rate_hz=20")
    assert cli.returncode == 0, cli.stderr
    with open(tmp_path / "out" / "poses.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["y"] != ""]
    assert len(rows) >= 90                       # the lights method on the fixture frames
    assert len(got["poses"]) == len(rows)        # every pose, none lost
    offset = got["poses"][0]["t"] - int(rows[0]["t_ns"])
    assert offset >= msgs.WALL_CLOCK_MIN_NS     # not 1970: from the replay's wall clock
    for msg, row in zip(got["poses"], rows, strict=True):
        assert msg["frame"] == "map" and msg["t"] == int(row["t_ns"]) + offset
        assert msg["x"] == pytest.approx(float(row["x"]), abs=1e-6)
        assert msg["y"] == pytest.approx(float(row["y"]), abs=1e-6)
    assert "ROS 2 node /ceilkit: " in cli.stdout and f"{len(rows)} poses" in cli.stdout

    rig = Rig.load(rec / "rig.yaml")
    site = Site.load(rec / "site.yaml")
    info = got["camera_info"][-1]
    assert info["frame"] == "camera_optical_frame"
    assert (info["width"], info["height"]) == (rig.camera.width, rig.camera.height)
    assert info["model"] == rig.camera.model
    # a light of the site through the received pose, the mount and camera_info lands
    # where ceilkit's camera model puts it (the mount from /tf_static when it is there)
    R_vc, t_vc = rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam
    if got["tf_static"]:
        st = got["tf_static"][0]
        assert (st["parent"], st["child"]) == ("base_link", "camera_optical_frame")
        R_vc = msgs.quaternion_matrix(dict(zip("xyzw", st["q"], strict=True)))
        t_vc = np.array(st["xyz"])
    X_w = np.array([*site.lights_m[len(site.lights_m) // 2], site.ceiling_height_m])
    for msg in got["poses"][::17]:
        pose = (msg["x"], msg["y"], msgs.quaternion_yaw(dict(zip("xyzw", msg["q"], strict=True))))
        p_cam = site_point_in_camera(pose, R_vc, t_vc, X_w)
        if p_cam[2] <= 0:
            continue
        np.testing.assert_allclose(project_with_camera_info(info, p_cam)[0],
                                   rig.camera.project(p_cam.reshape(1, 3))[0], atol=1e-6)
    for tf in got["tf"]:   # map -> base_link at each pose's stamp (tf2_msgs installed)
        assert (tf["parent"], tf["child"]) == ("map", "base_link")
        assert tf["t"] in {m["t"] for m in got["poses"]}
    assert got["images"], "no overlay image"
    img = cv2.imdecode(np.frombuffer(bytes.fromhex(got["images"][0]["data"]), np.uint8),
                       cv2.IMREAD_COLOR)
    assert got["images"][0]["format"] == "jpeg"
    assert img.shape == (rig.camera.height, rig.camera.width, 3)
