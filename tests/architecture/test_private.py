"""A private name (a leading underscore) stays in its package: no module imports one
from another folder (another method, or the shared ``features/`` from a method).

What one package shares with another is public and named as such, so that a maintainer
who changes a private helper needs to read only its own folder.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.architecture.test_layers import ROOT, module_name

FOLDERS = ("runtime", "calib", "cli")


def private_imports(path: Path, module: str, source: str | None = None
                    ) -> list[tuple[int, str]]:
    """``(line, "module.name")`` of every private name ``path`` imports from a module of
    another package (folder); ``as`` aliases do not make a name private."""
    tree = ast.parse(path.read_text(encoding="utf-8") if source is None else source)
    here = module.rsplit(".", 1)[0] if path.name != "__init__.py" else module
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
            continue
        there = node.module.rsplit(".", 1)[0]
        if not node.module.startswith("ceilkit.") or there == here:
            continue
        out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")]
    return out


def test_no_module_imports_a_private_name_of_another_package():
    found = []
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            found += [f"{path.relative_to(ROOT)}:{line} {name}"
                      for line, name in private_imports(path, module_name(path))]
    assert not found, "private names imported across packages: " + ", ".join(found)


def test_the_probe_finds_a_private_import():
    path = ROOT / "runtime" / "estimators" / "corridor" / "example.py"
    src = ("from ceilkit.runtime.features.lines import _core, public\n"
           "from ceilkit.runtime.estimators.corridor.frame import _same_package\n"
           "from ceilkit.runtime.geometry.fits import scaled as _alias\n")
    assert private_imports(path, module_name(path), src) == [
        (1, "ceilkit.runtime.features.lines._core")]
