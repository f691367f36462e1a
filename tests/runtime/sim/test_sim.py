"""The ceiling simulator: geometry against CameraModel.project, determinism, noise,
trajectories, the source, bad arguments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Block, Corridor, LampRow, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.io.recording import RecordingWriter
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.sim import render as sim
from ceilkit.runtime.sim.render import (
    SimOptions,
    SimSource,
    Trajectory,
    load_trajectory,
    random_poses,
    render_frame,
    render_radiance,
    straight_drive,
)

CLEAN = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0)


def small(rig: Rig, w: int = 320, h: int = 240) -> Rig:
    return Rig(rig.camera.scaled(w, h), rig.mount)


def project_world(rig: Rig, pts_w: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """Pixels (N, 2) of world points (N, 3) seen from vehicle pose (x, y, yaw)."""
    R = rig.mount.R_world_cam(yaw)
    c = rig.mount.camera_position(x, y, yaw)
    return rig.camera.project((np.asarray(pts_w, float) - c) @ R)


def blob_centroid(img: np.ndarray, u: float, v: float, thresh: float, r: int = 12):
    u0, v0 = int(round(u)), int(round(v))
    win = img[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1].astype(float)
    w = np.clip(win - thresh, 0.0, None)
    vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    return (w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()


# --------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("s", [3, 2])
def test_light_disc_centroid_on_projection_pinhole(s):
    cam = CameraModel.pinhole(200, 160, fx=150.0, cx=97.3, cy=81.8)
    rig = Rig(cam, Mount(pan_rad=0.4, tilt_rad=math.pi / 2, x_m=0.1, z_m=0.5))
    lights = np.array([[1.0, 0.4], [0.3, -0.7], [-0.4, 0.2]])
    site = Site(3.0, lights_m=lights)
    x, y, yaw = 0.2, 0.1, 0.3
    img = render_radiance(rig, site, x, y, yaw, CLEAN.replace(supersample=s))
    p = project_world(rig, np.c_[lights, np.full(3, 3.0)], x, y, yaw)
    for u, v in p:
        cu, cv = blob_centroid(img, u, v, sim.CEILING_GREY + sim.HALO_GREY + 5)
        assert abs(cu - u) < 0.1 and abs(cv - v) < 0.1


def test_light_disc_centroid_on_projection_fisheye(lights_rig):
    rig = Rig(lights_rig.camera.scaled(320, 240),
              Mount(pan_rad=0.3, tilt_rad=math.radians(80), swing_rad=0.1, z_m=0.5))
    lights = np.array([[1.0, 0.3], [0.5, -0.6], [2.0, 1.0]])
    site = Site(3.0, lights_m=lights)
    x, y, yaw = 0.2, 0.1, 0.4
    img = render_radiance(rig, site, x, y, yaw, CLEAN)
    p = project_world(rig, np.c_[lights, np.full(3, 3.0)], x, y, yaw)
    assert np.all(rig.camera.in_image(p, 15))
    for u, v in p:
        cu, cv = blob_centroid(img, u, v, 200.0)
        assert abs(cu - u) < 0.1 and abs(cv - v) < 0.1


def projected_disc(rig, centre_w, radius_m, x, y, yaw, n=8000):
    """Area centroid (2,) and area (px²) of a ceiling disc's exact image: its outline
    projected through the lens, as a polygon."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = np.c_[centre_w[0] + radius_m * np.cos(th), centre_w[1] + radius_m * np.sin(th),
                np.full(n, centre_w[2])]
    p = project_world(rig, rim, x, y, yaw)
    x_, y_ = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x_, -1), np.roll(y_, -1)
    cr = x_ * y1 - x1 * y_
    area = cr.sum() / 2
    return np.array([((x_ + x1) * cr).sum(), ((y_ + y1) * cr).sum()]) / (6 * area), area


def weighted_centroid(img, u, v, r=12, base=sim.CEILING_GREY):
    """Centroid and sum of ``img - base`` in a window: for a flat disc on a flat ceiling
    these are the disc image's area centroid and area (no threshold, no pixel locking)."""
    u0, v0 = int(round(u)), int(round(v))
    w = img[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1].astype(float) - base
    vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    return np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum(), w.sum()


