"""The link that streams poses to the vehicle's controller.

* :mod:`.nmea`: ``$PCEIL`` / ``$PCEIS`` proprietary sentences (default, for microcontrollers).
* :mod:`.mavlink`: MAVLink 2 VISION_POSITION_ESTIMATE + HEARTBEAT (ArduPilot, PX4).
* :mod:`.transport`: :class:`SerialLink`, :class:`FileLink`, :class:`MemoryLink` (a fake),
  one for both protocols, opened with ``with``.

See ``docs/serial.md`` for the byte layouts, the autopilot settings and the wiring.
"""

from .transport import (
    PROTOCOLS,
    FileLink,
    LinkBase,
    LinkCounters,
    MavlinkProtocol,
    MemoryLink,
    NmeaProtocol,
    Received,
    SerialLink,
    make_protocol,
    open_link,
)

__all__ = [
    "PROTOCOLS", "FileLink", "LinkBase", "LinkCounters", "MavlinkProtocol", "MemoryLink",
    "NmeaProtocol", "Received", "SerialLink", "make_protocol",
    "open_link",
]
