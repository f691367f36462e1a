"""Outputs that never overwrite what a user made (issue 40): the one check every writer
of a run calls before it writes, and the lock that keeps two runs out of one folder.

:func:`claim_outputs` refuses, before anything is written:

* an output that is one of the run's inputs, lies inside an input folder (a recording's
  ``frames/``, an image folder), or holds an input (``ConfigError`` keyed by the
  output's parameter, e.g. ``link``: the command line names its flag, ``--serial``);
* two outputs of one run on one path (``--serial OUT/poses.csv`` beside ``--out OUT``);
* an output file that exists, unless ``force`` (``PATH: already there; nothing was
  overwritten (force=True replaces it)``; the command lines say ``give --force``);

and takes the :class:`FolderLock` of every output folder first, and the lock of every
output file written on its own (:func:`file_lock`: ``.NAME.ceilkit.lock`` beside a
camera.yaml, a rig.yaml, a ``.param``), so that the check of what exists and the
writing after it are one run's alone. :func:`claimed` holds them for a ``with`` block.

A recording given as an input is its files (:func:`recording_inputs`): its
``frames.csv``, ``frames/``, ``frames.wal/``, rig, site, truth and odometry; an output
beside them in its folder (``REC/replay/``) is not inside an input.

Example::

    with contextlib.ExitStack() as stack:
        claim_outputs({"out": [out / "poses.csv"]}, folders={"out": [out]},
                      inputs=recording_inputs(rec), force=False, stack=stack)
        ...  # write
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import stat
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.io.files import output_error, refuse_existing

log = logging.getLogger("ceilkit.outputs")

LOCK_NAME = ".ceilkit.lock"
"""The lock file in an output folder: the holder's pid while a run writes there."""


def recording_inputs(recording: str | Path) -> list[Path]:
    """The inputs of a recording read by a run: a file (``.mcap``) itself; a folder's
    parts (``RECORDING_FILES``), so that outputs beside them are allowed."""
    # here, not at the top: a command that claims a file alone (``ceilcal board``)
    # need not import the recording reader (scipy, numba)
    from ceilkit.runtime.io.recording_reader import RECORDING_FILES

    path = Path(recording)
    return [path / n for n in RECORDING_FILES] if path.is_dir() else [path]


def _real(path: str | Path) -> Path:
    return Path(os.path.realpath(path))


def _inside(path: Path, folder: Path) -> bool:
    return folder in path.parents


def check_overlaps(inputs: Sequence[str | Path], outputs: Mapping[str, Sequence[Path]],
                   folders: Mapping[str, Sequence[Path]] | None = None) -> None:
    """Refuse outputs that are inputs, lie inside an input folder, hold an input, or are
    another output of the same run.

    Args:
        inputs: the files and folders read.
        outputs: by parameter name (``out``, ``record``, ``link``, ``tum``, ...), the
            files written.
        folders: by parameter name, the folders written into (``overlays``): refused
            when one is an input or inside one.

    Raises:
        ConfigError: keyed by the output's parameter, naming the path and the input.
    """
    read = [(_real(p), Path(p)) for p in inputs]
    items = [(key, Path(p), False) for key, paths in (folders or {}).items() for p in paths]
    items += [(key, Path(p), True) for key, paths in outputs.items() for p in paths]
    seen: dict[Path, str] = {}
    for key, path, is_file in items:
        target = _real(path)
        for r, shown in read:
            if r == target or (is_file and _inside(r, target)):
                raise ConfigError(None, key, f"{path} is an input of this run ({shown}): "
                                  "choose another output")
            if _inside(target, r) and r.is_dir():
                raise ConfigError(None, key, f"{path} lies inside an input of this run "
                                  f"({shown}): choose another output")
        if is_file:
            if seen.get(target, key) != key:
                raise ConfigError(None, key, f"{path} is already an output of this run: "
                                  "choose another")
            seen[target] = key


def claim_outputs(outputs: Mapping[str, Sequence[Path]], *,
                  folders: Mapping[str, Sequence[Path]] | None = None,
                  inputs: Sequence[str | Path] = (), force: bool = False,
                  stack: contextlib.ExitStack | None = None) -> None:
    """Check a run's outputs before anything is written (see the module docstring):
    :func:`check_overlaps`, then (with ``stack``) the lock of every folder in
    ``folders`` and of every output file outside them (:func:`file_lock`), released
    when ``stack`` closes, then no output file may exist unless
    ``force`` (a regular file or a folder: a FIFO or a device written to is not
    replaced).

    Raises:
        ConfigError: an output that is an input or another output; an existing file
            without ``force`` (naming it).
        OutputError: a folder or file another run is writing (its lock's pid), or a
            folder that cannot be created.
    """
    check_overlaps(inputs, outputs, folders)
    if stack is not None:
        done: set[Path] = set()
        for paths in (folders or {}).values():
            for folder in paths:
                if _real(folder) not in done:
                    done.add(_real(folder))
                    stack.enter_context(FolderLock(folder))
        for paths in outputs.values():
            for path in paths:  # a file outside the locked folders: its own lock beside it
                if _real(Path(path).parent) not in done and _lockable(Path(path)):
                    stack.enter_context(file_lock(path))
    if not force:
        for paths in outputs.values():
            for path in paths:  # a FIFO or a device (a link's pipe) is not replaced
                if Path(path).is_file() or Path(path).is_dir():
                    raise refuse_existing(path)


