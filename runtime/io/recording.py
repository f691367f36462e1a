"""Recordings, truth and pose files in the layouts of SPEC §2.

A recording is a folder::

    frames/000000.png ...          # 8-bit grey or BGR, as captured
    frames.csv                     # header `index,t_ns`, one row per frame
    rig.yaml, site.yaml            # as used when recording
    truth.csv                      # optional: `t_ns,x,y,yaw_deg`
    odometry.csv                   # optional: `t_ns,dx,dy,dyaw_deg`, increments in V
    frames.wal/000000.raw ...      # while recording live: the write-ahead frame log

Writing live is in two steps (:meth:`RecordingWriter.log`, then
:meth:`RecordingWriter.convert_next` on another thread): the raw frame is appended to
the write-ahead log ``frames.wal/`` with one ``writev`` (once it returns the bytes are
in the kernel's page cache, which outlives the process), before its pose is sent;
the PNG is encoded later, written atomically (by rename) before its ``frames.csv``
row, and a log segment is deleted once all its frames are PNGs (after an fsync when
``fsync_every_s`` is set). So a run killed at any instant leaves every frame whose
pose went out either as a PNG or in the log; :class:`Recording` reads both, and
:func:`repair_recording` turns the log into PNGs. :meth:`RecordingWriter.write` does
both steps at once (no log).

Every row of a CSV file is one ``write`` of the whole line, rolled back (truncated)
when it fails, so no file is ever cut mid-row. Files are written through a
:class:`Disk` (the operating system, or a fake such as :class:`FullDisk`). A file
that cannot be written is an :class:`~ceilkit.runtime.errors.OutputError` naming it
(its ``errno`` attribute says why: ``ENOSPC`` for a full disk).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import logging
import math
import os
import shutil
import struct
import threading
import zlib
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.io.sources import Frame, SourceBase

log = logging.getLogger("ceilkit.recording")

FRAMES_HEADER = ["index", "t_ns"]
TRUTH_HEADER = ["t_ns", "x", "y", "yaw_deg"]
ODOMETRY_HEADER = ["t_ns", "dx", "dy", "dyaw_deg"]
POSES_HEADER = ["t_ns", "x", "y", "yaw_deg", "lateral", "method", "quality", "latency_ms",
                "sigma_x", "sigma_y", "sigma_yaw_deg"]
POSES_SIGMA_COLUMNS = POSES_HEADER[8:]
"""The columns SPEC §2 added after the first eight; a file without them still reads."""

LOG_DIR = "frames.wal"
"""The write-ahead frame log's folder inside a recording."""
FRAMES_PER_SEGMENT = 32
"""Frames per log segment (a segment is deleted once all its frames are PNGs)."""
RECORDING_FILES = ("frames.csv", "frames", LOG_DIR, "rig.yaml", "site.yaml", "truth.csv",
                   "odometry.csv")
"""What a recording folder may hold; a folder holding any of them is not written over
unless told (``force``)."""
FORCE_HINT = "force=True replaces it"
"""The end of the message refusing to overwrite; the command lines name their flag."""

_RECORD = struct.Struct("<4sQqBc3IQI")  # magic, index, t_ns, ndim, dtype, shape, size, crc
_MAGIC = b"CKWF"


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


def output_error(path: str | Path, exc: OSError) -> OutputError:
    """An :class:`OutputError` naming ``path`` and the cause; ``.errno`` is kept."""
    err = OutputError(path, f"cannot write: {exc.strerror or exc}")
    err.errno = exc.errno  # type: ignore[attr-defined]
    return err


def refuse_existing(path: str | Path, what: str = "") -> ConfigError:
    """The error for an output that exists and was not to be overwritten (``what``: the
    subject when it is not ``path`` itself, e.g. ``a recording is``)."""
    return ConfigError(path, None, f"{what + ' ' if what else ''}already there; nothing "
                       f"was overwritten ({FORCE_HINT})")


