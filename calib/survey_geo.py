"""A survey placed on the Earth (issue 39's "the geodetic origin"; SPEC §2 ``origin``):
the first drive's first frame given in WGS-84 (``--anchor-geodetic LAT,LON,HEADING``:
where the vehicle stood, degrees, and its true heading, degrees clockwise from north).

* When the known site has an ``origin`` (W on the Earth), that point is the start pose
  in W (:func:`start_pose_from_geodetic`, through the site's local tangent plane,
  :class:`~ceilkit.runtime.geometry.geodesy.LocalTangentPlane`): the anchor.
* Otherwise the survey's W is the one its other anchor sets (a start pose, markers,
  lights), and the geodetic point places it on the Earth: :func:`origin_from_start`
  gives the ``origin`` that puts the first frame's solved pose on the given point and
  heading (the tangent plane at the start point: at 100 m from it the difference from
  W's own plane is under a millimetre).

Example::

    x, y, yaw = start_pose_from_geodetic(site.origin, (52.0, 4.0, 90.0))
    origin = origin_from_start((52.0, 4.0, 90.0), res.poses[0], alt_m=0.0)
"""

from __future__ import annotations

import math

from ceilkit.runtime.config.site import SiteOrigin
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane, wrap_heading_deg

OPTION = "--anchor-geodetic"


def parse_geodetic(text: str | None) -> tuple[float, float, float] | None:
    """``"LAT,LON,HEADING"`` (degrees) as a tuple; None when not given.

    Raises:
        ConfigError: keyed ``--anchor-geodetic``, for anything but three finite numbers
            with lat in (-90, 90) and lon in [-180, 180].
    """
    if text is None:
        return None
    try:
        lat, lon, heading = (float(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(None, OPTION, f"expected LAT,LON,HEADING (degrees), found "
                          f"{text!r}") from None
    if not (-90 < lat < 90 and -180 <= lon <= 180 and math.isfinite(heading)):
        raise ConfigError(None, OPTION, f"expected lat in (-90, 90), lon in [-180, 180] "
                          f"and a finite heading, found {text!r}")
    return lat, lon, heading


def start_pose_from_geodetic(origin: SiteOrigin, point: tuple[float, float, float]
                             ) -> tuple[float, float, float]:
    """The start pose ``(x, y, yaw rad)`` in W of a vehicle at ``point`` (lat, lon,
    heading degrees), W placed on the Earth by ``origin`` (the floor at its altitude)."""
    plane = LocalTangentPlane.of(origin)
    xyz = plane.world_from_geodetic(point[0], point[1], origin.alt_m)
    return float(xyz[0]), float(xyz[1]), plane.yaw_from_heading(point[2])


def origin_from_start(point: tuple[float, float, float], start_pose_w: tuple[float, ...],
                      alt_m: float = 0.0) -> SiteOrigin:
    """The ``origin`` that puts W's ``start_pose_w`` ``(x, y, yaw rad)`` on ``point``
    (lat, lon, vehicle heading degrees): W's +x heads ``heading + yaw``; W's origin is
    ``-(x, y)`` from the start point along W's axes."""
    x, y, yaw = (float(v) for v in start_pose_w[:3])
    heading = wrap_heading_deg(point[2] + math.degrees(yaw))
    at_start = LocalTangentPlane(point[0], point[1], alt_m, heading)
    lat, lon, _ = at_start.geodetic_from_world(-x, -y, 0.0)
    return SiteOrigin(lat, lon, alt_m, heading)
