"""The lights method on maps of many lights: the map's indexes (lights/index.py), the
matcher's two votes, and the same poses on the drive's own lights and on 100 000."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.lights import LightsEstimator
from ceilkit.runtime.estimators.lights.estimator import _min_spacing
from ceilkit.runtime.estimators.lights.index import ConstellationIndex, LightGrid, descriptors
from ceilkit.runtime.estimators.lights.matching import PAIR_VOTE_MAX_PAIRS, PatternMatcher
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS


def field(n: int, x0: float, seed: int, pitch: float = 1.6, jitter: float = 0.4
          ) -> np.ndarray:
    """``(n, 2)`` an irregular field: a ``pitch`` grid, each light moved by up to
    ``jitter`` on each axis, from ``(x0, -side pitch / 2)``."""
    side = int(math.ceil(math.sqrt(n)))
    gx, gy = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    g = np.stack([gx.ravel(), gy.ravel()], 1)[:n] * pitch
    g = g + np.random.default_rng(seed).uniform(-jitter, jitter, g.shape)
    return g + np.array([x0, -0.5 * side * pitch])


def seen_from(lights: np.ndarray, x: float, y: float, yaw: float, r: float,
              rng: np.random.Generator, noise_m: float = 0.02) -> np.ndarray:
    """The lights within ``r`` of ``(x, y)`` in V, with noise, nearest first."""
    z = (lights[:, 0] + 1j * lights[:, 1] - complex(x, y)) * complex(math.cos(yaw),
                                                                      -math.sin(yaw))
    z = z[np.argsort(np.abs(z))]
    z = z[np.abs(z) < r]
    return np.stack([z.real, z.imag], 1) + rng.normal(0, noise_m, (z.size, 2))


def test_grid_near_equals_every_light_within_reach():
    rng = np.random.default_rng(2)
    lights = np.concatenate([rng.uniform(-20, 20, (3000, 2)), [[500.0, -300.0]]])
    grid = LightGrid(lights, 3.0)
    for _ in range(200):
        x, y = rng.uniform(-30, 30, 2)
        r = rng.uniform(0.0, 12.0)
        want = np.flatnonzero(np.hypot(lights[:, 0] - x, lights[:, 1] - y) <= r)
        np.testing.assert_array_equal(grid.near(x, y, r), want)
    np.testing.assert_array_equal(grid.near(500.0, -300.0, 0.1), [3000])
    assert grid.near(1e6, 1e6, 5.0).size == 0          # off the grid
    assert LightGrid(np.zeros((0, 2)), 1.0).near(0.0, 0.0, 5.0).size == 0


def test_grid_of_a_huge_extent_keeps_its_keys_in_range():
    lights = np.array([[-1e9, -1e9], [1e9, 1e9], [0.0, 0.0]])
    grid = LightGrid(lights, 0.001)
    assert grid.cell_m > 0.001
    np.testing.assert_array_equal(grid.near(0.0, 0.0, 1.0), [2])


def test_descriptors_move_at_most_twice_the_points():
    """A quad's descriptor is rotation-invariant and Lipschitz: points moved by at most
    ``e`` move no entry by more than ``2 e`` (no ordering flips under noise)."""
    rng = np.random.default_rng(4)
    for _ in range(300):
        p = rng.uniform(-2, 2, (4, 2))
        e = 0.05
        moved = p + rng.uniform(-e / math.sqrt(2), e / math.sqrt(2), p.shape)
        a = rng.uniform(-math.pi, math.pi)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        q = np.arange(4)[None]
        d0, d1 = descriptors(p, q), descriptors(moved @ R.T + rng.uniform(-9, 9, 2), q)
        assert np.all(np.abs(d1 - d0) <= 2 * e + 1e-12)


def test_constellations_find_a_patch_of_a_large_field():
    """A frame's quads hit the map quads of the lights it sees, with up to two of an
    anchor's nearest lights missing from the frame."""
    rng = np.random.default_rng(6)
    lights = field(20000, 0.0, 1)
    index = ConstellationIndex(lights, 0.1)
    assert index.quads.shape == (10 * 20000, 4)
    for trial in range(20):
        k = rng.integers(20000)
        x, y = lights[k] + rng.uniform(-0.5, 0.5, 2)
        yaw = rng.uniform(-math.pi, math.pi)
        near = np.flatnonzero(np.hypot(*(lights - (x, y)).T) < 4.0)
        keep = near[rng.random(near.size) > (0.15 if trial % 2 else 0.0)]
        z = (lights[keep, 0] + 1j * lights[keep, 1] - complex(x, y)) * complex(
            math.cos(yaw), -math.sin(yaw))
        order = np.argsort(np.abs(z))
        q = np.stack([z.real, z.imag], 1)[order] + rng.normal(0, 0.02, (keep.size, 2))
        obs, maps = index.hits(q, np.arange(5))
        true = keep[order]
        right = (true[obs[:, 0]] == maps[:, 0]) & np.all(
            np.sort(true[obs], 1) == np.sort(maps, 1), axis=1)
        assert right.any()
        assert obs.shape[0] < 1000      # chance matches: some in 200 000 quads


