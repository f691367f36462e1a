"""MAVLink 2 framing, written by hand, for ArduPilot and PX4.

Pure, byte-exact encoders (no pymavlink at runtime) for the two messages the
link sends, and a small frame splitter to read back what the autopilot says:

* ``VISION_POSITION_ESTIMATE`` (id 102, CRC_EXTRA 158): the pose, stamped with the
  frame's capture time, in the autopilot's local NED frame.
* ``HEARTBEAT`` (id 0, CRC_EXTRA 50): once a second, as component 197
  (``MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY``), type 18 (``MAV_TYPE_ONBOARD_CONTROLLER``).
* ``TIMESYNC`` (id 111, CRC_EXTRA 34): the answer to the autopilot's requests (PX4
  sends them), so it can map the poses' capture stamps onto its clock.
* ``SET_GPS_GLOBAL_ORIGIN`` (id 48, CRC_EXTRA 41): the EKF origin, only when asked
  (ArduPilot needs one before it uses external navigation).
* ``ODOMETRY`` (id 331, CRC_EXTRA 91): the pose with its covariance, ``quality`` and
  ``reset_counter``, in ``MAV_FRAME_LOCAL_FRD`` / ``MAV_FRAME_BODY_FRD`` (what ArduPilot
  prefers for external navigation; PX4 takes it too), instead of VISION_POSITION_ESTIMATE
  with the ``mavlink-odometry`` protocol. See :func:`odometry_message`.

Frame (MAVLink 2, unsigned)::

    0xFD len incompat=0 compat=0 seq sysid compid msgid(3, LE) payload(len) crc(2, LE)

The payload holds the base fields sorted by type size (largest first; arrays by
their element size), then the extension fields in declaration order; trailing
zero bytes are cut (never the first byte). The CRC is X.25 (CRC-16/MCRF4XX) over
everything after 0xFD, then over the message's CRC_EXTRA byte.

Frame mapping, W (SPEC §1: x along the site, y left, z up, yaw counter-clockwise
from +x) to the autopilot's local NED (x north, y east, z down, yaw clockwise
from north), with W's +x taken as "north"::

    x_ned = x_W        y_ned = -y_W        z_ned = -z_W (= 0: the reference point
    yaw_ned = -yaw_W   roll = pitch = 0     is on the floor)

which is a reflection (det = -1) that turns a right-handed, z-up frame into the
right-handed, z-down NED. The covariance follows as ``J C J^T`` with
``J = diag(1, -1, -1)`` on ``(x, y, yaw)``.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate

STX_V2 = 0xFD
HEADER_LEN = 10  # STX .. msgid
CRC_LEN = 2

MSG_ID_HEARTBEAT = 0
MSG_ID_VISION_POSITION_ESTIMATE = 102
MSG_ID_TIMESYNC = 111
MSG_ID_SET_GPS_GLOBAL_ORIGIN = 48
MSG_ID_GPS_GLOBAL_ORIGIN = 49
MSG_ID_ODOMETRY = 331
CRC_EXTRA = {0: 50, 102: 158, 111: 34, 253: 83, 30: 39, 32: 185, 242: 104, 48: 41, 49: 39,
             331: 91}
MSG_NAMES = {0: "HEARTBEAT", 102: "VISION_POSITION_ESTIMATE", 111: "TIMESYNC",
             253: "STATUSTEXT", 30: "ATTITUDE", 32: "LOCAL_POSITION_NED",
             242: "HOME_POSITION", 48: "SET_GPS_GLOBAL_ORIGIN", 49: "GPS_GLOBAL_ORIGIN",
             331: "ODOMETRY"}

MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAVLINK_VERSION = 3
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
ODOMETRY_QUALITY_UNKNOWN = 0   # MAVLink: 0 unknown, 1 worst .. 100 best, -1 failed

DEFAULT_Z_VAR_M2 = 0.01
DEFAULT_ROLL_PITCH_VAR_RAD2 = math.radians(2.0) ** 2
UNOBSERVED_VAR_M2 = 1.0e6      # (1 km)^2: what ODOMETRY says about a coordinate not measured

UNOBSERVED_POLICIES = ("skip", "nan")


_REVERSED_BITS = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))
"""Each byte with its bits in reverse order (``0x01`` -> ``0x80``)."""


def _reverse16(v: int) -> int:
    return _REVERSED_BITS[v & 0xFF] << 8 | _REVERSED_BITS[v >> 8]


def crc_x25(data: bytes, crc: int = 0xFFFF) -> int:
    """MAVLink's checksum (CRC-16/MCRF4XX: poly 0x1021 reflected, init 0xFFFF).

    The reflected CRC of ``data`` is the plain CCITT CRC (``binascii.crc_hqx``, poly
    0x1021, most significant bit first) of the bit-reversed bytes, from the
    bit-reversed start value, bit-reversed: two C calls (about 1 us for a 130-byte
    frame, where the bytewise Python loop took 125 us).

    >>> hex(crc_x25(b"123456789"))
    '0x6f91'
    """
    return _reverse16(binascii.crc_hqx(bytes(data).translate(_REVERSED_BITS),
                                       _reverse16(crc)))


def frame_v2(msg_id: int, payload: bytes, seq: int, sysid: int, compid: int) -> bytes:
    """Wrap a full-length payload in a MAVLink 2 frame (unsigned), truncating trailing zeros.

    Args:
        msg_id: message id (0..2**24-1), must have a known CRC_EXTRA.
        payload: the payload in wire order, untruncated.
        seq: packet sequence, taken modulo 256.
        sysid, compid: sender's system and component ids (1..255, 0..255).
    """
    body = payload.rstrip(b"\x00") or payload[:1]
    header = struct.pack("<BBBBBBB", len(body), 0, 0, seq % 256, sysid, compid,
                         msg_id & 0xFF) + struct.pack("<H", msg_id >> 8)
    crc = crc_x25(bytes([CRC_EXTRA[msg_id]]), crc_x25(header + body))
    return bytes([STX_V2]) + header + body + struct.pack("<H", crc)


def encode_heartbeat(seq: int, sysid: int = 1,
                     compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                     system_status: int = MAV_STATE_ACTIVE) -> bytes:
    """A HEARTBEAT from an onboard vision component.

    Wire order: custom_mode u32, type u8, autopilot u8, base_mode u8, system_status u8,
    mavlink_version u8 (9 bytes before truncation).
    """
    payload = struct.pack("<IBBBBB", 0, MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID,
                          0, system_status, MAVLINK_VERSION)
    return frame_v2(MSG_ID_HEARTBEAT, payload, seq, sysid, compid)


def encode_vision_position_estimate(usec: int, x: float, y: float, z: float, roll: float,
                                    pitch: float, yaw: float, covariance: Sequence[float],
                                    reset_counter: int, seq: int, sysid: int = 1,
                                    compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
                                    ) -> bytes:
    """A raw VISION_POSITION_ESTIMATE (NED, metres and radians, as given).

    Wire order: usec u64, x, y, z, roll, pitch, yaw f32 (base, already sorted by
    size), then the extensions covariance f32[21], reset_counter u8: 117 bytes
    before truncation.
    """
    if len(covariance) != 21:
        raise ValueError(f"covariance must have 21 entries, found {len(covariance)}")
    payload = (struct.pack("<Q6f", int(usec) & 0xFFFF_FFFF_FFFF_FFFF, x, y, z, roll, pitch, yaw)
               + struct.pack("<21f", *covariance) + struct.pack("<B", reset_counter % 256))
    return frame_v2(MSG_ID_VISION_POSITION_ESTIMATE, payload, seq, sysid, compid)


def encode_timesync(tc1: int, ts1: int, seq: int, sysid: int = 1,
                    compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY) -> bytes:
    """A TIMESYNC (Time Synchronization Protocol v2, times in ns).

    A request has ``tc1 = 0`` and the sender's time in ``ts1``; the answer has the
    answerer's time in ``tc1`` and echoes ``ts1``. Wire order: tc1 i64, ts1 i64
    (the optional target_system/target_component extensions are not sent: 0, broadcast).
    """
    payload = struct.pack("<qq", int(tc1), int(ts1))
    return frame_v2(MSG_ID_TIMESYNC, payload, seq, sysid, compid)


def unpack_timesync(frame: MavFrame) -> tuple[int, int]:
    """``(tc1, ts1)`` of a TIMESYNC frame (payload zero-extended)."""
    return struct.unpack_from("<qq", frame.payload.ljust(16, b"\x00"), 0)


@dataclass(frozen=True)
class GeoOrigin:
    """An EKF origin: WGS84 latitude and longitude (degrees), altitude (m, AMSL)."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        if not (-90.0 <= self.lat_deg <= 90.0 and -180.0 <= self.lon_deg <= 180.0
                and math.isfinite(self.alt_m) and abs(self.alt_m) < 1e6):
            raise LinkError(f"origin must be lat in [-90, 90], lon in [-180, 180], a "
                             f"finite altitude in m; found {self.lat_deg}, "
                             f"{self.lon_deg}, {self.alt_m}")


