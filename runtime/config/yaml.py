"""Strict reading of YAML config files into plain values.

Files are parsed once with ``yaml.safe_load``; every access goes through a
:class:`Node`, which knows the file and the dotted key it came from, so that any
problem becomes one :class:`~ceilkit.runtime.errors.ConfigError` line such as::

    configs/rig.yaml: mount.tilt: expected a number in [0, 90], found 120

Unknown keys are errors (SPEC §2), never ignored.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml

from ceilkit.runtime.errors import ConfigError

_MISSING = object()


def load_yaml(path: str | Path) -> Node:
    """Read ``path`` with ``yaml.safe_load`` and return its root :class:`Node`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise ConfigError(path, None, f"invalid YAML{where}: {problem}") from None
    if data is None:
        data = {}
    return Node(data, path, "")


def _describe(value: Any) -> str:
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return repr(value) if len(value) < 40 else "a string"
    if value is None:
        return "nothing (null)"
    return repr(value)


class Node:
    """A value read from a file, with the file and the dotted key it came from."""

    __slots__ = ("value", "path", "key")

    def __init__(self, value: Any, path: str | Path | None, key: str):
        self.value = value
        self.path = path
        self.key = key

    # -- errors ---------------------------------------------------------------
    def error(self, message: str) -> ConfigError:
        return ConfigError(self.path, self.key or None, message)

    def expected(self, what: str) -> ConfigError:
        return self.error(f"expected {what}, found {_describe(self.value)}")

    # -- navigation -----------------------------------------------------------
    def _child_key(self, name: str | int) -> str:
        if isinstance(name, int):
            return f"{self.key}[{name}]"
        return f"{self.key}.{name}" if self.key else name

    def mapping(self, allowed: Sequence[str], required: Sequence[str] = ()) -> Node:
        """Check this node is a mapping with only ``allowed`` keys and all ``required``."""
        if not isinstance(self.value, dict):
            raise self.expected("a mapping")
        for k in self.value:
            if k not in allowed:
                key = self._child_key(str(k))
                raise ConfigError(
                    self.path, key, f"unknown key (allowed here: {', '.join(allowed)})"
                )
        for k in required:
            if k not in self.value:
                raise ConfigError(self.path, self._child_key(k), "missing required key")
        return self

    def has(self, name: str) -> bool:
        return isinstance(self.value, dict) and name in self.value

    def get(self, name: str, default: Any = _MISSING) -> Node:
        if not isinstance(self.value, dict):
            raise self.expected("a mapping")
        if name not in self.value:
            if default is _MISSING:
                raise ConfigError(self.path, self._child_key(name), "missing required key")
            return Node(default, self.path, self._child_key(name))
        return Node(self.value[name], self.path, self._child_key(name))

    def items(self) -> Iterator[Node]:
        if not isinstance(self.value, list):
            raise self.expected("a list")
        for i, v in enumerate(self.value):
            yield Node(v, self.path, self._child_key(i))

    def __len__(self) -> int:
        return len(self.value) if isinstance(self.value, (list, dict)) else 0

    # -- scalars --------------------------------------------------------------
    def number(self, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, what: str = "") -> float:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.expected(f"a finite number{what}")
        v = float(v)
        bad_lo = lo is not None and (v <= lo if lo_open else v < lo)
        bad_hi = hi is not None and v > hi
        if bad_lo or bad_hi:
            lo_s = "-inf" if lo is None else f"{lo:g}"
            hi_s = "inf" if hi is None else f"{hi:g}"
            bracket = "(" if lo_open else "["
            raise self.error(f"expected a number in {bracket}{lo_s}, {hi_s}]{what}, found {v:g}")
        return v

    def integer(self, lo: int | None = None, hi: int | None = None) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.expected("an integer")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.error(f"expected an integer in [{lo}, {hi}], found {v}")
        return v

    def string(self, choices: Sequence[str] | None = None) -> str:
        v = self.value
        if not isinstance(v, str):
            raise self.expected("a string")
        if choices is not None and v not in choices:
            raise self.error(f"expected one of {', '.join(choices)}, found {v!r}")
        return v

    def numbers(self, length: int | None = None) -> list[float]:
        if not isinstance(self.value, list):
            raise self.expected(f"a list of {length} numbers" if length else "a list of numbers")
        if length is not None and len(self.value) != length:
            raise self.error(f"expected {length} numbers, found {len(self.value)}")
        return [n.number() for n in self.items()]


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that the file is either the old or the new one.

    The bytes go to a temporary file beside ``path``, are flushed to disk, then
    renamed over it; an existing file is never left half-written. The new file gets
    the usual mode (``0666`` less the umask), not ``mkstemp``'s ``0600``.

    Raises:
        ConfigError: naming ``path``, when it cannot be written.
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise ConfigError(path, None, f"cannot write: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise ConfigError(path, None, f"cannot write: {exc.strerror or exc}") from None


def atomic_write_text(path: str | Path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` encoded as UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def dump_yaml(data: Any, header: str = "") -> str:
    """YAML text for ``data`` (block style, keys in insertion order), after ``header``."""
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    return header + body
