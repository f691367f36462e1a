"""The transport: fake, file and serial (over a pseudo-terminal) links."""

from __future__ import annotations

import math
import os
import threading

import pynmea2
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from ceilkit.runtime.errors import CeilkitError, LinkError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.link import FileLink, MemoryLink, SerialLink, mavlink, nmea, open_link

S = 1_000_000_000


class Clock:
    """A settable link clock (integer ns)."""

    def __init__(self) -> None:
        self.t = 0

    def __call__(self) -> int:
        return self.t


def pose(k: int, **kw) -> PoseEstimate:
    base = dict(t_ns=k * 33_000_000, method="lights", x_m=1.0 + 0.01 * k, y_m=2.0,
                yaw_rad=0.1, quality=0.8)
    base.update(kw)
    return PoseEstimate(**base)


def fail(k: int) -> Failure:
    return Failure(t_ns=k * 33_000_000, method="lights", reason="too_few_lights")


def sentences(data: bytes) -> list:
    lines = data.split(b"\r\n")
    assert lines[-1] == b"", "a sentence was cut"
    return [nmea.decode(ln) for ln in lines[:-1]]


# ------------------------------------------------------------------ memory fake


def test_memory_link_counts_and_encodes():
    clock = Clock()
    with MemoryLink("nmea", clock_ns=clock) as link:
        link.send(pose(0))
        link.send(fail(1))
        assert link.counters.sent == 2 and link.counters.dropped == 0
    assert bytes(link.written) == nmea.encode_pose(pose(0), 0) + nmea.encode_pose(fail(1), 1)
    assert link.state == "closed"
    with pytest.raises(LinkError, match="closed"):
        link.send(pose(2))


def test_backed_up_peer_drops_whole_stale_messages():
    clock = Clock()
    link = MemoryLink("nmea", capacity=100, max_buffer_bytes=300, clock_ns=clock)
    with link:
        for k in range(200):
            link.send(pose(k))
            clock.t += S // 30
        c = link.counters
        assert c.dropped > 0 and link.pending_bytes <= 300
        got = link.drain()
        while link.pending_bytes:
            link.poll()
            got += link.drain()
    decoded = sentences(bytes(link.written))
    assert got == bytes(link.written)
    c = link.counters
    assert len(decoded) == c.sent and c.sent + c.dropped == 200
    seqs = [d.seq for d in decoded]
    assert seqs == sorted(seqs) and seqs[-1] == 199  # the newest pose made it out


def test_status_at_1hz_while_no_valid_pose():
    clock = Clock()
    with MemoryLink("nmea", clock_ns=clock) as link:
        for k in range(30):  # 1 s of valid poses at 30 Hz: no status
            link.send(pose(k))
            clock.t += S // 30
        for k in range(30, 30 + 150):  # 5 s of failures
            link.send(fail(k))
            clock.t += S // 30
    out = sentences(bytes(link.written))
    status = [d for d in out if isinstance(d, nmea.NmeaStatus)]
    assert 4 <= len(status) <= 5
    assert all(s.reason == "too_few_lights" and not s.faulted for s in status)
    assert status[0].age_ms >= 1000
    assert all(b.t_ms - a.t_ms >= 1000 for a, b in zip(status, status[1:], strict=False))


def test_status_without_estimates_and_while_faulted():
    clock = Clock()
    with MemoryLink("nmea", clock_ns=clock) as link:
        link.poll()
        assert bytes(link.written) == b""  # the first second after opening is start-up
        clock.t += S
        link.poll()
        link.set_fault("camera_lost")
        for _ in range(3):
            clock.t += S
            link.poll()
    status = sentences(bytes(link.written))
    assert status[0].reason == "no_estimate" and status[0].age_ms is None
    assert status[0].t_ms == 1000
    assert [s.faulted for s in status] == [False, True, True, True, True]
    assert status[-1].reason == "camera_lost"


