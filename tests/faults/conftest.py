"""Fixtures of the fault-injection suite: the ceilkit log lines of a test."""

from __future__ import annotations

import logging

import pytest


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@pytest.fixture
def log_lines():
    """The warnings the runtime logged during the test (whatever the CLI did to the
    ``ceilkit`` logger's propagation)."""
    handler = _Lines()
    root = logging.getLogger("ceilkit")
    root.addHandler(handler)
    level = root.level
    root.setLevel(logging.WARNING)
    try:
        yield handler.lines
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
