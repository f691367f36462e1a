"""The simulator's ray grids: the same numbers as the camera model's rays, whether the
camera's rays come from the cache or not, and the cache stays within its bytes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim import render as R

LENSES = {
    "pinhole": CameraModel.pinhole(66, 50, 60.0),
    "plumb_bob": CameraModel.pinhole(66, 50, 55.0, dist=[-0.35, 0.12, 0.001, -0.002, 0.0]),
    "equidistant": CameraModel.pinhole(66, 50, 18.0, dist=[0.05, -0.01, 0.002, 0.0],
                                       model="equidistant"),
}


def tilt(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1.0, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


@pytest.mark.parametrize("lens", sorted(LENSES))
@pytest.mark.parametrize("s", [1, 2, 3])
def test_the_samples_rays_are_the_camera_models(lens, s):
    cam = LENSES[lens]
    b = R.CELL_PX * s
    hs, ws = -(-cam.height // R.CELL_PX) * b, -(-cam.width // R.CELL_PX) * b
    u, v = (np.arange(ws) + 0.5) / s - 0.5, (np.arange(hs) + 0.5) / s - 0.5
    rays, ok = R._unit_rays(cam, u, v)
    uu, vv = np.meshgrid(u, v)
    want, want_ok = cam.unit_rays(np.stack([uu.ravel(), vv.ravel()], axis=1), R._REPROJ_TOL_PX)
    want[~cam.in_image(np.stack([uu.ravel(), vv.ravel()], axis=1))] = 0.0
    assert np.array_equal(ok, want_ok) and np.array_equal(rays, want)
    assert not ok.all()         # 66x50 pads to whole cells: samples outside the image
    if lens == "equidistant":
        assert not ok[cam.in_image(np.stack([uu.ravel(), vv.ravel()], axis=1))].all()


@pytest.mark.parametrize("lens", sorted(LENSES))
@pytest.mark.parametrize("s", [2, 3])
def test_a_grid_from_cached_rays_is_the_grid_built_afresh(lens, s):
    cam = LENSES[lens]
    R._RAY_CACHE.clear()
    R._build_grid(cam, tilt(10.0), s)               # leaves the camera's rays cached
    assert (cam, s) in R._RAY_CACHE
    again = R._build_grid(cam, tilt(25.0), s)
    R._RAY_CACHE.clear()
    fresh = R._build_grid(cam, tilt(25.0), s)
    for name, a in vars(fresh).items():
        b = getattr(again, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
        else:
            assert a == b, name


def test_the_caches_keep_within_their_bytes(monkeypatch):
    cam = LENSES["plumb_bob"]
    R._GRID_CACHE.clear()
    R._RAY_CACHE.clear()
    one = R._grid(cam, tilt(0.0), 2)
    size = sum(a.nbytes for a in vars(one).values() if isinstance(a, np.ndarray))
    monkeypatch.setattr(R, "GRID_CACHE_BYTES", int(2.5 * size))
    for deg in (5.0, 10.0, 15.0):
        R._grid(cam, tilt(deg), 2)
    held = sum(a.nbytes for g in R._GRID_CACHE.values() for a in vars(g).values()
               if isinstance(a, np.ndarray))
    held += sum(a.nbytes for v in R._RAY_CACHE.values() for a in v)
    assert held <= 2.5 * size
    assert len(R._GRID_CACHE) == 2 and not R._RAY_CACHE     # the rays went first
    assert R._grid(cam, tilt(15.0), 2) is list(R._GRID_CACHE.values())[-1]
    monkeypatch.setattr(R, "GRID_CACHE_BYTES", 1)
    R._grid(cam, tilt(20.0), 2)
    assert len(R._GRID_CACHE) == 1                          # the newest is kept