def test_heartbeat_1hz_stops_while_faulted():
    clock = Clock()
    with MemoryLink("mavlink", clock_ns=clock, sysid=5) as link:
        for k in range(90):  # 3 s
            link.send(pose(k))
            clock.t += S // 30
        link.set_fault("camera_lost")
        for _ in range(3):
            clock.t += S
            link.poll()
        link.set_fault(None)
        link.poll()
        link.send(fail(100))
    msgs = mavlink2.MAVLink(None).parse_buffer(bytes(link.written))
    types = [m.get_type() for m in msgs]
    assert types.count("VISION_POSITION_ESTIMATE") == 90
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert len(hb) == 3  # t = 1, 2 s (none in the first second), then after the fault clears
    assert types[-1] == "HEARTBEAT"
    assert hb[0].type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb[0].get_srcComponent() == mavlink2.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    assert hb[-1].system_status == mavlink2.MAV_STATE_STANDBY
    assert hb[1].system_status == mavlink2.MAV_STATE_ACTIVE
    assert link.counters.skipped == 1  # the failure


def test_unplug_is_a_state_and_reopen_backs_off():
    clock = Clock()
    link = MemoryLink("nmea", clock_ns=clock, backoff_s=(0.5, 2.0))
    with link:
        link.send(pose(0))
        link.unplug()
        link.send(pose(1))
        assert link.state == "disconnected"
        attempts = []
        for _ in range(60):  # 6 s in 0.1 s steps
            clock.t += S // 10
            before = link._next_attempt_ns
            link.poll()
            if link._next_attempt_ns != before:
                attempts.append(clock.t)
        gaps = [b - a for a, b in zip(attempts, attempts[1:], strict=False)]
        assert gaps[:3] == [S, 2 * S, 2 * S]  # 0.5, then doubling, capped at 2 s
        link.replug()
        clock.t += 2 * S
        link.poll()
        assert link.state == "connected" and link.counters.reconnects == 1
        link.send(pose(2))
    d = sentences(bytes(link.written))
    assert [s.t_ms for s in d if isinstance(s, nmea.NmeaPose)][-1] == pose(2).t_ns // 10**6
    assert link.counters.dropped >= 1


def test_received_messages_go_to_callback_and_log(tmp_path):
    got = []
    log = tmp_path / "rx.log"
    with MemoryLink("nmea", on_receive=got.append, rx_log=log, clock_ns=Clock()) as link:
        link.feed(b"$PXYZ,ok*00\r\n$PXYZ,par")
        link.poll()
        link.feed(b"tial*01\r\n")
        link.poll()
    assert [r.raw for r in got] == [b"$PXYZ,ok*00", b"$PXYZ,partial*01"]
    assert log.read_text().splitlines()[1].endswith("$PXYZ,partial*01")
    assert link.counters.received == 2


def test_bad_options():
    with pytest.raises(LinkError, match="unknown link protocol"):
        MemoryLink("ubx")
    with pytest.raises(LinkError, match="system id"):
        MemoryLink("mavlink", sysid=0)
    with pytest.raises(LinkError, match="takes no options"):
        MemoryLink("nmea", sysid=3)
    with pytest.raises(LinkError, match="max_buffer_bytes"):
        MemoryLink("nmea", max_buffer_bytes=10)


# ------------------------------------------------------------------ file


def test_file_link_writes_wire_bytes(tmp_path):
    path = tmp_path / "poses.nmea"
    ests = [pose(0), fail(1), pose(2, x_m=None)]
    with FileLink(path, "nmea", periodic=False) as link:
        for e in ests:
            link.send(e)
    assert path.read_bytes() == b"".join(nmea.encode_pose(e, k) for k, e in enumerate(ests))


def test_file_link_bad_path(tmp_path):
    with pytest.raises(LinkError, match="cannot open link file"):
        FileLink(tmp_path / "no" / "such" / "dir.bin").open()


# ------------------------------------------------------------------ serial over a pty


class Pty:
    """A pseudo-terminal standing in for a USB-serial adapter, reached by a stable
    symlink (as /dev/serial/by-id/... is): unplug closes it, plug makes a new one."""

    def __init__(self, link_path) -> None:
        self.path = link_path
        self.master = -1
        self.slave = -1
        self.plug()

    def plug(self) -> None:
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        tmp = self.path.with_suffix(".new")
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.path)

    def unplug(self) -> None:
        os.close(self.master)
        os.close(self.slave)

    def read(self) -> bytes:
        out = b""
        while True:
            try:
                chunk = os.read(self.master, 65536)
            except BlockingIOError:
                return out
            if not chunk:
                return out
            out += chunk