def encode_set_gps_global_origin(origin: GeoOrigin, target_system: int, seq: int,
                                 sysid: int = 1,
                                 compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                                 time_usec: int = 0) -> bytes:
    """A SET_GPS_GLOBAL_ORIGIN for ``target_system`` (0: every system).

    Wire order: latitude, longitude (degE7) i32, altitude (mm) i32, target_system u8,
    then the extension time_usec u64.
    """
    payload = struct.pack("<iiiBQ", round(origin.lat_deg * 1e7), round(origin.lon_deg * 1e7),
                          round(origin.alt_m * 1000), int(target_system) & 0xFF,
                          int(time_usec) & 0xFFFF_FFFF_FFFF_FFFF)
    return frame_v2(MSG_ID_SET_GPS_GLOBAL_ORIGIN, payload, seq, sysid, compid)


# ------------------------------------------------------------------- pose -> message


def urt_index(i: int, j: int) -> int:
    """Index in the 21-float upper-right triangle of a row-major 6x6 (x, y, z, roll, pitch, yaw).

    >>> [urt_index(k, k) for k in range(6)]
    [0, 6, 11, 15, 18, 20]
    """
    if i > j:
        i, j = j, i
    return i * 6 - i * (i - 1) // 2 + (j - i)


_URT = tuple(tuple(urt_index(i, j) for j in range(6)) for i in range(6))
"""urt_index by row and column."""


