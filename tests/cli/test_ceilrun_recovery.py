"""`ceilrun` as a process on the vehicle: the camera and the serial adapter unplugged and
re-plugged mid-run, SIGTERM and SIGINT.

The process is the real command line (``ceilrun.main``) with one substitution: the
camera device is a ``FakeCamera`` serving the frames of tests/fixtures/corridor_rec at
30 fps, unplugged while a control file exists. The serial port is a pseudo-terminal
reached through a stable symlink, as ``/dev/serial/by-id/...`` is: unplugging closes
the pty and removes the link, re-plugging makes a new pty and a new link.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pynmea2
import pytest

from ceilkit.runtime.io.link import nmea
from ceilkit.runtime.io.recording import Recording, load_poses
from helpers import FIXTURES, ROOT

REC = FIXTURES / "corridor_rec"

DRIVER = r"""
import sys
from pathlib import Path

import cv2

import ceilkit.runtime.io.capture as capture

control = Path(sys.argv[1])
frames = sorted((Path(sys.argv[2]) / "frames").glob("*.png"))
images = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in frames]


class ControlledCamera(capture.FakeCamera):
    plugged = property(lambda self: not (control / "camera_unplugged").exists(),
                       lambda self, value: None)


camera = ControlledCamera(images, fps=30)


class Camera(capture.CameraSource):
    def __init__(self, device, *args, **kwargs):
        kwargs["open_capture"] = camera.open
        kwargs["max_backoff_s"] = 0.2
        super().__init__(device, *args, **kwargs)


capture.CameraSource = Camera
from ceilkit.cli.ceilrun import main  # noqa: E402

sys.argv = ["ceilrun", *sys.argv[3:]]
main()
"""


class Adapter:
    """A USB-serial adapter: a pty behind a stable symlink; what the controller reads,
    per plug-in."""

    def __init__(self, link: Path):
        self.link = link
        self.received: list[bytearray] = []
        self.master = self.slave = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.plug()

    def plug(self) -> None:
        self.master, self.slave = os.openpty()
        tmp = self.link.with_suffix(".new")
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.link)
        self.received.append(bytearray())
        self._stop.clear()
        self._thread = threading.Thread(target=self._read, args=(self.master,
                                                                  self.received[-1]),
                                        daemon=True)
        self._thread.start()

    def _read(self, fd: int, into: bytearray) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([fd], [], [], 0.02)
            if r:
                try:
                    into += os.read(fd, 65536)
                except OSError:
                    return

    def unplug(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        os.unlink(self.link)  # the /dev node vanishes
        os.close(self.master)
        os.close(self.slave)
        self.master = self.slave = -1

    def close(self) -> None:
        if self.master >= 0:
            self.unplug()


def _sentences(data: bytes) -> list:
    """Every sentence, checking that the data is whole sentences only."""
    lines = bytes(data).split(b"\r\n")
    assert lines[-1] == b"", "a sentence was cut"
    for line in lines[:-1]:
        pynmea2.parse(line.decode("ascii"))  # the real peer's parser accepts it
    return [nmea.decode(line + b"\r\n") for line in lines[:-1]]


def _wait(cond, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _start(tmp_path: Path, serial: str) -> subprocess.Popen:
    args = [sys.executable, "-c", DRIVER, str(tmp_path), str(REC),
            "--device", "/dev/video0", "--rig", str(REC / "rig.yaml"),
            "--site", str(REC / "site.yaml"), "--serial", serial,
            "--record", str(tmp_path / "rec"), "--out", str(tmp_path / "run"),
            # the fixture corridor is symmetric about its centre line: the heading is stated
            "--option", "assume_heading_deg=0"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # started as from an ssh session's shell (SIGHUP not ignored, even when the tests
    # run under nohup: a ceilrun started with nohup keeps running on a hang-up)
    return subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))


def _finish(proc: subprocess.Popen, sig: int) -> tuple[int, str]:
    proc.send_signal(sig)
    try:
        _out, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, err.decode()


def _check_recording(tmp_path: Path, err: str) -> int:
    """frames.csv rows == PNGs == poses.csv rows == frames the run reports."""
    rec = Recording(tmp_path / "rec")
    pngs = list((tmp_path / "rec" / "frames").glob("*.png"))
    poses = load_poses(tmp_path / "run" / "poses.csv")
    reported = int(err.split("  frames ")[1].split(",")[0])
    assert len(rec) == len(pngs) == poses.t_ns.size == reported > 0
    assert not list((tmp_path / "rec" / "frames").glob(".*"))  # no half-written image
    assert f"recorded {reported} frames" in err
    return reported


def test_unplug_and_replug_camera_and_serial_mid_run(tmp_path):
    adapter = Adapter(tmp_path / "ttyUSB0")
    proc = _start(tmp_path, str(adapter.link))
    try:
        def poses_on(k: int, n: int):
            return lambda: adapter.received[k].count(b"$PCEIL,") >= n

        _wait(poses_on(0, 10), 60, "the first poses")
        # the camera goes: the controller is told, the run goes on
        (tmp_path / "camera_unplugged").touch()
        _wait(lambda: b",F,camera_lost," in adapter.received[0], 15, "the camera_lost status")
        # the serial adapter goes too, then the camera comes back, then the adapter
        adapter.unplug()
        time.sleep(1.0)
        (tmp_path / "camera_unplugged").unlink()
        time.sleep(1.0)
        adapter.plug()
        _wait(poses_on(1, 10), 30, "poses after the re-plug")
        code, err = _finish(proc, signal.SIGTERM)
    finally:
        if proc.poll() is None:
            proc.kill()
        adapter.close()
    assert code == 0, err
    before, after = (_sentences(d) for d in adapter.received)
    assert any(isinstance(d, nmea.NmeaStatus) and d.faulted and d.reason == "camera_lost"
               for d in before)
    assert sum(isinstance(d, nmea.NmeaPose) and d.valid for d in after) >= 5
    seqs = [d.seq for d in after]
    assert seqs == sorted(seqs)  # one stream, carried on after the re-plug
    # the log says what happened
    assert "camera lost" in err and "camera back" in err and "camera reopened 1x" in err
    assert f"link {adapter.link}" in err and "lost" in err and "back after" in err
    assert "reconnects 1" in err and "(stopped by a signal)" in err
    _check_recording(tmp_path, err)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_signal_stops_cleanly_with_complete_files(tmp_path, sig):
    proc = _start(tmp_path, str(tmp_path / "out.nmea"))  # a regular file as --serial
    try:
        _wait(lambda: (tmp_path / "run" / "poses.csv").exists()
              and (tmp_path / "run" / "poses.csv").read_bytes().count(b"\n") > 10,
              60, "poses")
        code, err = _finish(proc, sig)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0, err
    assert "(stopped by a signal)" in err and "Traceback" not in err
    n = _check_recording(tmp_path, err)
    sent = _sentences((tmp_path / "out.nmea").read_bytes())
    assert sum(isinstance(d, nmea.NmeaPose) for d in sent) == n
