"""Tests of runtime/features/windows.py: the stacked-window spot reading and the
windowed spot stage (found decimated, read at full resolution)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.lights import LightsEstimator, project_lights
from ceilkit.runtime.features.spots import SpotParams, detect_spots
from ceilkit.runtime.features.windows import detect_spots_windowed, window_stats
from ceilkit.runtime.features.working import decimated_mask
from ceilkit.runtime.sim.render import SimOptions, render_frame

POSES = [(6.0, 0.5, 0.5), (12.0, 2.0, 2.8), (3.5, -2.0, -1.2), (9.0, -3.5, 1.9)]


def gaussian_spots(shape, centres, sigma, peak=180.0, background=40.0, seed=0):
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = np.full(shape, background)
    for u, v in centres:
        img += peak * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
    img += np.random.default_rng(seed).normal(0.0, 1.0, shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def test_window_stats_reads_known_spots():
    centres = [(30.3, 40.7), (101.6, 22.2), (70.0, 90.5)]
    img = gaussian_spots((120, 140), centres, 2.5)
    c = np.rint(centres).astype(np.int64)
    rows, ok, contrast = window_stats(img, c - 10, 21)
    assert ok.all() and np.all(contrast > 150)
    np.testing.assert_allclose(rows[:, :2], centres, atol=0.05)
    np.testing.assert_allclose(rows[:, 3], 40.0, atol=1.0)             # I_b: the border
    # a round spot: equal second moments, no cross term
    np.testing.assert_allclose(rows[:, 4], rows[:, 6], rtol=0.1)
    assert np.all(np.abs(rows[:, 5]) < 0.1 * rows[:, 4])
    # a window whose border cuts the spot is not ok; a flat window has no contrast
    rows2, ok2, _ = window_stats(img, np.array([[c[0, 0], c[0, 1] - 10]]), 21)
    assert not ok2[0]
    _, _, flat = window_stats(img, np.array([[0, 100]]), 15)
    assert flat[0] < 10


def frames(rig, site):
    for k, (x, y, yaw) in enumerate(POSES):
        yield render_frame(rig, site, x, y, yaw, rng=np.random.default_rng(k),
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8))


def inner(spots, margin_px=15.0):
    c = spots.centroids_px
    return c[(c[:, 0] > margin_px) & (c[:, 0] < 639 - margin_px) & (c[:, 1] > margin_px)
             & (c[:, 1] < 479 - margin_px)]


def test_windowed_stage_finds_the_full_resolution_spots(lights_rig, lights_site):
    """On fixture frames the decimated search with full-resolution windows finds every
    spot the full-resolution detector finds, at the same place (to 0.07 px), away from
    the image border (a light cut by the border is dropped by the windows' border
    check; the detector keeps its biased centroid); what it finds besides (a few dim,
    far lights at the fisheye's edge) are lights of the map."""
    est = LightsEstimator(lights_rig, lights_site)
    params = SpotParams()
    half = decimated_mask(est.valid_mask, 2)
    n_total = 0
    for img, pose in zip(frames(lights_rig, lights_site), POSES, strict=True):
        full = inner(detect_spots(img, params, est.valid_mask, est.nadir_px, 48))
        win = detect_spots_windowed(img, params, half, est.nadir_px, 48).centroids_px
        assert len(full) >= 8 and len(win) >= len(full) - 1
        d = np.linalg.norm(full[:, None] - win[None], axis=2)
        assert np.all(d.min(axis=1) < 0.07), d.min(axis=1)
        assert len(set(d.argmin(axis=1).tolist())) == len(full)        # one to one
        truth = project_lights(lights_rig, 3.0, est.lights_w, *pose)
        to_light = np.linalg.norm(win[:, None] - truth[None], axis=2)
        assert np.all(np.nanmin(to_light, axis=1) < 1.5)
        n_total += len(full)
    assert n_total >= 60


def test_windowed_stage_localizes_as_the_full_stage(lights_rig, lights_site):
    full = LightsEstimator(lights_rig, lights_site, {"spot_stage": "full"})
    win = LightsEstimator(lights_rig, lights_site, {"spot_stage": "windowed"})
    assert win.observer.windowed and not full.observer.windowed
    for img, (x, y, yaw) in zip(frames(lights_rig, lights_site), POSES, strict=True):
        a, b = full.estimate(img, 0), win.estimate(img, 0)
        assert a and b and b.diagnostics["mode"] == "global"
        assert math.hypot(b.x_m - x, b.y_m - y) < 0.003
        assert math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) < 0.001
        assert abs(math.degrees(math.remainder(b.yaw_rad - yaw, 2 * math.pi))) < 0.05


def test_windowed_stage_on_a_blank_frame_and_a_bad_name(lights_rig, lights_site):
    est = LightsEstimator(lights_rig, lights_site, {"spot_stage": "windowed"})
    assert len(detect_spots_windowed(np.full((480, 640), 90, np.uint8))) == 0
    assert not est.estimate(np.full((480, 640), 90, np.uint8), 0)
    with pytest.raises(ConfigError, match="spot_stage"):
        LightsEstimator(lights_rig, lights_site, {"spot_stage": "quarter"})
