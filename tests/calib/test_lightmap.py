"""Tests of calib/lightmap.py and `ceilcal lightmap`: survey a light map from a recording."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.lightmap import cluster_points, load_pose_table, survey_lights, write_site
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.recording import Recording
from ceilkit.runtime.sim import SimOptions, random_poses
from ceilkit.runtime.site import Site

OPTS = SimOptions(noise_sigma=2.0, blur_px=0.8, light_radius_m=0.08, supersample=2)


@pytest.fixture(scope="module")
def recording(tmp_path_factory, request):
    from ceilkit.runtime.rig import Rig
    from helpers import CONFIGS

    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    # a small part of the hall, so the test stays fast: x in [3, 8] m
    traj = random_poses(12, (3.0, 8.0), (-3.0, 3.0), (-math.pi, math.pi),
                        np.random.default_rng(4))
    out = tmp_path_factory.mktemp("lm") / "rec"
    simulate_recording(rig, site, traj, out, OPTS, seed=3)
    return out, site


def _match(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(found[:, None] - truth[None], axis=2)
    return d.min(axis=1)


def test_survey_recovers_lights(recording):
    out, site = recording
    lm = survey_lights(Recording(out))
    err = _match(lm.lights_m, site.lights_m)
    assert lm.lights_m.shape[0] >= 12            # the lights around x in [3, 8] m
    assert np.all(err < 0.01), err               # every surveyed light is a real one
    assert np.median(err) < 0.003
    assert np.all(lm.views >= 3) and np.all(lm.sigma_m > 0)
    assert np.all(lm.sigma_m < lm.spread_m + 1e-12)
    # the reported uncertainty is of the right size
    assert np.median(err) < 5 * np.median(lm.sigma_m) + 0.001


def test_cli_writes_site_keeping_other_sections(recording, tmp_path):
    out, site = recording
    target = tmp_path / "site.yaml"
    target.write_text("ceiling_height: 3.0\ncorridor:\n  lines_along: [-0.5, 0.5]\n"
                      "lights:\n  - [100.0, 100.0]\n")
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target)])
    assert res.exit_code == 0, res.output
    new = Site.load(target)
    assert new.corridor is not None and new.corridor.lines_along_m == (-0.5, 0.5)
    assert new.lights_m.shape[0] >= 12 and np.all(_match(new.lights_m, site.lights_m) < 0.01)
    text = target.read_text()
    assert text.startswith("# ceilcal lightmap") and "sigma_mm" in text and "lights[0]" in text


def test_cli_with_poses_file_and_errors(recording, tmp_path):
    out, _ = recording
    poses = tmp_path / "poses.csv"
    truth = load_pose_table(out / "truth.csv")
    rows = ["t_ns,x,y,yaw_deg,lateral,method,quality,latency_ms"]
    rows += [f"{t},{x},{y},{math.degrees(a)},,lights,1.0," for t, x, y, a in
             zip(truth.t_ns, truth.x_m, truth.y_m, truth.yaw_rad, strict=True)]
    poses.write_text("\n".join(rows) + "\n")
    target = tmp_path / "s.yaml"
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target),
                                   "--poses", str(poses)])
    assert res.exit_code == 0, res.output
    assert Site.load(target).lights_m.shape[0] >= 12
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target),
                                   "--poses", str(bad)])
    assert res.exit_code == 1 and "header" in res.output


def test_survey_errors(recording, tmp_path):
    out, _ = recording
    rec = Recording(out)
    t = load_pose_table(out / "truth.csv")
    shifted = type(t)(t.t_ns + 1, t.x_m, t.y_m, t.yaw_rad)
    with pytest.raises(ConfigError, match="no pose matches"):
        survey_lights(rec, shifted)
    with pytest.raises(CalibrationError, match="no light seen"):
        survey_lights(rec, min_views=1000)
    with pytest.raises(ConfigError, match="ceiling"):
        survey_lights(rec, ceiling_height_m=0.3)


def test_cluster_points_and_write_site(tmp_path):
    rng = np.random.default_rng(0)
    truth = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, -1.0]])
    pts = np.concatenate([truth + rng.normal(0, 0.005, truth.shape) for _ in range(5)]
                         + [[[5.0, 5.0]]])
    ids = np.concatenate([np.full(3, k) for k in range(5)] + [[9]])
    C, sig, spread, views, unassigned = cluster_points(pts, ids, 0.15, 3)
    assert C.shape == (3, 2) and np.all(views == 5) and unassigned == 1
    assert np.all(_match(C, truth) < 0.01)
    from ceilkit.calib.lightmap import LightMap
    lm = LightMap(C, sig, spread, views, 5, 16, 1)
    site = write_site(lm, tmp_path / "x.yaml", None, "# h\n", ceiling_height_m=2.8)
    assert site.ceiling_height_m == 2.8 and site.lights_m.shape == (3, 2)
    with pytest.raises(ConfigError, match="ceiling height"):
        write_site(lm, tmp_path / "y.yaml", None)
