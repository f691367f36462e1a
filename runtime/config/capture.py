"""capture.yaml: a camera's manual exposure and gain (what ``ceilcal exposure`` writes
and ``ceilrun --capture`` reads).

Layout (both keys optional; no other key)::

    exposure: 100.0      # manual exposure, the driver's units (V4L2: 100 us), > 0
    gain: 6.0            # manual gain, the driver's units (the simulator: dB)

Example::

    cap = load_capture("capture.yaml")
    source = open_source("/dev/video0", exposure=cap.exposure, gain=cap.gain)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .yaml import atomic_write_text, dump_yaml, load_yaml

CAPTURE_KEYS = ("exposure", "gain")


@dataclass(frozen=True)
class CaptureFile:
    """``exposure`` and ``gain`` from a capture file (None: not given)."""

    exposure: float | None = None
    gain: float | None = None


def load_capture(path: str | Path) -> CaptureFile:
    """Read a capture file strictly.

    Raises:
        ConfigError: naming the file and the key (unknown key, not a number, an
            exposure that is not positive).
    """
    node = load_yaml(path).mapping(CAPTURE_KEYS)
    exposure = node.get("exposure").number(0.0, lo_open=True) if node.has("exposure") \
        else None
    gain = node.get("gain").number() if node.has("gain") else None
    return CaptureFile(exposure, gain)


def save_capture(capture: CaptureFile, path: str | Path, header: Sequence[str] = ()) -> Path:
    """Write ``capture`` to ``path`` atomically, ``header`` lines as ``#`` comments."""
    data = {k: getattr(capture, k) for k in CAPTURE_KEYS if getattr(capture, k) is not None}
    text = "".join(f"# {line}\n" for line in header)
    atomic_write_text(path, dump_yaml(data, text))
    return Path(path)


__all__ = ["CAPTURE_KEYS", "CaptureFile", "load_capture", "save_capture"]
