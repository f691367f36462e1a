"""Strict reading of YAML config files into plain values.

Files are parsed once with a strict ``yaml.SafeLoader``; every access goes through a
:class:`Node`, which knows the file and the dotted key it came from, so that any
problem becomes one :class:`~ceilkit.runtime.errors.ConfigError` line such as::

    configs/rig.yaml: mount.tilt: expected a number in [0, 90], found 120

Unknown keys are errors (SPEC §2), never ignored; so are a key given twice in one
mapping (YAML would keep the last one silently) and a byte that is not UTF-8 (both
named with their line).
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml
from yaml.reader import ReaderError

from ceilkit.runtime.config.inputs import YAML_MAX_BYTES, read_input
from ceilkit.runtime.errors import ConfigError

_MISSING = object()


class DuplicateKeyError(yaml.YAMLError):
    """A mapping gives one key twice: ``key`` is the dotted key, lines are 1-based."""

    def __init__(self, key: str, line: int, first_line: int):
        super().__init__(f"{key}: given twice (line {line}, first at line {first_line})")
        self.key, self.line, self.first_line = key, line, first_line


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping.

    Before a document is constructed its node tree is walked once, keeping the dotted
    key of each mapping, so the error names where the second key is (merge keys
    ``<<`` may still be overridden, as YAML allows).
    """

    def construct_document(self, node: yaml.Node) -> Any:
        self._check_keys(node, "", set())
        return super().construct_document(node)

    def _check_keys(self, node: yaml.Node, key: str, seen: set[int]) -> None:
        if id(node) in seen:                      # an alias met again (or a cycle)
            return
        seen.add(id(node))
        if isinstance(node, yaml.SequenceNode):
            for i, child in enumerate(node.value):
                if not isinstance(child, yaml.ScalarNode):      # a scalar holds no key
                    self._check_keys(child, f"{key}[{i}]", seen)
        elif isinstance(node, yaml.MappingNode):
            first_line: dict[Any, int] = {}
            for key_node, value_node in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                name = self.construct_object(key_node, deep=True)
                child = f"{key}.{key_text(name)}" if key else key_text(name)
                line = key_node.start_mark.line + 1
                try:
                    if name in first_line:
                        raise DuplicateKeyError(child, line, first_line[name])
                    first_line[name] = line
                except TypeError:                 # unhashable key: the constructor says
                    pass
                self._check_keys(value_node, child, seen)


MAX_NUMBER_CHARS = 64
"""The longest number a YAML file may write, characters. Longer is an error: PyYAML
builds ``1:2:3...`` (YAML 1.1's base 60) in quadratic time and Python refuses an
integer of more than 4300 digits."""


def _check_number_length(node: yaml.ScalarNode) -> None:
    if len(node.value) > MAX_NUMBER_CHARS:
        raise yaml.constructor.ConstructorError(
            None, None, f"a number of {len(node.value)} characters (at most "
            f"{MAX_NUMBER_CHARS})", node.start_mark)


def _checked_number(construct: Any) -> Any:
    """``construct`` (a loader's int or float constructor) after the length check."""
    def checked(loader: yaml.BaseLoader, node: yaml.ScalarNode) -> Any:
        _check_number_length(node)
        return construct(loader, node)
    return checked


def _check_numbers(loader: type) -> None:
    """Give ``loader`` the number-length check on its int and float constructors."""
    for tag, construct in (("int", loader.construct_yaml_int),
                           ("float", loader.construct_yaml_float)):
        loader.add_constructor(f"tag:yaml.org,2002:{tag}", _checked_number(construct))


_check_numbers(StrictLoader)


FAST_YAML_BYTES = 64 << 10
"""A YAML input larger than this (a site of thousands of lights) is parsed by libyaml
(:class:`_FastStrictLoader`, when PyYAML has it: some 20 times faster), with the same
checks; any error is then reported by :class:`StrictLoader`, as for a small file."""


class _FastStrictLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """:class:`StrictLoader`'s checks (a key given twice, a number's length) on
    libyaml's parser."""

    _check_keys = StrictLoader._check_keys

    def construct_document(self, node: yaml.Node) -> Any:
        self._check_keys(node, "", set())
        return super().construct_document(node)


_check_numbers(_FastStrictLoader)


def _parse_fast(text: str) -> tuple[bool, Any]:
    """``(True, value)`` of ``text`` by :class:`_FastStrictLoader`, or ``(False, error)``
    when libyaml is not there (``None``) or the text is not a valid document (its
    ``YAMLError``: for a file up to :data:`SLOW_YAML_BYTES` the caller's
    :class:`StrictLoader` says why instead)."""
    if not getattr(yaml, "__with_libyaml__", False):
        return False, None
    loader = None
    try:
        loader = _FastStrictLoader(text)
        return True, loader.get_single_data()
    except yaml.YAMLError as exc:
        return False, exc
    finally:
        if loader is not None:
            loader.dispose()


