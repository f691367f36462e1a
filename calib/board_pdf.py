"""A calibration board as a one-page vector PDF at true scale (``ceilcal board``).

The board is a list of black rectangles in board coordinates (metres, x right, y down as
printed; :mod:`~ceilkit.calib.boards`): a chessboard's black squares, or a ChArUco
board's black squares and each marker's black cells, read from its dictionary's bit
matrix. They are written as PDF path rectangles (``x y w h re f``) in points
(1 pt = 1/72 in = 0.3528 mm), so a printer set to 100 % ("actual size") puts every edge
where it belongs, whatever the square size: the file and the memory it takes do not
grow with the square (a 9x6 chessboard is 35 rectangles, about 3 kB).

Layout on the paper (:data:`PAPERS`, portrait, else landscape): the squares centred
across, with a white quiet zone of half a square all round (it may reach into the
printer's unprinted edge, :data:`PRINTER_EDGE_MM`) and a label line below it giving the
exact ``--board --square [--marker]`` arguments. A board that does not fit, or a square
side that cannot be meant (sizes are metres: ``--square 25`` is 25 m), is refused in
one line before anything is written.

Example::

    board = parse_board("chess:9x6", 0.025)
    page = layout(board, "a4")              # landscape A4, 35 squares
    write_board_pdf(board, Path("board.pdf"), "a4")
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.yaml import atomic_write_bytes
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.outputs import claimed

from .boards import Board, CharucoBoard, ChessBoard

PT_PER_M = 72.0 / 0.0254
"""PDF points per metre (1 pt = 1/72 inch)."""
PAPERS: dict[str, tuple[float, float]] = {
    "a5": (148.0, 210.0), "a4": (210.0, 297.0), "a3": (297.0, 420.0),
    "a2": (420.0, 594.0), "a1": (594.0, 841.0), "a0": (841.0, 1189.0),
    "letter": (215.9, 279.4), "legal": (215.9, 355.6), "tabloid": (279.4, 431.8),
}
"""Paper sizes, width x height in millimetres (portrait)."""
DEFAULT_PAPER = "a4"
PRINTER_EDGE_MM = 5.0
"""Most printers leave this much of each edge unprinted: no square, no label there."""
QUIET_SQUARES = 0.5
"""White kept around the squares, in squares (the detectors need a light border)."""
LABEL_MM = 4.0
"""Height of the label line below the quiet zone."""
LABEL_PT = 8.0
"""The label's font size (smaller when the line would be wider than the paper)."""
SQUARE_RANGE_M = (0.001, 1.0)
"""A square side outside this (metres) is refused as meant in another unit."""


@dataclass(frozen=True)
class Page:
    """Where a board goes on the paper.

    Attributes:
        paper: the paper's name; ``landscape``: turned.
        width_mm, height_mm: the page as printed.
        origin_mm: the page position (from its top-left corner, y down) of the board
            point ``(0, 0)``.
        squares_mm: ``(x0, y0, x1, y1)`` of the squares on the page (top-left origin).
        label_top_mm: the top of the label line.
    """

    paper: str
    landscape: bool
    width_mm: float
    height_mm: float
    origin_mm: tuple[float, float]
    squares_mm: tuple[float, float, float, float]
    label_top_mm: float


def check_square(square_m: float) -> None:
    """Refuse a square side nobody prints (``square``; the hint: sizes are metres)."""
    lo, hi = SQUARE_RANGE_M
    if not (math.isfinite(square_m) and lo <= square_m <= hi):
        hint = (f" (sizes are metres: {square_m:g} mm is --square {square_m / 1000:g})"
                if math.isfinite(square_m) and square_m > hi else " (sizes are metres)")
        raise ConfigError(None, "square", f"expected a square side of {lo:g} to {hi:g} m, "
                          f"found {square_m!r}{hint}")


def paper_size(paper: str) -> tuple[float, float]:
    """``(width, height)`` in mm of a paper name (:data:`PAPERS`), portrait."""
    size = PAPERS.get(paper.strip().lower())
    if size is None:
        raise ConfigError(None, "paper", f"expected one of {', '.join(PAPERS)}, "
                          f"found {paper!r}")
    return size


def _quiet_mm(board: Board) -> float:
    return 1000.0 * QUIET_SQUARES * board.square_m  # type: ignore[attr-defined]


def _fits(board: Board, w_mm: float, h_mm: float) -> bool:
    x0, y0, x1, y1 = (1000.0 * v for v in board.extent_m)
    q, e = _quiet_mm(board), PRINTER_EDGE_MM
    side = max(q, e)
    return (x1 - x0) + 2 * side <= w_mm + 1e-9 and \
        (y1 - y0) + side + q + LABEL_MM + e <= h_mm + 1e-9


