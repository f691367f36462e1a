"""The link that streams poses to the vehicle's controller.

* :mod:`.nmea`: ``$PCEIL`` / ``$PCEIS`` proprietary sentences (default, for microcontrollers).
* :mod:`.mavlink`: MAVLink 2 VISION_POSITION_ESTIMATE or ODOMETRY + HEARTBEAT (ArduPilot,
  PX4).
* :mod:`.nmea_gps`: standard GPS sentences (RMC, GGA, GST, HDT) around the site's origin,
  for controllers that take a GPS.
* :mod:`.protocols`: one object per protocol (:func:`make_protocol`) turning estimates
  and the link's health into those messages, and answering the controller.
* :mod:`.transport`: :class:`SerialLink`, :class:`FileLink`, :class:`MemoryLink` (a fake),
  one for every protocol, opened with ``with``.

See ``docs/serial.md`` for the byte layouts, the autopilot settings and the wiring.
"""

from .protocols import (
    PROTOCOLS,
    MavlinkProtocol,
    NmeaGpsProtocol,
    NmeaProtocol,
    Received,
    make_protocol,
)
from .transport import FileLink, LinkBase, LinkCounters, MemoryLink, SerialLink, open_link

__all__ = [
    "PROTOCOLS", "FileLink", "LinkBase", "LinkCounters", "MavlinkProtocol", "MemoryLink",
    "NmeaGpsProtocol", "NmeaProtocol", "Received", "SerialLink", "make_protocol",
    "open_link",
]
