"""`ceilrun`: replay of fixture recordings, golden serial transcripts over a pty, live
runs on the simulator, and the errors a user can make."""

from __future__ import annotations

import os
import select
import threading

import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilrun import app
from ceilkit.runtime.io.link import mavlink
from ceilkit.runtime.io.recording import Recording, load_poses
from helpers import FIXTURES

GOLDEN = FIXTURES / "golden"
REGEN = os.environ.get("CEILKIT_REGEN_GOLDEN") == "1"  # the explicit switch


class PtyReader:
    """The controller's end of a pseudo-terminal; the slave's path is what ceilrun opens,
    exactly as it would open /dev/ttyUSB0."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self.data = bytearray()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.05)
            if r:
                try:
                    self.data += os.read(self.master, 4096)
                except OSError:
                    return

    def close(self) -> bytes:
        self._stop.set()
        self._t.join(2)
        os.close(self.master)
        os.close(self.slave)
        return bytes(self.data)


def _pose_transcript(protocol: str, data: bytes) -> bytes:
    """The pose messages of a transcript (the 1 Hz heartbeat/status messages depend on
    wall-clock timing and are left out)."""
    if protocol == "nmea":
        return b"".join(line + b"\n" for line in data.split(b"\n")
                        if line.startswith(b"$PCEIL,"))
    frames, _ = mavlink.split_frames(data)
    return b"".join(f.payload for f in frames if f.msg_id == 102)


def test_replay_writes_poses_and_reports_errors(tmp_path):
    res = CliRunner().invoke(app, ["replay", str(FIXTURES / "corridor_rec"), "--out",
                                   str(tmp_path), "--tum"])
    assert res.exit_code == 0, res.output
    assert "against truth.csv" in res.output and "heading" in res.output
    poses = load_poses(tmp_path / "poses.csv")
    assert poses.t_ns.size == len(Recording(FIXTURES / "corridor_rec"))
    assert (tmp_path / "poses.tum").exists()


# corridor poses have no x: MAVLink sends no VISION_POSITION_ESTIMATE for them by
# default (see docs/serial.md), so its MAVLink transcript is empty and not kept
@pytest.mark.parametrize("name,protocol", [("corridor", "nmea"), ("lights", "nmea"),
                                           ("lights", "mavlink")])
def test_golden_serial_transcripts(tmp_path, name, protocol):
    pty = PtyReader()
    try:
        res = CliRunner().invoke(app, ["replay", str(FIXTURES / f"{name}_rec"), "--out",
                                       str(tmp_path), "--serial", pty.path, "--protocol",
                                       protocol])
        assert res.exit_code == 0, res.output
    finally:
        data = pty.close()
    got = _pose_transcript(protocol, data)
    golden = GOLDEN / f"{name}_{protocol}.bin"
    if REGEN:
        golden.write_bytes(got)
    assert got == golden.read_bytes()
    n = len(Recording(FIXTURES / f"{name}_rec"))
    if protocol == "nmea":
        import pynmea2

        msgs = [pynmea2.parse(line.decode()) for line in got.splitlines()]
        assert len(msgs) == n
        assert all(m.manufacturer == "CEI" for m in msgs)
    else:
        from pymavlink.dialects.v20 import common as mavlink2

        mav = mavlink2.MAVLink(None)
        decoded = [m for m in (mav.parse_buffer(data) or [])
                   if m.get_type() == "VISION_POSITION_ESTIMATE"]
        assert len(decoded) == n


def test_live_on_the_simulator_records_and_streams(tmp_path):
    res = CliRunner().invoke(app, ["--device", "sim:corridor", "--frames", "6", "--serial",
                                   "-", "--record", str(tmp_path / "rec"), "--out",
                                   str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    assert "frames 6" in res.output and "against the source's ground truth" in res.output
    rec = Recording(tmp_path / "rec")
    assert len(rec) == 6
    assert load_poses(tmp_path / "run" / "poses.csv").t_ns.size == 6
    assert res.stdout.count("$PCEIL,") == 6
    # the simulator's truth goes with its frames: the recording replays against it
    assert rec.truth is not None and rec.truth.t_ns.tolist() == [f.t_ns for f in rec]
    again = CliRunner().invoke(app, ["replay", str(tmp_path / "rec")])
    assert again.exit_code == 0 and "against truth.csv" in again.output


@pytest.mark.parametrize("args,code,words", [
    (["--device", "/dev/video0", "--rig", "nope.yaml", "--site", "nope.yaml"], 1,
     "nope.yaml: file not found"),
    (["--device", "sim:corridor", "--method", "magic"], 2, "unknown method"),
    (["--device", "sim:nowhere"], 1, "no such example"),
    (["--device", "sim:corridor", "--frames", "2", "--serial", "/dev/ttyNOPE0"], 1,
     "/dev/ttyNOPE0"),
    (["replay", "/nonexistent/rec"], 1, "not a recording folder"),
    (["--device", "sim:corridor", "--frames", "2", "--serial", "/nonexistent/dir/out.nmea"],
     1, "cannot open link file /nonexistent/dir/out.nmea"),
    (["--device", "sim:corridor", "--frames", "2", "--protocol", "mavlink", "--serial", "-",
      "--ekf-origin", "48.1,11.5"], 1, "--ekf-origin"),
    (["--device", "sim:corridor", "--frames", "2", "--protocol", "mavlink", "--serial", "-",
      "--ekf-origin", "95,11.5,500"], 1, "lat in [-90, 90]"),
    (["--device", "sim:corridor", "--mavlink-missing-x", "zero"], 2, "zero"),
])
def test_bad_arguments_are_one_line(args, code, words):
    res = CliRunner().invoke(app, args)
    assert res.exit_code == code, res.output
    assert words in res.output
    if code == 1:
        assert res.output.count("error:") == 1


def test_serial_to_a_regular_file(tmp_path):
    out = tmp_path / "stream.nmea"
    res = CliRunner().invoke(app, ["--device", "sim:corridor", "--frames", "5", "--serial",
                                   str(out)])
    assert res.exit_code == 0, res.output
    lines = out.read_bytes().split(b"\r\n")
    assert lines[-1] == b""
    import pynmea2

    poses = [pynmea2.parse(ln.decode()) for ln in lines[:-1] if ln.startswith(b"$PCEIL")]
    assert len(poses) == 5 and "link " + str(out) in res.output


def test_mavlink_missing_x_nan_sends_corridor_poses(tmp_path):
    """The corridor method has no x: skipped by default, x = NaN with --mavlink-missing-x nan
    (decoded by pymavlink), with the yaw and y of the pose."""
    from pymavlink.dialects.v20 import common as mavlink2

    n = len(Recording(FIXTURES / "corridor_rec"))
    got = {}
    for policy in ("skip", "nan"):
        out = tmp_path / f"{policy}.bin"
        res = CliRunner().invoke(app, ["replay", str(FIXTURES / "corridor_rec"), "--out",
                                       str(tmp_path / policy), "--serial", str(out),
                                       "--protocol", "mavlink", "--mavlink-missing-x", policy])
        assert res.exit_code == 0, res.output
        got[policy] = [m for m in mavlink2.MAVLink(None).parse_buffer(out.read_bytes()) or []
                       if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert got["skip"] == []
    poses = load_poses(tmp_path / "nan" / "poses.csv")
    assert len(got["nan"]) == n
    import math

    for m, y, yaw in zip(got["nan"], poses.y_m, poses.yaw_rad, strict=True):
        assert math.isnan(m.x) and m.y == pytest.approx(-y, abs=1e-6)
        assert m.yaw == pytest.approx(-yaw, abs=1e-6) and math.isnan(m.covariance[0])
