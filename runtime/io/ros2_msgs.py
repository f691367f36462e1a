"""ROS 2 messages of ceilkit's outputs, as plain values (no ROS installation needed).

Pure functions from estimates to the fields of the standard ROS 2 messages, shared by
the ROS 2 node (:mod:`~ceilkit.runtime.io.ros2`, which copies them into rclpy
messages) and MCAP recordings (:mod:`~ceilkit.runtime.io.mcap_rec`, which serializes
them as CDR with the message definitions below, so ``ros2 bag`` and Foxglove read them).

Convention (REP-103/105 and SPEC §1): the site's W is ROS's ``map`` frame (ENU: x, y on
the floor, z up); the vehicle's V is ``base_link`` (x forward, y left, z up); a pose
is planar, so orientation is the quaternion of ``Rz(yaw)``. Covariances are 6x6
row-major over ``(x, y, z, rot_x, rot_y, rot_z)``: ``(x, y, yaw)`` from the filter,
an unobserved coordinate (the corridor method's x, an inf in ``PoseEstimate.cov``) as
:data:`UNOBSERVED_VAR` (never zero, never inf: ROS tools reject both), and z, roll,
pitch, which ceilkit does not estimate (a level floor), as :data:`PLANAR_VAR`.
Stamps are integer nanoseconds split into ``(sec, nanosec)``.

Example::

    msg = pose_msg(est, stamp_ns=est.t_ns)       # a PoseWithCovarianceStamped as dicts
    msg["pose"]["covariance"][0]                 # var(x), m^2
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, PoseEstimate

MAP_FRAME = "map"
"""ROS frame of the site's W (REP-105)."""
BASE_FRAME = "base_link"
"""ROS frame of the vehicle's V."""
ODOM_FRAME = "odom"
"""ROS frame of wheel odometry (continuous, drifting)."""
CAMERA_FRAME = "camera_optical_frame"
"""ROS frame of the camera: SPEC §1's C, OpenCV's axes (x right, y down, z along the
optical axis), which REP-103 calls an optical frame."""
WALL_CLOCK_MIN_NS = 1_000_000_000_000_000_000
"""Stamps below this (2001-09-09) are not wall-clock times: a simulator's (from 0) or a
camera's monotonic clock (since boot)."""
UNOBSERVED_VAR = 1.0e6
"""Variance (m², rad²) published for a coordinate the pose does not observe."""
PLANAR_VAR = 1.0e6
"""Variance of z, roll and pitch: not estimated by ceilkit (the vehicle is on the floor)."""
DEFAULT_VAR = (0.05 ** 2, 0.05 ** 2, math.radians(2.0) ** 2)
"""Variance of x, y, yaw for an estimate that carries no covariance (a method without
the fusion): the fusion's default 1σ of a fix."""
DIAG_NAME = "ceilkit: localizer"
"""``DiagnosticStatus.name`` of the localizer's state."""
OK, WARN, ERROR, STALE = 0, 1, 2, 3
"""``DiagnosticStatus.level`` values."""


PLANAR_AXES = (0, 1, 5)
"""(x, y, yaw) among ROS's (x, y, z, roll, pitch, yaw) covariance axes."""


def split_stamp(t_ns: int) -> dict[str, int]:
    """Integer ns to ``builtin_interfaces/Time`` fields (``sec`` may be negative)."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": int(sec), "nanosec": int(nsec)}


def join_stamp(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (an object with ``sec``/``nanosec`` or a mapping) to ns."""
    sec = stamp["sec"] if isinstance(stamp, Mapping) else stamp.sec
    nsec = stamp["nanosec"] if isinstance(stamp, Mapping) else stamp.nanosec
    return int(sec) * 1_000_000_000 + int(nsec)


def yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    """The quaternion of ``Rz(yaw)`` (x, y, z, w)."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw_rad), "w": math.cos(0.5 * yaw_rad)}


def quaternion_yaw(q: Any) -> float:
    """The yaw (rad) of a quaternion (object or mapping with x, y, z, w), about z."""
    get = (lambda k: float(q[k])) if isinstance(q, Mapping) else (lambda k: float(getattr(q, k)))
    x, y, z, w = get("x"), get("y"), get("z"), get("w")
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": split_stamp(stamp_ns), "frame_id": frame_id}


def pose_cov3(est: PoseEstimate) -> np.ndarray:
    """The (3, 3) covariance of ``(x, y, yaw)`` to publish: the estimate's, with an
    unobserved (inf, nan, or ``None`` coordinate) row/column as :data:`UNOBSERVED_VAR`
    on the diagonal and 0 off it; :data:`DEFAULT_VAR` without a covariance."""
    if est.cov is None:
        cov = np.diag(DEFAULT_VAR).astype(float)
    else:
        cov = np.array(est.cov, float).reshape(3, 3)
    observed = [est.x_m is not None, est.y_m is not None, True]
    for i in range(3):
        if not observed[i] or not np.all(np.isfinite(cov[i, :])) or \
                not np.isfinite(cov[i, i]) or cov[i, i] <= 0:
            cov[i, :] = 0.0
            cov[:, i] = 0.0
            cov[i, i] = UNOBSERVED_VAR
    return cov


def cov6(cov3: np.ndarray) -> list[float]:
    """A (3, 3) covariance of (x, y, yaw) as the 36 row-major values over
    (x, y, z, roll, pitch, yaw)."""
    c = np.zeros((6, 6))
    c[np.ix_(PLANAR_AXES, PLANAR_AXES)] = cov3
    c[2, 2] = c[3, 3] = c[4, 4] = PLANAR_VAR
    return [float(v) for v in c.ravel()]


def cov3_of(cov36: Sequence[float]) -> np.ndarray:
    """The (3, 3) block over (x, y, yaw) of 36 row-major values."""
    c = np.asarray(cov36, float).reshape(6, 6)
    return c[np.ix_(PLANAR_AXES, PLANAR_AXES)].copy()


def pose_with_cov(x_m: float, y_m: float, yaw_rad: float, cov3: np.ndarray) -> dict[str, Any]:
    return {"pose": {"position": {"x": float(x_m), "y": float(y_m), "z": 0.0},
                     "orientation": yaw_quaternion(yaw_rad)},
            "covariance": cov6(cov3)}


def pose_msg(est: PoseEstimate, stamp_ns: int | None = None,
             frame_id: str = MAP_FRAME) -> dict[str, Any]:
    """``geometry_msgs/PoseWithCovarianceStamped`` of a pose in W; an unobserved
    coordinate is 0 with :data:`UNOBSERVED_VAR`. ``stamp_ns`` defaults to ``est.t_ns``."""
    stamp = est.t_ns if stamp_ns is None else stamp_ns
    return {"header": header(stamp, frame_id),
            "pose": pose_with_cov(est.x_m if est.x_m is not None else 0.0,
                                  est.y_m if est.y_m is not None else 0.0,
                                  est.yaw_rad, pose_cov3(est))}


def odometry_msg(est: PoseEstimate, velocity: tuple[float, float, float],
                 velocity_cov: np.ndarray, stamp_ns: int | None = None,
                 frame_id: str = MAP_FRAME, child_frame_id: str = BASE_FRAME
                 ) -> dict[str, Any]:
    """``nav_msgs/Odometry``: the pose in ``frame_id`` and the twist ``velocity`` =
    ``(vx_mps, vy_mps, yaw_rate_rps)`` in ``child_frame_id`` (V), with its (3, 3)
    covariance."""
    stamp = est.t_ns if stamp_ns is None else stamp_ns
    vx, vy, wz = velocity
    return {"header": header(stamp, frame_id), "child_frame_id": child_frame_id,
            "pose": pose_with_cov(est.x_m if est.x_m is not None else 0.0,
                                  est.y_m if est.y_m is not None else 0.0,
                                  est.yaw_rad, pose_cov3(est)),
            "twist": {"twist": {"linear": {"x": float(vx), "y": float(vy), "z": 0.0},
                                "angular": {"x": 0.0, "y": 0.0, "z": float(wz)}},
                      "covariance": cov6(np.asarray(velocity_cov, float))}}


def wheel_odometry_msg(t_ns: int, x_m: float, y_m: float, yaw_rad: float,
                       frame_id: str = ODOM_FRAME, child_frame_id: str = BASE_FRAME
                       ) -> dict[str, Any]:
    """``nav_msgs/Odometry`` of integrated wheel odometry (pose only, variance unknown:
    :data:`UNOBSERVED_VAR`)."""
    return {"header": header(t_ns, frame_id), "child_frame_id": child_frame_id,
            "pose": pose_with_cov(x_m, y_m, yaw_rad, np.diag([UNOBSERVED_VAR] * 3)),
            "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0},
                                "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                      "covariance": [0.0] * 36}}


def pose_stamped_msg(t_ns: int, x_m: float, y_m: float, yaw_rad: float,
                     frame_id: str = MAP_FRAME) -> dict[str, Any]:
    """``geometry_msgs/PoseStamped`` (ground truth)."""
    return {"header": header(t_ns, frame_id),
            "pose": {"position": {"x": float(x_m), "y": float(y_m), "z": 0.0},
                     "orientation": yaw_quaternion(yaw_rad)}}


def _text(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def diagnostics_msg(stamp_ns: int, est: Estimate | None, counts: Mapping[str, Any],
                    fault: str | None = None, hardware_id: str = "ceilkit"
                    ) -> dict[str, Any]:
    """``diagnostic_msgs/DiagnosticArray`` with one status, :data:`DIAG_NAME`: ERROR with
    ``fault`` (camera lost, wrong frame size), WARN when the last frame gave no pose
    (the failure's reason), else OK; values: ``counts`` and the last estimate's method,
    quality or reason."""
    values = {k: _text(v) for k, v in counts.items()}
    if fault is not None:
        level, message = ERROR, f"fault: {fault}"
    elif est is None:
        level, message = STALE, "no frame yet"
    elif isinstance(est, PoseEstimate):
        level, message = OK, "localized"
        values.update(method=est.method, quality=_text(est.quality),
                      x_observed=str(est.x_m is not None).lower())
    else:
        level, message = WARN, f"no pose: {est.reason}"
        values.update(method=est.method, reason=est.reason)
    return {"header": header(stamp_ns, ""),
            "status": [{"level": level, "name": DIAG_NAME, "message": message,
                        "hardware_id": hardware_id,
                        "values": [{"key": k, "value": v} for k, v in values.items()]}]}


def _plain(v: Any, depth: int = 0) -> Any:
    """A JSON-able copy of diagnostics values (numbers, strings, short arrays)."""
    if isinstance(v, bool | int | str) or v is None:
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, np.generic):
        return _plain(v.item(), depth)
    if depth > 3:
        return None
    if isinstance(v, np.ndarray):
        return _plain(v.tolist(), depth + 1) if v.size <= 4096 else None
    if isinstance(v, Mapping):
        return {str(k): _plain(x, depth + 1) for k, x in v.items()}
    if isinstance(v, Sequence):
        return [_plain(x, depth + 1) for x in v]
    if isinstance(v, PoseEstimate):
        return {"method": v.method, "x": v.x_m, "y": v.y_m, "yaw_rad": v.yaw_rad,
                "quality": v.quality}
    if hasattr(v, "reason") and hasattr(v, "method"):
        return {"method": v.method, "reason": v.reason}
    return None


def detection_json(est: Estimate) -> str:
    """One frame's outcome as JSON (``std_msgs/String``): method, pose or reason, and
    the estimator's diagnostics (counts, residuals; what can be written as JSON)."""
    out: dict[str, Any] = {"t_ns": int(est.t_ns), "method": est.method}
    if isinstance(est, PoseEstimate):
        out.update(ok=True, x=est.x_m, y=est.y_m, yaw_rad=est.yaw_rad, quality=est.quality,
                   lateral=est.lateral_m)
    else:
        out.update(ok=False, reason=est.reason, detail=est.detail)
    out["diagnostics"] = _plain(dict(est.diagnostics))
    return json.dumps(out, separators=(",", ":"), allow_nan=False)


# ------------------------------------------------------------------ tf, camera, clock
def rotation_quaternion(R: np.ndarray) -> dict[str, float]:
    """The unit quaternion (x, y, z, w; w >= 0) of a (3, 3) rotation matrix."""
    R = np.asarray(R, float).reshape(3, 3)
    w = 0.5 * math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2]))
    x = 0.5 * math.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2]))
    y = 0.5 * math.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2]))
    z = 0.5 * math.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2]))
    x = math.copysign(x, R[2, 1] - R[1, 2])
    y = math.copysign(y, R[0, 2] - R[2, 0])
    z = math.copysign(z, R[1, 0] - R[0, 1])
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return {"x": x / n, "y": y / n, "z": z / n, "w": w / n}


