"""Ceiling-plane odometry: the vehicle's planar motion between two frames from ceiling
features tracked through the rig (an estimator-side stage any method can use).

Corners (``cv2.goodFeaturesToTrack``) of the earlier frame are tracked into the later
one by pyramidal KLT and checked back (forward-backward error); both sets are
undistorted and met with the ceiling plane in V (:func:`.pnp.ceiling_points_vehicle`);
a rigid 2-D fit ``q_prev ~ R(dyaw) p_now + (dx, dy)`` with one pass dropping pairs off
by more than 3 MADs gives the motion in the earlier frame's V. The covariance is the
fit's residual scatter, ``s² (JᵀJ)⁻¹``.

Example::

    odo = PlaneOdometry(PlanarGeometry.of(rig, site))
    inc = odo.step(grey)          # None on the first frame or with too few tracks
    inc.dx_m, inc.dy_m, inc.dyaw_rad, inc.cov
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ceilkit.runtime.estimators.block.pnp import PlanarGeometry, ceiling_points_vehicle
from ceilkit.runtime.geometry.fits import fit_rigid_2d

MAX_CORNERS = 150
MIN_TRACKS = 12
FB_MAX_PX = 0.5          # forward-backward disagreement of a kept track
LK = {"winSize": (21, 21), "maxLevel": 3,
      "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}


@dataclass(frozen=True)
class Increment:
    """The motion between two frames in the earlier frame's V: forward, left, CCW."""

    dx_m: float
    dy_m: float
    dyaw_rad: float
    cov: np.ndarray
    n: int


def plane_motion(q_prev: np.ndarray, p_now: np.ndarray) -> Increment | None:
    """The rigid fit of ceiling points (V, ``(N, 2)`` each) with an outlier pass."""
    keep = np.ones(len(q_prev), bool)
    for _ in range(2):
        if np.count_nonzero(keep) < MIN_TRACKS:
            return None
        yaw, t = fit_rigid_2d(p_now[keep], q_prev[keep])
        c, s = math.cos(yaw), math.sin(yaw)
        r = q_prev - (p_now @ np.array([[c, s], [-s, c]]) + t)
        d = np.hypot(r[:, 0], r[:, 1])
        med = float(np.median(d[keep]))
        keep = d <= max(3.0 * 1.4826 * med + med, 1e-6)
    n = int(np.count_nonzero(keep))
    if n < MIN_TRACKS:
        return None
    yaw, t = fit_rigid_2d(p_now[keep], q_prev[keep])
    c, s = math.cos(yaw), math.sin(yaw)
    pk = p_now[keep]
    r = q_prev[keep] - (pk @ np.array([[c, s], [-s, c]]) + t)
    s2 = float(np.sum(r * r)) / max(2 * n - 3, 1)
    # d(R p + t)/d(tx, ty, yaw): rows for x and y of every point
    rp = pk @ np.array([[c, s], [-s, c]])
    J = np.zeros((2 * n, 3))
    J[0::2, 0] = 1.0
    J[1::2, 1] = 1.0
    J[0::2, 2] = -rp[:, 1]
    J[1::2, 2] = rp[:, 0]
    cov = s2 * np.linalg.inv(J.T @ J)
    return Increment(float(t[0]), float(t[1]), float(yaw), cov, n)


class PlaneOdometry:
    """Frame-to-frame ceiling-plane odometry (see the module); one instance per stream."""

    def __init__(self, geo: PlanarGeometry) -> None:
        self.geo = geo
        self._prev: np.ndarray | None = None

    def reset(self) -> None:
        self._prev = None

    def step(self, grey: np.ndarray) -> Increment | None:
        """The motion since the previous frame given to :meth:`step`, or None."""
        prev, self._prev = self._prev, grey
        if prev is None:
            return None
        pts = cv2.goodFeaturesToTrack(prev, MAX_CORNERS, 0.01, 8, blockSize=5)
        if pts is None or len(pts) < MIN_TRACKS:
            return None
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, grey, pts, None, **LK)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, prev, nxt, None, **LK)
        fb = np.linalg.norm((back - pts).reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < FB_MAX_PX)
        if np.count_nonzero(ok) < MIN_TRACKS:
            return None
        cam = self.geo.camera
        q = ceiling_points_vehicle(self.geo, cam.unproject(pts.reshape(-1, 2)[ok]))
        p = ceiling_points_vehicle(self.geo, cam.unproject(nxt.reshape(-1, 2)[ok]))
        good = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
        return plane_motion(q[good], p[good])
