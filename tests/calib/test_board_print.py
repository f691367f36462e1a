"""`ceilcal board`: a vector PDF whose squares measure the stated size at 100 % scale
(measured in the file), which the detector finds once drawn, in bounded memory; a board
that does not fit its paper, or a square side in the wrong unit, is one error line."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib import board_pdf
from ceilkit.calib.boards import parse_board
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.errors import ConfigError

RE_RECT = re.compile(rb"(-?[\d.]+) (-?[\d.]+) (-?[\d.]+) (-?[\d.]+) re")


def parse_pdf(data: bytes) -> tuple[tuple[float, float], np.ndarray]:
    """The page size (pt) and the filled rectangles ``(N, 4)`` ``x y w h`` (pt, y up)
    of a PDF ``ceilcal board`` wrote, read from the file itself: the cross-reference
    table points at every object, the content stream's length is its /Length."""
    assert data.startswith(b"%PDF-1.") and data.rstrip().endswith(b"%%EOF")
    xref_at = int(data.rsplit(b"startxref", 1)[1].split()[0])
    assert data[xref_at:xref_at + 4] == b"xref"
    rows = data[xref_at:].split(b"\n")
    n = int(rows[1].split()[1])
    for k in range(1, n):           # each offset lands on "k 0 obj"
        off = int(rows[2 + k].split()[0])
        assert data[off:].startswith(b"%d 0 obj" % k)
    box = re.search(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", data)
    length = int(re.search(rb"/Length (\d+)", data).group(1))
    start = data.index(b"stream\n") + len(b"stream\n")
    stream = data[start:start + length]
    assert data[start + length:start + length + 10] == b"\nendstream"
    rects = np.array([[float(v) for v in m.groups()] for m in RE_RECT.finditer(stream)])
    return (float(box.group(1)), float(box.group(2))), rects


def rasterize(page_pt: tuple[float, float], rects: np.ndarray, px_per_pt: float
              ) -> np.ndarray:
    """The rectangles drawn black on white (a printer, for the detector)."""
    w, h = (int(round(v * px_per_pt)) for v in page_pt)
    img = np.full((h, w), 255, np.uint8)
    for x, y, rw, rh in rects * px_per_pt:
        top = h - (y + rh)
        img[int(round(top)):int(round(top + rh)), int(round(x)):int(round(x + rw))] = 0
    return img


CASES = [(spec, square, paper) for spec in ("chess:9x6", "charuco:5x7:4X4_50")
         for square in (0.025, 0.25) for paper in ("a4", "a3")]


@pytest.mark.parametrize("spec,square,paper", CASES)
def test_board_prints_at_true_scale_or_is_refused_in_one_line(tmp_path, spec, square, paper):
    out = tmp_path / "board.pdf"
    res = CliRunner().invoke(app, ["board", "--board", spec, "--square", str(square),
                                   "--paper", paper, "--out", str(out)])
    if square == 0.25:             # 2.5 m or 1.75 m of board: no paper holds it
        assert res.exit_code == 1 and not out.exists()
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("ceilcal: error: --square: ")
        assert "does not fit " + paper in lines[0] and "largest square that fits" in lines[0]
        return
    assert res.exit_code == 0, res.output
    (w, h), rects = parse_pdf(out.read_bytes())
    mm = sorted(board_pdf.PAPERS[paper])
    assert sorted((w / 72 * 25.4, h / 72 * 25.4)) == pytest.approx(mm, abs=1e-3)
    s_pt = square / 0.0254 * 72                        # 70.866 pt for 25 mm
    squares = rects[np.isclose(rects[:, 2], s_pt, atol=1e-3)]
    assert np.allclose(squares[:, 3], s_pt, atol=1e-3)   # every square 25.000 mm
    expected = 35 if spec.startswith("chess") else 35 - 17    # chess 10x7/2, 5x7 - markers
    assert len(squares) == expected
    edge = board_pdf.PRINTER_EDGE_MM / 25.4 * 72
    assert rects[:, 0].min() >= edge and (rects[:, 0] + rects[:, 2]).max() <= w - edge
    assert rects[:, 1].min() >= edge and (rects[:, 1] + rects[:, 3]).max() <= h - edge


@pytest.mark.parametrize("spec,marker", [("chess:7x5", None), ("charuco:5x7:4X4_50", 0.012),
                                         ("charuco:6x4:5X5_100:legacy", None)])
def test_the_printed_board_is_the_board_the_detector_knows(spec, marker):
    board = parse_board(spec, 0.02, marker)
    page, rects = parse_pdf(board_pdf.board_pdf(board, "a4"))
    px_per_pt = 2.0                                     # 144 dpi
    det = board.detect(rasterize(page, rects, px_per_pt))
    assert det is not None and len(det) == len(board.corners_board)
    # corners one square apart on paper, ids in the board's own order
    obj = det.points_board[:, :2]
    d_px = np.linalg.norm(np.diff(det.points_px[np.argsort(det.ids)], axis=0), axis=1)
    d_m = np.linalg.norm(np.diff(obj[np.argsort(det.ids)], axis=0), axis=1)
    one = np.isclose(d_m, 0.02)
    assert np.median(d_px[one]) == pytest.approx(0.02 / 0.0254 * 72 * px_per_pt, abs=0.5)
    np.testing.assert_allclose(board.corners_board[det.ids], det.points_board, atol=1e-9)


def test_memory_does_not_grow_with_the_square(tmp_path):
    """Peak RSS of a process that writes boards of 25 mm squares on A4 and A3 and of
    200 mm squares on A0, and refuses 250 mm squares on A4 and A3 and 25 m ones. The
    child reads its own high-water mark (VmHWM): ``getrusage``'s ``ru_maxrss`` of an
    exec'd child starts at the forking parent's (pytest's) on Linux."""
    script = f"""
import resource
from pathlib import Path
from ceilkit.calib.board_pdf import write_board_pdf
from ceilkit.calib.boards import parse_board
from ceilkit.runtime.errors import ConfigError
out = Path({str(tmp_path)!r})
for k, (spec, s, paper) in enumerate([("chess:9x6", 0.025, "a4"), ("charuco:5x7", 0.025, "a3"),
                                     ("chess:2x2", 0.2, "a0"), ("chess:9x6", 0.25, "a4"),
                                     ("charuco:5x7", 0.25, "a3"), ("chess:9x6", 25.0, "a4")]):
    try:
        write_board_pdf(parse_board(spec, s), out / f"b{{k}}.pdf", paper)
    except ConfigError:
        pass
status = Path("/proc/self/status")
hwm = [ln for ln in status.read_text().splitlines() if ln.startswith("VmHWM:")] \
    if status.exists() else []
print(hwm[0].split()[1] if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True)
    peak_mb = int(res.stdout.split()[-1]) / 1024
    assert peak_mb < 200, f"peak RSS {peak_mb:.0f} MB"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b0.pdf", "b1.pdf", "b2.pdf"]


@pytest.mark.parametrize("square", ["inf", "nan", "0", "-0.025", "25", "1e-5"])
def test_an_implausible_square_is_one_line_naming_the_flag(tmp_path, square):
    res = CliRunner().invoke(app, ["board", "--board", "chess:9x6", "--square", square,
                                   "--out", str(tmp_path / "b.pdf")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1, res.output
    assert lines[0].startswith("ceilcal: error: --square: ") and "metres" in lines[0]
    if square == "25":
        assert "--square 0.025" in lines[0]
    assert not (tmp_path / "b.pdf").exists()


def test_an_existing_board_is_kept_without_force(tmp_path):
    out = tmp_path / "board.pdf"
    out.write_bytes(b"mine")
    args = ["board", "--board", "chess:7x5", "--square", "0.02", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1 and str(out) in lines[0]
    assert "--force" in lines[0] and out.read_bytes() == b"mine"
    res = CliRunner().invoke(app, args + ["--force"])
    assert res.exit_code == 0, res.output
    assert out.read_bytes().startswith(b"%PDF")


@pytest.mark.parametrize("flag,value,words", [("--out", "board.png", ".pdf"),
                                              ("--paper", "b7", "a4")])
def test_bad_out_and_paper_name_their_flag(tmp_path, flag, value, words):
    args = {"--out": str(tmp_path / "board.pdf"), "--paper": "a4"}
    args[flag] = str(tmp_path / value) if flag == "--out" else value
    res = CliRunner().invoke(app, ["board", "--board", "chess:7x5", "--square", "0.02",
                                   *[a for kv in args.items() for a in kv]])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1
    assert lines[0].startswith(f"ceilcal: error: {flag}: ") and words in lines[0]


def test_layout_turns_the_page_and_finds_the_largest_square():
    page = board_pdf.layout(parse_board("chess:9x6", 0.025), "a4")   # 250 x 175 mm
    assert page.landscape and (page.width_mm, page.height_mm) == (297.0, 210.0)
    x0, y0, x1, y1 = page.squares_mm
    assert (x1 - x0, y1 - y0) == pytest.approx((250.0, 175.0))
    assert x0 == pytest.approx(297 - x1)                                # centred across
    with pytest.raises(ConfigError, match=r"largest square that fits is 25\.1 mm"):
        board_pdf.layout(parse_board("chess:9x6", 0.03), "a4")
    board_pdf.layout(parse_board("chess:9x6", 0.0251), "a4")          # and it does
