"""Tests of runtime/features/lines.py."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.lines import (
    SegmentDetector,
    detect_segments,
    edge_polarity,
    fit_line,
    merge_segments,
    refine_segments,
    refine_undistorted,
    segment_lengths,
    segment_lines,
    shift_segments,
    undistort_segments,
)
from ceilkit.runtime.geometry.camera import CameraModel


def edge_image(angle_deg: float, offset_px: float, noise: float, seed: int) -> np.ndarray:
    """160x120 step edge (dark left, bright right) through (80 + offset, 60), anti-aliased."""
    s = 8
    v, u = np.mgrid[0:120 * s, 0:160 * s]
    u = (u + 0.5) / s - 0.5
    v = (v + 0.5) / s - 0.5
    a = math.radians(angle_deg)
    d = (u - 80 - offset_px) * math.cos(a) + (v - 60) * math.sin(a)
    img = np.where(d > 0, 200.0, 60.0)
    img = cv2.resize(img, (160, 120), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("method", ["fld", "lsd", "hough", "ed"])
def test_detectors_find_the_edge(method):
    img = edge_image(10.0, 0.3, 2.0, 0)
    segs = detect_segments(img, method, 30)
    assert segs.shape[1] == 4 and segs.shape[0] >= 1
    a = math.radians(10.0)
    longest = segs[np.argmax(segment_lengths(segs))]
    for p in (longest[:2], longest[2:]):
        d = (p[0] - 80.3) * math.cos(a) + (p[1] - 60) * math.sin(a)
        assert abs(d) < 1.5


def test_refine_reaches_sub_pixel():
    a = math.radians(7.0)
    errs = []
    for seed, off in enumerate((0.0, 0.25, 0.5, -0.3)):
        img = edge_image(7.0, off, 2.0, seed)
        segs, rms = refine_segments(img, detect_segments(img, "fld", 30))
        p = segs[np.argmax(segment_lengths(segs))]
        for q in (p[:2], p[2:]):
            errs.append(abs((q[0] - 80 - off) * math.cos(a) + (q[1] - 60) * math.sin(a)))
        assert np.nanmax(rms) < 1.0
    assert max(errs) < 0.15


def test_fit_line_and_segment_lines():
    pts = np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 5.0]])
    ln = fit_line(pts)
    assert np.allclose(pts @ ln[:2] + ln[2], 0) and math.hypot(ln[0], ln[1]) == pytest.approx(1)
    segs = np.array([[0.0, 1.0, 2.0, 5.0], [1.0, 1.0, 1.0, 4.0]])
    lines = segment_lines(segs)
    assert np.allclose(np.hypot(lines[:, 0], lines[:, 1]), 1)
    for s, ln in zip(segs, lines, strict=True):
        assert abs(ln @ [s[0], s[1], 1]) < 1e-12 and abs(ln @ [s[2], s[3], 1]) < 1e-12


def test_undistort_segments_round_trip():
    cam = CameraModel.pinhole(640, 480, 400.0, dist=[-0.08, 0.02, 0, 0, 0])
    xy = np.array([[0.1, -0.2], [0.4, 0.3], [-0.5, 0.1], [0.0, 0.0]])
    segs_px = cam.distort(xy).reshape(-1, 4)
    assert np.allclose(undistort_segments(cam, segs_px), xy.reshape(-1, 4), atol=1e-9)


def test_merge_segments_groups_collinear_pieces():
    segs = np.array([[0, 0, 50, 1], [60, 1.2, 100, 2], [0, 30, 100, 30], [0.0, 0, 0, 40]])
    groups = merge_segments(segs, math.radians(2.0), 3.0)
    sets = sorted(sorted(g.tolist()) for g in groups)
    assert sets == [[0, 1], [2], [3]]


def test_bad_detector_and_colour_input():
    with pytest.raises(ConfigError):
        SegmentDetector("canny")
    bgr = np.zeros((4, 5, 3), np.uint8)
    assert to_grey(bgr).shape == (4, 5)


def stripe_image(offset_px: float, width_px: float, seed: int) -> np.ndarray:
    """160x120, a dark vertical stripe ``width_px`` wide centred at u = 80 + offset on
    grey 150 (anti-aliased, blur 0.8, noise 2)."""
    s = 8
    u = (np.arange(160 * s) + 0.5) / s - 0.5
    row = np.where(np.abs(u - 80 - offset_px) < width_px / 2, 95.0, 150.0)
    row = row.reshape(160, s).mean(axis=1)
    img = cv2.GaussianBlur(np.tile(row, (120, 1)), (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0, 2.0, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_edge_polarity_steps_and_thin_lines():
    segs = np.array([[80.0, 10.0, 80.0, 110.0], [80.0, 110.0, 80.0, 10.0]])
    pol, shift = edge_polarity(edge_image(0.0, 0.0, 2.0, 1), segs)
    assert pol.tolist() == [-1.0, 1.0] and np.all(np.isnan(shift))
    for off in (0.0, 0.3, -0.8):
        img = stripe_image(off, 1.5, 2)
        # a detector finds one edge of the stripe, 0.75 px off its centre
        on_edge = segs + np.array([off + 0.75, 0, off + 0.75, 0])
        pol, shift = edge_polarity(img, on_edge)
        assert pol.tolist() == [0.0, 0.0]
        centred = shift_segments(on_edge, shift)
        assert np.allclose(centred[:, 0], 80 + off, atol=0.15), centred
    flat = np.full((120, 160), 128, np.uint8)
    assert np.all(np.isnan(edge_polarity(flat, segs)[0]))


def test_refine_undistorted_straightens_a_distorted_line():
    """A straight line in the world is a curve in a distorted image: the detector's
    chord is off it in the middle; the refit in undistorted coordinates is not."""
    cam = CameraModel.pinhole(320, 240, 200.0, dist=[-0.1, 0.02, 0, 0, 0])
    x0 = 0.55                                     # the line x = x0 (normalized), near the edge
    s = 4
    vv, uu = np.mgrid[0:240 * s, 0:320 * s]
    px = np.stack([(uu.ravel() + 0.5) / s - 0.5, (vv.ravel() + 0.5) / s - 0.5], axis=1)
    xy = cam.unproject(px)
    # anti-aliased: a ramp one sub-sample wide, centred on the line
    img = 70.0 + 140.0 * np.clip(0.5 + (xy[:, 0] - x0) * 200.0 * s, 0, 1)
    img = img.reshape(240 * s, 320 * s)
    img = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + np.random.default_rng(3).normal(0, 2, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    ends = cam.distort(np.array([[x0, -0.45], [x0, 0.45]])).reshape(1, 4)
    # a detector fits a chord to the curved edge: between the curve's ends and middle
    sag = cam.distort(np.array([[x0, 0.0]]))[0, 0] - 0.5 * (ends[0, 0] + ends[0, 2])
    assert abs(sag) > 1.0
    chord = ends + np.array([[2 * sag / 3, 0.0, 2 * sag / 3, 0.0]])
    test_pts = np.array([[x0, -0.4, 1.0], [x0, 0.0, 1.0], [x0, 0.4, 1.0]])
    raw = segment_lines(undistort_segments(cam, chord))[0]
    assert np.max(np.abs(test_pts @ raw)) * 200 > 0.5
    segs_n, pol, rms = refine_undistorted(cam, img, chord)
    assert pol[0] == -1.0                  # bright on the right of a downward segment
    line = segment_lines(segs_n)[0]
    assert np.max(np.abs(test_pts @ line)) * 200 < 0.1            # px at the focal length
    assert rms[0] < 0.3
    # empty input
    e, p, r = refine_undistorted(cam, img, np.zeros((0, 4)))
    assert e.shape == (0, 4) and p.shape == (0,) and r.shape == (0,)


def test_segment_on_one_edge_of_a_blurred_seam_is_found_a_thin_line():
    """A 2 px seam 60 grey levels dark, blurred by 1.5 px: a detector's segment on one of
    its edges (2 px off the middle) sees the seam reach past one side of the +-4 px
    profile: neither a step nor a thin line there. The second look over +-6 px finds
    the thin line and its middle."""
    cam = CameraModel.pinhole(160, 120, 150.0)
    s = 8
    v, u = np.mgrid[0:120 * s, 0:160 * s]
    u = (u + 0.5) / s - 0.5
    img = np.where(np.abs(u - 80.0) <= 1.0, 130.0, 190.0)          # the seam: u = 80
    img = cv2.resize(img, (160, 120), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 1.5) + np.random.default_rng(5).normal(0, 2, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    seg = np.array([[82.0, 15.0, 82.0, 105.0]])                     # beside its right edge
    _, pol_narrow, rms_narrow = refine_undistorted(cam, img, seg, retry_half_width_px=None)
    assert np.isnan(pol_narrow[0]) and np.isnan(rms_narrow[0])
    segs_n, pol, rms = refine_undistorted(cam, img, seg)
    assert pol[0] == 0.0
    u_fit = cam.fx * segs_n[0, [0, 2]] + cam.cx                      # back to pixels
    assert np.all(np.abs(u_fit - 80.0) < 0.1) and rms[0] < 0.3


def test_detector_rows_keep_full_image_coordinates():
    img = np.zeros((120, 160), np.uint8)
    img[:, 80:] = 200
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    full = SegmentDetector("fld", 20)(img)
    part = SegmentDetector("fld", 20, rows=(40, 120))(img)
    assert part.shape[0] >= 1
    assert np.all(part[:, [1, 3]] >= 39.5) and np.allclose(part[:, [0, 2]].mean(), 79.5, atol=1)
    assert full[:, [1, 3]].min() < 10
    assert SegmentDetector("fld", 20, rows=(200, 300))(img).shape == (0, 4)
