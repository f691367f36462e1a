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
* ``/tf``, ``/tf_static``, ``camera_info``, the overlay image and ``/clock``:
  :mod:`~ceilkit.runtime.io.ros2_views`.

Every name is a node parameter (:data:`PARAMETERS`: a params file, ``-p``, or
``ceilrun --ros2-param``).

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
its own stamps when they are wall-clock times, else (before 2001: a simulator's from
0, a camera recording's monotonic ones) from the wall clock at the first frame, every
spacing kept); incoming odometry stamps are mapped back.

Delivery: with ``wait_subscribers_s`` the node waits for a subscriber to the poses
before the first frame; on closing it waits up to ``flush_s`` until every subscriber
has acknowledged every message (reliable QoS), so a replay to ROS loses nothing.

rclpy is imported only by :meth:`Ros2Node.open` (the ``ros2`` extra); nothing else in
ceilkit imports it. The node runs in its own rclpy context with a background executor
thread. Use ``ROS_LOCALHOST_ONLY=1`` and ``ROS_DOMAIN_ID`` as usual.

Example::

    with Ros2Node(Ros2Config()) as node:       # a sink of the pipeline
        node.send(est, False, capture_ns)
"""

from __future__ import annotations

import dataclasses
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
from ceilkit.runtime.io.ros2_views import Ros2Views, fill

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
        odom_frame_id, camera_frame_id: the odometry's frame and the camera's (an
            optical frame: x right, y down, z forward).
        tf: ``auto`` (``map → base_link``; ``map → odom`` once odometry comes in),
            ``map_base`` (always ``map → base_link``) or ``off``.
        camera_info_topic, image_topic: the camera model and the overlay (JPEG), the
            latter at most ``image_rate_hz`` (0: off) and of ``image_quality`` (1-100).
        publish_clock: publish the frames' stamps on ``/clock`` (``use_sim_time``).
        transient_local: the poses keep their last ``qos_depth`` messages for late
            subscribers that ask for them (``/tf_static`` and ``camera_info`` always do).
        flush_s: on closing, wait up to this long until every subscriber has
            acknowledged every message (reliable delivery of a replay's last poses).
        ros_args: rclpy's own arguments (``--ros-args --params-file F -r __ns:=/x``); node
            parameters (:data:`PARAMETERS`) override the fields above.
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
    odom_frame_id: str = msgs.ODOM_FRAME
    camera_frame_id: str = msgs.CAMERA_FRAME
    tf: str = "auto"
    camera_info_topic: str = "/ceilkit/camera_info"
    image_topic: str = "/ceilkit/overlay/compressed"
    image_rate_hz: float = 2.0
    image_quality: int = 80
    publish_clock: bool = False
    transient_local: bool = True
    flush_s: float = 5.0
    ros_args: tuple[str, ...] = ()


TF_MODES = ("auto", "map_base", "off")
PARAMETERS = ("frame_id", "child_frame_id", "odom_frame_id", "camera_frame_id", "tf",
              "pose_topic", "odom_topic", "diagnostics_topic", "initialpose_topic",
              "odometry_topic", "camera_info_topic", "image_topic", "image_rate_hz",
              "image_quality", "publish_clock", "transient_local", "qos_depth",
              "max_velocity_dt_s", "diagnostics_period_s", "wait_subscribers_s", "flush_s")
"""The node's parameters (``ros2 param``, a ``--params-file``, ``--ros2-param``): the
:class:`Ros2Config` fields of the same names; ``odometry_topic`` ``""`` is off."""


def ros2_config(base: Ros2Config | None = None, values: dict[str, Any] | None = None,
                where: str = "--ros2-param") -> Ros2Config:
    """``base`` with ``values`` (parameter name -> value, strings parsed as the field's
    type), checked.

    Raises:
        ConfigError: an unknown name or a value out of range, keyed ``where NAME``.
    """
    cfg = base or Ros2Config()
    out: dict[str, Any] = {}
    for name, value in (values or {}).items():
        if name not in PARAMETERS:
            raise ConfigError(None, where, f"unknown parameter {name!r}; expected one of "
                              f"{', '.join(PARAMETERS)}")
        out[name] = _parameter_value(name, getattr(cfg, name), value, where)
    return _checked(dataclasses.replace(cfg, **out), where)


def _parameter_value(name: str, default: Any, value: Any, where: str) -> Any:
    key = f"{where} {name}"
    try:
        if isinstance(default, bool):
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                return value.lower() in ("true", "1")
            return bool(value)
        if isinstance(default, int):
            return int(value)
        if isinstance(default, float):
            return float(value)
    except (TypeError, ValueError):
        raise ConfigError(None, key, f"expected a {type(default).__name__}, found "
                          f"{value!r}") from None
    if name == "tf" and isinstance(value, bool):   # YAML 1.1 (ROS's -p, params files): off
        return "auto" if value else "off"
    text = "" if value is None else str(value)
    return (text or None) if name == "odometry_topic" else text


def _checked(cfg: Ros2Config, where: str) -> Ros2Config:
    def bad(name: str, expected: str) -> ConfigError:
        return ConfigError(None, f"{where} {name}", f"expected {expected}, found "
                           f"{getattr(cfg, name)!r}")
    if cfg.tf not in TF_MODES:
        raise bad("tf", " or ".join(TF_MODES))
    for name in ("frame_id", "child_frame_id", "odom_frame_id", "camera_frame_id"):
        if not getattr(cfg, name) or getattr(cfg, name).startswith("/"):
            raise bad(name, "a frame id (not empty, no leading /)")
    for name in ("image_rate_hz", "max_velocity_dt_s", "diagnostics_period_s",
                 "wait_subscribers_s", "flush_s"):
        if not 0.0 <= getattr(cfg, name) < 1e6:
            raise bad(name, "a number of at least 0")
    if not 1 <= cfg.image_quality <= 100:
        raise bad("image_quality", "1 to 100")
    if not 1 <= cfg.qos_depth <= 100_000:
        raise bad("qos_depth", "1 to 100000")
    return cfg


def declare_parameters(node: Any, cfg: Ros2Config) -> Ros2Config:
    """Declare :data:`PARAMETERS` on ``node`` with ``cfg``'s values as defaults; the
    config with the values the node was given (a params file, ``-p``) instead."""
    from rcl_interfaces.msg import ParameterDescriptor

    values = {}
    for name in PARAMETERS:
        default = getattr(cfg, name)
        default = "" if default is None else default
        p = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True))
        values[name] = p.value
    return ros2_config(cfg, values, where="ROS parameter")


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


class Ros2Node:
    """See the module docstring. Counters: ``poses``, ``odometry_out``,
    ``diagnostics``, ``initial_poses`` (received), ``odometry_in`` (rows handed on).

    Args:
        config: names and topics.
        clock_offset_ns: added to estimate stamps (ns) to give ROS stamps; ``None``:
            0, unless the first frame's stamp is not a wall-clock time (below
            :data:`~ceilkit.runtime.io.ros2_msgs.WALL_CLOCK_MIN_NS`: a simulator's or a
            camera's monotonic clock), when the first frame is placed at the wall clock
            of its publication and the rest keep their spacing.
        rig: the camera model and mount (``camera_info``, ``/tf_static``, the overlay).
        draw: ``draw(image, estimate) -> BGR image``: the overlay (``None``: no image).
    """

    def __init__(self, config: Ros2Config | None = None, clock_offset_ns: int | None = 0,
                 rig: Any = None, draw: Callable[[np.ndarray, Estimate], np.ndarray]
                 | None = None):
        self.config = config or Ros2Config()
        self.clock_offset_ns = None if clock_offset_ns is None else int(clock_offset_ns)
        self.rig, self._draw = rig, draw
        self.views: Ros2Views | None = None
        self.tap: Any = None
        """An :class:`~ceilkit.runtime.viz.tap.EstimateTap` of the pipeline's estimator
        (:func:`~ceilkit.runtime.pipeline.build_pipeline` sets it): its ``latest``
        frame is what the overlay draws."""
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
        self._told_unfused = False
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

        cfg = self.config
        try:
            self._context = rclpy.Context()
            rclpy.init(args=["ceilkit", *cfg.ros_args], context=self._context)
            self._node = rclpy.create_node(cfg.node_name, namespace=cfg.namespace or None,
                                           context=self._context)
            self.config = cfg = declare_parameters(self._node, cfg)
            self._fqn = self._node.get_fully_qualified_name()   # after -r __ns:=, __node:=
            qos, latched = _qos(cfg)
            t = self._types
            self._pub_pose = self._node.create_publisher(
                t["pose"], cfg.pose_topic, latched if cfg.transient_local else qos)
            self._pub_odom = self._node.create_publisher(t["odom"], cfg.odom_topic, qos)
            self._pub_diag = self._node.create_publisher(t["diag"], cfg.diagnostics_topic,
                                                         qos)
            self._node.create_subscription(t["pose"], cfg.initialpose_topic,
                                           self._on_initial_pose, qos)
            if cfg.odometry_topic:
                self._node.create_subscription(t["odom"], cfg.odometry_topic,
                                               self._on_odometry, qos)
            self.views = Ros2Views(self._node, cfg, self.rig, self._draw, qos, latched)
            self._executor = SingleThreadedExecutor(context=self._context)
            self._executor.add_node(self._node)
        except ConfigError:
            self._shutdown()
            raise
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

    def flush(self) -> bool:
        """Wait (at most ``flush_s`` in all) until every subscriber has acknowledged
        every message; whether all did."""
        if self._node is None or self.config.flush_s <= 0:
            return True
        from rclpy.duration import Duration

        end = time.monotonic() + self.config.flush_s
        pubs = [self._pub_pose, self._pub_odom, self._pub_diag]
        pubs += self.views.publishers if self.views is not None else []
        ok = True
        for pub in pubs:
            left = max(0.0, end - time.monotonic())
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        return ok

    def close(self) -> None:
        """Wait for the last messages' acknowledgements (:meth:`flush`), stop the
        executor thread, destroy the node, shut its context down."""
        if self._node is not None and self._thread is not None and not self.flush():
            log.warning("ROS 2: not every subscriber acknowledged the last messages "
                        "within %.1f s", self.config.flush_s)
        if self.views is not None:
            self.views.close()
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
        views = f", {self.views.describe()}" if self.views is not None else ""
        offset = ("" if not self.clock_offset_ns else
                  f"; ROS stamps = t_ns + {self.clock_offset_ns} ns")
        name = getattr(self, "_fqn", f"{c.namespace or ''}/{c.node_name}")
        return (f"ROS 2 node {name}: {self.poses} poses on "
                f"{c.pose_topic}, {self.odometry_out} odometry on {c.odom_topic}, "
                f"{self.diagnostics} diagnostics{views}, {self.initial_poses} initial "
                f"poses, {self.odometry_in} odometry rows in{offset}")

    def _stamp(self, t_ns: int) -> int:
        if self.clock_offset_ns is None:
            self.clock_offset_ns = (time.time_ns() - int(t_ns)
                                    if int(t_ns) < msgs.WALL_CLOCK_MIN_NS else 0)
        return int(t_ns) + self.clock_offset_ns

    # ------------------------------------------------------------------ the sink
    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        """Publish one frame's outcome, then hand on a start pose received meanwhile."""
        self.frames += 1
        stamp = self._stamp(est.t_ns)
        cfg = self.config
        if self.frames == 1 and self.views is not None:
            self.views.publish_static(stamp)
        if isinstance(est, PoseEstimate) and self._node is not None:
            self._pub_pose.publish(fill(self._types["pose"](),
                                         msgs.pose_msg(est, stamp, cfg.frame_id)))
            self.poses += 1
            if est.x_m is not None and est.y_m is not None:
                prev, self._last_full = self._last_full, est
                vel = velocity_between(prev, est, cfg.max_velocity_dt_s) if prev else None
                if vel is not None:
                    self._pub_odom.publish(fill(self._types["odom"](), msgs.odometry_msg(
                        est, vel[0], vel[1], stamp, cfg.frame_id, cfg.child_frame_id)))
                    self.odometry_out += 1
            else:
                self._last_full = None
        self._last = est
        if self.views is not None:
            self.views.frame(est, stamp, self.tap.latest if self.tap is not None else None)
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
        stamp = (int(self._last.t_ns) if self._last is not None else 0) + \
            (self.clock_offset_ns or 0)
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
        msg = fill(t["diag"](), {"header": values["header"]})
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

    def add_odometry(self, t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float) -> None:
        """A wheel odometry row fed to the fusion by another path (a recording's, the
        link's): integrated into ``odom`` for ``map → odom → base_link``."""
        if self.views is not None:
            self.views.odometry.add(t_ns, dx_m, dy_m, dyaw_rad)

    def _on_odometry(self, msg: Any) -> None:
        t_ns = msgs.join_stamp(msg.header.stamp) - (self.clock_offset_ns or 0)
        p = msg.pose.pose
        pose = (float(p.position.x), float(p.position.y), msgs.quaternion_yaw(p.orientation))
        if self.views is not None:
            self.views.odometry.set(t_ns, pose, external=True)
        inc = self._odo.add(t_ns, *pose)
        if inc is not None and self.on_odometry is None and not self._told_unfused:
            self._told_unfused = True
            log.warning("odometry on %s not fused: this run's method has no fusion "
                        "(--method auto with --start-pose runs it)",
                        self.config.odometry_topic)
        if inc is None or self.on_odometry is None:
            return
        self.on_odometry(inc.t_ns, inc.dx_m, inc.dy_m, inc.dyaw_rad)
        self.odometry_in += 1


def _qos(cfg: Ros2Config) -> tuple[Any, Any]:
    """The streams' QoS (reliable, volatile) and the latched one (transient-local)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=cfg.qos_depth, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=cfg.qos_depth, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return qos, latched


def _status(types: dict[str, Any], s: dict[str, Any]) -> Any:
    st = types["status"]()
    st.level = bytes([s["level"]])
    st.name, st.message, st.hardware_id = s["name"], s["message"], s["hardware_id"]
    st.values = [types["kv"](key=v["key"], value=v["value"]) for v in s["values"]]
    return st


__all__ = ["PARAMETERS", "Ros2Config", "Ros2Node", "declare_parameters", "ros2_config",
           "start_pose_of", "velocity_between"]
