"""Writing files whole: the :class:`Disk` every output goes through (the operating
system, or the fake :class:`FullDisk`), files appended by whole records
(:class:`AppendFile`, :class:`CsvFile`: a failed write is cut back, never half a row),
and the errors an output raises (:func:`output_error`, :func:`refuse_existing`).

A file that cannot be written is an :class:`~ceilkit.runtime.errors.OutputError`
naming it (its ``errno`` attribute says why: ``ENOSPC`` for a full disk).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

from ceilkit.runtime.errors import ConfigError, OutputError

FORCE_HINT = "force=True replaces it"
"""The end of the message refusing to overwrite; the command lines name their flag."""


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
