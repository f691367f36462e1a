"""GPS sentences: byte layout, pynmea2 parsing, positions back to W, and a real gpsd."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import socket
import subprocess
import time
import tty
from datetime import datetime, timezone

import numpy as np
import pynmea2
import pytest

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane
from ceilkit.runtime.io.link import MemoryLink, make_protocol, nmea_gps, open_link
from ceilkit.runtime.io.link.nmea import MAX_SENTENCE_LEN

PLANE = LocalTangentPlane(52.1, 4.3, 12.0, heading_deg=33.3)
UTC0_NS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z
COV = np.array([[4e-4, 1e-4, 0.0], [1e-4, 1e-4, 0.0], [0.0, 0.0, 1e-5]])
STEP_NS = 200_000_000


def pose(**kw) -> PoseEstimate:
    base = dict(t_ns=0, method="lights", x_m=12.345, y_m=-6.5, yaw_rad=0.4, quality=0.9,
                cov=COV)
    base.update(kw)
    return PoseEstimate(**base)


def parse_all(data: bytes) -> list:
    lines = data.decode("ascii").split("\r\n")
    assert lines[-1] == ""
    for ln in lines[:-1]:
        assert len(ln) + 2 <= MAX_SENTENCE_LEN
    return [pynmea2.parse(ln, check=True) for ln in lines[:-1]]


def expected_ellipse(cov_xy, heading_deg):
    """Independent: rotate W's (x, y) covariance to (east, north) and take its axes."""
    h = math.radians(heading_deg)
    x_en = np.array([math.sin(h), math.cos(h)])     # W's +x in (east, north)
    y_en = np.array([-math.cos(h), math.sin(h)])    # W's +y, 90 deg counter-clockwise of it
    R = np.column_stack([x_en, y_en])
    c = R @ cov_xy @ R.T
    vals, vecs = np.linalg.eigh(c)
    orient = math.degrees(math.atan2(vecs[0, 1], vecs[1, 1])) % 180.0
    return math.sqrt(vals[1]), math.sqrt(vals[0]), orient, math.sqrt(c[1, 1]), math.sqrt(c[0, 0])


def world_of(msg) -> np.ndarray:
    return PLANE.world_from_geodetic(msg.latitude, msg.longitude, PLANE.alt_m)


# -------------------------------------------------------------------------- encoders


def test_group_is_rmc_gga_gst_hdt_and_pynmea2_parses_each():
    rmc, gga, gst, hdt = parse_all(nmea_gps.encode_fix(nmea_gps.fix_of(pose(), PLANE),
                                                       UTC0_NS + 450_000_000))
    assert [m.sentence_type for m in (rmc, gga, gst, hdt)] == ["RMC", "GGA", "GST", "HDT"]
    assert all(m.talker == "GP" for m in (rmc, gga, gst, hdt))
    assert rmc.status == "A" and rmc.mode_indicator == "A"
    assert rmc.datestamp.isoformat() == "2023-11-14"
    assert rmc.timestamp.isoformat() == gga.timestamp.isoformat() == "22:13:20.450000+00:00"
    assert gga.gps_qual == 1 and gga.num_sats == "12" and gga.horizontal_dil == "1.0"
    assert gga.altitude == pytest.approx(12.0, abs=1e-3)
    assert hdt.hdg_true == "T"


def test_position_maps_back_to_the_pose_within_0_15_mm():
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(200):
        x, y = rng.uniform(-150, 150, size=2)
        rmc, gga, _, _ = parse_all(nmea_gps.encode_fix(
            nmea_gps.fix_of(pose(x_m=float(x), y_m=float(y)), PLANE), UTC0_NS))
        for msg in (rmc, gga):
            worst = max(worst, float(np.hypot(*(world_of(msg)[:2] - (x, y)))))
    assert worst < 1.5e-4  # 7 decimals of minutes: <= 0.093 mm (lat), 0.057 mm (lon)


def test_heading_is_true_heading_clockwise_from_north():
    for yaw_deg, expect in [(0.0, 33.3), (90.0, 303.3), (-90.0, 123.3), (33.3, 0.0),
                            (34.0, 359.3)]:
        *_, hdt = parse_all(nmea_gps.encode_fix(nmea_gps.fix_of(
            pose(yaw_rad=math.radians(yaw_deg)), PLANE), UTC0_NS))
        assert float(hdt.heading) == pytest.approx(expect, abs=1e-3)
        assert 0.0 <= float(hdt.heading) < 360.0


