"""`ceilcal survey`: the files it writes, and bad input refused in one line."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap
from ceilkit.runtime.io.recording import POSES_HEADER, load_poses
from ceilkit.runtime.sim.render import SimOptions, straight_drive
from ceilkit.runtime.sim.scatter_file import scene_beside
from helpers import CONFIGS

RIG = CONFIGS / "office" / "rig.yaml"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A 2 m straight drive under the office scatter (20 frames, 0.1 m apart)."""
    rig = Rig.load(RIG)
    site = Site.load(CONFIGS / "office" / "site.yaml")
    traj = straight_drive(20, fps=5.0, speed_mps=0.5, x0_m=3.0, y_m=0.3)
    out = tmp_path_factory.mktemp("cli_survey") / "rec"
    simulate_recording(rig, site, traj, out, SimOptions(supersample=1,
                                                        scatter=scene_beside(site)), seed=3)
    return out


def _run(*args: str):
    return CliRunner().invoke(app, ["survey", *args])


def test_survey_writes_the_site(drive, tmp_path):
    out = tmp_path / "site"
    res = _run(str(RIG), str(drive), "--out", str(out), "--start-pose", "3,0.3,0")
    assert res.exit_code == 0, res.output
    assert "surveyed 20 frames of 1 drive(s)" in res.output
    site = Site.load(out / "site.yaml")
    assert site.ceiling_height_m == 2.7 and site.ceiling_map is not None
    cmap = CeilingMap.load(site.ceiling_map)
    assert len(cmap.points_xy) > 20 and cmap.anchor == "start pose"
    text = (out / "site.yaml").read_text()
    assert text.startswith("# site surveyed by ceilcal survey") and "1-sigma" in text
    assert (out / "poses.csv").read_text().splitlines()[0] == ",".join(POSES_HEADER)
    poses = load_poses(out / "poses.csv")
    assert len(poses.t_ns) == 20
    assert abs(poses.x_m[0] - 3.0) < 1e-9 and abs(poses.x_m[-1] - 4.9) < 0.02
    report = (out / "survey.md").read_text()
    assert "## Closures" in report and "## Sections and their 1-sigma" in report


def test_existing_outputs_are_refused_without_force(drive, tmp_path):
    out = tmp_path / "site"
    out.mkdir()
    (out / "site.yaml").write_text("ceiling_height: 3.0\n")
    res = _run(str(RIG), str(drive), "--out", str(out))
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1
    assert "site.yaml" in res.output and "--force" in res.output
    assert (out / "site.yaml").read_text() == "ceiling_height: 3.0\n"


@pytest.mark.parametrize("args, words", [
    (["--start-pose", "1,2"], "--start-pose"),
    (["--start-pose", "1,2,nan"], "--start-pose"),
    (["--ceiling-height", "-1"], "--ceiling-height"),
    (["--anchor-marker", "7,1,2"], "--anchor-marker"),
    (["--anchor-marker", "7,1,2,0,-0.2"], "--anchor-marker"),
    (["--anchor-geodetic", "52,4"], "--anchor-geodetic"),
    (["--anchor-geodetic", "91,4,0"], "--anchor-geodetic"),
    (["--marker-dictionary", "DICT_NOPE"], "--marker-dictionary"),
])
def test_bad_options_are_one_line(drive, tmp_path, args, words):
    res = _run(str(RIG), str(drive), "--out", str(tmp_path / "site"), *args)
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1 and words in res.output
    assert not (tmp_path / "site").exists()


def test_no_ceiling_height_is_one_line(drive, tmp_path):
    rec = tmp_path / "rec"
    shutil.copytree(drive, rec)
    (rec / "site.yaml").unlink()
    res = _run(str(RIG), str(rec), "--out", str(tmp_path / "site"))
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1 and "--ceiling-height" in res.output


def test_not_a_recording_is_one_line(tmp_path):
    res = _run(str(RIG), str(tmp_path / "nothing"), "--out", str(tmp_path / "site"),
               "--ceiling-height", "2.7")
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1 and "nothing" in res.output


def test_known_site_keeps_its_sections(drive, tmp_path):
    known = tmp_path / "known.yaml"
    known.write_text("ceiling_height: 2.7\ncorridor:\n  lines_along: [-0.6, 0.0, 0.6]\n")
    out = tmp_path / "site"
    res = _run(str(RIG), str(drive), "--out", str(out), "--site", str(known))
    assert res.exit_code == 0, res.output
    site = Site.load(out / "site.yaml")
    assert site.corridor is not None and np.allclose(site.corridor.lines_along_m,
                                                     [-0.6, 0.0, 0.6])


def test_known_lights_the_drive_never_saw_are_one_line(drive, tmp_path):
    known = tmp_path / "known.yaml"
    known.write_text("ceiling_height: 2.7\nlights:\n  - [0.0, 0.0]\n  - [2.0, 1.0]\n")
    res = _run(str(RIG), str(drive), "--out", str(tmp_path / "site"), "--site", str(known))
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1
    assert "known.yaml" in res.output and "lights" in res.output
    assert not (tmp_path / "site").exists()


def test_wheel_odometry_is_used_beside_the_camera(drive, tmp_path):
    from ceilkit.calib.survey import survey_drives
    from ceilkit.calib.survey_graph import relative
    from ceilkit.runtime.io.recording import Recording

    rec_dir = tmp_path / "rec"
    shutil.copytree(drive, rec_dir)
    truth = Recording(rec_dir).truth
    poses = np.c_[truth.x_m, truth.y_m, truth.yaw_rad]
    rows = ["t_ns,dx,dy,dyaw_deg"]
    for k in range(1, len(poses)):
        dx, dy, dyaw = relative(poses[k - 1], poses[k])
        rows.append(f"{truth.t_ns[k]},{dx:.6f},{dy:.6f},{np.degrees(dyaw):.6f}")
    (rec_dir / "odometry.csv").write_text("\n".join(rows) + "\n")
    rec = Recording(rec_dir)
    res = survey_drives([rec], rec.rig, 2.7, tuple(poses[0]))
    assert res.edge_kinds.get("wheel") == len(poses) - 1
    assert np.hypot(*(res.poses[-1, :2] - poses[-1, :2])) < 0.01


def test_a_known_marker_the_drive_never_saw_is_one_line(drive, tmp_path):
    res = _run(str(RIG), str(drive), "--out", str(tmp_path / "site"), "--ceiling-height",
               "2.7", "--anchor-marker", "7,1,2,0,0.2")
    assert res.exit_code == 1
    assert len(res.output.strip().splitlines()) == 1
    assert "marker(s) 7 not seen" in res.output and "none" in res.output
    assert not (tmp_path / "site").exists()
