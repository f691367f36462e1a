"""Writing a SPEC recording folder (:class:`RecordingWriter`): at once (a PNG, then its
``frames.csv`` row) or live in two steps (the raw frame into the write-ahead log on the
loop's thread, the PNG later on another); :func:`repair_recording` turns what a killed
run left in the log into PNGs. :class:`GuardedRecorder` and :func:`guarded_log` are the
recording policy the live loop's recorders share (a full disk pauses, a frame that is
no image is skipped).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.files import (
    OS_DISK,
    AppendFile,
    CsvFile,
    Disk,
    csv_line,
    output_error,
    refuse_existing,
)
from ceilkit.runtime.io.frame_log import (
    FRAMES_PER_SEGMENT,
    LOG_DIR,
    RECORD,
    LoggedFrame,
    load_logged,
    read_frame_log,
    record_header,
    segment_name,
)
from ceilkit.runtime.io.provenance import version_line
from ceilkit.runtime.io.recording_reader import RECORDING_FILES, Recording, frame_name
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.io.tables import (
    FRAMES_HEADER,
    ODOMETRY_HEADER,
    TRUTH_HEADER,
    Truth,
    read_rows,
)

log = logging.getLogger("ceilkit.recording")


def encode_png(image: np.ndarray, path: Path) -> bytes:
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
        self._odometry: CsvFile | None = None     # odometry.csv, by write_odometry
        self._odometry_lock = threading.Lock()    # rows come from the link's thread
        self._t_odometry_ns: int | None = None
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
            header = f"# recorded by {version_line()}\n{header}"
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
        data = encode_png(frame.image, path.with_name("." + path.name))
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
        offset = seg.size + RECORD.size
        seg.append([record_header(index, frame, data), data])
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
        data = encode_png(image, path)
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

    def write_odometry(self, t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float) -> bool:
        """One ``odometry.csv`` row (SPEC §2: the increment in V since the previous row,
        ending at ``t_ns``), written whole, its numbers as received (``repr``: a replay
        feeds the very same values). Safe from another thread (the link's receive hook).
        A row not after the last one (the file's stamps increase) or one coming after
        :meth:`close` is not written: ``False``."""
        with self._odometry_lock:
            if self.closed or (self._t_odometry_ns is not None
                               and t_ns <= self._t_odometry_ns):
                return False
            if self._odometry is None:
                self._odometry = CsvFile(self.folder / "odometry.csv", ODOMETRY_HEADER,
                                         self.disk)
            self._odometry.row([int(t_ns), repr(float(dx_m)), repr(float(dy_m)),
                                repr(math.degrees(dyaw_rad))])
            self._t_odometry_ns = int(t_ns)
            return True

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
        with self._odometry_lock:
            for fh in (self._frames, self._truth, self._odometry):
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
    rows = read_rows(folder / "frames.csv", FRAMES_HEADER)
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
                disk.replace_file(path, encode_png(load_logged(e), path))
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
