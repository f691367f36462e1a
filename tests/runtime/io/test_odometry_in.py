import math

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.io.link.mavlink import split_frames
from ceilkit.runtime.io.link.transport import Received
from ceilkit.runtime.io.odometry_in import (
    DifferentialDrive,
    OdometryReceiver,
    PoseDifferencer,
    decode_pceio,
    encode_pceio,
    unpack_odometry_pose,
    unpack_wheel_distance,
)


def _mav():
    return mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)


def test_pceio_round_trip_and_checksum_is_nmea_xor():
    raw = encode_pceio(1200, 0.015, -0.002, 0.2)
    assert raw == b"$PCEIO,1200,0.0150,-0.0020,0.200*54\r\n"
    body = raw[1:raw.index(b"*")]
    x = 0
    for c in body:
        x ^= c
    assert raw[raw.index(b"*") + 1:-2].decode() == f"{x:02X}"
    inc = decode_pceio(raw)
    assert inc.t_ns == 1_200_000_000
    assert (inc.dx_m, inc.dy_m) == (0.015, -0.002)
    assert inc.dyaw_rad == pytest.approx(math.radians(0.2))


@pytest.mark.parametrize("bad", [b"$PCEIO,1200,0.0150,0.0000,0.200*00",
                                 b"$PCEIO,1200,0.0150,0.0000*2B",
                                 b"$PCEIO,12x0,0.0150,0.0000,0.200",
                                 b"$PCEIO,1200,nan,0.0000,0.200"])
def test_pceio_errors(bad):
    if b"*" not in bad:
        body = bad[1:].decode()
        x = 0
        for c in body.encode():
            x ^= c
        bad = bad + f"*{x:02X}".encode()
    with pytest.raises(LinkError, match="PCEIO"):
        decode_pceio(bad)


def test_other_sentences_are_not_odometry():
    assert decode_pceio(b"$PCEIS,0,0,V,none,*3C") is None


def test_odometry_frames_are_differenced_into_v_increments():
    mav = _mav()
    nan = float("nan")
    frames = []
    # W pose (x, y, yaw): (0, 0, 90 deg) then (0, 0.1, 100 deg): 0.1 m forward in V
    for usec, north, east, yaw_w in ((1_000_000, 0.0, 0.0, 90.0), (1_100_000, 0.0, -0.1, 100.0)):
        yn = -math.radians(yaw_w)
        q = [math.cos(yn / 2), 0.0, 0.0, math.sin(yn / 2)]
        msg = mavlink2.MAVLink_odometry_message(usec, 1, 8, north, east, 0.0, q, nan, nan, nan,
                                                nan, nan, nan, [nan] * 21, [nan] * 21, 0, 0,
                                                0)
        frames.append(msg.pack(mav))
    got = [unpack_odometry_pose(f) for f in split_frames(b"".join(frames))[0]]
    assert got[0][0] == 1_000_000_000 and got[1][2] == pytest.approx(0.1, abs=1e-6)
    diff = PoseDifferencer()
    assert diff.add(*got[0]) is None
    inc = diff.add(*got[1])
    assert inc.dx_m == pytest.approx(0.1, abs=1e-6) and inc.dy_m == pytest.approx(0, abs=1e-6)
    assert inc.dyaw_rad == pytest.approx(math.radians(10), abs=1e-6)


def test_wheel_distance_and_differential_drive():
    mav = _mav()
    raw = mavlink2.MAVLink_wheel_distance_message(2_000_000, 2, [1.0, 1.2] + [0.0] * 14
                                                  ).pack(mav)
    frame = split_frames(raw)[0][0]
    t_ns, dist = unpack_wheel_distance(frame)
    assert t_ns == 2_000_000_000 and dist == (1.0, 1.2)
    broken = bytearray(raw)
    broken[20] ^= 0xFF
    frames = split_frames(bytes(broken))[0]
    if frames:  # the CRC_EXTRA of WHEEL_DISTANCE is checked here
        with pytest.raises(LinkError, match="CRC"):
            unpack_wheel_distance(frames[0])
    dd = DifferentialDrive(0.5)
    assert dd.add(0, 0.0, 0.0) is None
    straight = dd.add(1, 0.1, 0.1)
    assert (straight.dx_m, straight.dy_m, straight.dyaw_rad) == pytest.approx((0.1, 0, 0))
    turn = dd.add(2, 0.1, 0.1 + 0.5 * math.pi / 2)     # the right wheel goes further
    assert turn.dyaw_rad == pytest.approx(math.pi / 2)
    r = (0.5 * math.pi / 4) / (math.pi / 2)            # arc radius
    assert turn.dx_m == pytest.approx(r) and turn.dy_m == pytest.approx(r)
    with pytest.raises(LinkError):
        DifferentialDrive(0.0)


def test_receiver_feeds_the_sink_and_counts_bad_messages():
    rows = []
    rx = OdometryReceiver(lambda *a: rows.append(a), track_m=0.5)
    rx(Received(0, encode_pceio(100, 0.01, 0.0, 0.0).strip(), ""))
    rx(Received(0, b"$PCEIO,100,0.01,0,0*00", ""))
    rx(Received(0, b"$PCEIS,0,0,V,none,*3C", ""))
    mav = _mav()
    for usec, left in ((1_000, 0.0), (2_000, 0.2)):
        rx(Received(0, mavlink2.MAVLink_wheel_distance_message(
            usec, 2, [left, left] + [0.0] * 14).pack(mav), ""))
    assert rx.rows == 2 and rx.bad == 1
    assert rows[0] == (100_000_000, 0.01, 0.0, 0.0)
    assert rows[1][0] == 2_000_000 and rows[1][1] == pytest.approx(0.2)
