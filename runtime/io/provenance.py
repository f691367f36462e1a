"""What wrote a file: the package's version, named in every output's header.

Every file ceilkit writes names the version that wrote it where its format has room for
a comment (YAML and TUM ``#`` lines, the HTML report, the MCAP metadata); a format that
has none (``poses.csv``, ``frames.csv``, whose first line is their SPEC header) has a
``run.yaml`` beside it (:func:`run_metadata`) that names the version, the time and the
command line.

Example::

    >>> version_line().startswith("ceilkit ")
    True
"""

from __future__ import annotations

import shlex
import sys
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version

PACKAGE = "ceilkit"


def package_version() -> str:
    """The installed package's version (``0.1.0``), or ``unknown`` when it is run from
    a source tree that was never installed."""
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        return "unknown"


VERSION = package_version()
"""This package's version, read once."""


def version_line() -> str:
    """``ceilkit 0.1.0``: the line ``--version`` prints and file headers carry."""
    return f"{PACKAGE} {VERSION}"


RUN_METADATA = "run.yaml"
"""The file beside ``poses.csv`` (and in a recording) naming what wrote the folder."""


def run_metadata(what: str, command: str | None = None,
                 now: datetime | None = None) -> str:
    """The text of a :data:`RUN_METADATA` file (YAML): what the folder holds, the
    version, the time (UTC) and the command line (default this process's ``sys.argv``)."""
    now = now or datetime.now(timezone.utc)
    command = shlex.join(sys.argv) if command is None else command
    return "".join(f"{key}: {_quoted(value)}\n" for key, value in (
        ("written_by", version_line()), ("what", what),
        ("written", now.isoformat(timespec="seconds")), ("command", command)))


def _quoted(text: str) -> str:
    """``text`` as a YAML double-quoted scalar (any characters survive)."""
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{escaped}"'


__all__ = ["PACKAGE", "RUN_METADATA", "VERSION", "package_version", "run_metadata",
           "version_line"]
