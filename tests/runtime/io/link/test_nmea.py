"""NMEA sentences: byte-exact encodings, pynmea2 decoding, the 82-character limit."""

from __future__ import annotations

import math
from functools import reduce

import numpy as np
import pynmea2
import pytest

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.link import nmea


def pose(**kw) -> PoseEstimate:
    base = dict(t_ns=12_345_678_901, method="lights", x_m=1.5, y_m=-0.25,
                yaw_rad=math.radians(-30.0), quality=0.9)
    base.update(kw)
    return PoseEstimate(**base)


def xor_hex(body: bytes) -> str:
    return f"{reduce(lambda a, b: a ^ b, body, 0):02X}"


# Expected bytes, checked by hand: fields per docs/serial.md, checksums re-derived
# by xor_hex() and by pynmea2 below.
GOLDEN = [
    (pose(), 42, b"$PCEIL,42,12345,A,1.500,-0.250,-30.00,0.90,lights*11\r\n"),
    (pose(t_ns=5_000_000_000, method="corridor", x_m=None, y_m=0.125,
          yaw_rad=math.radians(1.5), quality=0.5), 65535,
     b"$PCEIL,65535,5000,A,,0.125,1.50,0.50,corridor*12\r\n"),
    (Failure(t_ns=7_000_000, method="lights", reason="too_few_lights"), 3,
     b"$PCEIL,3,7,V,,,,,lights*0C\r\n"),
]


@pytest.mark.parametrize("est, seq, expected", GOLDEN)
def test_encode_pose_golden(est, seq, expected):
    out = nmea.encode_pose(est, seq)
    assert out == expected
    body = out[1:out.index(b"*")]
    assert out[-4:-2].decode() == xor_hex(body)


def test_encode_status_golden():
    out = nmea.encode_status(9, 60_000, faulted=True, reason="camera_lost")
    assert out == b"$PCEIS,9,60000,F,camera_lost,*6B\r\n"
    assert nmea.encode_status(3, 1000, reason="too_few_lines", age_ms=2500) == \
        b"$PCEIS,3,1000,V,too_few_lines,2500*7E\r\n"


@pytest.mark.parametrize("est, seq, expected", GOLDEN)
def test_pynmea2_parses_pose(est, seq, expected):
    msg = pynmea2.parse(expected.decode("ascii").strip())  # checks the checksum
    assert isinstance(msg, pynmea2.ProprietarySentence)
    assert msg.manufacturer == "CEI"
    fields = msg.data
    assert fields[0] == "L"
    assert int(fields[1]) == seq
    assert int(fields[2]) == est.t_ns // 1_000_000
    if est:
        assert fields[3] == "A"
        assert fields[4] == ("" if est.x_m is None else f"{est.x_m:.3f}")
        assert float(fields[5]) == pytest.approx(est.y_m, abs=5e-4)
        assert float(fields[6]) == pytest.approx(est.yaw_deg, abs=5e-3)
        assert float(fields[7]) == pytest.approx(est.quality, abs=5e-3)
    else:
        assert fields[3:8] == ["V", "", "", "", ""]
    assert fields[8] == est.method


def test_pynmea2_parses_status():
    text = nmea.encode_status(70000, 2**32 + 5, reason="blank_frame", age_ms=10**9)
    msg = pynmea2.parse(text.decode().strip())
    assert isinstance(msg, pynmea2.ProprietarySentence)
    assert msg.data == ["S", str(70000 % 65536), "5", "V", "blank_frame", "9999999"]


def test_length_limit_extreme_values():
    worst = pose(t_ns=(2**32 - 1) * 1_000_000, x_m=-99999.999, y_m=-99999.999,
                 yaw_rad=math.radians(-179.994), quality=1.0, method="paper-corridor")
    out = nmea.encode_pose(worst, 65535)
    assert len(out) <= nmea.MAX_SENTENCE_LEN
    assert b",A," in out and b"-99999.999,-99999.999,-179.99," in out
    long_name = nmea.encode_pose(pose(method="a-very-long-method-name-indeed"), 65535)
    assert len(long_name) <= nmea.MAX_SENTENCE_LEN
    assert nmea.decode(long_name).method == "a-very-long-me"
    status = nmea.encode_status(65535, 2**32 - 1, faulted=True, reason="x" * 200, age_ms=10**12)
    assert len(status) <= nmea.MAX_SENTENCE_LEN