def ned_from_world(x_m: float | None, y_m: float | None, yaw_rad: float
                   ) -> tuple[float | None, float | None, float]:
    """``(north, east, yaw_ned)`` from a pose in W: ``(x, -y, -yaw)``, yaw wrapped to [-pi, pi)."""
    yaw = -yaw_rad
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return x_m, (None if y_m is None else -y_m), yaw


def covariance_ned(cov_world: np.ndarray | None, *, z_var_m2: float, roll_pitch_var_rad2: float,
                   x_observed: bool = True, y_observed: bool = True) -> list[float]:
    """The 21 floats of VISION_POSITION_ESTIMATE.covariance, in NED.

    Args:
        cov_world: 3x3 covariance of ``(x, y, yaw)`` in W (m², rad²), or ``None`` (unknown).
        z_var_m2: variance given to z (the vehicle is on the floor; not measured).
        roll_pitch_var_rad2: variance given to roll and pitch (level floor; not measured).
        x_observed, y_observed: a coordinate the method cannot observe gets NaN in its
            row and column (only used with the ``nan`` policy, for PX4).

    Returns:
        21 floats. An unknown (``None`` or non-finite where observed) covariance is
        all NaN, the MAVLink convention ("NaN in the first element: unknown"); the
        autopilots then use their own noise parameters (ArduPilot VISO_POS_M_NSE /
        VISO_YAW_M_NSE, PX4 EKF2_EVP_NOISE / EKF2_EVA_NOISE).
    """
    nan = float("nan")
    observed = (x_observed, y_observed, True)
    if cov_world is None:
        return [nan] * 21
    # plain floats (a 3x3 in numpy costs ~60 us per message in element accesses)
    rows = np.asarray(cov_world, dtype=float).reshape(3, 3).tolist()
    sign = (1.0, -1.0, -1.0)  # J = diag(sign); J C J^T elementwise (inf-safe)
    c = [[rows[a][b] * (sign[a] * sign[b]) for b in range(3)] for a in range(3)]
    for a in range(3):
        for b in range(3):
            if observed[a] and observed[b] and not math.isfinite(c[a][b]):
                return [nan] * 21
    out = [0.0] * 21
    out[_URT[2][2]] = float(z_var_m2)
    out[_URT[3][3]] = float(roll_pitch_var_rad2)
    out[_URT[4][4]] = float(roll_pitch_var_rad2)
    idx = (0, 1, 5)  # (x, y, yaw) -> rows of the 6x6
    for a in range(3):
        for b in range(a, 3):
            out[_URT[idx[a]][idx[b]]] = c[a][b] if observed[a] and observed[b] else nan
    for k, seen in ((0, x_observed), (1, y_observed)):
        if not seen:  # every entry in an unobserved row/column
            for j in range(6):
                out[_URT[k][j]] = nan
    return out


