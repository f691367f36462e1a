"""Compiled loops take their inputs by name (issue 35, item 4): no numba dispatcher
defined under ``ceilkit`` has more than :data:`MAX_PARAMETERS` parameters in its Python
signature. A loop that needs more takes the method's constants and the frame's arrays
as named tuples (numba types their fields by name), so two floats swapped no longer
compile and run.

Every module under the package is imported (``sim`` and ``viz`` included: a loop there
is held to the same rule) and each dispatcher it defines is counted once, where it is
defined.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import numba

MAX_PARAMETERS = 8

EXEMPT: dict[str, str] = {}
"""``module.name`` -> why it may exceed the limit for now. Keep this tiny."""


ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("runtime", "calib", "cli")
"""The folders installed under ``ceilkit`` (tests/, benchmarks/ and docs/ are not)."""


def _modules() -> list[str]:
    """Every module name under the package, from the files of :data:`PACKAGES`."""
    names = []
    for path in sorted(p for d in PACKAGES for p in (ROOT / d).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.append(".".join(["ceilkit", *parts]))
    return names


def dispatchers() -> dict[str, object]:
    """``module.name`` -> each numba dispatcher defined in a module of the package."""
    out: dict[str, object] = {}
    for name in _modules():
        try:
            module = importlib.import_module(name)
        except ImportError as exc:     # an optional extra (ROS 2, MCAP) not installed
            if exc.name is not None and exc.name.split(".")[0] == "ceilkit":
                raise
            continue
        for attr, value in vars(module).items():
            if isinstance(value, numba.core.dispatcher.Dispatcher) \
                    and value.py_func.__module__ == name:
                out[f"{name}.{attr}"] = value
    return out


def parameter_counts() -> dict[str, int]:
    """``module.name`` -> number of parameters of each dispatcher's Python function."""
    return {k: len(inspect.signature(d.py_func).parameters)
            for k, d in dispatchers().items()}


def test_the_walk_finds_the_loops() -> None:
    found = dispatchers()
    assert len(found) > 50, f"only {len(found)} compiled loops found: the walk is broken"
    assert "ceilkit.runtime.features.spots._component_moments" in found or any(
        k.startswith("ceilkit.runtime.features.spots.") for k in found)


def test_no_compiled_loop_takes_more_than_eight_parameters() -> None:
    counts = parameter_counts()
    over = {k: n for k, n in sorted(counts.items())
            if n > MAX_PARAMETERS and k not in EXEMPT}
    assert not over, (
        f"compiled loops with more than {MAX_PARAMETERS} parameters (pass the method's "
        f"constants and the frame's arrays as named tuples): "
        + ", ".join(f"{k} ({n})" for k, n in over.items()))


def test_exemptions_are_still_needed() -> None:
    counts = parameter_counts()
    stale = [k for k in EXEMPT if counts.get(k, 0) <= MAX_PARAMETERS]
    assert not stale, f"exempt but within the limit (or gone): {stale}"
