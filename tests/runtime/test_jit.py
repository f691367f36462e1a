"""runtime/jit.py: the warm-up makes the chosen methods' loops only, says how far it is,
and every loop a method's frames call is among the ones it made; a loop called from
another reuses its read-only version; a first start shares the compiling with helper
processes."""

from __future__ import annotations

import importlib
import os
import sys
import threading

import numba
import numpy as np
import pytest

from ceilkit.runtime import jit
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.corridor.estimator import CorridorEstimator
from ceilkit.runtime.estimators.lights.estimator import LightsEstimator
from ceilkit.runtime.multi import make_localizer
from ceilkit.runtime.tracking import Tracker
from helpers import CONFIGS

CORRIDOR, LIGHTS = (c.__module__ for c in (CorridorEstimator, LightsEstimator))
R = "ceilkit.runtime."


def test_reachable_follows_the_code_and_keeps_the_other_methods_out():
    corridor = jit.reachable([CorridorEstimator, Tracker])
    lights = jit.reachable([LightsEstimator, Tracker])
    assert {CORRIDOR, R + "estimators.corridor.hypotheses", R + "features.lines",
            R + "estimators.honesty", R + "tracking"} <= corridor
    assert not any(m.startswith(R + "estimators.lights") for m in corridor), corridor
    assert not any(m.startswith(R + "estimators.corridor") for m in lights), lights
    assert R + "estimators.block.detect" not in corridor | lights
    # features.lines calls quads' bilinear only from its compiled loops: compiled in
    assert R + "features.quads" not in corridor
    assert {LIGHTS, R + "features.spots"} <= jit.reachable([LIGHTS])   # a module: all of it
    assert jit.reachable(["not.a.module"]) == set()


def test_warm_up_runs_the_roots_warmers_reports_progress_and_keeps_the_rest(monkeypatch):
    ran: list[str] = []

    def fake(module: str):
        def warm() -> None:
            ran.append(module)
        warm.__module__ = module
        return warm

    lines_mod, spots_mod = R + "features.lines", R + "estimators.lights.observe"
    monkeypatch.setattr(jit, "_PENDING", [fake(lines_mod), fake(spots_mod)])
    steps: list[jit.WarmUpProgress] = []
    with jit.reporting(steps.append):
        jit.warm_up(roots=[CorridorEstimator])
    assert ran == [lines_mod]
    assert [w.__module__ for w in jit._PENDING] == [spots_mod]   # left for later
    n = len(jit.loops_of([lines_mod]))
    assert n > 0
    assert [(s.done, s.total, s.module) for s in steps] == [(0, n, lines_mod), (n, n, "")]
    # whether these loops were compiled or loaded depends on numba's cache (a fresh
    # checkout compiles them), so the line is checked against what was counted
    verb = "compiling" if steps[-1].compiled else "loading"
    assert steps[-1].line().startswith(f"{verb} the per-frame loops")
    assert f": {n}/{n}, " in steps[-1].line()
    assert not jit.WarmUpProgress(n, n, "", 0, 1.0).line().startswith("compiling")
    assert "first start on this machine" in jit.WarmUpProgress(1, 9, lines_mod, 1, 2.0).line()
    with jit.reporting(steps.append):
        jit.warm_up()                                            # everything left
    assert ran == [lines_mod, spots_mod] and jit._PENDING == []
    jit.warm_up()
    assert len(steps) == 4           # nothing left: no report


@pytest.mark.parametrize("method", ["lights", "corridor", "block"])
def test_every_loop_a_frame_calls_is_made_before_it(method, monkeypatch):
    """The loops a method's frames call from Python (tracked and global) all lie in the
    modules its warm-up follows from its estimator and tracker, so the first frame never
    compiles one."""
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    rig = Rig.load(CONFIGS / method / "rig.yaml")
    site = Site.load(CONFIGS / method / "site.yaml")
    opts = {"assume_heading_deg": 0.0} if method == "corridor" else None
    est, tracker = make_localizer(method, rig, site, opts)
    wanted = jit.reachable([type(est), type(tracker)])       # as make_localizer warms
    called: set[str] = set()
    for name in [m for m in list(jit.sys.modules) if m.startswith(jit.ROOT)]:
        for attr, obj in list(vars(jit.sys.modules[name]).items()):
            if isinstance(obj, numba.core.dispatcher.Dispatcher):
                monkeypatch.setattr(jit.sys.modules[name], attr, _Recorder(obj, called))
    start = ((site.markers.poses[0].x_m, site.markers.poses[0].y_m) if method == "block"
             else (3.0, 0.0))
    for k in range(2):
        img = render_frame(rig, site, start[0] + 0.02 * k, start[1], 0.01 * k,
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8, supersample=1))
        t_ns = k * 33_000_000
        tracker.update(est.estimate(img, t_ns, tracker.predict(t_ns)))
        est.estimate(img, t_ns, None)                       # the global search too
    assert called, "no loop was called"
    assert called <= wanted, sorted(called - wanted)


class _Recorder:
    """A compiled loop that notes its module when called from Python."""

    def __init__(self, dispatcher, called: set[str]):
        self.dispatcher, self.called = dispatcher, called

    def __call__(self, *args, **kwargs):
        self.called.add(self.dispatcher.py_func.__module__)
        return self.dispatcher(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.dispatcher, name)


INNER = '''
import numpy as np
from ceilkit.runtime.jit import arr, njit, warmer


@njit
def twice(a, out):
    for i in range(a.shape[0]):
        out[i] = 2.0 * a[i]
    return out


@warmer
def _warm():
    twice(arr(np.ones(2), np.float64), np.empty(2))
'''

