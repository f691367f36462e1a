"""Nothing a user made is overwritten (issue 40, item 1): every output kind refuses an
existing file in one line naming it and ``--force``; no output may be an input, lie
inside an input recording, or be another output of the run; two runs cannot write one
folder at once (the lock). Table-driven: one row per output kind, one per overlap."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app as ceilcal
from ceilkit.cli.ceilrun import app as ceilrun
from ceilkit.runtime.errors import OutputError
from ceilkit.runtime.io.outputs import LOCK_NAME, FolderLock, file_lock
from ceilkit.runtime.replay import replay
from helpers import CONFIGS, FIXTURES, held_elsewhere

run = CliRunner().invoke
REC = FIXTURES / "corridor_rec"
MARK = b"what the user made\n"


@pytest.fixture
def rec(tmp_path):
    """A copy of the 8-frame corridor recording."""
    return shutil.copytree(REC, tmp_path / "rec")


def _refused(res, tool: str, *words: str) -> str:
    """The run failed with exit 1 and exactly one stderr line holding ``words``."""
    assert res.exit_code == 1, (res.output, res.exception)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{tool}: error: "), res.stderr
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]




# -- one row per output kind: (tool, file made by the user, arguments) ---------------------
KINDS = [
    ("ceilrun", "o/poses.csv", ["replay", "{rec}", "--out", "{t}/o", "--method", "corridor"]),
    ("ceilrun", "o/poses.tum", ["replay", "{rec}", "--out", "{t}/o", "--tum"]),
    ("ceilrun", "o/truth.tum", ["replay", "{rec}", "--out", "{t}/o", "--tum"]),
    ("ceilrun", "o/report.html", ["replay", "{rec}", "--out", "{t}/o", "--report"]),
    ("ceilrun", "ov/000003.png", ["replay", "{rec}", "--out", "{t}/o", "--overlays",
                                  "{t}/ov"]),
    ("ceilrun", "link.nmea", ["replay", "{rec}", "--out", "{t}/o", "--serial",
                              "{t}/link.nmea"]),
    ("ceilrun", "o/poses.csv", ["--device", "sim:corridor", "--frames", "2", "--out",
                                "{t}/o"]),
    ("ceilrun", "link.nmea", ["--device", "sim:corridor", "--frames", "2", "--serial",
                              "{t}/link.nmea"]),
    ("ceilcal", "cam.yaml", ["intrinsics", "{t}", "--board", "chess:9x6", "--square",
                             "0.025", "--out", "{t}/cam.yaml"]),
    ("ceilcal", "cam.yaml", ["intrinsics", "--ceiling", "{rec}", "--out", "{t}/cam.yaml"]),
    ("ceilcal", "rig.yaml", ["mount", "{t}/p.yaml", "--site", "{rec}/site.yaml",
                             "--camera", "{t}/c.yaml", "--out", "{t}/rig.yaml"]),
    ("ceilcal", "rig.urdf.xml", ["mount", "{t}/p.yaml", "--site", "{rec}/site.yaml",
                                 "--camera", "{t}/c.yaml", "--out", "{t}/rig.yaml"]),
    ("ceilcal", "site.yaml", ["lightmap", "{rec}", "--out", "{t}/site.yaml"]),
    ("ceilcal", "capture.yaml", ["exposure", "--device", "sim:lights", "--out",
                                 "{t}/capture.yaml"]),
    ("ceilcal", "chk/check-site.yaml", ["check-site", "--rig", "{rec}/rig.yaml", "--site",
                                        "{rec}/site.yaml", "--out", "{t}/chk"]),
    # every file of an --out folder, the --plots of each command, the single files
    ("ceilrun", "o/run.yaml", ["replay", "{rec}", "--out", "{t}/o", "--method", "corridor"]),
    ("ceilrun", "o/run.yaml", ["--device", "sim:corridor", "--frames", "2", "--out",
                               "{t}/o"]),
    ("ceilcal", "pl/views.png", ["intrinsics", "{t}", "--board", "chess:9x6", "--square",
                                 "0.025", "--out", "{t}/cam.yaml", "--plots", "{t}/pl"]),
    ("ceilcal", "pl/mount_residuals.png", ["mount", "{t}/p.yaml", "--site",
                                           "{rec}/site.yaml", "--camera", "{t}/c.yaml",
                                           "--out", "{t}/rig.yaml", "--plots", "{t}/pl"]),
    ("ceilcal", "pl/lightmap.png", ["lightmap", "{rec}", "--out", "{t}/site.yaml", "--plots",
                                    "{t}/pl"]),
    ("ceilcal", "b.pdf", ["board", "--board", "chess:9x6", "--square", "0.025", "--out",
                          "{t}/b.pdf"]),
    ("ceilcal", "ap.param", ["autopilot", "--rig", "{rec}/rig.yaml", "--firmware",
                             "ardupilot-4.6", "--out", "{t}/ap.param"]),
]


@pytest.mark.parametrize(("tool", "made", "args"), KINDS,
                         ids=[f"{t}-{' '.join(a[:1])}-{m}" for t, m, a in KINDS])
def test_an_existing_output_is_refused_naming_it_and_force(tmp_path, rec, tool, made, args):
    target = tmp_path / made
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(MARK)
    argv = [a.format(rec=rec, t=tmp_path) for a in args]
    line = _refused(run(ceilrun if tool == "ceilrun" else ceilcal, argv), tool,
                    str(target), "already there", "--force")
    assert "force=True" not in line
    assert target.read_bytes() == MARK


# -- one row per calibration file: not replaced while another run writes it ---------------
LONE = [k for k in KINDS if k[0] == "ceilcal" and "/" not in k[1] and k[1] != "rig.urdf.xml"]


@pytest.mark.parametrize(("tool", "made", "args"), LONE, ids=[f"{a[0]}-{m}" for _, m, a in LONE])
def test_a_calibration_file_being_written_is_refused_even_with_force(tmp_path, rec, tool,
                                                                     made, args):
    target = tmp_path / made
    target.write_bytes(MARK)
    argv = [a.format(rec=rec, t=tmp_path) for a in args] + ["--force"]
    with held_elsewhere(file_lock(target)):  # another run is writing it
        _refused(run(ceilcal, argv), tool, f"{target}: another run", "is writing it",
                 f".{made}{LOCK_NAME}", "nothing was written")
    assert target.read_bytes() == MARK
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == [made]


def test_a_plots_folder_is_locked_and_never_an_input(tmp_path, rec):
    argv = ["lightmap", str(rec), "--out", str(tmp_path / "site.yaml"), "--plots"]
    with held_elsewhere(FolderLock(tmp_path / "pl")):
        _refused(run(ceilcal, [*argv, str(tmp_path / "pl")]), "ceilcal", "another run")
    frames = sorted(p.name for p in (rec / "frames").iterdir())
    _refused(run(ceilcal, [*argv, str(rec / "frames")]), "ceilcal", "--plots",
             "is an input of this run")
    assert sorted(p.name for p in (rec / "frames").iterdir()) == frames
    assert not (tmp_path / "site.yaml").exists()


def test_the_guided_calibration_refuses_plots_it_would_replace_naming_redo(tmp_path, rec):
    (tmp_path / "pl").mkdir()
    (tmp_path / "pl" / "views.png").write_bytes(MARK)
    line = _refused(run(ceilcal, [
        "calibrate", "--boards", str(tmp_path / "b"), "--board", "chess:9x6", "--square",
        "0.025", "--placements", str(tmp_path / "p.yaml"), "--site", str(rec / "site.yaml"),
        "--out", str(tmp_path / "cal"), "--plots", str(tmp_path / "pl")]),
        "ceilcal", str(tmp_path / "pl" / "views.png"), "already there", "--redo")
    assert "--force" not in line
    assert (tmp_path / "pl" / "views.png").read_bytes() == MARK
    assert not (tmp_path / "cal").exists()  # its lock made it and took it away


# -- one row per overlap of an output with an input or another output --------------------
OVERLAPS = [
    (["--serial", "{rec}/frames/000000.png"], "--serial", "lies inside an input",
     "frames/000000.png"),
    (["--overlays", "{rec}/frames"], "--overlays", "is an input", "frames/000000.png"),
    (["--overlays", "{rec}/frames/sub"], "--overlays", "lies inside an input",
     "frames/000000.png"),
    (["--serial", "{t}/o/poses.csv"], "--serial", "already an output", None),
    (["--serial", "{rec}/truth.csv"], "--serial", "is an input", "truth.csv"),
    (["--odometry", "{t}/odo.csv", "--serial", "{t}/odo.csv"], "--serial", "is an input",
     "../odo.csv"),
]


@pytest.mark.parametrize(("extra", "flag", "what", "kept"), OVERLAPS,
                         ids=[" ".join(o[0][:2]) for o in OVERLAPS])
def test_an_output_over_an_input_is_one_refusing_line(tmp_path, rec, extra, flag, what,
                                                      kept):
    (tmp_path / "odo.csv").write_text("t_ns,dx,dy,dyaw_deg\n")
    before = (rec / kept).read_bytes() if kept else None
    argv = ["replay", str(rec), "--out", str(tmp_path / "o")]
    argv += [a.format(rec=rec, t=tmp_path) for a in extra]
    _refused(run(ceilrun, argv), "ceilrun", flag, what)
    if kept:
        assert (rec / kept).read_bytes() == before
    assert not (tmp_path / "o").exists()  # nothing was written


def test_calibration_outputs_may_not_be_inputs(tmp_path, rec):
    site = (rec / "site.yaml").read_bytes()
    _refused(run(ceilcal, ["lightmap", str(rec), "--out", str(rec / "site.yaml"),
                           "--force"]), "ceilcal", "--out", "is an input")
    assert (rec / "site.yaml").read_bytes() == site
    rig = rec / "rig.yaml"
    before = rig.read_bytes()
    _refused(run(ceilcal, ["mount", str(tmp_path / "p.yaml"), "--site",
                           str(rec / "site.yaml"), "--rig", str(rig), "--out", str(rig),
                           "--force"]), "ceilcal", "--out", "is an input")
    assert rig.read_bytes() == before


# -- the lock -------------------------------------------------------------------------------
def test_a_folder_being_written_is_refused_and_released(tmp_path, rec):
    out = tmp_path / "o"
    with held_elsewhere(FolderLock(out)):  # another run holds it
        line = _refused(run(ceilrun, ["replay", str(rec), "--out", str(out)]), "ceilrun",
                        str(out), "another run", "is writing here", LOCK_NAME)
        assert "nothing was written" in line and not (out / "poses.csv").exists()
        _refused(run(ceilrun, ["--device", "sim:corridor", "--frames", "2", "--record",
                               str(out)]), "ceilrun", "another run")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    assert not out.exists()  # the lock made the folder and took it away again
    res = replay(rec, out, method="corridor", track=False)
    assert res.telemetry.frames == 8
    assert len((out / "poses.csv").read_text().splitlines()) == 9  # 8 rows, no more
    assert not (out / LOCK_NAME).exists()


def test_a_lock_held_by_another_process_names_its_pid(tmp_path, rec):
    out = tmp_path / "o"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys\nfrom ceilkit.runtime.io.outputs import "
         "FolderLock\nwith FolderLock(sys.argv[1]):\n    print('held', flush=True)\n"
         "    sys.stdin.read()\n", str(out)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputError, match=f"another run \\(pid {holder.pid}\\)"):
            replay(rec, out)
        assert not (out / "poses.csv").exists()
    finally:
        holder.stdin.close()
        holder.wait()
    assert replay(rec, out, method="corridor", track=False).telemetry.frames == 8


def test_a_stale_lock_is_taken_over_with_a_line(tmp_path, rec, log_lines):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # its pid is dead
    out = tmp_path / "o"
    out.mkdir()
    (out / LOCK_NAME).write_text(f"{gone.pid}\n")
    res = replay(rec, out, method="corridor", track=False)
    assert res.telemetry.frames == 8
    assert any(f"took over the stale lock of pid {gone.pid}" in ln for ln in log_lines)
    assert not (out / LOCK_NAME).exists()


def test_a_numbered_recording_keeps_what_exists(tmp_path):
    (tmp_path / "r-1").mkdir()
    (tmp_path / "r-1" / "frames.csv").write_bytes(MARK)
    res = run(ceilrun, ["--device", "sim:corridor", "--frames", "2", "--record",
                        str(tmp_path / "r-{n}"), "--rig",
                        str(CONFIGS / "corridor" / "rig.yaml")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r-1" / "frames.csv").read_bytes() == MARK
    assert len((tmp_path / "r-2" / "frames.csv").read_text().splitlines()) == 3


def test_a_command_without_force_never_names_it(tmp_path):
    """``ceilcal simulate`` replaces nothing: its refusal says to choose another output
    (it has no ``--force``), and placements never go into an existing recording."""
    out = tmp_path / "sim"
    assert run(ceilcal, ["simulate", "--out", str(out), "--frames", "2"]).exit_code == 0
    before = sorted(p.name for p in out.iterdir())
    line = _refused(run(ceilcal, ["simulate", "--out", str(out), "--frames", "2"]),
                    "ceilcal", str(out), "choose another output")
    assert "--force" not in line
    _refused(run(ceilcal, ["simulate", "--out", str(out), "--kind", "placements"]),
             "ceilcal", str(out), "a recording")
    assert sorted(p.name for p in out.iterdir()) == before
