"""The ROS 2 node: a pose sink and an odometry/start-pose source behind the protocols
the serial link uses (``send``, ``set_fault``; see :mod:`~ceilkit.runtime.pipeline`).

``ceilrun --ros2`` (or ``ceilkit-ros2``) opens a :class:`Ros2Node` beside the link. It
publishes, per frame of the pipeline (conventions of :mod:`~ceilkit.runtime.io.ros2_msgs`:
W is ``map``, V is ``base_link``):

* ``/ceilkit/pose`` (``geometry_msgs/PoseWithCovarianceStamped``): every published
  pose, stamped at the frame's capture time, with the filter's covariance (an
  unobserved x as a variance of 1e6 m², never zero); a frame with no pose publishes
  none (its reason goes to the diagnostics);
* ``/ceilkit/odom`` (``nav_msgs/Odometry``): the pose and the velocity in
  ``base_link``, when two consecutive poses with x and y are at most
  ``max_velocity_dt_s`` apart (the velocity is then known);
* ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``): the localizer's state (OK,
  WARN with the failure's reason, ERROR with a fault such as ``camera_lost``), on every
  change and at least every ``diagnostics_period_s``.

It subscribes to:

* ``/initialpose`` (``geometry_msgs/PoseWithCovarianceStamped``, RViz's "2D Pose
  Estimate"): a start pose, handed to ``on_initial_pose(t_ns, (x, y, yaw), cov3)`` on
  the pipeline's thread after the frame in hand (the fusion restarts its track there);
* an odometry topic (``nav_msgs/Odometry``, ``/odom`` by default): successive poses
  become increments in V, handed to ``on_odometry(t_ns, dx, dy, dyaw)`` (the fusion's
  :meth:`~ceilkit.runtime.fusion.Fusion.add_odometry`, safe from any thread).

Stamps: a message's stamp is the estimate's ``t_ns`` plus ``clock_offset_ns`` (the
session gives ``time_ns() - monotonic_ns()`` for a camera, whose frames are stamped on
the monotonic clock, so ROS sees wall-clock stamps; a replay or a simulator publishes
its own stamps, as ``ros2 bag play`` does); incoming odometry stamps are mapped back.

rclpy is imported only by :meth:`Ros2Node.open` (the ``ros2`` extra); nothing else in
ceilkit imports it. The node runs in its own rclpy context with a background executor
thread. Use ``ROS_LOCALHOST_ONLY=1`` and ``ROS_DOMAIN_ID`` as usual.

Example::

    with Ros2Node(Ros2Config()) as node:       # a sink of the pipeline
        node.send(est, False, capture_ns)
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceilkit.runtime.errors import ConfigError, LinkError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.io import ros2_msgs as msgs
from ceilkit.runtime.io.odometry_in import PoseDifferencer

log = logging.getLogger("ceilkit.ros2")

RVIZ_START_VAR = (0.25, 0.25, 0.06853891945200942)
"""Variances RViz's "2D Pose Estimate" sends (0.5 m, ~15°): used when a start pose
carries no usable covariance."""


@dataclass(frozen=True)
class Ros2Config:
    """The node's names and topics (``ceilrun --ros2 ...`` options).

    Attributes:
        node_name, namespace: the node.
        frame_id, child_frame_id: W and V in ROS (``map``, ``base_link``).
        pose_topic, odom_topic, diagnostics_topic: what is published.
        initialpose_topic: start poses (RViz's button).
        odometry_topic: wheel odometry in (``nav_msgs/Odometry``), or ``None``.
        qos_depth: history depth of every publisher and subscription (reliable).
        max_velocity_dt_s: the longest gap between two poses a velocity is taken over.
        diagnostics_period_s: the longest time between two diagnostics messages.
        wait_subscribers_s: on opening, wait up to this long for a subscriber to the
            poses (DDS discovery takes a moment: a replay would otherwise publish its
            first frames to no one); 0: do not wait.
    """

    node_name: str = "ceilkit"
    namespace: str = ""
    frame_id: str = msgs.MAP_FRAME
    child_frame_id: str = msgs.BASE_FRAME
    pose_topic: str = "/ceilkit/pose"
    odom_topic: str = "/ceilkit/odom"
    diagnostics_topic: str = "/diagnostics"
    initialpose_topic: str = "/initialpose"
    odometry_topic: str | None = "/odom"
    qos_depth: int = 100
    max_velocity_dt_s: float = 0.5
    diagnostics_period_s: float = 1.0
    wait_subscribers_s: float = 0.0


def velocity_between(a: PoseEstimate, b: PoseEstimate, max_dt_s: float
                     ) -> tuple[tuple[float, float, float], np.ndarray] | None:
    """The velocity from pose ``a`` to the later ``b`` in ``b``'s V: ``(vx, vy, yaw
    rate)`` (m/s, rad/s) and its (3, 3) covariance (the poses' variances summed over
    dt², ignoring their correlation: it bounds the error), or ``None`` when either
    lacks x or y or ``dt`` is not in ``(0, max_dt_s]``."""
    if None in (a.x_m, a.y_m, b.x_m, b.y_m):
        return None
    dt = (b.t_ns - a.t_ns) * 1e-9
    if not 0.0 < dt <= max_dt_s:
        return None
    vwx, vwy = (b.x_m - a.x_m) / dt, (b.y_m - a.y_m) / dt
    c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
    ca, cb = msgs.pose_cov3(a), msgs.pose_cov3(b)
    var_p = 0.5 * (ca[0, 0] + ca[1, 1] + cb[0, 0] + cb[1, 1]) / dt ** 2
    var_w = (ca[2, 2] + cb[2, 2]) / dt ** 2
    return ((c * vwx + s * vwy, -s * vwx + c * vwy, wrap_pi(b.yaw_rad - a.yaw_rad) / dt),
            np.diag([var_p, var_p, var_w]))


def start_pose_of(msg: Any, frame_id: str = msgs.MAP_FRAME
                  ) -> tuple[tuple[float, float, float], np.ndarray]:
    """``(x, y, yaw)`` and its (3, 3) covariance from a ``PoseWithCovarianceStamped``.

    Raises:
        LinkError: another frame than ``frame_id`` (an empty one is taken as it), or
            a value that is not finite.
    """
    fid = msg.header.frame_id.lstrip("/")
    if fid not in ("", frame_id):
        raise LinkError(f"initial pose in frame {msg.header.frame_id!r}, expected "
                        f"{frame_id!r}: ignored")
    p = msg.pose.pose
    pose = (float(p.position.x), float(p.position.y), msgs.quaternion_yaw(p.orientation))
    cov = msgs.cov3_of(list(msg.pose.covariance))
    if not (all(math.isfinite(v) for v in pose) and np.all(np.isfinite(cov))):
        raise LinkError("initial pose with values that are not finite: ignored")
    if np.any(np.diag(cov) <= 0) or np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) <= 0):
        cov = np.diag(RVIZ_START_VAR)
    return pose, cov


def _import_rclpy():
    try:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
    except ImportError as exc:
        raise ConfigError(None, "ros2", f"the ROS 2 node needs the ros2 extra (pip "
                          f"install 'ceilkit[ros2]'): {exc}") from None
    return rclpy, {"pose": PoseWithCovarianceStamped, "odom": Odometry,
                   "diag": DiagnosticArray, "status": DiagnosticStatus, "kv": KeyValue}


def _fill(msg: Any, values: dict[str, Any]) -> Any:
    """Copy nested plain ``values`` (:mod:`ros2_msgs`) into an rclpy message."""
    for key, v in values.items():
        if isinstance(v, dict):
            _fill(getattr(msg, key), v)
        else:
            setattr(msg, key, v)
    return msg


class Ros2Node:
    """See the module docstring. Counters: ``poses``, ``odometry_out``,
    ``diagnostics``, ``initial_poses`` (received), ``odometry_in`` (rows handed on).

    Args:
        config: names and topics.
        clock_offset_ns: added to estimate stamps (ns) to give ROS stamps.
    """

    def __init__(self, config: Ros2Config | None = None, clock_offset_ns: int = 0):
        self.config = config or Ros2Config()
        self.clock_offset_ns = int(clock_offset_ns)
        self.on_initial_pose: Callable[[int, tuple[float, float, float], np.ndarray],
                                       None] | None = None
        self.on_odometry: Callable[[int, float, float, float], None] | None = None
        self.poses = self.odometry_out = self.diagnostics = 0
        self.initial_poses = self.odometry_in = 0
        self.frames = 0
        self._fault: str | None = None
        self._last: Estimate | None = None
        self._last_full: PoseEstimate | None = None
        self._last_level: int | None = None
        self._last_diag_s = -math.inf
        self._pending_start: tuple[tuple[float, float, float], np.ndarray] | None = None
        self._lock = threading.Lock()
        self._odo = PoseDifferencer()
        self._rclpy: Any = None
        self._node: Any = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()

    # ------------------------------------------------------------------ life cycle
    def attach(self, tracker: Any) -> None:
        """Hand start poses and odometry to ``tracker`` when it takes them (the fusion
        and the tracker: ``set_start_pose``, thread-safe, taken at the next frame and
        published as a reset; the fusion: ``add_odometry``); otherwise they are logged
        as ignored."""
        if hasattr(tracker, "set_start_pose"):
            self.on_initial_pose = lambda t_ns, pose, cov: tracker.set_start_pose(
                t_ns, *pose, cov)
        if hasattr(tracker, "add_odometry"):
            self.on_odometry = tracker.add_odometry

    def open(self) -> Ros2Node:
        """Start the node (imports rclpy).

        Raises:
            ConfigError: the ``ros2`` extra is not installed.
            LinkError: rclpy cannot start (a bad name, no middleware).
        """
        rclpy, self._types = _import_rclpy()
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        cfg = self.config
        try:
            self._context = rclpy.Context()
            rclpy.init(context=self._context)
            self._node = rclpy.create_node(cfg.node_name, namespace=cfg.namespace or None,
                                           context=self._context)
            qos = QoSProfile(depth=cfg.qos_depth, reliability=ReliabilityPolicy.RELIABLE)
            t = self._types
            self._pub_pose = self._node.create_publisher(t["pose"], cfg.pose_topic, qos)
            self._pub_odom = self._node.create_publisher(t["odom"], cfg.odom_topic, qos)
            self._pub_diag = self._node.create_publisher(t["diag"], cfg.diagnostics_topic,
                                                         qos)
            self._node.create_subscription(t["pose"], cfg.initialpose_topic,
                                           self._on_initial_pose, qos)
            if cfg.odometry_topic:
                self._node.create_subscription(t["odom"], cfg.odometry_topic,
                                               self._on_odometry, qos)
            self._executor = SingleThreadedExecutor(context=self._context)
            self._executor.add_node(self._node)
        except Exception as exc:  # noqa: BLE001 - rclpy's own errors: one line
            self._shutdown()
            raise LinkError(f"ROS 2 node {cfg.node_name!r} cannot start: {exc}") from None
        self._rclpy = rclpy
        self._thread = threading.Thread(target=self._spin, name="ceilkit-ros2", daemon=True)
        self._thread.start()
        if cfg.wait_subscribers_s > 0 and not self.wait_for_subscribers(cfg.wait_subscribers_s):
            log.warning("no subscriber to %s after %.1f s: publishing anyway",
                        cfg.pose_topic, cfg.wait_subscribers_s)
        return self

    def wait_for_subscribers(self, timeout_s: float, count: int = 1) -> bool:
        """Wait (at most ``timeout_s``) until ``count`` subscribers match the poses'
        publisher; whether they did."""
        end = time.monotonic() + timeout_s
        while self._pub_pose.get_subscription_count() < count:
            if time.monotonic() >= end:
                return False
            time.sleep(0.02)
        return True

    def _spin(self) -> None:
        while not self._closing.is_set():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # noqa: BLE001 - shutting down, or a bad message
                if self._closing.is_set():
                    return
                log.warning("ROS 2 node: %s", exc)

    def _shutdown(self) -> None:
        ctx = getattr(self, "_context", None)
        if self._node is not None:
            try:
                self._node.destroy_node()
            except Exception:  # noqa: BLE001 - best effort at exit
                pass
            self._node = None
        if ctx is not None:
            try:
                ctx.try_shutdown()
            except Exception:  # noqa: BLE001
                pass

    def close(self) -> None:
        """Stop the executor thread, destroy the node, shut its context down."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if getattr(self, "_executor", None) is not None:
            try:
                self._executor.shutdown(timeout_sec=1.0)
            except Exception:  # noqa: BLE001
                pass
        self._shutdown()

    def __enter__(self) -> Ros2Node:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def describe(self) -> str:
        c = self.config
        return (f"ROS 2 node {c.namespace or ''}/{c.node_name}: {self.poses} poses on "
                f"{c.pose_topic}, {self.odometry_out} odometry on {c.odom_topic}, "
                f"{self.diagnostics} diagnostics, {self.initial_poses} initial poses, "
                f"{self.odometry_in} odometry rows in")

    # ------------------------------------------------------------------ the sink
    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        """Publish one frame's outcome, then hand on a start pose received meanwhile."""
        self.frames += 1
        stamp = int(est.t_ns) + self.clock_offset_ns
        cfg = self.config
        if isinstance(est, PoseEstimate) and self._node is not None:
            self._pub_pose.publish(_fill(self._types["pose"](),
                                         msgs.pose_msg(est, stamp, cfg.frame_id)))
            self.poses += 1
            if est.x_m is not None and est.y_m is not None:
                prev, self._last_full = self._last_full, est
                vel = velocity_between(prev, est, cfg.max_velocity_dt_s) if prev else None
                if vel is not None:
                    self._pub_odom.publish(_fill(self._types["odom"](), msgs.odometry_msg(
                        est, vel[0], vel[1], stamp, cfg.frame_id, cfg.child_frame_id)))
                    self.odometry_out += 1
            else:
                self._last_full = None
        self._last = est
        self._diagnose(stamp)
        with self._lock:
            start, self._pending_start = self._pending_start, None
        if start is not None:
            if self.on_initial_pose is None:
                log.warning("initial pose ignored: this run has no tracker to take it")
            else:
                self.on_initial_pose(int(est.t_ns), start[0], start[1])
                self._last_full = None

    def set_fault(self, reason: str | None) -> None:
        """The localizer is faulted (``camera_lost``, ...) or healthy again (``None``)."""
        self._fault = reason
        stamp = (int(self._last.t_ns) if self._last is not None else 0) + self.clock_offset_ns
        self._diagnose(stamp, force=True)

    def _diagnose(self, stamp_ns: int, force: bool = False) -> None:
        if self._node is None:
            return
        values = msgs.diagnostics_msg(stamp_ns, self._last, {
            "frames": self.frames, "poses": self.poses,
            "initial_poses": self.initial_poses, "odometry_rows_in": self.odometry_in},
            self._fault)
        level = values["status"][0]["level"]
        now = time.monotonic()
        if not force and level == self._last_level and \
                now - self._last_diag_s < self.config.diagnostics_period_s:
            return
        self._last_level, self._last_diag_s = level, now
        t = self._types
        msg = _fill(t["diag"](), {"header": values["header"]})
        msg.status = [_status(t, s) for s in values["status"]]
        self._pub_diag.publish(msg)
        self.diagnostics += 1

    # ------------------------------------------------------------------ the source
    def _on_initial_pose(self, msg: Any) -> None:
        try:
            start = start_pose_of(msg, self.config.frame_id)
        except LinkError as exc:
            log.warning("%s", exc)
            return
        with self._lock:
            self._pending_start = start
        self.initial_poses += 1
        x, y, yaw = start[0]
        log.warning("initial pose from %s: x %.3f m, y %.3f m, yaw %.2f deg",
                    self.config.initialpose_topic, x, y, math.degrees(yaw))

    def _on_odometry(self, msg: Any) -> None:
        t_ns = msgs.join_stamp(msg.header.stamp) - self.clock_offset_ns
        p = msg.pose.pose
        inc = self._odo.add(t_ns, float(p.position.x), float(p.position.y),
                            msgs.quaternion_yaw(p.orientation))
        if inc is None or self.on_odometry is None:
            return
        self.on_odometry(inc.t_ns, inc.dx_m, inc.dy_m, inc.dyaw_rad)
        self.odometry_in += 1


def _status(types: dict[str, Any], s: dict[str, Any]) -> Any:
    st = types["status"]()
    st.level = bytes([s["level"]])
    st.name, st.message, st.hardware_id = s["name"], s["message"], s["hardware_id"]
    st.values = [types["kv"](key=v["key"], value=v["value"]) for v in s["values"]]
    return st


__all__ = ["Ros2Config", "Ros2Node", "start_pose_of", "velocity_between"]
