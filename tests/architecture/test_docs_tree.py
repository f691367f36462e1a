"""docs/architecture.md and the tree agree (issue 35: "its layer table matches the
tree"): every module installed under ``ceilkit`` is named there (by its file name, or a
pattern such as ``paper_*.py``), and every ``.py`` path the page names exists."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
PACKAGES = ("runtime", "calib", "cli")


def named() -> set[str]:
    """The ``.py`` paths and patterns the page names in backquotes."""
    return set(re.findall(r"`([\w/*]+\.py)`", DOC.read_text()))


def modules() -> list[Path]:
    return sorted(p.relative_to(ROOT) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
                  if p.name != "__init__.py")


def test_every_module_is_on_the_page():
    names = {n.split("/")[-1] for n in named()} - {"NAME.py", "*.py"}  # a folder's, not a name
    missing = [str(m) for m in modules()
               if not any(fnmatch.fnmatch(m.name, n.replace("NAME", "*")) for n in names)]
    assert not missing, f"modules docs/architecture.md does not name: {missing}"


def test_every_file_the_page_names_exists():
    files = [p.relative_to(ROOT).as_posix() for p in ROOT.rglob("*.py")
             if ".venv" not in p.parts and "build" not in p.parts]
    gone = [n for n in sorted(named())
            if not any(fnmatch.fnmatch(f, n.replace("NAME", "*"))
                       or fnmatch.fnmatch(f, "*/" + n.replace("NAME", "*")) for f in files)]
    assert not gone, f"docs/architecture.md names files that are not in the tree: {gone}"
