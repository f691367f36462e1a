"""Tests of the window path's chord measurement (runtime/features/lines.py
``refine_chords(..., local_share)``, as runtime/estimators/corridor/track.py uses it) on
an interrupted edge: a lamp row's long edge, lamps and gaps along it (issue 38)."""

from __future__ import annotations

import cv2
import numpy as np

from ceilkit.runtime.estimators.corridor.track import LOCAL_SHARE, N_ALONG
from ceilkit.runtime.features.lines import refine_chords
from ceilkit.runtime.geometry.camera import CameraModel

EDGE_X = 100.3
"""The lamps' left edge (px, image column): a vertical step, bright on the right."""


def lamp_row(seed: int) -> np.ndarray:
    """200 x 200 frame: lamps 30 px long with 30 px gaps along a vertical edge at
    :data:`EDGE_X`, blurred 0.8 px, noise 2 grey levels."""
    yy, xx = np.mgrid[0:200, 0:200].astype(float)
    cover = np.clip(xx + 0.5 - EDGE_X, 0.0, 1.0)      # a pixel's share right of the edge
    on = (xx < 160.0) & (((yy - 20.0) % 60.0) < 30.0)
    sup = cv2.GaussianBlur(60.0 + 140.0 * cover * on, (0, 0), 0.8)
    sup += np.random.default_rng(seed).normal(0.0, 2.0, sup.shape)
    return np.clip(np.rint(sup), 0, 255).astype(np.uint8)


def chord_x(cam: CameraModel, segs_n: np.ndarray) -> np.ndarray:
    """Each fitted chord's column at its middle (px)."""
    return cam.fx * 0.5 * (segs_n[:, 0] + segs_n[:, 2]) + cam.cx


def test_a_chord_over_lamp_ends_is_located_on_the_lamps_alone():
    """Chords 48 px long over lamp ends and gaps (half of each on a lamp): every place
    located read the gap's noise as an edge anywhere across the profile (on the
    held-out corridors, chords 0.44 px rms off their line against 0.07 with the local
    kind). With the places whose own profile is no step, and their neighbours at a
    lamp's end, left out, each chord is on the edge to a few hundredths of a pixel."""
    cam = CameraModel.pinhole(200, 200, 300.0)
    chords = np.array([[EDGE_X, y0, EDGE_X, y0 + 48.0]
                       for y0 in (5.0, 21.0, 37.0, 53.0, 69.0, 85.0, 101.0, 117.0)])
    old, new = [], []
    for seed in range(6):
        grey = lamp_row(seed)
        sn0, pol0, rms0 = refine_chords(cam, grey, chords, 5.0, N_ALONG)
        sn1, pol1, rms1 = refine_chords(cam, grey, chords, 5.0, N_ALONG,
                                        local_share=LOCAL_SHARE)
        assert (pol1 == -1.0).all() and np.isfinite(rms1).all()   # bright to the right
        old.append(chord_x(cam, sn0[np.isfinite(rms0)]) - EDGE_X)
        new.append(chord_x(cam, sn1) - EDGE_X)
    old, new = np.concatenate(old), np.concatenate(new)
    assert np.abs(new).max() < 0.1
    assert np.sqrt(np.mean(old ** 2)) > 3.0 * np.sqrt(np.mean(new ** 2))


def test_local_share_zero_is_the_former_measurement():
    """``local_share`` 0 (the default, block/heading's) measures every place, as
    before: an unbroken edge gives the same line with and without the local kind."""
    cam = CameraModel.pinhole(200, 200, 300.0)
    grey = np.full((200, 200), 60, np.uint8)
    grey[:, 101:] = 200
    grey = cv2.GaussianBlur(grey, (0, 0), 0.8)
    chords = np.array([[100.5, 40.0, 100.5, 88.0], [100.5, 100.0, 100.5, 148.0]])
    a = refine_chords(cam, grey, chords, 5.0, N_ALONG)
    b = refine_chords(cam, grey, chords, 5.0, N_ALONG, local_share=LOCAL_SHARE)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_allclose(chord_x(cam, a[0]), chord_x(cam, b[0]), atol=1e-9)
