"""/tf, /tf_static and camera_info: the transforms' math (numeric, against SPEC §1), the
MCAP channels read by the mcap library's reader with a site point taken through them,
the node's parameters from the packaged parameter file through rclpy, and bad
parameters as one line each."""

from __future__ import annotations

import ast
import math

import numpy as np
import pytest
import yaml

from ceilkit.configs import ros2 as ros2_files
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.geometry.rotations import R_vehicle_cam
from ceilkit.runtime.io import ros2_msgs as msgs
from ceilkit.runtime.io.ros2 import PARAMETERS, Ros2Config, ros2_config
from ceilkit.runtime.io.ros2_views import OdometryPose
from helpers import CONFIGS, FIXTURES


def planar(t: dict) -> np.ndarray:
    """The (4, 4) matrix of a TransformStamped mapping."""
    out = np.eye(4)
    tr = t["transform"]
    out[:3, :3] = msgs.quaternion_matrix(tr["rotation"])
    out[:3, 3] = [tr["translation"][k] for k in "xyz"]
    return out


def pose(x: float | None, y: float, yaw: float) -> PoseEstimate:
    return PoseEstimate(7, "lights", x, y, yaw, 0.9)


def test_quaternion_round_trip_of_mounts():
    for pan, tilt, swing in ((0, 90, 0), (10, 45, -5), (-170, 30, 120), (0, 0, 0)):
        R = R_vehicle_cam(*np.radians((pan, tilt, swing)))
        q = msgs.rotation_quaternion(R)
        assert math.isclose(sum(v * v for v in q.values()), 1.0)
        np.testing.assert_allclose(msgs.quaternion_matrix(q), R, atol=1e-12)


def test_map_to_base_link_and_the_odom_chain_agree():
    est = pose(3.0, -1.5, math.radians(40))
    (direct,) = msgs.pose_transforms(est, 11)
    assert (direct["header"]["frame_id"], direct["child_frame_id"]) == ("map", "base_link")
    assert direct["header"]["stamp"] == {"sec": 0, "nanosec": 11}
    odom = (10.0, 2.0, math.radians(-75))   # wherever the wheel odometry has drifted to
    chain = msgs.pose_transforms(est, 11, odom_base=odom, with_odom_base=True)
    assert [(t["header"]["frame_id"], t["child_frame_id"]) for t in chain] == \
        [("map", "odom"), ("odom", "base_link")]
    np.testing.assert_allclose(planar(chain[0]) @ planar(chain[1]), planar(direct),
                               atol=1e-12)
    assert len(msgs.pose_transforms(est, 11, odom_base=odom)) == 1   # map -> odom only
    assert msgs.pose_transforms(pose(None, 0.2, 0.0), 11) == []        # no x: no transform


def test_camera_transform_and_camera_info_are_the_rigs():
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    tr = msgs.camera_transform(rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam)
    assert (tr["header"]["frame_id"], tr["child_frame_id"]) == \
        ("base_link", "camera_optical_frame")
    X_c = np.array([0.2, -0.1, 4.0])    # a point 4 m ahead of the lens
    np.testing.assert_allclose((planar(tr) @ [*X_c, 1])[:3],
                               rig.mount.R_vehicle_cam @ X_c + rig.mount.t_vehicle_cam)
    info = msgs.camera_info_msg(rig.camera, 5)
    assert info["distortion_model"] == rig.camera.model
    np.testing.assert_array_equal(np.reshape(info["k"], (3, 3)), rig.camera.K)
    assert len(info["p"]) == 12 and len(info["r"]) == 9
    assert (info["width"], info["height"]) == (rig.camera.width, rig.camera.height)