def test_light_disc_is_its_exact_image_fisheye(lights_rig):
    """The rendered disc's centroid and area are those of the disc's exact image. That
    centroid is *not* the projection of the light's centre: through perspective and the
    fisheye it lies 0.02-0.04 px towards the image centre (the shift the threshold
    centroid above sees), which is geometry, not a rendering error."""
    rig = Rig(lights_rig.camera.scaled(320, 240),
              Mount(pan_rad=0.3, tilt_rad=math.radians(80), swing_rad=0.1, z_m=0.5))
    lights = np.array([[1.0, 0.3], [0.5, -0.6], [2.0, 1.0]])
    site = Site(3.0, lights_m=lights)
    x, y, yaw = 0.2, 0.1, 0.4
    opts = CLEAN.replace(halo=0.0)
    img = render_radiance(rig, site, x, y, yaw, opts)
    cam = rig.camera
    for lx, ly in lights:
        want, area = projected_disc(rig, (lx, ly, 3.0), opts.light_radius_m, x, y, yaw)
        got, got_area = weighted_centroid(img, *want)
        assert np.linalg.norm(got - want) < 0.01
        assert got_area / (sim.LIGHT_GREY - sim.CEILING_GREY) == pytest.approx(area, rel=3e-3)
        centre = project_world(rig, np.array([[lx, ly, 3.0]]), x, y, yaw)[0]
        radial = (want - centre) @ (centre - [cam.cx, cam.cy]) / np.hypot(*(centre - [cam.cx,
                                                                               cam.cy]))
        assert -0.05 < radial < -0.015


def test_vignetting_pulls_spots_inwards(lights_rig):
    """Vignetting is physical and optional: the brighter inner side of a spot moves
    its weighted centroid towards the principal point, by about a hundredth of a pixel
    here (the halo shifts it too, by an amount that depends on the view)."""
    rig = small(lights_rig)
    lights = np.array([[1.2, 0.9], [-0.9, 0.6], [0.4, -1.1]])
    site = Site(3.0, lights_m=lights)
    bare = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0, halo=0.0)
    ref = render_frame(rig, site, 0.0, 0.0, 0.0, bare).astype(float)
    vig = render_frame(rig, site, 0.0, 0.0, 0.0, bare.replace(vignetting=0.3)).astype(float)
    cam = rig.camera
    shifts = []
    for lx, ly in lights:
        c = project_world(rig, np.array([[lx, ly, 3.0]]), 0.0, 0.0, 0.0)[0]
        out = (c - [cam.cx, cam.cy]) / np.hypot(*(c - [cam.cx, cam.cy]))
        got = []
        for img in (ref, vig):
            u0, v0 = np.rint(c).astype(int)
            win = img[v0 - 12:v0 + 13, u0 - 12:u0 + 13]
            bg = np.median(win)
            w = np.clip(win - (bg + 0.4 * (win.max() - bg)), 0.0, None)   # as spots.py
            vv, uu = np.mgrid[v0 - 12:v0 + 13, u0 - 12:u0 + 13]
            got.append(np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum())
        shifts.append((got[1] - got[0]) @ out)
    shifts = np.array(shifts)                     # radial, px
    assert np.all(shifts > -0.1) and np.all(shifts < -0.002)


def test_halo_option(lights_rig):
    rig = small(lights_rig, 160, 120)
    site = Site(3.0, lights_m=np.array([[0.0, 0.0]]))
    a = render_radiance(rig, site, 0.4, 0.0, 0.0, CLEAN.replace(halo=0.0))
    b = render_radiance(rig, site, 0.4, 0.0, 0.0, CLEAN.replace(halo=90.0))
    c = render_radiance(rig, site, 0.4, 0.0, 0.0, CLEAN)
    d = b - a
    assert d.max() > 40 and np.count_nonzero(d > 1) > 40         # a glow around the disc
    np.testing.assert_allclose(c - a, d / 2, atol=1e-3)    # linear in `halo`
    assert np.all(a[(a > sim.CEILING_GREY + 1e-3)] > sim.CEILING_GREY)


def test_fisheye_black_beyond_its_range(lights_rig, lights_site):
    rig = small(lights_rig)
    img = render_radiance(rig, lights_site, 5.0, 0.0, 0.0, CLEAN)
    assert img[0, 0] == 0 and img[-1, -1] == 0          # corners: beyond 90 deg
    assert img[120, 160] > 100                          # centre: the ceiling


