"""Files are read with limits (runtime/config/inputs.py): every YAML and CSV input,
given a FIFO, a device, a folder or a file over its size cap, is one line naming it
(never a block, a MemoryError or an endless read); a pathological YAML (a huge key,
a huge or base-60 number) is one short line, not a hang; numbers are bounded before
any arithmetic; table rows out of time order are refused, not sorted silently."""

from __future__ import annotations

import os
import shutil
import threading

import pytest
from typer.testing import CliRunner

from ceilkit.calib.mount import load_placements
from ceilkit.calib.poses import load_pose_csv
from ceilkit.cli.ceilrun import app
from ceilkit.runtime.config.camera import load_camera
from ceilkit.runtime.config.capture import load_capture
from ceilkit.runtime.config.inputs import CSV_MAX_BYTES, YAML_MAX_BYTES
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.tables import load_odometry, load_poses, load_truth
from ceilkit.runtime.sim.realism import load_presets
from helpers import CONFIGS, FIXTURES

CAMERA = load_camera(CONFIGS / "corridor" / "camera.yaml")

READERS = {   # an input a user gives -> how it is read, and its size cap
    "rig.yaml": (Rig.load, YAML_MAX_BYTES),
    "site.yaml": (Site.load, YAML_MAX_BYTES),
    "camera.yaml": (load_camera, YAML_MAX_BYTES),
    "capture.yaml": (load_capture, YAML_MAX_BYTES),
    "presets.yaml": (load_presets, YAML_MAX_BYTES),
    "placements.yaml": (lambda p: load_placements(p, CAMERA), YAML_MAX_BYTES),
    "truth.csv": (load_truth, CSV_MAX_BYTES),
    "odometry.csv": (load_odometry, CSV_MAX_BYTES),
    "poses.csv": (load_poses, CSV_MAX_BYTES),
    "mocap.csv": (load_pose_csv, CSV_MAX_BYTES),
}


def _fifo(path, cap):
    os.mkfifo(path)


def _folder(path, cap):
    path.mkdir()


def _device(path, cap):
    path.symlink_to("/dev/zero")


def _too_large(path, cap):
    with open(path, "wb") as fh:   # sparse: nothing is written, the size says it
        fh.truncate(cap + 1)


def _unreadable(path, cap):
    """A file whose reads fail: mode 000 for a user; as root (who reads anything), a
    link to ``/proc/self/mem``, which opens and fails every read."""
    if os.geteuid() == 0:
        path.symlink_to("/proc/self/mem")
    else:
        path.write_text("a: 1\n")
        path.chmod(0)


SPECIAL = {
    "a FIFO": (_fifo, "expected a regular file, found a FIFO (named pipe)"),
    "a folder": (_folder, "expected a regular file, found a folder"),
    "/dev/zero": (_device, "expected a regular file, found a character device"),
    "/dev/null": (lambda p, cap: p.symlink_to("/dev/null"),
                  "expected a regular file, found a character device"),
    "a symlink loop": (lambda p, cap: p.symlink_to(p),
                       "cannot read: Too many levels of symbolic links"),
    "unreadable": (_unreadable, "cannot read: "),
    "over the cap": (_too_large, "expected a file of at most "),
}


@pytest.mark.parametrize("name,special", [
    (name, special) for name in READERS for special in SPECIAL
    if (name, special) != ("placements.yaml", "a folder")])   # a recording: its placements
def test_a_special_file_is_one_line_naming_it(tmp_path, name, special):
    read, cap = READERS[name]
    make, words = SPECIAL[special]
    path = tmp_path / name
    make(path, cap)
    done = threading.Event()
    if special == "a FIFO":   # a reader that blocked would be released by a writer
        threading.Thread(target=_release_fifo, args=(path, done), daemon=True).start()
    try:
        with pytest.raises(ConfigError) as err:
            read(path)
    finally:
        done.set()
    assert str(err.value).startswith(f"{path}: {words}"), str(err.value)
    assert "\n" not in str(err.value)


def _release_fifo(path, done):
    """Open the FIFO for writing once the test is over: unblocks a reader that waited
    (which then fails the test by what it read), harmless when none did."""
    done.wait()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)
    except OSError:   # no reader: nothing to release
        pass


RIG = (CONFIGS / "corridor" / "rig.yaml").read_text()

