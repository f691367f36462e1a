"""The working resolution: decimated spot detection in full-resolution pixels, and the
lights estimator on a frame larger than its working size."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.estimators.lights import LightsEstimator
from ceilkit.runtime.features.lines import SegmentDetector, segment_lengths
from ceilkit.runtime.features.spots import detect_spots
from ceilkit.runtime.features.working import (
    decimate,
    decimated_mask,
    detect_spots_working,
    undecimate,
    working_factor,
)

SPOTS_PX = np.array([[400.3, 300.7], [1210.6, 820.2], [1650.9, 450.4], [700.1, 1100.8]])


def _spot_frame(h=1500, w=2000, sigma=9.0, seed=0):
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    img = np.full((h, w), 60.0)
    for u, v in SPOTS_PX:
        img += 170.0 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
    img += np.random.default_rng(seed).normal(0.0, 2.0, img.shape)
    return np.clip(img, 0, 255).round().astype(np.uint8)


def _scaled(rig, k):
    cam = rig.camera
    K = cam.K.copy()
    K[:2, :2] *= k
    K[:2, 2] = K[:2, 2] * k + (k - 1) / 2
    return dataclasses.replace(rig, camera=dataclasses.replace(
        cam, width=k * cam.width, height=k * cam.height, K=K, P=None))


def test_factor_decimate_undecimate():
    assert working_factor((3000, 4000)) == 3 and working_factor((480, 640)) == 1
    assert working_factor((3000, 4000), 0.0) == 1
    grey = np.zeros((20, 20), np.uint8)
    grey[4:6, 10:12] = 200                         # a 2x2 block centred on (10.5, 4.5)
    small = decimate(grey, 2)
    v, u = np.unravel_index(np.argmax(small), small.shape)
    np.testing.assert_allclose(undecimate(np.array([u, v]), 2), [10.5, 4.5])
    mask = np.zeros((20, 20), np.uint8)
    mask[:, :9] = 255
    assert decimated_mask(mask, 2)[:, :4].all() and not decimated_mask(mask, 2)[:, 5:].any()


def test_decimated_spots_match_the_truth_and_scale_their_moments():
    grey = _spot_frame()
    f = working_factor(grey.shape, 1.0)
    assert f == 2
    s = detect_spots_working(grey, factor=f)
    assert len(s) == len(SPOTS_PX)
    d = np.linalg.norm(s.centroids_px[:, None, :] - SPOTS_PX[None], axis=2)
    assert d.min(axis=1).max() < 0.05                     # the first moments are kept
    # second moments in full-resolution px^2: a Gaussian of sigma 9 px, cut at a threshold
    var = np.linalg.eigvalsh(s.cov_px)
    assert np.all((var > 20) & (var < 90))
    small = detect_spots(decimate(grey, f))
    np.testing.assert_allclose(s.areas_px, small.areas_px * 4)


def _estimate_doubled(cls, rig, site, x, y, yaw):
    """``cls`` at working size 0.3 Mpx (factor 2) on a frame of twice ``rig``'s size."""
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    rig = _scaled(rig, 2)
    img = render_frame(rig, site, x, y, yaw, SimOptions(supersample=1),
                       rng=np.random.default_rng(0))
    # (the packaged corridor is symmetric about its centre line: its heading is stated)
    opts = {"assume_heading_deg": 0.0} if cls.name == "corridor" else {}
    est = cls(rig, site, {"working_mpx": 0.3, **opts})
    return est, est.estimate(img, 0)


def test_lights_estimator_on_a_frame_above_its_working_size(lights_rig, lights_site):
    est, out = _estimate_doubled(LightsEstimator, lights_rig, lights_site, 1.0, 0.5, 0.3)
    assert est.observer.factor == 2
    assert out, out
    assert math.hypot(out.x_m - 1.0, out.y_m - 0.5) < 0.005
    assert abs(math.degrees(out.yaw_rad - 0.3)) < 0.1


@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_working_size_is_validated(lights_rig, lights_site, bad):
    with pytest.raises(ConfigError) as e:
        LightsEstimator(lights_rig, lights_site, {"working_mpx": bad})
    assert e.value.key == "options.working_mpx"


def test_decimated_segments_come_back_in_full_resolution_pixels():
    img = np.full((600, 800), 150, np.uint8)
    img[:, 300:] = 60                                   # a vertical edge at u = 299.5
    img[400:, :] = 220                                  # a horizontal one at v = 399.5
    segs = SegmentDetector("fld", 100.0, merge=False, factor=2)(img)
    assert segs.shape[0] >= 2
    vertical = segs[np.abs(segs[:, 0] - segs[:, 2]) < 1.0]
    horizontal = segs[np.abs(segs[:, 1] - segs[:, 3]) < 1.0]
    assert np.abs(vertical[:, [0, 2]] - 299.5).max() < 1.5
    assert np.abs(horizontal[:, [1, 3]] - 399.5).max() < 1.5
    assert (segment_lengths(segs) >= 100.0).all()


def test_corridor_estimator_on_a_frame_above_its_working_size(corridor_rig, corridor_site):
    est, out = _estimate_doubled(CorridorEstimator, corridor_rig, corridor_site, 2.0, 0.1,
                                 0.05)
    assert est.detector.factor == 2
    assert out, out
    assert abs(out.y_m - 0.1) < 0.001 and abs(math.degrees(out.yaw_rad - 0.05)) < 0.01
    assert out.quality >= 0.5