def quaternion_matrix(q: Any) -> np.ndarray:
    """The (3, 3) rotation of a unit quaternion (object or mapping with x, y, z, w)."""
    get = (lambda k: float(q[k])) if isinstance(q, Mapping) else (lambda k: float(getattr(q, k)))
    x, y, z, w = get("x"), get("y"), get("z"), get("w")
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def transform_msg(stamp_ns: int, parent: str, child: str, t_xyz: Sequence[float],
                  rotation: Mapping[str, float]) -> dict[str, Any]:
    """``geometry_msgs/TransformStamped`` ``T_parent_child``: ``X_parent = R X_child + t``."""
    x, y, z = (float(v) for v in t_xyz)
    return {"header": header(stamp_ns, parent), "child_frame_id": child,
            "transform": {"translation": {"x": x, "y": y, "z": z},
                          "rotation": dict(rotation)}}


def planar_transform(stamp_ns: int, parent: str, child: str, x_m: float, y_m: float,
                     yaw_rad: float) -> dict[str, Any]:
    """A planar ``T_parent_child`` (on the floor: z 0, a rotation about z)."""
    return transform_msg(stamp_ns, parent, child, (x_m, y_m, 0.0), yaw_quaternion(yaw_rad))


def map_from_odom(map_base: tuple[float, float, float], odom_base: tuple[float, float, float]
                  ) -> tuple[float, float, float]:
    """``T_map_odom = T_map_base · T_odom_base⁻¹`` of planar poses ``(x, y, yaw)``: what a
    localizer publishes beside an odometry source's ``odom → base_link`` (REP-105)."""
    xm, ym, am = map_base
    xo, yo, ao = odom_base
    a = am - ao
    c, s = math.cos(a), math.sin(a)
    return xm - (c * xo - s * yo), ym - (s * xo + c * yo), math.atan2(math.sin(a), math.cos(a))


