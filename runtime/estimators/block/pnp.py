"""Planar PnP: the vehicle pose ``(x, y, yaw)`` from a known quadrilateral on the ceiling.

With the mount's tilt, swing and height calibrated and the ceiling a plane at a known
height, only the vehicle's planar pose is unknown (SPEC §1):

1. closed form: each corner's viewing ray (lens undistorted) is turned into V by the
   mount and met with the ceiling plane (``geometry/ceiling.py``), giving the corners
   in V on the ceiling; a 2-D rigid fit to the block's corners in W is the pose
   (``X_W = Rz(yaw) X_V + (x, y)``).
   A mirrored solution cannot fit (the rays fix which side of the plane the camera
   is on), so the planar flip of 6-DoF PnP does not arise.
2. Gauss-Newton in pixels: the block's sides, projected for the pose, against points
   measured on the sides' edges; each point's residual is its distance to the projected
   side in normalized coordinates times the lens's local magnification (px). The
   covariance is the residuals' parts propagated (:func:`residual_parts`: the sides'
   common offset, per-side offsets, white noise).

:class:`PlanarSolver` is the block method's solve stage: measured sides
(:class:`.detect.Sides`) as a block of the site, its fix (:class:`TargetFix`), the
sides on a ceiling line left out and the covariance pooled per target. The estimator
builds it once and hands it to the marker reader (:mod:`.fallback`).

:func:`six_dof_check` solves the unconstrained 6-DoF PnP (OpenCV's IPPE) and reports how
far its camera lies from what the rig says (tilt, swing, height): a live check of the
mount.

Example::

    geo = PlanarGeometry.of(rig, site)
    x, y, yaw, rms_m = closed_form(geo, corners_norm, block.corners_m)
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.estimators.block.detect import Sides
from ceilkit.runtime.geometry.camera import CameraModel, magnification_points
from ceilkit.runtime.geometry.ceiling import (
    MIN_RZ,
    PlanarGeometry,
    ceiling_norm,
    ceiling_points_vehicle,
    kernel_mount,
    level_offset,
    meet_ceiling,
    on_ceiling,
    seen_from,
    to_camera,
)
from ceilkit.runtime.geometry.fits import fit_rigid_2d_complex, scaled_inverse3, student
from ceilkit.runtime.geometry.rotations import mount_angles, rot_z, wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

GN_ITERATIONS = 4
GN_STEP_EPS = 1e-6          # converged when the next step (m, rad) is below this
GN_LINEAR_EPS = 1e-4        # a step (m, rad) below this ends the fit: the closed form's
                            # start is 20-40 µm off on configs/block, its first step then
                            # leaves ~1e-9 (Gauss-Newton converges quadratically)
JAC_EPS = 1e-6              # finite-difference step, m and rad
_JAC_STEPS = np.vstack([np.zeros(3), np.eye(3) * JAC_EPS])   # the pose and its steps
_JAC_STEPS.flags.writeable = False
SIGMA_FLOOR_PX = 0.02       # the white noise's RMS in the covariance is at least this
                            # (a guard: the residuals set it, 0.029 px on configs/block's
                            # markers at noise 2; 0.05 over-covered a marker drive's
                            # error 3x in variance)
VERTICAL_RAD = math.radians(1.0)  # six_dof_check: swing unobservable this near 90°
RMS_BAD_PX = 1.0            # edge residual RMS at which a fix's quality reaches 0: a
                            # fix above it is refused (:class:`PlanarSolver`)


def closed_form(geo: PlanarGeometry, corners_norm: np.ndarray, corners_w: np.ndarray
                ) -> tuple[float, float, float, float]:
    """``(x_m, y_m, yaw_rad, rms_m)``: the rigid fit of the corners seen (normalized,
    ``(4, 2)``, in the order of ``corners_w``) to the block's corners in W ``(4, 2)``;
    ``rms_m`` is the fit's residual on the ceiling (NaN if a ray misses the ceiling)."""
    q = ceiling_points_vehicle(geo, corners_norm)
    if not np.all(np.isfinite(q)):
        return math.nan, math.nan, math.nan, math.nan
    p = np.asarray(corners_w, float)
    qc, pc = q[:, 0] + 1j * q[:, 1], p[:, 0] + 1j * p[:, 1]   # the four points' form
    rot, t = fit_rigid_2d_complex(qc, pc)
    r = rot * qc + t - pc
    rms = math.sqrt(float(np.mean(r.real * r.real + r.imag * r.imag)))
    return t.real, t.imag, math.atan2(rot.imag, rot.real), rms


