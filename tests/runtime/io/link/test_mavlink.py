"""MAVLink 2: byte-exact frames, pymavlink decoding, the W -> NED mapping, covariance."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.link import mavlink
from ceilkit.runtime.io.link.transport import MavlinkProtocol

COV_W = np.array([[0.0004, 0.0001, 0.00002],
                  [0.0001, 0.0009, -0.00003],
                  [0.00002, -0.00003, 0.0003]])


def pose(**kw) -> PoseEstimate:
    base = dict(t_ns=1_700_000_123_456_789, method="lights", x_m=2.0, y_m=1.0,
                yaw_rad=math.radians(30.0), quality=0.9, cov=COV_W)
    base.update(kw)
    return PoseEstimate(**base)


def parse(data: bytes) -> list:
    mav = mavlink2.MAVLink(None)
    return mav.parse_buffer(data) or []


def test_crc_x25_check_value():
    # CRC-16/MCRF4XX check value of "123456789"
    assert mavlink.crc_x25(b"123456789") == 0x6F91


def _crc_bytewise(data: bytes, crc: int = 0xFFFF) -> int:
    # the MAVLink C library's crc_accumulate, one byte at a time
    for b in data:
        tmp = b ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


def test_crc_x25_matches_bytewise_accumulation():
    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 7, 8, 9, 130, 280):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        start = int(rng.integers(0, 65536))
        assert mavlink.crc_x25(data, start) == _crc_bytewise(data, start)
        assert mavlink.crc_x25(data) == _crc_bytewise(data)


def test_heartbeat_golden():
    # fd | len 09 | incompat 00 | compat 00 | seq 07 | sys 01 | comp c5 (197) | id 000000 |
    # custom_mode 00000000 | type 12 (18) | autopilot 08 | base_mode 00 | status 04 |
    # version 03 | crc 565d (LE)
    assert mavlink.encode_heartbeat(7).hex() == "fd0900000701c50000000000000012080004035d56"


# usec 1700000123456 = 0x18bcfe74a40; x 2.0; y -1.0 (= -W y); z, roll, pitch 0;
# yaw -30 deg = bf060a92; cov[0] 4e-4, cov[1] -1e-4 (xy flipped), ... reset_counter 2.
VPE_GOLDEN = (
    "fd7500001101c5660000404ae7cf8b01000000000040000080bf000000000000000000000000920a06bf"
    "17b7d13917b7d1b8000000000000000000000000acc5a7b7faed6b3a000000000000000000000000"
    "82a8fbb70ad7233c0000000000000000000000000fb59f3a00000000000000000fb59f3a00000000"
    "52499d3902a95c")


def test_vision_position_estimate_golden():
    out = mavlink.pose_message(pose(), seq=17, reset_counter=2)
    assert out.hex() == VPE_GOLDEN
    assert len(out) == 10 + 117 + 2


def test_vision_position_estimate_matches_pymavlink_encoder():
    cov = [0.001 * (k + 1) for k in range(21)]
    mav = mavlink2.MAVLink(None, srcSystem=3, srcComponent=197)
    mav.seq = 200
    ref = mav.vision_position_estimate_encode(123, 1.0, -2.0, 0.0, 0.0, 0.0, 0.5, cov, 9)
    ours = mavlink.encode_vision_position_estimate(123, 1.0, -2.0, 0.0, 0.0, 0.0, 0.5, cov, 9,
                                                   seq=200, sysid=3)
    assert ours == ref.pack(mav)


def test_trailing_zero_truncation():
    out = mavlink.encode_vision_position_estimate(1, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                                  [0.0] * 21, 0, seq=0)
    assert out[1] == 12  # usec + x; the zero tail is cut
    (msg,) = parse(out)
    assert msg.x == 1.0 and msg.covariance == [0.0] * 21 and msg.reset_counter == 0
    zero = mavlink.encode_heartbeat(0, system_status=0)
    assert zero[1] == 9  # ends in mavlink_version 3: nothing to cut
    everything_zero = mavlink.frame_v2(0, bytes(9), 0, 1, 1)
    assert everything_zero[1] == 1  # the first byte is never cut


def test_pymavlink_reads_pose_in_ned():
    est = pose()
    (msg,) = parse(mavlink.pose_message(est, seq=17, reset_counter=2))
    assert msg.get_type() == "VISION_POSITION_ESTIMATE"
    assert msg.get_srcComponent() == 197 and msg.get_srcSystem() == 1
    assert msg.usec == est.t_ns // 1000
    assert (msg.x, msg.y, msg.z) == pytest.approx((2.0, -1.0, 0.0))
    assert (msg.roll, msg.pitch) == (0.0, 0.0)
    assert msg.yaw == pytest.approx(-math.radians(30.0))
    assert msg.reset_counter == 2
    c = np.array(msg.covariance)
    J = np.diag([1.0, -1.0, -1.0])
    cn = J @ COV_W @ J
    ij = [(0, 0), (1, 1), (5, 5), (0, 1), (0, 5), (1, 5)]
    for (i, j), (a, b) in zip(ij, [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)], strict=True):
        assert c[mavlink.urt_index(i, j)] == pytest.approx(cn[a, b], rel=1e-6)
    s = mavlink.VisionSettings()
    assert c[11] == pytest.approx(s.z_var_m2) and c[15] == c[18] == pytest.approx(
        s.roll_pitch_var_rad2)


def test_ned_mapping_is_a_reflection_of_w():
    # a vehicle facing W +y (yaw +90) at W (0, 1): in NED it is east of... west: y = -1,
    # facing yaw -90 (west), i.e. heading the way it moves.
    n, e, yaw = mavlink.ned_from_world(0.0, 1.0, math.pi / 2)
    assert (n, e) == (0.0, -1.0) and yaw == pytest.approx(-math.pi / 2)
    # moving one step along the heading in W lands one step along the heading in NED
    for yaw_w in np.linspace(-3, 3, 7):
        step_w = np.array([math.cos(yaw_w), math.sin(yaw_w)])
        n1, e1, yaw_ned = mavlink.ned_from_world(*step_w, yaw_w)
        assert (n1, e1) == pytest.approx((math.cos(yaw_ned), math.sin(yaw_ned)))


def test_unknown_covariance_is_nan():
    (msg,) = parse(mavlink.pose_message(pose(cov=None), 0, 0))
    assert all(math.isnan(v) for v in msg.covariance)
    inf_cov = COV_W.copy()
    inf_cov[0, 0] = math.inf
    (msg,) = parse(mavlink.pose_message(pose(cov=inf_cov), 0, 0))
    assert math.isnan(msg.covariance[0])


def test_unobserved_x_skipped_by_default_and_nan_on_request():
    corridor = pose(x_m=None, cov=np.diag([math.inf, 0.01, 0.001]), method="corridor")
    assert mavlink.pose_message(corridor, 0, 0) is None
    px4 = mavlink.VisionSettings(unobserved="nan")
    (msg,) = parse(mavlink.pose_message(corridor, 0, 0, settings=px4))
    assert math.isnan(msg.x) and msg.y == pytest.approx(-1.0)
    assert math.isfinite(msg.yaw) and msg.roll == 0.0 and msg.pitch == 0.0
    c = msg.covariance
    assert all(math.isnan(c[mavlink.urt_index(0, k)]) for k in range(6))
    assert c[6] == pytest.approx(0.01) and c[20] == pytest.approx(0.001)
    with pytest.raises(ValueError, match="unobserved"):
        mavlink.VisionSettings(unobserved="zero")


@pytest.mark.parametrize("est", [
    Failure(t_ns=1, method="lights", reason="too_few_lights"),
    pose(yaw_rad=float("nan")), pose(x_m=float("inf")), pose(x_m=None, y_m=None),
])
def test_nothing_sent_without_a_pose(est):
    assert mavlink.pose_message(est, 0, 0) is None


def test_protocol_sequence_wraps_and_reset_counter():
    proto = MavlinkProtocol(sysid=7, compid=197)
    data = b""
    for k in range(300):
        if k == 100:
            proto.relocalized()
        msg, valid = proto.pose(pose(t_ns=k * 10**7))
        assert valid
        data += msg
    frames = list(mavlink.iter_frames(data))
    assert [f.seq for f in frames] == [k % 256 for k in range(300)]
    msgs = parse(data)
    assert len(msgs) == 300
    assert [m.reset_counter for m in msgs[99:101]] == [0, 1]
    assert {m.get_srcSystem() for m in msgs} == {7}


def test_split_frames_skips_garbage_and_keeps_partial():
    hb = mavlink.encode_heartbeat(1)
    vpe = mavlink.pose_message(pose(), 2, 0)
    broken = bytearray(hb)
    broken[-1] ^= 0xFF
    buf = b"\x00junk" + bytes(broken) + hb + vpe + vpe[:20]
    frames, rest = mavlink.split_frames(buf)
    assert [f.name for f in frames] == ["HEARTBEAT", "VISION_POSITION_ESTIMATE"]
    assert all(f.crc_ok for f in frames) and rest == vpe[:20]
    fields = mavlink.unpack_vision_position_estimate(frames[1])
    assert fields["x"] == 2.0 and fields["reset_counter"] == 0


def test_describe_statustext_from_autopilot():
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    raw = mav.statustext_encode(4, b"EKF3 IMU0 is using external nav data").pack(mav)
    (frame,) = mavlink.iter_frames(raw)
    assert frame.crc_ok
    assert "STATUSTEXT" in mavlink.describe_frame(frame)
    assert "external nav" in mavlink.describe_frame(frame)


def test_urt_index_covers_the_triangle():
    idx = sorted(mavlink.urt_index(i, j) for i in range(6) for j in range(i, 6))
    assert idx == list(range(21))
    assert struct.calcsize("<Q6f21fB") == 117


# ---------------------------------------------------------------- TIMESYNC, EKF origin


def test_timesync_matches_pymavlink_and_round_trips():
    ours = mavlink.encode_timesync(123_456_789_000, -5, seq=3, sysid=1, compid=197)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    mav.seq = 3
    ref = mav.timesync_encode(123_456_789_000, -5).pack(mav)
    assert ours == bytes(ref)
    (frame,) = mavlink.iter_frames(ours)
    assert mavlink.unpack_timesync(frame) == (123_456_789_000, -5)
    assert "tc1=123456789000" in mavlink.describe_frame(frame)


def test_set_gps_global_origin_decodes_with_pymavlink():
    origin = mavlink.GeoOrigin(48.1173, 11.5167, 545.4)
    data = mavlink.encode_set_gps_global_origin(origin, target_system=1, seq=0)
    (msg,) = parse(data)
    assert msg.get_type() == "SET_GPS_GLOBAL_ORIGIN" and msg.target_system == 1
    assert (msg.latitude, msg.longitude, msg.altitude) == (481173000, 115167000, 545400)
    with pytest.raises(mavlink.LinkError, match="origin"):
        mavlink.GeoOrigin(91.0, 0.0, 0.0)


def _autopilot(sysid=1):
    return mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)


def test_protocol_answers_timesync_requests_only():
    proto = MavlinkProtocol()
    ap = _autopilot()
    request = bytes(ap.timesync_encode(0, 777_000).pack(ap))
    answer = bytes(ap.timesync_encode(5, 777_000).pack(ap))  # someone else's answer
    out = proto.answer(request, now_ns=42_000_000_000)
    assert proto.answer(answer, now_ns=1) == [] and proto.timesyncs == 1
    (msg,) = parse(b"".join(out))
    assert (msg.tc1, msg.ts1) == (42_000_000_000, 777_000)
    assert MavlinkProtocol(answer_timesync=False).answer(request, 1) == []


def test_protocol_sends_origin_until_acknowledged():
    from ceilkit.runtime.io.link.transport import Health

    origin = mavlink.GeoOrigin(-33.5, 151.25, 20.0)
    proto = MavlinkProtocol(origin=origin)
    health = Health(0, False, "", True, "stale", 0)
    ap = _autopilot(sysid=7)
    proto.answer(bytes(ap.heartbeat_encode(1, 3, 0, 0, 4).pack(ap)), 0)  # ArduPilot's
    names = [m.get_type() for m in parse(b"".join(proto.periodic(health)))]
    assert names == ["HEARTBEAT", "SET_GPS_GLOBAL_ORIGIN"]
    assert parse(b"".join(proto.periodic(health)))[1].target_system == 7
    proto.answer(bytes(ap.gps_global_origin_encode(-335000000, 1512500000, 20000).pack(ap)), 0)
    assert proto.origin_acknowledged
    assert [m.get_type() for m in parse(proto.periodic(health))] == ["HEARTBEAT"]
    assert MavlinkProtocol().periodic(health)[:1] == b"\xfd"  # no origin by default


# --------------------------------------------------------------------------- ODOMETRY


def odometry(est, settings=None, seq=0, reset_counter=0):
    out = mavlink.odometry_message(est, seq, reset_counter, settings=settings)
    assert out is not None
    (msg,) = parse(out)
    assert msg.get_type() == "ODOMETRY"
    return msg


def test_odometry_matches_pymavlink_encoder():
    cov = [0.001 * (k + 1) for k in range(21)]
    nan = float("nan")
    mav = mavlink2.MAVLink(None, srcSystem=4, srcComponent=197)
    mav.seq = 77
    ref = mav.odometry_encode(123, mavlink2.MAV_FRAME_LOCAL_FRD, mavlink2.MAV_FRAME_BODY_FRD,
                              1.0, -2.0, -0.5, [0.5, 0.0, 0.0, 0.5], nan, nan, nan, nan, nan,
                              nan, cov, [nan] * 21, 3, mavlink2.MAV_ESTIMATOR_TYPE_VISION, 42)
    ours = mavlink.encode_odometry(123, (1.0, -2.0, -0.5), (0.5, 0.0, 0.0, 0.5), cov, 3, 42,
                                   seq=77, sysid=4)
    assert ours == ref.pack(mav)


def test_odometry_fields_frames_and_mapping():
    sensor = (0.3, 0.1, 0.8)
    est = pose(quality=0.87)
    msg = odometry(est, mavlink.OdometrySettings(sensor_V_m=sensor), seq=9, reset_counter=4)
    assert msg.frame_id == mavlink2.MAV_FRAME_LOCAL_FRD == 20
    assert msg.child_frame_id == mavlink2.MAV_FRAME_BODY_FRD == 12
    assert msg.estimator_type == mavlink2.MAV_ESTIMATOR_TYPE_VISION
    assert msg.quality == 87 and msg.reset_counter == 4 and msg.get_seq() == 9
    assert msg.time_usec == est.t_ns // 1000
    # the camera's optical centre: (x, y) + Rz(yaw) t in W, then (x, -y, -z)
    c, s = math.cos(est.yaw_rad), math.sin(est.yaw_rad)
    cam_w = (2.0 + c * 0.3 - s * 0.1, 1.0 + s * 0.3 + c * 0.1)
    assert msg.x == pytest.approx(cam_w[0], abs=1e-6)
    assert msg.y == pytest.approx(-cam_w[1], abs=1e-6)
    assert msg.z == pytest.approx(-0.8, abs=1e-6)
    # body FRD -> local FRD: a rotation of -yaw_W about z (down)
    w, qx, qy, qz = msg.q
    assert (qx, qy) == (0.0, 0.0)
    assert 2 * math.atan2(qz, w) == pytest.approx(-est.yaw_rad, abs=1e-6)
    assert all(math.isnan(v) for v in (msg.vx, msg.vy, msg.vz, msg.rollspeed))
    assert math.isnan(msg.velocity_covariance[0])


def test_odometry_covariance_is_the_sensor_points_in_frd():
    t = (0.3, 0.1, 0.8)
    est = pose()
    msg = odometry(est, mavlink.OdometrySettings(sensor_V_m=t))
    c, s = math.cos(est.yaw_rad), math.sin(est.yaw_rad)
    lever = np.array([[1, 0, -s * t[0] - c * t[1]], [0, 1, c * t[0] - s * t[1]], [0, 0, 1]])
    J = np.diag([1.0, -1.0, -1.0])
    expect = J @ lever @ COV_W @ lever.T @ J
    cov = msg.pose_covariance
    u = mavlink.urt_index
    for (a, ia), (b, ib) in [((0, 0), (0, 0)), ((0, 0), (1, 1)), ((1, 1), (1, 1)),
                             ((0, 0), (2, 5)), ((1, 1), (2, 5)), ((2, 5), (2, 5))]:
        assert cov[u(ia, ib)] == pytest.approx(expect[a, b], rel=1e-5, abs=1e-9)
    assert cov[u(2, 2)] == pytest.approx(mavlink.DEFAULT_Z_VAR_M2)
    assert cov[u(3, 3)] == pytest.approx(mavlink.DEFAULT_ROLL_PITCH_VAR_RAD2)
    # with no lever arm the mapping is VISION_POSITION_ESTIMATE's
    plain = odometry(est).pose_covariance
    vpe = mavlink.covariance_ned(COV_W, z_var_m2=0.01, roll_pitch_var_rad2=math.radians(2) ** 2)
    assert plain == pytest.approx([float(np.float32(v)) for v in vpe], rel=1e-6)


def test_odometry_corridor_sends_y_and_yaw_with_a_huge_x_variance():
    cov = np.array([[np.inf, 0.0, 0.0], [0.0, 1e-4, 2e-6], [0.0, 2e-6, 1e-5]])
    est = pose(method="corridor", x_m=None, y_m=0.25, yaw_rad=math.radians(-10), cov=cov)
    msg = odometry(est)
    u = mavlink.urt_index
    assert msg.x == 0.0 and msg.y == pytest.approx(-0.25)
    assert msg.pose_covariance[u(0, 0)] == pytest.approx(mavlink.UNOBSERVED_VAR_M2)
    assert msg.pose_covariance[u(0, 1)] == 0.0 and msg.pose_covariance[u(0, 5)] == 0.0
    assert msg.pose_covariance[u(1, 1)] == pytest.approx(1e-4)
    assert msg.pose_covariance[u(1, 5)] == pytest.approx(2e-6)  # (-1)(-1): sign kept
    assert all(math.isfinite(v) for v in msg.pose_covariance)
    # without a covariance the placeholder x would be trusted: nothing is sent
    assert mavlink.odometry_message(pose(x_m=None, cov=None), 0, 0) is None


def test_odometry_known_covariance_missing_is_nan_first():
    msg = odometry(pose(cov=None))
    assert all(math.isnan(v) for v in msg.pose_covariance)


@pytest.mark.parametrize("est", [
    Failure(t_ns=5, method="lights", reason="no_lights"),
    pose(yaw_rad=float("nan")),
    pose(x_m=float("inf")),
    pose(x_m=None, y_m=None),
])
def test_odometry_nothing_for_what_cannot_be_sent(est):
    assert mavlink.odometry_message(est, 0, 0) is None


def test_odometry_quality_mapping():
    assert mavlink.odometry_quality(0.0) == 1      # 0 would mean "unknown"
    assert mavlink.odometry_quality(0.5) == 50
    assert mavlink.odometry_quality(2.0) == 100
    assert mavlink.odometry_quality(float("nan")) == 0


def test_odometry_settings_refuse_non_finite():
    with pytest.raises(ValueError):
        mavlink.OdometrySettings(sensor_V_m=(0.0, float("nan"), 0.0))


def test_pymavlink_decodes_every_odometry_of_a_random_run():
    rng = np.random.default_rng(14)
    settings = mavlink.OdometrySettings(sensor_V_m=(0.25, -0.05, 0.9))
    stream = b""
    sent = []
    for k in range(500):
        a = rng.normal(size=(3, 3)) * 0.01
        cov = a @ a.T + np.diag([1e-6, 1e-6, 1e-7])
        x = None if k % 5 == 0 else float(rng.uniform(-500, 500))
        est = pose(t_ns=10**9 + k * 33_000_000, x_m=x, y_m=float(rng.uniform(-50, 50)),
                   yaw_rad=float(rng.uniform(-math.pi, math.pi)), quality=float(rng.uniform()),
                   cov=cov)
        msg = mavlink.odometry_message(est, k, k // 7, settings=settings)
        stream += msg
        sent.append(est)
    msgs = parse(stream)
    assert len(msgs) == len(sent) == 500
    for est, msg in zip(sent, msgs, strict=True):
        assert msg.get_type() == "ODOMETRY" and msg.time_usec == est.t_ns // 1000
        yaw = 2 * math.atan2(msg.q[3], msg.q[0])
        assert math.cos(yaw + est.yaw_rad) == pytest.approx(1.0, abs=1e-9)
        assert all(math.isfinite(v) for v in msg.pose_covariance)
