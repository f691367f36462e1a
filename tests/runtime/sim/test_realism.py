"""The realism knobs: off is bit-identical, each knob changes the render the way it
should (cheap, small frames), presets parse, bad values are one clear error."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import LampRow, Site
from ceilkit.runtime.devices import open_source, packaged_config, sim_camera_options
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim import realism as RL
from ceilkit.runtime.sim import render as sim
from ceilkit.runtime.sim import scene as S
from ceilkit.runtime.sim.realism import Realism, load_preset, load_presets, parse_knobs
from ceilkit.runtime.sim.render import SimOptions, SimSource, Trajectory, straight_drive

CLEAN = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0)
F = 100.0            # focal length, px
H_CAM = 0.5
CEIL = 2.5           # ceiling 2 m above the camera: 50 px per metre on the ceiling


@pytest.fixture(scope="module")
def up_rig() -> Rig:
    """A 160 x 120 pinhole looking straight up: W's x runs along image rows (v), y along
    columns (u)."""
    return Rig(CameraModel.pinhole(160, 120, fx=F), Mount(tilt_rad=math.pi / 2, z_m=H_CAM))


@pytest.fixture(scope="module")
def stripe_site() -> Site:
    """One long lamp along x: a vertical bright stripe down the whole image."""
    return Site(CEIL, lamps=(LampRow(0.0, 0.0, 6.0, 0.2),))


def sideways(v_mps: float, n: int = 3) -> Trajectory:
    t = np.arange(n, dtype=np.int64) * 33_333_333
    return Trajectory(t, np.zeros(n), v_mps * t / 1e9, np.zeros(n))


def stripe_columns(img: np.ndarray) -> np.ndarray:
    """Per row: the intensity-weighted column of the stripe (above the ceiling grey)."""
    w = np.clip(img.astype(float) - sim.CEILING_GREY - 5, 0, None)
    u = np.arange(img.shape[1])
    return (w * u).sum(axis=1) / w.sum(axis=1)


def edge_width(profile: np.ndarray) -> float:
    """10-90 % rise width (px) of the first rising edge of a 1-D profile."""
    p = (profile - profile.min()) / (profile.max() - profile.min())
    seg = p[:int(np.argmax(p > 0.999)) + 1]           # up to the plateau

    def cross(level):
        k = int(np.flatnonzero(seg < level)[-1])
        return k + (level - seg[k]) / (seg[k + 1] - seg[k])

    return cross(0.9) - cross(0.1)


# --------------------------------------------------------------------------- off
def test_knobs_off_is_bit_identical(up_rig, stripe_site):
    traj = straight_drive(3, speed_mps=0.5)
    plain = SimSource(up_rig, stripe_site, traj, seed=3)
    off = SimSource(up_rig, stripe_site, traj, seed=3, realism=Realism(mains_hz=60.0))
    assert off.realism is None
    for k in range(3):
        assert np.array_equal(plain.render(k).image, off.render(k).image)
    # the realism path itself, with nothing on, gives the same bytes
    x, y, yaw = traj.pose(1)
    a = sim.render_frame(up_rig, stripe_site, x, y, yaw, SimOptions(), np.random.default_rng(5))
    b = RL.render_real(up_rig, stripe_site, traj.pose_at, int(traj.t_ns[1]), SimOptions(),
                       Realism(), np.random.default_rng(5))
    assert np.array_equal(a, b)


def test_corridor_example_off_matches_render_frame():
    p = packaged_config("corridor")
    rig, site = Rig.load(p / "rig.yaml"), Site.load(p / "site.yaml")
    rig = Rig(rig.camera.scaled(320, 240), rig.mount)
    traj = straight_drive(2, speed_mps=0.8, y_m=0.1)
    src = SimSource(rig, site, traj, seed=1, realism=Realism())
    img = sim.render_frame(rig, site, *traj.pose(1), SimOptions(), np.random.default_rng([1, 1]))
    assert np.array_equal(src.render(1).image, img)


# --------------------------------------------------------------------------- scene
def test_an_object_hides_the_lamps_flicker_too(up_rig):
    """The lamps' emission layer (modulated per row by ``flicker`` after the scene is
    drawn) is hidden under an object as their light is: a person walking under the
    camera once showed the lamps through them, darker rows in flicker's troughs."""
    site = Site(CEIL)
    pipe = S.PipeX(y=0.3, z=2.2, r=0.05, grey=90.0, spec=0.0)
    lay = RL.Layout((pipe,), None, np.zeros((0, 4)))
    base = sim.render_radiance(up_rig, site, 0.0, 0.0, 0.0, CLEAN)
    em = np.full(base.shape, 100.0, np.float32)
    img, hidden = RL._overlay_split(base, em, up_rig, site, (0.0, 0.0, 0.0), 0.0, CLEAN,
                                    Realism(pipes=1), lay)
    dark = img[60] < sim.CEILING_GREY - 20          # the pipe's columns on row 60
    assert dark.any() and np.all(hidden[60][dark][1:-1] == 0.0)   # edges: part covered
    assert np.all(hidden[60][~dark][:5] == 100.0)    # the open ceiling keeps its emission
    assert np.array_equal(img, RL._overlay(base, up_rig, site, (0.0, 0.0, 0.0), 0.0, CLEAN,
                                           Realism(pipes=1), lay))


