"""The ROS 2 node, checked by a real rclpy node in ANOTHER process: one
PoseWithCovarianceStamped per estimated frame of a replay (frame map, stamp = capture
time, the filter's covariance with an unobserved x large and never zero), Odometry and
DiagnosticArray; and an /initialpose from that process changes the track.

DDS discovery is bounded: the publisher waits for its subscriber (at most 20 s), the
other process gives up after 30 s. ROS_LOCALHOST_ONLY=1 and a domain of its own."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ceilkit.runtime.io import ros2_msgs as msgs
from helpers import FIXTURES

pytest.importorskip("rclpy", reason="the ros2 extra is not installed (pip install "
                    "'ceilkit[ros2]'; .ci/run installs it)")
pytest.importorskip("geometry_msgs.msg", reason="the ros2 extra is not installed")

from ceilkit.runtime.io.ros2 import Ros2Config  # noqa: E402
from ceilkit.runtime.replay import replay  # noqa: E402

REC = FIXTURES / "corridor_rec"
HEADING = {"assume_heading_deg": 0.0}   # the fixture corridor is symmetric: say its heading
START = (1.0, 0.244558, math.radians(8.262851))   # its truth's first y and heading; x 1

LISTENER = r"""
import json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from diagnostic_msgs.msg import DiagnosticArray

out, mode = sys.argv[1], sys.argv[2]
rclpy.init()
node = rclpy.create_node("ceilkit_test_listener")
qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
got = {"poses": [], "odom": [], "diag": []}
last = [time.monotonic()]
def stamp(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec
def on_pose(m):
    last[0] = time.monotonic()
    got["poses"].append({"t": stamp(m.header), "frame": m.header.frame_id,
                         "x": m.pose.pose.position.x, "y": m.pose.pose.position.y,
                         "cov": list(m.pose.covariance)})
def on_odom(m):
    got["odom"].append({"t": stamp(m.header), "frame": m.header.frame_id,
                        "child": m.child_frame_id, "vx": m.twist.twist.linear.x})
def on_diag(m):
    got["diag"].append([(s.level[0] if isinstance(s.level, bytes) else int(s.level),
                         s.name, s.message) for s in m.status])
node.create_subscription(PoseWithCovarianceStamped, "/ceilkit/pose", on_pose, qos)
node.create_subscription(Odometry, "/ceilkit/odom", on_odom, qos)
node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos)
pub = None
if mode == "initialpose":
    pub = node.create_publisher(PoseWithCovarianceStamped, "/initialpose", qos)
print("READY", flush=True)
end = time.monotonic() + 30.0
sent = False
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
    if pub is not None and not sent and pub.get_subscription_count() > 0 \
            and len(got["poses"]) >= 3:
        m = PoseWithCovarianceStamped()
        m.header.frame_id = "map"
        m.pose.pose.position.x = 7.0
        m.pose.pose.position.y = float(sys.argv[3])
        m.pose.pose.orientation.w = 1.0
        m.pose.covariance[0] = m.pose.covariance[7] = 0.01
        m.pose.covariance[35] = 0.001
        pub.publish(m)
        sent = True
        print("SENT", flush=True)
    if got["poses"] and time.monotonic() - last[0] > 2.0:
        break
json.dump(got, open(out, "w"))
node.destroy_node()
rclpy.shutdown()
"""


@pytest.fixture
def ros_env(monkeypatch):
    """ROS 2 on this host only, on a domain of this test run's own."""
    domain = str(100 + os.getpid() % 100)
    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    return dict(os.environ)


