"""The block method's window path (option ``track``): with a prior, the site's blocks and
markers are measured where the prior puts them, with no search of the frame.

:class:`Windows` projects every block and marker of the site from the prior
(:meth:`Windows.predicted`: those fully in view, the largest first) and measures one on
its predicted outline (:meth:`Windows.fix`): a first edge pass ``track_window_px``
across each side in pixels, then the undistorted pass about the corners it found
(:func:`.detect.measure_sides`), solved by the caller's planar PnP; the **window check**
refuses a fix that does not look like the predicted block. The estimator falls back to
its global path then (docs/methods/block.md).

Example::

    win = Windows(geo, targets_of(site, site.markers, 0.08), options)
    for target, px in win.predicted((x, y, yaw)):
        fix = win.fix(grey, target, px, solve)      # a fix, or None: the check failed
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.block.detect import (
    Sides,
    measure_sides,
    side_lengths_m,
    step_contrast,
)
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, project_px
from ceilkit.runtime.features.quads import BORDER_PX
from ceilkit.runtime.geometry.fits import rigid_fit_rms

TRACK_MIN_SHARE = 0.75      # window check: share of a side's stations with an edge point
TRACK_MAX_RMS_PX = 0.5      # window check: edge residual RMS of the refined pose
WINDOW = "window"           # diagnostics["mode"] of a window fix (else "global")


@dataclass(frozen=True, eq=False)
class Target:
    """A block or marker of the site as the window path predicts it: ``corners_w``
    ``(4, 2)`` in the order its sides are measured, ``symmetric`` when its shape also
    fits its corners turned (the prior then decides the correspondence)."""

    source: str
    corners_w: np.ndarray
    dark: bool
    symmetric: bool
    min_side_m: float


def targets_of(site: Any, markers: Any, shape_tol: float) -> list[Target]:
    """Every block and marker of the site as a :class:`Target` (``shape_tol``: the
    block method's option, relative to the shortest side)."""
    out = []
    for b in site.blocks:
        c = np.asarray(b.corners_m, float)
        side = float(side_lengths_m(c).min())
        out.append(Target(f"block:{b.id}", c, b.appearance != "bright",
                          turn_fits(c, shape_tol * side), side))
    for p in markers.poses if markers is not None else ():
        out.append(Target(f"marker:{p.id}", p.corners_m(), True, False, float(p.size_m)))
    return out


def turn_fits(corners: np.ndarray, tol_m: float) -> bool:
    """Whether the quad ``(4, 2)`` fits itself with its corners turned by one, two or
    three places within ``tol_m`` (RMS): a square (4 ways), a rectangle (2)."""
    return any(rigid_fit_rms(corners, np.roll(corners, -shift, axis=0))[2] < tol_m
               for shift in (1, 2, 3))


def shape_fits(blocks: Any, pv: np.ndarray, dark: bool, shape_tol: float
               ) -> list[tuple[Any, int, float, tuple]]:
    """``(block, shift, rms_m, (x, y, yaw))`` of every block of ``blocks`` (the site's)
    of that polarity and corner shift whose shape the quad ``pv`` (V, counter-clockwise)
    fits within ``shape_tol`` of its shortest side (the global path's matching)."""
    out = []
    for blk in blocks:
        if (blk.appearance == "bright") == dark:
            continue
        tol = shape_tol * float(side_lengths_m(blk.corners_m).min())
        for shift in range(4):
            yaw, t, rms = rigid_fit_rms(pv, blk.corners_m[(np.arange(4) + shift) % 4])
            if rms < tol:
                out.append((blk, shift, rms, (float(t[0]), float(t[1]), yaw)))
    return out


class Windows:
    """The site's targets predicted and measured from a prior (see the module).

    Args:
        geo: the rig and ceiling.
        targets: :func:`targets_of` the site.
        options: the block method's options (``track_window_px``, ``edge_points``,
            ``dark_ratio``, ``bright_ratio``, ``shape_tol``).
    """

    def __init__(self, geo: PlanarGeometry, targets: list[Target], options: Any) -> None:
        self.geo = geo
        self.targets = targets
        self.options = options
        self._corners = (np.concatenate([t.corners_w for t in targets]) if targets
                         else np.zeros((0, 2)))
        self._bright = np.array([not t.dark for t in targets], bool)

    def predicted(self, pose: np.ndarray) -> list[tuple[Target, np.ndarray]]:
        """``(target, corners px (4, 2))`` of the targets fully in view from ``pose``
        (a margin of the search window inside the frame): the dark ones first (markers,
        dark blocks), each polarity the largest first, the global path's order."""
        if not self.targets:
            return []
        px = project_px(self.geo, pose, self._corners).reshape(-1, 4, 2)
        margin = BORDER_PX + self.options.track_window_px + 1.0
        inside = self.geo.camera.in_image(px.reshape(-1, 2), margin).reshape(-1, 4).all(1)
        u, v = px[..., 0], px[..., 1]
        nxt = [1, 2, 3, 0]
        area = np.abs(np.sum(u * v[:, nxt] - u[:, nxt] * v, axis=1))
        return [(self.targets[k], px[k]) for k in np.lexsort((-area, self._bright))
                if inside[k]]

    def fixes(self, grey: np.ndarray, pose: np.ndarray, solve: Callable[..., Any],
              most: int) -> tuple[list[Any], int]:
        """Up to ``most`` fixes (:meth:`fix`) of the targets in view from ``pose``, in
        :meth:`predicted`'s order, and how many targets were tried."""
        out: list[Any] = []
        tried = 0
        for tgt, px in self.predicted(pose):
            tried += 1
            got = self.fix(grey, tgt, px, solve)
            if got is not None:
                out.append(got)
                if len(out) >= most:
                    break
        return out, tried

    def fix(self, grey: np.ndarray, tgt: Target, px: np.ndarray,
            solve: Callable[[Sides, np.ndarray, str, str], Any]) -> Any:
        """The fix of one target measured on its predicted outline ``px`` ``(4, 2)``
        (``solve(sides, corners_w, source, resolved_by)``: the estimator's planar PnP,
        a fix with ``refined`` and ``shape_m``, or None), or None when the window check
        fails: a side with fewer than :data:`TRACK_MIN_SHARE` of its stations on an
        edge, the wrong contrast across the outline (:func:`.detect.step_contrast`
        against ``dark_ratio`` / ``bright_ratio``), a shape off the block's by more than
        ``shape_tol``, an edge residual over :data:`TRACK_MAX_RMS_PX`, or a refined
        outline more than ``track_window_px`` from the predicted one."""
        o = self.options
        sides = measure_sides(grey, px, self.geo, o.edge_points, passes=2,
                              search_px=o.track_window_px)
        if sides is None or np.any(np.bincount(sides.side, minlength=4)
                                   < TRACK_MIN_SHARE * o.edge_points):
            return None
        ratio = step_contrast(grey, self.geo.camera.distort(sides.corners_norm))
        if not (ratio < o.dark_ratio if tgt.dark else ratio > o.bright_ratio):
            return None
        fix = solve(sides, tgt.corners_w, tgt.source, "prior" if tgt.symmetric else WINDOW)
        if fix is None or fix.refined.rms_px > TRACK_MAX_RMS_PX \
                or fix.shape_m > o.shape_tol * tgt.min_side_m:
            return None
        moved = project_px(self.geo, fix.refined.pose, tgt.corners_w) - px
        if not np.all(np.hypot(moved[:, 0], moved[:, 1]) <= o.track_window_px):
            return None
        return fix