def test_lamp_centre_and_size_on_projection():
    cam = CameraModel.pinhole(240, 180, fx=160.0)
    rig = Rig(cam, Mount(tilt_rad=math.pi / 2, z_m=0.6))
    site = Site(2.6, lamps=(LampRow(0.3, 0.1, 1.2, 0.3),))
    x, y, yaw = 0.0, 0.0, 0.25
    img = render_radiance(rig, site, x, y, yaw, CLEAN)
    corners = site.lamp_rectangles()[0]
    p = project_world(rig, np.c_[corners, np.full(4, 2.6)], x, y, yaw)
    assert np.all(cam.in_image(p, 3))
    frac = (img - sim.CEILING_GREY) / (sim.LAMP_GREY - sim.CEILING_GREY)
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    area = frac.sum()
    # the projected rectangle (the plane is parallel to the image): area and centroid
    x_, y_ = p[:, 0], p[:, 1]
    want_area = 0.5 * abs(np.dot(x_, np.roll(y_, -1)) - np.dot(y_, np.roll(x_, -1)))
    assert area == pytest.approx(want_area, rel=2e-3)
    assert (frac * uu).sum() / area == pytest.approx(p[:, 0].mean(), abs=0.05)
    assert (frac * vv).sum() / area == pytest.approx(p[:, 1].mean(), abs=0.05)


def test_seams_on_projected_lines(corridor_rig):
    rig = small(corridor_rig)
    site = Site(2.8, Corridor((-0.45, 0.45)))
    x, y, yaw = 1.3, 0.07, math.radians(2.0)
    img = render_radiance(rig, site, x, y, yaw, CLEAN.replace(seam_width_m=0.03))
    for yl in (-0.45, 0.45):
        X = np.linspace(x - 3, x + 40, 50000)
        p = project_world(rig, np.c_[X, np.full_like(X, yl), np.full_like(X, 2.8)], x, y, yaw)
        p = p[np.isfinite(p[:, 0])]
        errs = []
        for v in range(0, 240, 3):
            u = np.interp(v, *(p[np.argsort(p[:, 1])][:, ::-1].T))
            if not 10 < u < 310:
                continue
            u0 = int(round(u))
            dark = sim.CEILING_GREY - img[v, u0 - 8:u0 + 9].astype(float)
            errs.append((dark * np.arange(u0 - 8, u0 + 9)).sum() / dark.sum() - u)
        errs = np.array(errs)
        assert errs.size > 40
        assert abs(errs.mean()) < 0.02 and np.abs(errs).max() < 0.1


def test_lamp_edges_are_not_drawn_twice(corridor_rig, corridor_site):
    """lines_along at the lamp edges (+-0.15) and the lamp-edge lines_across are the
    lamps' own edges: no seam between lamps there."""
    rig = Rig(CameraModel.pinhole(160, 120, fx=100.0), Mount(tilt_rad=math.pi / 2, z_m=0.8))
    img = render_radiance(rig, corridor_site, 1.2, 0.0, 0.0, CLEAN)   # between two lamps
    p = project_world(rig, np.array([[1.2, 0.15, 2.8], [1.2, 0.45, 2.8]]), 1.2, 0.0, 0.0)
    (u1, v1), (u2, v2) = np.rint(p).astype(int)
    assert img[v1, u1] == pytest.approx(sim.CEILING_GREY, abs=1e-3)   # no seam
    assert img[v2, u2] < sim.CEILING_GREY - 5                          # a seam


def test_block_is_dark_and_walls_darker_than_ceiling(corridor_rig):
    blk = Block("A", np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]))
    site = Site(2.8, Corridor((-0.45, 0.45)), blocks=(blk,))
    rig = small(corridor_rig)
    img = render_radiance(rig, site, 0.0, 0.0, 0.0, CLEAN)
    p = project_world(rig, np.array([[2.3, 0.0, 2.8]]), 0.0, 0.0, 0.0)[0]
    assert img[int(round(p[1])), int(round(p[0]))] == pytest.approx(sim.BLOCK_GREY)
    w = sim.wall_half_width(site)
    assert w == pytest.approx(0.45 + sim.WALL_MARGIN_M)
    # a wall point, projected: wall grey, between the floor's and the ceiling's
    pw = project_world(rig, np.array([[3.0, w, 2.4]]), 0.0, 0.0, 0.0)[0]
    assert rig.camera.in_image(pw[None], 5)[0]
    val = img[int(round(pw[1])), int(round(pw[0]))]
    assert sim.WALL_BOTTOM_GREY < val < sim.WALL_TOP_GREY
    # no corridor: no walls, the same direction sees the ceiling
    img2 = render_radiance(rig, Site(2.8), 0.0, 0.0, 0.0, CLEAN)
    assert img2[int(round(pw[1])), int(round(pw[0]))] == pytest.approx(sim.CEILING_GREY)


def test_clutter_adds_edges(corridor_rig, corridor_site):
    rig = small(corridor_rig)
    a = render_radiance(rig, corridor_site, 3.0, 0.0, 0.0, CLEAN)
    b = render_radiance(rig, corridor_site, 3.0, 0.0, 0.0, CLEAN.replace(clutter=True))
    assert np.mean(np.abs(a - b) > 20) > 0.02


