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
machine: minutes for all of them on a slow 2-core VM). :func:`warm_up` does that
before the first frame: each module that holds loops registers a :func:`warmer` that
calls them once on tiny inputs of the types it passes them. ``ceilrun`` warms the
modules the chosen methods' code reaches (``warm_up(roots=...)``, :func:`reachable`:
followed from the estimator and tracker classes through the functions and classes their
code names; a loop outside them is made on its first call, should a frame ever need
it); ``ceilrun warm-up`` warms every registered module, once, for an
installer or a Dockerfile. :func:`reporting` hands each step's
:class:`WarmUpProgress` to a callback (the command line's progress line) meanwhile.

Example::

    with reporting(lambda p: print(p.line())):
        warm_up(roots=[LightsEstimator, Tracker])
"""

from __future__ import annotations

import contextlib
import sys
import time
import types
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, TypeVar

import numba
import numpy as np

F = TypeVar("F", bound=Callable[..., Any])
_PENDING: list[Callable[[], object]] = []   # warmers not yet run
_REPORTERS: list[Callable[[WarmUpProgress], None]] = []
ROOT = "ceilkit.runtime"
"""The package whose modules :func:`warm_up` follows from its roots."""


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


@dataclass(frozen=True)
class WarmUpProgress:
    """Where a :func:`warm_up` stands.

    Attributes:
        done: loops made so far; total: loops this warm-up makes.
        module: the module whose loops are being made now (``""`` once finished).
        compiled: loops of ``done`` that were compiled (not found in numba's cache).
        elapsed_s: seconds since the warm-up started.
    """

    done: int
    total: int
    module: str
    compiled: int
    elapsed_s: float

    def line(self) -> str:
        """One line for a person watching, e.g. ``compiling the per-frame loops (first
        start on this machine; numba's cache keeps them): 37/119, features.lines, 23 s``."""
        verb = ("compiling the per-frame loops (first start on this machine; numba's "
                "cache keeps them)" if self.compiled else "loading the per-frame loops")
        where = f", {self.module.removeprefix(ROOT + '.')}" if self.module else ""
        return f"{verb}: {self.done}/{self.total}{where}, {self.elapsed_s:.1f} s"


@contextlib.contextmanager
def reporting(callback: Callable[[WarmUpProgress], None]) -> Iterator[None]:
    """Within the block, every :func:`warm_up` calls ``callback`` (and any other
    reporting meanwhile) before each module's loops and once when done."""
    _REPORTERS.append(callback)
    try:
        yield
    finally:
        _REPORTERS.remove(callback)


def _loops(module: str) -> list[Any]:
    """The compiled loops (numba dispatchers) defined in ``module``."""
    return [v for v in vars(sys.modules[module]).values()
            if isinstance(v, numba.core.dispatcher.Dispatcher)
            and v.py_func.__module__ == module]


def loops_of(modules: Iterable[str]) -> list[Any]:
    """The compiled loops defined in ``modules`` (imported ones)."""
    return [d for m in sorted(modules) if m in sys.modules for d in _loops(m)]


def reachable(roots: Iterable[Any]) -> set[str]:
    """The modules of :data:`ROOT` whose code the ``roots`` run: from each root (a class,
    a function, or a module name: all of its globals), the functions and classes its code
    names (its globals, and attributes of modules it names), followed to the end, as
    far as Python code goes: a compiled loop's module is in, but not what the loop itself
    calls (compiled into it). Static, so a little wide (a branch never taken counts);
    the roots' own modules are in."""
    seen: set[int] = set()
    found: set[str] = set()
    todo: list[Any] = []
    for root in roots:
        module = sys.modules.get(root) if isinstance(root, str) else None
        if module is not None:
            found.add(root)
            todo += list(vars(module).values())
        elif not isinstance(root, str):
            todo.append(root)
    while todo:
        obj = todo.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, dict | list | tuple | set | frozenset | MappingProxyType):
            todo += list(obj.values() if isinstance(obj, dict | MappingProxyType) else obj)
            continue
        module = getattr(obj, "__module__", None)
        if not isinstance(module, str) or not module.startswith(ROOT):
            continue
        found.add(module)
        if isinstance(obj, numba.core.dispatcher.Dispatcher):
            continue
        if isinstance(obj, type):
            todo += list(obj.__mro__[1:])
            todo += [getattr(v, "__func__", None) or getattr(v, "fget", None) or v
                     for v in vars(obj).values()]
        elif hasattr(obj, "__wrapped__"):
            todo.append(obj.__wrapped__)
        elif hasattr(obj, "__code__"):
            todo += _named(obj.__code__, obj.__globals__)
        elif not isinstance(obj, types.ModuleType):
            todo.append(type(obj))
    return found


def _named(code: types.CodeType, globals_: dict[str, Any]) -> list[Any]:
    """What ``code`` (and the code nested in it) names among ``globals_``, and the
    attributes it names of the modules among them."""
    names = _all_names(code)
    out = []
    for n in names:
        v = globals_.get(n)
        if isinstance(v, types.ModuleType):
            if v.__name__.startswith(ROOT):
                out += [getattr(v, m) for m in names if hasattr(v, m)]
        elif v is not None:
            out.append(v)
    return out


def _all_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= _all_names(c)
    return names


def warm_up(roots: Iterable[Any] | None = None) -> float:
    """Load (the first time on a machine: compile) the loops registered since the last
    call, now rather than on a frame; the seconds it took.

    Args:
        roots: classes, functions or module names: only the warmers of the modules
            their code reaches (:func:`reachable`) run, the others stay registered for
            a later call (or their loops are made on first use); ``None``: every
            registered warmer.
    """
    t0 = time.perf_counter()
    wanted = None if roots is None else reachable(roots)
    todo = [w for w in _PENDING if wanted is None or w.__module__ in wanted]
    total = sum(len(_loops(w.__module__)) for w in todo)
    done = compiled = 0
    for w in todo:
        _report(WarmUpProgress(done, total, w.__module__, compiled,
                               time.perf_counter() - t0))
        _PENDING.remove(w)
        w()
        loops = _loops(w.__module__)
        done += len(loops)
        compiled += sum(1 for d in loops if sum(d.stats.cache_misses.values()))
    elapsed = time.perf_counter() - t0
    if todo:
        _report(WarmUpProgress(done, total, "", compiled, elapsed))
    return elapsed


def _report(progress: WarmUpProgress) -> None:
    for callback in list(_REPORTERS):
        callback(progress)


__all__ = ["ROOT", "WarmUpProgress", "arr", "loops_of", "njit", "reachable", "reporting",
           "warm_up", "warmer"]
