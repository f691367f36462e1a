"""Bit counts in compiled loops: a marker's code read against its dictionary
(``estimators/block/detect.py``), a ceiling feature's binary descriptor against the
map's (``estimators/texture/match.py``), both as 64-bit words."""

from __future__ import annotations

import numpy as np

from ceilkit.runtime.jit import njit, warmer


@njit
def popcount(x):  # pragma: no cover - compiled
    """The set bits of a uint64 (SWAR: pairs, nibbles, bytes, then one multiply)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@warmer
def _warm() -> None:
    popcount(np.uint64(3))


__all__ = ["popcount"]