# --------------------------------------------------------------------------- noise
def test_deterministic_for_a_seed_and_seeds_differ(corridor_rig, corridor_site):
    rig = small(corridor_rig, 160, 120)
    a = render_frame(rig, corridor_site, 1.0, 0.0, 0.0, rng=np.random.default_rng(5))
    b = render_frame(rig, corridor_site, 1.0, 0.0, 0.0, rng=np.random.default_rng(5))
    c = render_frame(rig, corridor_site, 1.0, 0.0, 0.0, rng=np.random.default_rng(6))
    assert a.dtype == np.uint8 and a.shape == (120, 160)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)


def test_noise_level(corridor_rig, corridor_site):
    rig = small(corridor_rig, 160, 120)
    opts = SimOptions(noise_sigma=0.0, vignetting=0.0)
    clean = render_frame(rig, corridor_site, 1.0, 0.0, 0.0, opts).astype(float)
    noisy = render_frame(rig, corridor_site, 1.0, 0.0, 0.0, opts.replace(noise_sigma=5.0),
                         np.random.default_rng(1)).astype(float)
    ok = (clean > 20) & (clean < 235)
    d = (noisy - clean)[ok]
    assert d.std() == pytest.approx(5.0, rel=0.05)
    assert abs(d.mean()) < 0.1


def test_exposure_and_vignetting(lights_rig, lights_site):
    rig = small(lights_rig, 160, 120)
    opts = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0)
    base = render_frame(rig, lights_site, 6.0, 0.0, 0.0, opts).astype(float)
    half = render_frame(rig, lights_site, 6.0, 0.0, 0.0, opts.replace(exposure=0.5))
    assert abs(float(half[60, 80]) - base[60, 80] / 2) <= 0.5
    vig = render_frame(rig, lights_site, 6.0, 0.0, 0.0, opts.replace(vignetting=0.4))
    cam = rig.camera
    assert vig[int(cam.cy), int(cam.cx)] == pytest.approx(base[int(cam.cy), int(cam.cx)],
                                                           abs=1)
    assert vig[60, 5] < base[60, 5] * 0.85                   # towards the edge


# --------------------------------------------------------------------------- trajectories
def test_straight_drive():
    tr = straight_drive(31, fps=10.0, speed_mps=0.6, x0_m=1.0, y_m=0.2,
                        yaw_rad=math.radians(90))
    assert tr.t_ns[1] == 100_000_000 and tr.t_ns.dtype == np.int64
    np.testing.assert_allclose(tr.x_m, 1.0, atol=1e-12)
    np.testing.assert_allclose(tr.y_m, 0.2 + 0.06 * np.arange(31))
    np.testing.assert_allclose(tr.yaw_rad, math.pi / 2)
    wv = straight_drive(600, fps=30.0, speed_mps=1.0, weave_m=0.1)
    assert np.max(np.abs(wv.y_m)) == pytest.approx(0.1, abs=1e-3)
    # the heading follows the path
    slope = np.gradient(wv.y_m, wv.x_m)
    np.testing.assert_allclose(wv.yaw_rad, np.arctan(slope), atol=2e-3)
    wb = straight_drive(100, yaw_wobble_rad=0.02, rng=np.random.default_rng(1))
    assert 0.015 < np.max(np.abs(wb.yaw_rad)) <= 0.02


def test_random_poses_within_ranges():
    rng = np.random.default_rng(2)
    tr = random_poses(50, (0.0, 10.0), (-0.3, 0.3), (-0.2, 0.2), rng, fps=20.0)
    assert len(tr) == 50 and tr.t_ns[-1] == 49 * 50_000_000
    assert tr.x_m.min() >= 0 and tr.x_m.max() <= 10 and np.ptp(tr.x_m) > 5
    assert np.all(np.abs(tr.y_m) <= 0.3) and np.all(np.abs(tr.yaw_rad) <= 0.2)


def test_load_trajectory_round_trip(tmp_path, corridor_rig, corridor_site):
    tr = straight_drive(5, weave_m=0.05, yaw_wobble_rad=0.01)
    with RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site, truth=True) as rec:
        for k in range(len(tr)):
            rec.write_truth(int(tr.t_ns[k]), *tr.pose(k))
    back = load_trajectory(tmp_path / "rec" / "truth.csv")
    np.testing.assert_array_equal(back.t_ns, tr.t_ns)
    np.testing.assert_allclose(back.y_m, tr.y_m, atol=1e-6)
    np.testing.assert_allclose(back.yaw_rad, tr.yaw_rad, atol=1e-7)