def device_of(path: str | Path) -> str:
    """The file system holding ``path`` as ``SOURCE (MOUNTPOINT)``, e.g.
    ``/dev/mmcblk0p2 (/)`` or ``tmpfs (/mnt/rec)``, from ``/proc/self/mounts``; the path
    itself where that cannot be read."""
    real = os.path.realpath(path)
    best = ("", "")
    try:
        with open("/proc/self/mounts", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                parts = line.split()
                if len(parts) < 2:
                    continue
                mnt = parts[1].replace("\\040", " ")
                inside = real == mnt or real.startswith(mnt.rstrip("/") + "/")
                if inside and len(mnt) >= len(best[1]):
                    best = (parts[0], mnt)
    except OSError:
        pass
    return f"{best[0]} ({best[1]})" if best[1] else str(path)


# --------------------------------------------------------------------------- the disk
@runtime_checkable
class Disk(Protocol):
    """How outputs reach the file system: the operating system (:data:`OS_DISK`), or a
    fake (:class:`FullDisk`) in tests and benchmarks. Every method raises ``OSError``."""

    def append(self, fd: int, parts: Sequence[bytes | memoryview]) -> int:
        """Append ``parts`` with one ``writev`` to ``fd`` (opened ``O_APPEND``); the count."""
        ...

    def truncate(self, fd: int, size: int) -> None:
        """Cut the file back to ``size`` bytes (a failed append rolled back)."""
        ...

    def replace_file(self, path: Path, data: bytes) -> None:
        """Write ``path`` atomically (a temporary beside it, then a rename)."""
        ...

    def fsync(self, path: Path) -> None:
        """Flush ``path`` (a file or a folder) to stable storage."""
        ...


class OsDisk:
    """The operating system's file system."""

    def append(self, fd: int, parts: Sequence[bytes | memoryview]) -> int:
        return os.writev(fd, parts)

    def truncate(self, fd: int, size: int) -> None:
        os.ftruncate(fd, size)

    def replace_file(self, path: Path, data: bytes) -> None:
        tmp = path.with_name("." + path.name)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
            finally:
                os.close(fd)
            os.replace(tmp, path)
        except OSError:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def fsync(self, path: Path) -> None:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


OS_DISK = OsDisk()


class FullDisk(OsDisk):
    """A fake disk that fills up: while ``full`` every append and file write fails with
    ``ENOSPC`` (``No space left on device``), as a full file system does; set ``full``
    back to ``False`` to free space. ``fail_after_bytes`` fills it after that many bytes."""

    def __init__(self, fail_after_bytes: int | None = None):
        self.full = False
        self.fail_after_bytes = fail_after_bytes
        self.written = 0
        self._lock = threading.Lock()

    def _take(self, n: int) -> None:
        with self._lock:
            if self.fail_after_bytes is not None and self.written + n > self.fail_after_bytes:
                self.full = True
                self.fail_after_bytes = None
            if self.full:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.written += n

    def append(self, fd: int, parts: Sequence[bytes | memoryview]) -> int:
        self._take(sum(len(p) for p in parts))
        return super().append(fd, parts)

    def replace_file(self, path: Path, data: bytes) -> None:
        self._take(len(data))
        super().replace_file(path, data)


class AppendFile:
    """A file written by whole records: each :meth:`append` is one write of the whole
    record, cut back when it fails, so the file never ends in half a record.

    Args:
        path: the file (created or truncated).
        disk: how it is written.
        header: written first (a CSV header line).
        truncate: ``False``: append to the file as it is.

    Raises:
        OutputError: the file cannot be created or its header written.
    """

    def __init__(self, path: Path, disk: Disk = OS_DISK, header: bytes = b"",
                 truncate: bool = True):
        self.path = Path(path)
        self.disk = disk
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if truncate else 0)
        try:
            self.fd = os.open(self.path, flags, 0o644)
            self.size = os.fstat(self.fd).st_size
        except OSError as exc:
            raise output_error(self.path, exc) from None
        if header:
            try:
                self.append([header])
            except OutputError:
                self.close()
                raise

    @property
    def closed(self) -> bool:
        return self.fd < 0

    def append(self, parts: Sequence[bytes | memoryview]) -> None:
        """Append one record (its parts in one write), or nothing.

        Raises:
            OutputError: it could not be written whole (the file is as before).
        """
        size = self.size
        want = sum(len(p) for p in parts)
        try:
            n = self.disk.append(self.fd, parts)
            if n != want:  # a short write: the disk filled up during it
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        except OSError as exc:
            with contextlib.suppress(OSError):
                self.disk.truncate(self.fd, size)
            raise output_error(self.path, exc) from None
        self.size += n

    def close(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1


def csv_line(fields: Sequence[object]) -> bytes:
    """One CSV line (``\\n``-terminated) as UTF-8 bytes."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(fields)
    return buf.getvalue().encode("utf-8")


class CsvFile(AppendFile):
    """A CSV file written row by row, each row whole or not at all."""

    def __init__(self, path: Path, header: Sequence[str], disk: Disk = OS_DISK):
        super().__init__(path, disk, csv_line(header))

    def row(self, fields: Sequence[object]) -> None:
        self.append([csv_line(fields)])


# --------------------------------------------------------------------------- frame log
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


def _record_header(index: int, frame: Frame, data: memoryview) -> bytes:
    img = frame.image
    shape = tuple(img.shape) + (0,) * (3 - img.ndim)
    return _RECORD.pack(_MAGIC, index, int(frame.t_ns), img.ndim, img.dtype.char.encode(),
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
        while pos + _RECORD.size <= len(data):
            magic, index, t_ns, ndim, dt, h, w, c, size, crc = _RECORD.unpack_from(data, pos)
            start = pos + _RECORD.size
            if magic != _MAGIC or ndim not in (2, 3) or start + size > len(data) \
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


# --------------------------------------------------------------------------- writing
def _encode_png(image: np.ndarray, path: Path) -> bytes:
    try:
        ok, buf = cv2.imencode(".png", image)
    except cv2.error:  # an empty or non-image array
        ok = False
    if not ok:
        shape = getattr(image, "shape", None)
        err = OutputError(path, f"cannot write the frame image (shape {shape})")
        err.errno = None  # type: ignore[attr-defined]
        raise err
    return buf.tobytes()


def clear_recording(folder: Path) -> None:
    """Delete what a recording holds in ``folder`` (:data:`RECORDING_FILES`)."""
    for name in RECORDING_FILES:
        p = folder / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


class RecordingWriter:
    """Writes a SPEC recording, frame by frame.

    Example::

        with RecordingWriter(out_dir, rig, site, truth=True) as rec:
            rec.write(frame)                       # PNG, then its frames.csv row
            rec.write_truth(frame.t_ns, x, y, yaw_rad)

    Live (:class:`~ceilkit.runtime.live.AsyncRecorder`): :meth:`log` on the loop's
    thread (the raw frame into the write-ahead log), :meth:`convert_next` and
    :meth:`sync` on another (PNGs, rows, fsync, old log segments deleted).

    With ``truth_of`` (the ground truth a source carries: the simulator's trajectory,
    a replayed recording's ``truth.csv``), each stored frame gets its truth row (by the
    frame's exact stamp), so the recording replays with its errors against truth.
    ``truth.csv`` is created at once with ``truth`` or ``truth_of``, else by the first
    :meth:`write_truth`.

    The folder appears whole: its rig, site and headers are written in a temporary
    folder beside it, renamed into place.

    Args:
        force: replace a recording already in ``folder`` (else a ConfigError).
        disk: how files are written (a fake in tests).
        keep_images: frames :meth:`log` keeps in memory for :meth:`convert_next`
            (beyond, they are read back from the log).

    Raises:
        ConfigError: the folder already holds a recording (nothing is overwritten).
        OutputError: a folder or file that cannot be written.
    """

    def __init__(self, folder: str | Path, rig: Rig, site: Site, truth: bool = False,
                 header: str = "", truth_of: Truth | None = None, force: bool = False,
                 disk: Disk = OS_DISK, keep_images: int = 64):
        self.folder = Path(folder)
        self.disk = disk
        held = [n for n in RECORDING_FILES if (self.folder / n).exists()]
        if not force:
            self.check_free(self.folder)
        self._make_folder(rig, site, header, force and bool(held))
        self._frames = CsvFile(self.folder / "frames.csv", FRAMES_HEADER, disk)
        self._truth_of = truth_of
        self._truth = (CsvFile(self.folder / "truth.csv", TRUTH_HEADER, disk)
                       if truth or truth_of is not None else None)
        self.count = 0        # frames stored (logged or written)
        self.converted = 0    # frames that are PNGs with their row
        self.keep_images = keep_images
        self._pending: deque[tuple[LoggedFrame, np.ndarray | None]] = deque()
        self._segment: AppendFile | None = None
        self._unsynced: list[Path] = []
        self._done_segments: list[Path] = []

    @staticmethod
    def check_free(folder: Path) -> None:
        """Raise the ConfigError refusing ``folder`` when it holds any of
        :data:`RECORDING_FILES` (a recording, or a rig or site file)."""
        held = [n for n in RECORDING_FILES if (folder / n).exists()]
        if held:
            what = "a recording is" if "frames.csv" in held or LOG_DIR in held \
                else f"{', '.join(held)} {'is' if len(held) == 1 else 'are'}"
            raise refuse_existing(folder, what)

    def _make_folder(self, rig: Rig, site: Site, header: str, clear: bool) -> None:
        parent = self.folder.parent
        tmp = parent / f".{self.folder.name}.partial-{os.getpid()}"
        try:
            parent.mkdir(parents=True, exist_ok=True)
            if tmp.exists():
                shutil.rmtree(tmp)
            (tmp / "frames").mkdir(parents=True)
            rig.save(tmp / "rig.yaml", header)
            site.save(tmp / "site.yaml", header)
            if clear:
                clear_recording(self.folder)
            if self.folder.is_dir() and any(self.folder.iterdir()):
                for p in tmp.iterdir():  # a folder with other files: move ours in
                    os.replace(p, self.folder / p.name)
                tmp.rmdir()
            else:
                os.replace(tmp, self.folder)  # replaces an empty folder
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise OutputError(self.folder, f"cannot create: {exc.strerror or exc}") from None

    @property
    def closed(self) -> bool:
        return self._frames.closed

    @property
    def pending(self) -> int:
        """Frames logged and not yet PNGs."""
        return len(self._pending)

    # ---------------------------------------------------------------- at once
    def write(self, frame: Frame) -> None:
        """Store one frame: its PNG first, then its row (no log)."""
        path = self.folder / "frames" / frame_name(self.count)
        data = _encode_png(frame.image, path.with_name("." + path.name))
        try:
            self.disk.replace_file(path, data)
        except OSError as exc:
            raise output_error(path, exc) from None
        self._frames.row([self.count, int(frame.t_ns)])
        self.count += 1
        self.converted += 1
        self._truth_row(frame.t_ns)

    # ---------------------------------------------------------------- in two steps
    def log(self, frame: Frame) -> int:
        """Append the raw frame to the write-ahead log (one ``writev``: in the page cache
        when it returns); its truth row too. The frame's index.

        Raises:
            OutputError: the log cannot be written (``errno`` ENOSPC: a full disk), or
                the image is not one (``errno`` None).
        """
        img = frame.image
        index = self.count
        if not isinstance(img, np.ndarray) or img.ndim not in (2, 3) or img.size == 0 \
                or img.dtype != np.uint8:
            err = OutputError(self.folder / LOG_DIR, "cannot write the frame image "
                              f"(shape {getattr(img, 'shape', None)})")
            err.errno = None  # type: ignore[attr-defined]
            raise err
        img = np.ascontiguousarray(img)
        data = memoryview(img).cast("B")
        seg = self._segment_for(index)
        offset = seg.size + _RECORD.size
        seg.append([_record_header(index, frame, data), data])
        entry = LoggedFrame(index, int(frame.t_ns), seg.path, offset, img.dtype.char,
                            tuple(img.shape), len(data), 0)
        keep = img if len(self._pending) < self.keep_images else None
        self._pending.append((entry, keep))
        self.count += 1
        self._truth_row(frame.t_ns)
        return index

    def _segment_for(self, index: int) -> AppendFile:
        path = self.folder / LOG_DIR / segment_name(index)
        if self._segment is None or self._segment.path != path:
            if self._segment is not None:
                self._segment.close()
            try:
                path.parent.mkdir(exist_ok=True)
            except OSError as exc:
                raise output_error(path.parent, exc) from None
            self._segment = AppendFile(path, self.disk)
        return self._segment

    def convert_next(self) -> bool:
        """Write the oldest logged frame as its PNG and ``frames.csv`` row; ``False``
        when none is pending. Thread-safe against :meth:`log`.

        Raises:
            OutputError: it could not be written (it stays pending, retried next time);
                ``errno`` None: the frame is no image (dropped from the pending ones).
        """
        if not self._pending:
            return False
        entry, image = self._pending[0]
        path = self.folder / "frames" / frame_name(entry.index)
        if image is None:
            with open(entry.path, "rb") as fh:
                fh.seek(entry.offset)
                image = np.frombuffer(fh.read(entry.size),
                                      np.dtype(entry.dtype)).reshape(entry.shape)
        data = _encode_png(image, path)
        try:
            self.disk.replace_file(path, data)
        except OSError as exc:
            raise output_error(path, exc) from None
        self._frames.row([entry.index, entry.t_ns])
        self._pending.popleft()
        self.converted += 1
        self._unsynced.append(path)
        if (entry.index + 1) % FRAMES_PER_SEGMENT == 0 or (
                not self._pending and self._segment is not None
                and self._segment.path != entry.path):
            self._done_segments.append(entry.path)
        return True

    def skip_next(self) -> None:
        """Give up the oldest pending frame (it cannot be a PNG: no image)."""
        if self._pending:
            entry, _ = self._pending.popleft()
            if (entry.index + 1) % FRAMES_PER_SEGMENT == 0:
                self._done_segments.append(entry.path)

    def sync(self, durable: bool) -> None:
        """Delete the log segments whose frames are all PNGs; with ``durable``, first
        fsync those PNGs, the frames folder, ``frames.csv``, ``truth.csv`` and the log
        segment being written (what a power cut may then lose is bounded by the time
        since the last call).

        Raises:
            OutputError: an fsync failed (the segments are kept).
        """
        if durable:
            paths = [*self._unsynced, self.folder / "frames", self._frames.path]
            if self._truth is not None:
                paths.append(self._truth.path)
            seg = self._segment
            if seg is not None and not seg.closed:
                paths.append(seg.path)
            for p in paths:
                try:
                    self.disk.fsync(p)
                except FileNotFoundError:
                    pass
                except OSError as exc:
                    raise output_error(p, exc) from None
        self._unsynced.clear()
        done, self._done_segments = self._done_segments, []
        for p in done:
            with contextlib.suppress(OSError):
                p.unlink()

    def write_truth(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        """One ``truth.csv`` row (the vehicle pose in W at ``t_ns``), written whole."""
        if self._truth is None:
            self._truth = CsvFile(self.folder / "truth.csv", TRUTH_HEADER, self.disk)
        self._truth.row([int(t_ns), f"{x_m:.6f}", f"{y_m:.6f}",
                         f"{math.degrees(yaw_rad):.6f}"])

    def _truth_row(self, t_ns: int) -> None:
        pose = self._truth_of.lookup(t_ns) if self._truth_of is not None else None
        if pose is not None:
            self.write_truth(t_ns, *pose)

    def close(self) -> None:
        """Close the files; the log (and its folder) goes once every frame is a PNG."""
        if self._segment is not None:
            self._segment.close()
        if not self._pending:
            self.sync(False)
            wal = self.folder / LOG_DIR
            if wal.is_dir():
                for p in wal.glob("*.raw"):
                    with contextlib.suppress(OSError):
                        p.unlink()
                with contextlib.suppress(OSError):
                    wal.rmdir()
        for fh in (self._frames, self._truth):
            if fh is not None:
                fh.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def repair_recording(folder: str | Path, disk: Disk = OS_DISK) -> int:
    """Turn the frames left in a killed run's write-ahead log into PNGs and
    ``frames.csv`` rows, delete the log and stray temporaries; the frames converted.

    Raises:
        ConfigError: not a recording, or a ``frames.csv`` that does not read.
        OutputError: a file that cannot be written (nothing is lost: the log stays).
    """
    folder = Path(folder)
    Recording(folder)  # checks the whole folder
    rows = _read_csv(folder / "frames.csv", FRAMES_HEADER)
    listed = {int(r[0]) for r in rows}
    last = max((int(r[1]) for r in rows), default=None)
    todo = [e for e in read_frame_log(folder) if e.index not in listed]
    if last is not None and todo and todo[0].t_ns <= last:
        raise ConfigError(folder / LOG_DIR, None, "logged frames older than frames.csv's "
                          "last row: repair by hand")
    frames = AppendFile(folder / "frames.csv", disk, truncate=False)
    try:
        for e in todo:
            path = folder / "frames" / frame_name(e.index)
            try:
                disk.replace_file(path, _encode_png(load_logged(e), path))
            except OSError as exc:
                raise output_error(path, exc) from None
            frames.append([csv_line([e.index, e.t_ns])])
    finally:
        frames.close()
    shutil.rmtree(folder / LOG_DIR, ignore_errors=True)
    for tmp in (folder / "frames").glob(".*.png"):
        with contextlib.suppress(OSError):
            tmp.unlink()
    return len(todo)


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth rows: ``t_ns`` (N,), ``x_m``, ``y_m``, ``yaw_rad`` (N,)."""

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray

    def lookup(self, t_ns: int) -> tuple[float, float, float] | None:
        """The truth row with exactly this stamp, or ``None``."""
        i = int(np.searchsorted(self.t_ns, t_ns))
        if i < self.t_ns.size and self.t_ns[i] == t_ns:
            return float(self.x_m[i]), float(self.y_m[i]), float(self.yaw_rad[i])
        return None


@dataclass(frozen=True, eq=False)
class Odometry:
    """Wheel odometry rows of ``odometry.csv`` (SPEC §2), in time order.

    Attributes:
        t_ns: ``(N,)`` int64 stamps, strictly increasing.
        dx_m, dy_m: ``(N,)`` the vehicle's displacement in V since the previous row, m.
        dyaw_rad: ``(N,)`` its turn since the previous row, rad (counter-clockwise).
    """

    t_ns: np.ndarray
    dx_m: np.ndarray
    dy_m: np.ndarray
    dyaw_rad: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.size)


def _read_csv(path: Path, header: list[str]) -> list[list[str]]:
    try:
        # utf-8-sig: a byte-order mark (spreadsheets write one) is not part of the header
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(path, None, f"cannot read: {exc}") from None
    if not rows or [c.strip() for c in rows[0]] != header:
        found = ",".join(rows[0]) if rows else "an empty file"
        raise ConfigError(path, "header", f"expected `{','.join(header)}`, found `{found}`")
    out = []
    for n, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ConfigError(path, f"line {n}",
                              f"expected {len(header)} fields, found {len(row)}")
        out.append([c.strip() for c in row])
    return out


def _int(path: Path, line: int, col: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ConfigError(path, f"line {line}: {col}",
                          f"expected an integer, found {text!r}") from None


def _float(path: Path, line: int, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise ConfigError(path, f"line {line}: {col}", f"expected a number, found {text!r}")
    return v


def _stamps(path: Path, rows: list[list[str]]) -> np.ndarray:
    """Column 0 of ``rows`` as int64 ``t_ns`` (line numbers from 2 in errors)."""
    t = [_int(path, i + 2, "t_ns", r[0]) for i, r in enumerate(rows)]
    for i, v in enumerate(t):
        if not -(2**63) <= v < 2**63:
            raise ConfigError(path, f"line {i + 2}: t_ns", f"expected a 64-bit stamp in ns, "
                              f"found {v}")
    return np.array(t, dtype=np.int64)


def _stamped_rows(path: Path, header: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A ``t_ns`` + three numbers table: ``(t_ns (N,) int64, values (N, 3))``."""
    rows = _read_csv(path, header)
    t_ns = _stamps(path, rows)
    vals = np.array([[_float(path, i + 2, c, r[k]) for k, c in enumerate(header[1:], 1)]
                     for i, r in enumerate(rows)], dtype=float).reshape(-1, 3)
    return t_ns, vals


def load_odometry(path: str | Path) -> Odometry:
    """Read ``odometry.csv`` (``t_ns,dx,dy,dyaw_deg``) strictly: the exact header, one
    integer stamp and three finite numbers a row, stamps strictly increasing.

    Raises:
        ConfigError: naming the file, the line and the column.
    """
    path = Path(path)
    t, vals = _stamped_rows(path, ODOMETRY_HEADER)
    if t.size > 1 and np.any(np.diff(t) <= 0):
        bad = int(np.argmax(np.diff(t) <= 0)) + 3
        raise ConfigError(path, f"line {bad}: t_ns", "stamps must increase")
    return Odometry(t, vals[:, 0], vals[:, 1], np.radians(vals[:, 2]))


def load_truth(path: str | Path) -> Truth:
    """Read ``truth.csv`` (``t_ns,x,y,yaw_deg``), sorted by time."""
    path = Path(path)
    t, vals = _stamped_rows(path, TRUTH_HEADER)
    order = np.argsort(t, kind="stable")
    return Truth(t[order], vals[order, 0], vals[order, 1], np.radians(vals[order, 2]))


def check_frame_image(image: np.ndarray, path: str | Path, rig: Rig) -> None:
    """Raise a ConfigError naming ``path`` unless ``image`` is what SPEC §2 allows and
    the rig's camera expects: 8-bit grey ``(H, W)`` or BGR ``(H, W, 3)``, ``W x H`` the
    camera's ``image_width x image_height``."""
    if image.dtype != np.uint8:
        raise ConfigError(path, None, f"expected an 8-bit image, found {image.dtype} "
                          "(convert to 8-bit grey or BGR)")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        what = f"{image.shape[2]} channels" if image.ndim == 3 else f"{image.ndim} dimensions"
        raise ConfigError(path, None, f"expected grey or BGR, found {what}")
    h, w = image.shape[:2]
    cam = rig.camera
    if (w, h) != (cam.width, cam.height):
        raise ConfigError(path, None, f"the image is {w}x{h} but the camera "
                          f"({rig.camera_file or rig.source or 'the rig'}) is "
                          f"{cam.width}x{cam.height}: a frame must come from the calibrated "
                          "camera at its calibrated size")


class StoredFrames(SourceBase):
    """A recording's frames read in order (``read``) by index (``frame(k)``): the
    shared half of :class:`Recording` and the MCAP recording."""

    _i = 0

    def __len__(self) -> int:
        raise NotImplementedError

    def frame(self, k: int) -> Frame:
        raise NotImplementedError

    def read(self) -> Frame | None:
        if self._i >= len(self):
            return None
        f = self.frame(self._i)
        self._i += 1
        return f


class GuardedRecorder:
    """What the live loop asks of a recorder (``writer``, ``guard``, frames kept out):
    the shared half of the folder recorder (live.AsyncRecorder) and the MCAP one."""

    writer: Any
    guard: Any = None
    skipped_images = 0

    @property
    def count(self) -> int:
        """Frames recorded so far."""
        return self.writer.count

    @property
    def not_recorded(self) -> int:
        """Frames that a full disk (or a frame that is no image) kept out."""
        return (self.guard.lost if self.guard is not None else 0) + self.skipped_images


class Recording(StoredFrames):
    """A SPEC recording opened for reading; also a frame source.

    The whole folder is checked when opened: ``frames.csv`` header and rows, every
    frame file present, stamps increasing, ``rig.yaml`` and ``site.yaml`` valid
    (unless ``rig``/``site`` override them), ``truth.csv`` and ``odometry.csv`` when
    present (``truth``, ``odometry``: ``None`` when absent). Frames still in the
    write-ahead log of a killed run (``frames.wal/``) are frames too (``logged``
    counts them; :func:`repair_recording` makes them PNGs). A ``truth.csv`` none of
    whose stamps is a frame's is warned about (errors against it cannot be measured).
    """

    live = False  # stored stamps: the live loop stamps frames with its own clock
    dropped = 0

    def __init__(self, folder: str | Path, rig: Rig | str | Path | None = None,
                 site: Site | str | Path | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ConfigError(self.folder, None, "not a recording folder (not found)")
        fpath = self.folder / "frames.csv"
        rows = _read_csv(fpath, FRAMES_HEADER)
        index = [_int(fpath, n, "index", r[0]) for n, r in enumerate(rows, start=2)]
        seen: dict[int, int] = {}
        for n, i in enumerate(index, start=2):
            if not 0 <= i < 2**63:
                raise ConfigError(fpath, f"line {n}: index", f"expected an integer >= 0, "
                                  f"found {i}")
            if i in seen:
                raise ConfigError(fpath, f"line {n}: index",
                                  f"index {i} already listed on line {seen[i]}")
            seen[i] = n
        t_ns = _stamps(fpath, [r[1:] for r in rows]).tolist()
        for n, i in enumerate(index, start=2):
            if not (self.folder / "frames" / frame_name(int(i))).exists():
                raise ConfigError(fpath, f"line {n}",
                                  f"frame file frames/{frame_name(int(i))} is missing")
        self._logged = {e.index: e for e in read_frame_log(self.folder) if e.index not in seen}
        for e in sorted(self._logged.values(), key=lambda e: e.index):
            index.append(e.index)
            t_ns.append(e.t_ns)
        self.index = np.array(index, dtype=np.int64)
        self.t_ns = np.array(t_ns, dtype=np.int64)
        if self.t_ns.size > 1 and np.any(np.diff(self.t_ns) <= 0):
            bad = int(np.argmax(np.diff(self.t_ns) <= 0)) + 1
            where = f"line {bad + 2}" if bad < len(rows) else f"{LOG_DIR} frame {index[bad]}"
            raise ConfigError(fpath, f"{where}: t_ns", "stamps must increase")
        self.rig = rig if isinstance(rig, Rig) else Rig.load(
            rig if rig is not None else self.folder / "rig.yaml")
        self.site = site if isinstance(site, Site) else Site.load(
            site if site is not None else self.folder / "site.yaml")
        tpath = self.folder / "truth.csv"
        self.truth = load_truth(tpath) if tpath.exists() else None
        if self.truth is not None and self.t_ns.size and self.truth.t_ns.size \
                and not np.isin(self.t_ns, self.truth.t_ns).any():
            log.warning("%s: none of its %d stamps is a frame's stamp in frames.csv: "
                        "errors against truth cannot be measured", tpath,
                        self.truth.t_ns.size)
        opath = self.folder / "odometry.csv"
        self.odometry = load_odometry(opath) if opath.exists() else None
        self._i = 0

    @property
    def logged(self) -> int:
        """Frames read from the write-ahead log (a killed run's last frames)."""
        return len(self._logged)

    def __len__(self) -> int:
        return int(self.index.size)

    def frame(self, k: int) -> Frame:
        """The k-th frame listed in ``frames.csv`` (then in the write-ahead log)."""
        i = int(self.index[k])
        entry = self._logged.get(i)
        if entry is not None:
            image, path = load_logged(entry), entry.path
        else:
            path = self.folder / "frames" / frame_name(i)
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise ConfigError(path, None, "cannot decode the image (corrupt or not a PNG)")
        check_frame_image(image, path, self.rig)
        return Frame(image, int(self.t_ns[k]), i)



def guarded_log(recorder: Any, write: Callable[[], None], at: int | None = None) -> bool:
    """Run ``write`` (one frame into ``recorder.writer``) under ``recorder.guard``;
    whether the frame was written. A frame that is no image is counted in
    ``recorder.skipped_images`` (warned once) and never recorded; with a guard, a
    failing disk pauses the recording (``guard.failed``), without one it raises. The
    one policy of the folder recorder (live.AsyncRecorder) and the MCAP recorder.
    ``at`` is the run's frame number (the frame's ``index``, as the user sees it) that
    the guard's lines name; by default the recorder's own count.
    """
    guard = recorder.guard
    if guard is not None and not guard.due("log"):
        guard.skip()
        return False
    try:
        write()
    except OutputError as exc:
        if getattr(exc, "errno", 0) is None:  # not an image: never recordable
            recorder.skipped_images += 1
            if recorder.skipped_images == 1:
                log.warning("%s; not recorded", exc)
            return False
        if guard is None:
            raise
        guard.skip()
        guard.failed(exc, recorder.writer.count if at is None else at, "log")
        return False
    if guard is not None:
        guard.ok(recorder.writer.count - 1 if at is None else at, "log")
    return True


# --------------------------------------------------------------------------- poses
def _fmt(v: float | None, digits: int) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def pose_sigmas(est: PoseEstimate) -> tuple[float | None, float | None, float | None]:
    """``(sigma_x_m, sigma_y_m, sigma_yaw_deg)``: the 1-sigma of the pose in W from the
    diagonal of ``est.cov``; ``None`` for a term that is unobserved (infinite), not a
    number, or without a covariance."""
    cov = est.cov
    if cov is None:
        return None, None, None
    diag = np.diagonal(np.asarray(cov, dtype=float))
    out = [math.sqrt(v) if math.isfinite(v) and v >= 0 else None for v in diag[:3]]
    yaw = None if out[2] is None else math.degrees(out[2])
    return out[0], out[1], yaw


def pose_row(est: Estimate, latency_ms: float | None) -> list[str]:
    """One ``poses.csv`` row; a failure keeps its time and method, pose fields empty."""
    lat = _fmt(latency_ms, 3)
    if isinstance(est, PoseEstimate):
        sx, sy, syaw = pose_sigmas(est)
        return [str(int(est.t_ns)), _fmt(est.x_m, 6), _fmt(est.y_m, 6),
                _fmt(math.degrees(est.yaw_rad), 6), _fmt(est.lateral_m, 6), est.method,
                f"{est.quality:.3f}", lat, _fmt(sx, 6), _fmt(sy, 6), _fmt(syaw, 6)]
    return [str(int(est.t_ns)), "", "", "", "", est.method, "0.000", lat, "", "", ""]


def tum_seconds(t_ns: int) -> str:
    """``t_ns`` as decimal seconds with all nine digits, exactly (no float rounding:
    an epoch stamp in float seconds keeps only microseconds)."""
    t = int(t_ns)
    sign, t = ("-", -t) if t < 0 else ("", t)
    return f"{sign}{t // 1_000_000_000}.{t % 1_000_000_000:09d}"


def tum_line(t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> bytes:
    """One TUM row ``t_s x y z qx qy qz qw`` of a planar pose (z = 0, yaw about z)."""
    h = yaw_rad / 2
    return (f"{tum_seconds(t_ns)} {x_m:.6f} {y_m:.6f} 0 0 0 "
            f"{math.sin(h):.9f} {math.cos(h):.9f}\n").encode()


def write_truth_tum(truth: Truth, path: str | Path) -> Path:
    """``truth.csv``'s rows as a TUM trajectory (beside ``poses.tum``, for ``evo_ape``).

    Raises:
        OutputError: the file cannot be written.
    """
    path = Path(path)
    rows = [tum_line(int(t), float(x), float(y), float(a))
            for t, x, y, a in zip(truth.t_ns, truth.x_m, truth.y_m, truth.yaw_rad, strict=True)]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"".join(rows))
    except OSError as exc:
        raise OutputError(path, f"cannot write: {exc.strerror}") from None
    return path


class PoseWriter:
    """Writes ``poses.csv`` (SPEC §2), a row per frame, each row one whole write (never
    cut by a full disk); optionally a TUM trajectory (``t_s x y z qx qy qz qw``, z = 0,
    the yaw as a quaternion about z) beside it. TUM has no empty field, so it holds only
    the poses with both x and y: failures, and poses that leave a coordinate unobserved
    (the corridor method's, without x), are left out of it rather than given a made-up 0.

    Args:
        path, tum_path: the files (created or truncated).
        disk: how they are written (a fake in tests).
    """

    def __init__(self, path: str | Path, tum_path: str | Path | None = None,
                 disk: Disk = OS_DISK):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(self.path.parent, f"cannot create: {exc.strerror}") from None
        self._csv = CsvFile(self.path, POSES_HEADER, disk)
        self.rows = 0
        self.tum_path = None if tum_path is None else Path(tum_path)
        self._tum = None
        if self.tum_path is not None:
            try:
                self._tum = AppendFile(self.tum_path, disk)
            except OutputError:
                self._csv.close()
                raise

    def write(self, est: Estimate, latency_ms: float | None = None) -> None:
        """One row, and a TUM line for a pose with x and y.

        Raises:
            OutputError: the file cannot be written (a full disk: ``errno`` ENOSPC),
                naming it; nothing of the row was written.
        """
        self._csv.row(pose_row(est, latency_ms))
        self.rows += 1
        if self._tum is not None and isinstance(est, PoseEstimate) \
                and est.x_m is not None and est.y_m is not None:
            self._tum.append([tum_line(est.t_ns, est.x_m, est.y_m, est.yaw_rad)])

    def close(self) -> None:
        self._csv.close()
        if self._tum is not None:
            self._tum.close()

    def __enter__(self) -> PoseWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class PoseTable:
    """``poses.csv`` read back; missing fields are NaN (the sigmas too, in a file
    written before SPEC added them)."""

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    lateral_m: np.ndarray
    method: list[str]
    quality: np.ndarray
    latency_ms: np.ndarray
    sigma_x_m: np.ndarray
    sigma_y_m: np.ndarray
    sigma_yaw_rad: np.ndarray


def load_poses(path: str | Path) -> PoseTable:
    """Read ``poses.csv`` by column name (SPEC §2): the SPEC header, or its first eight
    columns alone (a file from before the sigma columns).

    Raises:
        ConfigError: another header, a row of the wrong length, a field that is not a
            number (naming file, line and column).
    """
    path = Path(path)
    try:
        rows = _read_csv(path, POSES_HEADER)
    except ConfigError as exc:
        if exc.key != "header":
            raise
        try:
            rows = [r + [""] * len(POSES_SIGMA_COLUMNS)
                    for r in _read_csv(path, POSES_HEADER[:8])]
        except ConfigError as short:
            if short.key != "header":
                raise
            raise exc from None

    def col(k: int) -> np.ndarray:
        name = POSES_HEADER[k]
        return np.array([_float(path, n, name, r[k]) if r[k] else math.nan
                         for n, r in enumerate(rows, start=2)], dtype=float)

    return PoseTable(_stamps(path, rows), col(1), col(2), np.radians(col(3)), col(4),
                     [r[5] for r in rows], col(6), col(7), col(8), col(9),
                     np.radians(col(10)))
