"""Heading from ceiling parallels (Xu et al., eqs. 8-10), given the rig's rotation.

A ceiling line parallel to W's x axis has direction ``d_W = (1, 0, 0)``; seen by a
camera of mount ``R_VC`` on a vehicle of heading ``phi`` its direction in C is
``R_VC^T Rz(-phi) e_x``. The image line through two normalized points ``p1, p2``
(homogeneous) has the normal ``l = p1 x p2`` of the plane it spans with the optical
centre, and the line's direction lies in that plane: with ``m = R_VC l`` (in V),

    x-parallel:  m_x cos(phi) - m_y sin(phi) = 0          (eqs. 8 and 10)
    y-parallel:  m_x sin(phi) + m_y cos(phi) = 0          (eq. 9)

so each line gives ``phi = atan2(m_x, m_y)`` modulo pi (x) or that plus pi/2 (y): on a
grid of both, modulo pi/2. The lines' headings are combined as a weighted circular mean
of ``4 phi`` (weights ``|m_xy|^2``, the plane's tilt off the vertical); the branch is the
one nearest a given heading (a block's, the tracker's) when there is one, and the fusion
takes the heading with its period (``yaw_period_rad``) otherwise.

Pure math: arrays in, a frozen dataclass or None out. Fewer than two lines: None.

Example::

    h = heading_from_parallels(p1_norm, p2_norm, rig.mount.R_vehicle_cam)
    h.yaw_rad, h.sigma_rad, h.period_rad
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

PERIOD_RAD = math.pi / 2      # lines along both axes: heading known modulo a quarter turn
MIN_LINES = 2
SIGMA_FLOOR_RAD = math.radians(0.002)


@dataclass(frozen=True)
class ParallelsHeading:
    """A heading from ceiling parallels.

    Attributes:
        yaw_rad: the vehicle's heading in W (the branch nearest the hint, if given).
        sigma_rad: its 1-sigma, from the lines' spread about it (floored).
        period_rad: the heading is known modulo this (pi/2).
        n_lines: lines used.
    """

    yaw_rad: float
    sigma_rad: float
    period_rad: float
    n_lines: int


class HeadingGate(NamedTuple):
    """How :func:`_robust` picks and combines the lines: the reference heading ``hint``
    (rad, in W) when ``has_hint``, the gate ``gate`` (rad) about it, the heading's
    ``period`` (rad), the fewest lines ``min_lines`` and the sigma's floor ``floor``
    (rad)."""

    hint: float
    has_hint: bool
    gate: float
    period: float
    min_lines: int
    floor: float


def heading_from_parallels(p1_norm: np.ndarray, p2_norm: np.ndarray,
                           R_vehicle_cam: np.ndarray, hint_yaw_rad: float | None = None,
                           period_rad: float = PERIOD_RAD) -> ParallelsHeading | None:
    """The vehicle heading from ceiling lines parallel to W's axes (see the module).

    Args:
        p1_norm, p2_norm: ``(N, 2)`` two normalized (undistorted) points of each line.
        R_vehicle_cam: the mount's rotation (tilt, swing and pan calibrated).
        hint_yaw_rad: a heading near the truth (a block's, the tracker's): picks the
            branch; None: the branch in ``[-period/2, period/2)``.
        period_rad: pi/2 for lines along both axes, pi when all are along x.

    Returns:
        :class:`ParallelsHeading`, or None with fewer than :data:`MIN_LINES` lines.
    """
    return robust_heading(p1_norm, p2_norm, R_vehicle_cam, hint_yaw_rad, math.inf, None,
                          period_rad)[0]                      # (no gate: every line)


def robust_heading(p1_norm: np.ndarray, p2_norm: np.ndarray, R_vehicle_cam: np.ndarray,
                   hint_yaw_rad: float | None = None, gate_rad: float = math.radians(1.0),
                   weights: np.ndarray | None = None, period_rad: float = PERIOD_RAD
                   ) -> tuple[ParallelsHeading | None, np.ndarray]:
    """:func:`heading_from_parallels` on the lines that agree: lines off the ceiling's
    axes (a marker turned 45 degrees, clutter) are dropped. The reference is the hint
    when given, else the weighted circular mean of all lines refined once with a gate
    of 3 ``gate_rad``; lines within ``gate_rad`` (modulo the period) of it are kept.

    ``weights`` (``(N,)``, e.g. the lines' lengths) multiply eq. 10's ``|m_xy|^2``.

    Returns:
        ``(heading or None, kept)``: ``kept`` is the ``(N,)`` mask of the lines used.
    """
    p1 = arr(p1_norm, np.float64).reshape(-1, 2)
    p2 = arr(p2_norm, np.float64).reshape(-1, 2)
    wts = (np.ones(p1.shape[0]) if weights is None
           else arr(weights, np.float64).reshape(-1))
    kept = np.zeros(p1.shape[0], np.bool_)
    gate = HeadingGate(0.0 if hint_yaw_rad is None else float(hint_yaw_rad),
                       hint_yaw_rad is not None, float(gate_rad), float(period_rad),
                       MIN_LINES, SIGMA_FLOOR_RAD)
    found, yaw, sigma, n = _robust(p1, p2, arr(R_vehicle_cam, np.float64), wts, gate, kept)
    if not found:
        return None, kept
    return _near_hint(ParallelsHeading(wrap_pi(yaw), sigma, period_rad, n), hint_yaw_rad), kept


@njit
def _robust(p1, p2, R, weights, how, kept):  # pragma: no cover - compiled
    """:func:`robust_heading` in one loop: ``(found, yaw, sigma, n)`` and ``kept (N,)``
    (the lines used) set, the lines picked and combined as ``how`` (a
    :class:`HeadingGate`) says. Each line's heading is eq. 10's ``atan2(m_x, m_y)``
    (modulo the period) with ``m = R l / |R l|``, ``l = (x1, y1, 1) x (x2, y2, 1)``, and
    its weight ``|m_xy|²`` times ``weights``; the heading is their weighted circular
    mean (:func:`_circular_mean`), its sigma their weighted spread about it (floored)."""
    hint, has_hint, gate, period = how.hint, how.has_hint, how.gate, how.period
    min_lines, floor = how.min_lines, how.floor
    n_l = p1.shape[0]
    phi = np.empty(n_l)
    w = np.empty(n_l)
    ok = np.zeros(n_l, np.bool_)
    n_ok = 0
    for i in range(n_l):
        l0 = p1[i, 1] - p2[i, 1]
        l1 = p2[i, 0] - p1[i, 0]
        l2 = p1[i, 0] * p2[i, 1] - p1[i, 1] * p2[i, 0]
        m0 = l0 * R[0, 0] + l1 * R[0, 1] + l2 * R[0, 2]
        m1 = l0 * R[1, 0] + l1 * R[1, 1] + l2 * R[1, 2]
        m2 = l0 * R[2, 0] + l1 * R[2, 1] + l2 * R[2, 2]
        inv = 1.0 / max(math.sqrt(m0 * m0 + m1 * m1 + m2 * m2), 1e-300)
        m0, m1 = m0 * inv, m1 * inv
        phi[i] = math.atan2(m0, m1)
        w[i] = (m0 * m0 + m1 * m1) * weights[i]
        ok[i] = math.isfinite(phi[i]) and w[i] > 1e-12
        n_ok += ok[i]
    if n_ok < min_lines:
        return False, 0.0, 0.0, 0
    ref = hint if has_hint else _circular_mean(phi, w, ok, period)
    if not has_hint:
        sel = ok & (np.abs(_wrap_period(phi - ref, period)) < 3 * gate)
        if sel.sum() >= min_lines:
            ref = _circular_mean(phi, w, sel, period)
    kept[:] = ok & (np.abs(_wrap_period(phi - ref, period)) < gate)
    n = int(kept.sum())
    if n < min_lines:
        return False, 0.0, 0.0, 0
    yaw = _circular_mean(phi, w, kept, period)
    res = _wrap_period(phi - yaw, period)
    sw = swr = 0.0
    for i in range(n_l):
        if kept[i]:
            sw += w[i]
            swr += w[i] * res[i] * res[i]
    sigma = max(math.sqrt(swr / sw / max(n - 1, 1)), floor)
    return True, yaw, sigma, n


@njit
def _circular_mean(phi, w, use, period):  # pragma: no cover - compiled
    """The weighted circular mean of the headings ``phi`` of the lines ``use``, modulo
    the period."""
    k = 2 * math.pi / period
    zr = zi = 0.0
    for i in range(phi.size):
        if use[i]:
            zr += w[i] * math.cos(k * phi[i])
            zi += w[i] * math.sin(k * phi[i])
    return math.atan2(zi, zr) / k


@njit
def _wrap_period(a, period):  # pragma: no cover - compiled
    """``a`` modulo the period, in ``[-period/2, period/2)``."""
    return np.remainder(a + period / 2, period) - period / 2


def _near_hint(h: ParallelsHeading, hint_yaw_rad: float | None) -> ParallelsHeading:
    """``h`` on the branch nearest ``hint_yaw_rad`` (unchanged without a hint)."""
    if hint_yaw_rad is None:
        return h
    yaw = hint_yaw_rad + math.remainder(h.yaw_rad - hint_yaw_rad, h.period_rad)
    return ParallelsHeading(wrap_pi(yaw), h.sigma_rad, h.period_rad, h.n_lines)


@warmer
def _warm() -> None:
    p1 = np.array([[0.0, 0.0], [0.0, 0.1], [0.1, 0.0]])
    robust_heading(p1, p1 + [0.2, 0.0], np.eye(3), None)
    robust_heading(p1, p1 + [0.2, 0.0], np.eye(3), 0.0, weights=np.ones(3))
