"""Anchoring a survey by measured lights: the rigid motion of the plane that puts the
survey's lights on the lights a known site lists (``--site`` with two or more
``lights``), singled out or refused.

The survey is solved in the frame its start pose fixes; its lights (lit spots placed
with the solved poses) are then paired with the known ones: every pair of surveyed
lights at least :data:`MIN_BASE_M` apart, with every pair of known lights as far apart
(within :data:`PAIR_TOL_M`), proposes a motion; a motion's support is the surveyed
lights it brings within :data:`MATCH_TOL_M` of a known one. The best is accepted only
with at least two lights and no distinct motion (:data:`DISTINCT_M`,
:data:`DISTINCT_RAD` away) as well supported: a symmetric layout (a row, a regular
grid) is refused as ``ambiguous``, never settled by the start pose.

Example::

    a = anchor_by_lights(survey_lights_xy, site.lights_m)
    if a.ok: poses_w = a.apply(poses)         # (N, 3) in the site's W
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ceilkit.runtime.geometry.fits import fit_rigid_2d

MIN_BASE_M = 0.3
PAIR_TOL_M = 0.03
MATCH_TOL_M = 0.05
DISTINCT_M = 0.10
DISTINCT_RAD = math.radians(2.0)


@dataclass(frozen=True, eq=False)
class LightAnchor:
    """The motion ``X_W = Rz(yaw) X + t`` from the survey's frame to the site's, or why
    none (``reason``; falsy). ``pairs``: ``(K, 2)`` indices (surveyed, known) of the
    lights it matched; ``residual_m``: ``(K,)`` their distances after the fit;
    ``runner_up``: the best distinct motion's support."""

    ok: bool
    reason: str
    yaw_rad: float = 0.0
    t_m: np.ndarray | None = None
    pairs: np.ndarray | None = None
    residual_m: np.ndarray | None = None
    runner_up: int = 0

    def __bool__(self) -> bool:
        return self.ok

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """Poses ``(N, 3)`` (x, y, yaw) of the survey's frame in the site's W."""
        return move_poses(self.yaw_rad, self.t_m, poses)

    def apply_xy(self, xy: np.ndarray) -> np.ndarray:
        p = np.c_[np.asarray(xy, float).reshape(-1, 2), np.zeros(len(xy))]
        return self.apply(p)[:, :2]


def move_poses(yaw_rad: float, t_m: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses ``(N, 3)`` (x, y, yaw rad) moved by ``X' = Rz(yaw) X + t``: positions rotated
    and shifted, headings turned by ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    p = np.asarray(poses, float).reshape(-1, 3)
    out = p.copy()
    out[:, 0] = c * p[:, 0] - s * p[:, 1] + t_m[0]
    out[:, 1] = s * p[:, 0] + c * p[:, 1] + t_m[1]
    out[:, 2] = p[:, 2] + yaw_rad
    return out


def _motions(found: np.ndarray, known: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """Every motion two surveyed lights and two known lights as far apart propose."""
    out = []
    n, m = len(found), len(known)
    dk = np.linalg.norm(known[:, None] - known[None], axis=2)
    for i in range(n):
        for j in range(i + 1, n):
            d = float(np.linalg.norm(found[j] - found[i]))
            if d < MIN_BASE_M:
                continue
            for a, b in zip(*np.nonzero(np.abs(dk - d) <= PAIR_TOL_M), strict=True):
                if a == b or a >= m or b >= m:
                    continue
                u, v = found[j] - found[i], known[b] - known[a]
                yaw = math.atan2(v[1], v[0]) - math.atan2(u[1], u[0])
                c, s = math.cos(yaw), math.sin(yaw)
                t = known[a] - np.array([c * found[i, 0] - s * found[i, 1],
                                         s * found[i, 0] + c * found[i, 1]])
                out.append((yaw, t))
    return out


def _support(found: np.ndarray, known: np.ndarray, yaw: float, t: np.ndarray
             ) -> tuple[int, np.ndarray]:
    """How many surveyed lights the motion brings near a known one, and the pairs."""
    c, s = math.cos(yaw), math.sin(yaw)
    moved = found @ np.array([[c, s], [-s, c]]) + t
    d = np.linalg.norm(moved[:, None] - known[None], axis=2)
    nearest = np.argmin(d, axis=1)
    ok = d[np.arange(len(found)), nearest] <= MATCH_TOL_M
    return int(np.count_nonzero(ok)), np.c_[np.flatnonzero(ok), nearest[ok]]


def anchor_by_lights(found_xy: np.ndarray, known_xy: np.ndarray) -> LightAnchor:
    """The motion from the survey's frame to the site's W (module docstring)."""
    found = np.asarray(found_xy, float).reshape(-1, 2)
    known = np.asarray(known_xy, float).reshape(-1, 2)
    if len(found) < 2 or len(known) < 2:
        return LightAnchor(False, f"{len(found)} lights surveyed, {len(known)} known: "
                           "two of each are needed")
    scored = [(_support(found, known, yaw, t)[0], yaw, t) for yaw, t in _motions(found, known)]
    if not scored:
        return LightAnchor(False, "no two surveyed lights are as far apart as two known ones")
    scored.sort(key=lambda h: -h[0])
    n, yaw, t = scored[0]
    runner = max((h[0] for h in scored[1:]
                  if abs((h[1] - yaw + math.pi) % (2 * math.pi) - math.pi) > DISTINCT_RAD
                  or np.linalg.norm(h[2] - t) > DISTINCT_M), default=0)
    if n < 2:
        return LightAnchor(False, "no motion puts two surveyed lights on known ones")
    if runner >= n:
        return LightAnchor(False, f"ambiguous: another motion matches {runner} lights as "
                           f"well as the best's {n}", runner_up=runner)
    _, pairs = _support(found, known, yaw, t)
    yaw, t = fit_rigid_2d(found[pairs[:, 0]], known[pairs[:, 1]])
    n2, pairs = _support(found, known, yaw, np.asarray(t))
    c, s = math.cos(yaw), math.sin(yaw)
    moved = found[pairs[:, 0]] @ np.array([[c, s], [-s, c]]) + t
    res = np.linalg.norm(moved - known[pairs[:, 1]], axis=1)
    return LightAnchor(True, "", float(yaw), np.asarray(t, float), pairs, res, runner)
