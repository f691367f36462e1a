"""MCAP recordings: live record and replay, SIGKILL mid-run, SPEC folder <-> MCAP
round trip, the channels read by the mcap library's own reader, and bad input."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.mcap_rec import (
    IMAGE_TOPIC,
    POSE_TOPIC,
    McapRecording,
    convert_recording,
    mcap_summary,
    replay_folder,
)
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.replay import replay
from ceilkit.runtime.session import SessionConfig, run_session
from helpers import FIXTURES

pytest.importorskip("mcap", reason="the mcap extra is not installed (pip install "
                    "'ceilkit[mcap]')")
pytest.importorskip("mcap_ros2", reason="the mcap extra is not installed")

RUN = ("from ceilkit.cli.ceilrun import main; import sys; "
       "sys.argv = ['ceilrun', *sys.argv[1:]]; main()")

HEADING = {"assume_heading_deg": 0.0}
"""The simulated corridor is symmetric about its centre line: its heading is stated."""


def pose_rows(path: Path) -> list[dict[str, str]]:
    """poses.csv rows without the latency (the one column a run's timing decides)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        r.pop("latency_ms")
    return rows


def test_live_mcap_recording_replays_to_the_live_poses(tmp_path):
    rec = tmp_path / "run.mcap"
    res = run_session(SessionConfig(device="sim:corridor", frames=12, record=rec,
                                    out=tmp_path / "live", options=HEADING))
    assert res.run.recorded == 12
    summary = mcap_summary(rec)
    assert summary["complete"]
    assert summary["attachments"] == ["rig.yaml", "site.yaml"]
    counts = summary["messages"]
    assert counts[IMAGE_TOPIC] == 12 and counts["/ceilkit/truth"] == 12
    assert counts[POSE_TOPIC] == res.telemetry.estimated
    assert counts["/ceilkit/detections"] == 12 and counts["/diagnostics"] == 12
    again = replay(rec, options=HEADING)
    assert again.poses_path == tmp_path / "run.replay" / "poses.csv"
    assert again.telemetry.frames == 12
    assert pose_rows(again.poses_path) == pose_rows(tmp_path / "live" / "poses.csv")
    assert again.accuracy is not None and again.accuracy.estimated == 12


def test_mcap_library_reads_the_ros2_messages(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    rec = tmp_path / "run.mcap"
    run_session(SessionConfig(device="sim:corridor", frames=4, record=rec, options=HEADING))
    with open(rec, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        topics = {c.topic: s.name for c, s in
                  ((ch, reader.get_summary().schemas[ch.schema_id])
                   for ch in reader.get_summary().channels.values())}
        poses = [(m.log_time, d) for _, _, m, d in
                 reader.iter_decoded_messages(topics=[POSE_TOPIC])]
        images = [d for _, _, _, d in reader.iter_decoded_messages(topics=[IMAGE_TOPIC])]
    assert topics[POSE_TOPIC] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert topics[IMAGE_TOPIC] == "sensor_msgs/msg/CompressedImage"
    assert len(images) == 4 and images[0].format == "mono8; png compressed"
    assert bytes(images[0].data[:8]) == b"\x89PNG\r\n\x1a\n"
    assert poses
    for t_ns, p in poses:
        assert p.header.frame_id == "map"
        assert p.header.stamp.sec * 10**9 + p.header.stamp.nanosec == t_ns
        cov = np.asarray(p.pose.covariance).reshape(6, 6)
        assert np.all(np.diag(cov) > 0)
        assert cov[0, 0] == 1e6  # the corridor does not observe x: large, never zero
        assert cov[1, 1] < 1e-4 and cov[5, 5] < 1e-3  # y and yaw from the filter


def test_sigkilled_mcap_recording_reads_and_replays_every_finished_frame(tmp_path):
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    rec, out = tmp_path / "run.mcap", tmp_path / "live"
    proc = subprocess.Popen([sys.executable, "-c", RUN, "--device", "sim:corridor",
                             "--record", str(rec), "--out", str(out),
                             "--option", "assume_heading_deg=0"],
                            stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 120  # a loaded machine starts slowly
    poses = out / "poses.csv"
    while time.monotonic() < deadline and proc.poll() is None:
        if poses.exists() and poses.read_bytes().count(b"\n") > 8:
            break
        time.sleep(0.01)
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # the mcap library's own streaming reader: every whole message, then the cut end
    seen = 0
    with open(rec, "rb") as fh:
        try:
            for _ in NonSeekingReader(fh).iter_messages(log_time_order=False):
                seen += 1
        except (McapError, EOFError, ValueError):
            pass
    assert not mcap_summary(rec)["complete"]  # killed: no summary, no footer
    recording = McapRecording(rec)
    with open(poses, newline="") as fh:
        written = [int(r["t_ns"]) for r in csv.DictReader(fh)]
    assert seen >= len(recording) >= len(written) >= 8  # header + 8 rows seen before the kill
    assert set(written) <= set(recording.t_ns.tolist())  # every finished frame is in it
    res = replay(rec, tmp_path / "replay")
    assert res.telemetry.frames == len(recording)


def test_spec_recording_to_mcap_and_back_replays_to_identical_poses(tmp_path):
    src = FIXTURES / "corridor_rec"
    assert convert_recording(src, tmp_path / "c.mcap") == 8
    assert convert_recording(tmp_path / "c.mcap", tmp_path / "back") == 8
    back = Recording(tmp_path / "back")
    orig = Recording(src)
    assert np.array_equal(back.t_ns, orig.t_ns)
    for k in range(len(orig)):
        assert np.array_equal(back.frame(k).image, orig.frame(k).image)
    assert (tmp_path / "back" / "truth.csv").read_text() == (src / "truth.csv").read_text()
    for track in (True, False):
        a = replay(src, tmp_path / f"a{track}", track=track)
        b = replay(tmp_path / "c.mcap", tmp_path / f"b{track}", track=track)
        c = replay(tmp_path / "back", tmp_path / f"c{track}", track=track)
        assert pose_rows(a.poses_path) == pose_rows(b.poses_path) == pose_rows(c.poses_path)


def test_odometry_travels_through_mcap(tmp_path):
    src = tmp_path / "src"
    convert_recording(convert_src(tmp_path), src)
    rows = ["t_ns,dx,dy,dyaw_deg"] + [f"{k * 50_000_000},0.05,0.001,{0.1 * k:.1f}"
                                      for k in range(1, 16)]
    (src / "odometry.csv").write_text("\n".join(rows) + "\n")
    convert_recording(src, tmp_path / "o.mcap")
    convert_recording(tmp_path / "o.mcap", tmp_path / "back")
    a, b = Recording(src).odometry, Recording(tmp_path / "back").odometry
    assert np.array_equal(a.t_ns, b.t_ns)
    for col in ("dx_m", "dy_m", "dyaw_rad"):
        np.testing.assert_allclose(getattr(b, col), getattr(a, col), rtol=0, atol=1e-12)
    assert McapRecording(tmp_path / "o.mcap").odometry is not None
    pa = replay(src, tmp_path / "ra", method="auto")
    pb = replay(tmp_path / "o.mcap", tmp_path / "rb", method="auto")
    assert pose_rows(pa.poses_path) == pose_rows(pb.poses_path)


def convert_src(tmp_path: Path) -> Path:
    """An .mcap of the corridor fixture (a source to convert back)."""
    path = tmp_path / "fixture.mcap"
    convert_recording(FIXTURES / "corridor_rec", path)
    return path


def test_bad_input_is_one_error_naming_the_file(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap at all")
    with pytest.raises(ConfigError, match="bad.mcap: not an MCAP file"):
        McapRecording(bad)
    with pytest.raises(ConfigError, match="missing.mcap: file not found"):
        McapRecording(tmp_path / "missing.mcap")
    with pytest.raises(ConfigError, match="folder to .mcap or .mcap to a folder"):
        convert_recording(FIXTURES / "corridor_rec", tmp_path / "other")
    path = convert_src(tmp_path)
    before = path.read_bytes()
    with pytest.raises(ConfigError, match="a recording is"):
        convert_recording(FIXTURES / "corridor_rec", path)
    assert path.read_bytes() == before  # nothing lost
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(before[:300])  # header only: no rig attached yet
    with pytest.raises(ConfigError, match="cut.mcap: rig.yaml: not attached"):
        McapRecording(cut)


def test_replay_folder_beside_an_mcap():
    assert replay_folder(Path("a/run.mcap")) == Path("a/run.replay")
    assert replay_folder(Path("a/run")) == Path("a/run/replay")