def layout(board: Board, paper: str = DEFAULT_PAPER) -> Page:
    """Place ``board`` on ``paper`` (portrait if it fits, else landscape).

    Raises:
        ConfigError: ``square`` implausible (:func:`check_square`); ``paper`` unknown
            or too small for the board (the line gives the size needed and the largest
            square that fits).
    """
    check_square(board.square_m)  # type: ignore[attr-defined]
    name = paper.strip().lower()
    pw, ph = paper_size(name)
    turns = [(turned, w, h) for turned, (w, h) in ((False, (pw, ph)), (True, (ph, pw)))
             if _fits(board, w, h)]
    if not turns:
        raise _too_big(board, name, pw, ph)
    landscape, w, h = turns[0]
    x0, y0, x1, y1 = (1000.0 * v for v in board.extent_m)
    q, side = _quiet_mm(board), max(_quiet_mm(board), PRINTER_EDGE_MM)
    left = (w - (x1 - x0)) / 2
    block = (y1 - y0) + q + LABEL_MM
    top = max(side, (h - block) / 2)
    top = min(top, h - PRINTER_EDGE_MM - block)
    return Page(name, landscape, w, h, (left - x0, top - y0),
                (left, top, left + x1 - x0, top + y1 - y0), top + (y1 - y0) + q)


def _largest_square_mm(board: Board, pw: float, ph: float) -> float:
    """The largest square side (mm) at which ``board`` fits a ``pw x ph`` mm page."""
    x0, y0, x1, y1 = board.extent_m
    s = board.square_m  # type: ignore[attr-defined]
    nx, ny = (x1 - x0) / s, (y1 - y0) / s   # in squares
    e, lab = PRINTER_EDGE_MM, LABEL_MM
    best = 0.0
    for w, h in ((pw, ph), (ph, pw)):
        # a quiet zone of half a square wider than the printer's edge (s >= 2e) ...
        big = min(w / (nx + 2 * QUIET_SQUARES), (h - lab - e) / (ny + 2 * QUIET_SQUARES))
        # ... or narrower: the edge then sets the margins
        small = min((w - 2 * e) / nx, (h - 2 * e - lab) / (ny + QUIET_SQUARES), 2 * e)
        best = max(best, big if big >= 2 * e else small)
    return best


def _too_big(board: Board, paper: str, pw: float, ph: float) -> ConfigError:
    x0, y0, x1, y1 = (1000.0 * v for v in board.extent_m)
    s_mm = 1000.0 * board.square_m  # type: ignore[attr-defined]
    best = _largest_square_mm(board, pw, ph)
    hint = (f"; the largest square that fits is {math.floor(best * 10) / 10:g} mm "
            f"(--square {math.floor(best * 10) / 10000:g})" if best >= 1.0 else "")
    fits = [name for name, (w, h) in PAPERS.items() if _largest_square_mm(board, w, h) >= s_mm]
    other = (f"; or give a --paper it fits ({', '.join(fits)})" if fits else
             f"; it fits no --paper ({', '.join(PAPERS)}): give smaller squares")
    return ConfigError(None, "square", f"a {board.spec} board of {s_mm:g} mm squares "
                       f"({x1 - x0:g} x {y1 - y0:g} mm and its margins) does not fit "
                       f"{paper} ({pw:g} x {ph:g} mm, either way){hint}{other}")


def ink_rectangles(board: Board) -> np.ndarray:
    """``(N, 4)`` black rectangles ``(x, y, w, h)`` in board metres (y down).

    A chessboard: its black squares (:meth:`ChessBoard.texture`'s pattern). A ChArUco
    board: the squares without a marker, and each marker's black cells (its border and
    its 0 bits) from the dictionary, merged into runs along each row.
    """
    if isinstance(board, ChessBoard):
        s = board.square_m
        out = [(i * s, j * s, s, s) for j in range(-1, board.rows)
               for i in range(-1, board.cols) if (i + j) % 2 == 1]
        return np.asarray(out, float).reshape(-1, 4)
    if isinstance(board, CharucoBoard):
        return _charuco_rectangles(board)
    raise ConfigError(None, "board", f"cannot print a {type(board).__name__}")