def test_pipe_darkens_where_projected(up_rig):
    site = Site(CEIL)
    pipe = S.PipeX(y=0.3, z=2.2, r=0.05, grey=90.0, spec=0.0)
    lay = RL.Layout((pipe,), None, np.zeros((0, 4)))
    base = sim.render_radiance(up_rig, site, 0.0, 0.0, 0.0, CLEAN)
    img = RL._overlay(base, up_rig, site, (0.0, 0.0, 0.0), 0.0, CLEAN, Realism(pipes=1), lay)
    # the axis at y = 0.3, 1.7 m above the camera: u = cx -/+ F * 0.3 / 1.7
    cols = np.arange(img.shape[1])
    dark = img[60] < sim.CEILING_GREY - 20
    centre = cols[dark].mean()
    width = dark.sum()
    expect_w = 2 * 0.05 * F / 1.7                 # 5.9 px wide
    assert abs(width - expect_w) <= 1.5
    assert abs(abs(centre - up_rig.camera.cx) - F * 0.3 / 1.7) < 1.0
    assert np.allclose(img[:, cols[~dark].min():int(centre) - 8][:, :5],
                       base[:, cols[~dark].min():int(centre) - 8][:, :5])


def test_people_and_beams_occlude(up_rig, stripe_site):
    ppl = S.People(ys=(0.0,), x0s=(0.5,), speeds=(0.0,))
    beam = S.BeamsY(x0=-0.6, pitch=10.0, half_w=0.1, z_bot=2.2, z_top=CEIL, y_lo=-2, y_hi=2)
    base = sim.render_radiance(up_rig, stripe_site, 0.0, 0.0, 0.0, CLEAN)
    for obj in (ppl, beam):
        lay = RL.Layout((obj,), None, np.zeros((0, 4)))
        img = RL._overlay(base, up_rig, stripe_site, (0.0, 0.0, 0.0), 0.0, CLEAN,
                          Realism(people=1), lay)
        changed = np.abs(img - base) > 20
        assert 0.02 < changed.mean() < 0.6           # a part of the frame, not all of it
        # the lamp stripe is hidden where the object is
        assert img[changed].mean() < base[changed].mean()


def test_layout_is_fixed_to_the_world_and_seeded():
    p = packaged_config("corridor")
    site = Site.load(p / "site.yaml")
    real = load_preset(p / "site.yaml", "realistic")
    a, b = RL.layout(site, SimOptions(), real), RL._build_layout(site, SimOptions(), real)
    assert [repr(o) for o in a.objects] == [repr(o) for o in b.objects]
    c = RL._build_layout(site, SimOptions(), real.replace(layout_seed=1))
    assert [repr(o) for o in a.objects] != [repr(o) for o in c.objects]
    assert sum(isinstance(o, S.PipeX) for o in a.objects) == real.pipes


