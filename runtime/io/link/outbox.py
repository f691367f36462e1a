"""What waits to go out on a link: whole messages in a bounded buffer.

:class:`Outbox` is the link's framing and queueing, apart from its port and its state
machine (:mod:`.transport`): a message that was partly written is completed before any
other byte goes out (no torn frames); when the buffer is over its bound, whole messages
that have not started are dropped, oldest first (stale poses), counted, and reported on
the log while the peer stays backed up (at most every :data:`STALL_REPORT_NS`).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable

log = logging.getLogger("ceilkit.link")

STALL_REPORT_NS = 10_000_000_000
"""While the peer stays backed up (messages dropped), one log line per this period."""


class Outbox:
    """The bounded queue of a link's outgoing messages.

    Args:
        max_bytes: bound of what waits (the started message's rest included).
        clock_ns: the link's clock (integer ns), for the stall reports.
        describe: the link's name for the log lines.
        count: adds to the link's counters (``dropped``, ``sent``, ``bytes_sent``).
    """

    def __init__(self, max_bytes: int, clock_ns: Callable[[], int],
                 describe: Callable[[], str], count: Callable[..., None]) -> None:
        self.max_bytes = int(max_bytes)
        self._clock_ns = clock_ns
        self._describe = describe
        self._count = count
        self._queue: deque[bytes] = deque()
        self._queued_bytes = 0
        self._head = b""            # the unwritten rest of a message already started
        self._stall_since: int | None = None   # link clock of the first drop of a stall
        self._stall_drops = 0
        self._stall_reported = 0

    @property
    def pending_bytes(self) -> int:
        """Bytes accepted and not yet written."""
        return self._queued_bytes + len(self._head)

    @property
    def stalled(self) -> bool:
        """Messages are being dropped because the peer is not reading."""
        return self._stall_since is not None

    def put(self, msg: bytes) -> None:
        """Queue one whole message, dropping the oldest not-yet-started ones over the bound."""
        self._queue.append(msg)
        self._queued_bytes += len(msg)
        while self._queued_bytes + len(self._head) > self.max_bytes and self._queue:
            old = self._queue.popleft()  # oldest not-yet-started message: stale
            self._queued_bytes -= len(old)
            self._count(dropped=1)
            self._stalling()

    def pump(self, write_some: Callable[[bytes], int]) -> None:
        """Write what ``write_some`` takes now (it returns the count taken, 0 if none;
        its exceptions propagate with the rest kept)."""
        while self._head or self._queue:
            if not self._head:
                self._head = self._queue.popleft()
                self._queued_bytes -= len(self._head)
            n = write_some(self._head)
            if n:
                self._count(bytes_sent=n)
            if n < len(self._head):
                self._head = self._head[n:]
                return
            self._head = b""
            self._count(sent=1)
        self._flowing()

    def clear(self) -> int:
        """Discard everything (the port went away); return the count of messages lost."""
        lost = len(self._queue) + (1 if self._head else 0)
        self._queue.clear()
        self._queued_bytes = 0
        self._head = b""
        self._stall_since, self._stall_drops = None, 0  # lost, not stalled
        return lost

    def _stalling(self) -> None:
        """A message was dropped because the peer is backed up: report, rate-limited."""
        now = self._clock_ns()
        self._stall_drops += 1
        if self._stall_since is None:
            self._stall_since = self._stall_reported = now
            log.warning("link %s stalled: the peer is not reading; dropping the oldest "
                        "messages", self._describe())
        elif now - self._stall_reported >= STALL_REPORT_NS:
            self._stall_reported = now
            log.warning("link %s still stalled after %.0f s: %d messages dropped",
                        self._describe(), (now - self._stall_since) / 1e9, self._stall_drops)

    def _flowing(self) -> None:
        """Everything queued went out: a stall, if any, is over."""
        if self._stall_since is not None:
            log.warning("link %s flowing again after %.1f s (%d messages dropped)",
                        self._describe(), (self._clock_ns() - self._stall_since) / 1e9,
                        self._stall_drops)
            self._stall_since, self._stall_drops = None, 0