def project_norm(geo: PlanarGeometry, pose: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Normalized image points ``(N, 2)`` of ceiling points ``(N, 2)`` in W for a vehicle
    pose ``(x, y, yaw)`` (no lens distortion); NaN for a point behind the camera."""
    x, y, yaw = (float(v) for v in pose)
    return ceiling_norm(arr(geo.R_vehicle_cam, np.float64), arr(geo.t_vehicle_cam, np.float64),
                        float(geo.ceiling_m), x, y, yaw,
                        arr(points_w, np.float64).reshape(-1, 2), 1e-9)


def project_px(geo: PlanarGeometry, pose: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of ceiling points ``(N, 2)`` in W for a vehicle pose; NaN for
    a point behind the camera."""
    return geo.camera.distort(project_norm(geo, pose, points_w))


def magnification(camera: CameraModel, points_norm: np.ndarray) -> np.ndarray:
    """``(N,)`` pixels per normalized unit at each point: ``sqrt |det J|`` of the lens."""
    J = camera.distort_jacobian(points_norm)
    return np.sqrt(np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]))


def _side_residuals(geo: PlanarGeometry, poses: np.ndarray, corners_w: np.ndarray,
                    edge_norm: np.ndarray, side: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(P, M)`` residuals (px) of the edge points for each of ``poses`` ``(P, 3)`` at
    once (the pose and its finite-difference steps in one pass)."""
    q = seen_from(on_ceiling(corners_w, geo.ceiling_m), poses, geo.t_vehicle_cam)  # in V
    pc = q @ geo.R_vehicle_cam                                           # (P, 4, 3)
    c = pc[..., :2] / pc[..., 2:3]
    n = c[:, [1, 2, 3, 0]]                                       # side k: corner k -> k+1
    a, b = c[..., 1] - n[..., 1], n[..., 0] - c[..., 0]          # the line through both
    norm = np.hypot(a, b)
    a, b = a / norm, b / norm
    off = -(a * c[..., 0] + b * c[..., 1])
    return (a[:, side] * edge_norm[:, 0] + b[:, side] * edge_norm[:, 1]
            + off[:, side]) * scale


class SideEdges(NamedTuple):
    """A block's measured sides as the Gauss-Newton loops take them: the block's
    corners ``corners_w (4, 2)`` in W (side k runs from corner k to k+1), the edge
    points ``edge_norm (M, 2)`` (normalized), the side of each ``side (M,)`` and the
    scale of each residual ``scale (M,)`` (px per normalized unit,
    :func:`magnification`)."""

    corners_w: np.ndarray
    edge_norm: np.ndarray
    side: np.ndarray
    scale: np.ndarray


class GNArrays(NamedTuple):
    """What :func:`_gauss_newton` writes: the residuals ``r (M,)`` (px), their
    Jacobian ``J (M, 3)`` by the pose ``(x, y, yaw)`` and ``JtJ (3, 3)``."""

    r: np.ndarray
    J: np.ndarray
    JtJ: np.ndarray


class SeenBlock(NamedTuple):
    """One frame's view of a block as :func:`solve_core` takes it: its corners seen
    ``corners_norm (4, 2)`` (normalized) in the order of the block's corners
    ``corners_w (4, 2)`` (W), the edge points ``edge_norm (N, 2)`` (normalized), the
    side of each ``side (N,)``, and the sides left out ``drop (4,)`` bool."""

    corners_norm: np.ndarray
    corners_w: np.ndarray
    edge_norm: np.ndarray
    side: np.ndarray
    drop: np.ndarray


class SolvedOut(NamedTuple):
    """The arrays :func:`solve_core` writes: ``pose (4,)`` (x m, y m, yaw rad, the
    closed form's RMS on the ceiling m), ``cov (3, 3)`` and ``unit (3, 3)``
    (:class:`PlanarFit`'s ``cov`` and ``side_unit``)."""

    pose: np.ndarray
    cov: np.ndarray
    unit: np.ndarray


class Solved(NamedTuple):
    """What :func:`solve_core` returns: ``status`` (:data:`SOLVED`,
    :data:`NO_CLOSED_FORM`, :data:`SINGULAR`), the edge points used ``m``, their
    residual RMS ``rms_px``, the side offsets' variance ``var_b`` (px²) and whether
    ``unit`` was written ``has_unit``."""

    status: int
    m: int
    rms_px: float
    var_b: float
    has_unit: bool


@dataclass(frozen=True, eq=False)
class PlanarFit:
    """A refined planar pose: ``pose`` (x, y, yaw), ``cov`` 3x3 (m², rad²), ``rms_px``
    of the edge residuals, ``n`` points used."""

    pose: np.ndarray
    cov: np.ndarray
    rms_px: float
    n: int
    side_var_px2: float = 0.0               # σ_b² of this frame (:func:`side_offset_cov`)
    side_unit: np.ndarray | None = None     # the pose covariance per px² of σ_b²


class PooledSideOffsets:
    """The side offsets' variance of each target pooled over the frames it is seen in.

    One frame measures ``σ_b²`` from ``sides - 2`` degrees of freedom
    (:func:`side_offset_cov`): often far below the offsets' true variance (random
    offsets of 0.1-0.3 px: 79 % of four-sided poses inside their 95 % ellipse, 67 % on
    three). A side's offset on a ceiling is mostly the same from frame to frame (a seam
    beside an edge, an edge's profile), so a target's running mean
    (weight ``weight`` per frame) is a far better measure; a frame uses the larger of
    its own and the pooled one. ``self(source, refined)`` gives the refined pose with
    that covariance."""

    def __init__(self, weight: float = 0.2) -> None:
        self.weight = float(weight)
        self._var: dict[str, float] = {}

    def reset(self) -> None:
        """Forget every target's pooled variance (a new drive)."""
        self._var.clear()

    def __call__(self, source: str, ref: PlanarFit) -> PlanarFit:
        if ref.side_unit is None:
            return ref
        prev = self._var.get(source)
        v = ref.side_var_px2 if prev is None else \
            (1.0 - self.weight) * prev + self.weight * ref.side_var_px2
        self._var[source] = v
        if v <= ref.side_var_px2:
            return ref
        return dataclasses.replace(ref, cov=ref.cov + (v - ref.side_var_px2) * ref.side_unit)


@dataclass(frozen=True, eq=False)
class TargetFix:
    """A block or marker of the site solved on one frame.

    Attributes:
        source: ``marker:ID`` or ``block:ID``.
        refined: the refined pose, its covariance pooled per target
            (:class:`PooledSideOffsets`).
        shape_m: the closed form's RMS on the ceiling (m): how well the corners seen
            fit the block's shape.
        corners_norm: ``(4, 2)`` the corners seen (normalized), in the order of
            ``corners_w``.
        corners_w: ``(4, 2)`` the block's corners in W.
        resolved_by: how the correspondence was chosen: ``id`` (a marker), ``shape``
            (one fit), ``prior`` (the prior chose among twins), ``window``.
        twins: the correspondences the prior ruled out (:class:`.twins.BlockTwin`).
    """

    source: str
    refined: PlanarFit
    shape_m: float
    corners_norm: np.ndarray
    corners_w: np.ndarray
    resolved_by: str
    twins: tuple = ()


class PlanarSolver:
    """The block method's solve stage: measured sides as a block of the site, a
    :class:`TargetFix` (:func:`solve`, the sides ``drop`` leaves out, the covariance
    pooled per target). Built once by the estimator, called by it for a plain block
    and by :class:`.fallback.MarkerReader` for a marker.

    Args:
        geo: the rig and ceiling.
        drop: ``drop(corners_w)``: ``(4,)`` bool, the sides the refinement leaves out
            (:class:`.parallels.LinedSides`).
    """

    def __init__(self, geo: PlanarGeometry, drop: Callable[[np.ndarray], np.ndarray]
                 ) -> None:
        self.geo, self.drop = geo, drop
        self.pooled = PooledSideOffsets()

    def __call__(self, sides: Sides, corners_w: np.ndarray, source: str,
                 resolved_by: str) -> TargetFix | None:
        """The fix of measured ``sides`` as the block ``corners_w`` ``(4, 2)`` (W, in
        the order of ``sides.corners_norm``); None when a corner's ray misses the
        ceiling or the edge residual RMS exceeds :data:`RMS_BAD_PX` (quality 0: a quad
        cut by the frame or by clutter that still fits the block's shape)."""
        got = solve(self.geo, sides.corners_norm, corners_w, sides.edge_norm, sides.side,
                    self.drop(corners_w))
        if got is None:
            return None
        shape, ref = got
        if not (np.all(np.isfinite(ref.pose)) and ref.rms_px <= RMS_BAD_PX):
            return None         # the block's outline does not explain its edges
        return TargetFix(source, self.pooled(source, ref), shape, sides.corners_norm,
                         corners_w, resolved_by)


def refine(geo: PlanarGeometry, pose0: tuple[float, float, float], corners_w: np.ndarray,
           edge_norm: np.ndarray, side: np.ndarray, scale: np.ndarray) -> PlanarFit:
    """Gauss-Newton on the pose from ``pose0``: edge points ``(M, 2)`` (normalized) of
    side ``side`` (M,) (side k runs from corner k to k+1 of ``corners_w``), residuals in
    px by ``scale`` (M,) (:func:`magnification`). Needs M >= 3 over three sides."""
    pose = np.array(pose0, float)
    edges = SideEdges(arr(corners_w, np.float64), arr(edge_norm, np.float64),
                      arr(side, np.int64), arr(scale, np.float64))
    m = edges.side.size
    fit = GNArrays(np.empty(m), np.empty((m, 3)), np.empty((3, 3)))
    if _gauss_newton(kernel_mount(geo), pose, edges, fit):
        r, J, JtJ = fit
    else:                           # a singular step: numpy's least squares, from pose0
        pose = np.array(pose0, float)
        r, J, JtJ = _gauss_newton_numpy(geo, pose, *edges)
    rms = float(np.sqrt(np.mean(r * r)))
    try:
        A = np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        pose[2] = wrap_pi(pose[2])
        return PlanarFit(pose, np.full((3, 3), np.inf), rms, int(r.size))
    s2, var_b, unit, common = residual_parts(r, J, side, A)
    cov = s2 * A + common + (var_b * unit if unit is not None else 0.0)
    pose[2] = wrap_pi(pose[2])
    return PlanarFit(pose, cov, rms, int(r.size), var_b, unit)


def _gauss_newton_numpy(geo: PlanarGeometry, pose: np.ndarray, *args: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_gauss_newton` in numpy with ``lstsq`` where the normal equations are
    singular (``pose`` is moved in place): ``(r, J, JᵀJ)``."""
    for it in range(GN_ITERATIONS + 1):
        rr = _side_residuals(geo, pose + _JAC_STEPS, *args)
        r = rr[0]
        J = ((rr[1:] - r) / JAC_EPS).T
        JtJ = J.T @ J
        if it == GN_ITERATIONS:
            break
        try:
            step = np.linalg.solve(JtJ, -(J.T @ r))
        except np.linalg.LinAlgError:
            step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        size = float(np.max(np.abs(step)))
        if size < GN_STEP_EPS:
            break
        pose += step
        if size < GN_LINEAR_EPS:
            r = r + J @ step
            break
    return r, J, JtJ


@njit
def _gauss_newton(mount, pose, edges, fit):  # pragma: no cover - compiled
    """Gauss-Newton of :func:`refine` from ``pose`` (moved in place) through the rig
    ``mount`` (a :class:`KernelMount`; its lens unused) on ``edges`` (a
    :class:`SideEdges`): the residuals ``r (M,)`` (px), their Jacobian ``J (M, 3)``
    (forward differences of :data:`JAC_EPS`) and ``JᵀJ`` at the end, written into
    ``fit`` (a :class:`GNArrays`). At most
    :data:`GN_ITERATIONS` steps; ends on a step below :data:`GN_STEP_EPS` (``r, J`` at
    the converged pose) or below :data:`GN_LINEAR_EPS` (``r`` moved linearly by the
    step, ``J`` kept). False (the caller falls back) when the normal equations are
    singular."""
    r, J, JtJ = fit.r, fit.J, fit.JtJ
    m = edges.side.size
    rp = np.empty(m)
    g = np.empty(3)
    step = np.empty(3)
    for it in range(GN_ITERATIONS + 1):
        _sides_at(mount, pose[0], pose[1], pose[2], edges, r)
        for c in range(3):
            _sides_at(mount, pose[0] + (JAC_EPS if c == 0 else 0.0),
                      pose[1] + (JAC_EPS if c == 1 else 0.0),
                      pose[2] + (JAC_EPS if c == 2 else 0.0), edges, rp)
            for i in range(m):
                J[i, c] = (rp[i] - r[i]) / JAC_EPS
        for a in range(3):
            g[a] = 0.0
            for b in range(3):
                JtJ[a, b] = 0.0
            for i in range(m):
                g[a] -= J[i, a] * r[i]
                for b in range(3):
                    JtJ[a, b] += J[i, a] * J[i, b]
        if it == GN_ITERATIONS:
            break
        if not _solve3(JtJ, g, step):
            return False
        size = max(abs(step[0]), abs(step[1]), abs(step[2]))
        if size < GN_STEP_EPS:
            break
        for a in range(3):
            pose[a] += step[a]
        if size < GN_LINEAR_EPS:
            for i in range(m):
                r[i] += J[i, 0] * step[0] + J[i, 1] * step[1] + J[i, 2] * step[2]
            break
    return True


@njit
def _sides_at(mount, x, y, yaw, edges, out):  # pragma: no cover - compiled
    """:func:`_side_residuals` of one pose ``(x, y, yaw)`` (m, m, rad) into ``out (M,)``:
    ``edges`` (a :class:`SideEdges`) seen through the rig ``mount``."""
    R, t, ceiling_m = mount.R, mount.t, mount.ceiling_m
    corners_w, edge_norm, side, scale = edges.corners_w, edges.edge_norm, edges.side, \
        edges.scale
    cz, sz = math.cos(yaw), math.sin(yaw)
    c = np.empty((4, 2))
    for k in range(4):
        vx, vy = level_offset(x, y, cz, sz, corners_w[k, 0], corners_w[k, 1])
        p0, p1, p2 = to_camera(R, vx - t[0], vy - t[1], ceiling_m - t[2])
        c[k, 0], c[k, 1] = p0 / p2, p1 / p2
    ln = np.empty((4, 3))
    for k in range(4):
        n = (k + 1) % 4
        a, b = c[k, 1] - c[n, 1], c[n, 0] - c[k, 0]
        norm = math.hypot(a, b)
        a, b = a / norm, b / norm
        ln[k, 0], ln[k, 1], ln[k, 2] = a, b, -(a * c[k, 0] + b * c[k, 1])
    for i in range(side.size):
        k = side[i]
        out[i] = (ln[k, 0] * edge_norm[i, 0] + ln[k, 1] * edge_norm[i, 1]
                  + ln[k, 2]) * scale[i]


@njit
def _solve3(A, b, x):  # pragma: no cover - compiled
    """``x`` of ``A x = b`` (3x3), Gaussian elimination with partial pivoting as LAPACK's
    ``gesv``; False on a zero pivot (singular)."""
    M = np.empty((3, 4))
    for i in range(3):
        for j in range(3):
            M[i, j] = A[i, j]
        M[i, 3] = b[i]
    for col in range(3):
        piv = col
        for i in range(col + 1, 3):
            if abs(M[i, col]) > abs(M[piv, col]):
                piv = i
        if M[piv, col] == 0.0:
            return False
        if piv != col:
            for j in range(4):
                M[col, j], M[piv, j] = M[piv, j], M[col, j]
        for i in range(col + 1, 3):
            f = M[i, col] / M[col, col]
            for j in range(col, 4):
                M[i, j] -= f * M[col, j]
    for i in range(2, -1, -1):
        acc = M[i, 3]
        for j in range(i + 1, 3):
            acc -= M[i, j] * x[j]
        x[i] = acc / M[i, i]
    return True


def side_offset_cov(r: np.ndarray, J: np.ndarray, side: np.ndarray, A: np.ndarray
                    ) -> tuple[float, np.ndarray | None]:
    """``(σ_b², U)`` of :func:`residual_parts`: the variance of an offset of a whole
    side, px², and the pose covariance ``(3, 3)`` per px² of it (None under 3 sides)."""
    _, var_b, unit, _ = residual_parts(r, J, side, A)
    return var_b, unit


def residual_parts(r: np.ndarray, J: np.ndarray, side: np.ndarray, A: np.ndarray
                   ) -> tuple[float, float, np.ndarray | None, np.ndarray]:
    """``(s², σ_b², U, C_c)``: the fit's residuals ``r (M,)`` (px, Jacobian ``J (M, 3)``,
    ``A = (JᵀJ)⁻¹``) split by what moves the pose; the covariance is
    ``s² A + σ_b² U + C_c``.

    * **The common offset** of the four sides (the block seen larger or smaller: blur
      rounding a small marker's corners, a hatch's edges on tile seams): the pose does
      not absorb it (a shift moves opposite sides apart by nothing) and it barely moves
      the pose, yet it stays in every residual. With four sides it is a fourth
      parameter: ``c`` the mean residual, taken out of the residuals, and its own
      effect on the pose, ``C_c = c² A g gᵀ A`` (``g = Σ_i J_i``), added. (Counted as
      white noise and as side offsets, it made a hatch on seams 20-100x too wide in
      variance and small markers 2.5x; issue 36.)
    * **Side offsets** (an error that moves one side's every point: a seam flush with
      an edge, narrower than the blur): the pose absorbs a common shift of opposite
      sides, not a difference, so the sides' mean residuals ``r̄_k`` (less ``c``) keep
      ``K - 3`` degrees of freedom of those offsets on four sides, ``K - 2`` on three
      (where ``c`` and the lone side's shift are one). ``σ_b² = max(Σ_k r̄_k² - d / K
      Σ_k s_k² / n_k, 0) / d`` (``d`` those degrees, ``s_k`` the scatter within side
      k: white noise's share of the means) and ``U = A (Σ_k g_k g_kᵀ) A`` with
      ``g_k = Σ_{i in k} J_i``. ``(0, None)`` under three sides (no size check).
    * **White noise**: the rest, ``s²`` its sum of squares over its ``nu = M - 3``
      degrees of freedom (``M - 4`` with ``c``), at least :data:`SIGMA_FLOOR_PX`, times
      :func:`student` of ``nu``.

    One compiled loop (:func:`_side_offsets`)."""
    unit, common = np.empty((3, 3)), np.empty((3, 3))
    s2, var_b, has_unit = _side_offsets(arr(r, np.float64), arr(J, np.float64),
                                        arr(side, np.int64), arr(A, np.float64), unit,
                                        common)
    return s2, var_b, unit if has_unit else None, common


SOLVED, NO_CLOSED_FORM, SINGULAR = 0, 1, 2     # solve_core's outcomes


def solve(geo: PlanarGeometry, corners_norm: np.ndarray, corners_w: np.ndarray,
          edge_norm: np.ndarray, side: np.ndarray, drop: np.ndarray
          ) -> tuple[float, PlanarFit] | None:
    """``(rms_m, refined)``: :func:`closed_form` of the corners (its RMS on the
    ceiling), then :func:`refine` from it on the edge points ``(M, 2)`` of the sides
    not in ``drop`` ``(4,)`` bool, weighted by the lens's :func:`magnification`; None
    when a corner's ray misses the ceiling. One compiled call (:func:`solve_core`); a
    singular Gauss-Newton step falls back to :func:`refine`'s least squares."""
    seen = SeenBlock(arr(corners_norm, np.float64), arr(corners_w, np.float64),
                     arr(edge_norm, np.float64), arr(side, np.int64), arr(drop, np.bool_))
    got = SolvedOut(np.empty(4), np.empty((3, 3)), np.empty((3, 3)))
    res = solve_core(kernel_mount(geo), seen, got)
    out = got.pose
    if res.status == NO_CLOSED_FORM:
        return None
    if res.status == SINGULAR:
        en, sd = seen.edge_norm, seen.side
        keep = ~seen.drop[sd]
        return float(out[3]), refine(geo, (out[0], out[1], out[2]), seen.corners_w, en[keep],
                                     sd[keep], magnification(geo.camera, en[keep]))
    return float(out[3]), PlanarFit(out[:3].copy(), got.cov, res.rms_px, res.m, res.var_b,
                                  got.unit if res.has_unit else None)


@njit
def solve_core(mount, seen, solved):  # pragma: no cover - compiled
    """:func:`solve` in one call: ``seen`` (a :class:`SeenBlock`) through the rig
    ``mount`` (a :class:`KernelMount`), into ``solved`` (a :class:`SolvedOut`) the pose
    ``(x, y, yaw)`` and the closed form's RMS on the ceiling, and :class:`PlanarFit`'s
    ``cov`` and ``unit``; returns a :class:`Solved`, status :data:`SOLVED`,
    :data:`NO_CLOSED_FORM` or :data:`SINGULAR` (``solved.pose`` then holds the closed
    form, for the caller's least squares)."""
    R, t, ceiling_m = mount.R, mount.t, mount.ceiling_m
    corners_norm, corners_w, edge_norm, side, drop = seen
    out, cov, unit = solved
    # the closed form: the corners on the ceiling (V), rigidly fitted to the block's
    rise = ceiling_m - t[2]
    q = np.empty((4, 2))
    for i in range(4):
        rises, ox, oy = meet_ceiling(R, corners_norm[i, 0], corners_norm[i, 1], rise,
                                     MIN_RZ, 0.0)
        if not rises:
            return Solved(NO_CLOSED_FORM, 0, np.nan, 0.0, False)
        q[i, 0] = t[0] + ox
        q[i, 1] = t[1] + oy
        if not (math.isfinite(q[i, 0]) and math.isfinite(q[i, 1])):
            return Solved(NO_CLOSED_FORM, 0, np.nan, 0.0, False)
    qx, qy = 0.25 * q[:, 0].sum(), 0.25 * q[:, 1].sum()
    px, py = 0.25 * corners_w[:, 0].sum(), 0.25 * corners_w[:, 1].sum()
    sc = ss = 0.0
    for i in range(4):
        ax, ay = q[i, 0] - qx, q[i, 1] - qy
        bx, by = corners_w[i, 0] - px, corners_w[i, 1] - py
        sc += ax * bx + ay * by
        ss += ax * by - ay * bx
    size = math.hypot(sc, ss)
    c, s = (sc / size, ss / size) if size > 0 else (1.0, 0.0)
    tx, ty = px - (c * qx - s * qy), py - (s * qx + c * qy)
    e2 = 0.0
    for i in range(4):
        rx = c * q[i, 0] - s * q[i, 1] + tx - corners_w[i, 0]
        ry = s * q[i, 0] + c * q[i, 1] + ty - corners_w[i, 1]
        e2 += rx * rx + ry * ry
    out[0], out[1], out[2], out[3] = tx, ty, math.atan2(s, c), math.sqrt(0.25 * e2)
    # the edge points of the sides kept, weighted by the lens's magnification
    m = 0
    for i in range(side.size):
        m += not drop[side[i]]
    en, sd = np.empty((m, 2)), np.empty(m, np.int64)
    j = 0
    for i in range(side.size):
        if not drop[side[i]]:
            en[j, 0], en[j, 1], sd[j] = edge_norm[i, 0], edge_norm[i, 1], side[i]
            j += 1
    scale = np.empty(m)
    magnification_points(en, mount.code, mount.lens, scale)
    pose = out[:3].copy()
    r, J, JtJ = np.empty(m), np.empty((m, 3)), np.empty((3, 3))
    if not _gauss_newton(mount, pose, SideEdges(corners_w, en, sd, scale), GNArrays(r, J, JtJ)):
        return Solved(SINGULAR, m, np.nan, 0.0, False)
    ssr = 0.0
    for i in range(m):
        ssr += r[i] * r[i]
    rms = math.sqrt(ssr / m)
    out[0], out[1] = pose[0], pose[1]
    out[2] = (pose[2] + math.pi) % (2.0 * math.pi) - math.pi
    A = np.empty((3, 3))
    if not scaled_inverse3(JtJ, 1.0, A):
        cov[:] = np.inf
        return Solved(SOLVED, m, rms, 0.0, False)
    common = np.empty((3, 3))
    s2, var_b, has_unit = _side_offsets(r, J, sd, A, unit, common)
    for a in range(3):
        for b in range(3):
            cov[a, b] = (s2 * A[a, b] + common[a, b]
                         + (var_b * unit[a, b] if has_unit else 0.0))
    return Solved(SOLVED, m, rms, var_b, has_unit)


@njit
def _side_offsets(r, J, side, A, unit, common):  # pragma: no cover - compiled
    """:func:`residual_parts` in a loop: ``(s², σ_b², has unit)``, ``U`` into ``unit``,
    the common offset's term into ``common``."""
    sums = np.zeros((4, 6))                    # n, Σr, Σr², ΣJ (3) per side
    ssr = 0.0
    for i in range(side.size):
        k = side[i]
        sums[k, 0] += 1.0
        sums[k, 1] += r[i]
        sums[k, 2] += r[i] * r[i]
        ssr += r[i] * r[i]
        for c in range(3):
            sums[k, 3 + c] += J[i, c]
    common[:] = 0.0
    m_all = float(side.size)
    K = 0
    for k in range(4):
        K += sums[k, 0] > 0
    four = K == 4
    c0 = 0.0
    if four:                                   # the sides' common offset: a 4th parameter
        c0 = (sums[0, 1] + sums[1, 1] + sums[2, 1] + sums[3, 1]) / m_all
        ssr = max(ssr - m_all * c0 * c0, 0.0)
        Ag = np.zeros(3)                       # A g, g = Σ_i J_i
        for a in range(3):
            for b in range(3):
                Ag[a] += A[a, b] * (sums[0, 3 + b] + sums[1, 3 + b] + sums[2, 3 + b]
                                    + sums[3, 3 + b])
        for a in range(3):
            for b in range(3):
                common[a, b] = c0 * c0 * Ag[a] * Ag[b]
    nu = max(m_all - (4.0 if four else 3.0), 1.0)
    s2 = max(ssr / nu, SIGMA_FLOOR_PX * SIGMA_FLOOR_PX) * student(nu)
    if K < 3:
        return s2, 0.0, False
    mm = noise = 0.0
    G = np.zeros((3, 3))
    for k in range(4):
        n = sums[k, 0]
        if n == 0:
            continue
        m = sums[k, 1] / n - c0
        mm += m * m
        noise += max(sums[k, 2] - n * (m + c0) * (m + c0), 0.0) / max(n - 1.0, 1.0) / n
        for a in range(3):
            for b in range(3):
                G[a, b] += sums[k, 3 + a] * sums[k, 3 + b]
    dof = K - 3 if four else K - 2
    var_b = max(mm - noise * dof / K, 0.0) / dof
    for a in range(3):                         # U = A G A
        for b in range(3):
            acc = 0.0
            for i in range(3):
                for j in range(3):
                    acc += A[a, i] * G[i, j] * A[j, b]
            unit[a, b] = acc
    return s2, var_b, True


@functools.lru_cache(maxsize=8)
def _mount_tilt_swing(R_bytes: bytes) -> tuple[float, float]:
    """The rig's tilt and swing (:func:`mount_angles` of ``R_vehicle_cam``, cached)."""
    _, tilt, swing = mount_angles(np.frombuffer(R_bytes, float).reshape(3, 3))
    return tilt, swing


def six_dof_check(geo: PlanarGeometry, corners_norm: np.ndarray, corners_w: np.ndarray,
                  yaw_rad: float) -> dict[str, float]:
    """The unconstrained 6-DoF PnP (IPPE, on undistorted points) against the rig.

    Returns ``pnp6_tilt_deg``, ``pnp6_swing_deg`` (the 6-DoF mount minus the rig's; no
    swing within a degree of tilt 90°, where only pan + swing is observable) and
    ``pnp6_height_m`` (the 6-DoF camera height minus the mount's); empty if OpenCV finds
    no solution.
    """
    obj = np.hstack([np.asarray(corners_w, float), np.full((4, 1), geo.ceiling_m)])
    ok, rvec, tvec = cv2.solvePnP(obj, np.asarray(corners_norm, float).reshape(-1, 1, 2),
                                  np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return {}
    R_cw, _ = cv2.Rodrigues(rvec)
    R_wc = R_cw.T
    centre = -R_wc @ tvec.ravel()
    _, tilt6, swing6 = mount_angles(rot_z(-yaw_rad) @ R_wc)
    tilt, swing = _mount_tilt_swing(np.asarray(geo.R_vehicle_cam, np.float64).tobytes())
    out = {"pnp6_tilt_deg": math.degrees(tilt6 - tilt),
           "pnp6_height_m": float(centre[2] - geo.t_vehicle_cam[2])}
    if abs(tilt - math.pi / 2) > VERTICAL_RAD:        # swing is pan's twin when looking up
        out["pnp6_swing_deg"] = math.degrees(wrap_pi(swing6 - swing))
    return out


@warmer
def _warm() -> None:
    R = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T.copy()
    square = np.array([[1.0, -0.2], [1.4, -0.2], [1.4, 0.2], [1.0, 0.2]])
    geo = PlanarGeometry(CameraModel.pinhole(4, 4, 2.0), R, np.zeros(3), 3.0)
    edge = project_norm(geo, (1.2, 0.0, 0.0), square[np.repeat(np.arange(4), 2)])
    refine(geo, (1.2, 0.0, 0.0), square, edge, np.repeat(np.arange(4), 2), np.ones(8))
    solve(geo, edge[::2], square, edge, np.repeat(np.arange(4), 2), np.zeros(4, bool))
