"""One exception tree for ceilkit.

Every error a user can cause (a bad file, a bad argument, a port that will not
open) is a :class:`CeilkitError`; the command lines catch only these, print one
line on stderr and exit 1. Anything else is a bug and keeps its traceback.

A frame on which a method cannot estimate is *not* an error: it is a
:class:`ceilkit.runtime.estimators.base.Failure` value.
"""

from __future__ import annotations

from pathlib import Path


class CeilkitError(Exception):
    """Root of every error ceilkit raises on purpose."""


class ConfigError(CeilkitError):
    """A config or data file (or an argument) is missing, malformed or impossible.

    The message names the file, the dotted key, what was expected and what was found,
    e.g. ``rig.yaml: mount.tilt: expected a number in [0, 90] degrees, found 120``.
    """

    def __init__(self, path: str | Path | None, key: str | None, message: str):
        self.path = None if path is None else str(path)
        self.key = key
        self.detail = message
        where = ": ".join(p for p in (self.path, key) if p)
        super().__init__(f"{where}: {message}" if where else message)


class CalibrationError(CeilkitError):
    """A calibration could not be solved (no board found, too few views, ...)."""


class CaptureError(CeilkitError):
    """A frame source could not be opened or read."""


class LinkError(CeilkitError):
    """A pose link (serial port, file) could not be opened or written."""


class OutputError(CeilkitError):
    """An output (poses, a recording, a calibration file) could not be written: a full
    disk, a missing folder, no permission, or a file that exists and was not to be
    overwritten. The message names the path and the cause (``no space left``)."""

    def __init__(self, path: str | Path, message: str):
        self.path = str(path)
        self.detail = message
        super().__init__(f"{self.path}: {message}")