YAMLS = {   # a rig.yaml that once hung, raised or printed megabytes -> its one line
    "a 50 kB unknown key": (RIG + "? " + "k" * 50_000 + "\n: 1\n",
                            "kkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkk... (50000 characters): "
                            "unknown key (allowed here: camera, mount)"),
    "a 50 kB plain key": (RIG + "k" * 50_000 + ": 1\n",
                          "invalid YAML at line 4, column 50001: could not find expected ':'"),
    "a 100 000-digit key": (RIG + "? " + "9" * 100_000 + "\n: 1\n",
                            "invalid YAML at line 4, column 3: a number of 100000 characters "
                            "(at most 64)"),
    "a base-60 number of 30 000 parts": (
        RIG.replace("z: 0.80}", "z: " + ":".join(["59"] * 30_000) + "}"),
        "invalid YAML at line 3, column 64: a number of 89999 characters (at most 64)"),
    "a number past a float": (RIG.replace("z: 0.80}", "z: 1.0e+400}"),
                              "mount.z: expected a finite number m, found inf"),
    "100 000 nested lists": (RIG + "x: " + "[" * 100_000 + "\n",  # a RecursionError once
                             "invalid YAML: nested too deeply (thousands of levels; a "
                             "config file has a few)"),
}


@pytest.mark.parametrize("case", YAMLS)
def test_a_pathological_yaml_is_one_short_line(tmp_path, case):
    text, line = YAMLS[case]
    shutil.copy(CONFIGS / "corridor" / "camera.yaml", tmp_path)
    (tmp_path / "rig.yaml").write_text(text)
    with pytest.raises(ConfigError) as err:
        Rig.load(tmp_path / "rig.yaml")
    assert str(err.value) == f"{tmp_path / 'rig.yaml'}: {line}"


NUMBERS = [   # (file, text replaced, by, the line's end): bounded before arithmetic
    ("camera.yaml", "data: [-0.08,", "data: [1.0e+308,",
     "distortion_coefficients.data[0]: expected a number in [-1000, 1000], found 1e+308"),
    ("camera.yaml", "data: [400.0,", "data: [1.0e+300,",
     "camera_matrix.data[0]: expected a number in [-1e+06, 1e+06], found 1e+300"),
    ("site.yaml", "lines_along: [", "lines_along: [1.0e+300, ",
     "corridor.lines_along[0]: expected a number in [-1e+09, 1e+09], found 1e+300"),
]


@pytest.mark.parametrize("name,old,new,line", NUMBERS)
def test_a_huge_number_in_a_config_names_the_file_and_key(tmp_path, name, old, new, line):
    text = (CONFIGS / "corridor" / name).read_text()
    assert old in text
    (tmp_path / name).write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError) as err:
        (load_camera if name == "camera.yaml" else Site.load)(tmp_path / name)
    assert str(err.value) == f"{tmp_path / name}: {line}"


CSVS = [   # (file, its text, the line's end)
    ("truth.csv", "t_ns,x,y,yaw_deg\n0,0,0,0\n200,1,0,0\n100,2,0,0\n",
     "line 4: t_ns: stamps must increase (rows in time order), found 100 after 200"),
    ("odometry.csv", "t_ns,dx,dy,dyaw_deg\n0,0,0,0\n100,1e308,0,0\n",
     "line 3: dx: expected a number in [-1000, 1000], found '1e308'"),
    ("odometry.csv", "t_ns,dx,dy,dyaw_deg\n0,0,0,0\n100,0,0,1e6\n",
     "line 3: dyaw_deg: expected a number in [-3600, 3600], found '1e6'"),
    ("truth.csv", "t_ns,x,y,yaw_deg\n" + "9" * 5000 + ",0,0,0\n",
     "line 2: t_ns: expected an integer, found '99999999999999999999'... (5000 characters)"),
    ("truth.csv", "t_ns,x,y,yaw_deg\n0,nan,0,0\n", "line 2: x: expected a number, found 'nan'"),
    ("truth.csv", "t_ns,x,y,yaw_deg\n0," + "1" * 200_000 + ",0,0\n",
     "line 2: not CSV: field larger than field limit (131072)"),
    ("truth.csv", "t_ns,x,y,yaw_deg\n0,\xff,0,0\n".encode("latin-1"),
     "line 2: not UTF-8 text: byte 0xff (save the file as UTF-8)"),
]


