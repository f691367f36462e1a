"""Boards: parsing, detection on rendered images against the exact corner pixels."""

from __future__ import annotations

import numpy as np
import pytest

from ceilkit.calib import boards
from ceilkit.calib.boards import (
    CharucoBoard,
    ChessBoard,
    Detection,
    decimate,
    look_at_pose,
    parse_board,
    refine_corners,
    render_board,
    undecimate,
    working_factor,
)
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel

CAM = CameraModel.pinhole(640, 480, fx=500.0, dist=[-0.2, 0.05, 0.001, -0.0005, 0.0])


def test_parse_board_specs():
    b = parse_board("chess:9x6", 0.025)
    assert isinstance(b, ChessBoard) and (b.cols, b.rows) == (9, 6)
    assert b.corners_board.shape == (54, 3)
    np.testing.assert_allclose(b.corners_board[10], [0.025, 0.025, 0.0])
    c = parse_board("charuco:5x7:5X5_100:legacy", 0.04, 0.03)
    assert isinstance(c, CharucoBoard) and c.legacy and c.dictionary == "5X5_100"
    assert c.corners_board.shape == (24, 3)
    assert c.cv_board.getLegacyPattern()


@pytest.mark.parametrize("spec,square,marker,key", [
    ("chess:9", 0.025, None, "board"), ("chess:1x6", 0.025, None, "board"),
    ("chess:9x6", -1.0, None, "square"), ("charuco:5x7:NOPE", 0.04, 0.03, "board"),
    ("charuco:5x7", 0.04, 0.05, "marker"), ("charuco:30x30:4X4_50", 0.04, 0.03, "board"),
    ("chess:9x6", float("inf"), None, "square"), ("chess:9x6", float("nan"), None, "square"),
    ("charuco:5x7", float("inf"), 0.03, "square"),
    ("chess:9x6", 0.025, float("nan"), "marker"), ("chess:9x6", 0.025, 0.02, "marker"),
])
def test_parse_board_errors(spec, square, marker, key):
    with pytest.raises(ConfigError) as e:
        parse_board(spec, square, marker)
    assert e.value.key == key


def test_chessboard_alternatives_include_swapped_and_neighbours():
    specs = [a.spec for a in ChessBoard(9, 6, 0.03).alternatives()]
    assert "chess:6x9" in specs and "chess:8x6" in specs and "chess:9x7" in specs
    assert "chess:9x6" not in specs


@pytest.mark.parametrize("board", [ChessBoard(9, 6, 0.03),
                                   CharucoBoard(7, 5, 0.04, 0.03, "4X4_50")])
def test_render_then_detect_matches_exact_corners(board):
    rvec, t = look_at_pose(board, 0.5, 25.0, 30.0, 10.0, (0.03, -0.02))
    img, px, vis = render_board(board, CAM, rvec, t, np.random.default_rng(3))
    assert img.shape == (480, 640) and img.dtype == np.uint8
    assert vis.all()
    det = board.detect(img, "a")
    assert det is not None and len(det) >= 20
    truth = px[det.ids]
    err = det.points_px - truth
    if isinstance(board, ChessBoard) and np.abs(err).max() > 5:   # 180 deg ambiguity
        err = det.points_px - px[::-1][det.ids]
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.3
    np.testing.assert_allclose(det.points_board, board.corners_board[det.ids])



def test_each_corner_gets_a_window_that_fits_its_squares():
    """A board tilted 60 deg has 15 px squares on its far side: OpenCV's fixed 11 px
    half-window there reaches the far sides of the neighbouring squares and moves the
    corners by pixels; the per-corner window (0.35 of the corner's shortest spacing)
    keeps every corner within a third of a pixel of the truth."""
    errs = {}
    for half in (None, 11):
        board = ChessBoard(9, 6, 0.03, subpix_half=half)
        rvec, t = look_at_pose(board, 0.9, 60.0, 0.0, 5.0)
        img, px, _ = render_board(board, CAM, rvec, t, np.random.default_rng(3),
                                  noise_sigma=1.0, blur_sigma_px=0.6)
        det = board.detect(img)
        assert det is not None
        err = det.points_px - px[det.ids]
        if np.abs(err).max() > 20:                              # 180 deg ambiguity
            err = det.points_px - px[::-1][det.ids]
        errs[half] = np.linalg.norm(err, axis=1)
        spacing = np.linalg.norm(np.diff(px.reshape(6, 9, 2), axis=1), axis=2).min()
        assert spacing < 2.5 * 11                     # the fixed window is too wide here
    assert errs[None].max() < 0.35, errs[None].max()
    assert errs[11].max() > 3.0, errs[11].max()
    with pytest.raises(ConfigError, match="half-window"):
        ChessBoard(9, 6, 0.03, subpix_half=1)

def test_detect_returns_none_without_board():
    blank = np.full((120, 160), 128, np.uint8)
    assert ChessBoard(9, 6, 0.03).detect(blank) is None
    assert CharucoBoard(5, 7, 0.04, 0.03).detect(blank) is None


def test_detection_checks_lengths_and_subsets():
    d = Detection("x", (640, 480), [0, 1, 2], np.zeros((3, 2)), np.zeros((3, 3)))
    s = d.subset(np.array([True, False, True]))
    assert len(s) == 2 and list(s.ids) == [0, 2]
    with pytest.raises(ValueError):
        Detection("x", (640, 480), [0, 1], np.zeros((3, 2)), np.zeros((3, 3)))