@contextlib.contextmanager
def claimed(outputs: Mapping[str, Sequence[Path]], *,
            folders: Mapping[str, Sequence[Path]] | None = None,
            inputs: Sequence[str | Path] = (), force: bool = False) -> Iterator[None]:
    """:func:`claim_outputs` with its locks held until the ``with`` block ends: a
    calibration claims its file before minutes of work, and a second run started
    meanwhile is refused at once instead of writing over the first one's file."""
    with contextlib.ExitStack() as stack:
        claim_outputs(outputs, folders=folders, inputs=inputs, force=force, stack=stack)
        yield


def file_lock(path: str | Path) -> FolderLock:
    """The lock of an output file written on its own (a camera.yaml, a board's PDF):
    ``.NAME.ceilkit.lock`` beside it (``.camera.yaml.ceilkit.lock``)."""
    path = Path(path)
    return FolderLock(path.parent, f".{path.name}{LOCK_NAME}", subject=path)


def _lockable(path: Path) -> bool:
    """Whether an output file gets a lock beside it: a file to be made or a regular file
    (not a device or a FIFO written to, e.g. a link's ``/dev/ttyUSB0``)."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except FileNotFoundError:
        return True
    except OSError:
        return False


_HELD = threading.local()
"""The locks this thread holds (real lock path -> depth): a run's own nested claim (the
guided calibration's mount step, in its locked folder) takes them again."""


def _held() -> dict[Path, int]:
    if not hasattr(_HELD, "paths"):
        _HELD.paths = {}
    return _HELD.paths


def _pid_in(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class FolderLock:
    """The lock of an output folder: ``FOLDER/.ceilkit.lock`` holding the pid of the
    run writing there, with an exclusive ``flock`` on it (the kernel drops it when the
    process dies, however it dies). A second run is refused while the first holds it;
    a lock file left by a run that was killed is taken over, with a line saying whose
    it was. The folder is created when missing, and removed again on release if it
    was created here and is empty (a refused run leaves nothing behind). ``name``:
    another lock file (``.run.mcap.lock``: the lock of one file beside others), and
    ``subject`` that file (the refusal names it: ``another run is writing it``). A lock
    the same thread already holds is taken again (a step of the run that holds it) and
    released with the outermost.

    Raises:
        OutputError: another run holds the lock (naming its pid); the folder or the
            lock cannot be created.
    """

    def __init__(self, folder: str | Path, name: str = LOCK_NAME,
                 subject: str | Path | None = None):
        self.folder = Path(folder)
        self.path = self.folder / name
        self.subject = subject  # the one file this lock is of (named when refused)
        self.fd = -1
        self.created = False
        self.nested = False

    def __enter__(self) -> FolderLock:
        key = _real(self.path)
        if key in _held():
            _held()[key] += 1
            self.nested = True
            return self
        self.created = not self.folder.exists()
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self.fd = self._acquire()
        except OSError as exc:
            self._remove_folder()
            raise output_error(self.path, exc) from None
        except OutputError:
            self._remove_folder()
            raise
        _held()[key] = 1
        return self

    def _acquire(self) -> int:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                pid = _pid_in(fd)
                os.close(fd)
                if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                    raise
                raise OutputError(self.subject or self.folder, f"another run (pid "
                                  f"{pid or '?'}) is writing "
                                  f"{'it' if self.subject else 'here'} ({self.path}); "
                                  "nothing was written: wait for it or choose another "
                                  "output") from None
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:  # not a lock file its holder removed while we opened it
                break
            os.close(fd)
        old = _pid_in(fd)
        if old is not None and old != os.getpid():
            log.warning("%s: took over the stale lock of pid %d (%s)", self.path, old,
                        "which no longer holds it" if _alive(old) else "no longer running")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return fd

    def _remove_folder(self) -> None:
        if self.created:
            with contextlib.suppress(OSError):
                self.folder.rmdir()

    def __exit__(self, *exc: object) -> None:
        if self.nested:
            self.nested = False
            _held()[_real(self.path)] -= 1
            return
        if self.fd < 0:
            return
        _held().pop(_real(self.path), None)
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self.fd)
        self.fd = -1
        self._remove_folder()