def test_gst_is_the_pose_covariance_in_east_north():
    _, _, gst, _ = parse_all(nmea_gps.encode_fix(nmea_gps.fix_of(pose(), PLANE), UTC0_NS))
    major, minor, orient, s_lat, s_lon = expected_ellipse(COV[:2, :2], PLANE.heading_deg)
    assert gst.std_dev_major == pytest.approx(major, abs=1e-4)
    assert gst.std_dev_minor == pytest.approx(minor, abs=1e-4)
    assert gst.orientation == pytest.approx(orient, abs=1e-4)
    assert gst.std_dev_latitude == pytest.approx(s_lat, abs=1e-4)
    assert gst.std_dev_longitude == pytest.approx(s_lon, abs=1e-4)
    assert gst.rms is None and gst.std_dev_altitude is None


def test_ellipse_of_axis_aligned_and_rotated():
    e = nmea_gps.ellipse_of(np.diag([1.0, 4.0]))  # larger north: major along north
    assert (e.semi_major_m, e.semi_minor_m, e.orientation_deg) == (2.0, 1.0, 0.0)
    a = math.radians(30.0)
    v = np.array([math.sin(a), math.cos(a)])   # 30 deg east of north
    c = 9.0 * np.outer(v, v) + 1.0 * np.outer([v[1], -v[0]], [v[1], -v[0]])
    e = nmea_gps.ellipse_of(c)
    assert e.semi_major_m == pytest.approx(3.0) and e.orientation_deg == pytest.approx(30.0)
    assert nmea_gps.ellipse_of(np.array([[np.inf, 0], [0, 1.0]])) is None


@pytest.mark.parametrize("est", [
    Failure(t_ns=0, method="lights", reason="no_lights"),
    pose(x_m=None, method="corridor"),
    pose(y_m=float("nan")),
])
def test_no_fix_says_invalid_and_carries_no_position(est):
    rmc, gga, gst, hdt = parse_all(nmea_gps.encode_fix(nmea_gps.fix_of(est, PLANE), UTC0_NS))
    assert rmc.status == "V" and rmc.mode_indicator == "N" and rmc.lat == "" and rmc.lon == ""
    assert gga.gps_qual == 0 and gga.lat == "" and gga.altitude is None
    assert gst.std_dev_major is None
    if isinstance(est, Failure):
        assert hdt.heading is None
    else:  # a corridor pose still has its heading
        assert float(hdt.heading) == pytest.approx(PLANE.heading_from_yaw(0.4), abs=1e-3)


def test_no_covariance_leaves_gst_empty_but_the_fix_valid():
    rmc, gga, gst, _ = parse_all(nmea_gps.encode_fix(nmea_gps.fix_of(pose(cov=None), PLANE),
                                                     UTC0_NS))
    assert rmc.status == "A" and gga.gps_qual == 1 and gst.std_dev_major is None


def test_extremes_fit_82_characters_and_hemispheres():
    plane = LocalTangentPlane(-89.9, -179.99, -99999.0, 359.9)
    fix = nmea_gps.fix_of(pose(x_m=0.0, y_m=0.0, cov=np.diag([1e12, 1e12, 1.0])), plane)
    rmc, gga, gst, _ = parse_all(nmea_gps.encode_fix(fix, UTC0_NS, satellites=99, hdop=99.9))
    assert (gga.lat_dir, gga.lon_dir) == ("S", "W")
    assert gga.latitude == pytest.approx(-89.9) and gga.longitude == pytest.approx(-179.99)
    assert gst.std_dev_major == 99999.0


def test_minutes_never_round_to_sixty():
    text, hemi = nmea_gps._angle(51.99999999999, 2, "NS")
    assert (text, hemi) == ("5200.0000000", "N")


# -------------------------------------------------------------------------- protocol


