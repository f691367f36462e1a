"""calib/workflow.py: the library functions behind `ceilcal` commands: results, files
written, and errors keyed by parameter names (the CLI maps them to flags)."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board
from ceilkit.calib.lightmap import KnownLights
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.recording import Recording
from helpers import CONFIGS, FIXTURES

CORRIDOR = CONFIGS / "corridor"


def small_rig(tmp_path, w=96, h=72):
    rig = Rig.load(CORRIDOR / "rig.yaml")
    path = tmp_path / "small_rig.yaml"
    Rig(rig.camera.scaled(w, h), rig.mount).save(path)
    return path


def test_simulate_writes_a_recording_with_truth(tmp_path):
    run = workflow.simulate(tmp_path / "rec", rig=small_rig(tmp_path), frames=3, fps=10.0,
                            lateral_m=0.1, supersample=1, seed=2)
    rec = Recording(run.folder)
    assert len(rec) == 3 and rec.t_ns.tolist() == [0, 100_000_000, 200_000_000]
    np.testing.assert_allclose(rec.truth.y_m, 0.1, atol=1e-6)
    assert (run.width, run.height) == (96, 72)
    assert run.lines()[0].startswith(f"wrote 3 frames (96x72) to {tmp_path / 'rec'}")


@pytest.mark.parametrize("kwargs,key", [
    ({"noise_sigma": -1.0}, "options.noise_sigma"), ({"lateral_m": math.nan}, "y_m"),
])
def test_simulate_names_the_parameter_and_writes_nothing(tmp_path, kwargs, key):
    with pytest.raises(ConfigError) as err:
        workflow.simulate(tmp_path / "rec", rig=small_rig(tmp_path), frames=2, **kwargs)
    assert err.value.key == key and not (tmp_path / "rec").exists()


def test_intrinsics_checks_its_arguments_before_any_detection(tmp_path):
    board = parse_board("chess:9x6", 0.025)
    with pytest.raises(ConfigError) as err:
        workflow.intrinsics(board, tmp_path / "c.yaml", folder=tmp_path, video=tmp_path)
    assert err.value.key == "source" and "exactly one image source" in str(err.value)
    with pytest.raises(ConfigError) as err:
        workflow.intrinsics(board, tmp_path / "c.yaml", folder=tmp_path, model="fisheye")
    assert err.value.key == "model"
    with pytest.raises(OutputError, match="does not exist"):
        workflow.intrinsics(board, tmp_path / "no" / "c.yaml", folder=tmp_path)


def test_intrinsics_from_a_folder_writes_the_camera(tmp_path):
    run = workflow.intrinsics(parse_board("chess:9x6", 0.03), tmp_path / "camera.yaml",
                              folder=FIXTURES / "opencv_left", plots=tmp_path / "plots")
    assert run.camera_path.exists() and len(run.plots) == 3
    text = run.camera_path.read_text()
    assert text.startswith("# camera intrinsics by ceilcal intrinsics")
    assert "RMS" in "\n".join(run.lines()) and run.result.report.rms_px < 1.0


def test_mount_errors_name_parameters(tmp_path):
    with pytest.raises(ConfigError) as err:
        workflow.mount(tmp_path / "pl", CORRIDOR / "site.yaml", tmp_path / "rig.yaml")
    assert err.value.key == "camera"
    with pytest.raises(ConfigError) as err:
        workflow.mount(tmp_path / "pl", CORRIDOR / "site.yaml", tmp_path / "rig.yaml",
                       camera=CORRIDOR / "camera.yaml", fix=["roll"])
    assert err.value.key == "fix" and "unknown parameter 'roll'" in str(err.value)
    assert not (tmp_path / "rig.yaml").exists()


def test_lightmap_chaining_takes_no_poses(tmp_path):
    with pytest.raises(ConfigError) as err:
        workflow.lightmap(FIXTURES / "lights_rec", tmp_path / "site.yaml",
                          poses=FIXTURES / "lights_rec" / "truth.csv",
                          known=KnownLights((0.0, 0.0), yaw_deg=0.0))
    assert err.value.key == "poses"


def test_lightmap_from_known_poses_writes_the_site(tmp_path):
    run = workflow.lightmap(FIXTURES / "lights_rec", tmp_path / "site.yaml", min_views=1)
    assert run.site_path.exists() and run.lightmap.lights_m.shape[0] >= 1
    assert run.lines()[0].startswith(f"{tmp_path / 'site.yaml'}: ")


def test_calibrate_keeps_the_files_it_finds(tmp_path):
    """Resumable: camera.yaml and rig.yaml already there, no check: nothing is redone
    (the board folder is not even read)."""
    out = tmp_path / "cal"
    out.mkdir()
    shutil.copy(CORRIDOR / "camera.yaml", out / "camera.yaml")
    shutil.copy(CORRIDOR / "rig.yaml", out / "rig.yaml")
    said: list[str] = []
    run = workflow.calibrate(tmp_path / "none", parse_board("chess:9x6", 0.04),
                             tmp_path / "none", CORRIDOR / "site.yaml", out,
                             on_line=said.append)
    assert run.check is None and run.lines() == said
    assert said[0] == f"step 1/3: intrinsics: kept {out / 'camera.yaml'}"
    assert said[1] == f"step 2/3: mount: kept {out / 'rig.yaml'}"
    assert said[2].startswith("step 3/3: check: skipped")


def test_provenance_header_names_the_command():
    text = workflow.provenance_header("rig.yaml written by a notebook", ["rms 0.1 px"],
                                      command="notebook")
    lines = text.splitlines()
    assert lines[0] == "# rig.yaml written by a notebook" and lines[1].startswith("# written ")
    assert lines[2:] == ["# command: notebook", "# rms 0.1 px"]
