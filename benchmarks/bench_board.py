"""Peak memory of `ceilcal board` (the command line, a process each) at 25 and 250 mm
squares on A4 and A3, and of the library call alone (`calib.board_pdf`).

Each case runs in its own process, which reads its high-water mark from
``/proc/self/status`` (VmHWM) when it ends: ``getrusage``'s ``ru_maxrss`` of an exec'd
child starts at the parent's on Linux. Prints, per case, the outcome (the page and the
measured square, or the refusal line) and the peak RSS in MB.

    .venv/bin/python benchmarks/bench_board.py
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

CASES = [(spec, square, paper) for spec in ("chess:9x6", "charuco:5x7")
         for square in (0.025, 0.25) for paper in ("a4", "a3")] + [("chess:2x2", 0.2, "a0")]

CHILD = """
import atexit, sys
from pathlib import Path
def hwm():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            sys.stderr.write(f"VMHWM {{int(line.split()[1]) / 1024:.1f}}\\n")
atexit.register(hwm)
{body}
"""
CLI = """
from ceilkit.cli.ceilcal import main
sys.argv = ["ceilcal"] + {args!r}
try:
    main()   # the console script: builds the board command alone
except SystemExit:
    pass
"""
LIBRARY = """
from ceilkit.calib.board_pdf import write_board_pdf
from ceilkit.calib.boards import parse_board
from ceilkit.runtime.errors import ConfigError
try:
    page = write_board_pdf(parse_board({spec!r}, {square!r}), Path({out!r}), {paper!r})
    print("wrote", page.paper, page.landscape)
except ConfigError as exc:
    print("refused:", exc)
"""


def child(body: str) -> tuple[str, float]:
    """What ``body`` printed in a child process (its VmHWM line taken out), and that
    process's peak resident memory, MB (also ``bench_startup.py``'s)."""
    res = subprocess.run([sys.executable, "-c", CHILD.format(body=body)],
                         capture_output=True, text=True)
    peak = float(re.search(r"VMHWM ([\d.]+)", res.stderr).group(1))
    return re.sub(r"VMHWM [\d.]+\n?", "", res.stdout + res.stderr).strip(), peak


def run(body: str) -> tuple[str, float]:
    text, peak = child(body)
    return text.replace("\n", " "), peak


def square_pt(pdf: Path, square_m: float) -> str:
    """The measured side of the squares in the PDF (pt and mm)."""
    data = pdf.read_bytes()
    sides = [float(w) for w, h in re.findall(rb"[\d.]+ [\d.]+ ([\d.]+) ([\d.]+) re", data)
             if abs(float(w) - float(h)) < 1e-6 and float(w) > 0.9 * square_m / 0.0254 * 72]
    s = max(sides)
    return f"square {s:.4f} pt = {s / 72 * 25.4:.4f} mm"


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for k, (spec, square, paper) in enumerate(CASES):
            out = Path(tmp) / f"cli{k}.pdf"
            args = ["board", "--board", spec, "--square", str(square), "--paper", paper,
                    "--out", str(out)]
            text, peak_cli = run(CLI.format(args=args))
            lib = Path(tmp) / f"lib{k}.pdf"
            _, peak_lib = run(LIBRARY.format(spec=spec, square=square, out=str(lib),
                                             paper=paper))
            what = square_pt(out, square) if out.exists() else text[:110]
            print(f"{spec:<12} {1000 * square:5g} mm {paper:<3} cli {peak_cli:6.1f} MB  "
                  f"library {peak_lib:6.1f} MB  {what}")


if __name__ == "__main__":
    main()