def test_protocol_stamps_capture_time_in_utc_and_reports_validity():
    proto = make_protocol("nmea-gps", plane=PLANE, utc_ns=lambda: UTC0_NS + 10**9,
                          capture_clock_ns=lambda: 5 * 10**9)
    msg, valid = proto.pose(pose(t_ns=5 * 10**9 - 250_000_000))
    assert valid
    rmc = parse_all(msg)[0]
    assert rmc.timestamp.isoformat() == "22:13:20.750000+00:00"  # now - 250 ms
    msg, valid = proto.pose(pose(t_ns=0))  # 5 s old: still its capture time
    assert parse_all(msg)[0].timestamp.isoformat() == "22:13:16+00:00"
    msg, valid = proto.pose(pose(t_ns=10**15))  # not this clock (a replay): now
    assert parse_all(msg)[0].timestamp.isoformat() == "22:13:21+00:00"
    assert proto.pose(Failure(0, "lights", "no_lights"))[1] is False


def test_stamps_of_another_clock_keep_their_spacing():
    """Frames of a replay or the simulator (stamps not of the capture clock) are stamped
    as far apart as their frames, whenever the fixes are sent: 33 ms frames sent 20 ms
    apart (an unpaced run) are 33 ms apart in RMC (centiseconds, truncated)."""
    now = [UTC0_NS]
    proto = make_protocol("nmea-gps", plane=PLANE, utc_ns=lambda: now[0],
                          capture_clock_ns=lambda: 10**18)
    stamps = []
    for k in range(4):
        now[0] = UTC0_NS + k * 20_000_000
        rmc = parse_all(proto.pose(pose(t_ns=k * 33_333_333))[0])[0]
        stamps.append(rmc.timestamp.isoformat())
    assert stamps == ["22:13:20+00:00", "22:13:20.030000+00:00", "22:13:20.060000+00:00",
                      "22:13:20.090000+00:00"]
    now[0] += 60 * 10**9      # a minute's pause: anchored again, at now
    rmc = parse_all(proto.pose(pose(t_ns=4 * 33_333_333))[0])[0]
    assert rmc.timestamp.isoformat() == "22:14:20.060000+00:00"


def test_link_sends_invalid_groups_once_a_second_without_a_pose():
    clock = [0]
    link = MemoryLink("nmea-gps", plane=PLANE, clock_ns=lambda: clock[0],
                      utc_ns=lambda: UTC0_NS + clock[0], capture_clock_ns=lambda: clock[0])
    with link:
        link.send(pose(t_ns=0))
        first = parse_all(link.drain())
        assert first[0].status == "A"
        clock[0] = 1_500_000_000
        link.poll()
        later = parse_all(link.drain())
        assert [m.sentence_type for m in later] == ["RMC", "GGA", "GST", "HDT"]
        assert later[0].status == "V" and later[1].gps_qual == 0  # never the stale position
        assert link.counters.sent == 2


def test_open_link_needs_the_site_origin(tmp_path):
    class Site:
        origin = None

    with pytest.raises(LinkError, match="origin"):
        open_link(tmp_path / "out.nmea", "nmea-gps", site=Site())
    with pytest.raises(LinkError, match="origin"):
        make_protocol("nmea-gps")

    class Origin:
        lat_deg, lon_deg, alt_m, heading_deg = 52.1, 4.3, 12.0, 33.3

    Site.origin = Origin()
    out = tmp_path / "out.nmea"
    with open_link(out, "nmea-gps", site=Site(), periodic=False) as link:
        link.send(pose())
    rmc, gga, _, _ = parse_all(out.read_bytes())
    assert float(np.hypot(*(world_of(gga)[:2] - (12.345, -6.5)))) < 1e-4


# ------------------------------------------------------------------------- real gpsd


GPSD = shutil.which("gpsd")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gpsd_reports(text: str) -> list[dict]:
    """gpsd's JSON lines; gpsd 3.22 writes ATT with stray commas, read its fields by name."""
    out = []
    for line in text.splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            fields = dict(re.findall(r'"(class|time)":"([^"]*)"', line))
            for key, num in re.findall(r'"(heading)":(-?[0-9.]+)', line):
                fields[key] = float(num)
            out.append(fields)
    return out


def _t_ns(iso: str) -> int:
    dt = datetime.fromisoformat(iso.replace("Z", "+00:00"))
    return round(dt.timestamp() * 1000) * 1_000_000