def tf_msg(transforms: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``tf2_msgs/TFMessage`` of ``transforms`` (``/tf`` and ``/tf_static``)."""
    return {"transforms": [dict(t) for t in transforms]}


def pose_transforms(est: PoseEstimate, stamp_ns: int, map_frame: str = MAP_FRAME,
                    base_frame: str = BASE_FRAME, odom_frame: str = ODOM_FRAME,
                    odom_base: tuple[float, float, float] | None = None,
                    with_odom_base: bool = False) -> list[dict[str, Any]]:
    """The ``/tf`` transforms of a pose: ``map → base_link``, or with ``odom_base`` (the
    odometry's pose of the vehicle in ``odom`` at the frame's time) ``map → odom``, and
    ``odom → base_link`` too when ``with_odom_base`` (no other node publishes it). A pose
    without x or y (the corridor method's) has no transform: ``[]``."""
    if est.x_m is None or est.y_m is None:
        return []
    pose = (float(est.x_m), float(est.y_m), float(est.yaw_rad))
    if odom_base is None:
        return [planar_transform(stamp_ns, map_frame, base_frame, *pose)]
    out = [planar_transform(stamp_ns, map_frame, odom_frame, *map_from_odom(pose, odom_base))]
    if with_odom_base:
        out.append(planar_transform(stamp_ns, odom_frame, base_frame, *odom_base))
    return out


def camera_transform(R_vehicle_cam: np.ndarray, t_vehicle_cam: Sequence[float],
                     stamp_ns: int = 0, base_frame: str = BASE_FRAME,
                     camera_frame: str = CAMERA_FRAME) -> dict[str, Any]:
    """``base_link → camera`` (``/tf_static``) of the rig's mount: ``X_V = R_VC X_C + t``
    (SPEC §1), the camera frame an optical one (x right, y down, z forward)."""
    return transform_msg(stamp_ns, base_frame, camera_frame, t_vehicle_cam,
                         rotation_quaternion(R_vehicle_cam))


def camera_info_msg(camera: Any, stamp_ns: int, frame_id: str = CAMERA_FRAME
                    ) -> dict[str, Any]:
    """``sensor_msgs/CameraInfo`` of a :class:`~ceilkit.runtime.geometry.camera.CameraModel`
    (the rig's ``camera.yaml`` is in ROS's own layout: the same K, D, R, P)."""
    return {"header": header(stamp_ns, frame_id), "height": int(camera.height),
            "width": int(camera.width), "distortion_model": str(camera.model),
            "d": [float(v) for v in np.asarray(camera.dist, float).ravel()],
            "k": [float(v) for v in np.asarray(camera.K, float).ravel()],
            "r": [float(v) for v in np.asarray(camera.R_rect, float).ravel()],
            "p": [float(v) for v in np.asarray(camera.P, float).ravel()],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0,
                    "do_rectify": False}}


def compressed_image_msg(stamp_ns: int, data: bytes, fmt: str,
                         frame_id: str = CAMERA_FRAME) -> dict[str, Any]:
    """``sensor_msgs/CompressedImage`` (``fmt``: image_transport's, e.g. ``jpeg``)."""
    return {"header": header(stamp_ns, frame_id), "format": fmt, "data": data}


# ----------------------------------------------------------------- definitions (ros2msg)
_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_POINT = "float64 x\nfloat64 y\nfloat64 z\n"
_QUAT = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_POSE = "Point position\nQuaternion orientation\n"
_POSE_COV = "Pose pose\nfloat64[36] covariance\n"
_TWIST = "Vector3 linear\nVector3 angular\n"
_TWIST_COV = "Twist twist\nfloat64[36] covariance\n"
_VECTOR3 = "float64 x\nfloat64 y\nfloat64 z\n"
_DIAG_STATUS = ("byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\n"
                "string name\nstring message\nstring hardware_id\nKeyValue[] values\n")
_KEY_VALUE = "string key\nstring value\n"
_TRANSFORM_STAMPED = "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"
_TRANSFORM = "Vector3 translation\nQuaternion rotation\n"
_CAMERA_INFO = ("std_msgs/Header header\nuint32 height\nuint32 width\n"
                "string distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\n"
                "float64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n")
_ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"


def _definition(main: str, deps: Sequence[tuple[str, str]]) -> str:
    sep = "=" * 80
    return main + "".join(f"{sep}\nMSG: {name}\n{text}" for name, text in deps)


_GEOM = [("geometry_msgs/Pose", _POSE), ("geometry_msgs/Point", _POINT),
         ("geometry_msgs/Quaternion", _QUAT)]
_STD = [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]

DEFINITIONS: Mapping[str, str] = {
    "sensor_msgs/msg/CompressedImage": _definition(
        "std_msgs/Header header\nstring format\nuint8[] data\n", _STD),
    "geometry_msgs/msg/PoseWithCovarianceStamped": _definition(
        "std_msgs/Header header\nPoseWithCovariance pose\n",
        [*_STD, ("geometry_msgs/PoseWithCovariance", _POSE_COV), *_GEOM]),
    "geometry_msgs/msg/PoseStamped": _definition(
        "std_msgs/Header header\nPose pose\n", [*_STD, *_GEOM]),
    "nav_msgs/msg/Odometry": _definition(
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
        [*_STD, ("geometry_msgs/PoseWithCovariance", _POSE_COV), *_GEOM,
         ("geometry_msgs/TwistWithCovariance", _TWIST_COV), ("geometry_msgs/Twist", _TWIST),
         ("geometry_msgs/Vector3", _VECTOR3)]),
    "diagnostic_msgs/msg/DiagnosticArray": _definition(
        "std_msgs/Header header\nDiagnosticStatus[] status\n",
        [*_STD, ("diagnostic_msgs/DiagnosticStatus", _DIAG_STATUS),
         ("diagnostic_msgs/KeyValue", _KEY_VALUE)]),
    "std_msgs/msg/String": "string data\n",
    "tf2_msgs/msg/TFMessage": _definition(
        "geometry_msgs/TransformStamped[] transforms\n",
        [("geometry_msgs/TransformStamped", _TRANSFORM_STAMPED), *_STD,
         ("geometry_msgs/Transform", _TRANSFORM), ("geometry_msgs/Vector3", _VECTOR3),
         ("geometry_msgs/Quaternion", _QUAT)]),
    "sensor_msgs/msg/CameraInfo": _definition(
        _CAMERA_INFO, [*_STD, ("sensor_msgs/RegionOfInterest", _ROI)]),
}
"""ROS 2 message definitions (the ``ros2msg`` schema encoding MCAP uses), by type name."""
