"""``paper-block``: the reference-block method as Xu et al. write it, a baseline beside
``block`` (same detection of blocks and markers, :mod:`.block.detect`).

* Initial pose, eq. 3-4: the four corners' normalized image points and the block's
  corners on the ceiling (the ceiling plane as the world's ``z = 0``) give the linear
  homogeneous system of eq. 3 in ``(n_w, o_w, p_w)`` (8 equations, 9 unknowns): its
  null vector by SVD, scaled to ``|n_w| = |o_w| = 1`` on average, ``p_wz > 0``, the
  rotation ``[n o n x o]`` orthonormalized. The camera pose then gives the vehicle's
  through the mount. Nothing of the rig's tilt or height constrains it (6 DoF), and
  there is no refinement in pixels.
* Heading, eq. 10: from the ceiling's parallels found on the frame by a line detector
  (FLD), the branch nearest the PnP heading; the PnP heading where fewer than two.

Covariance: none in the paper; ``cov`` is the 6-DoF solution's scatter model
``diag(sigma_m², sigma_m², sigma_rad²)`` from the corners' reprojection RMS (pixels
over the focal length times the range). A symmetric block is handled as in ``block``.
"""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.estimators.block.detect import Sides
from ceilkit.runtime.estimators.block.estimator import BlockEstimator, BlockOptions
from ceilkit.runtime.estimators.block.pnp import PlanarFit, PlanarSolver, TargetFix, project_norm
from ceilkit.runtime.geometry.rotations import wrap_pi

MIN_SIGMA_PX = 0.3      # the corners' reprojection RMS is floored at this


def linear_pnp(corners_norm: np.ndarray, corners_w: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Eq. 3: ``(R_cw, p_w)`` (the ceiling frame in the camera; ceiling at z = 0) from
    four normalized image points ``(4, 2)`` and their ceiling points ``(4, 2)``."""
    x = np.asarray(corners_w, float)
    u = np.asarray(corners_norm, float)
    A = np.zeros((2 * len(x), 9))     # unknowns n_x n_y n_z o_x o_y o_z p_x p_y p_z
    for i, ((xw, yw), (xc, yc)) in enumerate(zip(x, u, strict=True)):
        A[2 * i] = [xw, 0, -xc * xw, yw, 0, -xc * yw, 1, 0, -xc]
        A[2 * i + 1] = [0, xw, -yc * xw, 0, yw, -yc * yw, 0, 1, -yc]
    h = np.linalg.svd(A)[2][-1]
    n, o, p = h[0:3], h[3:6], h[6:9]
    scale = 2.0 / (np.linalg.norm(n) + np.linalg.norm(o))
    if not math.isfinite(scale):
        return None
    n, o, p = n * scale, o * scale, p * scale
    if p[2] < 0:
        n, o, p = -n, -o, -p
    U, _, Vt = np.linalg.svd(np.column_stack([n, o, np.cross(n, o)]))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return None
    return R, p


class PaperSolver(PlanarSolver):
    """The block method's solve stage as the paper has it: eq. 3-4 on the four corners
    (no refinement in pixels, no pooling; ``drop`` unused)."""

    def __call__(self, sides: Sides, corners_w: np.ndarray, source: str,
                 resolved_by: str) -> TargetFix | None:
        g = self.geo
        got = linear_pnp(sides.corners_norm, corners_w)
        if got is None:
            return None
        R_cw, p = got
        R_wc = R_cw.T
        c_w = -R_wc @ p + np.array([0.0, 0.0, g.ceiling_m])
        R_wv = R_wc @ g.R_vehicle_cam.T
        t_wv = c_w - R_wv @ g.t_vehicle_cam
        pose = np.array([t_wv[0], t_wv[1], math.atan2(R_wv[1, 0], R_wv[0, 0])])
        if not np.all(np.isfinite(pose)):
            return None
        f = float(g.camera.K[0, 0])
        r = project_norm(g, pose, corners_w) - sides.corners_norm
        rms_px = float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) * f
        rng = float(np.linalg.norm(p))
        s_px = max(rms_px, MIN_SIGMA_PX)
        sm = s_px / f * rng
        span = float(np.max(np.linalg.norm(corners_w - corners_w.mean(0), axis=1)))
        cov = np.diag([sm ** 2, sm ** 2, (sm / max(span, 1e-3)) ** 2])
        ref = PlanarFit(pose, cov, rms_px, len(corners_w))
        return TargetFix(source, ref, float("nan"), sides.corners_norm, corners_w, resolved_by)


class PaperBlockEstimator(BlockEstimator):
    """Xu et al.'s procedure (see the module); options as ``block``'s."""

    name = "paper-block"
    Options = BlockOptions
    Solver = PaperSolver

    def _parallels(self, grey: np.ndarray, hint: float | None,
                   pose: np.ndarray | None = None, max_chords: int = 0):
        """Eq. 10 on the frame's detected lines (the paper has no prediction)."""
        return super()._parallels(grey, hint, None)

    def _fuse(self, pose: np.ndarray, cov: np.ndarray, h) -> tuple[np.ndarray, np.ndarray]:
        """The paper takes the heading from the parallels as it is (no fusion)."""
        pose = pose.copy()
        pose[2] = wrap_pi(h.yaw_rad)
        cov = cov.copy()
        cov[2, :] = cov[:, 2] = 0.0
        cov[2, 2] = h.sigma_rad ** 2
        return pose, cov
