"""The link protocols: what goes on the wire for each estimate and once a second, and
what is answered to the controller; :func:`make_protocol` gives one by name
(:data:`PROTOCOLS`). Pure: bytes in, bytes out, no port; the transport
(:mod:`.transport`) writes them.

Each protocol is a :class:`LinkProtocol`: ``pose(est)`` (the message for one estimate),
``periodic(health)`` (the 1 Hz messages given the link's :class:`Health`),
``relocalized()``, ``split_incoming(buffer)`` (whole messages read back) and
``answer(raw, now_ns)`` (replies, e.g. MAVLink TIMESYNC). The byte encodings are those
of :mod:`.nmea`, :mod:`.nmea_gps` and :mod:`.mavlink`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Estimate
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane

from . import mavlink, nmea, nmea_gps

PROTOCOLS = ("nmea", "mavlink", "mavlink-odometry", "nmea-gps")
"""``nmea``: $PCEIL/$PCEIS; ``mavlink``: VISION_POSITION_ESTIMATE; ``mavlink-odometry``:
ODOMETRY instead (needs the rig: it sends the camera's position); ``nmea-gps``: GGA, RMC,
GST and HDT (needs the site's geodetic origin)."""
MAX_FIX_AGE_NS = 10_000_000_000  # an estimate older than this is not of the capture clock


@dataclass(frozen=True)
class Received:
    """One message read back from the controller.

    Attributes:
        t_ns: the link's clock when it was read.
        raw: the message's bytes (an NMEA line without ``\\r\\n``, or a whole MAVLink frame).
        text: a one-line description for logs.
    """

    t_ns: int
    raw: bytes
    text: str


@dataclass(frozen=True)
class Health:
    """What the link knows about the localizer when periodic messages are due."""

    now_ns: int
    faulted: bool
    fault_reason: str
    valid_recently: bool      # a valid pose arrived within the last second (link clock)
    last_reason: str          # the last failure's reason, or no_estimate / stale
    age_ms: int | None        # ms since the last valid pose arrived (link clock)


class LinkProtocol(Protocol):
    """Turns estimates and link health into whole messages (bytes)."""

    name: str

    def pose(self, est: Estimate) -> tuple[bytes | None, bool]:
        """The message for one estimate (``None``: nothing to send) and whether it is a pose."""
        ...

    def periodic(self, health: Health) -> bytes | list[bytes] | None:
        """Whole messages due once a second (none, one, or several)."""
        ...

    def relocalized(self) -> None: ...

    def split_incoming(self, buffer: bytes) -> tuple[list[tuple[bytes, str]], bytes]: ...

    def answer(self, raw: bytes, now_ns: int) -> list[bytes]:
        """Messages to send back for one message read from the controller (may be none)."""
        ...


class _NmeaLines:
    """What both NMEA protocols share: lines read back, no reset counter, no answers."""

    def relocalized(self) -> None:
        """NMEA carries no reset counter: the controller sees the jump in the position."""

    def split_incoming(self, buffer: bytes) -> tuple[list[tuple[bytes, str]], bytes]:
        lines, rest = nmea.split_sentences(buffer)
        return [(ln, ln.decode("ascii", "replace")) for ln in lines], rest

    def answer(self, raw: bytes, now_ns: int) -> list[bytes]:
        return []


class NmeaProtocol(_NmeaLines):
    """``$PCEIL`` per estimate, ``$PCEIS`` once a second while no valid pose (or faulted)."""

    name = "nmea"

    def __init__(self) -> None:
        self.seq = 0

    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) % nmea.SEQ_MODULO
        return s

    def pose(self, est: Estimate) -> tuple[bytes | None, bool]:
        return nmea.encode_pose(est, self._next_seq()), nmea.pose_is_sendable(est)

    def periodic(self, health: Health) -> bytes | None:
        if health.valid_recently and not health.faulted:
            return None
        reason = health.fault_reason if health.faulted else health.last_reason
        return nmea.encode_status(self._next_seq(), health.now_ns // 1_000_000,
                                  faulted=health.faulted, reason=reason, age_ms=health.age_ms)

class NmeaGpsProtocol(_NmeaLines):
    """GPS sentences (RMC, GGA, GST, HDT) per estimate, an invalid group once a second
    while there is no valid pose (or while faulted), as a receiver without a fix does.

    Args:
        plane: where W lies on the Earth (the site's ``origin``).
        utc_ns: the UTC clock (ns) the sentences are stamped with.
        capture_clock_ns: the clock frames are stamped with; a fix is stamped
            ``utc_ns() - (capture_clock_ns() - est.t_ns)`` (its capture time in UTC) when that age
            is within 10 s. Otherwise its stamps are another clock's (a replay, the
            simulator): a fix is stamped ``est.t_ns + offset``, the offset taken from
            ``utc_ns()`` at the first such fix (and again whenever the stamps drift more
            than 10 s from it), so the fixes are as far apart as their frames.
        satellites, hdop: the fixed numbers written in GGA (see :mod:`.nmea_gps`).
    """

    name = "nmea-gps"

    def __init__(self, plane: LocalTangentPlane, *,
                 utc_ns: Callable[[], int] = time.time_ns,
                 capture_clock_ns: Callable[[], int] = time.monotonic_ns,
                 satellites: int = nmea_gps.DEFAULT_SATELLITES,
                 hdop: float = nmea_gps.DEFAULT_HDOP) -> None:
        if not isinstance(plane, LocalTangentPlane):
            raise LinkError("the nmea-gps protocol needs the site's geodetic origin "
                            "(site.yaml origin: {lat, lon, alt, heading})")
        if not 0 <= int(satellites) <= 99 or not 0.0 <= float(hdop) <= 99.9:
            raise LinkError(f"satellites must be in 0..99 and hdop in [0, 99.9], found "
                            f"{satellites}, {hdop}")
        self.plane = plane
        self.utc_ns, self.capture_clock_ns = utc_ns, capture_clock_ns
        self.satellites, self.hdop = int(satellites), float(hdop)
        self._offset_ns: int | None = None   # UTC minus the stamps of another clock

    def _encode(self, fix: nmea_gps.GpsFix, utc: int) -> bytes:
        return nmea_gps.encode_fix(fix, utc, satellites=self.satellites, hdop=self.hdop)

    def pose(self, est: Estimate) -> tuple[bytes | None, bool]:
        fix = nmea_gps.fix_of(est, self.plane)
        age = self.capture_clock_ns() - est.t_ns
        now = self.utc_ns()
        if 0 <= age <= MAX_FIX_AGE_NS:
            return self._encode(fix, now - age), fix.valid
        if self._offset_ns is None or abs(est.t_ns + self._offset_ns - now) > MAX_FIX_AGE_NS:
            self._offset_ns = now - est.t_ns
        return self._encode(fix, est.t_ns + self._offset_ns), fix.valid

    def periodic(self, health: Health) -> bytes | None:
        if health.valid_recently and not health.faulted:
            return None
        return self._encode(nmea_gps.GpsFix(health.now_ns, None, None, None, None, None),
                            self.utc_ns())

class MavlinkProtocol:
    """VISION_POSITION_ESTIMATE (or ODOMETRY) per pose, HEARTBEAT once a second unless
    faulted.

    Args:
        sysid, compid: the sender's ids (default 1 and 197, MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
        settings: how poses map to the message (z and roll/pitch variance, the
            policy for a pose missing x or y).
        origin: an EKF origin to send as SET_GPS_GLOBAL_ORIGIN once a second (with the
            HEARTBEAT) until the autopilot reports GPS_GLOBAL_ORIGIN; ``None`` (default):
            never sent.
        answer_timesync: answer TIMESYNC requests (``tc1 = 0``) with the link's clock in
            ns, the clock poses are stamped with (PX4 maps the stamps through it).
        odometry: send ODOMETRY (with these settings) instead of VISION_POSITION_ESTIMATE;
            the protocol is then named ``mavlink-odometry``. ``None`` (default): VPE.

    Attributes:
        timesyncs: TIMESYNC requests answered.
        origin_acknowledged: the autopilot reported its GPS_GLOBAL_ORIGIN.
        autopilot_sysid: the system id of the last autopilot HEARTBEAT heard (or ``None``).
    """

    name = "mavlink"

    def __init__(self, sysid: int = 1, compid: int = mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                 settings: mavlink.VisionSettings | None = None,
                 origin: mavlink.GeoOrigin | None = None, answer_timesync: bool = True,
                 odometry: mavlink.OdometrySettings | None = None) -> None:
        if not 1 <= int(sysid) <= 255:
            raise LinkError(f"MAVLink system id must be in 1..255, found {sysid}")
        if not 0 <= int(compid) <= 255:
            raise LinkError(f"MAVLink component id must be in 0..255, found {compid}")
        self.sysid, self.compid = int(sysid), int(compid)
        self.settings = settings or mavlink.VisionSettings()
        self.odometry = odometry
        if odometry is not None:
            self.name = "mavlink-odometry"
        self.origin = origin
        self.answer_timesync = answer_timesync
        self.seq = 0
        self.reset_counter = 0
        self.timesyncs = 0
        self.origin_acknowledged = False
        self.autopilot_sysid: int | None = None

    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) % 256
        return s

    def pose(self, est: Estimate) -> tuple[bytes | None, bool]:
        # the sequence number is only spent on a message that is sent
        if self.odometry is not None:
            msg = mavlink.odometry_message(est, self.seq, self.reset_counter, sysid=self.sysid,
                                           compid=self.compid, settings=self.odometry)
        else:
            msg = mavlink.pose_message(est, self.seq, self.reset_counter, sysid=self.sysid,
                                       compid=self.compid, settings=self.settings)
        if msg is not None:
            self._next_seq()
        return msg, msg is not None

    def periodic(self, health: Health) -> bytes | list[bytes] | None:
        if health.faulted:
            return None
        status = mavlink.MAV_STATE_ACTIVE if health.valid_recently else mavlink.MAV_STATE_STANDBY
        beat = mavlink.encode_heartbeat(self._next_seq(), self.sysid, self.compid, status)
        if self.origin is None or self.origin_acknowledged:
            return beat
        target = self.autopilot_sysid or 0
        return [beat, mavlink.encode_set_gps_global_origin(
            self.origin, target, self._next_seq(), self.sysid, self.compid)]

    def relocalized(self) -> None:
        self.reset_counter = (self.reset_counter + 1) % 256

    def split_incoming(self, buffer: bytes) -> tuple[list[tuple[bytes, str]], bytes]:
        frames, rest = mavlink.split_frames(buffer)
        return [(f.raw, mavlink.describe_frame(f)) for f in frames], rest

    def answer(self, raw: bytes, now_ns: int) -> list[bytes]:
        frames, _ = mavlink.split_frames(raw)
        out: list[bytes] = []
        for f in frames:
            if f.msg_id == mavlink.MSG_ID_HEARTBEAT:
                p = f.payload.ljust(9, b"\x00")
                if p[5] != mavlink.MAV_AUTOPILOT_INVALID:  # an autopilot, not a GCS/companion
                    self.autopilot_sysid = f.sysid
            elif f.msg_id == mavlink.MSG_ID_GPS_GLOBAL_ORIGIN:
                self.origin_acknowledged = True
            elif f.msg_id == mavlink.MSG_ID_TIMESYNC and self.answer_timesync:
                tc1, ts1 = mavlink.unpack_timesync(f)
                if tc1 == 0:  # a request; tc1 != 0 is an answer to someone else
                    self.timesyncs += 1
                    out.append(mavlink.encode_timesync(now_ns, ts1, self._next_seq(),
                                                       self.sysid, self.compid))
        return out


def make_protocol(protocol: str | LinkProtocol, **options) -> LinkProtocol:
    """A protocol object from its name (one of :data:`PROTOCOLS`) or one given as is.

    ``mavlink-odometry`` is ``mavlink`` with ``odometry=`` (default settings unless
    given); ``nmea-gps`` needs ``plane=`` (a
    :class:`~ceilkit.runtime.geometry.geodesy.LocalTangentPlane`).
    """
    if not isinstance(protocol, str):
        return protocol
    if protocol == "nmea":
        if options:
            raise LinkError(f"the nmea protocol takes no options, found {sorted(options)}")
        return NmeaProtocol()
    if protocol == "mavlink":
        return MavlinkProtocol(**options)
    if protocol == "mavlink-odometry":
        options.setdefault("odometry", mavlink.OdometrySettings())
        return MavlinkProtocol(**options)
    if protocol == "nmea-gps":
        plane = options.pop("plane", None)
        return NmeaGpsProtocol(plane, **options)
    raise LinkError(f"unknown link protocol {protocol!r} (choose from {', '.join(PROTOCOLS)})")