@pytest.fixture
def pty(tmp_path):
    p = Pty(tmp_path / "ttyUSB0")
    yield p
    for fd in (p.master, p.slave):
        try:
            os.close(fd)
        except OSError:
            pass


def test_serial_link_over_pty_nmea(pty):
    clock = Clock()
    with SerialLink(pty.path, 115200, "nmea", clock_ns=clock, service_interval_s=None) as link:
        link.send(pose(3))
        link.send(PoseEstimate(t_ns=1, method="corridor", x_m=None, y_m=-0.5, yaw_rad=0.0,
                               quality=0.5))
        data = pty.read()
    lines = data.decode().split("\r\n")
    msg = pynmea2.parse(lines[0])
    assert isinstance(msg, pynmea2.ProprietarySentence)
    assert msg.data[:6] == ["L", "0", "99", "A", "1.030", "2.000"]
    assert pynmea2.parse(lines[1]).data[4] == ""  # the corridor has no x


def test_serial_link_over_pty_mavlink_reads_back(pty):
    got = []
    with SerialLink(pty.path, 57600, "mavlink", clock_ns=Clock(), service_interval_s=None,
                    on_receive=got.append) as link:
        link.send(pose(1))
        ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        os.write(pty.master, ap.heartbeat_encode(10, 3, 0, 0, 4).pack(ap))
        link.clock_ns.t += S
        link.poll()
        data = pty.read()
    msgs = mavlink2.MAVLink(None).parse_buffer(data)
    assert [m.get_type() for m in msgs] == ["VISION_POSITION_ESTIMATE", "HEARTBEAT"]
    assert msgs[0].x == pytest.approx(1.01) and msgs[0].y == pytest.approx(-2.0)
    assert [r.text.split()[0] for r in got] == ["HEARTBEAT"]


def test_serial_link_backed_up_never_blocks_or_tears(pty):
    clock = Clock()
    with SerialLink(pty.path, 115200, "mavlink", clock_ns=clock, service_interval_s=None,
                    max_buffer_bytes=1024) as link:
        n = 2000  # ~260 kB: far more than the pty buffers while nobody reads
        for k in range(n):
            link.send(pose(k))
            clock.t += S // 30
        assert link.counters.dropped > 0 and link.pending_bytes <= 1024
        data = pty.read()
        while link.pending_bytes:
            link.poll()
            data += pty.read()
    frames, rest = mavlink.split_frames(data)
    assert rest == b""
    assert all(f.crc_ok for f in frames)
    # every byte on the wire belongs to a whole, valid frame
    assert sum(len(f.raw) for f in frames) == len(data)
    c = link.counters
    assert len(frames) == c.sent and c.bytes_sent == len(data)
    poses = [f for f in frames if f.msg_id == mavlink.MSG_ID_VISION_POSITION_ESTIMATE]
    assert len(poses) + c.dropped + c.skipped >= n - 1
    assert mavlink.unpack_vision_position_estimate(poses[-1])["usec"] == pose(n - 1).t_ns // 1000


def test_serial_link_survives_unplug_and_replug(pty):
    clock = Clock()
    with SerialLink(pty.path, 115200, "nmea", clock_ns=clock, service_interval_s=None,
                    backoff_s=(0.5, 4.0)) as link:
        link.send(pose(0))
        assert sentences(pty.read())[0].seq == 0
        pty.unplug()
        for k in range(1, 10):  # the pipeline keeps running
            link.send(pose(k))
            clock.t += S // 10
        assert link.state == "disconnected" and link.counters.dropped >= 1
        pty.plug()
        for k in range(10, 40):
            link.send(pose(k))
            clock.t += S // 10
        assert link.state == "connected" and link.counters.reconnects == 1
        after = sentences(pty.read())
    assert after and after[-1].seq == 39
    assert all(isinstance(d, nmea.NmeaPose) for d in after)


