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

A loop is made on its first call: about 0.7 s for the first of a process (numba's
start), then milliseconds each from the cache (seconds each to compile, once per
machine). :func:`warm_up` does that before the first frame: each module that holds
loops registers a :func:`warmer` that calls them once on tiny inputs of the types it
passes them, and ``ceilrun`` runs every registered warmer after building the
estimator.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TypeVar

import numba
import numpy as np

F = TypeVar("F", bound=Callable[..., Any])
_PENDING: list[Callable[[], object]] = []   # warmers not yet run


def njit(fn: F) -> F:
    """``numba.njit`` with the project's settings (see module)."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)


def arr(a: Any, dtype: Any) -> Any:
    """``a`` as a loop takes every input array: C-contiguous, of ``dtype``, read-only
    (numba compiles a read-only array as another type than a writable one; the site's
    corners and the cached constants are read-only, a frame may be: one kind for all
    inputs is one machine code per loop). A writable array becomes a read-only view;
    nothing is copied unless its dtype or layout differ. (The arrays a loop writes
    into are made by its caller and passed as they are.)"""
    if type(a) is not np.ndarray or a.dtype != dtype:
        a = np.ascontiguousarray(a, dtype)
    flags = a.flags
    if not flags.c_contiguous:
        a = np.ascontiguousarray(a)
        flags = a.flags
    if flags.writeable:
        a = a.view()
        a.setflags(write=False)
    return a


def warmer(fn: F) -> F:
    """Register ``fn`` (no arguments) for :func:`warm_up`: it calls its module's loops
    once, on tiny inputs of the dtypes and ranks the module passes them."""
    _PENDING.append(fn)
    return fn


def warm_up() -> float:
    """Load (the first time on a machine: compile) every loop registered since the last
    call, now rather than on the first frame; the seconds it took."""
    t0 = time.perf_counter()
    while _PENDING:
        _PENDING.pop(0)()
    return time.perf_counter() - t0


__all__ = ["arr", "njit", "warm_up", "warmer"]