OUTER = '''
import numpy as np
from ceilkit.runtime.jit import arr, njit, warmer
from {inner} import twice


@njit
def total(a, k):
    b = a * 1.0                        # writable: numba alone would compile a twin
    return twice(b, np.empty(b.shape[0])).sum() + twice(b, np.empty(3))[k]


@warmer
def _warm():
    total(arr(np.ones(3), np.float64), 0)
'''


@pytest.fixture
def loop_modules(tmp_path, monkeypatch, request):
    """Two fresh modules of compiled loops (the outer one calls the inner one), with
    their numba cache beside them in ``tmp_path`` (empty: a first start)."""
    tag = request.node.name.replace("[", "_").replace("]", "").replace("-", "_")
    inner, outer = f"jit_inner_{tag}", f"jit_outer_{tag}"
    (tmp_path / f"{inner}.py").write_text(INNER)
    (tmp_path / f"{outer}.py").write_text(OUTER.format(inner=inner))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])]))
    monkeypatch.setattr(jit, "_PENDING", [])
    mods = importlib.import_module(inner), importlib.import_module(outer)
    yield mods
    for m in (inner, outer):
        sys.modules.pop(m, None)


def test_an_inner_call_reuses_the_read_only_version(loop_modules):
    inner, outer = loop_modules
    x = jit.arr(np.arange(3.0), np.float64)
    assert outer.total(x, 2) == 10.0
    # one machine code for the call from Python (read-only input) and from the loop
    # (writable input, literal index): numba alone makes two of each
    assert inner.twice.signatures == [(numba.float64[::1].copy(readonly=True),
                                       numba.float64[::1])]
    assert len(outer.total.signatures) == 1
    np.testing.assert_array_equal(inner.twice(x, np.empty(3)), [0.0, 2.0, 4.0])
    # a call from Python with a writable input still gets its own exact version
    assert outer.total.py_func(x, 2) == 10.0          # calls `twice` from Python
    assert len(inner.twice.signatures) == 2


def test_unwritten_finds_the_arrays_a_loop_only_reads():
    def f(a, b, c, d, e, g, h, k):
        c[0] = a[1] + len(b) * e.shape[0]
        v = d[1:]               # a view kept: may be written through
        for x in g:
            h(x)                # handed to a call: may be written
        c[1:2] += k * 2.0
        return v

    assert jit.unwritten(f) == frozenset({0, 1, 4, 5, 7})
    assert jit.unwritten(len) == frozenset()          # no source


def test_a_cold_warm_up_shares_the_compiling_with_a_helper(loop_modules, monkeypatch):
    inner, outer = loop_modules
    names = [inner.__name__, outer.__name__]
    assert jit.callee_first(names[::-1]) == names
    assert not jit.cached(names)
    # the two processes take modules from one queue: which makes which depends on how
    # fast the helper starts; here this process takes its second module only once the
    # helper has taken one, as on an idle machine
    take, helper_took = jit.CompileHelpers.take, threading.Event()
    main = threading.current_thread()
    calls = {"main": 0}

    def paced(pool):
        if threading.current_thread() is not main:
            module = take(pool)
            helper_took.set()
            return module
        calls["main"] += 1
        if calls["main"] > 1:      # a helper's start (python, numba) took over 60 s at
            helper_took.wait(300)   # load 40-55 on 2 cores: the pacing, not a time limit
        return take(pool)

    monkeypatch.setattr(jit.CompileHelpers, "take", paced)
    steps: list[jit.WarmUpProgress] = []
    with jit.reporting(steps.append):
        jit.warm_up(roots=names, helpers=1)
    assert jit._PENDING == []
    assert jit.cached(names)
    # this process made the inner module, the helper the outer one, which is then
    # loaded here from the cache
    assert sum(outer.total.stats.cache_hits.values()) == 1
    assert sum(inner.twice.stats.cache_misses.values()) == 1
    assert [(s.done, s.total, s.module, s.compiled) for s in steps] == [
        (0, 2, names[0], 0), (2, 2, "", 2)]
    assert steps[-1].line().startswith("compiling the per-frame loops (first start on this "
                                       "machine, 2 processes; ")
    assert outer.total(jit.arr(np.arange(3.0), np.float64), 2) == 10.0


def test_a_helper_that_cannot_make_a_module_hands_it_back(loop_modules, monkeypatch):
    inner, outer = loop_modules
    monkeypatch.delenv("PYTHONPATH")            # the helper cannot import them
    names = [inner.__name__, outer.__name__]
    with jit.reporting(lambda p: None):
        jit.warm_up(roots=names, helpers=1)
    assert jit._PENDING == [] and jit.cached(names)
    assert sum(outer.total.stats.cache_misses.values()) == 1   # made here after all


def test_helper_count_reads_the_environment(monkeypatch):
    monkeypatch.setenv(jit.HELPERS_ENV, "0")
    assert jit.helper_count() == 0
    monkeypatch.setenv(jit.HELPERS_ENV, "2")
    assert jit.helper_count() == 2
    monkeypatch.delenv(jit.HELPERS_ENV)
    assert jit.helper_count() == max(0, min(3, len(os.sched_getaffinity(0)) - 1))
    monkeypatch.setenv(jit.HELPERS_ENV, "two")
    with pytest.raises(ConfigError, match="CEILKIT_COMPILE_HELPERS: expected a whole"):
        jit.helper_count()


def test_an_index_naming_a_renamed_type_reads_as_empty():
    """An upgrade that renamed a type in a loop's signature leaves an index numba cannot
    unpickle: it reads as an empty cache (the loop recompiles) instead of raising."""
    from ceilkit.runtime import jit

    class Index:
        def _load_index(self):
            raise AttributeError("Can't get attribute 'Mount' on <module ...>")

    index = Index()
    jit._stale_tolerant(index)
    assert index._load_index() == {}
