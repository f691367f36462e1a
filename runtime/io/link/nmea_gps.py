"""A GPS receiver's NMEA 0183 stream of the pose, for controllers that take a GPS.

Pure, byte-exact encoders; the port handling is in :mod:`.transport` (protocol
``nmea-gps``). Each estimate becomes one group of four standard sentences, in the order
a receiver sends them (talker ``GP``, each at most 82 characters with ``\\r\\n``)::

    $GPRMC,<hhmmss.ss>,<A|V>,<ddmm.mmmmmmm>,<N|S>,<dddmm.mmmmmmm>,<E|W>,,,<ddmmyy>,,,<A|N>*hh
    $GPGGA,<hhmmss.ss>,<lat>,<N|S>,<lon>,<E|W>,<1|0>,<sats>,<hdop>,<alt>,M,,M,,*hh
    $GPGST,<hhmmss.ss>,,<semi-major>,<semi-minor>,<orient>,<sigma lat>,<sigma lon>,*hh
    $GPHDT,<heading>,T*hh

* **Position**: the vehicle's reference point (V's origin, SPEC §1) placed on WGS-84 by
  the site's origin (SPEC §2 ``origin``) through the local tangent plane
  (:class:`~ceilkit.runtime.geometry.geodesy.LocalTangentPlane`, exact to far below a
  millimetre); latitude and longitude with 7 decimals of minutes (<= 0.1 mm of
  rounding). ``alt`` is the point's height (the floor: the site's ``alt``), 3 decimals;
  the geoid separation is left empty.
* **Valid only when measured**: a pose with x and y gives ``A`` / fix quality 1; a
  failure or a pose missing x or y (the corridor method) gives ``V`` / quality 0 with
  every position field empty: never a stale position marked valid.
* **Heading** (``HDT``): true heading of the vehicle, degrees clockwise from north,
  3 decimals, ``heading - yaw_W``; empty when there is no yaw (a failure). A corridor
  pose still has one.
* **Error ellipse** (``GST``): 1-sigma semi-major and semi-minor axes (m), the
  major axis's orientation (degrees from true north, [0, 180)), and the 1-sigma
  latitude and longitude errors (m), from the pose covariance rotated into east/north;
  empty fields where there is no position or no covariance. The RMS and altitude
  fields are empty (not measured).
* ``sats`` and ``hdop`` are fixed numbers (12 and 1.0 by default, 00 and empty without
  a fix): a controller that gates on them accepts the fix; ``GST`` carries the accuracy.
* Speed and course over ground (``RMC``) are empty: one estimate has no velocity.

Example::

    >>> from ceilkit.runtime.geometry.geodesy import LocalTangentPlane
    >>> plane = LocalTangentPlane(52.0, 4.0, 10.0, heading_deg=0.0)
    >>> est = PoseEstimate(t_ns=0, method="lights", x_m=0.0, y_m=0.0, yaw_rad=0.0,
    ...                    quality=0.9)
    >>> encode_fix(fix_of(est, plane), utc_ns=1_700_000_000_000_000_000).split(b"\\r\\n")[3]
    b'$GPHDT,0.000,T*06'
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane

from .nmea import MAX_SENTENCE_LEN, checksum

TALKER = "GP"
MINUTE_DECIMALS = 7
HEADING_DECIMALS = 3
SIGMA_DECIMALS = 4
DEFAULT_SATELLITES = 12
DEFAULT_HDOP = 1.0
FIX_GPS = 1
FIX_NONE = 0


@dataclass(frozen=True)
class Ellipse:
    """1-sigma horizontal error: axes (m), major axis from true north (deg), lat/lon (m)."""

    semi_major_m: float
    semi_minor_m: float
    orientation_deg: float
    sigma_lat_m: float
    sigma_lon_m: float


@dataclass(frozen=True)
class GpsFix:
    """What one estimate says in GPS terms; ``None`` fields are not known.

    Attributes:
        t_ns: the estimate's capture time.
        lat_deg, lon_deg, alt_m: the position, or ``None`` (no fix).
        heading_deg: true heading in [0, 360), or ``None``.
        ellipse: the error ellipse, or ``None``.
    """

    t_ns: int
    lat_deg: float | None
    lon_deg: float | None
    alt_m: float | None
    heading_deg: float | None
    ellipse: Ellipse | None

    @property
    def valid(self) -> bool:
        return self.lat_deg is not None


def ellipse_of(cov_en_m2: np.ndarray) -> Ellipse | None:
    """The error ellipse of a ``(2, 2)`` covariance in (east, north), m²; ``None`` if unusable.

    >>> e = ellipse_of(np.array([[4.0, 0.0], [0.0, 1.0]]))
    >>> e.semi_major_m, e.semi_minor_m, e.orientation_deg
    (2.0, 1.0, 90.0)
    """
    c = np.asarray(cov_en_m2, dtype=float)
    if not np.all(np.isfinite(c)):
        return None
    c = 0.5 * (c + c.T)
    vals, vecs = np.linalg.eigh(c)  # ascending
    if vals[0] < 0.0 and vals[0] < -1e-12 * max(1.0, abs(vals[1])):
        return None
    major = vecs[:, 1]
    orient = math.degrees(math.atan2(major[0], major[1])) % 180.0
    if round(orient, SIGMA_DECIMALS) >= 180.0:
        orient = 0.0
    return Ellipse(math.sqrt(max(vals[1], 0.0)), math.sqrt(max(vals[0], 0.0)), orient,
                   math.sqrt(max(c[1, 1], 0.0)), math.sqrt(max(c[0, 0], 0.0)))


def fix_of(est: Estimate, plane: LocalTangentPlane) -> GpsFix:
    """The GPS view of one estimate: a position only when x and y are both measured."""
    if not isinstance(est, PoseEstimate) or not math.isfinite(est.yaw_rad):
        return GpsFix(est.t_ns, None, None, None, None, None)
    heading = plane.heading_from_yaw(est.yaw_rad)
    xy = (est.x_m, est.y_m)
    if any(v is None or not math.isfinite(v) for v in xy):
        return GpsFix(est.t_ns, None, None, None, heading, None)
    lat, lon, alt = plane.geodetic_from_world(float(est.x_m), float(est.y_m), 0.0)
    ellipse = None
    if est.cov is not None:
        ellipse = ellipse_of(plane.cov_enu(np.asarray(est.cov, dtype=float)[:2, :2]))
    return GpsFix(est.t_ns, lat, lon, alt, heading, ellipse)


# -------------------------------------------------------------------------- sentences


def _angle(value_deg: float, degree_digits: int, hemispheres: str) -> tuple[str, str]:
    """``(d..dmm.mmmmmmm, hemisphere)`` with the minutes rounded once, in integers."""
    scale = 10**MINUTE_DECIMALS
    total = round(abs(value_deg) * 60 * scale)
    degrees, rest = divmod(total, 60 * scale)
    minutes, frac = divmod(rest, scale)
    text = f"{degrees:0{degree_digits}d}{minutes:02d}.{frac:0{MINUTE_DECIMALS}d}"
    return text, hemispheres[0] if value_deg >= 0 else hemispheres[1]


def _utc(utc_ns: int) -> tuple[str, str]:
    """``(hhmmss.ss, ddmmyy)`` of a UTC time in ns (centiseconds, truncated)."""
    cs = utc_ns // 10_000_000
    day = datetime.fromtimestamp(cs // 100, tz=timezone.utc)
    return f"{day:%H%M%S}.{cs % 100:02d}", f"{day:%d%m%y}"


def _sentence(body: str) -> bytes:
    out = f"${body}*{checksum(body)}\r\n".encode("ascii")
    if len(out) > MAX_SENTENCE_LEN:  # bounded by the formats; a guard, not a check
        raise ValueError(f"NMEA sentence of {len(out)} characters exceeds {MAX_SENTENCE_LEN}")
    return out


def _sigma(v: float) -> str:
    return f"{min(v, 99999.0):.{SIGMA_DECIMALS}f}"


def encode_fix(fix: GpsFix, utc_ns: int, *, satellites: int = DEFAULT_SATELLITES,
               hdop: float = DEFAULT_HDOP) -> bytes:
    """The ``RMC``, ``GGA``, ``GST`` and ``HDT`` sentences of one fix, stamped ``utc_ns``."""
    hms, dmy = _utc(utc_ns)
    if fix.valid:
        lat, ns = _angle(float(fix.lat_deg), 2, "NS")
        lon, ew = _angle(float(fix.lon_deg), 3, "EW")
        pos = f"{lat},{ns},{lon},{ew}"
        rmc = f"{TALKER}RMC,{hms},A,{pos},,,{dmy},,,A"
        gga = (f"{TALKER}GGA,{hms},{pos},{FIX_GPS},{satellites:02d},{hdop:.1f},"
               f"{fix.alt_m:.3f},M,,M,,")
    else:
        rmc = f"{TALKER}RMC,{hms},V,,,,,,,{dmy},,,N"
        gga = f"{TALKER}GGA,{hms},,,,,{FIX_NONE},00,,,M,,M,,"
    e = fix.ellipse if fix.valid else None
    if e is None:
        gst = f"{TALKER}GST,{hms},,,,,,,"
    else:
        gst = (f"{TALKER}GST,{hms},,{_sigma(e.semi_major_m)},{_sigma(e.semi_minor_m)},"
               f"{e.orientation_deg:.{SIGMA_DECIMALS}f},{_sigma(e.sigma_lat_m)},"
               f"{_sigma(e.sigma_lon_m)},")
    heading = "" if fix.heading_deg is None else f"{fix.heading_deg:.{HEADING_DECIMALS}f}"
    if heading == f"{360.0:.{HEADING_DECIMALS}f}":
        heading = f"{0.0:.{HEADING_DECIMALS}f}"
    hdt = f"{TALKER}HDT,{heading},T"
    return b"".join(_sentence(s) for s in (rmc, gga, gst, hdt))
