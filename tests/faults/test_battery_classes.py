"""The battery's later classes as tests (issue 40, item 6), one table each: a conversion
never writes into or onto its source and is locked like every output; a simulation's
folder is locked; a ChArUco board's bad ``--marker``, ``--paper`` and sizes; every
numeric flag given an empty string or a number with a unit; a recording's frame empty,
garbage, of another resolution or missing (/dev/null, a symlink loop and an unreadable
file as every YAML and CSV input: ``test_input_limits.py``)."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
import typer.main
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app as ceilcal
from ceilkit.cli.ceilrun import app as ceilrun
from ceilkit.cli.values import OWN_CHECKS, flag_name, numeric_kind, range_of
from ceilkit.runtime.io.mcap_rec import convert_recording
from ceilkit.runtime.io.outputs import FolderLock
from helpers import FIXTURES, held_elsewhere

run = CliRunner().invoke
REC = FIXTURES / "corridor_rec"


@pytest.fixture
def rec(tmp_path):
    """A copy of the 8-frame corridor recording."""
    return shutil.copytree(REC, tmp_path / "rec")


def _one_line(res, tool: str, *words: str) -> str:
    """The run failed (exit 1 or 2) with exactly one stderr line holding ``words``."""
    assert res.exit_code in (1, 2), (res.output, res.exception)
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{tool}: error: "), res.stderr
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


# -- ceilrun convert: never into or onto its source; locked while written ----------------
CONVERTS = [  # (src, dst, --force, words of the line, what must stay as it was)
    ("{rec}", "{rec}/frames/x.mcap", False, ("DST", "lies inside an input"), "{rec}/frames"),
    ("{rec}", "{rec}/x.mcap", False, ("DST", "lies inside an input"), "{rec}"),
    ("{t}/in.mcap", "{t}/lnk", True, ("DST", "is an input"), "{t}/in.mcap"),
    ("{t}/in.mcap", "{rec}", False, ("{rec}", "a recording is already there", "--force"),
     "{rec}/frames"),
]


def _state(path):
    """What must not change: a folder's listing, a file's bytes."""
    return sorted(p.name for p in path.iterdir()) if path.is_dir() else path.read_bytes()


@pytest.mark.parametrize(("src", "dst", "force", "words", "kept"), CONVERTS,
                         ids=[f"{s} {d}" for s, d, *_ in CONVERTS])
def test_a_conversion_into_or_onto_its_source_is_one_line(tmp_path, rec, src, dst, force,
                                                          words, kept):
    convert_recording(rec, tmp_path / "in.mcap")
    (tmp_path / "lnk").symlink_to(tmp_path / "in.mcap")
    fill = {"rec": rec, "t": tmp_path}
    before = _state(type(tmp_path)(kept.format(**fill)))
    argv = ["convert", src.format(**fill), dst.format(**fill)] + (["--force"] if force else [])
    _one_line(run(ceilrun, argv), "ceilrun", *(w.format(**fill) for w in words))
    assert _state(type(tmp_path)(kept.format(**fill))) == before


def test_a_conversion_is_refused_while_another_run_writes_its_output(tmp_path, rec):
    convert_recording(rec, tmp_path / "in.mcap")
    out = tmp_path / "conv"
    with held_elsewhere(FolderLock(out)):  # another conversion into the folder
        _one_line(run(ceilrun, ["convert", str(tmp_path / "in.mcap"), str(out), "--force"]),
                  "ceilrun", str(out), "another run", "is writing here")
    assert not out.exists()
    mcap = tmp_path / "x.mcap"
    mcap.write_bytes(b"what the user made\n")
    with held_elsewhere(FolderLock(tmp_path, ".x.mcap.lock", subject=mcap)):  # a recording
        _one_line(run(ceilrun, ["convert", str(rec), str(mcap), "--force"]), "ceilrun",
                  str(mcap), "another run", "is writing it")
    assert mcap.read_bytes() == b"what the user made\n"
    assert convert_recording(tmp_path / "in.mcap", out) == 8  # and free again after
    assert not (out / ".ceilkit.lock").exists()


def test_a_simulation_folder_being_written_is_refused(tmp_path):
    out = tmp_path / "sim"
    with held_elsewhere(FolderLock(out)):
        _one_line(run(ceilcal, ["simulate", "--out", str(out), "--frames", "2"]), "ceilcal",
                  str(out), "another run")
    assert not out.exists()


# -- ceilcal board with a ChArUco board ----------------------------------------------------
CHARUCO = ["board", "--board", "charuco:5x7", "--square", "0.04"]
BOARDS = [(["--marker", v], "--marker") for v in
          ("nan", "inf", "-inf", "-1", "0", "1e308", "", "0.04", "0.05", "30mm")]
BOARDS += [(["--marker", "0.03", "--paper", v], "--paper") for v in ("", "a99", "210x297")]
BOARDS += [(["--marker", "0.03", "--square", "0.5"], "--square"),
           (["--marker", "0.03", "--board", "charuco:0x7"], "--board"),
           (["--marker", "0.03", "--board", "charuco:5x7:NO_SUCH_DICT"], "--board")]


@pytest.mark.parametrize(("extra", "flag"), BOARDS, ids=[" ".join(e) for e, _ in BOARDS])
def test_a_bad_charuco_board_is_one_line_naming_its_flag(tmp_path, extra, flag):
    out = tmp_path / "b.pdf"
    _one_line(run(ceilcal, [*CHARUCO, *extra, "--out", str(out)]), "ceilcal", flag)
    assert not out.exists()


# -- every numeric flag, from the CLI's own table: empty, or a number with a unit ---------
UNITS = {"m": "mm", "m/s": "km/h", "s": "ms", "ms": "s", "degrees": "rad", "Hz": "kHz",
         "px": "mm", "bit/s": "kbit/s", "frames": "s"}


def _numeric():
    for prog, app in (("ceilrun", ceilrun), ("ceilcal", ceilcal)):
        top = typer.main.get_command(app)
        for name, cmd in [("", top), *top.commands.items()]:
            for p in cmd.params:
                if numeric_kind(p) is not None and name not in OWN_CHECKS:
                    yield pytest.param(prog, app, name, cmd, p,
                                       id=f"{prog} {name} {flag_name(p)}".replace("  ", " "))


def _required(cmd, name):
    out = []
    for p in cmd.params:
        if getattr(p, "required", False):
            kind, flag = numeric_kind(p), flag_name(p)
            value = f"{range_of(name, flag).hi:g}" if kind else "x"
            out += [value] if p.param_type_name == "argument" else [flag, value]
    return out


@pytest.mark.parametrize(("prog", "app", "name", "cmd", "param"), list(_numeric()))
def test_an_empty_or_unit_suffixed_number_is_one_line_naming_its_flag(prog, app, name, cmd,
                                                                      param):
    flag = flag_name(param)
    span = range_of(name, flag)
    unit = UNITS.get(span.unit.split(" (")[0], "x")
    for text in ("", f"{max(min(1.0, span.hi), span.lo + 1e-3):g}{unit}"):
        res = run(app, [*([name] if name else []), *_required(cmd, name), f"{flag}={text}"])
        _one_line(res, prog, f"{flag}: ")


# -- a recording's frame: empty, garbage, another resolution, missing ---------------------
def _png(shape=None) -> bytes:
    img = cv2.imread(str(REC / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
    if shape is not None:
        img = cv2.resize(img, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return cv2.imencode(".png", img)[1].tobytes()


FRAMES = {  # how frame 2 is damaged -> its bytes (None: removed), what the run does
    "zero bytes": (b"", "row", "empty file"),
    "garbage": (np.random.default_rng(2).bytes(40_000), "row", "cannot decode"),
    "half the resolution": (_png((240, 320)), "refused", "the image is 320x240 but"),
    "1x1 px": (_png((1, 1)), "refused", "the image is 1x1 but"),
    "missing": (None, "refused", "frame file frames/000002.png is missing"),
}
"""A damaged file is a failed row (``bad_frame``, named); a frame that is not of the
rig's camera, or a row with no file, is not a recording SPEC §2 allows: the replay is
refused in one line naming the file (a row of frames.csv, a frame)."""


@pytest.mark.parametrize("how", sorted(FRAMES))
def test_a_damaged_or_odd_frame_is_a_named_failure_or_refusal(tmp_path, rec, how, log_lines):
    data, does, words = FRAMES[how]
    path = rec / "frames" / "000002.png"
    path.unlink() if data is None else path.write_bytes(data)
    argv = ["replay", str(rec), "--out", str(tmp_path / "o"), "--method", "corridor",
            "--option", "assume_heading_deg=0"]
    res = run(ceilrun, argv)
    if does == "refused":
        _one_line(res, "ceilrun", words, "frames.csv" if data is None else str(path))
        return
    assert res.exit_code == 0, res.output
    yaw = [r.split(",")[3] for r in (tmp_path / "o" / "poses.csv").read_text().splitlines()]
    assert len(yaw) == 9 and yaw[3] == "" and yaw[4] != "" and yaw[1] != ""  # frame 2 only
    assert any(str(path) in ln and words in ln and "bad_frame" in ln for ln in log_lines)


# -- odometry over the link out of bounds: refused and counted, never raised ---------------
def _pceio(body: str) -> bytes:
    x = 0
    for c in body.encode():
        x ^= c
    return f"${body}*{x:02X}".encode()


PCEIO = {  # a $PCEIO body with a correct checksum -> refused (False) or malformed (True)
    "dx 1e308": ("PCEIO,100,1e308,0,0", False),
    "dy -1e308": ("PCEIO,100,0,-1e308,0", False),
    "dyaw 1e308 deg": ("PCEIO,100,0,0,1e308", False),
    "all 1e308": ("PCEIO,100,1e308,-1e308,1e308", False),
    "dx 900 m": ("PCEIO,100,900,0,0", False),
    "dx 1e400 (inf)": ("PCEIO,100,1e400,0,0", True),
    "a 31-digit stamp": ("PCEIO,1000000000000000000000000000000,0.01,0,0", True),
    "a stamp of 1.5 ms": ("PCEIO,1.5,0.01,0,0", True),
    "a stamp of -5 ms": ("PCEIO,-5,0.01,0,0", True),
}


@pytest.mark.parametrize("name", sorted(PCEIO))
def test_link_odometry_out_of_bounds_is_refused_and_counted(name):
    from ceilkit.runtime.fusion import Fusion
    from ceilkit.runtime.io.link.transport import Received
    from ceilkit.runtime.io.odometry_in import OdometryReceiver

    body, malformed = PCEIO[name]
    fusion = Fusion()
    rx = OdometryReceiver(fusion.add_odometry)
    rx(Received(0, _pceio(body), ""))
    assert (rx.bad, rx.refused) == ((1, 0) if malformed else (0, 1)), (rx.bad, rx.refused)
    assert fusion.odometry_refused == (0 if malformed else 1)


CALIBRATIONS = [  # (fixture, arguments, exit code: the corridor is no tiled ceiling)
    ("lights_rec", ["lightmap", "{rec}", "--out", "{t}/site.yaml"], 0),
    ("corridor_rec", ["intrinsics", "--ceiling", "{rec}", "--out", "{t}/cam.yaml"], 1),
]


@pytest.mark.parametrize(("fixture", "args", "code"), CALIBRATIONS,
                         ids=[a[0] for _, a, _ in CALIBRATIONS])
def test_a_calibration_skips_a_damaged_frame_naming_it(tmp_path, fixture, args, code,
                                                        log_lines):
    rec = shutil.copytree(FIXTURES / fixture, tmp_path / "rec")
    (rec / "frames" / "000002.png").write_bytes(b"")
    res = run(ceilcal, [a.format(rec=rec, t=tmp_path) for a in args])
    assert res.exit_code == code and (res.exception is None
                                      or isinstance(res.exception, SystemExit)), res.output
    assert f"{rec}/frames/000002.png: empty file: skipped (bad_frame)" in log_lines