def test_grid_verification_equals_all_lights():
    """The lights within reach of a pose give the same candidates as every light
    (the matcher bucketed from 0 lights against the matcher that is not)."""
    rng = np.random.default_rng(5)
    lights = np.concatenate([rng.uniform(0, 12, (80, 2)), field(64, 14.0, 3)])
    every = PatternMatcher(lights, 0.1, 6.0)
    local = PatternMatcher(lights, 0.1, 6.0, index_from=0)
    assert local._grid[0].size > 0 and every._grid[0].size == 0
    n = 0
    for _ in range(40):
        x, y, yaw = rng.uniform(0, 20), rng.uniform(-4, 12), rng.uniform(-math.pi, math.pi)
        q = seen_from(lights, x, y, yaw, 3.0, rng)
        if q.shape[0] < 3:
            continue
        a, b = every.match(q), local.match(q)
        assert len(a) == len(b)
        n += len(a)
        for u, v in zip(a, b, strict=True):
            assert (u.x_m, u.y_m, u.yaw_rad, u.score, u.missing) == (
                v.x_m, v.y_m, v.yaw_rad, v.score, v.missing)
            np.testing.assert_array_equal(u.pairs, v.pairs)
        starts = np.array([[x + 0.05, y - 0.05, yaw + 0.01], [x + 3.0, y, yaw]])
        ta, tb = every.twins(q, starts, 0.2, 3), local.twins(q, starts, 0.2, 3)
        assert [(c.x_m, c.y_m, c.missing) for c in ta] == [(c.x_m, c.y_m, c.missing)
                                                          for c in tb]
    assert n > 30


def test_a_large_map_votes_through_its_constellations():
    """100 000 lights: the constellations vote (no pair table), and a frame of the
    hall finds the pose it finds on the hall's lights alone."""
    rng = np.random.default_rng(8)
    hall = Site.load(CONFIGS / "lights" / "site.yaml").lights_m
    big = np.concatenate([hall, field(100000 - hall.shape[0], 40.0, 2)])
    small_m, big_m = PatternMatcher(hall, 0.1, 12.0), PatternMatcher(big, 0.1, 12.0)
    assert small_m.index is None and big_m.index is not None
    assert big_m.pair_d.size == 0 and PAIR_VOTE_MAX_PAIRS < 25e6
    found = 0
    for _ in range(15):
        x, y, yaw = rng.uniform(2, 16), rng.uniform(-4, 4), rng.uniform(-math.pi, math.pi)
        q = seen_from(hall, x, y, yaw, 6.0, rng)
        a, b = small_m.match(q), big_m.match(q)
        if not a:
            continue
        assert b, (x, y, yaw)
        assert math.hypot(a[0].x_m - b[0].x_m, a[0].y_m - b[0].y_m) < 1e-6
        assert b[0].inliers == a[0].inliers
        found += 1
    assert found >= 12


def test_min_spacing_of_many_lights():
    lights = field(100000, 0.0, 5)
    d = np.sort(np.hypot(*(lights[:2000, None] - lights[None, :2000]).transpose(2, 0, 1))
                .ravel())
    assert _min_spacing(lights) <= d[2000]             # at most the sample's smallest
    assert _min_spacing(np.array([[0.0, 0.0], [3.0, 4.0]])) == 5.0
    assert _min_spacing(np.zeros((1, 2))) == math.inf


@pytest.fixture(scope="module")
def lights_rig() -> Rig:
    return Rig.load(CONFIGS / "lights" / "rig.yaml")


def test_the_same_poses_with_100000_lights(lights_rig):
    """The estimator of the hall's lights and of the hall with 100 000 lights beside it
    (beyond the view) give the same pose, frame after frame."""
    hall = Site.load(CONFIGS / "lights" / "site.yaml")
    big = Site(hall.ceiling_height_m, lights_m=np.concatenate(
        [hall.lights_m, field(100000 - hall.lights_m.shape[0], 32.0, 7)]))
    small_e, big_e = LightsEstimator(lights_rig, hall), LightsEstimator(lights_rig, big)
    assert big_e.matcher.index is not None
    rng = np.random.default_rng(3)
    posed = 0
    for k in range(6):
        x, y, yaw = 3.0 + 2.0 * k, rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi)
        img = render_frame(lights_rig, hall, x, y, yaw,
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8),
                           rng=np.random.default_rng(k))
        a, b = small_e.estimate(img, k), big_e.estimate(img, k)
        assert bool(a) == bool(b)
        if a:
            posed += 1
            assert math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) < 1e-6
            assert abs(a.yaw_rad - b.yaw_rad) < 1e-9
            assert math.hypot(a.x_m - x, a.y_m - y) < 0.02
        else:
            assert a.reason == b.reason
    assert posed >= 4
