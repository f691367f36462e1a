"""`ceilrun`: replay of fixture recordings, golden serial transcripts over a pty, live
runs on the simulator, and the errors a user can make."""

from __future__ import annotations

import os
import select
import threading

import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilrun import app
from ceilkit.runtime.link import mavlink
from ceilkit.runtime.recording import Recording, load_poses
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
    assert len(Recording(tmp_path / "rec")) == 6
    assert load_poses(tmp_path / "run" / "poses.csv").t_ns.size == 6
    assert res.stdout.count("$PCEIL,") == 6


@pytest.mark.parametrize("args,code,words", [
    (["--device", "/dev/video0", "--rig", "nope.yaml", "--site", "nope.yaml"], 1,
     "nope.yaml: file not found"),
    (["--device", "sim:corridor", "--method", "magic"], 2, "unknown method"),
    (["--device", "sim:nowhere"], 1, "no such example"),
    (["--device", "sim:corridor", "--frames", "2", "--serial", "/dev/ttyNOPE0"], 1,
     "/dev/ttyNOPE0"),
    (["replay", "/nonexistent/rec"], 1, "not a recording folder"),
])
def test_bad_arguments_are_one_line(args, code, words):
    res = CliRunner().invoke(app, args)
    assert res.exit_code == code, res.output
    assert words in res.output
    if code == 1:
        assert res.output.count("error:") == 1
