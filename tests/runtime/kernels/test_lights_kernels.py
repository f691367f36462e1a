"""The lights method's compiled loops against the array code they stand for
(tests/lights_reference.py): the same numbers on spots spread over the frame, its
edges, below the horizon and of every size and shape."""

from __future__ import annotations

import math

import lights_reference as ref
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.estimators.lights.observe import SpotObserver, examine_core
from ceilkit.runtime.estimators.lights.rays import view_mask
from ceilkit.runtime.features.spots import SpotParams, rows_to_spots
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.jit import arr
from helpers import CONFIGS


def _rigs() -> list[Rig]:
    return [Rig.load(CONFIGS / "lights" / "rig.yaml"),
            Rig(CameraModel.pinhole(320, 240, 160.0, dist=[-0.2, 0.04, 0.0, 0.0, 0.0]),
                Mount(pan_rad=0.4, tilt_rad=math.radians(70), swing_rad=0.1,
                      x_m=0.3, y_m=-0.1, z_m=0.8)),
            Rig(CameraModel(320, 240, np.array([[90.0, 0, 160], [0, 90.0, 120], [0, 0, 1]]),
                            np.array([0.05, -0.01, 0.0, 0.0]), "equidistant"),
                Mount(z_m=0.5)),
            # tilted past the horizon: part of the frame sees no ceiling
            Rig(CameraModel.pinhole(320, 240, 200.0), Mount(tilt_rad=math.radians(15),
                                                            z_m=0.5))]


def _spots(observer: SpotObserver, rng: np.random.Generator, n: int):
    """Spots over (and a little beyond) the frame, their areas and moments around the
    predicted ones at their place, some far off."""
    cam = observer.rig.camera
    cen = rng.uniform([-3, -3], [cam.width + 2, cam.height + 2], (n, 2))
    tab = observer.grid(cen)
    a_pred = np.nan_to_num(tab[:, 7], nan=20.0)
    area = a_pred * rng.choice([0.1, 0.5, 1.0, 1.5, 6.0], n) + rng.normal(0, 2, n)
    s = np.sqrt(np.maximum(area, 1.0) / math.pi) / 2
    ratio = rng.choice([1.0, 0.8, 0.1], n)
    th = rng.uniform(0, math.pi, n)
    c, si = np.cos(th), np.sin(th)
    l1, l2 = s * s, (s * ratio) ** 2
    rows = np.column_stack([cen, rng.uniform(100, 250, n), rng.uniform(20, 90, n),
                            c * c * l1 + si * si * l2, c * si * (l1 - l2),
                            si * si * l1 + c * c * l2, area])
    return rows_to_spots(rows, n)


