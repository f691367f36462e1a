"""ceilcal autopilot: parameter values from the rig, and files MAVProxy / QGroundControl read."""

from __future__ import annotations

import contextlib
import io
import math

import pytest
from pymavlink import mavparm
from typer.testing import CliRunner

from ceilkit.calib import autopilot
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Mount
from ceilkit.runtime.errors import ConfigError
from helpers import ROOT

RIG_TEXT = """camera: {camera}
mount: {{pan: 1.5, tilt: 80.0, swing: 0.0, x: 0.30, y: -0.05, z: 0.80}}
"""


@pytest.fixture
def rig_file(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(RIG_TEXT.format(camera=ROOT / "configs" / "corridor" / "camera.yaml"))
    return path


def load_param(path) -> dict[str, float]:
    """The file as MAVProxy's ``param load`` reads it (pymavlink's MAVParmDict.load)."""
    params = mavparm.MAVParmDict()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert params.load(str(path))
    assert "Invalid line" not in out.getvalue(), out.getvalue()
    return dict(params)


def load_qgc(path) -> dict[str, tuple[float, int]]:
    """A QGroundControl .params file: comments, then vehicle, component, name, value, type."""
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        vehicle, component, name, value, kind = line.split("\t")
        assert (vehicle, component) == ("1", "1") and kind in ("6", "9")
        if kind == "6":
            assert str(int(value)) == value
        out[name] = (float(value), int(kind))
    return out


def test_sensor_offset_is_the_camera_in_body_frd():
    mount = Mount(x_m=0.3, y_m=-0.05, z_m=0.8)
    assert autopilot.sensor_offset_frd(mount) == (0.3, 0.05, -0.8)
    assert autopilot.sensor_offset_frd(mount, (0.1, 0.02, 0.25)) == (0.2, 0.07, -0.55)


def test_ardupilot_param_file_loads_as_mavproxy_does_and_matches_the_rig(rig_file, tmp_path):
    out = tmp_path / "ceilkit.param"
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), "--for", "ardupilot",
                                   "--firmware", "ardupilot-4.6",
                                   "--out", str(out), "--autopilot-at", "0.1,0.0,0.2",
                                   "--delay-ms", "35"])
    assert res.exit_code == 0, res.output
    params = load_param(out)
    assert params["VISO_TYPE"] == 1 and params["VISO_ORIENT"] == 0
    assert params["VISO_POS_X"] == pytest.approx(0.30 - 0.1)
    assert params["VISO_POS_Y"] == pytest.approx(0.05)           # y right = -y left
    assert params["VISO_POS_Z"] == pytest.approx(-(0.80 - 0.2))  # z down: the camera is above
    assert params["VISO_DELAY_MS"] == 35
    assert params["EK3_SRC1_POSXY"] == 6 and params["EK3_SRC1_YAW"] == 6
    assert params["EK3_SRC1_VELXY"] == 0 and params["EK3_SRC1_POSZ"] == 1
    assert params["AHRS_EKF_TYPE"] == 3 and params["COMPASS_USE"] == 0
    text = out.read_text()
    assert text.startswith("# ceilkit external navigation for ardupilot-4.6: the whole set; "
                           "load this file\n# written ")
    assert "# command: " in text and f"# rig: {rig_file}" in text and "EKF origin" in text
    for line in text.splitlines():  # Mission Planner's form: NAME,VALUE or a comment
        assert line.startswith("#") or (line.count(",") == 1 and " " not in line)


def test_ardupilot_corridor_fuses_the_heading_only(rig_file, tmp_path):
    out = tmp_path / "corridor.param"
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), "--firmware",
                                   "ardupilot-4.5", "--out", str(out), "--corridor"])
    assert res.exit_code == 0, res.output
    params = load_param(out)
    assert params["EK3_SRC1_POSXY"] == 0 and params["EK3_SRC1_YAW"] == 6


def test_px4_params_file_is_qgroundcontrol_format_and_matches_the_rig(rig_file, tmp_path):
    out = tmp_path / "ceilkit.params"
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), "--for", "px4",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    params = load_qgc(out)
    assert params["EKF2_EV_CTRL"] == (9.0, 6)
    assert params["EKF2_HGT_REF"] == (0.0, 6)
    assert params["EKF2_EV_POS_X"] == (pytest.approx(0.30), 9)
    assert params["EKF2_EV_POS_Y"] == (pytest.approx(0.05), 9)
    assert params["EKF2_EV_POS_Z"] == (pytest.approx(-0.80), 9)
    assert params["EKF2_EV_DELAY"] == (pytest.approx(autopilot.DEFAULT_DELAY_MS), 9)
    assert params["EKF2_MAG_TYPE"] == (5.0, 6)


