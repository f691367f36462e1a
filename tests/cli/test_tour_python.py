"""docs/tour.md §7, "The same from Python", runs as printed (issue 37: it ended in
``ConfigError: run1: not a recording folder``): the snippet, taken from the page, in a
fresh process in an empty folder."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from helpers import ROOT


def tour_snippet() -> str:
    """The indented code block of docs/tour.md's section 7."""
    text = (ROOT / "docs" / "tour.md").read_text()
    section = text.split("## 7. The same from Python", 1)[1].split("\n## ", 1)[0]
    lines, block = section.splitlines(), []
    for line in lines:
        if line.startswith("    ") or (block and not line.strip()):
            block.append(line)
        elif block:
            break
    return textwrap.dedent("\n".join(block))


def test_the_tours_python_snippet_runs(tmp_path):
    code = tour_snippet()
    assert "run_session" in code and "replay(" in code
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "wrote py-camera.yaml" in proc.stdout
    assert "recorded 20 frames in py-run" in proc.stdout
    assert "replay py-run with lights (no tracking): 20 frames" in proc.stdout
    assert (tmp_path / "py-run" / "replay" / "poses.csv").exists()
