"""Twins: the other poses a frame supports when what it shows is symmetric (issue 36).

* A plain square block fits its corners in 4 ways, a rectangle in 2: each fit is a
  vehicle pose, related to the others by a rigid motion of W (:class:`BlockTwin`, from one
  correspondence's corners to another's). With no prior the frame is ``ambiguous`` and
  carries every fit (:func:`fit_hypotheses`); with a prior the published pose carries
  the twins the prior ruled out (:func:`with_twins`).
* The heading from the ceiling's parallels alone is known modulo their period: every
  branch is a hypothesis (:func:`heading_branches`), never a full pose.

Hypotheses of one estimate are equally weighted (the frame supports them equally) and
sum to 1; the published one (or the first fit) first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import Hypothesis
from ceilkit.runtime.estimators.block.detect import Sides
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, solve
from ceilkit.runtime.geometry.fits import rigid_fit_rms
from ceilkit.runtime.geometry.rotations import wrap_pi

_LABELS = {0: "same_turn", 90: "quarter_turn", -90: "quarter_turn", 180: "half_turn",
           -180: "half_turn"}


@dataclass(frozen=True)
class BlockTwin:
    """Another correspondence of a symmetric block: the rigid motion of W taking the
    published correspondence's corners to this one's (``p' = R(yaw) p + t``)."""

    yaw_rad: float
    t: tuple[float, float]
    label: str


def twin(corners_a: np.ndarray, corners_b: np.ndarray) -> BlockTwin:
    """The rigid motion of W taking the corners ``corners_a`` ``(4, 2)`` onto
    ``corners_b`` (the same block's corners in another order, or another block's),
    labelled by its turn."""
    yaw, t, _ = rigid_fit_rms(np.asarray(corners_a, float), np.asarray(corners_b, float))
    deg = round(math.degrees(wrap_pi(yaw)))
    return BlockTwin(float(yaw), (float(t[0]), float(t[1])), _LABELS.get(deg, f"turn {deg:+d} deg"))


def target_twins(corners_w: np.ndarray, tol_m: float) -> tuple[BlockTwin, ...]:
    """The turns of a block's corners ``(4, 2)`` (by one, two, three places) that fit
    its own shape within ``tol_m`` RMS, as twins of the corners as given."""
    c = np.asarray(corners_w, float)
    turns = [np.roll(c, -k, axis=0) for k in (1, 2, 3)]
    return tuple(twin(c, r) for r in turns if rigid_fit_rms(c, r)[2] < tol_m)


def moved(pose: np.ndarray, cov: np.ndarray | None, tw: BlockTwin, weight: float,
          label: str | None = None) -> Hypothesis:
    """The vehicle pose ``(x, y, yaw)`` with its covariance moved by ``tw``'s motion of
    W: the pose the frame gives under that correspondence."""
    c, s = math.cos(tw.yaw_rad), math.sin(tw.yaw_rad)
    x = c * pose[0] - s * pose[1] + tw.t[0]
    y = s * pose[0] + c * pose[1] + tw.t[1]
    out = None
    if cov is not None:
        J = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out = J @ cov @ J.T
    return Hypothesis(float(x), float(y), wrap_pi(float(pose[2]) + tw.yaw_rad), out,
                      weight, tw.label if label is None else label)


def with_twins(pose: np.ndarray, cov: np.ndarray, twins: tuple[BlockTwin, ...]
               ) -> tuple[Hypothesis, ...]:
    """The published pose first, then each twin the prior ruled out (equal weights);
    empty without twins."""
    if not twins:
        return ()
    w = 1.0 / (1 + len(twins))
    return (Hypothesis(float(pose[0]), float(pose[1]), wrap_pi(float(pose[2])), cov, w,
                       "published"), *(moved(pose, cov, t, w) for t in twins))


def fit_hypotheses(geo: PlanarGeometry, sides: Sides, fits: list[Any],
                   every: list[np.ndarray], drop: np.ndarray, rms_bad_px: float
                   ) -> tuple[Hypothesis, ...] | None:
    """Every pose a symmetric block fits (``fits``: :func:`.window.shape_fits`'s
    ``(block, shift, rms, pose)``; ``every`` their corners in W in the measured order),
    equally weighted: the first fit solved on the edges (:func:`.pnp.solve`, the sides
    ``drop`` left out) and moved onto each other fit's corners. None when the solve
    fails or its edge RMS exceeds ``rms_bad_px`` (a quad cut by the frame's edge that
    still fits the shape: its closed forms would be centimetres off)."""
    got = solve(geo, sides.corners_norm, every[0], sides.edge_norm, sides.side, drop)
    ref = got[1] if got is not None else None
    if ref is None or not (np.all(np.isfinite(ref.pose)) and ref.rms_px <= rms_bad_px):
        return None
    pose, cov = np.array(ref.pose, float), np.array(ref.cov, float)
    w = 1.0 / len(fits)
    out = []
    for (blk, _, _, _), c in zip(fits, every, strict=True):
        tw = twin(every[0], c)
        out.append(moved(pose, cov, tw, w, f"block:{blk.id} {tw.label}"))
    return tuple(out)


def heading_branches(yaw_rad: float, period_rad: float, cov: np.ndarray
                     ) -> tuple[Hypothesis, ...]:
    """A heading known modulo ``period_rad``: every branch (the published ``yaw_rad``
    first), no position; empty when the period is a full turn."""
    turns = max(1, round(2 * math.pi / period_rad))
    if turns == 1:
        return ()
    return tuple(Hypothesis(None, None, wrap_pi(yaw_rad + k * period_rad), cov, 1.0 / turns,
                            "published" if k == 0 else f"turn {k}") for k in range(turns))
