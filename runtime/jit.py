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

One machine code per loop where numba would make two: a loop called from another
loop gets the arrays its caller made, which are writable, where a call from Python
passes read-only ones (:func:`arr`); numba compiles each kind apart (the corridor
method's 65 loops were 95 compiles, and 40 % of its compile time went to such twins
and their callees' twins). :class:`SharedDispatcher` gives the
inner call the compiled version it already has when only that differs (a writable
array is passed as a read-only one, a literal integer as an integer: the same code,
the same arithmetic), and compiles an inner call for read-only arrays where the loop
never writes them (:func:`unwritten`), so that the call from Python finds it made.

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
A warm-up that finds loops missing from the cache shares the compiling with helper
processes, one per further CPU (:class:`CompileHelpers`, :func:`helper_count`): each
module's loops are compiled in one of them, the others load them from the cache.
A warm-up inside :func:`stop_when` stops, helpers and all, as soon as its event is set
(:class:`WarmUpInterrupted`: ``ceilrun``'s Ctrl-C during a first start's compiling).

Example::

    with reporting(lambda p: print(p.line())):
        warm_up(roots=[LightsEstimator, Tracker])
"""

from __future__ import annotations

import ast
import contextlib
import importlib
import inspect
import os
import pickle
import subprocess
import sys
import textwrap
import threading
import time
import types
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, TypeVar

import numba
import numpy as np
from numba.core import types as nb_types
from numba.core import typing
from numba.core.errors import TypingError
from numba.core.registry import CPUDispatcher

from ceilkit.runtime.errors import ConfigError

F = TypeVar("F", bound=Callable[..., Any])
_PENDING: list[Callable[[], object]] = []   # warmers not yet run
_REPORTERS: list[Callable[[WarmUpProgress], None]] = []
ROOT = "ceilkit.runtime"
"""The package whose modules :func:`warm_up` follows from its roots."""


OPTIONS = {"nopython": True, "nogil": True, "error_model": "numpy", "boundscheck": None}
"""numba's target options of every loop (``numba.njit(nogil=True, error_model="numpy")``)."""


def njit(fn: F) -> F:
    """``numba.njit(cache=True, nogil=True, error_model="numpy")`` as a
    :class:`SharedDispatcher` (see module)."""
    disp = SharedDispatcher(py_func=fn, locals={}, targetoptions=dict(OPTIONS))
    disp.enable_caching()
    _stale_tolerant(disp._cache._cache_file)
    return disp  # type: ignore[return-value]


def _stale_tolerant(index: Any) -> None:
    """Let numba's cache index of an older source read as empty when it cannot be
    unpickled. numba unpickles an index before it compares the source's stamp, so after
    an upgrade that renamed a type in a loop's signature (a NamedTuple of arguments), a
    cache left beside the source would raise instead of being recompiled."""
    load = index._load_index

    def load_or_empty() -> dict:
        try:
            return load()
        except (AttributeError, ImportError, EOFError, pickle.UnpicklingError):
            return {}

    index._load_index = load_or_empty


class SharedDispatcher(CPUDispatcher):
    """numba's CPU dispatcher whose calls from other compiled loops reuse a version
    compiled for read-only arrays (and plain integers) rather than compile a twin.

    Calls from Python are numba's own (an exact match, else a compile), so that their
    fast path stays exact; only the typing of a call inside another loop (what numba
    compiles it for) changes. Nothing changes what a loop computes: a writable array
    passed where a read-only one is typed is the same pointer, strides and data.
    """

    def get_call_template(self, args: Any, kws: Any) -> Any:
        pysig, args = self._compiler.fold_argument_types(args, kws)
        if self._can_compile:
            self._compile_inner(tuple(args))
        name = self.py_func.__name__
        template = typing.make_concrete_template(
            f"CallTemplate({name})", key=name, signatures=self.nopython_signatures)
        return template, pysig, args, {}

    def _compile_inner(self, args: tuple[Any, ...]) -> None:
        """Make sure a version that takes ``args`` exists: the exact one, one that
        differs only by read-only arrays or plain integers, else one compiled for
        read-only arrays where the loop never writes them, else the exact one."""
        if args in self.overloads or any(_accepts(sig, args) for sig in self.overloads):
            return
        shared = _shared_args(args, unwritten(self.py_func))
        if shared != args:
            try:
                self.compile(shared)
                return
            except TypingError:   # an array it does write after all (through a view)
                pass
        self.compile(args)


def _accepts(sig: tuple[Any, ...], args: tuple[Any, ...]) -> bool:
    """Whether the version compiled for ``sig`` takes ``args`` unchanged: each the same
    type, a writable array where ``sig`` has the read-only one, or a literal integer
    where ``sig`` has its integer type."""
    if len(sig) != len(args):
        return False
    return all(a == s or _readonly(a) == s or nb_types.unliteral(a) == s
               for s, a in zip(sig, args, strict=True))


def _readonly(t: Any) -> Any:
    if isinstance(t, nb_types.Array) and type(t) is nb_types.Array and t.mutable:
        return t.copy(readonly=True)
    return t


def _shared_args(args: tuple[Any, ...], unwritten_at: frozenset[int]) -> tuple[Any, ...]:
    """``args`` with the arrays at ``unwritten_at`` read-only and literals plain."""
    return tuple(nb_types.unliteral(_readonly(a) if i in unwritten_at else a)
                 for i, a in enumerate(args))


_UNWRITTEN: dict[Any, frozenset[int]] = {}
_SAFE_ATTRS = frozenset({"shape", "size", "ndim", "dtype"})


def unwritten(fn: Callable[..., Any]) -> frozenset[int]:
    """The positions of ``fn``'s parameters its code only reads: every use of the name
    an element or slice read (``p[i]``, ``p[a:b]`` as a value), ``len(p)``, one of
    ``p.shape/size/ndim/dtype``, an operand of arithmetic or a comparison, or the
    iterable of a ``for``. Anything else (an item assigned, a call's argument, a method,
    a name bound to it) counts as written. Found from the source; empty when there is
    none."""
    if fn in _UNWRITTEN:
        return _UNWRITTEN[fn]
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(fn)))
    except (OSError, TypeError, SyntaxError):
        tree = None
    node = tree.body[0] if tree is not None and tree.body else None
    out: frozenset[int] = frozenset()
    if isinstance(node, ast.FunctionDef):
        params = [a.arg for a in node.args.posonlyargs + node.args.args]
        parents = {id(c): p for p in ast.walk(node) for c in ast.iter_child_nodes(p)}
        written = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)
                   and n.id in params and not _only_read(n, parents)}
        out = frozenset(i for i, p in enumerate(params) if p not in written)
    _UNWRITTEN[fn] = out
    return out