# --------------------------------------------------------------------------- source
def test_sim_source(corridor_rig, corridor_site):
    rig = small(corridor_rig, 96, 72)
    tr = straight_drive(4, fps=30.0)
    with SimSource(rig, corridor_site, tr, seed=3) as src:
        frames = list(src)
        assert src.read() is None
        again = src.render(2)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.t_ns for f in frames] == list(tr.t_ns)
    assert isinstance(frames[0], Frame) and frames[0].image.shape == (72, 96)
    np.testing.assert_array_equal(again.image, frames[2].image)
    x, y, yaw = src.pose(2)
    np.testing.assert_array_equal(
        frames[2].image,
        render_frame(rig, corridor_site, x, y, yaw, SimOptions(), np.random.default_rng([3, 2])))
    other = SimSource(rig, corridor_site, tr, seed=4).render(2)
    assert np.any(other.image != frames[2].image)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kw", [
    {"noise_sigma": -1.0}, {"blur_px": -0.5}, {"exposure": 0.0}, {"vignetting": 1.0},
    {"supersample": 0}, {"supersample": 2.5}, {"seam_width_m": 0.0},
    {"light_radius_m": -0.1}, {"wall_half_width_m": 0.0}, {"noise_sigma": math.nan},
    {"halo": -1.0},
])
def test_bad_options(kw):
    with pytest.raises(ConfigError, match=f"options.{next(iter(kw))}"):
        SimOptions(**kw)


def test_bad_render_arguments(corridor_rig, corridor_site):
    rig = small(corridor_rig, 64, 48)
    with pytest.raises(ConfigError, match="y_m"):
        render_frame(rig, corridor_site, 0.0, math.nan, 0.0)
    with pytest.raises(ConfigError, match="ceiling_height"):
        render_frame(rig, Site(0.5), 0.0, 0.0, 0.0)
    with pytest.raises(ConfigError, match="rng"):
        render_frame(rig, corridor_site, 0.0, 0.0, 0.0, rng=3)


def test_bad_trajectories(tmp_path):
    with pytest.raises(ConfigError, match="n"):
        straight_drive(0)
    with pytest.raises(ConfigError, match="fps"):
        straight_drive(3, fps=0.0)
    with pytest.raises(ConfigError, match="y_range"):
        random_poses(3, (0, 1), (1, 0), (0, 0), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="stamps must increase"):
        Trajectory(np.array([0, 5, 5]), np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ConfigError, match="yaw_rad"):
        Trajectory(np.array([0, 5]), np.zeros(2), np.zeros(2), np.zeros(3))
    with pytest.raises(ConfigError, match="not found"):
        load_trajectory(tmp_path / "missing.csv")
    bad = tmp_path / "truth.csv"
    bad.write_text("t_ns,x,y,yaw_deg\n0,1,2,abc\n")
    with pytest.raises(ConfigError, match="yaw_deg"):
        load_trajectory(bad)


def test_packaged_corridor_seams_as_the_site_says(corridor_site):
    """configs/corridor: lines_across every 1.2 m from -0.6 are the lamps' short ends
    while there are lamps (x >= -0.6), so they are drawn only as lamp ends; before the
    first lamp (x = -1.8) an across line is a seam from wall to wall. lines_along at
    +-0.45 are seams everywhere, at +-0.15 the lamps' long edges only."""
    rig = Rig(CameraModel.pinhole(200, 200, fx=60.0), Mount(tilt_rad=math.pi / 2, z_m=0.8))
    x0 = -1.2
    img = render_radiance(rig, corridor_site, x0, 0.0, 0.0, CLEAN)

    def grey(x, y):
        u, v = np.rint(project_world(rig, np.array([[x, y, 2.8]]), x0, 0.0, 0.0)[0]).astype(int)
        return img[v, u]

    for y in (-0.3, 0.0, 0.3):
        assert grey(-1.8, y) < sim.CEILING_GREY - 5          # a seam across, no lamp there
        assert grey(-2.4, y) == pytest.approx(sim.CEILING_GREY, abs=1e-3)
    assert grey(-0.6, 0.3) == pytest.approx(sim.CEILING_GREY, abs=1e-3)   # lamp end only
    assert grey(-0.3, 0.0) == pytest.approx(sim.LAMP_GREY, abs=1e-3)
    assert grey(-1.2, 0.45) < sim.CEILING_GREY - 5 and grey(-1.2, -0.45) < sim.CEILING_GREY - 5
    assert grey(-1.2, 0.15) == pytest.approx(sim.CEILING_GREY, abs=1e-3)