@dataclass(frozen=True)
class VisionSettings:
    """How poses are turned into VISION_POSITION_ESTIMATE.

    Attributes:
        z_var_m2: variance sent for z (m²). ArduPilot folds x, y and z variance into
            one position error, so keep it of the order of the x/y variance.
        roll_pitch_var_rad2: variance sent for roll and pitch (rad²); ArduPilot folds
            them into the yaw error the same way.
        unobserved: a pose missing x or y: ``skip`` sends nothing (safe for both
            autopilots: ArduPilot has no per-axis check and would take a NaN
            position into its EKF); ``nan`` sends NaN in that coordinate and its
            covariance row (PX4 EKF2 then fuses yaw only).
    """

    z_var_m2: float = DEFAULT_Z_VAR_M2
    roll_pitch_var_rad2: float = DEFAULT_ROLL_PITCH_VAR_RAD2
    unobserved: str = "skip"

    def __post_init__(self) -> None:
        if self.unobserved not in UNOBSERVED_POLICIES:
            raise ValueError(f"unobserved must be one of {UNOBSERVED_POLICIES}, "
                             f"found {self.unobserved!r}")


def pose_message(est: Estimate, seq: int, reset_counter: int, *, sysid: int = 1,
                 compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                 settings: VisionSettings | None = None) -> bytes | None:
    """VISION_POSITION_ESTIMATE for one estimate, or ``None`` when nothing may be sent.

    ``None`` for a :class:`Failure`, a non-finite yaw or observed coordinate, and (with
    the default ``skip`` policy) a pose missing x or y. Never a finite position with
    NaN angles: roll = pitch = 0 and yaw is always finite in a sent message.

    ``usec`` is the frame's capture time ``t_ns // 1000`` (the vision clock; ArduPilot
    corrects the offset by jitter estimation, PX4 needs TIMESYNC, see docs/serial.md).
    """
    s = settings or VisionSettings()
    if not isinstance(est, PoseEstimate) or not math.isfinite(est.yaw_rad):
        return None
    if est.x_m is None and est.y_m is None:
        return None
    for v in (est.x_m, est.y_m):
        if v is not None and not math.isfinite(v):
            return None
    if (est.x_m is None or est.y_m is None) and s.unobserved == "skip":
        return None
    north, east, yaw = ned_from_world(est.x_m, est.y_m, est.yaw_rad)
    cov = covariance_ned(est.cov, z_var_m2=s.z_var_m2, roll_pitch_var_rad2=s.roll_pitch_var_rad2,
                         x_observed=est.x_m is not None, y_observed=est.y_m is not None)
    nan = float("nan")
    return encode_vision_position_estimate(
        est.t_ns // 1000, nan if north is None else north, nan if east is None else east,
        0.0, 0.0, 0.0, yaw, cov, reset_counter, seq, sysid, compid)


