"""Folders are layers: a module imports only its own layer and the layers below it.

The order, lowest first (docs/architecture.md): errors, jit, geometry, config, features,
estimators, io, sim, viz, the orchestration modules at runtime/'s top (pipeline, tracking,
live, replay, metrics, devices, ...), calib, cli. The test parses every source file's
imports (lazy ones inside functions too), so a violation fails here before it ships.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"runtime": "ceilkit.runtime", "calib": "ceilkit.calib", "cli": "ceilkit.cli"}
LAYERS = ["errors", "jit", "geometry", "config", "features", "estimators", "io", "sim", "viz",
          "runtime", "calib", "cli"]
"""Layer names, lowest first; ``runtime`` is the orchestration at runtime/'s top."""


def layer_of(module: str) -> int | None:
    """The layer index of a ``ceilkit.*`` module name, None outside ceilkit."""
    parts = module.split(".")
    if parts[0] != "ceilkit" or len(parts) < 2:
        return None
    if parts[1] in ("calib", "cli"):
        return LAYERS.index(parts[1])
    if parts[1] != "runtime":
        return None
    if len(parts) >= 3 and parts[2] in LAYERS[:9]:
        return LAYERS.index(parts[2])
    return LAYERS.index("runtime")


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    parts = list(rel.with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join([PACKAGES[parts[0]], *parts[1:]])


def imports(path: Path, module: str, source: str | None = None) -> list[tuple[int, str]]:
    """``(line, imported module)`` of every import in ``path`` (or in ``source``, as if it
    were ``path``'s text), relative ones resolved."""
    text = path.read_text(encoding="utf-8") if source is None else source
    tree = ast.parse(text, str(path))
    pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = pkg[:len(pkg) - node.level + 1] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            out.append((node.lineno, name))
            if not node.module:  # `from . import x`: x is a module of that package
                out += [(node.lineno, f"{name}.{a.name}") for a in node.names]
    return out


def sources() -> list[Path]:
    return sorted(p for d in PACKAGES for p in (ROOT / d).rglob("*.py"))


def test_layers_are_known_folders():
    """Every runtime subfolder is a layer: a new folder must be placed in the order."""
    folders = {p.name for p in (ROOT / "runtime").iterdir()
               if p.is_dir() and (p / "__init__.py").exists()}
    assert folders <= set(LAYERS[:9]), folders - set(LAYERS[:9])


def upward(path: Path, source: str | None = None) -> list[str]:
    """The imports of ``path`` (or of ``source`` placed at ``path``) that point up."""
    module = module_name(path)
    own = layer_of(module)
    return [f"{path.relative_to(ROOT)}:{line} imports {name} ({LAYERS[layer_of(name)]})"
            for line, name in imports(path, module, source)
            if layer_of(name) is not None and layer_of(name) > own]


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_down(path):
    bad = upward(path)
    assert not bad, (f"{LAYERS[layer_of(module_name(path))]} may not import a higher "
                     "layer: " + "; ".join(bad))


def test_the_check_catches_an_upward_import():
    """The checker itself, through the functions the test above calls: a real module
    passes, and a probe in features/ importing io (absolute) and sim (relative) fails
    on both lines; a downward relative import passes."""
    f = ROOT / "runtime" / "features" / "lines.py"
    assert upward(f) == [] and imports(f, module_name(f))
    probe = ROOT / "runtime" / "features" / "_probe_.py"
    fake = ("from ceilkit.runtime.io.sources import Frame\nfrom ..sim import render\n"
            "from ..geometry import camera\nimport numpy\n")
    assert upward(probe, fake) == [
        "runtime/features/_probe_.py:1 imports ceilkit.runtime.io.sources (io)",
        "runtime/features/_probe_.py:2 imports ceilkit.runtime.sim (sim)",
    ]
    assert not probe.exists()
