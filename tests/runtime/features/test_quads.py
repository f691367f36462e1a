"""Quadrilateral detection and edge points on synthetic images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features import quads
from ceilkit.runtime.features.quads import (
    MarkerCodes,
    detect_quads,
    edge_points,
    marker_cells,
    marker_dictionary,
)


def square_image(corners: np.ndarray, inside: int = 40, outside: int = 150) -> np.ndarray:
    img = np.full((240, 320), outside, np.uint8)
    big = np.full((240 * 8, 320 * 8), outside, np.uint8)
    cv2.fillPoly(big, [np.rint((corners + 0.5) * 8 - 0.5).astype(np.int32)], inside)
    img[:] = cv2.GaussianBlur(cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA),
                              (0, 0), 1.0)
    return img


CORNERS = np.array([[100.0, 60.0], [210.0, 75.0], [200.0, 170.0], [95.0, 160.0]])


def test_detect_quads_finds_a_dark_quad_and_not_a_line():
    img = square_image(CORNERS)
    img[20:23, :] = 40                                   # a seam-like line
    quads = detect_quads(img, dark=True)
    assert len(quads) == 1 and not quads[0].at_border
    d = np.linalg.norm(quads[0].corners_px[:, None] - CORNERS[None], axis=2).min(axis=1)
    assert d.max() < 2.0


@pytest.mark.parametrize("x0", [100.0, 100.25, 100.5, 100.75])
def test_edge_points_find_a_blurred_step_to_a_tenth_of_a_pixel(x0):
    row = np.clip(np.arange(320) - x0 + 0.5, 0, 1) * 110 + 40      # exact pixel coverage
    img = cv2.GaussianBlur(np.tile(row, (240, 1)).astype(np.float32), (0, 0), 1.0)
    img = np.rint(img).astype(np.uint8)
    coarse = np.array([[50.0, 50.0], [x0 + 0.7, 50.0], [x0 + 0.7, 150.0], [50.0, 150.0]])
    pts, side = edge_points(img, coarse, per_side=6)
    assert np.sum(side == 1) == 6
    assert np.max(np.abs(pts[side == 1, 0] - x0)) < 0.1


def test_unknown_dictionary_is_a_one_line_error():
    with pytest.raises(ConfigError, match="markers.dictionary"):
        marker_dictionary("DICT_9X9_1")


@pytest.mark.parametrize("name", ["DICT_4X4_50", "DICT_APRILTAG_36h11", "DICT_7X7_1000"])
def test_marker_codes_read_every_turn_and_correct_up_to_max_errors(name):
    codes = MarkerCodes(name)
    rng = np.random.default_rng(1)
    n_ids = marker_dictionary(name).bytesList.shape[0]
    for marker_id in rng.choice(n_ids, 6, replace=False):
        printed = marker_cells(name, int(marker_id))[1:-1, 1:-1].astype(bool)
        for s in range(4):
            # an outline whose corner s is the printed top-left reads the code turned
            read = np.rot90(printed, -s).copy()
            assert codes.identify(read) == (marker_id, s, 0)
            flip = rng.choice(read.size, codes.max_errors, replace=False)
            read.flat[flip] ^= True
            assert codes.identify(read) == (marker_id, s, codes.max_errors)
    noise = rng.random((200, codes.bits, codes.bits)) > 0.5
    got = [codes.identify(c) for c in noise]
    assert all(g is None or g[2] <= codes.max_errors for g in got)


def test_bit_count_without_numpy_2_agrees():
    words = np.random.default_rng(2).integers(0, 2 ** 63, 1000, dtype=np.uint64)
    want = np.array([bin(int(w)).count("1") for w in words])
    assert np.array_equal(quads._BYTE_BITS[words.view(np.uint8).reshape(-1, 8)].sum(axis=1),
                          want)
    assert np.array_equal(quads._bit_count(words), want)


def test_a_signed_edge_search_takes_a_small_markers_outer_edge():
    """A marker of 3 px per cell: a black border one cell wide between its quiet ring
    and its inner cells, both within the ±3 px search of its outer edge. Where the
    inner cells' edge is the steeper (whiter cells than the ring), the unsigned search
    takes it from a start a pixel inside the outer edge; the search for a step dark
    inside (sign -1, corners clockwise as displayed) takes the outer edge."""
    img = np.full((80, 80), 150, np.uint8)
    img[17:63, 17:63] = 200                 # the quiet ring (one cell: 3 px)
    img[20:60, 20:60] = 30                  # the black border ...
    img[23:57, 23:57] = 250                 # ... one cell wide; white inner cells
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    for a, b in ((19.0, 60.0), (20.0, 59.0)):
        coarse = np.array([[a, a], [b, a], [b, b], [a, b]])
        for sign in (-1, 0):
            pts, side = edge_points(img, coarse, 12, 3.0, sign=sign)
            assert np.bincount(side, minlength=4).min() == 12
            across = np.where(side % 2 == 0, pts[:, 1], pts[:, 0])
            outer = np.minimum(abs(across - 19.5), abs(across - 59.5))
            inner = np.minimum(abs(across - 22.5), abs(across - 56.5))
            if sign:
                assert outer.max() < 1.0
            elif a == 20.0:
                assert inner.max() < 1.0


def marker_image(cell_px: float, ring_white: bool, blur: float, cells: int = 6
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A marker of ``cells`` cells across its black border, ``cell_px`` a cell, turned 7°,
    its quiet ring white on a grey ceiling, its first code ring all white
    (``ring_white``) or all black, the rest grey, rendered at 8x8 samples a pixel and
    blurred by ``blur`` px; and its outline ``(4, 2)`` px (clockwise as displayed)."""
    s, c0, a = 8, np.array([60.0, 55.0]), np.radians(7.0)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    big = np.full((120 * s, 120 * s), 120, np.uint8)
    outline = None
    for lo, level in ((-1, 230), (0, 25), (1, 230 if ring_white else 25), (2, 128)):
        hi = cells - lo
        px = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]]) * cell_px @ turn.T + c0
        cv2.fillPoly(big, [np.rint((px + 0.5) * s - 0.5).astype(np.int32)], level)
        outline = px if lo == 0 else outline
    img = cv2.resize(big, (120, 120), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(img, (0, 0), blur), outline


def side_offsets(img: np.ndarray, outline: np.ndarray, cells: int) -> np.ndarray:
    """Each side's mean edge point, px outwards of the true side (from a coarse outline
    0.7 px off), by :func:`edge_points` with ``cells``."""
    pts, side = edge_points(img, outline + np.array([0.6, -0.4]), 12, 3.0, sign=-1,
                            cells=cells)
    assert np.bincount(side, minlength=4).min() >= 6
    out = []
    for k in range(4):
        a, b = outline[k], outline[(k + 1) % 4]
        t = (b - a) / np.linalg.norm(b - a)
        out.append(float(((pts[side == k] - a) @ np.array([t[1], -t[0]])).mean()))
    return np.array(out)


@pytest.mark.parametrize("cell_px", [3.2, 3.9, 4.4])
def test_a_markers_edge_does_not_follow_the_colour_of_its_first_code_cells(cell_px):
    """At about 4 px a cell the profile's ends (±3 px) lie on the first code cells'
    blurred edge: a white ring there moved every side's step outwards (by 0.08-0.36 px
    at blur 0.8 here). Read half a cell either side (``cells``), the step moves by at
    most a quarter of that (the 1-D model of docs/methods/block.md: a fifth) and a
    side lies within 0.15 px of the truth whatever the code."""
    got = {}
    for cells in (0, 6):
        dark, white = (side_offsets(*marker_image(cell_px, w, 0.8), cells)
                       for w in (False, True))
        got[cells] = float(np.mean(white - dark))
        if cells:
            assert np.abs(np.concatenate([dark, white])).max() < 0.15
    assert got[0] > 0.07
    assert abs(got[6]) < 0.25 * got[0]
