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

import numpy as np

from ceilkit.runtime.geometry.rotations import wrap_pi

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


def line_headings(p1_norm: np.ndarray, p2_norm: np.ndarray, R_vehicle_cam: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per line (two normalized image points each, ``(N, 2)``): the heading
    ``atan2(m_x, m_y)`` of eq. 10 (modulo pi/2 on a grid) and its weight ``|m_xy|^2``."""
    a = np.asarray(p1_norm, float).reshape(-1, 2)
    b = np.asarray(p2_norm, float).reshape(-1, 2)
    # l = (x1, y1, 1) x (x2, y2, 1), written out
    ln = np.empty((a.shape[0], 3))
    ln[:, 0] = a[:, 1] - b[:, 1]
    ln[:, 1] = b[:, 0] - a[:, 0]
    ln[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    m = ln @ np.asarray(R_vehicle_cam, float).T                      # R_VC l, row-wise
    m /= np.maximum(np.sqrt((m * m).sum(axis=1)), 1e-300)[:, None]
    return np.arctan2(m[:, 0], m[:, 1]), m[:, 0] ** 2 + m[:, 1] ** 2


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
    phi, w = line_headings(p1_norm, p2_norm, R_vehicle_cam)
    ok = np.isfinite(phi) & (w > 1e-12)
    if np.count_nonzero(ok) < MIN_LINES:
        return None
    return _near_hint(_weighted(phi[ok], w[ok], period_rad), hint_yaw_rad)


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
    phi, w = line_headings(p1_norm, p2_norm, R_vehicle_cam)
    if weights is not None:
        w = w * np.asarray(weights, float)
    ok = np.isfinite(phi) & (w > 1e-12)
    if np.count_nonzero(ok) < MIN_LINES:
        return None, np.zeros(len(phi), bool)

    def near(ref: float, gate: float) -> np.ndarray:
        return ok & (np.abs(_wrapped(phi - ref, period_rad)) < gate)

    ref = hint_yaw_rad if hint_yaw_rad is not None else _mean(phi[ok], w[ok], period_rad)
    if hint_yaw_rad is None:
        sel = near(ref, 3 * gate_rad)
        if np.count_nonzero(sel) >= MIN_LINES:
            ref = _mean(phi[sel], w[sel], period_rad)
    kept = near(ref, gate_rad)
    if np.count_nonzero(kept) < MIN_LINES:
        return None, kept
    return _near_hint(_weighted(phi[kept], w[kept], period_rad), hint_yaw_rad), kept


def _wrapped(a: np.ndarray, period_rad: float) -> np.ndarray:
    """``a`` modulo the period, in ``[-period/2, period/2)``."""
    return np.remainder(a + period_rad / 2, period_rad) - period_rad / 2


def _mean(phi: np.ndarray, w: np.ndarray, period_rad: float) -> float:
    """The weighted circular mean of line headings modulo the period."""
    k = 2 * math.pi / period_rad
    z = np.sum(w * np.exp(1j * k * phi))
    return math.atan2(z.imag, z.real) / k


def _near_hint(h: ParallelsHeading, hint_yaw_rad: float | None) -> ParallelsHeading:
    """``h`` on the branch nearest ``hint_yaw_rad`` (unchanged without a hint)."""
    if hint_yaw_rad is None:
        return h
    yaw = hint_yaw_rad + math.remainder(h.yaw_rad - hint_yaw_rad, h.period_rad)
    return ParallelsHeading(wrap_pi(yaw), h.sigma_rad, h.period_rad, h.n_lines)


def _weighted(phi: np.ndarray, w: np.ndarray, period_rad: float) -> ParallelsHeading:
    """The weighted circular mean of line headings and its sigma (see the module)."""
    yaw = _mean(phi, w, period_rad)
    res = _wrapped(phi - yaw, period_rad)
    dof = max(len(phi) - 1, 1)
    sigma = max(math.sqrt(float(np.sum(w * res * res)) / float(np.sum(w)) / dof),
                SIGMA_FLOOR_RAD)
    return ParallelsHeading(wrap_pi(yaw), sigma, period_rad, int(len(phi)))