def test_grid_extends_finds_corners_beyond_a_sub_grid():
    """A 7x4 grid found inside a 9x6 board has X-junctions beyond it; the whole board none."""
    board = ChessBoard(9, 6, 0.03)
    rvec, t = look_at_pose(board, 0.5, 10.0, 30.0, 5.0, (0.0, 0.0))
    img, px, _ = render_board(board, CAM, rvec, t, np.random.default_rng(4))
    whole = board.detect(img, "a")
    assert whole is not None and board.grid_extends(img, whole) == (0, 0, 0, 0)
    # the 7x4 sub-grid: inner corners 1..7 of rows 1..4 of the true grid
    sub = ChessBoard(7, 4, 0.03)
    grid = px.reshape(6, 9, 2)[1:5, 1:8].reshape(-1, 2)
    det = Detection("a", (640, 480), np.arange(28), grid, sub.corners_board)
    left, right, top, bottom = sub.grid_extends(img, det)
    assert (left, right, top, bottom) == (1, 1, 1, 1)


# -- the working resolution (issue 16: large frames) ----------------------------------------

BIG = CameraModel.pinhole(2304, 1728, fx=1900.0, dist=[-0.12, 0.04, 0.0, 0.0, 0.0])


def test_working_factor_decimate_and_undecimate_agree():
    assert working_factor((3000, 4000)) == 3 and working_factor((1000, 1000)) == 1
    assert working_factor((1728, 2304)) == 2 and working_factor((3000, 4000), 0.0) == 1
    grey = np.zeros((30, 31), np.uint8)
    grey[12:15, 18:21] = 255                   # a 3x3 block centred on pixel (19, 13)
    small = decimate(grey, 3)
    assert small.shape == (10, 10)
    v, u = np.unravel_index(np.argmax(small), small.shape)
    np.testing.assert_allclose(undecimate(np.array([u, v]), 3), [19.0, 13.0])


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_working_size_is_validated(bad):
    for make in (lambda: ChessBoard(9, 6, 0.03, working_mpx=bad),
                 lambda: CharucoBoard(7, 5, 0.04, 0.03, working_mpx=bad)):
        with pytest.raises(ConfigError) as e:
            make()
        assert e.value.key == "working_mpx"


def _rms(det, px):
    e = np.linalg.norm(det.points_px - px[det.ids], axis=1)
    flipped = np.linalg.norm(det.points_px[::-1] - px[det.ids], axis=1)   # a 180 deg order
    e = min(e, flipped, key=lambda a: float(a.max()))
    return float(np.sqrt(np.mean(e ** 2)))


def test_decimated_chessboard_finds_the_full_resolution_corners():
    board = ChessBoard(9, 6, 0.03)
    rvec, t = look_at_pose(board, 0.45, 30.0, 60.0, 15.0, (0.02, -0.01))
    img, px, vis = render_board(board, BIG, rvec, t, np.random.default_rng(7),
                                blur_sigma_px=1.2, supersample=1)
    assert vis.all()
    det = board.detect(img)                                  # found at 1152x864
    full = ChessBoard(9, 6, 0.03, working_mpx=0.0).detect(img)
    assert det is not None and full is not None and len(det) == len(full) == 54
    # the same corners: the full-resolution grid refined with the same windows
    same = refine_corners(img, full.points_px.reshape(-1, 1, 2).astype(np.float32), 9, 6,
                          max_half=22).reshape(-1, 2)
    assert np.abs(det.points_px - same).max() < 0.1
    assert _rms(det, px) <= _rms(full, px) + 0.02


def test_decimated_charuco_is_as_accurate_as_full_resolution():
    board = CharucoBoard(7, 5, 0.04, 0.03)
    rvec, t = look_at_pose(board, 0.55, 25.0, 200.0, -10.0, (0.01, 0.02))
    img, px, vis = render_board(board, BIG, rvec, t, np.random.default_rng(8),
                                blur_sigma_px=1.2, supersample=1)
    det = board.detect(img)
    full = CharucoBoard(7, 5, 0.04, 0.03, working_mpx=0.0).detect(img)
    assert det is not None and full is not None and len(det) == len(full) == 24
    assert np.array_equal(np.sort(det.ids), np.sort(full.ids))
    assert _rms(det, px) <= _rms(full, px) + 0.02
    assert _rms(det, px) < 0.15


@pytest.mark.parametrize("rows", [35, 36, 37])
def test_a_render_in_strips_has_no_seam(monkeypatch, rows):
    """A render too big to trace at once is traced in strips of rows; the strips share
    the lens table's node grid, so the image is the one traced whole (an odd strip moved
    its sub-pixel samples: up to 73 grey levels at the strips' rows, 320x240 at s = 3)."""
    cam = CameraModel.pinhole(320, 240, 250.0, dist=[-0.2, 0.05, 0.001, -0.002, 0.0])
    board = parse_board("chess:9x6", 0.025)
    rvec, t = look_at_pose(board, 0.4, 20, 30, 10)
    whole, _, _ = render_board(board, cam, rvec, t, noise_sigma=0, blur_sigma_px=0)
    monkeypatch.setattr(boards, "_RENDER_SUBPIXELS", 320 * 9 * rows)
    strips, _, _ = render_board(board, cam, rvec, t, noise_sigma=0, blur_sigma_px=0)
    assert np.array_equal(strips, whole)