@pytest.mark.parametrize("radius_m", [0.08, 0.0])
def test_examination_equals_the_array_reading(radius_m):
    rng = np.random.default_rng(11)
    checked = kept = 0
    for rig in _rigs():
        observer = SpotObserver(rig, 3.0, radius_m, SpotParams(),
                                view_mask(rig, math.radians(80.0)), (rig.camera.cx,
                                                                     rig.camera.cy), 12)
        for _ in range(20):
            spots = _spots(observer, rng, 40)
            q, ok, table = examine_core(arr(spots.centroids_px, np.float64),
                                        arr(spots.areas_px, np.float64),
                                        arr(spots.cov_px, np.float64), observer.grid_arrays,
                                        observer.mount, observer.checks)
            q_ref, ok_ref, table_ref = ref.examine(observer, spots)
            np.testing.assert_array_equal(ok, ok_ref)
            np.testing.assert_allclose(table, table_ref, rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(np.isnan(q), np.isnan(q_ref))
            np.testing.assert_allclose(q, q_ref, rtol=1e-12, atol=1e-12)
            checked += len(spots)
            kept += int(ok.sum())
    # both answers occur, often
    assert 0.2 * checked < kept < checked


def _layouts(rng: np.random.Generator):
    """Light maps: a regular grid (many equally good poses), a jittered grid, a random
    scatter, a corridor's two rows."""
    g = np.arange(6) * 2.0
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    yield grid
    yield grid + rng.normal(0, 0.15, grid.shape)
    yield rng.uniform(0, 12, (40, 2))
    xs = np.cumsum(rng.uniform(0.5, 1.4, 30))
    yield np.stack([xs, rng.choice([-1, 1], xs.size) * rng.uniform(0.55, 1.05, xs.size)], 1)


def _same_candidates(got, want) -> None:
    """The same candidates; those of equal score and rms (a symmetric layout's poses,
    whose order is the rounding's) in any order."""
    def canonical(cands):
        return sorted(cands, key=lambda c: (-c.score, -c.inliers, round(c.rms_m, 9),
                                            round(c.x_m, 6), round(c.y_m, 6)))

    assert len(got) == len(want)
    for g, w in zip(canonical(got), canonical(want), strict=True):
        np.testing.assert_allclose([g.x_m, g.y_m, g.yaw_rad, g.rms_m],
                                   [w.x_m, w.y_m, w.yaw_rad, w.rms_m], rtol=0, atol=1e-9)
        assert (g.score, g.missing) == (w.score, w.missing)
        np.testing.assert_array_equal(g.pairs, w.pairs)


@pytest.mark.parametrize("with_visibility", [True, False])
def test_pattern_matcher_equals_the_array_reading(with_visibility):
    """Candidates, hypotheses, associations and verifications of the compiled matcher
    against the array matcher it replaced, on observations with noise, outliers and
    missed lights, ambiguous layouts included."""
    from ceilkit.runtime.estimators.lights.matching import PatternMatcher
    from ceilkit.runtime.estimators.lights.observe import VisibilityTable

    rng = np.random.default_rng(5)
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    mask = view_mask(rig, math.radians(75.0))
    n_cands = n_ambiguous = 0
    for lights in _layouts(rng):
        vis = (VisibilityTable(rig, 3.0, lights, mask, (rig.camera.cx, rig.camera.cy), 12)
               if with_visibility else None)
        got_m = PatternMatcher(lights, 0.1, 6.0, visible=vis)
        want_m = ref.ArrayMatcher(lights, 0.1, 6.0, visible=vis)
        for _ in range(15):
            x, y, yaw = rng.uniform(1, 10), rng.uniform(-1, 10), rng.uniform(-math.pi, math.pi)
            z = (lights[:, 0] + 1j * lights[:, 1] - complex(x, y)) * complex(
                math.cos(yaw), -math.sin(yaw))
            near = np.flatnonzero(np.abs(z) < 3.0)
            seen = near[rng.random(near.size) < 0.85]
            q = np.stack([z[seen].real, z[seen].imag], 1) + rng.normal(0, 0.02, (seen.size, 2))
            q = np.concatenate([q, rng.uniform(-3, 3, (rng.integers(0, 3), 2))])
            order = rng.permutation(q.shape[0])
            got, want = got_m.match(q, order), want_m.match(q, order)
            _same_candidates(got, want)
            n_cands += len(got)
            n_ambiguous += len(got) > 1 and got[1].score >= got[0].score - 1
            if q.shape[0] < 2:
                continue
            np.testing.assert_allclose(got_m.hypotheses(q), want_m.hypotheses(q),
                                       rtol=0, atol=1e-9)
            for gate in (0.1, 0.5):
                t = np.array([x, y]) + rng.normal(0, 0.05, 2)
                np.testing.assert_array_equal(got_m.associate(q, yaw, t, gate),
                                              want_m.associate(q, yaw, t, gate))
                g, w = got_m.verify(q, yaw, t, gate), want_m.verify(q, yaw, t, gate)
                assert (g is None) == (w is None)
                if g is not None:
                    _same_candidates([g], [w])
    assert n_cands > 60 and n_ambiguous > 5       # many candidates, rivals among them



def _abs_association(qc, rot, t, lights_c, gate):  # pragma: no cover - compiled
    """The association as the compiled loop read it before it compared squared
    distances: every distance by ``abs``, ``np.argmin`` per row (the first of equal
    ones), the first smallest per column."""
    n, m = qc.size, lights_c.size
    d = np.empty((n, m))
    for i in range(n):
        p = qc[i] * rot + t
        for j in range(m):
            d[i, j] = abs(p - lights_c[j])
    out = np.empty((n, 2), np.int64)
    k = 0
    for i in range(n):
        if m == 0:
            break
        j = np.argmin(d[i])
        if not d[i, j] < gate:
            continue
        best = 0
        for r in range(1, n):
            if d[r, j] < d[best, j]:
                best = r
        if best == i:
            out[k, 0], out[k, 1] = i, j
            k += 1
    return out[:k].copy()


def test_association_ties_equal_the_abs_reading():
    """Points midway between lights of a grid (equal distances to two or four of them),
    repeated observations, points a rounding apart, and a random scatter: the compiled
    association (squared distances, ``abs`` near a tie) pairs them as the loop reading
    every distance by ``abs`` does (compiled too: numba's ``abs`` of a complex number
    and numpy's may round a tie apart differently, so the array reading is no
    reference on exact ties)."""
    import numba

    from ceilkit.runtime.estimators.lights.matching import _associate

    want_f = numba.njit(_abs_association)
    rng = np.random.default_rng(9)
    g = np.arange(5) * 1.2
    grid = np.stack(np.meshgrid(g, g * 2.0), -1).reshape(-1, 2)
    pairs = 0
    for trial in range(600):
        if trial % 2:
            lights = grid[:, 0] + 1j * grid[:, 1]
            q = rng.integers(0, 9, 8) * 0.6 + 1j * rng.integers(0, 9, 8) * 1.2
            q = np.concatenate([q, q[:2], q[2:3] + 1e-15])
        else:
            lights = rng.uniform(0, 6, 30) + 1j * rng.uniform(0, 6, 30)
            q = lights[rng.integers(0, 30, 10)] + rng.normal(0, 0.03, 10)
        for yaw, gate in ((0.0, 0.7), (0.0, 0.61), (math.pi / 2, 10.0), (0.3, 0.1)):
            rot = complex(math.cos(yaw), math.sin(yaw))
            want = want_f(q, rot, 0j, lights, gate)
            np.testing.assert_array_equal(_associate(q, rot, 0j, lights, gate), want)
            pairs += want.shape[0]
    assert pairs > 2000


def test_visibility_lookup_equals_the_array_reading():
    from ceilkit.runtime.estimators.lights.observe import VisibilityTable

    rng = np.random.default_rng(8)
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    lights = rng.uniform(0, 12, (60, 2))
    for max_spots in (4, 12, 100):
        vis = VisibilityTable(rig, 3.0, lights, view_mask(rig, math.radians(75.0)),
                              (rig.camera.cx, rig.camera.cy), max_spots, 0.08)
        seen = 0
        for _ in range(50):
            pose = rng.uniform(-2, 14), rng.uniform(-2, 14), rng.uniform(-4, 4)
            ok, cell, z = vis.locate(*pose)
            ok_r, cell_r, z_r = ref.locate(vis, *pose)
            np.testing.assert_array_equal(ok, ok_r)
            np.testing.assert_array_equal(cell, cell_r)
            np.testing.assert_allclose(z, z_r, rtol=0, atol=1e-12)
            seen += int(ok.sum())
        assert seen > 50
