"""One meaning, one implementation: a helper the runtime shares is defined once and
imported by the modules that need it (issue 35, item 8)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SHARED = {"chi2_quantile": "runtime/geometry/ekf.py",
          "ceiling_norm": "runtime/geometry/ceiling.py",
          "ceiling_rays": "runtime/geometry/ceiling.py",
          "meet_ceiling": "runtime/geometry/ceiling.py"}
"""A shared function -> the one module defining it."""


def definitions(name: str) -> list[str]:
    """The files under runtime/ and calib/ defining a top-level function ``name``."""
    out = []
    for path in sorted(p for d in ("runtime", "calib") for p in (ROOT / d).rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        if any(isinstance(n, ast.FunctionDef) and n.name == name for n in tree.body):
            out.append(str(path.relative_to(ROOT)))
    return out


@pytest.mark.parametrize("name", sorted(SHARED))
def test_a_shared_function_is_defined_once(name):
    assert definitions(name) == [SHARED[name]]


def test_the_model_checks_use_the_fusions_chi2_quantile():
    from ceilkit.runtime.estimators import honesty
    from ceilkit.runtime.geometry import ekf

    assert honesty.chi2_quantile is ekf.chi2_quantile
    assert ekf.chi2_quantile(0.999, 3) == pytest.approx(16.266, abs=1e-3)
    assert ekf.chi2_quantile(0.95, 0) == float("inf")