SLOW_YAML_BYTES = 1 << 20
"""A YAML input larger than this that libyaml refuses is not parsed again in pure Python
to word the error (PyYAML's scanner is slower than linear on a long key: 8 MiB took 13 s):
libyaml's own error is reported."""


NUMBER_LIMIT = 1e9
"""The largest magnitude of a number a YAML file gives where its key sets no range."""


def key_text(name: Any, limit: int = 60) -> str:
    """A key as an error message names it: cut to its first characters and its length
    when longer than ``limit`` (a file with a 1 MB key gets a short line)."""
    text = str(name)
    return text if len(text) <= limit else f"{text[:40]}... ({len(text)} characters)"


def parse_yaml(data: bytes, path: str | Path | None = None) -> Any:
    """The value of the YAML document in ``data`` (UTF-8), read strictly.

    Raises:
        ConfigError: naming ``path`` and the line, for a byte that is not UTF-8,
            invalid YAML or a key given twice in one mapping (with its dotted key).
    """
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        line_start = data.rfind(b"\n", 0, exc.start) + 1
        column = len(data[line_start:exc.start].decode("utf-8", "replace")) + 1
        raise ConfigError(path, None, f"not UTF-8 text: byte 0x{data[exc.start]:02x} at "
                                      f"line {line}, column {column} (save the file as "
                                      f"UTF-8)") from None
    loader = None
    try:
        if len(data) > FAST_YAML_BYTES:
            ok, value = _parse_fast(text)
            if ok:
                return value
            if value is not None and len(data) > SLOW_YAML_BYTES:
                raise value
        loader = StrictLoader(text)             # checks the characters first
        return loader.get_single_data()
    except DuplicateKeyError as exc:
        raise ConfigError(path, exc.key, f"duplicate key at line {exc.line} (first given "
                                         f"at line {exc.first_line})") from None
    except RecursionError:  # ``[[[[...``: the parser recurses once per level
        raise ConfigError(path, None, "invalid YAML: nested too deeply (thousands of "
                                      "levels; a config file has a few)") from None
    except ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - (text.rfind("\n", 0, exc.position) + 1) + 1
        char = f" (#x{exc.character:04x})" if isinstance(exc.character, int) else ""
        raise ConfigError(path, None, f"invalid YAML at line {line}, column {column}: "
                                      f"{exc.reason}{char}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise ConfigError(path, None, f"invalid YAML{where}: {problem}") from None
    finally:
        if loader is not None:
            loader.dispose()


def load_yaml(path: str | Path) -> Node:
    """Read ``path`` strictly (:func:`parse_yaml`) and return its root :class:`Node`:
    a regular file of at most :data:`~ceilkit.runtime.config.inputs.YAML_MAX_BYTES`
    (:func:`~ceilkit.runtime.config.inputs.read_input`)."""
    path = Path(path)
    value = parse_yaml(read_input(path, YAML_MAX_BYTES), path)
    return Node({} if value is None else value, path, "")


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
                key = self._child_key(key_text(k))
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
        """A finite number in ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``); an open end
        (None) is :data:`NUMBER_LIMIT`: every number a file gives is bounded before
        any arithmetic is done with it."""
        lo = -NUMBER_LIMIT if lo is None else lo
        hi = NUMBER_LIMIT if hi is None else hi
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.expected(f"a finite number{what}")
        try:
            v = float(v)                  # a YAML integer may be too large for a float
        except OverflowError:
            v = math.inf
        if not math.isfinite(v):
            raise self.expected(f"a finite number{what}")
        bad_lo = lo is not None and (v <= lo if lo_open else v < lo)
        bad_hi = hi is not None and v > hi
        if bad_lo or bad_hi:
            lo_s = "-inf" if lo is None else f"{lo:g}"
            hi_s = "inf" if hi is None else f"{hi:g}"
            bracket = "(" if lo_open else "["
            raise self.error(f"expected a number in {bracket}{lo_s}, {hi_s}]{what}, found {v:g}")
        return v

    def integer(self, lo: int, hi: int) -> int:
        """An integer in ``[lo, hi]``: every integer a file gives is range-checked."""
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

    def numbers(self, length: int | None = None, lo: float | None = None,
                hi: float | None = None) -> list[float]:
        """A list of ``length`` (any when None) finite numbers, each in ``[lo, hi]``."""
        if not isinstance(self.value, list):
            raise self.expected(f"a list of {length} numbers" if length else "a list of numbers")
        if length is not None and len(self.value) != length:
            raise self.error(f"expected {length} numbers, found {len(self.value)}")
        return [n.number(lo, hi) for n in self.items()]


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