@pytest.mark.parametrize("name,text,line", CSVS)
def test_a_bad_table_row_is_one_line_naming_file_line_and_column(tmp_path, name, text, line):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError) as err:
        (load_truth if name == "truth.csv" else load_odometry)(path)
    assert str(err.value) == f"{path}: {line}"


run = CliRunner().invoke


@pytest.mark.parametrize("what", ["rig", "site"])
def test_the_command_line_says_it_in_one_line(tmp_path, what):
    os.mkfifo(tmp_path / f"{what}.yaml")
    res = run(app, ["replay", str(FIXTURES / "corridor_rec"), "--out", str(tmp_path / "o"),
                    f"--{what}", str(tmp_path / f"{what}.yaml")])
    assert res.exit_code == 1
    assert res.stderr.strip().splitlines()[-1] == (
        f"ceilrun: error: {tmp_path / what}.yaml: expected a regular file, found a FIFO "
        "(named pipe)")
    assert not (tmp_path / "o").exists()


def test_a_recording_with_truth_out_of_order_is_refused(tmp_path):
    rec = tmp_path / "rec"
    shutil.copytree(FIXTURES / "corridor_rec", rec)
    rows = (rec / "truth.csv").read_text().splitlines()
    rows[2], rows[3] = rows[3], rows[2]
    (rec / "truth.csv").write_text("\n".join(rows) + "\n")
    res = run(app, ["replay", str(rec), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1
    assert res.stderr.strip().splitlines()[-1].startswith(
        f"ceilrun: error: {rec / 'truth.csv'}: line 4: t_ns: stamps must increase")


@pytest.mark.parametrize("special", ["a FIFO", "/dev/zero", "a folder"])
def test_an_mcap_recording_that_is_no_file_is_one_line(tmp_path, special):
    """An MCAP recording has no size cap (it is read as a stream), but it must be a
    regular file: a FIFO would block, /dev/zero never end."""
    from ceilkit.runtime.io.mcap_rec import open_recording

    make, words = SPECIAL[special]
    path = tmp_path / "run.mcap"
    make(path, 0)
    with pytest.raises(ConfigError) as err:
        open_recording(path)
    assert str(err.value) == f"{path}: {words}"


def _view(token):
    import contextlib

    from ceilkit.runtime.viz.web import open_view

    with contextlib.ExitStack() as stack:
        open_view(None, token, None, None, stack)


def _capture(**kw):
    from ceilkit.runtime.session import CaptureSettings

    CaptureSettings(**kw)


def _start_pose(text):
    from ceilkit.runtime.multi import parse_start_pose

    parse_start_pose(text)


def _sim_drive(n):
    from ceilkit.runtime.sim.render import straight_drive

    straight_drive(n)


LIBRARY = [   # (call, the parameter the ConfigError names): the CLI shows it as its flag
    (lambda: _view(""), "view_token"),
    (lambda: _capture(fourcc="TOOLONG"), "fourcc"),
    (lambda: _capture(width=-1), "width"),
    (lambda: _capture(fps=float("nan")), "fps"),
    (lambda: _start_pose("1e308,0,0"), "start_pose"),
    (lambda: _start_pose("0,0,1e9"), "start_pose"),
    (lambda: _sim_drive(10**12), "n"),
]


@pytest.mark.parametrize("call,key", LIBRARY, ids=[k for _, k in LIBRARY])
def test_the_library_refuses_a_bad_value_naming_its_parameter(call, key):
    with pytest.raises(ConfigError) as err:
        call()
    assert err.value.key == key and err.value.path is None


EMPTY_PATHS = [  # an empty path flag (an unset shell variable) is read as '.' once converted
    ["--device", "sim:corridor", "--rig", ""],
    ["--device", "sim:corridor", "--out", ""],
    ["--device", "sim:corridor", "--capture", ""],
    ["replay", "x", "--overlays", ""],
    ["replay", ""],
]


@pytest.mark.parametrize("argv", EMPTY_PATHS, ids=[" ".join(a[-2:]) for a in EMPTY_PATHS])
def test_an_empty_path_flag_is_refused_naming_it(argv):
    res = CliRunner().invoke(app, argv)
    flag = argv[-2] if argv[-2].startswith("--") else "RECORDING"
    assert res.exit_code == 1, res.output
    assert res.stderr.strip() == f"ceilrun: error: {flag}: expected a value, found an " \
                                 "empty string"
