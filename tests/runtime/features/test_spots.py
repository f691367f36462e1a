"""Tests of runtime/spots.py: Niblack thresholding, identification, sub-pixel centroids."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ceilkit.runtime.features.spots import (
    SpotParams,
    axis_ratios,
    detect_spots,
    niblack_mask,
    perception_level,
    tile_niblack_mask,
)


def blobs(centres: np.ndarray, radius: float = 5.0, peak: float = 200.0, bg: float = 50.0,
          noise: float = 2.0, seed: int = 0, size: tuple[int, int] = (160, 240),
          axes: tuple[float, float] | None = None) -> np.ndarray:
    """Anti-aliased discs (or ellipses) at sub-pixel ``centres`` (N, 2), blurred, noisy."""
    ss = 8
    h, w = size
    acc = np.zeros((h * ss, w * ss), np.uint8)
    ax = (radius, radius) if axes is None else axes
    for u, v in centres:
        c = (int(round((u + 0.5) * ss - 0.5)), int(round((v + 0.5) * ss - 0.5)))
        cv2.ellipse(acc, c, (int(ax[0] * ss), int(ax[1] * ss)), 0, 0, 360, 255, -1)
    img = bg + (peak - bg) * cv2.resize(acc.astype(np.float32) / 255, (w, h),
                                        interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def nearest(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(found[:, None] - truth[None], axis=2).min(axis=1)


CENTRES = np.array([[40.3, 30.7], [120.6, 80.2], [200.1, 130.9], [60.8, 120.4]])


def test_subpixel_centroids():
    spots = detect_spots(blobs(CENTRES))
    assert len(spots) == 4
    err = nearest(spots.centroids_px, CENTRES)
    assert err.max() < 0.1, err
    assert np.all(spots.contrast > 100) and np.all(spots.level > 2.0)
    assert np.all(np.abs(spots.areas_px - np.pi * 25) < 40)


def test_blank_and_noise_frames_give_no_spots():
    assert len(detect_spots(np.full((120, 160), 80, np.uint8))) == 0
    noisy = np.random.default_rng(1).normal(80, 4, (120, 160)).clip(0, 255).astype(np.uint8)
    assert len(detect_spots(noisy)) == 0
    assert len(detect_spots(np.zeros((0, 0), np.uint8))) == 0


def test_exposure_changes_and_colour_input():
    for peak, bg in ((120.0, 20.0), (255.0, 120.0), (90.0, 10.0)):
        spots = detect_spots(blobs(CENTRES, peak=peak, bg=bg))
        assert len(spots) == 4, (peak, bg)
        assert nearest(spots.centroids_px, CENTRES).max() < 0.15
    bgr = cv2.cvtColor(blobs(CENTRES), cv2.COLOR_GRAY2BGR)
    assert len(detect_spots(bgr)) == 4


def test_dim_reflection_and_elongated_streak_rejected():
    img = blobs(CENTRES)
    refl = blobs(np.array([[180.0, 40.0]]), peak=35.0, bg=0.0, noise=0.0)   # dim, +35
    streak = blobs(np.array([[120.0, 140.0]]), axes=(30.0, 1.5), peak=150.0, bg=0.0,
                   noise=0.0)
    out = cv2.add(cv2.add(img, refl), streak)
    spots = detect_spots(out)
    assert len(spots) == 4
    assert nearest(spots.centroids_px, CENTRES).max() < 0.15
    assert spots.rejected.get("dim", 0) == 1 and spots.rejected.get("shape", 0) == 1


def test_glare_halo_keeps_core():
    img = blobs(CENTRES).astype(np.float32)
    yy, xx = np.mgrid[0:160, 0:240]
    u, v = CENTRES[1]
    img += 90.0 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 30.0 ** 2))   # halo
    img = np.clip(img, 0, 255).astype(np.uint8)
    spots = detect_spots(img, SpotParams(max_area_px=400))
    err = nearest(spots.centroids_px, CENTRES)
    assert len(spots) >= 3 and err.max() < 0.3, err


def test_valid_mask_and_max_regions():
    img = blobs(CENTRES)
    valid = np.zeros_like(img)
    valid[:, :100] = 255
    spots = detect_spots(img, valid=valid)
    assert len(spots) == 2 and np.all(spots.centroids_px[:, 0] < 100)
    near = detect_spots(img, centre_px=(120.0, 80.0), max_regions=1)
    assert len(near) == 1 and nearest(near.centroids_px, CENTRES[1:2])[0] < 0.1


def test_perception_level_formula():
    lv = perception_level(np.array([240.0]), np.array([40.0]), np.array([100.0]))
    want = 200.0 * 100 ** 0.33 / (1.97 * 40 ** 0.72)
    assert lv[0] == pytest.approx(want)
    # a brighter background raises the visibility threshold; a larger object lowers it
    assert perception_level([140.0], [100.0], [100.0])[0] < perception_level(
        [80.0], [40.0], [100.0])[0]
    assert perception_level([80.0], [40.0], [10.0])[0] < perception_level(
        [80.0], [40.0], [100.0])[0]


def test_niblack_masks_agree_on_spots():
    img = blobs(CENTRES)
    m1 = niblack_mask(img, 41, 0.8, 25.0)
    m2 = tile_niblack_mask(img, 64, 2.5)
    ref = cv2.ximgproc.niBlackThreshold(img, 255, cv2.THRESH_BINARY, 41, 0.8)
    for u, v in CENTRES:
        p = (int(round(v)), int(round(u)))
        assert m1[p] == 255 and m2[p] == 255 and ref[p] == 255
    assert (m1 > 0).mean() < 0.05 and (m1 > 0).sum() <= (ref > 0).sum()



def _array_levels(small, win, k, min_contrast, rel):
    """The Niblack levels as the array operations read them (before niblack_levels)."""
    mean = cv2.boxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(small, cv2.CV_32F, (win, win), borderType=cv2.BORDER_REFLECT)
    box = (mean.copy(), sq.copy())
    sq -= mean * mean
    std = cv2.sqrt(np.maximum(sq, 0.0, out=sq))
    floor = np.maximum(mean * np.float32(rel), np.float32(min_contrast))
    std *= np.float32(k)
    thr = np.add(mean, np.maximum(std, floor, out=std), out=mean)
    return np.minimum(np.maximum(thr, 0.0, out=thr), 254.0, out=thr).astype(np.uint8), box


def test_niblack_levels_equal_the_array_reading():
    """The compiled thresholds are the array operations' bit for bit: noise, spots,
    two-level (0/255) frames, flat frames, small and large windows."""
    from ceilkit.runtime.features.spots import niblack_levels

    rng = np.random.default_rng(4)
    imgs = [(rng.random((60, 80)) * 255).astype(np.uint8),
            np.where(rng.random((60, 80)) > 0.85, 255, 0).astype(np.uint8),
            np.full((60, 80), 255, np.uint8), np.zeros((60, 80), np.uint8),
            cv2.resize(blobs(CENTRES), (60, 40), interpolation=cv2.INTER_LINEAR)]
    differ = 0
    for img in imgs:
        for win, k, mc, rel in [(11, 0.8, 10.0, 0.2), (3, 0.8, 10.0, 0.2),
                                (21, 1.3, 0.0, 0.0), (7, 0.5, 5.0, 0.35)]:
            want, (mean, sq) = _array_levels(img, win, k, mc, rel)
            got = niblack_levels(mean, sq, np.float32(k), np.float32(mc), np.float32(rel),
                                 np.float32(254.0))
            differ += int(np.count_nonzero(got != want))
    assert differ == 0


def test_axis_ratios():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[2.0, 0.0], [0.0, 2.0]]])
    np.testing.assert_allclose(axis_ratios(cov), [0.5, 1.0])


def test_lone_region_shortcut_matches_contour_path():
    """A region no other region reaches is measured without drawing its contour; the
    numbers are those of the general path."""
    from ceilkit.runtime.features.spots import _alone, _region_stats

    img = blobs(np.array([[40.3, 30.7], [120.6, 80.2], [131.0, 84.0]]), radius=4.0)
    mask = niblack_mask(img, 41, 0.8, 10.0, 0.2)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = np.array([cv2.boundingRect(c) for c in contours])
    alone = _alone(boxes)
    assert alone.sum() == 1 and (~alone).sum() == 2   # the two close discs reach each other
    for c, b, lone in zip(contours, boxes, alone, strict=True):
        full = _region_stats(img, mask, c, *b, True)
        if lone:
            fast = _region_stats(img, mask, None, *b, True)
            np.testing.assert_allclose(fast[:4], full[:4], rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(fast[4], full[4], rtol=1e-9, atol=1e-12)
            assert fast[5] == full[5]


def test_lone_regions_measured_together_match_one_by_one():
    """The batched statistics of lone regions (:func:`_lone_region_stats`) are those of
    :func:`_region_stats`, weighted and binary, including windows cut by the image's
    edges and a region with no positive weight (flagged for the caller)."""
    from ceilkit.runtime.features.spots import _alone, _lone_region_stats, _region_stats

    centres = np.array([[40.3, 30.7], [120.6, 80.2], [200.1, 130.9], [60.8, 120.4],
                        [2.2, 70.5], [236.9, 5.1], [150.4, 157.6]])
    img = blobs(centres, radius=4.0)
    mask = niblack_mask(img, 41, 0.8, 10.0, 0.2)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = np.array([cv2.boundingRect(c) for c in contours])
    boxes = boxes[_alone(boxes)]
    assert boxes.shape[0] >= 6
    for weighted in (True, False):
        stats, ok = _lone_region_stats(img, mask, boxes, weighted)
        assert ok.all()
        for row, b in zip(stats, boxes, strict=True):
            u, v, i_o, i_b, cov, area = _region_stats(img, mask, None, *b, weighted)
            assert (row[0], row[1], row[2], row[3], row[7]) == (u, v, i_o, i_b, area)
            np.testing.assert_allclose(row[4:7], [cov[0, 0], cov[0, 1], cov[1, 1]],
                                       rtol=1e-9, atol=1e-12)
    # a flat region (every weight 0 in its window) is left to the caller
    flat = np.full((40, 40), 90, np.uint8)
    m = np.zeros_like(flat)
    m[18:22, 18:22] = 255
    _, ok = _lone_region_stats(flat, m, np.array([[18, 18, 4, 4]]))
    assert not ok[0]


def test_detect_spots_batched_equals_one_by_one():
    """detect_spots with the batched lone-region path gives the spots of measuring
    every region with _region_stats (forced by a batch limit of 0)."""
    import ceilkit.runtime.features.spots as S

    img = blobs(CENTRES)
    a = detect_spots(img, centre_px=(120.0, 80.0), max_regions=3)
    old = S._BATCH_MAX_SIDE
    try:
        S._BATCH_MAX_SIDE = 0
        b = detect_spots(img, centre_px=(120.0, 80.0), max_regions=3)
    finally:
        S._BATCH_MAX_SIDE = old
    assert len(a) == len(b) == 3 and a.rejected == b.rejected
    np.testing.assert_array_equal(a.centroids_px, b.centroids_px)
    np.testing.assert_array_equal(a.areas_px, b.areas_px)
    np.testing.assert_allclose(a.cov_px, b.cov_px, rtol=1e-9, atol=1e-12)


def test_vignetted_plateau_centroid_is_the_disc_centre(monkeypatch):
    """Vignetting tilts a light's plateau; the weighted centroid is taken on the window
    divided by the plateau's own linear gain, so the gain does not move it (without
    the flattening it moves ~0.1 px towards the bright side)."""
    from ceilkit.runtime.features import spots as spots_mod

    truth = np.array([[60.3, 50.6], [150.7, 110.2], [190.4, 45.9]])
    img = blobs(truth, radius=12.0, noise=0.0).astype(np.float64)
    h, w = img.shape
    gain = 1.0 - 1e-3 * (np.arange(w)[None, :] - 120.0) - 6e-4 * (np.arange(h)[:, None] - 80.0)
    noise = np.random.default_rng(3).normal(0, 0.5, img.shape)

    def shift() -> np.ndarray:
        """How far the gain moves each centroid (px)."""
        c = [detect_spots(np.clip(np.rint(img * g + noise), 0, 255).astype(np.uint8)
                          ).centroids_px for g in (gain, 1.0)]
        assert c[0].shape == c[1].shape == (3, 2)
        return np.linalg.norm(c[0] - c[1], axis=1)

    assert shift().max() < 0.01
    # flattening off
    monkeypatch.setattr(spots_mod, "FLAT", spots_mod.FLAT._replace(min_area_px=10 ** 9))
    assert shift().min() > 0.05


def test_peaked_spot_is_not_flattened():
    """A peaked light (a Gaussian): its slope is its shape, not a gain; the plane leaves
    it rough, so the window is used as it is."""
    from ceilkit.runtime.features.spots import flattened

    yy, xx = np.mgrid[:41, :41].astype(float)
    win = np.clip(60 + 170 * np.exp(-((xx - 20.4) ** 2 + (yy - 19.7) ** 2) / (2 * 6.0 ** 2)),
                  0, 255).astype(np.uint8)
    obj = (win > 145).astype(np.uint8)
    assert flattened(win, obj, 170.0) is None
    disc = (xx - 20.4) ** 2 + (yy - 19.7) ** 2 < 15.0 ** 2
    flat = np.where(disc, 230, 60).astype(np.uint8)                 # a flat plateau
    assert flattened(flat, disc, 170.0) is None                     # nothing to take out
    tilted = np.rint(flat * (1.0 + 2e-3 * (xx - 20.0))).astype(np.uint8)
    out = flattened(tilted, disc, 170.0)
    core = out[disc & ((xx - 20.4) ** 2 + (yy - 19.7) ** 2 < 11.0 ** 2)]
    assert np.ptp(core) < 1.5 < np.ptp(tilted[disc])                # its tilt taken out


def test_window_stats_flatten_the_plateau_too(monkeypatch):
    """The tracked path's windows (features/windows.window_stats) read a vignetted
    light as the detector does: the gain does not move the centroid."""
    from ceilkit.runtime.features import windows as windows_mod

    truth = np.array([[60.3, 50.6], [150.7, 110.2], [190.4, 45.9]])
    img = blobs(truth, radius=12.0, noise=0.0).astype(np.float64)
    h, w = img.shape
    gain = 1.0 - 1e-3 * (np.arange(w)[None, :] - 120.0) - 6e-4 * (np.arange(h)[:, None] - 80.0)
    side = 41
    corner = np.rint(truth).astype(np.int64) - side // 2

    def shift() -> np.ndarray:
        c = []
        for g in (gain, 1.0):
            rows, ok, _ = windows_mod.window_stats(
                np.clip(np.rint(img * g), 0, 255).astype(np.uint8), corner, side)
            assert ok.all()
            c.append(rows[:, :2])
        return np.linalg.norm(c[0] - c[1], axis=1)

    assert shift().max() < 0.01
    # flattening off
    monkeypatch.setattr(windows_mod, "FLAT", windows_mod.FLAT._replace(min_area_px=10 ** 9))
    assert shift().min() > 0.05
