"""The corridor's window path with a rolling shutter (issue 38): a frame whose prior
carries no velocity goes to the global path (``track.window_applies``), one whose prior
carries it takes the window path; and the window search is on by default."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.estimators.corridor.estimator import CorridorOptions
from ceilkit.runtime.estimators.corridor.track import window_applies
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.sim.realism import Realism, render_real
from ceilkit.runtime.sim.render import SimOptions, Trajectory

CONFIGS = Path(__file__).resolve().parents[3] / "configs"
READOUT_MS = 25.0
VELOCITY = (0.8, 0.3, 0.35)          # m/s, m/s, rad/s in W: sideways and turning
START = (4.0, 0.1, math.radians(3.0))
HEADING = {"assume_heading_deg": 0.0}
"""The packaged corridor is symmetric about its centre line: these tests state the
heading, as a user may."""


@pytest.fixture(scope="module")
def skewed():
    """``(rig, site, frame, truth)``: the packaged corridor seen through a 25 ms rolling
    shutter by a vehicle moving at :data:`VELOCITY` (constant over the frame)."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    t = np.array([-10 ** 8, 0, 10 ** 8], np.int64)
    (x0, y0, a0), (vx, vy, w) = START, VELOCITY
    traj = Trajectory(t, x0 + vx * t / 1e9, y0 + vy * t / 1e9, a0 + w * t / 1e9)
    img = render_real(rig, site, traj.pose_at, 0, SimOptions(noise_sigma=0.0),
                      Realism(rolling_shutter_ms=READOUT_MS, time_samples=16))
    return rig, site, img, START


def _prior(velocity):
    _, y, yaw = START
    return PoseEstimate(0, "track", None, y + 0.005, yaw + 0.002, 0.0,
                        cov=np.diag([np.inf, 0.01 ** 2, math.radians(0.1) ** 2]),
                        velocity=velocity)


def test_window_applies_needs_a_velocity_only_with_a_readout():
    moving, still = _prior(VELOCITY), _prior(None)
    assert window_applies(0.0, still) and window_applies(0.0, moving)
    assert window_applies(READOUT_MS, moving) and not window_applies(READOUT_MS, still)
    assert not window_applies(0.0, None) and not window_applies(READOUT_MS, None)
    assert not window_applies(0.0, PoseEstimate(0, "track", None, None, 0.0, 0.0))


def test_a_prior_without_velocity_sends_a_rolling_shutter_frame_global(skewed):
    """Without the rows' motion both paths fit the skewed frame with zero rates, and
    their errors are that motion seen through where their evidence lies; such a frame is
    decided by the global path: the same estimate as with the window search off."""
    rig, site, img, _ = skewed
    opts = {**HEADING, "readout_ms": READOUT_MS}
    win = CorridorEstimator(rig, site, {**opts, "window_search": True, "window_full_every": 0})
    glob = CorridorEstimator(rig, site, {**opts, "window_search": False})
    w, g = win.estimate(img, 0, _prior(None)), glob.estimate(img, 0, _prior(None))
    assert isinstance(w, PoseEstimate) and isinstance(g, PoseEstimate), (w, g)
    assert w.diagnostics["hypothesis"] != "window"
    assert w.diagnostics["search"] == g.diagnostics["search"] != "window"
    assert (w.y_m, w.yaw_rad) == (g.y_m, g.yaw_rad)


def test_a_prior_with_velocity_takes_the_window_path(skewed):
    """With the velocity the rows are predicted as the frame was exposed: a window fix,
    within 1.5 mm and 0.02 deg of the stamp's pose; with a global shutter assumed
    (``readout_ms`` 0) the window path runs without a velocity too."""
    rig, site, img, (_, y, yaw) = skewed
    win = CorridorEstimator(rig, site, {**HEADING, "readout_ms": READOUT_MS,
                                        "window_search": True, "window_full_every": 0})
    e = win.estimate(img, 0, _prior(VELOCITY))
    assert isinstance(e, PoseEstimate) and e.diagnostics["hypothesis"] == "window", e
    assert abs(e.y_m - y) < 1.5e-3 and abs(math.degrees(wrap_pi(e.yaw_rad - yaw))) < 0.02
    flat = CorridorEstimator(rig, site, {**HEADING, "window_search": True,
                                         "window_full_every": 0})
    assert flat.estimate(img, 0, _prior(None)).diagnostics["hypothesis"] == "window"


def test_the_window_search_is_on_by_default(skewed):
    """Issue 38: a default corridor estimator with a prior takes the window path (its
    global search every 30 window fixes)."""
    rig, site, img, _ = skewed
    assert CorridorOptions().window_search and CorridorOptions().window_full_every == 30
    est = CorridorEstimator(rig, site, HEADING)
    assert est.lines_track is not None
    assert est.estimate(img, 0, _prior(None)).diagnostics["hypothesis"] == "window"
