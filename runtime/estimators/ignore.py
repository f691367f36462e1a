"""SPEC §2 ``ignore`` regions for image features: where on the ceiling a feature seen
from a pose lies, and whether a region holds it.

Map features (lights, blocks, markers) inside a region are left out of the maps when an
estimator is built (``Site.ignored``, ``Site.without_ignored``). A feature found on the
frame can only be placed on the ceiling through a pose: the prior's. With one (its
``x_m`` and ``y_m`` known), features whose ceiling point lies in a region are not used;
without one, they are (nothing places them).

Example::

    regions = IgnoreRegions.of(rig, site)          # None when the site has none
    keep = regions.keep_segments(segs_norm, prior)  # (N,) bool, or None: no pose
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ceilkit.runtime.geometry.ceiling import (
    PlanarGeometry,
    ceiling_points_vehicle,
    vehicle_to_world,
)


def _pose(pose: Any) -> np.ndarray | None:
    """``(x, y, yaw)`` of a pose estimate (``x_m``, ``y_m``, ``yaw_rad``) or of a
    ``(3,)`` array; None when there is none or it has no position."""
    if pose is None:
        return None
    if hasattr(pose, "x_m"):
        if pose.x_m is None or pose.y_m is None:
            return None
        return np.array([pose.x_m, pose.y_m, pose.yaw_rad], float)
    return np.asarray(pose, float).reshape(3)


def ignored_from(site: Any, points_v: np.ndarray, pose: Any) -> np.ndarray | None:
    """``(N,)`` bool: which ceiling points ``(N, 2)`` in V (a frame's features met with
    the ceiling) lie in one of ``site``'s ``ignore`` regions when the vehicle is at
    ``pose`` (``x_m``, ``y_m``, ``yaw_rad``: a prior, or an ``(x, y, yaw)`` array);
    None when the site has no region or the pose no position. Points that are not
    finite are not inside."""
    if not site.ignore_m:                 # the common case: no work on the frame path
        return None
    xyz = _pose(pose)
    if xyz is None:
        return None
    w = vehicle_to_world(points_v, xyz[0], xyz[1], xyz[2])
    ok = np.all(np.isfinite(w), axis=1)
    out = np.zeros(len(w), bool)
    out[ok] = site.ignored(w[ok])
    return out


class IgnoreRegions:
    """The site's ``ignore`` regions seen through the rig (module doc)."""

    def __init__(self, geo: PlanarGeometry, site: Any) -> None:
        self.geo, self.site = geo, site

    @classmethod
    def of(cls, rig: Any, site: Any) -> IgnoreRegions | None:
        """The regions of ``site`` for ``rig``; None when the site has none."""
        return cls(PlanarGeometry.of(rig, site), site) if site.ignore_m else None

    def inside(self, points_norm: np.ndarray, pose: Any) -> np.ndarray | None:
        """``(N,)`` bool: which undistorted normalized image points ``(N, 2)`` see the
        ceiling inside a region from ``pose`` (``x_m``, ``y_m``, ``yaw_rad``); None
        when the pose has no position. A ray that does not rise to the ceiling is not
        inside."""
        if _pose(pose) is None:
            return None
        q = ceiling_points_vehicle(self.geo, np.asarray(points_norm, float).reshape(-1, 2))
        return ignored_from(self.site, q, pose)

    def keep_segments(self, segs_norm: np.ndarray, pose: Any) -> np.ndarray | None:
        """``(N,)`` bool: the segments ``(N, 4)`` (undistorted normalized endpoints)
        none of whose ends and middle lies in a region; None when the pose has no
        position."""
        s = np.asarray(segs_norm, float).reshape(-1, 4)
        pts = np.concatenate([s[:, :2], s[:, 2:], 0.5 * (s[:, :2] + s[:, 2:])])
        hit = self.inside(pts, pose)
        if hit is None:
            return None
        return ~hit.reshape(3, -1).any(axis=0)


__all__ = ["IgnoreRegions", "ignored_from"]