# ----------------------------------------------------------------------------- odometry


def encode_odometry(usec: int, xyz_m: Sequence[float], q_wxyz: Sequence[float],
                    pose_covariance: Sequence[float], reset_counter: int, quality: int,
                    seq: int, sysid: int = 1,
                    compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY) -> bytes:
    """A raw ODOMETRY (id 331) in ``MAV_FRAME_LOCAL_FRD`` with child ``MAV_FRAME_BODY_FRD``.

    Velocity and angular rates are NaN with an all-NaN velocity covariance (MAVLink:
    unknown); ``estimator_type`` is ``MAV_ESTIMATOR_TYPE_VISION``.

    Wire order: time_usec u64, x, y, z f32, q f32[4], vx, vy, vz, rollspeed, pitchspeed,
    yawspeed f32, pose_covariance f32[21], velocity_covariance f32[21], frame_id u8,
    child_frame_id u8, then the extensions reset_counter u8, estimator_type u8,
    quality i8: 233 bytes before truncation.
    """
    if len(pose_covariance) != 21:
        raise ValueError(f"pose_covariance must have 21 entries, found {len(pose_covariance)}")
    nan = float("nan")
    payload = (struct.pack("<Q3f4f", int(usec) & 0xFFFF_FFFF_FFFF_FFFF, *xyz_m, *q_wxyz)
               + struct.pack("<6f", *([nan] * 6))
               + struct.pack("<21f", *pose_covariance) + struct.pack("<21f", *([nan] * 21))
               + struct.pack("<BBBBb", MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD,
                             reset_counter % 256, MAV_ESTIMATOR_TYPE_VISION,
                             max(-1, min(100, int(quality)))))
    return frame_v2(MSG_ID_ODOMETRY, payload, seq, sysid, compid)


@dataclass(frozen=True)
class OdometrySettings:
    """How poses are turned into ODOMETRY.

    Attributes:
        z_var_m2, roll_pitch_var_rad2: as :class:`VisionSettings` (not measured: the
            vehicle is on a level floor; ArduPilot folds them into one error each).
        unobserved_var_m2: variance sent for a coordinate the method does not observe
            (the corridor method's x), whose value is then sent as 0. PX4 weighs each
            axis by its own variance (it takes y); ArduPilot folds x, y, z into one
            error, so it must not use the position (``EK3_SRC1_POSXY`` = 0, what
            ``ceilcal autopilot --corridor`` writes) and takes the yaw.
        sensor_V_m: the point whose position is sent, in V (m): the camera's optical
            centre (the rig's mount x, y, z), which is what the autopilots' ``VISO_POS_*``
            / ``EKF2_EV_POS_*`` describe. ``(0, 0, 0)`` sends V's origin.
    """

    z_var_m2: float = DEFAULT_Z_VAR_M2
    roll_pitch_var_rad2: float = DEFAULT_ROLL_PITCH_VAR_RAD2
    unobserved_var_m2: float = UNOBSERVED_VAR_M2
    sensor_V_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        values = (self.z_var_m2, self.roll_pitch_var_rad2, self.unobserved_var_m2,
                  *self.sensor_V_m)
        if len(self.sensor_V_m) != 3 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"odometry settings must be finite, sensor_V_m three numbers; "
                             f"found {self}")


def odometry_quality(quality: float) -> int:
    """ODOMETRY's ``quality`` (1 worst .. 100 best; 0 unknown) of a quality in [0, 1].

    >>> [odometry_quality(q) for q in (0.0, 0.004, 0.5, 1.0, float("nan"))]
    [1, 1, 50, 100, 0]
    """
    if not math.isfinite(quality):
        return ODOMETRY_QUALITY_UNKNOWN
    return max(1, min(100, round(100.0 * quality)))


