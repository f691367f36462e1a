"""`ceilcal lightmap` by chaining frames: options, the written site file, errors."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.cli.ceilcal_lightmap import parse_xy
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from helpers import CONFIGS

A = (2.505, 0.064)     # configs/lights: the drive starts under this light
B = (4.443, 0.018)     # the next light along +x


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    n = 16
    s = np.linspace(0.0, 1.0, n)
    traj = Trajectory(np.arange(n, dtype=np.int64) * 100_000_000, A[0] + 3.0 * s,
                      A[1] + 0.5 * np.sin(np.pi * s), 0.2 * s)
    out = tmp_path_factory.mktemp("cli_chain") / "rec"
    simulate_recording(rig, site, traj, out, SimOptions(supersample=2, halo=0.0,
                                                        vignetting=0.0), seed=2)
    return out, site


def _err(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(found[:, None] - truth[None], axis=2).min(axis=1)


def test_chain_with_second_light_writes_site_and_height(rec, tmp_path):
    out, site = rec
    target = tmp_path / "site.yaml"
    target.write_text("ceiling_height: 3.0\ncorridor:\n  lines_along: [-0.5, 0.5]\n")
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target),
                                   "--known-light", f"{A[0]},{A[1]}",
                                   "--second-light", f"{B[0]}, {B[1]}", "--force"])
    assert res.exit_code == 0, res.output  # --force: into an existing site.yaml
    assert "chained frames" in res.output and "ceiling height" in res.output
    new = Site.load(target)
    assert new.corridor is not None                      # other sections kept
    assert new.lights_m.shape[0] >= 10
    assert np.all(_err(new.lights_m, site.lights_m) < 0.01)
    assert abs(new.ceiling_height_m - 3.0) < 0.01        # fitted to the taped A-B
    text = target.read_text()
    assert text.startswith("# ceilcal lightmap") and "chained survey" in text
    assert "sx_mm" in text and "lights[0]" in text and "gauge: light A" in text


def test_chain_with_start_yaw_keeps_height(rec, tmp_path):
    out, site = rec
    target = tmp_path / "s.yaml"
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target),
                                   "--known-light", f"{A[0]},{A[1]}", "--start-yaw", "0"])
    assert res.exit_code == 0, res.output
    new = Site.load(target)
    assert new.ceiling_height_m == 3.0
    assert np.median(_err(new.lights_m, site.lights_m)) < 0.005


@pytest.mark.parametrize("args, flag", [
    (["--known-light", "2.5"], "--known-light"),
    (["--known-light", "a,b"], "--known-light"),
    (["--known-light", "2.5,0.06"], "--second-light"),
    (["--start-yaw", "10"], "--known-light"),
    (["--known-light", "2.5,0.06", "--start-yaw", "0", "--poses", "x.csv"], "--poses"),
])
def test_bad_options_name_the_flag(rec, tmp_path, args, flag):
    out, _ = rec
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(tmp_path / "o.yaml"),
                                   *args])
    assert res.exit_code == 1
    assert flag in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o.yaml").exists()


def test_second_light_never_seen_is_an_error(rec, tmp_path):
    out, _ = rec
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(tmp_path / "o.yaml"),
                                   "--known-light", f"{A[0]},{A[1]}",
                                   "--second-light", "40.0,0.0"])
    assert res.exit_code == 1 and "never seen" in res.output


def test_parse_xy():
    assert parse_xy("1.5, -2", "--x") == (1.5, -2.0)
    assert parse_xy(None, "--x") is None
    with pytest.raises(ConfigError, match="--x"):
        parse_xy("1,2,3", "--x")
    with pytest.raises(ConfigError, match="finite"):
        parse_xy("nan,1", "--x")
