"""runtime/jit.py: the warm-up makes the chosen methods' loops only, says how far it is,
and every loop a method's frames call is among the ones it made."""

from __future__ import annotations

import numba
import pytest

from ceilkit.runtime import jit
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
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
    # features.lines calls quads' _bilinear only from its compiled loops: compiled in
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
