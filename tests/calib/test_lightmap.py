"""Tests of calib/lightmap.py and `ceilcal lightmap`: survey a light map from a recording."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.lightmap import (
    KnownLights,
    chain_points,
    cluster_points,
    load_pose_table,
    survey_chain,
    survey_lights,
    write_site,
)
from ceilkit.calib.poses import StampedPoses
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory, random_poses, straight_drive

OPTS = SimOptions(noise_sigma=2.0, blur_px=0.8, light_radius_m=0.08, supersample=2)


@pytest.fixture(scope="module")
def recording(tmp_path_factory, request):
    from ceilkit.runtime.config.rig import Rig
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
    res = CliRunner().invoke(app, ["lightmap", str(out), "--out", str(target), "--force"])
    assert res.exit_code == 0, res.output  # --force: into an existing site.yaml
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
                                   "--poses", str(bad), "--force"])
    assert res.exit_code == 1 and "header" in res.output


def test_survey_errors(recording, tmp_path):
    out, _ = recording
    rec = Recording(out)
    t = load_pose_table(out / "truth.csv")
    later = type(t)(t.t_ns + 10**12, t.x_m, t.y_m, t.yaw_rad)   # covering no frame
    with pytest.raises(ConfigError, match="no pose matches"):
        survey_lights(rec, later)
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


# ---------------------------------------------------------------- chaining survey
# Halo and vignetting off: both pull a spot's centroid inwards by a few hundredths of a
# pixel (docs/simulator.md), a bias the survey cannot tell from the geometry.
CHAIN_OPTS = SimOptions(noise_sigma=2.0, blur_px=0.8, light_radius_m=0.08, supersample=2,
                        halo=0.0, vignetting=0.0)
A_LIGHT = (2.505, 0.064)      # configs/lights: the drive starts under this light
B_LIGHT = (7.496, -5.103)     # a second light, 7.2 m away, seen on the way


def chain_trajectory(n: int = 28) -> Trajectory:
    """A weaving drive of 6 m along +x from under light A, turning a little."""
    s = np.linspace(0.0, 1.0, n)
    return Trajectory(np.arange(n, dtype=np.int64) * 100_000_000, A_LIGHT[0] + 6.0 * s,
                      A_LIGHT[1] + np.sin(2 * np.pi * s), 0.3 + 0.4 * np.sin(3 * s))


@pytest.fixture(scope="module")
def chain_rec(tmp_path_factory):
    from ceilkit.runtime.config.rig import Rig
    from helpers import CONFIGS

    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    out = tmp_path_factory.mktemp("chain") / "rec"
    simulate_recording(rig, site, chain_trajectory(), out, CHAIN_OPTS, seed=5)
    return out, site


def _errors(lm_lights: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(lm_lights[:, None] - truth[None], axis=2).min(axis=1)


def test_chain_survey_with_two_known_lights(chain_rec):
    out, site = chain_rec
    res = survey_chain(Recording(out), KnownLights(A_LIGHT, second_m=B_LIGHT))
    lm = res.lightmap
    err = _errors(lm.lights_m, site.lights_m)
    assert lm.lights_m.shape[0] >= 15 and res.unplaced == 0
    assert np.all(err < 0.01), err                    # every light is a real one, < 1 cm
    assert np.median(err) < 0.003
    np.testing.assert_allclose(lm.lights_m[res.anchor], A_LIGHT, atol=1e-9)
    np.testing.assert_allclose(lm.lights_m[res.second], B_LIGHT, atol=1e-9)
    free = np.ones(lm.lights_m.shape[0], bool)
    free[[res.anchor, res.second]] = False
    # the reported 1-sigma is the size of the errors: within it on average
    ratio = err[free] / lm.sigma_m[free]
    assert 0.3 < np.mean(ratio) < 1.3, ratio
    assert res.height_fitted and abs(res.ceiling_height_m - 3.0) < 0.01
    # frame poses come out too, against the truth
    tr = Recording(out).truth
    pe = np.hypot(res.poses[:, 0] - tr.x_m[res.frames], res.poses[:, 1] - tr.y_m[res.frames])
    assert np.median(pe) < 0.003


def test_chain_survey_with_start_yaw(chain_rec):
    out, site = chain_rec
    yaw0 = math.degrees(chain_trajectory().yaw_rad[0])
    res = survey_chain(Recording(out), KnownLights(A_LIGHT, yaw_deg=yaw0))
    err = _errors(res.lightmap.lights_m, site.lights_m)
    assert res.second == -1 and not res.height_fitted and res.ceiling_height_m == 3.0
    assert np.all(err < 0.01) and np.median(err) < 0.004
    # a wrong heading turns the whole map about light A
    res2 = survey_chain(Recording(out), KnownLights(A_LIGHT, yaw_deg=yaw0 + 1.0))
    far = np.argmax(np.linalg.norm(res2.lightmap.lights_m - A_LIGHT, axis=1))
    assert _errors(res2.lightmap.lights_m[far:far + 1], site.lights_m)[0] > 0.05


def test_chain_survey_bad_inputs(chain_rec, tmp_path):
    out, _ = chain_rec
    rec = Recording(out)
    with pytest.raises(CalibrationError, match="second known light is never seen"):
        survey_chain(rec, KnownLights(A_LIGHT, second_m=(A_LIGHT[0] + 30.0, 0.0)))
    with pytest.raises(ConfigError, match="anchor_frame"):
        survey_chain(rec, KnownLights(A_LIGHT, yaw_deg=0.0, anchor_frame=500))
    with pytest.raises(ConfigError, match="x axis"):
        KnownLights(A_LIGHT)
    with pytest.raises(ConfigError, match="second_m"):
        KnownLights(A_LIGHT, second_m=A_LIGHT)


def test_chain_points_errors_no_overlap_and_unseen_light():
    rig, site = _lights_rig_site()
    obs, _ = _synthetic_drive(rig, site, np.random.default_rng(0))
    # frames that share no light: each sees its own three lights, 5 m further each time
    rng = np.random.default_rng(1)
    J = np.tile(100.0 * np.eye(2), (3, 1, 1))
    apart = [(k, rng.uniform(-1.0, 1.0, (3, 2)) + (5.0 * k, 0.0), J) for k in range(6)]
    with pytest.raises(CalibrationError, match="do not overlap"):
        chain_points(apart, rig, 3.0, KnownLights(A_LIGHT, yaw_deg=0.0))
    # the frame under the known light saw nothing
    with pytest.raises(CalibrationError, match="known light is never seen"):
        chain_points(obs[1:], rig, 3.0, KnownLights(A_LIGHT, yaw_deg=0.0))
    with pytest.raises(ConfigError, match="min_views"):
        chain_points(obs, rig, 3.0, KnownLights(A_LIGHT, yaw_deg=0.0), min_views=1)


def _lights_rig_site():
    from ceilkit.runtime.config.rig import Rig
    from helpers import CONFIGS

    return (Rig.load(CONFIGS / "lights" / "rig.yaml"),
            Site.load(CONFIGS / "lights" / "site.yaml"))


def _synthetic_drive(rig, site, rng, sigma_px: float = 0.1):
    """Per-frame ceiling points of the true lights seen along chain_trajectory(), from
    pixels with Gaussian noise ``sigma_px`` (no images, no bias)."""
    from ceilkit.runtime.estimators.lights import (
        ceiling_points,
        interp_grid,
        jacobian_grid,
        project_lights,
    )

    traj = chain_trajectory(40)
    jg = jacobian_grid(rig, 3.0, 8)
    obs = []
    for k in range(len(traj)):
        px = project_lights(rig, 3.0, site.lights_m, *traj.pose(k))
        q_true, ok = ceiling_points(rig, 3.0, px)
        ok &= np.linalg.norm(q_true, axis=1) < 2.5 * math.tan(math.radians(60))
        noisy = px[ok] + rng.normal(0.0, sigma_px, (int(ok.sum()), 2))
        obs.append((k, ceiling_points(rig, 3.0, noisy)[0], interp_grid(jg, 8, noisy)))
    return obs, traj


@pytest.mark.parametrize("second", [True, False])
def test_chain_adjustment_covariance_is_consistent(second):
    """Unbiased pixel noise: the errors match the adjustment's 1-sigma over 3 drives."""
    rig, site = _lights_rig_site()
    ratios = []
    for seed in range(3):
        obs, traj = _synthetic_drive(rig, site, np.random.default_rng(seed))
        known = (KnownLights(A_LIGHT, second_m=B_LIGHT) if second
                 else KnownLights(A_LIGHT, yaw_deg=math.degrees(traj.yaw_rad[0])))
        res = chain_points(obs, rig, 3.0, known, systematic_px=0.0)
        lm = res.lightmap
        free = lm.sigma_m > 0
        ratios.append(_errors(lm.lights_m[free], site.lights_m) / lm.sigma_m[free])
    r = np.concatenate(ratios)
    # |error| / radial sigma of a 2-D Gaussian averages 0.89
    assert 0.6 < np.mean(r) < 1.2, np.mean(r)
    assert np.mean(r > 2.5) < 0.05


