"""Start-up order independence: nothing on disk until camera and port are open; a
port that appears later is waited for with --wait; without it, one line."""

from __future__ import annotations

import os
import threading

from typer.testing import CliRunner

from ceilkit.cli.ceilrun import app
from ceilkit.runtime.session import LinkConfig, SessionConfig, run_session


def test_a_missing_port_is_one_line_and_nothing_on_disk(tmp_path):
    res = CliRunner().invoke(app, ["--device", "sim:corridor", "--frames", "5",
                                   "--record", str(tmp_path / "rec"),
                                   "--out", str(tmp_path / "run"),
                                   "--serial", str(tmp_path / "ttyUSB9")])
    assert res.exit_code == 1
    assert res.stderr.strip().splitlines() == [
        f"ceilrun: error: cannot open serial port {tmp_path / 'ttyUSB9'}: no such device "
        "(is the adapter plugged in? see ls /dev/serial/by-id/)"]
    assert sorted(os.listdir(tmp_path)) == []   # no skeleton blocks the restart


class Backoff(threading.Event):
    """A stop event whose ``wait`` (the back-off between attempts to open) returns at
    once, recording the delay asked for and calling ``on_wait(n)`` with the number of
    waits so far: the test plays the clock, nothing sleeps."""

    def __init__(self, on_wait):
        super().__init__()
        self.on_wait = on_wait
        self.delays: list[float] = []

    def wait(self, timeout=None):
        self.delays.append(timeout)
        self.on_wait(len(self.delays))
        return self.is_set()


def test_a_port_appearing_later_is_waited_for_without_debris(tmp_path, log_lines):
    port = tmp_path / "ttyUSB0"
    seen_before: list[list[str]] = []
    pty: list[int] = []

    def plug_in(waits):  # after the third back-off (retries in between)
        if waits == 3:
            seen_before.append(sorted(os.listdir(tmp_path)))
            master, slave = os.openpty()
            pty.extend((master, slave))
            os.symlink(os.ttyname(slave), port)

    stop = Backoff(plug_in)
    try:
        cfg = SessionConfig(device="sim:corridor", frames=5, record=tmp_path / "rec",
                            link=LinkConfig(str(port)), wait=True)
        res = run_session(cfg, stop)
    finally:
        for fd in pty:
            os.close(fd)
    assert stop.delays == [0.5, 1.0, 2.0]   # back-off, doubling up to WAIT_BACKOFF_S
    assert seen_before == [[]]   # nothing was created while waiting
    assert res.telemetry.frames == 5 and res.run.recorded == 5
    assert sum(ln.startswith("waiting for serial port") for ln in log_lines) == 1


def test_a_stop_while_waiting_ends_cleanly_with_nothing_on_disk(tmp_path):
    stop = Backoff(lambda waits: waits == 2 and stop.set())   # a signal while waiting
    res = run_session(SessionConfig(device="sim:corridor", frames=5,
                                    record=tmp_path / "rec", out=tmp_path / "run",
                                    link=LinkConfig(str(tmp_path / "ttyUSB3")), wait=True),
                      stop)
    assert res.run.stopped and res.telemetry.frames == 0 and stop.delays == [0.5, 1.0]
    assert os.listdir(tmp_path) == []


def test_a_mistyped_port_never_becomes_an_output_file(tmp_path, monkeypatch):
    """A path under /dev or named tty* that does not exist is a missing port (one line,
    nothing on disk); a path elsewhere is a regular file receiving the wire (docs/serial.md)."""
    monkeypatch.chdir(tmp_path)
    for port in ("/dev/ttyUSB9", "/dev/tty-typo", "/dev/serial0x", "ttyACM7"):
        res = CliRunner().invoke(app, ["--device", "sim:corridor", "--frames", "2",
                                       "--out", "run", "--serial", port])
        assert res.exit_code == 1, port
        assert res.stderr.strip().splitlines() == [
            f"ceilrun: error: cannot open serial port {port}: no such device "
            "(is the adapter plugged in? see ls /dev/serial/by-id/)"], port
        assert os.listdir(tmp_path) == [], port
    res = CliRunner().invoke(app, ["--device", "sim:corridor", "--frames", "2",
                                   "--serial", "wire.nmea"])
    assert res.exit_code == 0 and (tmp_path / "wire.nmea").read_bytes().count(b"$PCEIL,") == 2
