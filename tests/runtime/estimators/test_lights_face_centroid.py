"""The lit face's centroid on the ceiling plane from a spot's image moments
(``rays.ceiling_centroids``, issue 39 / 36): a disc and a rectangle seen off-axis
through an equidistant fisheye (and a tilted pinhole) are placed at their true centre,
where the image centroid's ray misses it by a millimetre (disc) or two centimetres
(panel); on the axis both agree."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.lights import ceiling_centroids, ceiling_points, view_mask
from ceilkit.runtime.estimators.lights.rays import project_lights
from ceilkit.runtime.features.spots import detect_spots
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, render_frame

H = 3.0


def fisheye_rig() -> Rig:
    """bench_heldout_texture's scatter1 kind: 800x600 equidistant, f 300, looking up."""
    K = np.array([[300.0, 0.0, 399.5], [0.0, 300.0, 299.5], [0.0, 0.0, 1.0]])
    cam = CameraModel(800, 600, K, [0.02, -0.005, 0.0, 0.0], "equidistant")
    return Rig(cam, Mount(tilt_rad=math.pi / 2, swing_rad=0.02, x_m=0.1, z_m=0.5))


def tilted_rig() -> Rig:
    cam = CameraModel.pinhole(640, 480, 400.0, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    return Rig(cam, Mount(pan_rad=0.3, tilt_rad=math.radians(60), x_m=0.3, z_m=0.8))


def face_moments(rig: Rig, centre: np.ndarray, inside, reach_m: float, ss: int = 8
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Image centroid and second central moments (px²) of a uniformly lit face on the
    ceiling (``inside(d)``: ``d`` ``(K, 2)`` offsets from ``centre`` in W, the vehicle
    at the origin facing +x), each pixel weighted by the share of its ``ss x ss``
    samples whose rays meet the face: the image of the face, exactly, bar sampling."""
    th = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    ring = centre + reach_m * np.stack([np.cos(th), np.sin(th)], 1)
    px = project_lights(rig, H, ring, 0.0, 0.0, 0.0)
    (u0, v0), (u1, v1) = np.floor(px.min(0)) - 2, np.ceil(px.max(0)) + 2
    uu, vv = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    shape = uu.shape + (ss, ss)
    U = np.broadcast_to(uu[..., None, None] + off[None, None, None, :], shape).ravel()
    V = np.broadcast_to(vv[..., None, None] + off[None, None, :, None], shape).ravel()
    q, ok = ceiling_points(rig, H, np.stack([U, V], 1))
    assert ok.all()
    w = inside(q - centre).reshape(uu.shape + (ss * ss,)).mean(axis=2)
    m = w.sum()
    c = np.array([(w * uu).sum(), (w * vv).sum()]) / m
    du, dv = uu - c[0], vv - c[1]
    S = np.array([[(w * du * du).sum(), (w * du * dv).sum()],
                  [(w * du * dv).sum(), (w * dv * dv).sum()]]) / m
    return c, S


def disc(r: float):
    return lambda d: np.hypot(d[:, 0], d[:, 1]) <= r


def rectangle(length: float, width: float, yaw: float):
    c, s = math.cos(yaw), math.sin(yaw)
    return lambda d: ((np.abs(c * d[:, 0] + s * d[:, 1]) <= length / 2)
                      & (np.abs(-s * d[:, 0] + c * d[:, 1]) <= width / 2))


def errors_mm(rig: Rig, centre, inside, reach_m: float) -> tuple[float, float]:
    """``(|image centroid's ray - centre|, |face centroid - centre|)``, mm."""
    centre = np.asarray(centre, float)
    c, S = face_moments(rig, centre, inside, reach_m)
    old, ok_old = ceiling_points(rig, H, c[None])
    new, ok_new = ceiling_centroids(rig, H, c[None], S[None])
    assert ok_old.all() and ok_new.all()
    return 1e3 * float(np.hypot(*(old[0] - centre))), 1e3 * float(np.hypot(*(new[0] - centre)))


@pytest.mark.parametrize("r_m", [1.0, 2.0, 3.0])
def test_fisheye_disc_off_axis_is_placed_at_its_centre(r_m):
    rig = fisheye_rig()
    centre = (0.1 + r_m * math.cos(0.5), r_m * math.sin(0.5))
    old, new = errors_mm(rig, centre, disc(0.075), 0.075)
    assert old > 0.7                     # the image centroid's ray: 0.78-1.19 mm short
    assert new < 0.1                     # the face's centroid: 0.01-0.05 mm


@pytest.mark.parametrize("r_m", [1.0, 2.5])
def test_fisheye_rectangle_off_axis_is_placed_at_its_centre(r_m):
    rig = fisheye_rig()
    centre = (0.1 + r_m * math.cos(2.0), r_m * math.sin(2.0))
    old, new = errors_mm(rig, centre, rectangle(0.58, 0.58, 0.3), 0.42)
    assert old > 10.0                    # a 0.58 m panel: 15-23 mm short
    assert new < 0.3                     # 0.1-0.2 mm (third order)
    old, new = errors_mm(rig, centre, rectangle(0.6, 0.2, -0.7), 0.32)
    assert old > 8.0 and new < 0.3


def test_tilted_pinhole_disc_is_placed_at_its_centre():
    rig = tilted_rig()
    old, new = errors_mm(rig, (2.4, 1.5), disc(0.075), 0.075)
    assert old > 5 * new and new < 0.1


def test_on_the_axis_agrees_with_the_centroid_ray():
    rig = fisheye_rig()
    c = np.array([[rig.camera.cx, rig.camera.cy]])
    S = np.array([[[80.0, 10.0], [10.0, 50.0]]])
    new, ok = ceiling_centroids(rig, H, c, S)
    old, _ = ceiling_points(rig, H, c)
    assert ok.all() and np.allclose(new, old, atol=1e-9)
    # no extent, no correction, anywhere
    c = np.array([[120.0, 80.0], [600.0, 450.0]])
    new, _ = ceiling_centroids(rig, H, c, np.zeros((2, 2, 2)))
    assert np.allclose(new, ceiling_points(rig, H, c)[0], atol=1e-12)


def test_rays_that_do_not_rise_are_flagged_and_empty_input():
    rig = tilted_rig().with_mount(Mount(tilt_rad=0.0, z_m=0.8))    # looking level
    px = np.array([[320.0, 470.0], [320.0, 10.0], [320.0, 240.0]])   # below, above, at
    q0, ok0 = ceiling_points(rig, H, px)
    q, ok = ceiling_centroids(rig, H, px, np.tile(np.eye(2) * 20.0, (3, 1, 1)))
    assert np.array_equal(ok, [False, True, False]) and np.array_equal(ok, ok0)
    assert np.all(np.isnan(q[~ok])) and np.all(np.isfinite(q[ok]))
    q, ok = ceiling_centroids(rig, H, np.zeros((0, 2)), np.zeros((0, 2, 2)))
    assert q.shape == (0, 2) and ok.shape == (0,)


def test_detected_spots_of_the_simulator_land_on_the_disc_centre():
    """Through the whole detection path (render, detect_spots' weighted moments): the
    face's centroid is 0.18-0.44 mm off where the image centroid's ray is 0.88-1.41 mm
    off. What is left is the detector's: its weights drop each edge's ramp below 40 % of
    the contrast, which moves the centroid 0.01-0.02 px off the face's image (and makes
    the moments 10 % small); with the exact image moments the point is 0.03-0.07 mm
    off (the tests above)."""
    rig = fisheye_rig()
    opts = SimOptions(noise_sigma=0.0, blur_px=0.8, vignetting=0.0, supersample=4,
                      light_radius_m=0.075, halo=0.0, texture=0.0)
    lights = np.array([[0.1 + r * math.cos(a), r * math.sin(a)]
                       for r, a in ((1.2, 0.5), (2.2, 2.5), (3.0, -1.0))])
    img = render_frame(rig, Site(H, lights_m=lights), 0.0, 0.0, 0.0, opts)
    spots = detect_spots(img, None, view_mask(rig, math.radians(60.0)))
    old, _ = ceiling_points(rig, H, spots.centroids_px)
    new, _ = ceiling_centroids(rig, H, spots.centroids_px, spots.cov_px)
    d_old = np.linalg.norm(old[:, None] - lights[None], axis=2).min(axis=0)
    d_new = np.linalg.norm(new[:, None] - lights[None], axis=2).min(axis=0)
    assert np.all(d_old > 0.8e-3)
    assert np.all(d_new < 0.5e-3) and np.all(d_new < 0.4 * d_old)