def test_hanging_lamp_row_drawn_at_its_height(up_rig):
    flat = Site(CEIL, lamps=(LampRow(0.0, 0.0, 0.4, 0.2),))
    hung = Site(CEIL, lamps=(LampRow(0.0, 0.0, 0.4, 0.2, z_m=1.5),))
    a = RL.render_real(up_rig, flat, lambda t: (0, 0, 0), 0, CLEAN, Realism())
    b = RL.render_real(up_rig, hung, lambda t: (0, 0, 0), 0, CLEAN, Realism())
    # 1 m above the camera instead of 2 m: twice as long in the image
    la, lb = (np.sum(img[:, 80] > 200) for img in (a, b))
    assert abs(la - 0.4 * F / 2.0) <= 1 and abs(lb - 0.4 * F / 1.0) <= 1


# --------------------------------------------------------------------------- camera
def test_motion_blur_widens_an_edge_by_the_motion(up_rig, stripe_site):
    v, te = 2.0, 40.0                           # 8 cm over the exposure = 4 px
    traj = sideways(v)
    sharp = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, CLEAN, Realism())
    blur = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, CLEAN,
                          Realism(motion_blur_ms=te, time_samples=17))
    w0 = edge_width(sharp[40:80].astype(float).mean(axis=0))
    w1 = edge_width(blur[40:80].astype(float).mean(axis=0))
    length = v * te / 1e3 * F / (CEIL - H_CAM)
    assert w0 < 1.5
    assert abs(w1 - 0.8 * length) < 0.6          # a box of that length: 10-90 % is 0.8 L
    # the blurred stripe's centre is where the camera was mid-exposure: at the stamp
    shift = stripe_columns(blur[40:80]).mean() - stripe_columns(sharp[40:80]).mean()
    assert abs(shift) < 0.3


def test_rolling_shutter_skews_a_vertical_line(up_rig, stripe_site):
    v, ro = 2.0, 50.0                           # 10 cm during readout = 5 px
    traj = sideways(v)
    glob = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, CLEAN, Realism())
    roll = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, CLEAN,
                          Realism(rolling_shutter_ms=ro, time_samples=11))
    rows = np.arange(120)
    k0 = np.polyfit(rows, stripe_columns(glob), 1)[0]
    k1 = np.polyfit(rows, stripe_columns(roll), 1)[0]
    expect = v * ro / 1e3 * F / (CEIL - H_CAM) / 119
    assert abs(k0) < 1e-3
    assert abs(abs(k1) - expect) < 0.1 * expect
    # the stamp is the middle of the centre row's exposure: the centre row sees the
    # stamp's pose, as the global shutter does; the top row half the readout earlier
    mid = stripe_columns(roll)[59:61].mean() - stripe_columns(glob)[59:61].mean()
    assert abs(mid) < 0.2
    assert abs(abs(stripe_columns(roll)[0] - stripe_columns(glob)[0]) - 59.5 * expect) \
        < 0.2 * 59.5 * expect


def test_without_time_knobs_the_frame_is_the_plain_render(up_rig, stripe_site):
    traj = sideways(2.0)
    plain = sim.render_frame(up_rig, stripe_site, *traj.pose_at(0), CLEAN,
                           np.random.default_rng(0))
    real = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, CLEAN, Realism(),
                          np.random.default_rng(0))
    assert np.array_equal(plain, real)


