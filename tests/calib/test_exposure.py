"""The exposure assistant on the simulator's camera (its exposure model:
runtime.devices.sim_camera_options), the scores on known frames, the capture file."""

from __future__ import annotations

import numpy as np
import pytest

from ceilkit.calib.exposure import (
    assist,
    method_for_site,
    noise_sigma,
    score_edges,
    score_lights,
    sweep,
    write_capture,
)
from ceilkit.runtime.config.capture import load_capture
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.devices import open_source, packaged_config
from ceilkit.runtime.errors import CalibrationError, ConfigError

EXPOSURES = (25.0, 50.0, 100.0, 200.0)
GAINS = (0.0, 6.0)


def _sim(name: str):
    cfg = packaged_config(name)
    rig, site = Rig.load(cfg / "rig.yaml"), Site.load(cfg / "site.yaml")
    return lambda e, g: open_source(f"sim:{name}", rig, site, exposure=e, gain=g, frames=1)


def test_noise_estimate_ignores_edges():
    rng = np.random.default_rng(0)
    img = np.full((200, 200), 100.0)
    img[:, 100:] = 180.0                                   # a strong straight edge
    grey = np.clip(img + rng.normal(0, 3.0, img.shape), 0, 255).round().astype(np.uint8)
    assert noise_sigma(grey) == pytest.approx(3.0, rel=0.1)


def test_spot_score_refuses_saturated_and_dark_frames():
    yy, xx = np.mgrid[:120, :160]
    spot = np.exp(-((xx - 80) ** 2 + (yy - 60) ** 2) / (2 * 6.0 ** 2))
    rng = np.random.default_rng(1)

    def frame(scale):
        img = 40 * scale + 200 * scale * spot + rng.normal(0, 2.0, spot.shape)
        return np.clip(img, 0, 255).round().astype(np.uint8)
    good, dark, bloom = score_lights(frame(1.0)), score_lights(frame(0.02)), \
        score_lights(frame(3.0))
    assert good.reason == "" and good.value > 50
    assert dark.reason == "dark" and dark.value == 0
    assert bloom.reason == "saturated" and bloom.saturated > 0.05


def test_lights_sweep_picks_the_brightest_setting_that_does_not_clip(tmp_path):
    result = sweep(_sim("lights"), "lights", EXPOSURES, GAINS, settle=0, frames=1)
    by = {(s.exposure, s.gain): s for s in result.settings}
    assert by[(200.0, 0.0)].score.reason == "saturated"
    assert by[(100.0, 6.0)].score.reason == "saturated"
    # 50 at +6 dB is as bright as 100 at 0 dB, with twice the read noise
    assert (result.best.exposure, result.best.gain) == (100.0, 0.0)
    assert result.best.score.value > by[(50.0, 6.0)].score.value > by[(25.0, 0.0)].score.value
    frame = _sim("lights")(100.0, 0.0).read().image
    assert np.median(frame) > 30 and np.mean(frame >= 254) < 0.002   # neither dark nor clipped
    path = write_capture(result, tmp_path / "capture.yaml", "ceilcal exposure test")
    cap = load_capture(path)
    assert (cap.exposure, cap.gain) == (100.0, 0.0)
    assert "* " in path.read_text() and "saturated" in path.read_text()


def test_corridor_assist_writes_the_setting_the_edges_want(tmp_path):
    run = assist("sim:corridor", tmp_path / "cap.yaml", exposures=EXPOSURES, gains=(0.0,),
                 settle=0, frames=1)
    assert run.result.method == "corridor"          # from the example's site
    assert (run.best.exposure, run.best.gain) == (100.0, 0.0)
    assert run.best.score.saturated < 0.05
    by = {s.exposure: s for s in run.result.settings}
    assert by[200.0].score.reason == "saturated"
    assert by[25.0].score.value < by[50.0].score.value < run.best.score.value
    assert load_capture(run.out).exposure == 100.0
    assert any("written to" in line for line in run.lines())


def test_edge_score_on_a_flat_frame_is_dark():
    assert score_edges(np.full((60, 80), 20, np.uint8)).reason == "dark"
    assert score_edges(np.full((60, 80), 255, np.uint8)).reason == "saturated"


def test_nothing_admissible_writes_nothing(tmp_path):
    result = sweep(_sim("lights"), "lights", (800.0,), (12.0,), settle=0, frames=1)
    assert result.best is None
    with pytest.raises(CalibrationError, match="no setting"):
        write_capture(result, tmp_path / "c.yaml")
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("kwargs,key", [
    ({"method": "spots"}, "method"), ({"exposures": (0.0,)}, "exposures"),
    ({"gains": (float("nan"),)}, "gains"), ({"frames": 0}, "frames")])
def test_bad_sweeps_name_their_key(tmp_path, kwargs, key):
    with pytest.raises(ConfigError) as e:
        assist("sim:lights", tmp_path / "c.yaml", **kwargs)
    assert e.value.key == key


def test_a_live_camera_needs_a_method_or_a_site(tmp_path):
    with pytest.raises(ConfigError) as e:
        assist("/dev/video99", tmp_path / "c.yaml")
    assert e.value.key == "method"


def test_method_follows_the_site():
    for name, method in (("lights", "lights"), ("corridor", "corridor"), ("block", "block")):
        assert method_for_site(Site.load(packaged_config(name) / "site.yaml")) == method
