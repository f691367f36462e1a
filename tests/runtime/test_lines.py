"""Tests of runtime/lines.py."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.camera import CameraModel
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.lines import (
    SegmentDetector,
    as_gray,
    detect_segments,
    fit_line,
    merge_segments,
    refine_segments,
    segment_lengths,
    segment_lines,
    undistort_segments,
)


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


@pytest.mark.parametrize("method", ["fld", "lsd", "hough"])
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
    assert as_gray(bgr).shape == (4, 5)
