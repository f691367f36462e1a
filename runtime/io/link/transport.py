"""Carry encoded poses to the vehicle's controller: a serial port, a file, or a fake.

One transport for every protocol (:data:`PROTOCOLS`: ``nmea``, ``mavlink``,
``mavlink-odometry``, ``nmea-gps``). The pipeline calls,
from its loop::

    with SerialLink("/dev/ttyUSB0", 115200, "nmea") as link:
        for est in estimates:
            link.send(est)          # never blocks
            if jumped:
                link.relocalized()  # MAVLink reset_counter += 1
        ...
        link.set_fault("camera_lost")   # stops HEARTBEAT, sends PCEIS state F

Guarantees:

* **Never blocks.** The port is opened non-blocking (``O_NONBLOCK``, pyserial
  ``write_timeout=0``); each call writes what the driver takes now and keeps the rest
  in a bounded buffer (``max_buffer_bytes``).
* **No torn frames.** A message that was partly written is completed before any other
  byte goes out. When the peer is backed up, whole messages that have not started are
  dropped, oldest first (stale poses), and counted. Only an unplug can cut a message.
* **Unplug is a state, not an error.** After a successful start, a write or read
  error closes the port, ``state`` becomes ``"disconnected"``, poses are dropped
  (counted) and the port is reopened with exponential back-off
  (``backoff_s = (first, max)``), and at once when a port that was gone is there
  again (a serial port's device node, a socat link: :meth:`LinkBase._reappeared`);
  ``counters.lost`` and ``counters.reconnects`` count both, and each is one line on
  the ``ceilkit.link`` log (``lost (why)``, ``back after 2.3 s``).
  Opening the port the user named fails with :class:`LinkError`, one line.
* **Periodic messages.** ``poll()`` (called by ``send()``, by the pipeline, and by an
  optional service thread every ``service_interval_s``) sends the 1 Hz HEARTBEAT
  (MAVLink, not while faulted) or the 1 Hz ``$PCEIS`` status (NMEA, while there has
  been no valid pose for 1 s, or while faulted), and reads what the controller sends
  back: each message goes to ``on_receive`` and, as a line, to ``rx_log``. With a
  service thread (a serial port's default: it wakes as soon as input arrives), reading
  back is left to it: ``send()`` only encodes and writes.

Times: ``clock_ns`` (default ``time.monotonic_ns``, the clock frames are stamped
with) drives the periodic messages and the back-off; poses carry their own
capture time.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import stat
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Estimate, Failure
from ceilkit.runtime.geometry.geodesy import LocalTangentPlane

from . import mavlink
from .outbox import Outbox
from .protocols import (  # noqa: F401 - PROTOCOLS and the protocols: importable from here too
    PROTOCOLS,
    Health,
    LinkProtocol,
    MavlinkProtocol,
    NmeaGpsProtocol,
    NmeaProtocol,
    Received,
    make_protocol,
)

log = logging.getLogger("ceilkit.link")

PERIOD_NS = 1_000_000_000
MAX_RX_PENDING = 4096


# ------------------------------------------------------------------------ the link


@dataclass(frozen=True)
class LinkCounters:
    """Counts since the link was opened.

    Attributes:
        sent: whole messages written (poses and periodic ones).
        dropped: messages discarded: buffer full (peer backed up) or port unplugged.
        skipped: estimates the protocol had nothing to send for (MAVLink: a failure,
            a pose missing x with the ``skip`` policy).
        reconnects: successful reopenings after an unplug.
        bytes_sent: bytes written.
        received: messages read back from the controller.
        lost: times the port went away (an unplug, the peer gone).
    """

    sent: int = 0
    dropped: int = 0
    skipped: int = 0
    reconnects: int = 0
    bytes_sent: int = 0
    received: int = 0
    lost: int = 0


class _Disconnected(Exception):
    """The port went away (internal)."""


class LinkBase:
    """The state machine shared by every link; subclasses provide the port hooks.

    What waits to be written (framing, the bound, stall reports) is its :class:`Outbox`.
    """

    def __init__(self, protocol: str | LinkProtocol = "nmea", *, max_buffer_bytes: int = 1024,
                 on_receive: Callable[[Received], None] | None = None,
                 rx_log: str | Path | None = None, clock_ns: Callable[[], int] = time.monotonic_ns,
                 backoff_s: tuple[float, float] = (0.5, 8.0),
                 service_interval_s: float | None = None, **protocol_options) -> None:
        self.protocol = make_protocol(protocol, **protocol_options)
        if max_buffer_bytes < 256:
            raise LinkError(f"max_buffer_bytes must be at least 256, found {max_buffer_bytes}")
        if not 0 < backoff_s[0] <= backoff_s[1]:
            raise LinkError(f"backoff_s must be (first, max) with 0 < first <= max, "
                            f"found {backoff_s}")
        self.max_buffer_bytes = int(max_buffer_bytes)
        self.on_receive = on_receive
        self.rx_log_path = None if rx_log is None else Path(rx_log)
        self._rx_log: IO[str] | None = None
        self.clock_ns = clock_ns
        self.backoff_s = backoff_s
        self.service_interval_s = service_interval_s
        self._lock = threading.RLock()
        self._outbox = Outbox(self.max_buffer_bytes, lambda: self.clock_ns(),
                              lambda: self.describe(), self._count)
        self._rx = b""
        self._counters = LinkCounters()
        self._state = "closed"
        self._attempts = 0
        self._next_attempt_ns = 0
        self._lost_ns = 0                           # link clock when the port went away
        self._faulted = False
        self._fault_reason = ""
        self._last_valid_ns: int | None = None      # link clock when a valid pose arrived
        self._last_estimate: Estimate | None = None
        self._last_was_valid = False
        self.periodic_enabled = True
        self._next_periodic_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.state_at_close = ""                     # "connected" / "disconnected"

    # ---------------------------------------------------------------- port hooks

    def _open_port(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _close_port(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _write_some(self, data: bytes) -> int:  # pragma: no cover - abstract
        """Write without blocking; return the count taken (0 if none); raise _Disconnected."""
        raise NotImplementedError

    def _read_some(self) -> bytes:
        """Read what is there without blocking; raise _Disconnected."""
        return b""

    def _reappeared(self) -> bool:
        """The port, gone at the last attempt, is there again: reopen now (each poll)."""
        return False

    # ---------------------------------------------------------------- lifecycle

    def open(self) -> LinkBase:
        """Open the port (``LinkError`` with one line when it cannot) and start the service."""
        with self._lock:
            if self._state != "closed":
                return self
            self._open_port()
            if self.rx_log_path is not None:
                try:
                    self._rx_log = open(self.rx_log_path, "a", encoding="utf-8")  # noqa: SIM115
                except OSError as exc:
                    self._close_port()
                    raise LinkError(f"cannot open receive log {self.rx_log_path}: "
                                    f"{exc.strerror}") from None
            self._state = "connected"
            self.state_at_close = ""
            # the first periodic message is due one period after opening: startup is
            # not "no pose", and a replay's first pose is never preceded by a status
            self._next_periodic_ns = self.clock_ns() + PERIOD_NS
        if self.service_interval_s:
            self._stop.clear()
            self._thread = threading.Thread(target=self._service, name="ceilkit-link",
                                            daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Flush what can go out without blocking, stop the service, close the port."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:
            if self._state == "connected":
                try:
                    self._pump()
                except _Disconnected:
                    pass
            if self._state != "closed":
                self._close_port()
                self.state_at_close = self._state
            self._state = "closed"
            if self._rx_log is not None:
                self._rx_log.close()
                self._rx_log = None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _wait_input(self, timeout_s: float) -> None:
        """Sleep up to ``timeout_s``, waking early when the port has input (a port hook)."""
        self._stop.wait(timeout_s)

    def _service(self) -> None:
        interval = float(self.service_interval_s or 0.05)
        while not self._stop.is_set():
            self._wait_input(interval)
            if self._stop.is_set():
                break
            try:
                self.poll()
            except Exception:  # noqa: BLE001 - e.g. a failing on_receive; keep serving
                log.exception("link service: poll failed")

    # ---------------------------------------------------------------- the pipeline's API

    @property
    def state(self) -> str:
        """``connected``, ``disconnected`` (unplugged, reopening with back-off) or ``closed``."""
        return self._state

    @property
    def counters(self) -> LinkCounters:
        """A snapshot of the counters."""
        return self._counters

    @property
    def stalled(self) -> bool:
        """The peer is not reading: messages are being dropped (reported on the log
        while it lasts, at most every 10 s)."""
        return self._outbox.stalled

    @property
    def pending_bytes(self) -> int:
        """Bytes accepted by :meth:`send` and not yet written."""
        return self._outbox.pending_bytes

    def send(self, est: Estimate, relocalized: bool = False,
             capture_ns: int | None = None) -> None:
        """Encode one estimate and write it without blocking (or buffer or drop it).

        Args:
            est: the pose or failure; its ``t_ns`` is the capture time sent.
            relocalized: the pose jumped: bump the reset counter first (as
                :meth:`relocalized`), so this pose carries the new value.
            capture_ns: accepted for the pipeline's sink protocol; ``est.t_ns`` is used.
        """
        with self._lock:
            if self._state == "closed":
                raise LinkError("send() on a closed link")
            if relocalized:
                self.protocol.relocalized()
            now = self.clock_ns()
            msg, valid = self.protocol.pose(est)
            self._last_estimate, self._last_was_valid = est, valid
            if valid:
                self._last_valid_ns = now
            if msg is None:
                self._count(skipped=1)
            else:
                self._enqueue(msg)
            # with a service thread, reading back is its work (it wakes on input): the
            # pose's path is encode and write only
            self._poll_locked(now, read=self._thread is None)

    def relocalized(self) -> None:
        """The pose jumped (a relocalization): bump MAVLink's reset_counter."""
        with self._lock:
            self.protocol.relocalized()

    def set_fault(self, reason: str | None) -> None:
        """Mark the localizer faulted (``reason``) or healthy again (``None``).

        While faulted, MAVLink stops its HEARTBEAT and NMEA sends ``$PCEIS`` with state F.
        """
        with self._lock:
            self._faulted = reason is not None
            self._fault_reason = reason or ""
            now = self.clock_ns()
            self._next_periodic_ns = min(self._next_periodic_ns, now)
            if self._state != "closed":
                self._poll_locked(now)  # the first F status goes out at once

    def poll(self) -> None:
        """Do the periodic work now: reopen, periodic messages, write, read."""
        with self._lock:
            if self._state != "closed":
                self._poll_locked(self.clock_ns())

    # ---------------------------------------------------------------- internals

    def _count(self, **inc: int) -> None:
        c = self._counters
        self._counters = replace(c, **{k: getattr(c, k) + v for k, v in inc.items()})

    def _enqueue(self, msg: bytes) -> None:
        if self._state != "connected":
            self._count(dropped=1)
            return
        self._outbox.put(msg)

    def _poll_locked(self, now: int, read: bool = True) -> None:
        if self._state == "disconnected" and (now >= self._next_attempt_ns
                                              or self._reappeared()):
            self._try_reopen(now)
        if self.periodic_enabled and now >= self._next_periodic_ns:
            self._next_periodic_ns = now + PERIOD_NS
            msgs = self.protocol.periodic(_health(self, now))
            for msg in [msgs] if isinstance(msgs, bytes) else (msgs or ()):
                self._enqueue(msg)
        if self._state == "connected":
            try:
                self._pump()
                if read and self._read():
                    self._pump()  # answers (TIMESYNC) go out at once: PX4 times the round trip
            except _Disconnected as exc:
                self._lost(now, str(exc))

    def _pump(self) -> None:
        self._outbox.pump(self._write_some)

    def _read(self) -> bool:
        """Read and dispatch what the controller sent; True if answers were queued."""
        data = self._read_some()
        if not data:
            return False
        self._rx += data
        messages, self._rx = self.protocol.split_incoming(self._rx)
        self._rx = self._rx[-MAX_RX_PENDING:]
        now = self.clock_ns()
        answered = False
        answer = getattr(self.protocol, "answer", None)
        for raw, text in messages:
            self._count(received=1)
            if answer is not None:
                for reply in answer(raw, now):
                    self._enqueue(reply)
                    answered = True
            if self._rx_log is not None:
                self._rx_log.write(f"{now / 1e9:.3f} {text}\n")
                self._rx_log.flush()
            if self.on_receive is not None:
                self.on_receive(Received(now, raw, text))
        return answered

    def _lost(self, now: int, why: str) -> None:
        dropped = self._outbox.clear()
        self._rx = b""
        if dropped:
            self._count(dropped=dropped)
        try:
            self._close_port()
        except OSError:
            pass
        self._state = "disconnected"
        self._count(lost=1)
        self._attempts = 0
        self._lost_ns = now
        self._next_attempt_ns = now + int(self.backoff_s[0] * 1e9)
        log.warning("link %s lost (%s); poses are dropped until it is back", self.describe(),
                    why)

    def _try_reopen(self, now: int) -> None:
        try:
            self._open_port()
        except LinkError as exc:
            self._attempts += 1
            delay = min(self.backoff_s[1], self.backoff_s[0] * 2 ** self._attempts)
            self._next_attempt_ns = now + int(delay * 1e9)
            log.debug("reopen of %s failed (%s); next in %.1f s", self.describe(), exc, delay)
            return
        self._state = "connected"
        self._count(reconnects=1)
        log.warning("link %s back after %.1f s (%d failed attempts to reopen); poses resume",
                    self.describe(), (now - self._lost_ns) / 1e9, self._attempts)

    def describe(self) -> str:
        return f"{type(self).__name__}({self.protocol.name})"


