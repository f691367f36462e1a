"""Size limits on the per-frame path (issue #10) and in calib/ (issue #35): no class
over 300 lines, no function over 80 lines.

The per-frame path is runtime/ minus runtime/sim/ (the renderer, never on the vehicle)
and runtime/viz/ (figures); calib/ is checked whole. Sizes are AST spans: from the
``def``/``class`` line to the last line of the body, docstring and comments inside
included, decorators not.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUNTIME = ROOT / "runtime"
CALIB = ROOT / "calib"
OFF_PATH = ("sim", "viz")
"""runtime/ subfolders off the per-frame path."""
MAX_CLASS_LINES = 300
MAX_FUNCTION_LINES = 80

EXEMPT: dict[str, str] = {}
"""``path::qualified name`` -> why it is over its limit for now. Keep this tiny."""


def oversized(source: str, rel: str) -> dict[str, int]:
    """``path::qualified name`` -> line count of each class or function over its limit."""
    out: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}{child.name}"
                lines = child.end_lineno - child.lineno + 1
                limit = MAX_CLASS_LINES if isinstance(child, ast.ClassDef) \
                    else MAX_FUNCTION_LINES
                if lines > limit:
                    out[f"{rel}::{name}"] = lines
                visit(child, f"{name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source, rel), "")
    return out


def per_frame_sources() -> list[Path]:
    return [p for p in sorted(RUNTIME.rglob("*.py"))
            if p.relative_to(RUNTIME).parts[0] not in OFF_PATH]


def calib_sources() -> list[Path]:
    return sorted(CALIB.rglob("*.py"))


def measured() -> dict[str, int]:
    found: dict[str, int] = {}
    for path in per_frame_sources() + calib_sources():
        rel = path.relative_to(ROOT).as_posix()
        found.update(oversized(path.read_text(encoding="utf-8"), rel))
    return found


def test_no_class_or_function_over_its_limit_on_the_per_frame_path_and_in_calib():
    over = {k: v for k, v in measured().items() if k not in EXEMPT}
    assert not over, "over the size limit (class 300, function 80 lines): " + ", ".join(
        f"{k} ({v} lines)" for k, v in sorted(over.items()))


def test_exemptions_are_still_needed():
    found = measured()
    stale = sorted(k for k in EXEMPT if k not in found)
    assert not stale, f"exempt but within the limit now (remove from EXEMPT): {stale}"


def test_the_measure_sees_methods_nested_functions_and_classes():
    body = "\n".join(f"        x{i} = {i}" for i in range(80))  # 80 lines, 8 spaces
    src = (f"class A:\n    def m(self):\n{body}\n\n"
           f"def f():\n    def g():\n{body}\n\n"
           "def ok():\n    return 1\n")
    got = oversized(src, "x.py")
    assert set(got) == {"x.py::A.m", "x.py::f", "x.py::f.g"}
    big = "class B:\n" + "\n".join(f"    y{i} = {i}" for i in range(300)) + "\n"
    assert oversized(big, "y.py") == {"y.py::B": 301}
    assert per_frame_sources() and not any(
        p.relative_to(RUNTIME).parts[0] in OFF_PATH for p in per_frame_sources())
    assert ROOT / "calib" / "lightmap.py" in calib_sources()