def test_flicker_bands_with_a_rolling_shutter_only(up_rig, stripe_site):
    still = sideways(0.0)
    real = Realism(flicker=0.5, rolling_shutter_ms=30.0)
    dim = CLEAN.replace(exposure=0.6)           # nothing clips
    band = RL.render_real(up_rig, stripe_site, still.pose_at, 0, dim, real)
    glob = RL.render_real(up_rig, stripe_site, still.pose_at, 0, dim,
                          real.replace(rolling_shutter_ms=0.0))
    lamp_b, lamp_g = band[:, 78:82].astype(float).mean(axis=1), glob[:, 78:82].mean(axis=1)
    ceil_b = band[:, 10:20].astype(float).mean(axis=1)
    assert np.ptp(lamp_b) > 60                  # 30 ms at 100 Hz: three bright/dark bands
    assert np.ptp(lamp_g) < 1                   # a global shutter: one level
    assert np.ptp(ceil_b) < 1                   # only the lamps flicker
    # three periods of 10 ms over the readout
    spec = np.abs(np.fft.rfft(lamp_b - lamp_b.mean()))
    assert int(np.argmax(spec)) == 3


def test_unequal_and_failed_lamps():
    site = Site(CEIL, lamps=(LampRow(0.0, 0.0, 0.4, 0.2, pitch_m=0.8, count=50),))
    lay = RL.layout(site, SimOptions(), Realism(lamp_spread=0.1, lamps_off=0.3))
    g = lay.emitters.lamp_gain[0]
    assert 5 < np.sum(g == 0) < 25 and 0.05 < np.std(g[g > 0]) < 0.15
    k = int(np.flatnonzero(g == 0)[0])
    rig = Rig(CameraModel.pinhole(160, 120, fx=F), Mount(tilt_rad=math.pi / 2, z_m=H_CAM))
    img = RL.render_real(rig, site, lambda t: (0.8 * k, 0.0, 0.0), 0, CLEAN,
                         Realism(lamp_spread=0.1, lamps_off=0.3))
    assert abs(float(img[60, 80]) - sim.OFF_GREY) < 2


