"""What the ROS 2 node shows RViz and Foxglove beside the poses: ``/tf``, ``/tf_static``,
``camera_info``, a compressed overlay image and ``/clock`` (see
:mod:`~ceilkit.runtime.io.ros2` for the node and its parameters).

* ``/tf_static``: ``base_link → camera`` from the rig's mount (SPEC §1: ``X_V = R_VC
  X_C + t``; the camera frame is an optical one), published once, transient-local, as
  ``robot_state_publisher`` does;
* ``/tf`` per pose with x and y (REP-105): ``map → base_link``; once odometry comes in
  (the ``odometry_topic``'s ``nav_msgs/Odometry`` or rows fed by :meth:`add_odometry`),
  ``map → odom`` (``T_map_base · T_odom_base⁻¹``, the odometry pose the latest at or
  before the frame) and, for rows ceilkit integrates itself, ``odom → base_link`` too
  (a ROS odometry source publishes that one). ``tf: map_base`` keeps ``map →
  base_link``, ``tf: off`` publishes none. A pose without x (the corridor method's)
  has no transform;
* ``camera_info`` (``sensor_msgs/CameraInfo``) from the rig's ``camera.yaml`` (already
  ROS's layout) with each image;
* the overlay (:func:`~ceilkit.runtime.viz.overlay.draw_overlay`, handed in as ``draw``:
  io does not import viz) as JPEG ``sensor_msgs/CompressedImage`` at most
  ``image_rate_hz``, drawn and encoded on a thread of its own so the frame loop never
  waits for it;
* ``/clock`` (``rosgraph_msgs/Clock``, with ``publish_clock``): the frames' stamps, for
  nodes run with ``use_sim_time`` during a replay.

``/tf`` needs the ``tf2_msgs`` package, which a ROS 2 installation has and the PyPI
wheels lack: without it the node says so once and publishes the rest.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.io import ros2_msgs as msgs

log = logging.getLogger("ceilkit.ros2")


def import_view_types() -> dict[str, Any]:
    """The message classes of the views; ``tf`` is ``None`` without ``tf2_msgs``."""
    from geometry_msgs.msg import TransformStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, CompressedImage
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        TFMessage = None  # noqa: N806 - a class, or None
    return {"tf": TFMessage, "transform": TransformStamped, "camera_info": CameraInfo,
            "image": CompressedImage, "clock": Clock}


class OdometryPose:
    """The vehicle's pose in ``odom`` over time: set from ``nav_msgs/Odometry`` poses
    (``external``: the odometry's node publishes ``odom → base_link``) or integrated
    from increments in V (rows in time order). Thread-safe; :meth:`at` gives the latest
    at or before a time (the first one before it). Keeps the last ``keep`` rows."""

    def __init__(self, keep: int = 100_000):
        self._lock = threading.Lock()
        self._t: list[int] = []
        self._poses: list[tuple[float, float, float]] = []
        self._keep = keep
        self.external = False

    def set(self, t_ns: int, pose: tuple[float, float, float], external: bool) -> None:
        with self._lock:
            self.external = self.external or external
            k = bisect.bisect_right(self._t, int(t_ns))
            self._t.insert(k, int(t_ns))
            self._poses.insert(k, pose)
            if len(self._t) > self._keep:
                del self._t[0], self._poses[0]

    def add(self, t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float) -> None:
        with self._lock:
            x, y, a = self._poses[-1] if self._poses else (0.0, 0.0, 0.0)
        c, s = math.cos(a), math.sin(a)
        self.set(t_ns, (x + c * dx_m - s * dy_m, y + s * dx_m + c * dy_m, a + dyaw_rad),
                 external=False)

    def at(self, t_ns: int) -> tuple[float, float, float] | None:
        with self._lock:
            if not self._t:
                return None
            k = bisect.bisect_right(self._t, int(t_ns))
            return self._poses[max(k - 1, 0)]


class Ros2Views:
    """The publishers of the module docstring on ``node`` (an rclpy node).

    Args:
        node, config: the node and its :class:`~ceilkit.runtime.io.ros2.Ros2Config`.
        rig: the camera and its mount (``None``: no ``/tf_static``, ``camera_info`` or
            image).
        draw: ``draw(image, estimate) -> BGR image``, the overlay.
        qos, latched: the QoS of the streams and of ``/tf_static`` (transient-local).
    """

    def __init__(self, node: Any, config: Any, rig: Any, draw: Callable | None,
                 qos: Any, latched: Any):
        self.types = import_view_types()
        self.config, self.rig, self._draw = config, rig, draw
        self.odometry = OdometryPose()
        self.tf = self.static = self.camera_infos = self.images = self.clocks = 0
        t, c = self.types, config
        self._pub_tf = self._pub_static = self._pub_info = self._pub_image = None
        if c.tf != "off" and t["tf"] is not None:
            self._pub_tf = node.create_publisher(t["tf"], "/tf", qos)
            self._pub_static = node.create_publisher(t["tf"], "/tf_static", latched)
        elif c.tf != "off":
            log.warning("no /tf: the tf2_msgs package is not installed (a ROS 2 "
                        "installation has it; the PyPI wheels do not)")
        if rig is not None:
            self._pub_info = node.create_publisher(t["camera_info"], c.camera_info_topic,
                                                   latched)
            if c.image_rate_hz > 0 and draw is not None:
                self._pub_image = node.create_publisher(t["image"], c.image_topic, qos)
        self._pub_clock = (node.create_publisher(t["clock"], "/clock", qos)
                           if c.publish_clock else None)
        self._slot: tuple[np.ndarray, Estimate, int] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._next_image_ns: int | None = None
        self._thread: threading.Thread | None = None
        if self._pub_image is not None:
            self._thread = threading.Thread(target=self._images, name="ceilkit-ros2-image",
                                            daemon=True)
            self._thread.start()

    @property
    def publishers(self) -> list[Any]:
        return [p for p in (self._pub_tf, self._pub_static, self._pub_info, self._pub_image,
                            self._pub_clock) if p is not None]

    def publish_static(self, stamp_ns: int) -> None:
        """``base_link → camera`` on ``/tf_static`` and the first ``camera_info``."""
        if self.rig is None:
            return
        c = self.config
        if self._pub_static is not None:
            m = self.rig.mount
            tr = msgs.camera_transform(m.R_vehicle_cam, m.t_vehicle_cam, stamp_ns,
                                       c.child_frame_id, c.camera_frame_id)
            self._pub_static.publish(self._tf_message([tr]))
            self.static += 1
        self._camera_info(stamp_ns)

    def _camera_info(self, stamp_ns: int) -> None:
        if self._pub_info is not None:
            self._pub_info.publish(fill(self.types["camera_info"](), msgs.camera_info_msg(
                self.rig.camera, stamp_ns, self.config.camera_frame_id)))
            self.camera_infos += 1

    def _tf_message(self, transforms: list[dict[str, Any]]) -> Any:
        out = self.types["tf"]()
        out.transforms = [fill(self.types["transform"](), t) for t in transforms]
        return out

    def frame(self, est: Estimate, stamp_ns: int,
              latest: tuple[np.ndarray, Estimate] | None) -> None:
        """One frame: its transforms, ``/clock``, and (rate-limited) its overlay from
        ``latest`` (the tap's image and raw estimate)."""
        c = self.config
        if self._pub_clock is not None:
            m = self.types["clock"]()
            fill(m, {"clock": msgs.split_stamp(stamp_ns)})
            self._pub_clock.publish(m)
            self.clocks += 1
        if self._pub_tf is not None and isinstance(est, PoseEstimate):
            odom = self.odometry.at(int(est.t_ns)) if c.tf == "auto" else None
            trs = msgs.pose_transforms(est, stamp_ns, c.frame_id, c.child_frame_id,
                                       c.odom_frame_id, odom,
                                       odom is not None and not self.odometry.external)
            if trs:
                self._pub_tf.publish(self._tf_message(trs))
                self.tf += 1
        if self._pub_image is not None and latest is not None:
            period = int(1e9 / c.image_rate_hz)
            if self._next_image_ns is None or stamp_ns >= self._next_image_ns:
                self._next_image_ns = stamp_ns + period
                self._slot = (latest[0], latest[1], stamp_ns)
                self._wake.set()

    def _images(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.2)
            self._wake.clear()
            slot, self._slot = self._slot, None
            if slot is None:
                continue
            try:
                image = self._draw(slot[0], slot[1])
                ok, buf = cv2.imencode(".jpg", image,
                                       [cv2.IMWRITE_JPEG_QUALITY, self.config.image_quality])
                if not ok:
                    continue
                self._camera_info(slot[2])
                self._pub_image.publish(fill(self.types["image"](), msgs.compressed_image_msg(
                    slot[2], buf.tobytes(), "jpeg", self.config.camera_frame_id)))
                self.images += 1
            except Exception as exc:  # noqa: BLE001 - a view must never stop the run
                if self._stop.is_set():
                    return
                log.warning("ROS 2 overlay image: %s", exc)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def describe(self) -> str:
        return (f"{self.tf} /tf, {self.static} /tf_static, {self.camera_infos} camera_info, "
                f"{self.images} overlay images" + (f", {self.clocks} /clock"
                                                    if self._pub_clock is not None else ""))


def fill(msg: Any, values: dict[str, Any]) -> Any:
    """Copy nested plain ``values`` (:mod:`ros2_msgs`) into an rclpy message."""
    for key, v in values.items():
        if isinstance(v, dict):
            fill(getattr(msg, key), v)
        else:
            setattr(msg, key, v)
    return msg


__all__ = ["OdometryPose", "Ros2Views", "fill", "import_view_types"]