def test_service_thread_sends_status_without_the_pipeline(pty):
    clock = Clock()
    seen = threading.Event()
    clock.t = S  # past the start-up second
    with SerialLink(pty.path, 115200, "nmea", clock_ns=clock, service_interval_s=0.01):
        clock.t = 2 * S
        data = b""
        for _ in range(500):  # bounded wait for the thread's first status sentence
            data += pty.read()
            if b"\r\n" in data:
                seen.set()
                break
            threading.Event().wait(0.01)
    assert seen.is_set()
    assert isinstance(sentences(data.split(b"\r\n")[0] + b"\r\n")[0], nmea.NmeaStatus)


def test_unopenable_ports_raise_link_error(tmp_path, pty):
    with pytest.raises(LinkError, match="no such device") as info:
        SerialLink(tmp_path / "ttyNOPE", 115200).open()
    assert isinstance(info.value, CeilkitError) and "\n" not in str(info.value)
    plain = tmp_path / "plain.txt"
    plain.write_text("not a tty")
    with pytest.raises(LinkError, match="cannot open serial port"):
        SerialLink(plain, 115200).open()
    with SerialLink(pty.path, 115200, service_interval_s=None):
        with pytest.raises(LinkError, match="busy"):
            SerialLink(pty.path, 115200, service_interval_s=None).open()
    with pytest.raises(LinkError, match="baud"):
        SerialLink(pty.path, 0)


def test_yaw_nan_pose_never_reaches_the_wire(pty):
    with SerialLink(pty.path, 115200, "mavlink", clock_ns=Clock(),
                    service_interval_s=None) as link:
        link.clock_ns.t += S
        link.send(pose(0, yaw_rad=math.nan))
        data = pty.read()
    assert [f.name for f in mavlink.iter_frames(data)] == ["HEARTBEAT"]


