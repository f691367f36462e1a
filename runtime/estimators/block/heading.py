"""The block method's heading stage: the ceiling's parallels measured on a frame
(:mod:`.parallels` turns them into a heading, Xu et al. eqs. 8-10).

With a pose near the truth (a block's fix, the tracker's prior) and the site's ceiling
lines (its corridor section), the lines are measured where they must be
(:func:`.seams.predicted_chords`, ``mode = "predicted"``); else segments are detected on
the frame (FastLineDetector, ``mode = "detected"``). Segments in the site's ``ignore``
regions are not used (SPEC §2) when a pose places them.

Example::

    stage = ParallelsStage(geo, site, min_px=60.0, gate_deg=1.0)
    h = stage(grey, hint_yaw_rad, pose)       # ParallelsHeading or None; stage.mode
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.block.parallels import (
    PERIOD_RAD,
    ParallelsHeading,
    robust_heading,
)
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.estimators.block.seams import MAX_CHORDS, predicted_chords
from ceilkit.runtime.estimators.ignore import IgnoreRegions
from ceilkit.runtime.features.lines import (
    SegmentDetector,
    refine_chords,
    refine_undistorted,
    segment_lengths,
)
from ceilkit.runtime.geometry.fits import student


class ParallelsStage:
    """The heading from a frame's ceiling parallels (see the module).

    Args:
        geo: the rig and ceiling.
        site: the site (its corridor section's lines, its ignore regions).
        min_px: shortest detected segment used as a parallel.
        gate_deg: a line farther than this from the heading (modulo the period) is not
            a parallel of the ceiling's axes.
    """

    def __init__(self, geo: PlanarGeometry, site: Any, min_px: float, gate_deg: float
                 ) -> None:
        self.geo, self.site = geo, site
        self.corridor = site.corridor if site.has_section("corridor") else None
        self.gate_rad = math.radians(gate_deg)
        self.min_px = float(min_px)
        self._detector: SegmentDetector | None = None     # made on first use
        self.ignore = IgnoreRegions(geo, site) if site.ignore_m else None
        self.mode = ""           # how the last heading's lines were found

    def __call__(self, grey: np.ndarray, hint: float | None,
                 pose: np.ndarray | None = None, max_chords: int = MAX_CHORDS
                 ) -> ParallelsHeading | None:
        """The heading from ``grey`` ``(H, W)`` uint8, the branch nearest ``hint``
        (radians, or None), the lines predicted from ``pose`` ``(x, y, yaw)`` when
        given (at most ``max_chords`` chords); None with fewer than two lines."""
        segs = np.zeros((0, 4))
        if pose is not None and self.corridor is not None:
            segs = predicted_chords(self.geo, self.corridor, pose, max_chords, self.site)
            mode = "predicted"
        if len(segs) < 2:
            if self._detector is None:
                self._detector = SegmentDetector("fld", self.min_px)
            segs = self._detector(grey)
            mode = "detected"
        if len(segs) < 2:
            return None
        # predicted chords sit within a pixel or two of their line: no wider retry, one
        # compiled call (refine_chords)
        if mode == "predicted":
            sn, _, rms = refine_chords(self.geo.camera, grey, segs)
        else:
            sn, _, rms = refine_undistorted(self.geo.camera, grey, segs)
        good = np.isfinite(rms) if mode == "predicted" else np.ones(len(sn), bool)
        if self.ignore is not None and pose is not None:    # SPEC §2: not in a region
            good &= self.ignore.keep_segments(sn, pose)
        length = segment_lengths(segs)
        h, kept = robust_heading(sn[good, :2], sn[good, 2:], self.geo.R_vehicle_cam, hint,
                                 self.gate_rad, length[good], PERIOD_RAD)
        self.mode = mode
        if h is None:
            return None
        w = line_weights(sn[good, :2], sn[good, 2:], self.geo.R_vehicle_cam, length[good])
        return dataclasses.replace(h, sigma_rad=h.sigma_rad * few_lines_factor(w[kept]))


def line_weights(p1_norm: np.ndarray, p2_norm: np.ndarray, R_vehicle_cam: np.ndarray,
                 length: np.ndarray) -> np.ndarray:
    """``(N,)`` the weights :func:`.parallels.robust_heading` gives lines through the
    normalized points ``p1, p2 (N, 2)``: eq. 10's ``|m_xy|²`` (``m = R l / |R l|``, ``l``
    the plane of the line and the optical centre) times ``length``."""
    ones = np.ones((len(p1_norm), 1))
    m = np.cross(np.hstack([p1_norm, ones]), np.hstack([p2_norm, ones])) @ \
        np.asarray(R_vehicle_cam, float).T
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    return (m[:, 0] ** 2 + m[:, 1] ** 2) * np.asarray(length, float)


def few_lines_factor(w: np.ndarray) -> float:
    """The factor (>= 1) on :func:`.parallels.robust_heading`'s sigma (the lines' weighted
    spread over ``n - 1``) for lines of weights ``w (n,)``: the spread of a weighted mean
    counts ``n_eff = (Σw)² / Σw²`` lines, not ``n``, and a spread from ``nu = n_eff - 1``
    of them is a Student-t scale: ``sqrt((n - 1) / nu * nu / (nu - 2))`` (at most 3 in
    variance for ``nu`` at most 3). (The sigma over ``n - 1`` was 1.1-1.5x too small in
    variance on 17-20 chords, bench_ambiguity's tile cases; issue 36.)"""
    n = w.size
    if n < 2 or not np.sum(w) > 0:
        return 1.0
    nu = max(float(np.sum(w)) ** 2 / float(np.sum(w * w)) - 1.0, 1.0)
    return math.sqrt(max((n - 1) / nu, 1.0) * student(nu))


__all__ = ["ParallelsStage", "few_lines_factor", "line_weights"]