def test_length_limit_random_sweep():
    rng = np.random.default_rng(7)
    for _ in range(300):
        est = pose(t_ns=int(rng.integers(0, 2**62)), x_m=float(rng.uniform(-2e5, 2e5)),
                   y_m=float(rng.uniform(-2e5, 2e5)), yaw_rad=float(rng.uniform(-50, 50)),
                   quality=float(rng.uniform(-2, 2)))
        out = nmea.encode_pose(est, int(rng.integers(0, 2**40)))
        assert len(out) <= nmea.MAX_SENTENCE_LEN
        nmea.decode(out)  # valid


@pytest.mark.parametrize("bad", [
    dict(x_m=100000.0), dict(y_m=-1e6), dict(x_m=float("nan")), dict(y_m=float("inf")),
    dict(yaw_rad=float("nan")), dict(x_m=None, y_m=None),
])
def test_unsendable_pose_is_sent_as_void(bad):
    out = nmea.decode(nmea.encode_pose(pose(**bad), 1))
    assert not out.valid and out.x_m is None and out.yaw_deg is None


def test_fields_are_normalised():
    d = nmea.decode(nmea.encode_pose(pose(yaw_rad=math.radians(270.0)), 0))
    assert d.yaw_deg == -90.0
    d = nmea.decode(nmea.encode_pose(pose(yaw_rad=math.radians(179.999)), 0))
    assert d.yaw_deg == -180.0  # [-180, 180): rounding never gives 180.00
    out = nmea.encode_pose(pose(x_m=-0.0001, quality=1.7), 0)
    assert b",0.000," in out and b",1.00," in out
    assert nmea.decode(nmea.encode_pose(pose(quality=-0.2), 0)).quality == 0.0
    out = nmea.encode_pose(pose(method="a,b*c$d"), 0)
    assert nmea.decode(out).method == "a_b_c_d"


def test_t_ms_and_seq_wrap():
    d = nmea.decode(nmea.encode_pose(pose(t_ns=(2**32 + 17) * 1_000_000), 65536 + 4))
    assert (d.seq, d.t_ms) == (4, 17)


def test_decode_round_trip():
    est = pose(x_m=-12.3456, y_m=7.0004, yaw_rad=math.radians(123.456), quality=0.333)
    d = nmea.decode(nmea.encode_pose(est, 5))
    assert d == nmea.NmeaPose(5, 12345, True, -12.346, 7.0, 123.46, 0.33, "lights")
    s = nmea.decode(nmea.encode_status(6, 99, faulted=False, reason="ambiguous", age_ms=12))
    assert s == nmea.NmeaStatus(6, 99, False, "ambiguous", 12)


@pytest.mark.parametrize("text, words", [
    ("$PCEIL,1,2,A,1.000,,3.00,0.50,lights*00", "checksum"),
    ("PCEIL,1,2,A,1.000,,3.00,0.50,lights", "not an NMEA"),
    ("$GPGGA,1*" + xor_hex(b"GPGGA,1"), "unknown sentence"),
    ("$PCEIL,1,2,Q,,,,,lights*" + xor_hex(b"PCEIL,1,2,Q,,,,,lights"), "bad field"),
    ("$PCEIL,x,2,A,,,,,lights*" + xor_hex(b"PCEIL,x,2,A,,,,,lights"), "bad field"),
    ("$PCEIS," + "9" * 80 + "*00", "exceeds 82"),
])
def test_decode_rejects(text, words):
    with pytest.raises(LinkError, match=words):
        nmea.decode(text)


def test_split_sentences_keeps_partial_rest():
    lines, rest = nmea.split_sentences(b"$A*00\r\n\r\n$B*01\r\n$PCE")
    assert lines == [b"$A*00", b"$B*01"] and rest == b"$PCE"


def test_checksum_matches_bytewise_xor():
    rng = np.random.default_rng(4)
    for n in range(0, 90):  # every length modulo the 8-byte words
        body = bytes(rng.integers(32, 127, n, dtype=np.uint8)).decode("ascii")
        assert nmea.checksum(body) == xor_hex(body.encode("ascii"))


@pytest.mark.parametrize("value, decimals, text", [
    (-0.0, 3, "0.000"), (-0.0004, 3, "0.000"), (-0.0005, 3, "-0.001"), (-0.004, 2, "0.00"),
    (-0.006, 2, "-0.01"), (0.0004, 3, "0.000"), (-10.0, 2, "-10.00")])
def test_fixed_point_has_no_negative_zero(value, decimals, text):
    assert nmea._fmt_fixed(value, decimals) == text
