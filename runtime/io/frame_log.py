"""The write-ahead frame log of a live recording (``frames.wal/`` in its folder).

Each frame is one record (a header: magic, index, stamp, dtype, shape, size, CRC-32;
then the raw pixels) appended with one ``writev`` to a segment ``NNNNNN.raw`` of
:data:`FRAMES_PER_SEGMENT` frames, named by its first frame. A record cut short or
whose checksum fails ends its segment when read back (what a kill or a power loss
leaves); :func:`read_frame_log` lists what is whole, :func:`load_logged` reads one.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.sources import Frame

LOG_DIR = "frames.wal"
"""The write-ahead frame log's folder inside a recording."""
FRAMES_PER_SEGMENT = 32
"""Frames per log segment (a segment is deleted once all its frames are PNGs)."""

RECORD = struct.Struct("<4sQqBc3IQI")  # magic, index, t_ns, ndim, dtype, shape, size, crc
MAGIC = b"CKWF"


@dataclass(frozen=True)
class LoggedFrame:
    """Where a frame of the write-ahead log lies: segment file, byte offset of its data."""

    index: int
    t_ns: int
    path: Path
    offset: int
    dtype: str
    shape: tuple[int, ...]
    size: int
    crc: int


def segment_name(index: int) -> str:
    """The log segment holding frame ``index``: ``NNNNNN.raw`` named by its first frame."""
    return f"{index - index % FRAMES_PER_SEGMENT:06d}.raw"


def record_header(index: int, frame: Frame, data: memoryview) -> bytes:
    img = frame.image
    shape = tuple(img.shape) + (0,) * (3 - img.ndim)
    return RECORD.pack(MAGIC, index, int(frame.t_ns), img.ndim, img.dtype.char.encode(),
                        *shape, len(data), zlib.crc32(data))


def read_frame_log(folder: str | Path) -> list[LoggedFrame]:
    """The frames of a recording's write-ahead log, in index order; a record cut short
    or whose checksum fails ends its segment (what a kill or power loss leaves)."""
    out: list[LoggedFrame] = []
    wal = Path(folder) / LOG_DIR
    if not wal.is_dir():
        return out
    for seg in sorted(wal.glob("*.raw")):
        try:
            data = seg.read_bytes()
        except OSError:
            continue
        pos = 0
        while pos + RECORD.size <= len(data):
            magic, index, t_ns, ndim, dt, h, w, c, size, crc = RECORD.unpack_from(data, pos)
            start = pos + RECORD.size
            if magic != MAGIC or ndim not in (2, 3) or start + size > len(data) \
                    or zlib.crc32(memoryview(data)[start:start + size]) != crc:
                break
            out.append(LoggedFrame(index, t_ns, seg, start, dt.decode("ascii", "replace"),
                                   (h, w, c)[:ndim], size, crc))
            pos = start + size
    out.sort(key=lambda e: e.index)
    return out


def load_logged(entry: LoggedFrame) -> np.ndarray:
    """The image of a logged frame.

    Raises:
        ConfigError: the log segment cannot be read or holds something else now.
    """
    try:
        with open(entry.path, "rb") as fh:
            fh.seek(entry.offset)
            data = fh.read(entry.size)
        image = np.frombuffer(data, dtype=np.dtype(entry.dtype)).reshape(entry.shape)
    except (OSError, TypeError, ValueError) as exc:
        raise ConfigError(entry.path, f"frame {entry.index}",
                          f"cannot read the logged frame: {exc}") from None
    if zlib.crc32(data) != entry.crc:
        raise ConfigError(entry.path, f"frame {entry.index}", "checksum mismatch")
    return image
