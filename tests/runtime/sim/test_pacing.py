"""A simulated live run (``ceilrun --device sim:NAME``) comes at its frames' pace and
stays on its map (issue 37: 3000 frames in 58.7 s, driving off the map)."""

from __future__ import annotations

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.devices import SIM_END_MARGIN_M, open_source, sim_length_m
from ceilkit.runtime.sim.render import SimOptions, SimSource, straight_drive
from helpers import CONFIGS


def test_sim_frames_wait_for_their_stamps():
    """``pace`` is asked to wait until each frame is due by its stamp (30 fps: 33 ms
    apart, counted from the first), less the time the frame took; never a negative
    wait."""
    now = [100.0]
    waits: list[float] = []

    def pace(s: float) -> None:
        waits.append(round(s, 6))
        now[0] += s

    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    src = SimSource(rig, site, straight_drive(4, fps=30.0), SimOptions(supersample=1),
                    pace=pace, clock=lambda: now[0])
    assert src.read().index == 0 and waits == []        # the first frame: at once
    now[0] += 0.010                                     # 10 ms to render and process
    src.read()
    now[0] += 0.050                                     # a slow frame: late, no wait
    src.read()
    src.read()
    assert waits == [0.023333, 0.016667]             # frame 2 late: frame 3 on time
    assert src.read() is None


def test_a_long_sim_run_shuttles_within_the_site():
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    length = sim_length_m(site)
    lights_x = np.asarray(site.lights_m)[:, 0]
    assert length == float(lights_x.max()) - SIM_END_MARGIN_M   # the lights end the map
    src = open_source("sim:lights", rig, site, frames=3000)
    x = src.trajectory.x_m
    assert x.min() >= -0.01 and x.max() <= length + 0.01     # 100 s at 0.8 m/s: 80 m
    assert np.sum(np.diff(np.sign(np.diff(x))) != 0) == 2      # turned back at each end
    assert np.max(np.abs(np.diff(x))) <= 0.8 / 30 + 1e-9       # never faster than 0.8 m/s
    short = open_source("sim:lights", rig, site, frames=30).trajectory.x_m
    assert np.all(np.diff(short) > 0)                          # a short run: straight on
    assert sim_length_m(Site.load(CONFIGS / "corridor" / "site.yaml")) > 100