def listener(tmp_path: Path, env: dict, mode: str, *args: str) -> tuple[subprocess.Popen,
                                                                        Path]:
    out = tmp_path / f"{mode}.json"
    proc = subprocess.Popen([sys.executable, "-c", LISTENER, str(out), mode, *args],
                            env=env, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "READY"
    return proc, out


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_replay_publishes_one_pose_per_estimated_frame(tmp_path, ros_env):
    proc, out = listener(tmp_path, ros_env, "listen")
    try:
        res = replay(REC, tmp_path / "r", ros2=Ros2Config(wait_subscribers_s=20.0),
                     options=HEADING)
        proc.wait(timeout=40)
    finally:
        proc.kill()
    got = json.loads(out.read_text())
    est = [r for r in rows(res.poses_path) if r["y"] != ""]
    assert len(est) >= 5
    assert len(got["poses"]) == len(est)
    # the fixture's stamps start at 0 (a simulator's): ROS sees them from the wall clock
    # of the replay's first frame on, every spacing kept to the nanosecond
    offset = got["poses"][0]["t"] - int(est[0]["t_ns"])
    assert offset >= msgs.WALL_CLOCK_MIN_NS
    for msg, row in zip(got["poses"], est, strict=True):
        assert msg["frame"] == "map"
        assert msg["t"] == int(row["t_ns"]) + offset         # capture time, shifted
        assert msg["y"] == pytest.approx(float(row["y"]), abs=1e-6)
        cov = msg["cov"]
        assert min(cov[0], cov[7], cov[14], cov[21], cov[28], cov[35]) > 0
        if row["x"] == "" or row["sigma_x"] == "":
            assert cov[0] == msgs.UNOBSERVED_VAR             # unobserved x: large
        else:
            assert cov[0] ** 0.5 == pytest.approx(float(row["sigma_x"]), abs=1e-6)
        assert cov[7] ** 0.5 == pytest.approx(float(row["sigma_y"]), abs=1e-6)
    assert got["diag"] and all(s[0][1] == msgs.DIAG_NAME for s in got["diag"])
    for o in got["odom"]:
        assert o["frame"] == "map" and o["child"] == "base_link"
        assert o["t"] - offset in {int(r["t_ns"]) for r in est}


def test_initialpose_from_another_process_changes_the_track(tmp_path, ros_env):
    base = replay(REC, tmp_path / "base", method="auto", start_pose=START)
    before = [r for r in rows(base.poses_path) if r["y"] != ""]   # x: the start pose's,
    y0 = float(before[0]["y"])                                    # never published
    proc, out = listener(tmp_path, ros_env, "initialpose", repr(y0))
    sent = []

    def progress(done: int, total: int) -> None:
        if done == 3:   # hold the replay here until the other process has sent it
            line = proc.stdout.readline().strip()
            sent.append(line)
            time.sleep(0.5)   # delivery to the node's executor thread

    try:
        res = replay(REC, tmp_path / "r", method="auto", start_pose=START,
                     progress=progress, ros2=Ros2Config(wait_subscribers_s=20.0))
        proc.wait(timeout=40)
    finally:
        proc.kill()
    assert sent == ["SENT"]
    after = rows(res.poses_path)
    assert [r["x"] for r in after[:3]] == [r["x"] for r in rows(base.poses_path)[:3]]
    # without it the track stays at x 1 (then x is unobserved); with it, from frame 4
    # on the track starts again at x 7, the y of the message
    kept = [r["x"] for r in rows(base.poses_path)[3:]]
    assert all(x == "" or abs(float(x) - 1.0) < 1e-6 for x in kept)
    # (a corridor-only track's x is published only while its 1-sigma is within 0.1 m:
    # the start pose's 5 cm grows past it by the next frame's time, the velocity not
    # being known; so the fusion's own count says the pose was taken)
    moved = [float(r["x"]) for r in after[3:] if r["x"] != ""]
    assert all(abs(x - 7.0) < 1e-3 for x in moved)
    assert any("1 start poses" in line for line in res.fusion), res.fusion
    assert not any("1 start poses" in line for line in base.fusion), base.fusion
    # the message's y and heading agree with the frames: the track goes on through it
    assert abs(float(after[4]["y"]) - float(rows(base.poses_path)[4]["y"])) < 0.01
    got = json.loads(out.read_text())
    assert len(got["poses"]) == len([r for r in after if r["y"] != ""])
    assert all(o["frame"] == "map" and o["child"] == "base_link" for o in got["odom"])