def test_jpeg_quality_changes_the_bytes(up_rig, stripe_site):
    traj = sideways(0.0)
    ref = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, SimOptions(), Realism(),
                         np.random.default_rng(1))
    errs = []
    for q in (95, 40):
        img = RL.render_real(up_rig, stripe_site, traj.pose_at, 0, SimOptions(),
                             Realism(jpeg=q), np.random.default_rng(1))
        assert img.dtype == np.uint8 and img.shape == ref.shape
        ok, buf = cv2.imencode(".jpg", ref, [cv2.IMWRITE_JPEG_QUALITY, q])
        assert np.array_equal(img, cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
        errs.append(np.abs(img.astype(float) - ref).mean())
    assert 0 < errs[0] < errs[1]


def test_auto_exposure_swings_the_gain(up_rig, stripe_site):
    real = Realism(auto_exposure=0.2, ae_period_s=4.0)
    still = sideways(0.0)
    means = np.array([RL.render_real(up_rig, stripe_site, still.pose_at, int(t * 1e9),
                                     CLEAN, real)[:, :40].mean()
                      for t in np.arange(0.0, 4.0, 0.25)]) / sim.CEILING_GREY
    assert np.all(np.abs(means - 1) <= 0.2 + 0.01)    # within the amplitude
    assert np.ptp(means) > 0.3                        # and swinging over most of it


def test_glossy_walls_mirror_the_lamps():
    p = packaged_config("corridor")
    rig, site = Rig.load(p / "rig.yaml"), Site.load(p / "site.yaml")
    rig = Rig(rig.camera.scaled(160, 120), rig.mount)
    a = RL.render_real(rig, site, lambda t: (1.0, 0.1, 0.0), 0, CLEAN, Realism())
    b = RL.render_real(rig, site, lambda t: (1.0, 0.1, 0.0), 0, CLEAN, Realism(gloss=0.5))
    assert np.sum(b.astype(int) - a > 30) > 20


# --------------------------------------------------------------------------- presets
@pytest.mark.parametrize("name", ["corridor", "lights", "block"])
def test_realistic_preset_parses_for_every_example(name):
    real = load_preset(packaged_config(name) / "site.yaml", "realistic")
    assert real.active and real.rolling_shutter_ms > 0 and real.jpeg > 0


def test_realistic_preset_renders(up_rig):
    p = packaged_config("lights")
    site = Site.load(p / "site.yaml")
    real = load_preset(p / "site.yaml", "realistic").replace(time_samples=2)
    src = SimSource(up_rig, site, straight_drive(2, x0_m=2.0), seed=1, realism=real)
    img = src.render(1).image
    plain = SimSource(up_rig, site, straight_drive(2, x0_m=2.0), seed=1).render(1).image
    assert img.shape == plain.shape and not np.array_equal(img, plain)


def test_bad_presets_name_file_and_key(tmp_path):
    f = tmp_path / "presets.yaml"
    f.write_text("realistic:\n  pipes: 2\n  jpg: 80\n")
    with pytest.raises(ConfigError, match=r"presets.yaml: realistic.jpg: unknown key"):
        load_presets(f)
    f.write_text("realistic:\n  flicker: 2.0\n")
    with pytest.raises(ConfigError, match=r"presets.yaml: realistic.flicker: .*\[0, 1\]"):
        load_presets(f)
    with pytest.raises(ConfigError, match="no such preset"):
        f.write_text("realistic:\n  pipes: 1\n")
        load_preset(tmp_path / "site.yaml", "other")
    with pytest.raises(ConfigError, match="no presets file"):
        load_preset(tmp_path / "sub" / "site.yaml", "realistic")


def test_parse_knobs_and_only():
    r = parse_knobs(["motion_blur_ms=8", "jpeg=70"], Realism(pipes=2))
    assert (r.pipes, r.motion_blur_ms, r.jpeg) == (2, 8.0, 70)
    assert r.only("jpeg").on == ("jpeg",)
    for bad in (["motion_blur=8"], ["jpeg"], ["jpeg=x"], ["pipes=1.5"], ["lamps_off=2"]):
        with pytest.raises(ConfigError) as e:
            parse_knobs(bad)
        assert e.value.key == "sim-fault"
    with pytest.raises(ConfigError):
        Realism(time_samples=1)


def test_sim_device_query_and_camera_controls():
    p = packaged_config("corridor")
    rig, site = Rig.load(p / "rig.yaml"), Site.load(p / "site.yaml")
    src = open_source("sim:corridor?preset=realistic&jpeg=60,people=0", rig, site, frames=3)
    assert src.realism.jpeg == 60 and src.realism.people == 0 and src.realism.pipes == 3
    assert open_source("sim:corridor", rig, site, frames=3).realism is None
    with pytest.raises(ConfigError, match="device: sim:corridor\\?nope=1"):
        open_source("sim:corridor?nope=1", rig, site, frames=3)
    opts, real = sim_camera_options(200.0, 6.0)
    assert opts.exposure == pytest.approx(2.0 * 10 ** 0.3) and real.motion_blur_ms == 20.0
    nominal, _ = sim_camera_options(None, None)
    assert nominal.exposure == 1.0 and nominal.noise_sigma == pytest.approx(2.0)
    assert opts.noise_sigma > nominal.noise_sigma
    with pytest.raises(ConfigError):
        sim_camera_options(-1.0, None)


def test_trajectory_pose_at():
    tr = Trajectory(np.array([0, 100, 200]), np.array([0.0, 1.0, 3.0]), np.zeros(3),
                    np.array([0.0, 0.1, 0.2]))
    assert tr.pose_at(50) == pytest.approx((0.5, 0.0, 0.05))
    assert tr.pose_at(150) == pytest.approx((2.0, 0.0, 0.15))
    assert tr.pose_at(300) == pytest.approx((5.0, 0.0, 0.3))   # extended along the last step
    assert tr.pose_at(-100) == pytest.approx((-1.0, 0.0, -0.1))