@contextlib.contextmanager
def _gpsd_on_pty():
    master, slave = os.openpty()
    tty.setraw(slave)
    port = _free_port()
    proc = subprocess.Popen([GPSD, "-N", "-n", "-b", "-s", "115200", "-S", str(port),
                             os.ttyname(slave)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    client = None
    try:
        deadline = time.monotonic() + 10.0
        while client is None:
            try:
                client = socket.create_connection(("127.0.0.1", port), timeout=1.0)
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise
                time.sleep(0.05)
        client.sendall(b'?WATCH={"enable":true,"json":true};\n')
        client.settimeout(0.1)
        yield master, client
    finally:
        if client is not None:
            client.close()
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)


def _read_until(client, done, timeout_s: float = 10.0) -> str:
    data = b""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done(data):
        with contextlib.suppress(TimeoutError, socket.timeout):
            chunk = client.recv(65536)
            if not chunk:
                break
            data += chunk
    return data.decode("utf-8", "replace")


@pytest.mark.skipif(GPSD is None, reason="gpsd is not installed (Debian: apt-get install "
                    "gpsd gpsd-clients; .ci/run installs it)")
def test_gpsd_reads_the_stream_through_a_pty_and_maps_back_to_the_poses():
    rng = np.random.default_rng(14)
    poses = {}
    for k in range(24):
        if k == 10:
            est = Failure(t_ns=k * STEP_NS, method="lights", reason="no_lights")
        elif k == 11:
            est = pose(t_ns=k * STEP_NS, method="corridor", x_m=None, y_m=0.2, yaw_rad=1.0)
        else:
            a = rng.normal(size=(2, 2)) * 0.02
            cov = np.eye(3) * 1e-5
            cov[:2, :2] = a @ a.T + np.eye(2) * 1e-6
            est = pose(t_ns=k * STEP_NS, x_m=float(rng.uniform(-150, 150)),
                       y_m=float(rng.uniform(-150, 150)),
                       yaw_rad=float(rng.uniform(-math.pi, math.pi)), cov=cov)
        poses[UTC0_NS + k * STEP_NS] = est
    stamps = iter(poses)
    link = MemoryLink("nmea-gps", plane=PLANE, utc_ns=lambda: next(stamps),
                      capture_clock_ns=lambda: 10**18)  # stamps of another clock
    link.periodic_enabled = False  # one group per pose: every stamp is a pose's
    with _gpsd_on_pty() as (master, client), link:
        _read_until(client, lambda d: b'"class":"WATCH"' in d, 5.0)
        for est in poses.values():
            link.send(est)
            os.write(master, link.drain())
        last_utc = datetime.fromtimestamp(max(poses) / 1e9, tz=timezone.utc)
        last = f'"time":"{last_utc:%Y-%m-%dT%H:%M:%S.%f}'
        text = _read_until(client, lambda d: d.count(last[:-3].encode()) >= 3)
    reports = _gpsd_reports(text)
    tpv = {_t_ns(r["time"]): r for r in reports if r.get("class") == "TPV" and "time" in r}
    att = {_t_ns(r["time"]): r for r in reports if r.get("class") == "ATT" and "time" in r}
    gst = {_t_ns(r["time"]): r for r in reports if r.get("class") == "GST" and "time" in r}
    worst_m, worst_deg, worst_gst = 0.0, 0.0, 0.0
    for t, est in poses.items():
        fix = nmea_gps.fix_of(est, PLANE)
        if not fix.valid:
            assert t not in tpv or tpv[t].get("mode", 1) < 2 or "lat" not in tpv[t]
            continue
        r = tpv[t]
        assert r["mode"] >= 2
        back = PLANE.world_from_geodetic(r["lat"], r["lon"], PLANE.alt_m)
        worst_m = max(worst_m, float(np.hypot(back[0] - est.x_m, back[1] - est.y_m)))
        heading = PLANE.heading_from_yaw(est.yaw_rad)
        d = (att[t]["heading"] - heading + 180.0) % 360.0 - 180.0
        worst_deg = max(worst_deg, abs(d))
        major, minor, _, s_lat, s_lon = expected_ellipse(est.cov[:2, :2], PLANE.heading_deg)
        g = gst[t]
        worst_gst = max(worst_gst, abs(g["major"] - major), abs(g["minor"] - minor),
                        abs(g["lat"] - s_lat), abs(g["lon"] - s_lon))
    print(f"gpsd: {len(tpv)} TPV, worst position {worst_m * 1000:.3f} mm, heading "
          f"{worst_deg:.4f} deg, GST sigma {worst_gst * 1000:.2f} mm")
    assert worst_m < 1e-3
    assert worst_deg < 0.01
    assert worst_gst < 1e-3  # gpsd prints the sigmas with 3 decimals
