"""The spot detector's region walk (compiled: ``spots._classify``, ``spots._walk``)
against the array reading it replaced (tests/spots_reference.py): the same rows, in the
same order, and the same drop counts, on cluttered ceilings, close pairs of lights and
glare halos, for every option of the walk."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import spots_reference as ref

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.features.spots import SpotParams, _measure_regions, niblack_mask
from ceilkit.runtime.sim.realism import load_preset
from ceilkit.runtime.sim.render import SimSource, straight_drive
from helpers import CONFIGS


def _frames() -> list[np.ndarray]:
    """Lights frames with the realistic preset's clutter (grilles, fixtures, windows,
    pipes, glare), and a synthetic one with two lights that touch and a large halo."""
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    real = load_preset(CONFIGS / "lights" / "site.yaml", "realistic")
    traj = straight_drive(4, 30.0, rng=np.random.default_rng(3), speed_mps=3.0, x0_m=1.0,
                          y_m=-1.0, yaw_rad=0.5, weave_m=0.3)
    src = SimSource(rig, site, traj, seed=3, realism=real)
    frames = [src.render(k).image for k in range(4)]
    img = np.full((200, 260), 60, np.uint8)
    cv2.circle(img, (60, 60), 6, 230, -1)
    cv2.circle(img, (74, 62), 5, 220, -1)          # touches the one before
    cv2.circle(img, (170, 120), 45, 120, -1)         # a halo ...
    cv2.circle(img, (170, 120), 8, 250, -1)          # ... around a light
    cv2.circle(img, (2, 150), 6, 230, -1)            # cut by the frame's edge
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    return frames + [cv2.add(img, np.random.default_rng(1).integers(0, 4, img.shape,
                                                                    dtype=np.uint8))]


def test_region_walk_equals_the_array_reading():
    examined = specials = 0
    reasons: set[str] = set()
    for grey, params in itertools.product(_frames(), (SpotParams(), SpotParams(max_area_px=60))):
        if grey.ndim == 3:
            grey = cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY)
        mask = niblack_mask(grey, params.window_px, params.k, params.min_contrast,
                            params.min_contrast_rel)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        boxes = np.array([cv2.boundingRect(c) for c in contours]).reshape(-1, 4)
        specials += int((~ref.boxes_alone(boxes)).sum())
        h, w = grey.shape
        for weighted, rethreshold, centre, most, drop_cut in itertools.product(
                (True, False), (True, False), (None, (w / 2, h / 2)), (None, 3, 48),
                (True, False)):
            got_rej: dict[str, int] = {}
            want_rej: dict[str, int] = {}
            got = _measure_regions(grey, mask, contours, params, weighted, rethreshold,
                                   centre, most, got_rej, drop_cut)
            want = ref.measure_regions(grey, mask, contours, params, weighted, rethreshold,
                                       centre, most, want_rej, drop_cut)
            np.testing.assert_array_equal(got, np.array(want, float).reshape(-1, 8))
            assert got_rej == want_rej
            examined += len(contours)
            reasons |= set(got_rej)
    assert examined > 1000 and specials >= 2
    assert reasons == {"beyond_max_regions", "small", "cut", "large"}
