"""The corridor's window fix does not follow its prior (issue 36): on a tile grid, the
chords searched about a prior a fraction of a pixel off were located with an error
that depends on that offset (the profile's samples 0.5 px apart: a seam's centroid
gains or loses a sample with the phase; the edge model leans towards the profile's
middle), alike on every chord, so the fix kept a share of the prior's error that no
residual shows (bench_ambiguity's tiles loop: mean NEES 5.47 against [0.96, 3.42]).
A fit that moved the lines is searched again about itself (``REMEASURE_PX``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import tile_grid

POSES = [(1.0 + 1.5 * math.cos(a), 1.5 * math.sin(a), a + math.pi / 2)
         for a in np.linspace(0.0, 1.6, 8)]
"""Poses on bench_ambiguity's tiles loop (m, m, rad)."""

OFF_PX = 0.2
"""The prior's lateral offset, in pixels at the ceiling (where the old pull peaked)."""


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    return tile_grid(tmp_path_factory.mktemp("tiles"))


def test_the_window_fix_does_not_follow_a_prior_a_fraction_of_a_pixel_off(tiles):
    """From priors ``OFF_PX`` to either side of the truth, the window fixes of the same
    frames agree: their mean half difference (what the fix keeps of the prior's 1.07
    mm offset) was 42 um against the fixes' median 1 sigma of 25 um; now 5 um against
    15 (the second search about a fit still 42 um off keeps a tenth of that)."""
    rig, site = tiles
    est = CorridorEstimator(rig, site, {"window_full_every": 0})
    off_m = OFF_PX * est.setup.ceiling_above_cam_m / est.setup.f_px
    pulls, sigmas = [], []
    for k, (x, y, yaw) in enumerate(POSES):
        img = render_frame(rig, site, x, y, yaw, rng=np.random.default_rng(k),
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8))
        fix = []
        for side in (1.0, -1.0):
            est.forget()
            e = est.estimate(img, 0, PoseEstimate(0, "track", x, y + side * off_m, yaw, 0.0))
            assert e and e.diagnostics["search"] == "window"
            assert abs(e.y_m - y) < 1e-3
            fix.append(e.y_m)
            sigmas.append(math.sqrt(e.cov[1, 1]))
        pulls.append(0.5 * (fix[0] - fix[1]))
    pull = float(np.mean(pulls))
    assert abs(pull) < 0.5 * float(np.median(sigmas)), (pull, np.median(sigmas))
