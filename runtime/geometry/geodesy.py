"""Where W lies on the Earth: W <-> WGS-84 through the local tangent plane at W's origin.

Convention (SPEC §2 ``origin: {lat, lon, alt, heading}``): W's origin is at geodetic
latitude ``lat_deg``, longitude ``lon_deg`` (WGS-84, degrees) and height ``alt_m``;
W's +x points along ``heading_deg``, degrees clockwise from true north; W's z is the
local up (the tangent plane's normal, the ellipsoid normal at the origin). So, with
``h = heading``, a point of W in the plane's east-north-up (ENU) axes is::

    east  = x sin h - y cos h        north = x cos h + y sin h        up = z

and a vehicle heading (clockwise from true north) is ``h - yaw_W``.

The plane -> geodetic step is exact (ENU -> ECEF is a rotation and a shift; ECEF ->
geodetic is solved by Newton iterations to far below a micrometre), so a point 1 km
from the origin comes back within 1e-6 m: "flat Earth" formulas are not used.

Example::

    >>> plane = LocalTangentPlane(52.0, 4.0, 0.0, heading_deg=90.0)   # +x points east
    >>> lat, lon, alt = plane.geodetic_from_world(100.0, 0.0, 0.0)
    >>> round(lat, 6), round(lon, 6)
    (52.0, 4.001456)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
NEWTON_STEPS = 6  # ECEF -> geodetic: each step squares the error; 3 already reach 1e-12 m


def ecef_from_geodetic(lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
    """Earth-centred, Earth-fixed ``(3,)`` metres of a WGS-84 point."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    return np.array([(n + h_m) * math.cos(lat) * math.cos(lon),
                     (n + h_m) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - WGS84_E2) + h_m) * math.sin(lat)])


def geodetic_from_ecef(xyz_m: np.ndarray) -> tuple[float, float, float]:
    """``(lat_deg, lon_deg, h_m)`` of an ECEF point (away from the Earth's centre)."""
    x, y, z = (float(v) for v in xyz_m)
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    lat = math.atan2(z, p * (1.0 - WGS84_E2))  # start: the point on the surface
    h = 0.0
    for _ in range(NEWTON_STEPS):
        n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
        h = p / math.cos(lat) - n if abs(lat) < math.pi / 4 else z / math.sin(lat) - n * (
            1.0 - WGS84_E2)
        lat = math.atan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    return math.degrees(lat), math.degrees(lon), h


def R_ecef_enu(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rotation whose columns are east, north, up at a geodetic point, in ECEF."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, -sl * co, cl * co],
                     [co, -sl * so, cl * so],
                     [0.0, cl, sl]])


def wrap_heading_deg(deg: float) -> float:
    """A heading in [0, 360)."""
    out = deg % 360.0
    return 0.0 if out >= 360.0 else out


@dataclass(frozen=True)
class LocalTangentPlane:
    """W placed on the Earth by its origin and the heading of its +x (SPEC §2 ``origin``).

    Attributes:
        lat_deg, lon_deg: W's origin, WGS-84 degrees.
        alt_m: height of W's origin (the floor), metres; used as the plane's height.
        heading_deg: direction of W's +x, degrees clockwise from true north.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    heading_deg: float

    def __post_init__(self) -> None:
        ok = (-90.0 < self.lat_deg < 90.0 and -180.0 <= self.lon_deg <= 180.0
              and math.isfinite(self.alt_m) and abs(self.alt_m) < 1e5
              and math.isfinite(self.heading_deg))
        if not ok:
            raise ValueError(f"origin must be lat in (-90, 90), lon in [-180, 180], a finite "
                             f"alt and heading; found {self.lat_deg}, {self.lon_deg}, "
                             f"{self.alt_m}, {self.heading_deg}")

    @classmethod
    def of(cls, origin: object) -> LocalTangentPlane:
        """The plane of any object with ``lat_deg, lon_deg, alt_m, heading_deg`` (a site's
        ``origin``)."""
        return cls(float(origin.lat_deg), float(origin.lon_deg),  # type: ignore[attr-defined]
                   float(origin.alt_m), float(origin.heading_deg))  # type: ignore[attr-defined]

    @property
    def R_enu_world(self) -> np.ndarray:
        """``(3, 3)``: W coordinates to the plane's east, north, up."""
        h = math.radians(self.heading_deg)
        s, c = math.sin(h), math.cos(h)
        return np.array([[s, -c, 0.0], [c, s, 0.0], [0.0, 0.0, 1.0]])

    def _origin_ecef(self) -> np.ndarray:
        return ecef_from_geodetic(self.lat_deg, self.lon_deg, self.alt_m)

    def geodetic_from_world(self, x_m: float, y_m: float, z_m: float = 0.0
                            ) -> tuple[float, float, float]:
        """``(lat_deg, lon_deg, alt_m)`` of a point of W."""
        enu = self.R_enu_world @ np.array([x_m, y_m, z_m], dtype=float)
        ecef = self._origin_ecef() + R_ecef_enu(self.lat_deg, self.lon_deg) @ enu
        return geodetic_from_ecef(ecef)

    def world_from_geodetic(self, lat_deg: float, lon_deg: float, alt_m: float
                            ) -> np.ndarray:
        """``(3,)`` W coordinates of a WGS-84 point (the inverse of the above)."""
        d = ecef_from_geodetic(lat_deg, lon_deg, alt_m) - self._origin_ecef()
        enu = R_ecef_enu(self.lat_deg, self.lon_deg).T @ d
        return self.R_enu_world.T @ enu

    def heading_from_yaw(self, yaw_rad: float) -> float:
        """True heading (degrees clockwise from north, [0, 360)) of a yaw in W."""
        return wrap_heading_deg(self.heading_deg - math.degrees(yaw_rad))

    def yaw_from_heading(self, heading_deg: float) -> float:
        """Yaw in W (radians, [-pi, pi)) of a true heading."""
        deg = (self.heading_deg - heading_deg + 180.0) % 360.0 - 180.0
        return math.radians(deg)

    def cov_enu(self, cov_xy_world: np.ndarray) -> np.ndarray:
        """``(2, 2)`` covariance in (east, north) of a ``(2, 2)`` one in W's (x, y)."""
        R = self.R_enu_world[:2, :2]
        return R @ np.asarray(cov_xy_world, dtype=float) @ R.T