def _only_read(name: ast.Name, parents: dict[int, ast.AST]) -> bool:
    """Whether this use of a name only reads the array it names (see :func:`unwritten`)."""
    if not isinstance(name.ctx, ast.Load):
        return False
    up = parents.get(id(name))
    if isinstance(up, ast.Subscript):   # an item read, not a view kept or handed on
        above = parents.get(id(up))
        return up.value is name and isinstance(up.ctx, ast.Load) and not isinstance(
            above, ast.Assign | ast.AnnAssign | ast.NamedExpr | ast.Return | ast.Tuple
            | ast.Call | ast.Attribute | ast.withitem | ast.Subscript | ast.keyword)
    if isinstance(up, ast.Attribute):
        return up.attr in _SAFE_ATTRS
    if isinstance(up, ast.Call):
        return (isinstance(up.func, ast.Name) and up.func.id == "len"
                and up.args == [name])
    if isinstance(up, ast.For):
        return up.iter is name
    return isinstance(up, ast.BinOp | ast.Compare | ast.UnaryOp)


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
        helpers: helper processes compiling beside this one (:class:`CompileHelpers`).
    """

    done: int
    total: int
    module: str
    compiled: int
    elapsed_s: float
    helpers: int = 0

    def line(self) -> str:
        """One line for a person watching, e.g. ``compiling the per-frame loops (first
        start on this machine; numba's cache keeps them): 37/119, features.lines, 23 s``
        (``first start on this machine, 2 processes; ...`` with a helper)."""
        procs = f", {1 + self.helpers} processes" if self.helpers else ""
        verb = (f"compiling the per-frame loops (first start on this machine{procs}; "
                "numba's cache keeps them)" if self.compiled else
                "loading the per-frame loops")
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


def warm_up(roots: Iterable[Any] | None = None, helpers: int | None = None) -> float:
    """Load (the first time on a machine: compile) the loops registered since the last
    call, now rather than on a frame; the seconds it took.

    Args:
        roots: classes, functions or module names: only the warmers of the modules
            their code reaches (:func:`reachable`) run, the others stay registered for
            a later call (or their loops are made on first use); ``None``: every
            registered warmer.
        helpers: helper processes that compile beside this one when some of the
            loops are not in numba's cache yet (:class:`CompileHelpers`); ``None``:
            :func:`helper_count`. Loops found in the cache are loaded here alone.
    """
    t0 = time.perf_counter()
    _check_stopped()
    wanted = None if roots is None else reachable(roots)
    todo = [w for w in _PENDING if wanted is None or w.__module__ in wanted]
    by_module: dict[str, list[Callable[[], object]]] = {}
    for w in todo:
        by_module.setdefault(w.__module__, []).append(w)
    order = callee_first(list(by_module))
    total = sum(len(_loops(m)) for m in order)
    n_helpers = helper_count() if helpers is None else helpers
    pool = (CompileHelpers(order, n_helpers)
            if n_helpers > 0 and len(order) > 1 and not cached(order) else None)
    _WARMING.append(threading.get_ident())
    try:
        if pool is not None:
            pool.start()
        done, compiled = _make(order, by_module, pool, total, t0)
    finally:                        # an interrupt too: the helpers stop with this
        _WARMING.remove(threading.get_ident())
        if pool is not None:
            pool.close()
    elapsed = time.perf_counter() - t0
    if todo:
        _report(WarmUpProgress(done, total, "", compiled, elapsed,
                               n_helpers if pool is not None else 0))
    return elapsed


def _make(order: list[str], by_module: dict[str, list[Callable[[], object]]],
          pool: CompileHelpers | None, total: int, t0: float) -> tuple[int, int]:
    """:func:`warm_up`'s modules made here (and by ``pool``'s helpers, then loaded
    here): the loops made, and how many of them were compiled."""
    n_pool = len(pool) if pool is not None else 0
    done = compiled = 0

    def run(module: str) -> tuple[int, int]:
        for w in by_module[module]:
            _PENDING.remove(w)
            w()
        loops = _loops(module)
        return len(loops), sum(1 for d in loops if sum(d.stats.cache_misses.values()))

    queue = pool.take if pool is not None else iter([*order, None]).__next__
    for last in (False, True):      # last: what a failed helper handed back
        while (module := queue()) is not None:
            _check_stopped()
            extra = pool.progress() if pool is not None else (0, 0)
            _report(WarmUpProgress(done + extra[0], total, module, compiled + extra[1],
                                   time.perf_counter() - t0, n_pool))
            n, c = run(module)
            done, compiled = done + n, compiled + c
        if pool is None or last:
            break
        made = pool.join()
    if pool is not None:            # their loads: from the cache the helpers filled
        for module, c in made.items():
            done, compiled = done + run(module)[0], compiled + c
    return done, compiled


class WarmUpInterrupted(KeyboardInterrupt):
    """A :func:`warm_up` stopped before it made every loop (:func:`stop_when`). Its
    helper processes are stopped; numba writes each cache file whole (a temporary
    file renamed), so the loops made so far are kept and the others are compiled on a
    later start. A ``KeyboardInterrupt``, so that no ``except Exception`` in the
    compiler takes it for a failed compile."""


_STOPS: list[threading.Event] = []
_WARMING: list[int] = []            # the threads in a warm-up now


@contextlib.contextmanager
def stop_when(stop: threading.Event) -> Iterator[None]:
    """Within the block, a :func:`warm_up` raises :class:`WarmUpInterrupted` once
    ``stop`` is set: when it starts, before each module, or at once when
    :func:`interrupt` is called (the signal handler that sets ``stop`` calls it: a
    first start's compiling takes minutes)."""
    _STOPS.append(stop)
    try:
        yield
    finally:
        _STOPS.remove(stop)


def _check_stopped() -> None:
    if any(s.is_set() for s in _STOPS):
        raise WarmUpInterrupted("the warm-up was stopped")


def interrupt() -> None:
    """For a signal handler (on the main thread) that has just set the event of a
    :func:`stop_when`: a warm-up under way in this thread stops now (raises
    :class:`WarmUpInterrupted` from the handler, wherever the compiling is); nothing
    when none is."""
    if threading.get_ident() in _WARMING:
        _check_stopped()


HELPERS_ENV = "CEILKIT_COMPILE_HELPERS"
"""The environment variable that sets :func:`helper_count` (``0``: compile alone)."""


def helper_count() -> int:
    """How many helper processes a warm-up that compiles starts: ``$CEILKIT_COMPILE_HELPERS``,
    else one fewer than the CPUs this process may run on, at most 3."""
    value = os.environ.get(HELPERS_ENV, "").strip()
    if not value:
        return max(0, min(3, len(os.sched_getaffinity(0)) - 1))
    if not value.isdigit():
        raise ConfigError(None, HELPERS_ENV, f"expected a whole number >= 0, found {value!r}")
    return int(value)


def cached(modules: Iterable[str]) -> bool:
    """Whether numba's cache holds machine code of the current source for every loop of
    ``modules`` (a later start: loading them takes milliseconds each, and helpers would
    only cost their start); ``False`` after an upgrade changed a source."""
    for d in loops_of(modules):
        index = getattr(d._cache, "_cache_file", None)
        if index is None or not os.path.exists(index._index_path) or not index._load_index():
            return False
    return True


def callee_first(modules: list[str]) -> list[str]:
    """``modules`` ordered so that a module comes after those whose loops its loops
    call (when no cycle prevents it), otherwise as given: a helper then finds a
    callee in the cache rather than compiling it a second time."""
    inside = set(modules)
    needs = {m: {v.py_func.__module__ for d in _loops(m)
                 for v in _named(d.py_func.__code__, d.py_func.__globals__)
                 if isinstance(v, numba.core.dispatcher.Dispatcher)} & inside - {m}
             for m in modules}
    out: list[str] = []
    left = list(modules)
    while left:
        ready = next((m for m in left if needs[m] <= set(out)), left[0])
        out.append(ready)
        left.remove(ready)
    return out


class CompileHelpers:
    """Processes that compile loops into numba's cache beside this one (a first start
    on a machine with more than one CPU: each loop compiles in one process, so the
    compile takes about 1/(n+1) of the time).

    Each helper is ``python -c 'ceilkit.runtime.jit.serve()'``: it reads module names on
    its stdin, imports each and runs its warmers (numba writes the machine code to its
    cache, as any first call does), and answers ``done MODULE COMPILED``. This process
    and the helpers take modules from one queue (:meth:`take`); this process then loads
    the helpers' modules from the cache (:meth:`join`). A helper that fails or cannot
    start hands its module back: this process makes it itself (and reports any error).
    Nothing a loop computes depends on which process compiled it.
    """

    def __init__(self, modules: list[str], n: int):
        self._queue = list(modules)
        self._lock = threading.Lock()
        self._done: dict[str, int] = {}
        self._loops: dict[str, int] = {}
        self._procs: list[subprocess.Popen] = []
        self._closed = False
        self._threads = [threading.Thread(target=self._feed, daemon=True,
                                          name=f"compile-helper-{k}") for k in range(n)]

    def __len__(self) -> int:
        return len(self._threads)

    def start(self) -> None:
        """Start the helpers (each on a thread that feeds it modules)."""
        for t in self._threads:
            t.start()

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the helpers now (a warm-up interrupted; nothing once they are done): no
        module is handed out any more, and each helper process is terminated and waited
        for (killed after ``timeout_s``). A loop a helper was compiling is not written:
        numba writes a cache file whole or not at all."""
        with self._lock:
            self._closed = True
            self._queue.clear()
            procs = list(self._procs)
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def take(self) -> str | None:
        """The next module to make (``None``: none left, or closed)."""
        with self._lock:
            return self._queue.pop(0) if self._queue and not self._closed else None

    def progress(self) -> tuple[int, int]:
        """Loops the helpers made so far, and of them compiled."""
        with self._lock:
            return sum(self._loops.values()), sum(self._done.values())

    def join(self) -> dict[str, int]:
        """Wait for the helpers; the modules they made, each with its loops compiled."""
        for t in self._threads:
            t.join()
        return dict(self._done)

    def _feed(self) -> None:
        code = "from ceilkit.runtime.jit import serve; serve()"
        try:
            proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                    text=True)
        except OSError:
            return
        with self._lock:
            self._procs.append(proc)
            if self._closed:        # closed while it started
                proc.terminate()
        with proc:
            while (module := self.take()) is not None:
                try:
                    proc.stdin.write(module + "\n")
                    proc.stdin.flush()
                    answer = proc.stdout.readline().split()
                except OSError:
                    answer = []
                if answer[:2] != ["done", module] or len(answer) != 4:
                    with self._lock:               # this process makes it
                        if not self._closed:
                            self._queue.insert(0, module)
                    break
                with self._lock:
                    self._done[module], self._loops[module] = int(answer[2]), int(answer[3])
            with contextlib.suppress(OSError):
                proc.stdin.close()


def serve() -> None:
    """A :class:`CompileHelpers` process: for each module name read on stdin, import it,
    run its warmers, and answer ``done MODULE COMPILED LOOPS`` (or ``failed MODULE``).
    A Ctrl-C on the terminal reaches the helpers too: they end quietly (the warm-up they
    serve stops them all, :meth:`CompileHelpers.close`)."""
    try:
        _serve()
    except KeyboardInterrupt:
        pass


def _serve() -> None:
    for line in sys.stdin:
        module = line.strip()
        try:
            importlib.import_module(module)
            for w in [w for w in _PENDING if w.__module__ == module]:
                _PENDING.remove(w)
                w()
            loops = _loops(module)
            compiled = sum(1 for d in loops if sum(d.stats.cache_misses.values()))
        except Exception:   # noqa: BLE001 - the parent makes it again and reports it
            print(f"failed {module}", flush=True)
            continue
        print(f"done {module} {compiled} {len(loops)}", flush=True)


def _report(progress: WarmUpProgress) -> None:
    for callback in list(_REPORTERS):
        callback(progress)


__all__ = ["HELPERS_ENV", "ROOT", "CompileHelpers", "SharedDispatcher", "WarmUpInterrupted",
           "WarmUpProgress", "arr", "cached", "callee_first", "helper_count", "interrupt",
           "loops_of", "njit", "reachable", "reporting", "serve", "stop_when", "unwritten",
           "warm_up", "warmer"]