def test_pipeline_sink_protocol_bumps_reset_counter():
    with MemoryLink("mavlink", clock_ns=Clock()) as link:
        link.send(pose(0), False, 0)
        link.send(pose(1), True, 33_000_000)
        link.send(pose(2), False, 66_000_000)
    msgs = [m for m in mavlink2.MAVLink(None).parse_buffer(bytes(link.written))
            if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert [m.reset_counter for m in msgs] == [0, 1, 1]


def test_open_link_chooses_stdout_or_port(tmp_path, pty, capfdbinary):
    with open_link("-", "nmea", service_interval_s=None) as link:
        assert isinstance(link, FileLink)
        link.send(pose(0))
    assert capfdbinary.readouterr().out.startswith(b"$PCEIL,0,0,A,")
    with open_link(pty.path, "mavlink", 57600, system_id=9, component_id=197,
                   service_interval_s=None, clock_ns=Clock()) as link:
        assert isinstance(link, SerialLink) and link.baud == 57600
        link.send(pose(0))
        msgs = mavlink2.MAVLink(None).parse_buffer(pty.read())
    assert {m.get_srcSystem() for m in msgs} == {9}
    with pytest.raises(LinkError, match="cannot open serial port"):
        open_link(tmp_path / "ttyACM9").open()


def test_service_thread_answers_timesync_over_pty(pty):
    ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    with SerialLink(pty.path, 115200, "mavlink", service_interval_s=0.05) as link:
        os.write(pty.master, ap.timesync_encode(0, 123_456).pack(ap))
        data = b""
        for _ in range(300):  # bounded wait: the thread wakes on input
            data += pty.read()
            if any(m.get_type() == "TIMESYNC" for m in
                   mavlink2.MAVLink(None).parse_buffer(data) or []):
                break
            threading.Event().wait(0.01)
        now = link.clock_ns()
    (msg,) = [m for m in mavlink2.MAVLink(None).parse_buffer(data) if m.get_type() == "TIMESYNC"]
    assert msg.ts1 == 123_456 and 0 < msg.tc1 <= now  # our monotonic clock, ns
    assert link.protocol.timesyncs == 1 and link.counters.received == 1


def test_open_link_writes_a_regular_file(tmp_path):
    out = tmp_path / "poses.nmea"
    out.write_bytes(b"old content\r\n")
    with open_link(out, "nmea", clock_ns=Clock()) as link:
        assert isinstance(link, FileLink)
        link.send(pose(0))
    assert out.read_bytes() == nmea.encode_pose(pose(0), 0)  # truncated, then the wire bytes
    with open_link(out, "mavlink", unobserved="nan", clock_ns=Clock()) as link:
        link.send(pose(1, x_m=None))
    (msg,) = mavlink2.MAVLink(None).parse_buffer(out.read_bytes())
    assert math.isnan(msg.x) and msg.y == pytest.approx(-2.0)
    with pytest.raises(LinkError, match="unobserved"):
        open_link(out, "mavlink", unobserved="zero")
    with pytest.raises(LinkError, match="cannot open link file"):
        open_link(tmp_path / "no" / "dir" / "x.nmea").open()


def test_is_serial_path(tmp_path, pty):
    from ceilkit.runtime.io.link.transport import is_serial_path

    assert is_serial_path("/dev/ttyUSB0") and is_serial_path(tmp_path / "ttyV0")
    (tmp_path / "port").symlink_to(os.ttyname(pty.slave))
    assert is_serial_path(tmp_path / "port")  # a symlink to a character device
    assert not is_serial_path(tmp_path / "poses.nmea")


# ------------------------------------------------------------------ new protocols


class _Mount:
    x_m, y_m, z_m = 0.3, 0.1, 0.8


class _Rig:
    mount = _Mount()


class _Origin:
    lat_deg, lon_deg, alt_m, heading_deg = 52.1, 4.3, 12.0, 33.3


class _Site:
    origin = _Origin()


def test_every_protocol_name_opens(tmp_path):
    from ceilkit.runtime.io.link import PROTOCOLS

    assert set(PROTOCOLS) == {"nmea", "mavlink", "mavlink-odometry", "nmea-gps"}
    for name in PROTOCOLS:
        out = tmp_path / f"{name}.bin"
        with open_link(out, name, rig=_Rig(), site=_Site(), periodic=False) as link:
            assert link.protocol.name == name
            link.send(pose(1))
        assert out.stat().st_size > 0


def test_mavlink_odometry_link_sends_odometry_and_the_site_origin(pty):
    with open_link(pty.path, "mavlink-odometry", 115200, rig=_Rig(), site=_Site(),
                   clock_ns=Clock(), service_interval_s=None) as link:
        link.send(pose(1), relocalized=True)
        link.send(fail(2))
        link.clock_ns.t = 2 * S
        link.poll()
        msgs = mavlink2.MAVLink(None).parse_buffer(pty.read())
    kinds = [m.get_type() for m in msgs]
    assert kinds == ["ODOMETRY", "HEARTBEAT", "SET_GPS_GLOBAL_ORIGIN"]
    odo, _, origin = msgs
    assert odo.reset_counter == 1 and odo.z == pytest.approx(-0.8)
    assert odo.x == pytest.approx(1.01 + math.cos(0.1) * 0.3 - math.sin(0.1) * 0.1, abs=1e-6)
    assert origin.latitude == round(52.1e7) and origin.altitude == 12000
    assert link.counters.skipped == 1  # the failure: no ODOMETRY


def test_mavlink_odometry_needs_the_rig(tmp_path):
    with pytest.raises(LinkError, match="rig"):
        open_link(tmp_path / "x.bin", "mavlink-odometry")


def test_explicit_ekf_origin_wins_over_the_sites(tmp_path):
    link = open_link(tmp_path / "x.bin", "mavlink-odometry", rig=_Rig(), site=_Site(),
                     origin=mavlink.GeoOrigin(1.0, 2.0, 3.0))
    assert link.protocol.origin == mavlink.GeoOrigin(1.0, 2.0, 3.0)
    plain = open_link(tmp_path / "y.bin", "mavlink", site=_Site())
    assert plain.protocol.origin is None  # mavlink keeps its default: only --ekf-origin


def test_nmea_gps_over_a_serial_pty(pty):
    with open_link(pty.path, "nmea-gps", 115200, site=_Site(), clock_ns=Clock(),
                   service_interval_s=None) as link:
        link.send(pose(1))
        link.send(fail(2))
        data = pty.read()
    parsed = [pynmea2.parse(ln, check=True) for ln in data.decode().split("\r\n")[:-1]]
    assert [m.sentence_type for m in parsed] == ["RMC", "GGA", "GST", "HDT"] * 2
    assert parsed[0].status == "A" and parsed[4].status == "V"
