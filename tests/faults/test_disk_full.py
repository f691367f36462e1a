"""A disk that fills up mid-run (a fake through the declared Disk protocol): the pose
stream goes on without a gap, one line names the disk, nothing is half-written, and
recording resumes when space is freed."""

from __future__ import annotations

import threading

import pytest

from ceilkit.runtime.errors import OutputError
from ceilkit.runtime.estimators.base import Failure
from ceilkit.runtime.io.recording import (
    POSES_HEADER,
    Disk,
    FullDisk,
    PoseWriter,
    Recording,
    load_poses,
)
from ceilkit.runtime.session import LinkConfig, SessionConfig, run_session

FRAMES = 60


def _wire_stamps(path) -> list[int]:
    return [int(line.split(b",")[2]) for line in path.read_bytes().split(b"\r\n")[:-1]
            if line.startswith(b"$PCEIL,")]


def test_the_fake_disk_follows_the_protocol():
    assert isinstance(FullDisk(), Disk)


def test_a_full_disk_mid_run_pauses_the_outputs_and_never_the_link(tmp_path, log_lines):
    disk = FullDisk(fail_after_bytes=4_000_000)   # fills after ~12 frames of 640x480
    freed = threading.Event()

    def on_frame(tel):
        if tel.frames == 30:  # an operator deletes old files
            disk.full = False
            freed.set()

    cfg = SessionConfig(device="sim:corridor", frames=FRAMES, record=tmp_path / "rec",
                        out=tmp_path / "run", link=LinkConfig(str(tmp_path / "wire.nmea")),
                        fsync_every_s=0.5)
    res = run_session(cfg, on_frame=on_frame, disk=disk)
    assert freed.is_set() and res.telemetry.frames == FRAMES
    # the pose stream: one sentence per frame, in order, no gap
    stamps = _wire_stamps(tmp_path / "wire.nmea")
    assert len(stamps) == FRAMES and stamps == sorted(stamps)
    # one line says it, naming the disk; another says recording resumed
    stopped = [ln for ln in log_lines if "recording stopped at frame" in ln]
    assert len(stopped) == 1 and stopped[0].startswith("no space left on ")
    assert "localization continues" in stopped[0] and "(" in stopped[0]
    assert any("recording resumed at frame" in ln for ln in log_lines)
    assert any("poses.csv stopped at row" in ln for ln in log_lines)
    # counted: recorded + not recorded = every frame
    assert res.run.recorded + res.run.not_recorded == FRAMES and res.run.not_recorded > 0
    rec = Recording(tmp_path / "rec")
    assert len(rec) == res.run.recorded and rec.logged == 0
    text = "\n".join(res.lines())
    assert "recording: " in text and "frames not written" in text
    # nothing half-written: every poses.csv row is whole
    lines = (tmp_path / "run" / "poses.csv").read_text().splitlines()
    assert lines[0] == ",".join(POSES_HEADER)
    assert all(len(ln.split(",")) == len(POSES_HEADER) for ln in lines)
    assert load_poses(tmp_path / "run" / "poses.csv").t_ns.size == len(lines) - 1


def test_a_short_write_is_rolled_back(tmp_path):
    class HalfDisk(FullDisk):
        def append(self, fd, parts):  # the disk fills during the write
            import os

            data = b"".join(bytes(p) for p in parts)
            if self.full:
                return os.write(fd, data[: len(data) // 2])
            return os.write(fd, data)

    disk = HalfDisk()
    w = PoseWriter(tmp_path / "poses.csv", disk=disk)
    w.write(Failure(1, "corridor", "too_few_lines"))
    disk.full = True
    with pytest.raises(OutputError, match="No space left") as err:
        w.write(Failure(2, "corridor", "too_few_lines"))
    assert err.value.errno == 28
    disk.full = False
    w.write(Failure(3, "corridor", "too_few_lines"))
    w.close()
    assert load_poses(tmp_path / "poses.csv").t_ns.tolist() == [1, 3]


def test_the_lines_name_the_runs_frame_not_the_recorders_count(tmp_path, log_lines,
                                                               corridor_rig, corridor_site):
    """A recording that starts at run frame 100 and pauses twice: each line names the
    frame the user sees (its index in the run), never the recording's own count."""
    import os

    import numpy as np

    from ceilkit.runtime.io.recording import OsDisk, RecordingWriter
    from ceilkit.runtime.io.sources import Frame
    from ceilkit.runtime.live import AsyncRecorder
    from ceilkit.runtime.pipeline import OutputGuard

    class LogDisk(FullDisk):  # only the write-ahead log fills (the encoder keeps up)
        def replace_file(self, path, data):
            OsDisk.replace_file(self, path, data)

        def append(self, fd, parts):
            if "frames.wal" in os.readlink(f"/proc/self/fd/{fd}"):
                return super().append(fd, parts)
            return OsDisk.append(self, fd, parts)

    disk = LogDisk()
    guard = OutputGuard("recording", tmp_path, retry_s=0.0)
    frames = [Frame(np.full((4, 4), k % 250, np.uint8), (k + 1) * 10_000_000, k)
              for k in range(100, 130)]
    with AsyncRecorder(RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site,
                                       disk=disk), guard=guard) as rec:
        for f in frames:
            disk.full = f.index in range(105, 110) or f.index in range(120, 124)
            rec.write(f)
    stopped = [ln for ln in log_lines if "recording stopped at frame" in ln]
    resumed = [ln for ln in log_lines if "recording resumed at frame" in ln]
    assert [ln.split("stopped at frame ")[1].split(",")[0] for ln in stopped] == ["105",
                                                                                 "120"]
    assert [ln.split("resumed at frame ")[1].split(" ")[0] for ln in resumed] == ["110",
                                                                                 "124"]
    assert guard.lost == 9 and len(Recording(tmp_path / "rec")) == 21
