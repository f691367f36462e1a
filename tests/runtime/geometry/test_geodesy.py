"""W <-> WGS-84 through the local tangent plane: known points, first-order radii, round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ceilkit.runtime.geometry import geodesy
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane

B_M = geodesy.WGS84_A_M * (1.0 - geodesy.WGS84_F)


def test_ecef_of_known_points():
    assert geodesy.ecef_from_geodetic(0.0, 0.0, 0.0) == pytest.approx([geodesy.WGS84_A_M, 0, 0])
    assert geodesy.ecef_from_geodetic(90.0, 0.0, 0.0) == pytest.approx([0, 0, B_M], abs=1e-6)
    assert geodesy.ecef_from_geodetic(0.0, 90.0, 100.0) == pytest.approx(
        [0, geodesy.WGS84_A_M + 100.0, 0], abs=1e-6)


@pytest.mark.parametrize("lat", [-89.5, -33.9, 0.0, 45.0, 52.1, 89.5])
def test_geodetic_of_ecef_inverts(lat):
    for lon, h in [(-179.9, -50.0), (4.3, 12.0), (151.2, 3000.0)]:
        back = geodesy.geodetic_from_ecef(geodesy.ecef_from_geodetic(lat, lon, h))
        assert back[0] == pytest.approx(lat, abs=1e-11)
        assert back[1] == pytest.approx(lon, abs=1e-11)
        assert back[2] == pytest.approx(h, abs=1e-6)


def test_small_offsets_follow_the_meridian_and_prime_vertical_radii():
    lat = 52.1
    plane = LocalTangentPlane(lat, 4.3, 0.0, heading_deg=0.0)  # +x north, +y west
    e2, a = geodesy.WGS84_E2, geodesy.WGS84_A_M
    w = math.sqrt(1 - e2 * math.sin(math.radians(lat)) ** 2)
    m_radius, n_radius = a * (1 - e2) / w**3, a / w
    la, lo, _ = plane.geodetic_from_world(1.0, 0.0)          # 1 m north
    assert math.radians(la - lat) * m_radius == pytest.approx(1.0, rel=1e-6)
    la, lo, _ = plane.geodetic_from_world(0.0, -1.0)         # 1 m east
    assert math.radians(lo - 4.3) * n_radius * math.cos(math.radians(lat)) == pytest.approx(
        1.0, rel=1e-6)


def test_heading_turns_w_on_the_plane():
    plane = LocalTangentPlane(10.0, 20.0, 0.0, heading_deg=90.0)  # +x east, +y north
    enu = plane.R_enu_world @ np.array([1.0, 2.0, 3.0])
    assert enu == pytest.approx([1.0, 2.0, 3.0 * 1.0])
    plane = LocalTangentPlane(10.0, 20.0, 0.0, heading_deg=33.3)
    h = math.radians(33.3)
    assert plane.R_enu_world @ np.array([1.0, 0.0, 0.0]) == pytest.approx(
        [math.sin(h), math.cos(h), 0.0])
    assert plane.heading_from_yaw(math.radians(90.0)) == pytest.approx(303.3)
    assert plane.yaw_from_heading(303.3) == pytest.approx(math.radians(90.0))
    assert plane.heading_from_yaw(math.radians(33.3)) == pytest.approx(0.0, abs=1e-9)


def test_round_trip_over_a_site_is_far_below_a_millimetre():
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(100):
        plane = LocalTangentPlane(float(rng.uniform(-80, 80)), float(rng.uniform(-180, 180)),
                                  float(rng.uniform(-100, 3000)), float(rng.uniform(0, 360)))
        pt = rng.uniform(-1000, 1000, size=3)
        back = plane.world_from_geodetic(*plane.geodetic_from_world(*pt))
        worst = max(worst, float(np.abs(back - pt).max()))
    assert worst < 1e-6


def test_cov_enu_rotates_and_of_reads_an_origin():
    class Origin:
        lat_deg, lon_deg, alt_m, heading_deg = 52.0, 4.0, 1.0, 90.0

    plane = LocalTangentPlane.of(Origin())
    assert plane.cov_enu(np.diag([4.0, 1.0])) == pytest.approx(np.diag([4.0, 1.0]))
    plane = LocalTangentPlane(52.0, 4.0, 0.0, 0.0)  # +x north: x variance is north's
    assert plane.cov_enu(np.diag([4.0, 1.0])) == pytest.approx(np.diag([1.0, 4.0]))


@pytest.mark.parametrize("bad", [(90.0, 0, 0, 0), (0, 181.0, 0, 0), (0, 0, float("nan"), 0),
                                 (0, 0, 0, float("inf"))])
def test_bad_origin_is_refused(bad):
    with pytest.raises(ValueError):
        LocalTangentPlane(*bad)
