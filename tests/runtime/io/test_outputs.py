"""The output claim and its locks (issue 40): :func:`claim_outputs` refuses what exists,
an output over an input and two outputs on one file; :class:`FolderLock` and
:func:`file_lock` keep a second run out while the first writes (another thread or
process), are taken again by the run that holds them, skip devices, and leave nothing
behind."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys

import pytest

from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.outputs import (
    LOCK_NAME,
    FolderLock,
    claim_outputs,
    claimed,
    file_lock,
)
from helpers import held_elsewhere


def test_a_lone_file_is_locked_beside_it_while_claimed(tmp_path):
    cam = tmp_path / "camera.yaml"
    lock = tmp_path / f".camera.yaml{LOCK_NAME}"
    with claimed({"out": [cam]}):
        assert lock.read_text().strip() == str(os.getpid())
    assert not lock.exists() and sorted(tmp_path.iterdir()) == []


def test_a_file_being_written_is_refused_naming_the_pid(tmp_path):
    cam = tmp_path / "camera.yaml"
    with held_elsewhere(file_lock(cam)), pytest.raises(
            OutputError, match=f"another run \\(pid {os.getpid()}\\) is writing"):
        with claimed({"out": [cam]}, force=True):
            cam.write_text("second\n")
    assert not cam.exists()


def test_a_file_locked_by_another_process_is_refused(tmp_path):
    cam = tmp_path / "rig.yaml"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys\nfrom ceilkit.runtime.io.outputs import "
         "file_lock\nwith file_lock(sys.argv[1]):\n    print('held', flush=True)\n"
         "    sys.stdin.read()\n", str(cam)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputError, match=f"pid {holder.pid}"):
            with claimed({"out": [cam]}):
                pass
    finally:
        holder.stdin.close()
        holder.wait()
    with claimed({"out": [cam]}):  # free again
        pass


def test_an_existing_output_is_refused_under_the_lock(tmp_path):
    cam = tmp_path / "camera.yaml"
    cam.write_text("mine\n")
    with pytest.raises(ConfigError, match="camera.yaml: already there; nothing was "
                       "overwritten"), claimed({"out": [cam]}):
        pass
    assert cam.read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.yaml"]
    with claimed({"out": [cam]}, force=True):
        pass


def test_the_holding_thread_takes_its_lock_again(tmp_path):
    """A step of a run (the guided calibration's mount, its plots in the locked
    ``--out``) claims a folder the run holds: taken again, released with the outer."""
    out = tmp_path / "cal"
    with FolderLock(out):
        with claimed({"plots": [out / "mount_residuals.png"]}, folders={"plots": [out]}):
            assert (out / LOCK_NAME).exists()
        assert (out / LOCK_NAME).exists()  # the outer still holds it
        with held_elsewhere(FolderLock(tmp_path / "x")), pytest.raises(OutputError):
            with FolderLock(tmp_path / "x"):
                pass
    assert not out.exists()


def test_files_in_a_locked_folder_take_no_lock_of_their_own(tmp_path):
    out = tmp_path / "o"
    with contextlib.ExitStack() as stack:
        claim_outputs({"out": [out / "poses.csv", out / "run.yaml"]},
                      folders={"out": [out]}, stack=stack)
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


def test_a_device_written_to_gets_no_lock_beside_it(tmp_path):
    """``--serial /dev/null``-like outputs: no lock file is made in ``/dev``."""
    with contextlib.ExitStack() as stack:
        claim_outputs({"link": [os.devnull]}, stack=stack)
        assert not os.path.exists(os.path.join(os.path.dirname(os.devnull),
                                               f".null{LOCK_NAME}"))


@pytest.mark.parametrize(("outputs", "folders", "inputs", "what"), [
    ({"out": ["{t}/a.yaml"]}, {}, ["{t}/a.yaml"], "is an input of this run"),
    ({"plots": ["{t}/rec/frames/x.png"]}, {"plots": ["{t}/rec/frames"]}, ["{t}/rec/frames"],
     "is an input of this run"),
    ({"plots": ["{t}/rec/frames/p/x.png"]}, {"plots": ["{t}/rec/frames/p"]},
     ["{t}/rec/frames"], "lies inside an input"),
    ({"out": ["{t}/a.yaml"], "plots": ["{t}/a.yaml"]}, {}, [], "already an output"),
], ids=["file-is-input", "plots-is-input", "plots-in-input", "two-outputs"])
def test_overlaps_are_refused_before_any_lock(tmp_path, outputs, folders, inputs, what):
    (tmp_path / "rec" / "frames").mkdir(parents=True)
    (tmp_path / "a.yaml").write_text("x: 1\n")

    def fill(m):
        return {k: [v.format(t=tmp_path) for v in vs] for k, vs in m.items()}
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    with pytest.raises(ConfigError, match=what), claimed(
            fill(outputs), folders=fill(folders), force=True,
            inputs=[i.format(t=tmp_path) for i in inputs]):
        pass
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before  # no lock, no folder
