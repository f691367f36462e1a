"""runtime/session.py: the live session as a library call (what `ceilrun` runs)."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.recording import Recording, load_poses
from ceilkit.runtime.session import (
    LinkConfig,
    SessionConfig,
    load_rig_site,
    run_session,
    stop_on_signals,
)
from helpers import CONFIGS


def test_a_simulated_session_writes_poses_records_and_streams(tmp_path):
    cfg = SessionConfig(device="sim:lights", frames=5, out=tmp_path / "run",
                        record=tmp_path / "rec",
                        link=LinkConfig(str(tmp_path / "out.nmea")))
    res = run_session(cfg)
    assert res.method == "lights" and res.telemetry.frames == 5 and not res.run.stopped
    assert load_poses(tmp_path / "run" / "poses.csv").t_ns.size == 5
    rec = Recording(tmp_path / "rec")
    assert len(rec) == 5 and rec.truth is not None and res.run.recorded == 5
    assert (tmp_path / "out.nmea").read_bytes().count(b"$PCEIL,") == 5
    assert res.link and res.link[0].startswith(f"link {tmp_path / 'out.nmea'}")
    # the simulator's truth: errors of a lights fix are sub-millimetre
    assert res.accuracy is not None and res.accuracy.estimated == 5
    assert res.accuracy.position_m.max < 0.005
    text = "\n".join(res.lines())
    assert "lights on sim:lights" in text and "  frames 5," in text
    assert f"recorded 5 frames in {tmp_path / 'rec'}" in text


def test_options_reach_the_estimator_and_a_bad_one_is_named(tmp_path):
    res = run_session(SessionConfig(device="sim:corridor", frames=3,
                                    options={"min_contrast": "255"}))
    assert res.telemetry.failures["blank_frame"] == 3
    with pytest.raises(ConfigError) as err:
        run_session(SessionConfig(device="sim:corridor", frames=3, options={"nope": "1"}))
    assert err.value.key == "options.nope"
    with pytest.raises(ConfigError) as err:
        run_session(SessionConfig(device="sim:corridor", method="magic"))
    assert err.value.key == "method" and "unknown method 'magic'" in str(err.value)


def test_a_stop_request_ends_the_session_at_once(tmp_path):
    stop = threading.Event()
    stop.set()
    res = run_session(SessionConfig(device="sim:corridor", frames=5, out=tmp_path), stop)
    assert res.run.stopped and res.telemetry.frames == 0
    assert "(stopped by a signal)" in res.lines()[0]
    assert not (tmp_path / "poses.csv").exists()  # stopped before anything was written


def test_rig_and_site_are_needed_off_the_simulator():
    with pytest.raises(ConfigError) as err:
        load_rig_site("/dev/video0", None, CONFIGS / "corridor" / "site.yaml")
    assert err.value.key == "rig"
    with pytest.raises(ConfigError) as err:
        load_rig_site("/dev/video0", CONFIGS / "corridor" / "rig.yaml", None)
    assert err.value.key == "site"
    rig, site = load_rig_site("sim:lights", None, None)
    assert site.has_lights


def test_an_output_that_cannot_be_written_is_an_output_error(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="file"):
        run_session(SessionConfig(device="sim:corridor", frames=2, out=tmp_path / "file"))


def test_stop_on_signals_turns_sigint_into_a_stop_request():
    before = signal.getsignal(signal.SIGINT)     # SIG_IGN when pytest runs in the
    with stop_on_signals() as stop:               # background of a shell, else Python's
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.wait(2.0)
    assert signal.getsignal(signal.SIGINT) is before             # the handler put back


def test_sighup_stops_like_sigterm_unless_started_with_nohup():
    original = signal.getsignal(signal.SIGHUP)    # SIG_IGN under nohup
    try:
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        with stop_on_signals() as stop:
            os.kill(os.getpid(), signal.SIGHUP)
            assert stop.wait(2.0)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL    # put back
        signal.signal(signal.SIGHUP, signal.SIG_IGN)                 # nohup ceilrun
        with stop_on_signals() as stop:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
            assert not stop.wait(0.2)                 # the hang-up did not stop it
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, original)


def test_frames_below_zero_and_existing_outputs_are_config_errors(tmp_path):
    with pytest.raises(ConfigError) as err:
        run_session(SessionConfig(device="sim:corridor", frames=-5))
    assert err.value.key == "frames"
    (tmp_path / "poses.csv").write_text("x")
    with pytest.raises(ConfigError, match="already there.*force=True"):
        run_session(SessionConfig(device="sim:corridor", frames=2, out=tmp_path))
    assert (tmp_path / "poses.csv").read_text() == "x"
    res = run_session(SessionConfig(device="sim:corridor", frames=2, out=tmp_path,
                                    force=True))
    assert res.telemetry.frames == 2 and load_poses(tmp_path / "poses.csv").t_ns.size == 2


def test_numbered_record_folders_and_outputs_that_are_inputs(tmp_path):

    from ceilkit.runtime.session import check_outputs, record_folder

    assert record_folder(tmp_path / "r-{n}") == tmp_path / "r-1"
    (tmp_path / "r-1").mkdir()
    assert record_folder(tmp_path / "r-{n}") == tmp_path / "r-2"
    assert record_folder(tmp_path / "plain") == tmp_path / "plain"
    rig = tmp_path / "cfg" / "rig.yaml"
    with pytest.raises(ConfigError) as err:
        check_outputs([rig], {"record": [tmp_path / "cfg" / "rig.yaml"]})
    assert err.value.key == "record" and "is an input of this run" in str(err.value)
    with pytest.raises(ConfigError):  # recording into the recording being read
        check_outputs([tmp_path], {"record": [tmp_path / "frames.csv"]})
    check_outputs([rig], {"out": [tmp_path / "run" / "poses.csv"]})
    check_outputs([tmp_path / "frames.csv", tmp_path / "frames"],  # a recording's parts:
                  {"out": [tmp_path / "poses.csv"]})                 # poses beside: fine
