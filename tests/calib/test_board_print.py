"""`ceilcal board`: a printable board whose squares are the stated size at the dpi and
which the detector finds."""

import numpy as np
import pytest
from PIL import Image

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board, printable_board
from ceilkit.runtime.errors import ConfigError


def test_chessboard_png_is_found_with_the_stated_square_pitch(tmp_path):
    b = parse_board("chess:7x5", 0.02)
    out = workflow.board(b, tmp_path / "board.png", dpi=150)
    img = np.array(Image.open(out))
    assert Image.open(out).info["dpi"] == pytest.approx((150, 150), abs=0.1)
    det = b.detect(img)
    assert det is not None
    pts = det.points_px.reshape(5, 7, 2)
    pitch = np.median(np.linalg.norm(np.diff(pts, axis=1), axis=2))
    assert pitch == pytest.approx(0.02 * 150 / 0.0254, abs=0.3)   # 118.1 px


def test_charuco_pdf_and_bad_values(tmp_path):
    b = parse_board("charuco:5x7:4X4_50", 0.03)
    img = printable_board(b, 100, "label")
    assert b.detect(img[: int(round((7 * 0.03 + 0.03) * 100 / 0.0254)) + 1]) is not None
    out = workflow.board(b, tmp_path / "b.pdf", dpi=100)
    assert out.read_bytes()[:4] == b"%PDF"
    with pytest.raises(ConfigError, match="png or .pdf"):
        workflow.board(b, tmp_path / "b.jpg")
    with pytest.raises(ConfigError, match="dpi"):
        printable_board(b, 10)
