"""Overlays: pure, the right things drawn where the estimate and the site say."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.viz.overlay import (
    LINE_COLOURS,
    MATCHED_BGR,
    caption,
    draw_overlay,
    drawn_estimate,
    norm_to_px,
    world_to_px,
)
from helpers import FIXTURES


@pytest.fixture(scope="module")
def corridor():
    rec = Recording(FIXTURES / "corridor_rec")
    # the fixture corridor is symmetric about its centre line: the heading is stated
    return rec, make_estimator("corridor", rec.rig, rec.site, {"assume_heading_deg": 0.0})


@pytest.fixture(scope="module")
def lights():
    rec = Recording(FIXTURES / "lights_rec")
    return rec, make_estimator("lights", rec.rig, rec.site)


def test_world_to_px_inverts_the_camera_ray(corridor):
    rec = corridor[0]
    rig: Rig = rec.rig
    x, y, yaw = 1.0, 0.2, math.radians(10)
    px = np.array([[320.0, 200.0]])
    ray_c = np.r_[rig.camera.unproject(px)[0], 1.0]
    R_wc = rig.mount.R_world_cam(yaw)
    c_w = rig.mount.camera_position(x, y, yaw)
    d_w = R_wc @ ray_c
    s = (rec.site.ceiling_height_m - c_w[2]) / d_w[2]
    p_w = c_w + s * d_w
    assert np.allclose(world_to_px(rig, x, y, yaw, p_w[None]), px, atol=1e-6)
    behind = c_w - 5 * d_w
    assert np.isnan(world_to_px(rig, x, y, yaw, behind[None])).all()


def test_norm_to_px_round_trip(corridor):
    cam = corridor[0].rig.camera
    px = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 400.0]])
    assert np.allclose(norm_to_px(corridor[0].rig, cam.unproject(px)), px, atol=1e-3)


def test_corridor_overlay_is_pure_and_colours_matched_segments(corridor):
    rec, est = corridor
    frame = rec.frame(3)
    image = frame.image.copy()
    e = est.estimate(frame.image, frame.t_ns)
    assert e and {"segments_n", "along", "across", "assign"} <= set(e.diagnostics)
    img = draw_overlay(frame.image, e, rec.rig, rec.site)
    assert np.array_equal(frame.image, image)  # the frame is not touched
    assert img.shape == (*frame.image.shape[:2], 3) and img.dtype == np.uint8
    assert np.array_equal(img, draw_overlay(frame.image, e, rec.rig, rec.site))  # pure
    # each matched forward segment is drawn in its site line's colour at its midpoint
    d = e.diagnostics
    segs_px = norm_to_px(rec.rig, np.asarray(d["segments_n"]).reshape(-1, 2)).reshape(-1, 4)
    checked = 0
    for i in np.flatnonzero(d["along"] & (d["assign"] >= 0)):
        u, v = (segs_px[i, :2] + segs_px[i, 2:]) / 2
        colour = LINE_COLOURS[int(d["assign"][i]) % len(LINE_COLOURS)]
        patch = img[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2].reshape(-1, 3)
        checked += any(np.abs(p.astype(int) - colour).max() < 40 for p in patch)
    assert checked >= 2


def test_lights_overlay_marks_matched_spots(lights):
    rec, est = lights
    frame = rec.frame(2)
    e = est.estimate(frame.image, frame.t_ns)
    assert e and len(e.diagnostics["pairs"]) >= 3
    img = draw_overlay(frame.image, e, rec.rig, rec.site)
    spots = np.asarray(e.diagnostics["spots_px"])
    i_spot = int(e.diagnostics["pairs"][0][0])
    u, v = spots[i_spot]
    ring = img[int(v) - 11:int(v) + 12, int(u) - 11:int(u) + 12].reshape(-1, 3)
    assert (np.abs(ring.astype(int) - MATCHED_BGR).max(axis=1) < 60).sum() > 10


def test_failure_overlay_shows_the_reason(lights):
    rec, est = lights
    blank = np.full_like(rec.frame(0).image, 40)
    f = est.estimate(blank, 5)
    assert not f
    img = draw_overlay(blank, f, rec.rig, rec.site)
    assert caption(f)[1] == f"FAILED: {f.reason}"
    assert (img != 40).any()  # the text box


def test_a_gated_failure_draws_the_rejected_estimate():
    pose = PoseEstimate(1, "lights", 1.0, 2.0, 0.0, 0.9)
    gated = Failure(1, "lights", "gated", diagnostics={"rejected": pose})
    shown, was_gated = drawn_estimate(gated)
    assert shown is pose and was_gated
    assert drawn_estimate(pose) == (pose, False)
    assert "GATED" in caption(pose, True)[2]


def test_block_overlay_draws_corners(tmp_path):
    from ceilkit.runtime.devices import packaged_config
    from ceilkit.runtime.sim.render import render_frame
    cfg = packaged_config("block")
    rig, site = Rig.load(cfg / "rig.yaml"), Site.load(cfg / "site.yaml")
    est = make_estimator("block", rig, site)
    m = site.markers.poses[0]  # the camera under marker 0
    image = render_frame(rig, site, m.x_m - rig.mount.x_m, m.y_m - rig.mount.y_m, 0.0)
    e = est.estimate(image, 1)
    assert e and e.diagnostics["source"] == f"marker:{m.id}"
    img = draw_overlay(image, e, rig, site)
    assert img.shape[:2] == image.shape[:2]
    assert e.diagnostics["corners_norm"].shape == (4, 2)
    corners = norm_to_px(rig, e.diagnostics["corners_norm"])
    u, v = corners[0]
    patch = img[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3].reshape(-1, 3)
    assert (np.abs(patch.astype(int) - MATCHED_BGR).max(axis=1) < 60).any()
