"""Wheel odometry from the controller, as increments in V (pure decoders).

Three ways in, all turned into :class:`OdometryIncrement` (the ``odometry.csv`` row of
SPEC §2: the vehicle's displacement ``dx_m, dy_m`` in V and turn ``dyaw_rad`` since
the previous one):

* the NMEA sentence ``$PCEIO,<t_ms>,<dx>,<dy>,<dyaw>*hh`` (:func:`decode_pceio`):
  ``t_ms`` the end of the increment on the localizer's clock (ms, integer), ``dx, dy``
  metres in V, ``dyaw`` degrees counter-clockwise, ``hh`` the XOR checksum;
* MAVLink ``ODOMETRY`` (id 331) from an autopilot: successive poses in its local NED
  frame, differenced into increments (:class:`PoseDifferencer`);
* MAVLink ``WHEEL_DISTANCE`` (id 9000): cumulative distance of each wheel; a
  differential drive's left (``distance[0]``) and right (``distance[1]``) wheels over
  its track width (:class:`DifferentialDrive`).

:class:`OdometryReceiver` is the link's ``on_receive`` hook
(:class:`~ceilkit.runtime.io.link.transport.Received` messages in, increments to a
callback out). Stamps are taken as sent: the controller stamps on the localizer's
clock (``time_usec`` / ``t_ms``), as the poses it receives are stamped.

Example::

    inc = decode_pceio(b"$PCEIO,1200,0.0150,0.0000,0.20*hh")
    print(inc.t_ns, inc.dx_m, inc.dyaw_rad)
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.io.link.mavlink import MavFrame, crc_x25, split_frames
from ceilkit.runtime.io.link.nmea import checksum

TALKER = "PCEIO"
MAX_T_MS = (2**63 - 1) // 1_000_000
"""The latest ``$PCEIO`` stamp, ms: its ns fit a signed 64-bit integer (SPEC's t_ns)."""
MSG_ID_ODOMETRY = 331
MSG_ID_WHEEL_DISTANCE = 9000
CRC_EXTRA_WHEEL_DISTANCE = 113


@dataclass(frozen=True)
class OdometryIncrement:
    """One odometry row: ``t_ns`` its end, ``dx_m, dy_m`` in V, ``dyaw_rad`` CCW."""

    t_ns: int
    dx_m: float
    dy_m: float
    dyaw_rad: float


# ------------------------------------------------------------------------------ NMEA
def encode_pceio(t_ms: int, dx_m: float, dy_m: float, dyaw_deg: float) -> bytes:
    """The ``$PCEIO`` sentence (with ``\\r\\n``): 4 decimals for metres, 3 for degrees.

    >>> encode_pceio(1200, 0.015, 0.0, 0.2)
    b'$PCEIO,1200,0.0150,0.0000,0.200*7B\\r\\n'
    """
    body = f"{TALKER},{int(t_ms)},{dx_m:.4f},{dy_m:.4f},{dyaw_deg:.3f}"
    return f"${body}*{checksum(body)}\r\n".encode("ascii")


def decode_pceio(sentence: bytes | str) -> OdometryIncrement | None:
    """A ``$PCEIO`` sentence as an increment; ``None`` for any other sentence.

    Raises:
        LinkError: a ``$PCEIO`` sentence with a bad checksum, field count or number.
    """
    text = sentence.decode("ascii", "replace") if isinstance(sentence, bytes) else sentence
    text = text.strip()
    if not text.startswith("$" + TALKER + ","):
        return None
    body, star, cs = text[1:].partition("*")
    if not star or cs.upper() != checksum(body):
        raise LinkError(f"$PCEIO: bad checksum in {text!r}")
    parts = body.split(",")
    if len(parts) != 5:
        raise LinkError(f"$PCEIO: expected 4 fields, found {len(parts) - 1} in {text!r}")
    try:
        t_ms = int(parts[1])
        dx, dy, dyaw = (float(v) for v in parts[2:])
    except ValueError:
        raise LinkError(f"$PCEIO: expected numbers, found {text!r}") from None
    if not all(math.isfinite(v) for v in (dx, dy, dyaw)):
        raise LinkError(f"$PCEIO: expected finite numbers, found {text!r}")
    if not 0 <= t_ms <= MAX_T_MS:  # a stamp in ns must fit 64 bits
        raise LinkError(f"$PCEIO: expected a stamp in [0, {MAX_T_MS}] ms, found {text!r}")
    return OdometryIncrement(t_ms * 1_000_000, dx, dy, math.radians(dyaw))


# --------------------------------------------------------------------------- MAVLink
def unpack_odometry_pose(frame: MavFrame) -> tuple[int, float, float, float]:
    """``(t_ns, x_m, y_m, yaw_rad)`` in W of an ODOMETRY frame (NED to W: x north,
    y = -east, yaw = -yaw_ned; payload zero-extended as MAVLink 2 truncates)."""
    p = frame.payload.ljust(233, b"\x00")
    usec, x, y, _z, qw, qx, qy, qz = struct.unpack_from("<Q3f4f", p, 0)
    yaw_ned = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return usec * 1000, float(x), -float(y), wrap_pi(-yaw_ned)


def unpack_wheel_distance(frame: MavFrame) -> tuple[int, tuple[float, ...]]:
    """``(t_ns, distances_m)`` of a WHEEL_DISTANCE frame (``count`` wheels).

    Raises:
        LinkError: a bad CRC (the frame's CRC_EXTRA is 113).
    """
    raw = frame.raw
    if raw and raw[0] == 0xFD:
        end = 10 + raw[1]
        crc = crc_x25(bytes([CRC_EXTRA_WHEEL_DISTANCE]), crc_x25(raw[1:end]))
        if crc != struct.unpack_from("<H", raw, end)[0]:
            raise LinkError("WHEEL_DISTANCE: bad CRC")
    p = frame.payload.ljust(137, b"\x00")
    usec = struct.unpack_from("<Q", p, 0)[0]
    dist = struct.unpack_from("<16d", p, 8)
    count = min(p[136], 16)
    return usec * 1000, tuple(float(d) for d in dist[:count])


class PoseDifferencer:
    """Successive absolute poses (W) into increments in V of the previous pose."""

    def __init__(self) -> None:
        self._last: tuple[int, float, float, float] | None = None

    def add(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float
            ) -> OdometryIncrement | None:
        last, self._last = self._last, (t_ns, x_m, y_m, yaw_rad)
        if last is None or t_ns <= last[0]:
            return None
        dx, dy = x_m - last[1], y_m - last[2]
        c, s = math.cos(last[3]), math.sin(last[3])
        return OdometryIncrement(t_ns, c * dx + s * dy, -s * dx + c * dy,
                                 wrap_pi(yaw_rad - last[3]))


class DifferentialDrive:
    """Cumulative left/right wheel distances (m) into increments (arc model)."""

    def __init__(self, track_m: float):
        if not (math.isfinite(track_m) and track_m > 0):
            raise LinkError(f"the wheel track must be > 0 m, found {track_m!r}")
        self.track_m = track_m
        self._last: tuple[int, float, float] | None = None

    def add(self, t_ns: int, left_m: float, right_m: float) -> OdometryIncrement | None:
        last, self._last = self._last, (t_ns, left_m, right_m)
        if last is None or t_ns <= last[0]:
            return None
        dl, dr = left_m - last[1], right_m - last[2]
        d, dyaw = 0.5 * (dl + dr), (dr - dl) / self.track_m
        # the chord of the arc, at half the turn
        chord = d if abs(dyaw) < 1e-9 else 2.0 * d / dyaw * math.sin(0.5 * dyaw)
        return OdometryIncrement(t_ns, chord * math.cos(0.5 * dyaw),
                                 chord * math.sin(0.5 * dyaw), dyaw)


class OdometryReceiver:
    """The link's ``on_receive`` hook: odometry messages to ``sink(t_ns, dx, dy, dyaw)``.

    Counts ``rows`` delivered, ``refused`` ones (the sink returned ``False``: the
    fusion's bound, ``fusion.plausible_increment``) and ``bad`` messages (a malformed
    ``$PCEIO``, a bad CRC); other messages are ignored. ``track_m``: the wheel track
    for WHEEL_DISTANCE (None: WHEEL_DISTANCE is ignored).
    """

    def __init__(self, sink: Callable[[int, float, float, float], bool | None],
                 track_m: float | None = None):
        self.sink = sink
        self.rows = 0
        self.refused = 0
        self.bad = 0
        self._poses = PoseDifferencer()
        self._wheels = DifferentialDrive(track_m) if track_m is not None else None

    def __call__(self, received) -> None:
        raw: bytes = received.raw
        try:
            for inc in self._decode(raw):
                self.rows += 1
                if self.sink(inc.t_ns, inc.dx_m, inc.dy_m, inc.dyaw_rad) is False:
                    self.refused += 1
        except LinkError:
            self.bad += 1

    def _decode(self, raw: bytes) -> list[OdometryIncrement]:
        if raw.startswith(b"$"):
            inc = decode_pceio(raw)
            return [] if inc is None else [inc]
        out = []
        for frame in split_frames(raw)[0]:
            inc = None
            if frame.msg_id == MSG_ID_ODOMETRY:
                inc = self._poses.add(*unpack_odometry_pose(frame))
            elif frame.msg_id == MSG_ID_WHEEL_DISTANCE and self._wheels is not None:
                t_ns, dist = unpack_wheel_distance(frame)
                if len(dist) >= 2:
                    inc = self._wheels.add(t_ns, dist[0], dist[1])
            if inc is not None:
                out.append(inc)
        return out


__all__ = ["OdometryIncrement", "encode_pceio", "decode_pceio", "unpack_odometry_pose",
           "unpack_wheel_distance", "PoseDifferencer", "DifferentialDrive",
           "OdometryReceiver"]
