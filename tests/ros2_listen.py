"""A ROS 2 subscriber in a process of its own, and a 100-frame recording to replay to
it: shared by tests/runtime/io/test_ros2_cli.py and benchmarks/bench_ros2_replay.py.

Run as a script (``python tests/ros2_listen.py OUT.json``), the listener subscribes to
what ``ceilrun replay --ros2`` publishes (poses, ``camera_info``, the overlay, ``/tf``
and ``/tf_static`` when ``tf2_msgs`` is installed), prints ``READY``, and spins until
a line arrives on its stdin (the parent's "the replay has ended"), or 600 s; then it
writes what it received as JSON to OUT.json.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

FIXTURES = Path(__file__).resolve().parent / "fixtures"
LISTENER = Path(__file__).resolve()
CLI = ("import sys; from ceilkit.cli.ceilrun import main; "
       "sys.argv = ['ceilrun', *sys.argv[1:]]; main()")


def pingpong_recording(out: Path, n: int = 100, src: Path = FIXTURES / "lights_rec") -> Path:
    """A SPEC recording of ``n`` frames at 10 Hz: ``src``'s frames forth and back
    (0..5, 4..0, 1..), symlinked, with the matching ``truth.csv`` rows."""
    out.mkdir(parents=True)
    (out / "frames").mkdir()
    for name in ("rig.yaml", "site.yaml"):
        (out / name).write_bytes((src / name).read_bytes())
    with open(src / "truth.csv", newline="") as fh:
        truth = list(csv.DictReader(fh))
    m = len(truth)
    order = [k % (2 * m - 2) for k in range(n)]
    order = [k if k < m else 2 * m - 2 - k for k in order]
    frames, rows = ["index,t_ns"], ["t_ns,x,y,yaw_deg"]
    for k, j in enumerate(order):
        t = k * 100_000_000
        os.symlink((src / "frames" / f"{j:06d}.png").resolve(), out / "frames" / f"{k:06d}.png")
        frames.append(f"{k},{t}")
        r = truth[j]
        rows.append(f"{t},{r['x']},{r['y']},{r['yaw_deg']}")
    (out / "frames.csv").write_text("\n".join(frames) + "\n")
    (out / "truth.csv").write_text("\n".join(rows) + "\n")
    return out


def ros_env(domain: int) -> dict[str, str]:
    """This environment with ROS 2 on this host only, on ``domain``."""
    env = dict(os.environ)
    env.update(ROS_LOCALHOST_ONLY="1", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(domain))
    return env


def replay_to_listener(rec: Path, out: Path, env: dict[str, str], *args: str
                       ) -> tuple[dict, subprocess.CompletedProcess, float]:
    """Start the listener, run ``ceilrun replay REC --out OUT --ros2 ARGS`` as a
    subprocess (as a user would), then stop the listener: what it received, the CLI's
    completed process and the CLI's wall time (s)."""
    got = out.with_suffix(".json")
    proc = subprocess.Popen([sys.executable, str(LISTENER), str(got)], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
        t0 = time.monotonic()
        cli = subprocess.run([sys.executable, "-c", CLI, "replay", str(rec), "--out", str(out),
                              "--ros2", *args], env=env, capture_output=True, text=True,
                             timeout=300)
        elapsed = time.monotonic() - t0
        try:
            proc.stdin.write("stop\n")
            proc.stdin.flush()
        except BrokenPipeError:   # it gave up waiting: what it wrote is all it got
            pass
        proc.wait(timeout=60)
    finally:
        proc.kill()
    return json.loads(got.read_text()), cli, elapsed


def _listen(out: str) -> None:
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, CompressedImage

    rclpy.init()
    node = rclpy.create_node("ceilkit_test_listener")
    qos = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got: dict[str, list] = {"poses": [], "camera_info": [], "images": [], "tf": [],
                            "tf_static": []}

    def stamp(h) -> int:
        return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec

    def on_pose(m) -> None:
        p = m.pose.pose
        got["poses"].append({"t": stamp(m.header), "frame": m.header.frame_id,
                             "x": p.position.x, "y": p.position.y,
                             "q": [p.orientation.x, p.orientation.y, p.orientation.z,
                                   p.orientation.w]})

    def on_info(m) -> None:
        got["camera_info"].append({"t": stamp(m.header), "frame": m.header.frame_id,
                                   "width": m.width, "height": m.height,
                                   "model": m.distortion_model, "d": list(m.d),
                                   "k": list(m.k), "p": list(m.p)})

    def on_image(m) -> None:
        got["images"].append({"t": stamp(m.header), "frame": m.header.frame_id,
                              "format": m.format, "data": bytes(m.data).hex()})

    def on_tf(key: str):
        def take(m) -> None:
            for t in m.transforms:
                r, q = t.transform.translation, t.transform.rotation
                got[key].append({"t": stamp(t.header), "parent": t.header.frame_id,
                                 "child": t.child_frame_id, "xyz": [r.x, r.y, r.z],
                                 "q": [q.x, q.y, q.z, q.w]})
        return take

    node.create_subscription(PoseWithCovarianceStamped, "/ceilkit/pose", on_pose, qos)
    node.create_subscription(CameraInfo, "/ceilkit/camera_info", on_info, latched)
    node.create_subscription(CompressedImage, "/ceilkit/overlay/compressed", on_image, qos)
    try:
        from tf2_msgs.msg import TFMessage
        node.create_subscription(TFMessage, "/tf", on_tf("tf"), qos)
        node.create_subscription(TFMessage, "/tf_static", on_tf("tf_static"), latched)
    except ImportError:
        pass
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    print("READY", flush=True)
    end = time.monotonic() + 600.0   # a first start compiles for minutes
    while not stop.is_set() and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    for _ in range(10):   # what is already in the middleware's queue
        rclpy.spin_once(node, timeout_sec=0.01)
    Path(out).write_text(json.dumps(got))
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    _listen(sys.argv[1])