def _sensor_pose_cov(cov_world: np.ndarray, yaw_rad: float, sensor_V_m: Sequence[float],
                     observed: Sequence[bool], unobserved_var_m2: float) -> np.ndarray | None:
    """3x3 covariance of the sensor point's (x, y) and yaw in W, or ``None`` if unknown."""
    c = np.array(cov_world, dtype=float).reshape(3, 3)
    for a in range(3):
        if not observed[a]:
            c[a, :] = 0.0
            c[:, a] = 0.0
            c[a, a] = unobserved_var_m2
    if not np.all(np.isfinite(c)):
        return None
    s, co = math.sin(yaw_rad), math.cos(yaw_rad)
    tx, ty = float(sensor_V_m[0]), float(sensor_V_m[1])
    lever = np.array([[1.0, 0.0, -s * tx - co * ty], [0.0, 1.0, co * tx - s * ty],
                      [0.0, 0.0, 1.0]])  # d(x + Rz(yaw) t) / d(x, y, yaw)
    return lever @ c @ lever.T


def odometry_message(est: Estimate, seq: int, reset_counter: int, *, sysid: int = 1,
                     compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                     settings: OdometrySettings | None = None) -> bytes | None:
    """ODOMETRY for one estimate, or ``None`` when nothing may be sent.

    The frame mapping is VISION_POSITION_ESTIMATE's, W -> ``MAV_FRAME_LOCAL_FRD`` with
    W's +x as "forward": ``(x, -y, -z)``, yaw ``-yaw_W``; the body frame is FRD
    (V's x, -y, -z), so ``q = (cos(psi/2), 0, 0, sin(psi/2))`` with ``psi = -yaw_W``.
    The position is that of ``settings.sensor_V_m`` (the camera), ``x + Rz(yaw) t``.

    ``None`` for a :class:`Failure`, a non-finite yaw or observed coordinate, a pose
    with neither x nor y, and a pose missing x or y that has no covariance (an all-NaN
    covariance would make ArduPilot trust the placeholder). A missing coordinate is
    sent as 0 with variance ``unobserved_var_m2`` and no correlation.
    """
    s = settings or OdometrySettings()
    if not isinstance(est, PoseEstimate) or not math.isfinite(est.yaw_rad):
        return None
    observed = (est.x_m is not None, est.y_m is not None, True)
    if not (observed[0] or observed[1]):
        return None
    if any(v is not None and not math.isfinite(v) for v in (est.x_m, est.y_m)):
        return None
    cov = None if est.cov is None else _sensor_pose_cov(est.cov, est.yaw_rad, s.sensor_V_m,
                                                        observed, s.unobserved_var_m2)
    if cov is None and not all(observed):
        return None
    tx, ty, tz = s.sensor_V_m
    c, sn = math.cos(est.yaw_rad), math.sin(est.yaw_rad)
    x_w = (est.x_m or 0.0) + c * tx - sn * ty
    y_w = (est.y_m or 0.0) + sn * tx + c * ty
    north, east, yaw = ned_from_world(x_w, y_w, est.yaw_rad)
    covariance = covariance_ned(cov, z_var_m2=s.z_var_m2,
                                roll_pitch_var_rad2=s.roll_pitch_var_rad2)
    q = (math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0))
    return encode_odometry(est.t_ns // 1000, (north, east, -tz), q, covariance, reset_counter,
                           odometry_quality(est.quality), seq, sysid, compid)


# -------------------------------------------------------------------------- decoding


@dataclass(frozen=True)
class MavFrame:
    """One MAVLink frame read back. ``crc_ok`` is ``None`` when the CRC_EXTRA is unknown."""

    msg_id: int
    seq: int
    sysid: int
    compid: int
    payload: bytes
    crc_ok: bool | None
    raw: bytes

    @property
    def name(self) -> str:
        return MSG_NAMES.get(self.msg_id, f"MSG_{self.msg_id}")


