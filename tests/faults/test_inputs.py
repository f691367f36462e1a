"""Corrupt inputs, overwrites and faults that must be loud: each is one line (an error
or an announced degradation), never a traceback or silence."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilrun import app
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.capture import CameraSource, FakeCamera
from ceilkit.runtime.io.link import MemoryLink, nmea
from ceilkit.runtime.io.recording import LOG_DIR, Recording
from ceilkit.runtime.live import FAILURE_STREAK_FRAMES, WRONG_SIZE_FAULT, run_live
from ceilkit.runtime.pipeline import Pipeline
from helpers import CONFIGS

run = CliRunner().invoke


def _record(tmp_path, n=12):
    res = run(app, ["--device", "sim:corridor", "--frames", str(n), "--record",
                    str(tmp_path / "rec")])
    assert res.exit_code == 0, res.output
    return tmp_path / "rec"


def _one_error_line(res, *words):
    assert res.exit_code == 1, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ceilrun: error: "), res.stderr
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


def test_negative_frames_is_an_error(tmp_path):
    _one_error_line(run(app, ["--device", "sim:corridor", "--frames", "-5"]),
                    "--frames", "-5")


def test_a_20_digit_stamp_is_one_line(tmp_path):
    rec = _record(tmp_path, 2)
    (rec / "frames.csv").write_text("index,t_ns\n0,12345678901234567890\n1,5\n")
    _one_error_line(run(app, ["replay", str(rec)]), "frames.csv", "line 2: t_ns", "64-bit")


def test_truth_matching_no_frame_warns(tmp_path, log_lines):
    rec = _record(tmp_path, 3)
    (rec / "truth.csv").write_text("t_ns,x,y,yaw_deg\n7,0,0,0\n")
    res = run(app, ["replay", str(rec)])
    assert res.exit_code == 0
    assert any("truth.csv: none of its 1 stamps is a frame's" in ln for ln in log_lines)


def test_existing_outputs_are_refused_naming_force(tmp_path):
    rec = _record(tmp_path, 3)
    before = (rec / "frames.csv").read_bytes()
    _one_error_line(run(app, ["--device", "sim:corridor", "--frames", "3", "--record",
                              str(rec)]), "a recording is already there", "--force")
    assert (rec / "frames.csv").read_bytes() == before
    cfg = tmp_path / "cfg"
    cfg.mkdir()
    (cfg / "rig.yaml").write_text("x")
    (cfg / "site.yaml").write_text("y")
    _one_error_line(run(app, ["--device", "sim:corridor", "--frames", "3", "--record",
                              str(cfg)]), "rig.yaml, site.yaml are already there")
    assert (cfg / "rig.yaml").read_text() == "x"
    assert run(app, ["--device", "sim:corridor", "--frames", "3", "--out",
                     str(tmp_path / "run")]).exit_code == 0
    _one_error_line(run(app, ["--device", "sim:corridor", "--frames", "3", "--out",
                              str(tmp_path / "run")]), "poses.csv: already there", "--force")
    ok = run(app, ["--device", "sim:corridor", "--frames", "4", "--record", str(rec),
                   "--out", str(tmp_path / "run"), "--force"])
    assert ok.exit_code == 0 and len(Recording(rec)) == 4
    _one_error_line(run(app, ["replay", str(rec), "--out", str(tmp_path / "run")]),
                    "--force")


def test_the_library_replay_refuses_an_existing_poses_file(tmp_path):
    """``replay()`` itself (not only the CLI) never truncates an existing poses.csv."""
    from ceilkit.runtime.io.recording import load_poses
    from ceilkit.runtime.replay import replay
    from ceilkit.runtime.session import LinkConfig

    rec = _record(tmp_path, 3)
    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.csv").write_text("x")
    with pytest.raises(ConfigError, match="already there.*force=True") as err:
        replay(rec, out)
    assert err.value.path == str(out / "poses.csv")
    assert (out / "poses.csv").read_text() == "x"
    assert not (out / "poses.tum").exists()
    with pytest.raises(ConfigError, match="is an input of this run") as err:
        replay(rec, tmp_path / "o", link=LinkConfig(str(rec / "truth.csv")))
    assert err.value.key == "link" and not (tmp_path / "o").exists()
    res = replay(rec, out, force=True)
    assert res.telemetry.frames == 3 and load_poses(out / "poses.csv").t_ns.size == 3


def test_numbered_recording_folders(tmp_path):
    for n in (1, 2):
        res = run(app, ["--device", "sim:corridor", "--frames", "2", "--record",
                        str(tmp_path / "run-{n}")])
        assert res.exit_code == 0 and f"recorded 2 frames in {tmp_path}/run-{n}" in res.stderr


def test_an_output_may_not_be_an_input(tmp_path):
    rec = _record(tmp_path, 3)
    truth = (rec / "truth.csv").read_bytes()
    _one_error_line(run(app, ["replay", str(rec), "--serial", str(rec / "truth.csv"),
                              "--out", str(tmp_path / "o")]),
                    "--serial", "is an input of this run")
    assert (rec / "truth.csv").read_bytes() == truth
    _one_error_line(run(app, ["--rig", str(CONFIGS / "corridor" / "rig.yaml"), "--device",
                              "sim:corridor", "--frames", "2", "--record",
                              str(CONFIGS / "corridor"), "--force"]),
                    "--record", "is an input of this run")


def test_an_error_after_the_progress_bar_starts_on_its_own_line(tmp_path):
    import cv2  # a frame of the wrong size is an error (a damaged file is a bad_frame)

    rec = _record(tmp_path, 12)
    cv2.imwrite(str(rec / "frames" / "000011.png"), np.zeros((2, 2), np.uint8))
    res = run(app, ["replay", str(rec), "--progress"])
    assert res.exit_code == 1
    assert "\nceilrun: error: " in res.stderr and "] 10/12\n" in res.stderr


def test_a_frame_log_cut_by_a_kill_reads_up_to_the_cut(tmp_path, log_lines):
    rec = _record(tmp_path, 3)
    from ceilkit.runtime.io.recording import RecordingWriter
    from ceilkit.runtime.io.sources import Frame

    w = RecordingWriter(tmp_path / "r2", Recording(rec).rig, Recording(rec).site)
    frames = [Recording(rec).frame(k) for k in range(3)]
    for f in frames:
        w.log(Frame(f.image, f.t_ns, f.index))
    seg = next((tmp_path / "r2" / LOG_DIR).glob("*.raw"))
    seg.write_bytes(seg.read_bytes()[:-1000])   # the last record cut short
    back = Recording(tmp_path / "r2")
    assert len(back) == 2 and back.logged == 2
    assert np.array_equal(back.frame(1).image, frames[1].image)


class _SizeEstimator:
    name = "fake"

    def estimate(self, image, t_ns, prior=None):
        if image.shape != (4, 4):
            return Failure(t_ns, "fake", "bad_frame")
        return PoseEstimate(t_ns, "fake", 1.0, 2.0, 0.0, 0.9)


def test_a_live_frame_of_the_wrong_size_is_reported_at_once(log_lines):
    cam = FakeCamera([np.zeros((3, 5), np.uint8)], fps=200)
    stop = threading.Event()

    def on_frame(tel):
        if tel.frames == 3:
            cam.images[:] = [np.zeros((4, 4), np.uint8)]
        if tel.frames == 6:
            stop.set()

    with CameraSource("/dev/video7", open_capture=cam.open) as src, \
            MemoryLink("nmea") as link:
        p = Pipeline(_SizeEstimator(), [link])
        run_live(src, p, stop=stop, on_frame=on_frame, camera_size=(4, 4))
    assert any("is 5x3 but the camera is calibrated at 4x4" in ln for ln in log_lines)
    assert any("of the camera's size again" in ln for ln in log_lines)
    sentences = [nmea.decode(ln + b"\r\n") for ln in bytes(link.written).split(b"\r\n")
                 if ln]
    faults = [d for d in sentences if isinstance(d, nmea.NmeaStatus) and d.faulted]
    assert faults and faults[0].reason == WRONG_SIZE_FAULT


def test_a_run_of_failures_is_reported_while_running(log_lines):
    from ceilkit.runtime.io.sources import Frame, ListSource

    frames = [Frame(np.zeros((3, 3), np.uint8), k, k) for k in range(FAILURE_STREAK_FRAMES)]
    frames.append(Frame(np.zeros((4, 4), np.uint8), 99, 99))
    run_live(ListSource(frames), Pipeline(_SizeEstimator()))
    assert f"no pose for {FAILURE_STREAK_FRAMES} frames: each failed with bad_frame" \
        in log_lines
    assert any(ln.startswith("poses again after") for ln in log_lines)


def test_a_stalled_link_is_reported_while_running(log_lines):
    with MemoryLink("nmea", capacity=300) as link:
        for k in range(60):
            link.send(PoseEstimate(k * 1_000_000, "fake", 1.0, 2.0, 0.0, 0.9))
        assert link.stalled
        for _ in range(20):  # the controller reads again
            link.drain()
            link.poll()
        assert link.pending_bytes == 0 and not link.stalled
    assert sum("stalled: the peer is not reading" in ln for ln in log_lines) == 1
    assert any("flowing again" in ln for ln in log_lines)