def test_odometry_pose_integrates_and_looks_up_by_time():
    odo = OdometryPose()
    assert odo.at(0) is None
    odo.add(100, 1.0, 0.0, math.pi / 2)
    odo.add(200, 1.0, 0.0, 0.0)
    assert odo.at(150) == (1.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(odo.at(10**9), (1.0, 1.0, math.pi / 2), atol=1e-12)
    assert odo.at(50) == (1.0, 0.0, math.pi / 2)    # before the first: the first
    assert not odo.external


def test_bad_parameters_are_one_line_naming_them():
    with pytest.raises(ConfigError, match=r"--ros2-param tf: expected auto or map_base "
                       r"or off, found 'maybe'"):
        ros2_config(values={"tf": "maybe"})
    with pytest.raises(ConfigError, match="unknown parameter 'frame'"):
        ros2_config(values={"frame": "map"})
    with pytest.raises(ConfigError, match="image_rate_hz: expected a float, found 'fast'"):
        ros2_config(values={"image_rate_hz": "fast"})
    with pytest.raises(ConfigError, match="camera_frame_id: expected a frame id"):
        ros2_config(values={"camera_frame_id": "/cam"})
    cfg = ros2_config(values={"odometry_topic": "", "publish_clock": "true",
                              "image_quality": "60"})
    assert cfg.odometry_topic is None and cfg.publish_clock and cfg.image_quality == 60


def test_packaged_parameter_file_names_every_parameter_with_its_default():
    doc = yaml.safe_load(ros2_files.PARAMS.read_text())
    params = doc["/**"]["ros__parameters"]
    assert set(params) == set(PARAMETERS)
    default = Ros2Config()
    for name, value in params.items():
        expected = getattr(default, name)
        assert value == ("" if expected is None else expected), name
    tree = ast.parse(ros2_files.LAUNCH.read_text())   # a valid launch file, ROS's API
    names = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in names
    assert "ceilkit-ros2" in ros2_files.LAUNCH.read_text()


def test_params_file_and_ros_args_set_the_nodes_parameters(monkeypatch):
    pytest.importorskip("rclpy", reason="the ros2 extra is not installed")
    pytest.importorskip("sensor_msgs.msg", reason="the ros2 extra is not installed")
    from ceilkit.runtime.io.ros2 import Ros2Node

    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    args = ("--ros-args", "--params-file", str(ros2_files.PARAMS), "-p", "tf:=map_base",
            "-p", "child_frame_id:=robot", "-p", "image_rate_hz:=0.5")
    with Ros2Node(Ros2Config(frame_id="world", ros_args=args)) as node:
        cfg = node.config
    assert (cfg.tf, cfg.child_frame_id, cfg.image_rate_hz) == ("map_base", "robot", 0.5)
    assert cfg.frame_id == "map"            # the file wins over the flag
    with pytest.raises(ConfigError, match="ROS parameter tf: expected auto"):
        Ros2Node(Ros2Config(ros_args=("--ros-args", "-p", "tf:=sideways"))).open()
    with Ros2Node(Ros2Config(ros_args=("--ros-args", "-p", "tf:=off"))) as node:
        assert node.config.tf == "off"      # YAML reads off as false: still off


def test_mcap_carries_tf_tf_static_and_camera_info_consistent_with_the_poses(tmp_path):
    pytest.importorskip("mcap_ros2", reason="the mcap extra is not installed")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from ceilkit.runtime.config.site import Site
    from ceilkit.runtime.io.mcap_rec import CHANNELS
    from ceilkit.runtime.session import SessionConfig, run_session
    from ceilkit.runtime.viz.overlay import world_to_px

    rec = tmp_path / "run.mcap"    # the fixture recording played as a camera, recorded
    src = FIXTURES / "lights_rec"
    run_session(SessionConfig(device=str(src), rig=src / "rig.yaml", site=src / "site.yaml",
                              record=rec))
    with open(rec, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name
                   for c in summary.channels.values()}
        got: dict[str, list] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append((message.log_time, decoded))
    for topic in ("/tf", "/tf_static", "/ceilkit/camera_info"):
        assert schemas[topic] == CHANNELS[topic]
    assert len(got["/tf_static"]) == 1 and len(got["/ceilkit/camera_info"]) == 6
    assert len(got["/tf"]) == len(got["/ceilkit/pose"]) >= 5
    rig, site = Rig.load(src / "rig.yaml"), Site.load(src / "site.yaml")
    (static,) = got["/tf_static"][0][1].transforms
    T_bc = planar(_plain(static))
    info = got["/ceilkit/camera_info"][0][1]
    K, D = np.reshape(info.k, (3, 3)), np.asarray(info.d)
    assert static.header.frame_id == "base_link"
    assert static.child_frame_id == info.header.frame_id == "camera_optical_frame"
    truth = {t: m for t, m in got["/ceilkit/truth"]}
    checked = 0
    for (t, tf), (_, p) in zip(got["/tf"], got["/ceilkit/pose"], strict=True):
        (tr,) = tf.transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("map", "base_link")
        assert msgs.join_stamp(tr.header.stamp) == msgs.join_stamp(p.header.stamp) == t
        T_mc = planar(_plain(tr)) @ T_bc                 # map -> camera, from /tf alone
        for X_w in site.lights_m[:: max(1, len(site.lights_m) // 6)]:
            X = np.linalg.solve(T_mc, [*X_w, site.ceiling_height_m, 1.0])[:3]
            if X[2] < 0.3:
                continue
            px = _fisheye(K, D, X)                        # ... and camera_info alone
            at_pose = world_to_px(rig, p.pose.pose.position.x, p.pose.pose.position.y,
                                  msgs.quaternion_yaw(p.pose.pose.orientation),
                                  np.array([[*X_w, site.ceiling_height_m]]))[0]
            np.testing.assert_allclose(px, at_pose, atol=1e-6)
            tp = truth[t].pose
            at_truth = world_to_px(rig, tp.position.x, tp.position.y,
                                   msgs.quaternion_yaw(tp.orientation),
                                   np.array([[*X_w, site.ceiling_height_m]]))[0]
            assert np.linalg.norm(px - at_truth) < 0.5    # the pose is right: < 0.5 px
            checked += 1
    assert checked >= 10


def _plain(tr) -> dict:
    """A decoded TransformStamped as the mapping :func:`planar` takes."""
    t, q = tr.transform.translation, tr.transform.rotation
    return {"transform": {"translation": {"x": t.x, "y": t.y, "z": t.z},
                          "rotation": {"x": q.x, "y": q.y, "z": q.z, "w": q.w}}}


def _fisheye(K: np.ndarray, D: np.ndarray, X: np.ndarray) -> np.ndarray:
    import cv2

    px, _ = cv2.fisheye.projectPoints(X.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    return px.reshape(2)


def test_ros2_never_changes_the_method_or_the_poses(tmp_path, monkeypatch):
    pytest.importorskip("rclpy", reason="the ros2 extra is not installed")
    pytest.importorskip("sensor_msgs.msg", reason="the ros2 extra is not installed")
    import csv

    from ceilkit.runtime.replay import replay

    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    src = FIXTURES / "lights_rec"
    plain = replay(src, tmp_path / "plain")
    ros = replay(src, tmp_path / "ros", ros2=Ros2Config(image_rate_hz=0.0, flush_s=0.0))
    assert plain.method == ros.method == "lights"      # before: "auto" with --ros2

    def rows(path):
        with open(path, newline="") as fh:
            return [{k: v for k, v in r.items() if k != "latency_ms"}
                    for r in csv.DictReader(fh)]
    assert rows(ros.poses_path) == rows(plain.poses_path)
    assert any(line.startswith("ROS 2 node /ceilkit: 6 poses") for line in ros.link)
