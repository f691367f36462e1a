"""Reading an input file with limits: the one place a config or data file is opened.

Every YAML file (rig, site, camera, capture, presets, placements) and every CSV table
(``frames.csv``, ``truth.csv``, ``odometry.csv``, ``poses.csv``, a pose file) is read
by :func:`read_input`:

* only a **regular file** (or a link to one): a folder, a FIFO, a device such as
  ``/dev/zero`` or a socket is one line, never a block (a FIFO is opened without
  waiting for a writer) or an endless read;
* at most a **size cap**: :data:`YAML_MAX_BYTES` for YAML (a site of 100 000 lights,
  2.5 MiB, parses in about 3 s), :data:`CSV_MAX_BYTES` for CSV (about 3 million
  rows of ``poses.csv``, a day at 30 fps).

Example::

    data = read_input("rig.yaml", YAML_MAX_BYTES)
    # ConfigError: rig.yaml: expected a regular file, found a FIFO (named pipe)
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ceilkit.runtime.errors import ConfigError

YAML_MAX_BYTES = 8 << 20
"""The largest YAML input read, bytes (8 MiB: some 300 000 lights in a site; a file
this large is parsed by libyaml, :data:`~ceilkit.runtime.config.yaml.FAST_YAML_BYTES`)."""

CSV_MAX_BYTES = 256 << 20
"""The largest CSV input read, bytes (256 MiB)."""

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def size_text(n: int) -> str:
    """``n`` bytes for a message: ``512 bytes``, ``3.2 KiB``, ``1 MiB``."""
    if n < 1024:
        return f"{n} bytes"
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        n /= 1024
        if n < 1024 or unit == "TiB":
            return f"{n:.3g} {unit}"
    raise AssertionError("unreachable")


def _check_regular(path: str | Path, mode: int) -> None:
    if not stat.S_ISREG(mode):
        kind = next((k for test, k in _KINDS if test(mode)), "something else")
        raise ConfigError(path, None, f"expected a regular file, found {kind}")


def require_regular_file(path: str | Path) -> None:
    """Refuse ``path`` unless it is a regular file (or a link to one), for an input
    read as a stream with no size cap (an MCAP recording).

    Raises:
        ConfigError: naming ``path``: not found, or what it is instead.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read: {exc.strerror or exc}") from None
    _check_regular(path, st.st_mode)


def read_input(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, which must hold at most ``max_bytes``.

    Raises:
        ConfigError: naming ``path``: not found, not a regular file (a folder, a FIFO,
            a device: what it is), larger than ``max_bytes`` (both sizes), or not
            readable (the system's reason).
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        _check_regular(path, st.st_mode)
        if st.st_size > max_bytes:
            raise ConfigError(path, None, f"expected a file of at most "
                                          f"{size_text(max_bytes)}, found "
                                          f"{size_text(st.st_size)}")
        chunks, left = [], max_bytes + 1
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if left <= 0:                                   # grew while being read
        raise ConfigError(path, None, f"expected a file of at most {size_text(max_bytes)}")
    return b"".join(chunks)