def _frame_at(buf: bytes, i: int) -> tuple[MavFrame | None, int]:
    """Try a frame at ``buf[i]``: (frame, its length), (None, 0) if incomplete, (None, -1) bad."""
    if buf[i] == STX_V2:
        if len(buf) - i < HEADER_LEN:
            return None, 0
        plen, incompat = buf[i + 1], buf[i + 2]
        total = HEADER_LEN + plen + CRC_LEN + (13 if incompat & 0x01 else 0)
        if len(buf) - i < total:
            return None, 0
        seq, sysid, compid = buf[i + 4], buf[i + 5], buf[i + 6]
        msg_id = buf[i + 7] | (buf[i + 8] << 8) | (buf[i + 9] << 16)
        payload = bytes(buf[i + HEADER_LEN:i + HEADER_LEN + plen])
        crc_pos = i + HEADER_LEN + plen
    elif buf[i] == 0xFE:  # MAVLink 1
        if len(buf) - i < 6:
            return None, 0
        plen = buf[i + 1]
        total = 6 + plen + CRC_LEN
        if len(buf) - i < total:
            return None, 0
        seq, sysid, compid, msg_id = buf[i + 2], buf[i + 3], buf[i + 4], buf[i + 5]
        payload = bytes(buf[i + 6:i + 6 + plen])
        crc_pos = i + 6 + plen
    else:
        return None, -1
    raw = bytes(buf[i:i + total])
    crc_ok = None
    if msg_id in CRC_EXTRA:
        crc = crc_x25(bytes([CRC_EXTRA[msg_id]]), crc_x25(bytes(buf[i + 1:crc_pos])))
        crc_ok = crc == struct.unpack_from("<H", buf, crc_pos)[0]
        if not crc_ok:
            return None, -1
    return MavFrame(msg_id, seq, sysid, compid, payload, crc_ok, raw), total


def split_frames(buffer: bytes) -> tuple[list[MavFrame], bytes]:
    """Frames in ``buffer`` and the incomplete rest; garbage and bad-CRC bytes are skipped.

    A frame whose CRC_EXTRA is not in :data:`CRC_EXTRA` is returned with ``crc_ok=None``.
    """
    frames: list[MavFrame] = []
    i = 0
    n = len(buffer)
    while i < n:
        frame, length = _frame_at(buffer, i)
        if length == 0:
            break
        if frame is None:
            i += 1
            continue
        frames.append(frame)
        i += length
    return frames, bytes(buffer[i:])


def iter_frames(data: bytes) -> Iterator[MavFrame]:
    """Every complete frame in ``data`` (a helper for tests and logs)."""
    yield from split_frames(data)[0]


def unpack_vision_position_estimate(frame: MavFrame) -> dict[str, object]:
    """The fields of a VISION_POSITION_ESTIMATE frame (payload zero-extended to 117 bytes)."""
    p = frame.payload.ljust(117, b"\x00")
    usec, x, y, z, roll, pitch, yaw = struct.unpack_from("<Q6f", p, 0)
    cov = struct.unpack_from("<21f", p, 32)
    return {"usec": usec, "x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw,
            "covariance": list(cov), "reset_counter": p[116]}


def describe_frame(frame: MavFrame) -> str:
    """One log line for a frame read back from the autopilot."""
    text = f"{frame.name} sys={frame.sysid} comp={frame.compid} seq={frame.seq}"
    if frame.msg_id == MSG_ID_TIMESYNC:
        tc1, ts1 = unpack_timesync(frame)
        text += f" tc1={tc1} ts1={ts1}"
    if frame.msg_id == 253:  # STATUSTEXT: severity u8, text char[50]
        p = frame.payload.ljust(51, b"\x00")
        msg = p[1:51].split(b"\x00")[0].decode("ascii", "replace")
        text += f" severity={p[0]} text={msg!r}"
    return text
