"""What the benchmarks state of the packaged corridor's heading.

The packaged corridor (configs/corridor) is symmetric about its centre line: one frame
cannot tell a vehicle heading down it from one heading back, and without a prior every
frame is ``ambiguous`` (docs/methods/honesty.md; ``bench_ambiguity.py`` measures that).
Every benchmark drive there heads along +x, and the benchmarks say so, as a user whose
vehicle starts down the corridor may (``--option assume_heading_deg=0``): their figures
are the method's accuracy once the half turn is ruled out.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

STATED = {"assume_heading_deg": 0.0}


def stated(method: str | None, options: Mapping[str, Any] | None = None,
           site: Any = None) -> Mapping[str, Any] | None:
    """``options`` with the stated heading added for the corridor method (and ``auto``,
    whose corridor cue takes it, on a ``site`` with corridor lines when one is given);
    other methods' options unchanged."""
    if method not in ("corridor", "auto") or (
            method == "auto" and site is not None and getattr(site, "corridor", None) is None):
        return options
    return {**STATED, **(options or {})}
