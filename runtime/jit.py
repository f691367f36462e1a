"""Compiled loops of the hot paths (numba): the decorator they share.

A tracked frame does little arithmetic: a few thousand pixels in a dozen windows, a
few dozen edge stations, a 3x3 solve. In numpy each step is a call of 1-15 us on small
arrays, so a frame's time is the count of calls, not the work. The loops here do one
stage in one compiled call, over the same pixels and with the same reading as the
array code they replace (whose docstrings stay the reference for the method).

Compiled with :func:`njit`: ``cache=True`` (the machine code is kept beside the source,
or in numba's user cache when that is not writable, so only the first run on a machine
compiles), ``nogil=True`` (a capture thread runs beside the estimator), no fast-math
(the results are IEEE like numpy's, reassociation aside).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])


def njit(fn: F) -> F:
    """``numba.njit`` with the project's settings (see module)."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)


__all__ = ["njit"]