def _charuco_rectangles(board: CharucoBoard) -> np.ndarray:
    s = board.square_m
    cv_board = board.cv_board
    dictionary = cv_board.getDictionary()
    n = int(dictionary.markerSize)
    white: set[tuple[int, int]] = set()
    out: list[tuple[float, float, float, float]] = []
    for mid, corners in zip(np.asarray(cv_board.getIds()).ravel(), cv_board.getObjPoints(),
                            strict=True):
        c = np.asarray(corners, float).reshape(4, 3)[:, :2]
        x0, y0 = c.min(axis=0)
        side = float(c[:, 0].max() - x0)
        cx, cy = c.mean(axis=0)
        white.add((int(cx // s), int(cy // s)))
        bits = cv2.aruco.generateImageMarker(dictionary, int(mid), n + 2, borderBits=1)
        cell = side / (n + 2)
        for r, row in enumerate(bits < 128):
            k = 0
            while k < n + 2:
                if not row[k]:
                    k += 1
                    continue
                k1 = k
                while k1 < n + 2 and row[k1]:
                    k1 += 1
                out.append((x0 + k * cell, y0 + r * cell, (k1 - k) * cell, cell))
                k = k1
    out += [(i * s, j * s, s, s) for j in range(board.squares_y)
            for i in range(board.squares_x) if (i, j) not in white]
    return np.asarray(out, float).reshape(-1, 4)


def board_label(board: Board) -> str:
    """The line printed below the board: its exact arguments and the check to make."""
    s = board.square_m  # type: ignore[attr-defined]
    marker = getattr(board, "marker_m", None)
    return (f"--board {board.spec} --square {s:g}"
            + (f" --marker {marker:g}" if marker is not None else "")
            + f"   square {1000 * s:g} mm: print at 100 % (actual size, no fit to page); "
              "measure a square before calibrating")


def _pdf_text(text: str) -> str:
    return text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")


def board_pdf(board: Board, paper: str = DEFAULT_PAPER, title: str = "") -> bytes:
    """The one-page PDF of ``board`` on ``paper`` (see the module doc).

    Raises:
        ConfigError: as :func:`layout`.
    """
    page = layout(board, paper)
    h_pt = page.height_mm / 1000.0 * PT_PER_M
    ox, oy = page.origin_mm
    ops = ["0 g"]
    for x, y, w, h in ink_rectangles(board):
        left = (ox / 1000.0 + x) * PT_PER_M
        top = (oy / 1000.0 + y) * PT_PER_M
        ops.append(f"{left:.4f} {h_pt - top - h * PT_PER_M:.4f} {w * PT_PER_M:.4f} "
                   f"{h * PT_PER_M:.4f} re")
    ops.append("f")
    label = board_label(board)
    avail_pt = (page.width_mm - 2 * PRINTER_EDGE_MM) / 1000.0 * PT_PER_M
    size = max(3.0, min(LABEL_PT, avail_pt / (0.5 * len(label))))
    base = h_pt - (page.label_top_mm / 1000.0 * PT_PER_M + size)
    width_pt = 0.5 * size * len(label)           # about Helvetica's mean advance
    left = page.squares_mm[0] / 1000.0 * PT_PER_M
    left = left if left + width_pt <= avail_pt else PRINTER_EDGE_MM / 1000.0 * PT_PER_M
    ops.append(f"BT /F1 {size:.2f} Tf {left:.4f} {base:.4f} Td ({_pdf_text(label)}) Tj ET")
    return _pdf_document("\n".join(ops).encode("ascii"), page, title or label)


def _pdf_document(content: bytes, page: Page, title: str) -> bytes:
    """A minimal PDF: catalog (no print scaling), one page, its content, Helvetica."""
    w = page.width_mm / 1000.0 * PT_PER_M
    h = page.height_mm / 1000.0 * PT_PER_M
    stamp = datetime.now(timezone.utc).strftime("D:%Y%m%d%H%M%SZ")
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R /ViewerPreferences << /PrintScaling /None >> >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {w:.4f} {h:.4f}] "
         "/Resources << /Font << /F1 5 0 R >> >> /Contents 4 0 R >>").encode(),
        b"<< /Length %d >>\nstream\n" % len(content) + content + b"\nendstream",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica >>",
        (f"<< /Title ({_pdf_text(title)}) /Producer (ceilkit ceilcal board) "
         f"/CreationDate ({stamp}) >>").encode("ascii", "replace"),
    ]
    out = bytearray(b"%PDF-1.6\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for k, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % k + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += (b"trailer\n<< /Size %d /Root 1 0 R /Info %d 0 R >>\nstartxref\n%d\n%%%%EOF\n"
            % (len(objects) + 1, len(objects), xref))
    return bytes(out)


def write_board_pdf(board: Board, out: Path, paper: str = DEFAULT_PAPER,
                    force: bool = False) -> Page:
    """Write ``board`` as a PDF to print at 100 %; returns its layout.

    Raises:
        ConfigError: ``out`` is not a ``.pdf``, or exists (without ``force``); as
            :func:`layout`. Nothing is written then.
        OutputError: ``out`` cannot be written.
    """
    out = Path(out)
    if out.suffix.lower() != ".pdf":
        raise ConfigError(None, "out", f"expected a .pdf file (a vector board prints at "
                          f"true scale), found {str(out)!r}")
    page = layout(board, paper)
    if out.is_dir():
        raise OutputError(out, "is a folder; expected a file path")
    with claimed({"out": [out]}, force=force):  # refused when there; locked while written
        data = board_pdf(board, paper)
        try:
            atomic_write_bytes(out, data)
        except ConfigError as exc:
            raise OutputError(out, exc.detail) from None
    return page


__all__ = ["DEFAULT_PAPER", "PAPERS", "PRINTER_EDGE_MM", "PT_PER_M", "Page", "board_label",
           "board_pdf", "check_square", "ink_rectangles", "layout", "paper_size",
           "write_board_pdf"]
