"""The survey under a rolling shutter: a frame put back to its stamp is the frame a
global shutter takes (the simulator's rolling shutter is the reference), the chain's
velocities are the drive's, and a survey told the readout is not shrunk along the
travel."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.calib.simulate import simulate_recording
from ceilkit.calib.survey import SurveyOptions, result_frames, survey_drives
from ceilkit.calib.survey_graph import compose
from ceilkit.calib.survey_shutter import GlobalShutter, chain_velocities
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.realism import Realism
from ceilkit.runtime.sim.render import SimOptions, SimSource, straight_drive
from ceilkit.runtime.sim.scatter_file import scene_beside
from helpers import CONFIGS

READOUT_MS = 25.0
SPEED = 0.5


@pytest.fixture(scope="module")
def office():
    return Rig.load(CONFIGS / "office" / "rig.yaml"), Site.load(CONFIGS / "office" / "site.yaml")


def _band_shifts(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(5,)`` the shift along the image's columns (px) of b against a in five bands
    of rows, top to bottom (phase correlation)."""
    out = []
    for v0 in range(40, 440, 80):
        pa, pb = (x[v0:v0 + 80, 160:480].astype(np.float32) for x in (a, b))
        out.append(cv2.phaseCorrelate(pa, pb)[0][1])
    return np.array(out)


def test_a_frame_put_back_to_its_stamp_is_the_global_shutters(office):
    rig, site = office
    traj = straight_drive(3, fps=10.0, speed_mps=SPEED, x0_m=3.0, y_m=0.0, yaw_rad=0.3)
    opts = SimOptions(noise_sigma=0.0, blur_px=0.0, supersample=1, scatter=scene_beside(site))
    with SimSource(rig, site, traj, opts, 1) as src:
        glob = to_grey(src.render(1).image)
    with SimSource(rig, site, traj, opts, 1,
                   realism=Realism(rolling_shutter_ms=READOUT_MS, time_samples=8)) as src:
        rolled = to_grey(src.render(1).image)
    gs = GlobalShutter.of(rig, site.ceiling_height_m, READOUT_MS)
    back = gs(rolled, (SPEED, 0.0, 0.0))
    raw, fixed = _band_shifts(glob, rolled), _band_shifts(glob, back)
    # the rows read before the stamp (top) and after it (bottom) are shifted apart
    assert raw[0] - raw[-1] > 0.6, raw
    assert np.max(np.abs(fixed)) < 0.1, fixed
    assert gs(rolled, (0.0, 0.0, 0.0)) is rolled
    assert GlobalShutter.of(rig, site.ceiling_height_m, 0.0) is None


def test_a_turning_frame_is_put_back_too(office):
    rig, site = office
    gs = GlobalShutter.of(rig, site.ceiling_height_m, READOUT_MS)
    # a pure turn at 1 rad/s: a point 1 m ahead (V x) read at the row time tau moves
    # by -tau across (V -y) in the turned frame; 25 ms over the rows: about 2.4 px
    p = gs.source_px((0.0, 0.0, 1.0))
    at_centre = np.argmin(np.hypot(*(gs.q - [0.0, 0.0]).T))
    assert np.hypot(*(p[at_centre] - gs.px0[at_centre])) < 0.05
    ahead = np.argmin(np.hypot(*(gs.q - [1.0, 0.0]).T))
    moved = p[ahead] - gs.px0[ahead]
    assert 1.5 < np.hypot(*moved) < 4.0


def test_chain_velocities_are_the_drives():
    t_ns = np.arange(40) * 100_000_000
    # a circle of radius 2 m at 0.5 m/s (0.25 rad/s), started anywhere in any frame
    yaw = 0.4 + 0.25 * t_ns / 1e9
    chain = np.column_stack([1.0 + 2.0 * np.sin(yaw), -3.0 - 2.0 * np.cos(yaw), yaw])
    v = chain_velocities(chain, t_ns)
    # central differences along the arc: the chord's speed, within 0.1 %
    assert np.allclose(v[1:-1, 0], 0.5, rtol=1e-3)
    assert np.allclose(v[1:-1, 1], 0.0, atol=0.5 * math.sin(0.025))
    assert np.allclose(v[:, 2], 0.25, rtol=1e-9)
    assert np.all(chain_velocities(chain[:1], t_ns[:1]) == 0.0)


@pytest.fixture(scope="module")
def rolling_drive(office, tmp_path_factory):
    """A 2 m straight drive at 0.5 m/s under a 25 ms rolling shutter (supersample 1, no
    noise: the scale is what is measured)."""
    rig, site = office
    traj = straight_drive(41, fps=10.0, speed_mps=SPEED, x0_m=2.0, y_m=0.3, yaw_rad=0.0)
    out = tmp_path_factory.mktemp("shutter") / "drive"
    simulate_recording(rig, site, traj, out, SimOptions(
        noise_sigma=1.0, blur_px=0.0, supersample=1, scatter=scene_beside(site)), seed=2,
        realism=Realism(rolling_shutter_ms=READOUT_MS, time_samples=8))
    return Recording(out)


def _driven(res) -> float:
    """The surveyed distance from the first frame to the last, m."""
    return float(np.hypot(*(res.poses[-1, :2] - res.poses[0, :2])))


def test_told_the_readout_the_survey_keeps_its_scale(rolling_drive):
    rec = rolling_drive
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    true_m = float(np.hypot(*(truth[-1, :2] - truth[0, :2])))
    plain = survey_drives([rec], rec.rig, rec.site.ceiling_height_m, tuple(truth[0]))
    told = survey_drives([rec], rec.rig, rec.site.ceiling_height_m, tuple(truth[0]),
                         SurveyOptions(readout_ms=READOUT_MS))
    assert plain.velocity is None and told.readout_ms == READOUT_MS
    assert np.allclose(told.velocity[5:-5, 0], SPEED, rtol=0.02)
    short = (true_m - _driven(plain)) / true_m
    left = (true_m - _driven(told)) / true_m
    assert short > 0.003, short             # shrunk along the travel (0.53 % expected)
    assert abs(left) < 0.1 * short, (short, left)
    # its frames are read the same way afterwards (the map, the markers)
    read = result_frames(told, [rec], rec.rig)
    k = int(told.frame[10])
    assert not np.array_equal(read.grey(0, k), to_grey(rec.frame(k).image))
    assert result_frames(plain, [rec], rec.rig).shutter is None


def test_a_negative_readout_is_refused():
    with pytest.raises(ConfigError, match="readout_ms"):
        SurveyOptions(readout_ms=-1.0)


def test_compose_of_the_velocity_moves_the_frame_forward():
    # the velocity is in each frame's own V: a chain heading -y drives along +x of V
    t_ns = np.arange(5) * 100_000_000
    chain = np.array([compose(np.array([0.0, 0.0, -math.pi / 2]),
                              np.array([0.05 * k, 0.0, 0.0])) for k in range(5)])
    v = chain_velocities(chain, t_ns)
    assert np.allclose(v[:, 0], 0.5) and np.allclose(v[:, 1:], 0.0, atol=1e-12)