def test_mocap_poses_at_120_hz_interpolated_and_their_offset_estimated(tmp_path):
    """Poses at their own 120 Hz stamps, 6.67 ms late (8 samples of a 1200 Hz drive):
    the offset is found within its sigma and 0.1 ms, and the map is as good as with
    poses at the frames' stamps; ignoring the offset smears it by about a centimetre."""
    from ceilkit.runtime.config.rig import Rig
    from helpers import CONFIGS

    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    hz = 1200
    dense = straight_drive(8 * hz, fps=hz, speed_mps=0.8, x0_m=2.5, weave_m=1.0,
                           weave_period_m=3.0, yaw_wobble_rad=math.radians(20),
                           rng=np.random.default_rng(0))
    ks = np.linspace(30, 8 * hz - 30, 12).astype(int)
    out = simulate_recording(rig, site, Trajectory(dense.t_ns[ks], dense.x_m[ks],
                                                   dense.y_m[ks], dense.yaw_rad[ks]),
                             tmp_path / "rec", OPTS, seed=0)
    lag = 8
    js = np.arange(lag, 8 * hz, hz // 120)
    mocap = StampedPoses(dense.t_ns[js], dense.x_m[js - lag], dense.y_m[js - lag],
                      dense.yaw_rad[js - lag])
    rec = Recording(out)
    exact = survey_lights(rec)
    lm = survey_lights(rec, mocap)
    true_s = lag / hz
    assert exact.offset_s is None
    assert abs(lm.offset_s - true_s) < max(3 * lm.offset_sigma_s, 2e-5)
    assert abs(lm.offset_s - true_s) < 1e-4
    err = _match(lm.lights_m, site.lights_m)
    assert lm.lights_m.shape[0] >= 10 and np.median(err) < 0.004, err
    ignored = survey_lights(rec, mocap, offset_s=0.0)
    assert np.median(_match(ignored.lights_m, site.lights_m)) > 2 * np.median(err)
    from ceilkit.calib.lightmap import lightmap_header_lines
    assert any("pose time offset" in line and "estimated" in line
               for line in lightmap_header_lines(lm))