def test_offsets_follow_a_calibrated_rig_exactly():
    mount = Mount(pan_rad=0.0, tilt_rad=math.radians(45.0), x_m=0.4125, y_m=0.0333, z_m=1.2)
    by_name = {p.name: p.value for p in autopilot.autopilot_params(mount, "ardupilot",
                                                                  "ardupilot-4.6")}
    assert (by_name["VISO_POS_X"], by_name["VISO_POS_Y"], by_name["VISO_POS_Z"]) == (
        0.4125, -0.0333, -1.2)
    text = autopilot.format_params(autopilot.autopilot_params(mount, "px4"), "px4")
    assert "1\t1\tEKF2_EV_POS_Y\t-0.0333\t9" in text


def test_errors_name_the_option(rig_file, tmp_path):
    with pytest.raises(ConfigError, match="--for"):
        autopilot.autopilot_params(Mount(), "betaflight")
    for bad in ("1,2", "a,b,c", "0,0,1000", "nan,0,0"):
        with pytest.raises(ConfigError, match="--autopilot-at"):
            autopilot.parse_autopilot_at(bad)
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), "--for", "inav",
                                   "--out", str(tmp_path / "x.param")])
    assert res.exit_code == 1 and "--for" in res.output
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(tmp_path / "missing.yaml"),
                                   "--for", "px4", "--out", str(tmp_path / "x.params")])
    assert res.exit_code == 1 and "missing.yaml" in res.output


@pytest.mark.parametrize("firmware,gps,absent", [("ardupilot-4.5", "GPS_TYPE", "GPS1_TYPE"),
                                                 ("ardupilot-4.6", "GPS1_TYPE", "GPS_TYPE"),
                                                 ("ardupilot-4.7", "GPS1_TYPE", "GPS_TYPE")])
def test_each_firmware_gets_its_own_parameter_names(rig_file, firmware, gps, absent):
    """4.6 moved the GPS parameters to per-instance groups (GPS1_TYPE); the rest of the
    set is named alike in 4.5, 4.6 and 4.7 (calib/autopilot.py names the sources)."""
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), "--firmware",
                                   firmware])
    assert res.exit_code == 0, res.output
    out = rig_file.with_name(f"rig.{firmware}.param")         # beside the rig, by purpose
    assert f"wrote {out}" in res.output
    params = load_param(out)
    assert params[gps] == 0 and absent not in params
    assert set(params) - {gps} == {
        "VISO_TYPE", "VISO_POS_X", "VISO_POS_Y", "VISO_POS_Z", "VISO_ORIENT",
        "VISO_DELAY_MS", "VISO_POS_M_NSE", "VISO_YAW_M_NSE", "AHRS_EKF_TYPE",
        "EK3_SRC1_POSXY", "EK3_SRC1_VELXY", "EK3_SRC1_POSZ", "EK3_SRC1_VELZ", "EK3_SRC1_YAW",
        "COMPASS_USE", "COMPASS_USE2", "COMPASS_USE3"}
    assert "load this file" in out.read_text().splitlines()[0]


def one_line(res) -> str:
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1, res.output
    return lines[0]


@pytest.mark.parametrize("args,flag", [
    (["--for", "ardupilot"], "--firmware"),                  # which release?
    (["--for", "px4", "--firmware", "ardupilot-4.6"], "--firmware"),
    (["--firmware", "ardupilot-4.8"], "--firmware"),
    ([], "--for"),
    (["--for", "px4", "--delay-ms", "-1"], "--delay-ms"),
    (["--for", "px4", "--delay-ms", "nan"], "--delay-ms"),
    (["--for", "px4", "--delay-ms", "inf"], "--delay-ms"),
    (["--firmware", "ardupilot-4.6", "--delay-ms", "1000"], "--delay-ms"),
])
def test_bad_flags_are_one_line_naming_the_flag_and_nothing_is_written(rig_file, args, flag):
    res = CliRunner().invoke(app, ["autopilot", "--rig", str(rig_file), *args])
    assert one_line(res).startswith(f"ceilcal: error: {flag}: ")
    assert sorted(p.name for p in rig_file.parent.iterdir()) == ["rig.yaml"]


def test_an_existing_parameter_file_is_kept_without_force(rig_file, tmp_path):
    out = tmp_path / "ap.param"
    out.write_text("MINE,1\n")
    args = ["autopilot", "--rig", str(rig_file), "--firmware", "ardupilot-4.6",
            "--out", str(out)]
    line = one_line(CliRunner().invoke(app, args))
    assert str(out) in line and "--force" in line and out.read_text() == "MINE,1\n"
    res = CliRunner().invoke(app, args + ["--force"])
    assert res.exit_code == 0, res.output
    assert load_param(out)["GPS1_TYPE"] == 0
