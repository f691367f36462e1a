"""The typed per-frame contract (issue 35): what crosses a module boundary is a typed
field of the estimate (``provenance``, ``hypotheses``, ``cues``, ``increment``), never a
``diagnostics`` key. ``diagnostics`` are for logs and reports: only the views
(``runtime/viz/``) read keys of them."""

from __future__ import annotations

import ast
import dataclasses

from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from helpers import ROOT

READERS = ("runtime/viz/",)
"""Where reading a ``diagnostics`` key is allowed: the overlays and reports draw them."""


def _key_reads(tree: ast.AST) -> list[int]:
    """Lines reading ``X.diagnostics[...]`` or ``X.diagnostics.get(...)``."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Attribute) \
                and node.value.attr == "diagnostics" and isinstance(node.ctx, ast.Load):
            out.append(node.lineno)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("get", "__getitem__") \
                and isinstance(node.func.value, ast.Attribute) \
                and node.func.value.attr == "diagnostics":
            out.append(node.lineno)
    return out


def test_no_module_reads_another_modules_diagnostics_keys():
    found = []
    for folder in ("runtime", "calib", "cli"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel.startswith(READERS):
                continue
            found += [f"{rel}:{n}" for n in _key_reads(ast.parse(path.read_text()))]
    assert not found, "diagnostics keys read outside the views: " + ", ".join(found)


def test_the_probe_finds_key_reads():
    """The scan itself: both spellings are caught, a typed field is not."""
    src = ("a = est.diagnostics['mode']\nb = est.diagnostics.get('cues')\n"
           "c = est.provenance\nd = {**est.diagnostics}\n")
    assert _key_reads(ast.parse(src)) == [1, 2]


def test_what_crosses_modules_is_typed():
    """The fields the fusion, the tracker and the link rely on are declared fields."""
    pose = {f.name for f in dataclasses.fields(PoseEstimate)}
    failure = {f.name for f in dataclasses.fields(Failure)}
    typed = {"provenance", "hypotheses", "cues", "increment", "hypotheses_complete"}
    assert typed <= pose
    assert typed - {"provenance"} <= failure