def _health(link: LinkBase, now: int) -> Health:
    """What the periodic status tells of ``link``'s poses at ``now``."""
    valid_recently = (link._last_valid_ns is not None
                      and now - link._last_valid_ns < PERIOD_NS)
    age = None if link._last_valid_ns is None else (now - link._last_valid_ns) // 1_000_000
    est = link._last_estimate
    if est is None:
        reason = "no_estimate"
    elif isinstance(est, Failure):
        reason = est.reason
    else:
        reason = "stale" if link._last_was_valid else "unsendable"
    return Health(now, link._faulted, link._fault_reason, valid_recently, reason, age)


# ------------------------------------------------------------------------ serial


def _open_error(port: str, exc: BaseException) -> LinkError:
    code = getattr(exc, "errno", None)
    if code == errno.ENOENT:
        why = "no such device (is the adapter plugged in? see ls /dev/serial/by-id/)"
    elif code in (errno.EACCES, errno.EPERM):
        why = "permission denied (add the user to the dialout group)"
    elif code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY):
        why = "busy: another program holds it open"
    elif code == errno.ENOTTY:
        why = "not a serial port"
    else:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return LinkError(f"cannot open serial port {port}: {why}")


class SerialLink(LinkBase):
    """A serial port (USB-serial adapter, UART) carrying ``nmea`` or ``mavlink``.

    Args:
        port: the device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``).
        baud: bits per second (8N1, no flow control).
        protocol: ``nmea`` (default) or ``mavlink``, or a protocol object.
        max_buffer_bytes: bound of what waits for a backed-up peer.
        on_receive: called with each :class:`Received` message from the controller.
        rx_log: a text file each received message is appended to, one line each.
        clock_ns: the link's clock (integer ns).
        backoff_s: ``(first, max)`` delays between reopen attempts after an unplug.
        service_interval_s: period of the service thread that sends the 1 Hz messages,
            reads and reconnects while the pipeline is busy; ``None``: the caller's
            :meth:`poll` and :meth:`send` do it.
        **protocol_options: ``sysid``, ``compid``, ``settings`` for ``mavlink``.

    Raises:
        LinkError: on :meth:`open` (``with``), when the port cannot be opened: one line.
    """

    def __init__(self, port: str | Path, baud: int = 115200,
                 protocol: str | LinkProtocol = "nmea", *,
                 service_interval_s: float | None = 0.05, **options) -> None:
        super().__init__(protocol, service_interval_s=service_interval_s, **options)
        if int(baud) <= 0:
            raise LinkError(f"baud must be a positive integer, found {baud}")
        self.port = str(port)
        self.baud = int(baud)
        self._serial = None
        self._fd = -1
        self._absent = False    # the last attempt to open found no such port

    def describe(self) -> str:
        return f"{self.port}@{self.baud} ({self.protocol.name})"

    def _open_port(self) -> None:
        import serial  # pyserial

        try:
            ser = serial.Serial(self.port, self.baud, timeout=0, write_timeout=0,
                                exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._absent = not os.path.exists(self.port)
            raise _open_error(self.port, exc) from None
        self._absent = False
        fd = ser.fileno()
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) | os.O_NONBLOCK)
        self._serial, self._fd = ser, fd

    def _reappeared(self) -> bool:
        # the device node (or the by-id / socat symlink's target) is back: a re-plug,
        # the peer's socat restarted; a port that is there but fails waits the back-off
        return self._absent and os.path.exists(self.port)

    def _close_port(self) -> None:
        ser, self._serial, self._fd = self._serial, None, -1
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - the port may already be gone
                pass

    def _write_some(self, data: bytes) -> int:
        # os.write on the non-blocking fd: pyserial's write() spins on EAGAIN with
        # write_timeout=0, this returns 0 instead.
        try:
            return os.write(self._fd, data)
        except BlockingIOError:
            return 0
        except InterruptedError:
            return 0
        except OSError as exc:
            raise _Disconnected(f"write: {exc.strerror}") from None

    def _wait_input(self, timeout_s: float) -> None:
        fd = self._fd
        if fd < 0:
            self._stop.wait(timeout_s)
            return
        try:
            poller = select.poll()
            poller.register(fd, select.POLLIN)
            events = poller.poll(timeout_s * 1000)
        except (OSError, ValueError):
            events = []
        if events and events[0][1] & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
            self._stop.wait(0.01)  # a hang-up stays "ready": let poll() notice, no spin

    def _read_some(self) -> bytes:
        # pyserial sets VMIN = VTIME = 0, so an empty read is "nothing yet"; a hang-up
        # shows as POLLHUP / POLLERR, or as readable-but-empty (as pyserial reads it)
        poller = select.poll()
        poller.register(self._fd, select.POLLIN)
        events = poller.poll(0)
        mask = events[0][1] if events else 0
        if mask & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
            raise _Disconnected("hang-up")
        if not mask & select.POLLIN:
            return b""
        try:
            data = os.read(self._fd, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise _Disconnected(f"read: {exc.strerror}") from None
        if not data:
            raise _Disconnected("readable but no data (device disconnected?)")
        return data


def is_serial_path(target: str | Path) -> bool:
    """Whether ``--serial`` names a serial port rather than a regular output file.

    A port: a path under ``/dev/``, a character device (also through a symlink, as
    ``/dev/serial/by-id/...`` and socat links are), or a name starting with ``tty``
    (a port that is unplugged right now). Anything else is a file.
    """
    path = Path(target)
    if str(path).startswith("/dev/") or path.name.startswith("tty"):
        return True
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return False


def open_link(target: str | Path, protocol: str = "nmea", baud: int = 115200, *,
              system_id: int = 1, component_id: int = mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
              unobserved: str = "skip", origin: mavlink.GeoOrigin | None = None,
              rig: object | None = None, site: object | None = None,
              **options) -> LinkBase:
    """The link for a command line's ``--serial`` value.

    ``-`` is stdout; a serial port (see :func:`is_serial_path`) is a :class:`SerialLink`;
    any other path is a regular file, truncated and written with the wire's bytes
    (:class:`FileLink`). The result is not open yet: use it with ``with``.

    Args:
        protocol: one of :data:`PROTOCOLS`.
        unobserved: ``mavlink`` policy for a pose missing x or y (``skip`` or ``nan``, see
            :class:`~ceilkit.runtime.io.link.mavlink.VisionSettings`).
        origin: MAVLink: an EKF origin to send until acknowledged (ArduPilot). With
            ``mavlink-odometry`` it defaults to the site's ``origin`` when there is one.
        rig: the rig (its ``mount``): ``mavlink-odometry`` sends the camera's position.
        site: the site (its ``origin``): ``nmea-gps`` places W on the Earth with it.
    """
    proto_opts = _protocol_options(protocol, system_id, component_id, unobserved, origin,
                                   rig, site, options.get("clock_ns"))
    if str(target) == "-":
        return FileLink("-", protocol, **proto_opts, **options)
    if is_serial_path(target):
        return SerialLink(target, baud, protocol, **proto_opts, **options)
    options.pop("service_interval_s", None)
    return FileLink(target, protocol, append=False, **proto_opts, **options)


def _protocol_options(protocol: str, system_id: int, component_id: int, unobserved: str,
                      origin: mavlink.GeoOrigin | None, rig: object | None,
                      site: object | None, clock_ns: Callable[[], int] | None) -> dict:
    """The protocol's constructor options for :func:`open_link` (LinkError when missing)."""
    site_origin = getattr(site, "origin", None)
    if protocol == "mavlink":
        try:
            settings = mavlink.VisionSettings(unobserved=unobserved)
        except ValueError as exc:
            raise LinkError(str(exc)) from None
        return {"sysid": system_id, "compid": component_id, "settings": settings,
                "origin": origin}
    if protocol == "mavlink-odometry":
        mount = getattr(rig, "mount", None)
        if mount is None:
            raise LinkError("the mavlink-odometry protocol sends the camera's position: "
                            "it needs the rig (rig.yaml mount)")
        if origin is None and site_origin is not None:
            origin = mavlink.GeoOrigin(site_origin.lat_deg, site_origin.lon_deg,
                                       site_origin.alt_m)
        odometry = mavlink.OdometrySettings(sensor_V_m=(mount.x_m, mount.y_m, mount.z_m))
        return {"sysid": system_id, "compid": component_id, "origin": origin,
                "odometry": odometry}
    if protocol == "nmea-gps":
        if site_origin is None:
            raise LinkError("the nmea-gps protocol needs the site's geodetic origin "
                            "(site.yaml origin: {lat, lon, alt, heading})")
        try:
            plane = LocalTangentPlane.of(site_origin)
        except ValueError as exc:
            raise LinkError(str(exc)) from None
        return {"plane": plane} if clock_ns is None else {"plane": plane,
                                                          "capture_clock_ns": clock_ns}
    return {}


# ------------------------------------------------------------------------ file, fake


class FileLink(LinkBase):
    """The same bytes as on the wire, to a file (``-`` for stdout). Never drops.

    Periodic messages follow ``clock_ns`` as on a port; pass ``periodic=False`` to
    write only the per-estimate messages (a replay, compared byte for byte).
    ``append=False`` truncates the file when it is first opened.
    """

    def __init__(self, path: str | Path, protocol: str | LinkProtocol = "nmea", *,
                 periodic: bool = True, append: bool = True, **options) -> None:
        options.setdefault("max_buffer_bytes", 1 << 20)
        super().__init__(protocol, **options)
        self.path = str(path)
        self.periodic_enabled = periodic
        self.append = append
        self._file: IO[bytes] | None = None

    def describe(self) -> str:
        return f"{self.path} ({self.protocol.name})"

    def _open_port(self) -> None:
        if self.path == "-":
            self._file = sys.stdout.buffer
            return
        try:
            self._file = open(self.path, "ab" if self.append else "wb")  # noqa: SIM115
            self.append = True  # a reopen after an error appends
        except OSError as exc:
            raise LinkError(f"cannot open link file {self.path}: {exc.strerror}") from None

    def _close_port(self) -> None:
        f, self._file = self._file, None
        if f is None:
            return
        if f is sys.stdout.buffer:
            f.flush()
        else:
            f.close()

    def _write_some(self, data: bytes) -> int:
        if self._file is None:
            raise _Disconnected("file closed")
        try:
            n = self._file.write(data)
            self._file.flush()
        except OSError as exc:
            raise _Disconnected(f"write: {exc.strerror}") from None
        return len(data) if n is None else n


class MemoryLink(LinkBase):
    """An in-memory fake port for tests.

    ``capacity`` bytes may sit unread at the fake peer before it is backed up (writes
    then take only what fits, like a full driver buffer); :meth:`drain` reads them.
    :meth:`unplug` and :meth:`replug` simulate the cable; :meth:`feed` queues bytes
    the controller sends.
    """

    def __init__(self, protocol: str | LinkProtocol = "nmea", *, capacity: int | None = None,
                 **options) -> None:
        super().__init__(protocol, **options)
        self.capacity = capacity
        self.written = bytearray()     # everything ever written, in order
        self._unread = bytearray()
        self._incoming = bytearray()
        self.plugged = True

    def _open_port(self) -> None:
        if not self.plugged:
            raise LinkError("cannot open memory link: unplugged")

    def _close_port(self) -> None:
        self._unread.clear()

    def _write_some(self, data: bytes) -> int:
        if not self.plugged:
            raise _Disconnected("write: unplugged")
        room = len(data) if self.capacity is None else self.capacity - len(self._unread)
        n = max(0, min(len(data), room))
        self.written += data[:n]
        self._unread += data[:n]
        return n

    def _read_some(self) -> bytes:
        if not self.plugged:
            raise _Disconnected("read: unplugged")
        data = bytes(self._incoming)
        self._incoming.clear()
        return data

    def drain(self) -> bytes:
        """What the fake peer has not read yet; reading frees the capacity."""
        data = bytes(self._unread)
        self._unread.clear()
        return data

    def feed(self, data: bytes) -> None:
        """Bytes the controller sends, read at the next poll."""
        self._incoming += data

    def unplug(self) -> None:
        self.plugged = False

    def replug(self) -> None:
        self.plugged = True
