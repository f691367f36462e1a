"""Frames and the protocol every frame source follows.

A source is opened with ``with`` and read frame by frame; ``read()`` returns
``None`` at the end of a finite source. Frames are stamped at grab with a
monotonic clock in integer nanoseconds (recordings keep their stored stamps).

Every source declares two attributes the live loop reads:

* ``live``: its stamps are on ``time.monotonic_ns`` at grab (a camera), so they are
  the capture times; ``False`` for stored or synthetic stamps (a recording, a video,
  the simulator), which the loop replaces by its own clock;
* ``dropped``: frames the source skipped (a camera's latest-frame policy); 0 for
  sources that never skip.

A :class:`LiveSource` (a camera) may have no frame yet: it is waited on in short
slices (:meth:`LiveSource.wait_frame`) so that a stop request is honoured and a lost
camera is reported while it is reopened.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ceilkit.runtime.features.grey import to_grey


@dataclass(frozen=True, eq=False)
class Frame:
    """One captured image.

    Attributes:
        image: ``(H, W)`` uint8 grey or ``(H, W, 3)`` uint8 BGR, as captured.
        t_ns: capture time, integer nanoseconds.
        index: the frame's number in its source (0-based).
        damage: ``""`` for a frame read whole; otherwise one line naming the file and
            why it is no image (a truncated JPEG or PNG, :mod:`~ceilkit.runtime.io.images`):
            ``image`` is then empty (``(0, 0)``) and the pipeline publishes a
            ``bad_frame`` failure for it (:meth:`damaged` makes one).
    """

    image: np.ndarray
    t_ns: int
    index: int
    damage: str = ""

    @classmethod
    def damaged(cls, damage: str, t_ns: int, index: int) -> Frame:
        """A frame whose file was no image (``damage``: the reason, naming the file)."""
        return cls(np.zeros((0, 0), np.uint8), int(t_ns), int(index), damage)

    @property
    def grey(self) -> np.ndarray:
        """The image as 8-bit grey."""
        return to_grey(self.image)


@runtime_checkable
class FrameSource(Protocol):
    """Anything that yields frames: a camera, a video, a folder, a recording, the simulator."""

    live: bool
    dropped: int

    def read(self) -> Frame | None:
        """The next frame, or ``None`` at the end of a finite source."""
        ...

    def close(self) -> None:
        ...

    def __enter__(self) -> FrameSource:
        ...

    def __exit__(self, *exc: object) -> None:
        ...


@runtime_checkable
class LiveSource(FrameSource, Protocol):
    """A source that may have no frame yet (a camera being reopened): waited on in slices."""

    @property
    def closed(self) -> bool:
        """True once closed: no frame will come any more."""
        ...

    def wait_frame(self, timeout_s: float) -> Frame | None:
        """The newest frame not yet returned, or ``None`` when none came within
        ``timeout_s`` or the source is closed; never raises."""
        ...


class SourceBase:
    """Context-manager and iteration boilerplate for sources.

    A subclass declares ``live`` and ``dropped`` (see the module docstring).
    """

    live: bool
    dropped: int

    def read(self) -> Frame | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame


class ListSource(SourceBase):
    """A fake source over frames held in memory (for tests)."""

    live = False
    dropped = 0

    def __init__(self, frames: list[Frame]):
        self._frames = list(frames)
        self._i = 0

    def read(self) -> Frame | None:
        if self._i >= len(self._frames):
            return None
        f = self._frames[self._i]
        self._i += 1
        return f
