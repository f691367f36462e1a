"""The joint refinement of a labeled frame: Gauss-Newton on ``(psi, c_y)``, the camera's
pan and y in W, over pixel residuals, and the vehicle pose it implies.

Residuals (px): each matched forward segment's two endpoints to their site line's
predicted image line, and each across segment's endpoint offset from the line
joining its midpoint to the across vanishing point. Huber weights (k = 1 px); the
covariance is the frame's own residual variance propagated, in three parts: a forward
segment's two endpoints come from one line fit, so their errors are not independent
(an offset and a turn of the segment, the turn's about 3 times the offset's variance),
and each part has its own variance (:func:`residual_cov`).

A rolling shutter (:class:`RowRates`): each observation is seen from the pose at its
row's time ``tau`` (:func:`~ceilkit.runtime.geometry.shutter.row_times_s`), to first
order ``psi + w tau`` and ``c_y + v tau`` with ``w`` the yaw rate and ``v`` the camera's
y speed in W, taken from the prior's velocity; what their uncertainty does to the pose
is added to the covariance (:func:`gauss_newton_rows`).

Example::

    gn = gn_inputs(fr, labeling.along, labeling.across, labeling.assign, setup)
    fit = gauss_newton(labeling.psi_rad, labeling.camera_y_m, gn, setup, iterations=6)
    yaw_rad, y_m, cov = vehicle_pose(fit, setup)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.corridor.frame import FrameLines
from ceilkit.runtime.estimators.corridor.geometry import vanishing_directions
from ceilkit.runtime.estimators.corridor.hypotheses import Labeling
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.geometry.fits import student
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.jit import arr, njit, warmer

STEP_DONE = (1e-5, 2e-4)
"""A step below this in ``(psi rad, c_y m)`` converges: the next is far smaller."""

MIN_SIGMA2_PX2 = 0.0004
"""Floor of each residual variance (px^2) in the covariance (:func:`residual_cov`): 0.02
px, as the lights' and the block's (a guard for a fit whose few residuals happen to be
tiny). It was 0.1 px,
which over-covered the simulated drives' error about 4x in variance (mean NEES 0.56 of
2 dof on the reversed corridor, ``benchmarks/bench_ambiguity.py``), then 0.05 px, which
still set the covariance of a clean camera: at noise 0.5 the endpoints' residual
variance is 0.0019 px², and 0.05 px gave a NEES of 0.39 of its dof on the forward
corridor, 0.02 px 0.52 (at noise 2 the residuals, 0.0037 px², set it either way)."""


@dataclass(frozen=True, eq=False)
class GNInputs:
    """The fixed inputs of :func:`residuals`.

    For the matched forward segments' endpoints ``e = (ex, ey, 1)`` (K of them):
    ``e0, e1, ez (K,)`` = ``R[i] . e`` (i = 0, 1, 2; ``R = R_level_cam``; then
    ``vb . e = s e0 + c e1`` and ``va . e = c e0 - s e1`` for ``c, s = cos, sin psi``)
    and their site lines' y ``(K,)``; for the across segments' lines ``l`` (B of
    them): ``p0, p1 (B,)`` = ``R[i] . l``, their midpoints ``mx_b, my_b (B,)`` and pixel
    scale ``scale_b (B,)`` (length f / sqrt 2).
    """

    n_a: int
    y: np.ndarray
    e0: np.ndarray
    e1: np.ndarray
    ez: np.ndarray
    p0: np.ndarray
    p1: np.ndarray
    mx_b: np.ndarray
    my_b: np.ndarray
    scale_b: np.ndarray
    tau: np.ndarray | None = None
    tau_b: np.ndarray | None = None

    @functools.cached_property
    def arrays(self) -> GNArrays:
        """The arrays as the compiled loops take them (:func:`_arrays`), made once."""
        return _arrays(self)


class RowRates(NamedTuple):
    """A rolling shutter's motion prior for :func:`gauss_newton_rows` (a named tuple:
    the compiled loops take it as it is).

    Attributes:
        w_rps, v_mps: the camera's yaw rate (rad/s) and y speed in W (m/s) expected
            (the prior's velocity: ``v = vy + w (Rz(yaw) t_VC)_x``; 0 when not known).
        sigma_w_rps, sigma_v_mps: their standard deviations.
    """

    w_rps: float
    v_mps: float
    sigma_w_rps: float
    sigma_v_mps: float


class LevelCamera(NamedTuple):
    """The camera as the compiled loops of the fit take it: ``R (3, 3)``
    (``R_level_cam``, float64), the ceiling's height above the camera ``h_m`` (m) and
    the focal length ``f_px`` (px)."""

    R: np.ndarray
    h_m: float
    f_px: float


class FrameArrays(NamedTuple):
    """A frame's segments as :func:`gn_arrays` reads them (:class:`.frame.FrameLines`'
    arrays, read-only): endpoints ``segs (N, 4)`` and lines ``lines_t (3, N)``
    (normalized), midpoints ``mx, my (N,)`` and lengths ``len_n (N,)``."""

    segs: np.ndarray
    lines_t: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    len_n: np.ndarray


_GN_ARRAYS = ("y", "e0", "e1", "ez", "p0", "p1", "mx_b", "my_b", "scale_b")
"""The fields of :class:`GNInputs` the compiled loops read, in their order."""

GNArrays = NamedTuple("GNArrays", [("n_a", int), *((k, np.ndarray) for k in _GN_ARRAYS)])
GNArrays.__doc__ = """:class:`GNInputs`' arrays as the compiled loops take them
(:func:`gn_arrays`): the count of matched forward segments ``n_a``, then the fields
:data:`_GN_ARRAYS` (``y, e0, e1, ez (K,)``, ``p0, p1, mx_b, my_b, scale_b (B,)``) as
:class:`GNInputs` names them."""


class Directions(NamedTuple):
    """``cos psi, sin psi`` and the vanishing directions ``va, vb`` of
    :func:`.geometry.vanishing_directions`, flat (:func:`directions_core`)."""

    c: float
    s: float
    va0: float
    va1: float
    va2: float
    vb0: float
    vb1: float
    vb2: float


class HuberFit(NamedTuple):
    """What :func:`huber_steps` returns: the solution ``psi, cy`` (rad, m), the normal
    matrix ``h00, h01, h10, h11`` of the last step and its ``Σ w r²`` ``wrr``."""

    psi: float
    cy: float
    h00: float
    h01: float
    h10: float
    h11: float
    wrr: float


def camera_y_speed(yaw_rad: float, vy_mps: float, w_rps: float,
                   setup: CorridorSetup) -> float:
    """The camera's y speed in W (m/s) of a vehicle at ``yaw_rad`` moving at ``vy_mps``
    and turning at ``w_rps``: ``vy + w (Rz(yaw) t_VC)_x``."""
    t_vx = math.cos(yaw_rad) * setup.t_vc[0] - math.sin(yaw_rad) * setup.t_vc[1]
    return vy_mps + w_rps * t_vx


def gn_inputs(fr: FrameLines, along: np.ndarray, across: np.ndarray, assign: np.ndarray,
              setup: CorridorSetup, tau_s: np.ndarray | None = None) -> GNInputs:
    """:class:`GNInputs` of the forward segments ``along`` matched by ``assign`` ``(N,)``
    (site line index, -1 none) and the ``across`` segments. ``tau_s`` ``(N, 2)``: each
    endpoint's row time (s, :func:`~ceilkit.runtime.geometry.shutter.row_times_s`; an
    across segment takes its endpoints' mean), None for a global shutter."""
    f64 = np.float64
    lines = FrameArrays(arr(fr.segs, f64).reshape(-1, 4), arr(fr.lines_t, f64),
                        arr(fr.mx, f64), arr(fr.my, f64), arr(fr.len_n, f64))
    n_a, y, e0, e1, ez, p0, p1, mx_b, my_b, scale_b = gn_arrays(
        lines, arr(along, np.bool_), arr(across, np.bool_), arr(assign, np.int64),
        arr(setup.site_y, f64), level_camera(setup, setup.R_level_cam))
    tau = tau_b = None
    if tau_s is not None:
        tau = tau_s[np.flatnonzero(along & (assign >= 0))].ravel()
        tau_b = tau_s[np.flatnonzero(across)].mean(axis=1)
    return GNInputs(n_a=n_a, y=y, e0=e0, e1=e1, ez=ez, p0=p0, p1=p1, mx_b=mx_b, my_b=my_b,
                    scale_b=scale_b, tau=tau, tau_b=tau_b)


def level_camera(setup: CorridorSetup, R: np.ndarray) -> LevelCamera:
    """The :class:`LevelCamera` of ``setup`` with the rotation ``R`` (its
    ``R_level_cam`` or its rows, as the caller passes them: the same numbers, made once
    per setup)."""
    if R is setup.R_level_cam or R is setup.R_rows:
        return _setup_camera(setup)
    return LevelCamera(arr(R, np.float64), float(setup.ceiling_above_cam_m),
                       float(setup.f_px))


@functools.lru_cache(maxsize=16)
def _setup_camera(setup: CorridorSetup) -> LevelCamera:
    """:func:`level_camera` of ``setup``'s own rotation."""
    return LevelCamera(arr(setup.R_level_cam, np.float64),
                       float(setup.ceiling_above_cam_m), float(setup.f_px))


@njit
def gn_arrays(lines, along, across, assign, site_y, cam):  # pragma: no cover - compiled
    """:func:`gn_inputs`' arrays in one loop from the frame's segments ``lines`` (a
    :class:`FrameArrays`), the camera ``cam`` (a :class:`LevelCamera`): a
    :class:`GNArrays`, the matched forward segments' endpoints ``p`` as ``R p``
    (``e0, e1, ez``) with their site line's ``y`` (twice), the across segments' lines
    as ``R[0] l``, ``R[1] l`` with their midpoints and ``len f_px / sqrt 2``."""
    segs, lines_t, mx, my, len_n = lines
    R, f_px = cam.R, cam.f_px
    n = segs.shape[0]
    n_a = n_b = 0
    for i in range(n):
        n_a += along[i] and assign[i] >= 0
        n_b += across[i]
    y = np.empty(2 * n_a)
    e0 = np.empty(2 * n_a)
    e1 = np.empty(2 * n_a)
    ez = np.empty(2 * n_a)
    p0 = np.empty(n_b)
    p1 = np.empty(n_b)
    mx_b = np.empty(n_b)
    my_b = np.empty(n_b)
    scale_b = np.empty(n_b)
    k = b = 0
    for i in range(n):
        if along[i] and assign[i] >= 0:
            for e in range(2):
                ex, ey = segs[i, 2 * e], segs[i, 2 * e + 1]
                y[k] = site_y[assign[i]]
                e0[k] = R[0, 0] * ex + R[0, 1] * ey + R[0, 2]
                e1[k] = R[1, 0] * ex + R[1, 1] * ey + R[1, 2]
                ez[k] = R[2, 0] * ex + R[2, 1] * ey + R[2, 2]
                k += 1
        if across[i]:
            l0, l1, l2 = lines_t[0, i], lines_t[1, i], lines_t[2, i]
            p0[b] = R[0, 0] * l0 + R[0, 1] * l1 + R[0, 2] * l2
            p1[b] = R[1, 0] * l0 + R[1, 1] * l1 + R[1, 2] * l2
            mx_b[b], my_b[b] = mx[i], my[i]
            scale_b[b] = len_n[i] * (f_px / math.sqrt(2.0))
            b += 1
    return GNArrays(n_a, y, e0, e1, ez, p0, p1, mx_b, my_b, scale_b)


def residuals(psi_rad: float, camera_y_m: float, gd: GNInputs,
              setup: CorridorSetup) -> np.ndarray:
    """``(K + B, 3)``: the pixel residuals (column 2) and their Jacobian in
    ``(psi, c_y)`` (columns 0, 1), along endpoints first, then across segments (a global
    shutter: every observation at the stamp's pose).

    With ``R_cw = R^T Rz(-psi)`` the ceiling line ``y = y_j`` is seen as
    ``l = R_cw (0, h, -(y_j - c_y)) = h vb - (y_j - c_y) m2`` (``vb`` the across
    direction, ``R_cw``'s y column; ``m2 = R[2]``, its z column), so
    ``dl/dpsi = h va`` and ``dl/dc_y = m2``."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    va, vb = vanishing_directions(psi_rad, setup.R_rows)
    h, f = setup.ceiling_above_cam_m, setup.f_px
    m2 = setup.R_rows[2]
    e0, e1, ez = gd.e0, gd.e1, gd.ez
    na, kb = e0.size, gd.p0.size
    out = np.empty((na + kb, 3))
    dy = gd.y - camera_y_m
    l0 = h * vb[0] - dy * m2[0]
    l1 = h * vb[1] - dy * m2[1]
    q = 1.0 / np.hypot(l0, l1)
    u = (h * (s * e0 + c * e1) - dy * ez) * q                  # signed distance
    dn_psi = h * (l0 * va[0] + l1 * va[1]) * q                  # d|l_xy|/dpsi
    dn_cy = (l0 * m2[0] + l1 * m2[1]) * q
    fq = f * q
    out[:na, 0] = (h * (c * e0 - s * e1) - u * dn_psi) * fq
    out[:na, 1] = (ez - u * dn_cy) * fq
    out[:na, 2] = u * f
    if kb:
        mx, my = gd.mx_b, gd.my_b
        p0, p1 = gd.p0, gd.p1
        bx = vb[0] - vb[2] * mx
        by = vb[1] - vb[2] * my
        den = np.hypot(bx, by)
        dden = (bx * (va[0] - va[2] * mx) + by * (va[1] - va[2] * my)) / den
        num = s * p0 + c * p1                                   # l . vb
        scale = gd.scale_b / den
        out[na:, 0] = ((c * p0 - s * p1) - num * dden / den) * scale   # l . va = dnum
        out[na:, 1] = 0.0
        out[na:, 2] = num * scale
    return out


@dataclass(frozen=True)
class PanOffsetFit:
    """The refined camera pan and y in W and their 2x2 covariance.

    Attributes:
        psi_rad, camera_y_m: the solution. cov: ``((p00, p01), (p10, p11))`` of
            ``(psi, c_y)`` (rad², rad m, m²; inf where the normal equations are
            singular). rms_px: the residuals' rms (NaN without residuals).
        residuals_px: ``(K + B,)`` the last step's pixel residuals (along endpoints
            first, then across segments), for the model check
            (:mod:`~ceilkit.runtime.estimators.honesty`).
    """

    psi_rad: float
    camera_y_m: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    rms_px: float
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)


def gauss_newton(psi_rad: float, camera_y_m: float, gd: GNInputs, setup: CorridorSetup,
                 iterations: int) -> PanOffsetFit:
    """At most ``iterations`` (at least 1) Huber-weighted Gauss-Newton steps on
    ``(psi, c_y)`` from the given start; stops on a step below :data:`STEP_DONE` or
    singular normal equations. The residuals and weights of the last step describe the
    solution (its step was below the threshold, the one after it far smaller)."""
    r = np.empty(gd.e0.size + gd.p0.size)
    psi, cy, h00, h01, h10, h11, wrr = huber_steps(
        (float(psi_rad), float(camera_y_m)), gd.arrays,
        level_camera(setup, setup.R_rows), max(1, iterations), r)
    det = h00 * h11 - h01 * h10
    C = residual_cov(psi, cy, gd, setup) if abs(det) > 1e-300 else None
    return pan_offset_fit(psi, cy, C, r)


def pan_offset_fit(psi: float, cy: float, C: np.ndarray | None, r: np.ndarray
                   ) -> PanOffsetFit:
    """The :class:`PanOffsetFit` of :func:`gauss_newton`'s solution ``(psi, cy)``, its
    covariance ``C (2, 2)`` (None: singular) and last residuals ``r`` (px)."""
    if C is not None:
        cov = ((float(C[0, 0]), float(C[0, 1])), (float(C[1, 0]), float(C[1, 1])))
    else:
        nan = float("nan")
        cov = ((np.inf, nan), (nan, np.inf))        # (as T diag(inf, inf) T^T: inf * 0)
    rms_px = math.sqrt(float(r @ r) / r.size) if r.size else float("nan")
    return PanOffsetFit(psi, cy, cov, rms_px, r)


def along_fit(segs_n: np.ndarray, line: np.ndarray, site_y: np.ndarray, cam: LevelCamera,
              psi_rad: float, camera_y_m: float, iterations: int) -> tuple[float, float, float]:
    """``(psi, c_y, rms_px)`` of :func:`gauss_newton` on forward segments only, each on
    its known site line: ``segs_n (N, 4)`` undistorted normalized, ``line (N,)`` indexes
    ``site_y (J,)`` (m), ``cam`` the :class:`LevelCamera` of ``R_level_cam``; the same
    numbers as :func:`gn_inputs` and :func:`joint_fit` of that labeling (a global
    shutter) without their arrays, covariance or objects: one compiled call
    (:func:`along_steps`), for a fit whose only use is where to search again."""
    r = np.empty(2 * segs_n.shape[0])
    psi, cy = along_steps(arr(segs_n, np.float64), arr(line, np.int64), site_y, cam,
                          (float(psi_rad), float(camera_y_m)),
                          max(1, iterations), r)
    return psi, cy, (math.sqrt(float(r @ r) / r.size) if r.size else float("nan"))


@njit
def along_steps(segs, line, site_y, cam, start, iterations, r):  # pragma: no cover - compiled
    """:func:`along_fit`: :func:`gn_arrays`' forward rows of ``segs (N, 4)`` on site lines
    ``site_y[line]`` (the same arithmetic), then :func:`huber_steps` (``r (2N,)``: the
    residuals written out); ``(psi, c_y)``."""
    n = segs.shape[0]
    R = cam.R
    y, e0, e1, ez = np.empty(2 * n), np.empty(2 * n), np.empty(2 * n), np.empty(2 * n)
    for i in range(n):
        for e in range(2):
            k = 2 * i + e
            ex, ey = segs[i, 2 * e], segs[i, 2 * e + 1]
            y[k] = site_y[line[i]]
            e0[k] = R[0, 0] * ex + R[0, 1] * ey + R[0, 2]
            e1[k] = R[1, 0] * ex + R[1, 1] * ey + R[1, 2]
            ez[k] = R[2, 0] * ex + R[2, 1] * ey + R[2, 2]
    none = np.empty(0)
    fit = huber_steps(start, GNArrays(2 * n, y, e0, e1, ez, none, none, none, none, none),
                      cam, iterations, r)
    return fit.psi, fit.cy


def _arrays(gd: GNInputs) -> GNArrays:
    """``gd``'s arrays as the compiled loops take them (read-only float64)."""
    return GNArrays(int(gd.e0.size), *(arr(getattr(gd, k), np.float64) for k in _GN_ARRAYS))


@njit
def huber_steps(start, gd, cam, iterations, r):  # pragma: no cover - compiled
    """The steps of :func:`gauss_newton` from ``start (psi, c_y)`` on the arrays ``gd``
    (a :class:`GNArrays`) through ``cam`` (a :class:`LevelCamera`), at most
    ``iterations``, stopping on a step below :data:`STEP_DONE` (the residuals of
    :func:`residuals`, written out): a :class:`HuberFit` with the normal matrix and
    ``r`` (the residuals, px) of the last step's start."""
    psi, cy = start
    na, kb = gd.e0.size, gd.p0.size
    R = cam.R
    h00 = h01 = h10 = h11 = wrr = 0.0
    for _ in range(iterations):
        dirs = directions_core(psi, R)
        h00 = h01 = h11 = g0 = g1 = wrr = 0.0
        for i in range(na + kb):
            j0, j1, ri = observation(i, na, dirs, cy, gd, cam)
            r[i] = ri
            w = min(1.0, 1.0 / max(abs(ri), 1e-9))            # Huber, k = 1 px
            h00 += w * j0 * j0
            h01 += w * j0 * j1
            h11 += w * j1 * j1
            g0 += w * j0 * ri
            g1 += w * j1 * ri
            wrr += w * ri * ri
        h10 = h01
        det = h00 * h11 - h01 * h10
        if not abs(det) > 1e-300:
            break
        d_psi = -(h11 * g0 - h01 * g1) / det
        d_cy = -(h00 * g1 - h10 * g0) / det
        psi, cy = psi + d_psi, cy + d_cy
        if abs(d_psi) < STEP_DONE[0] and abs(d_cy) < STEP_DONE[1]:
            break
    return HuberFit(psi, cy, h00, h01, h10, h11, wrr)


@njit
def directions_core(psi, R):  # pragma: no cover - compiled
    """The :class:`Directions` of :func:`.geometry.vanishing_directions` at ``psi``."""
    c, s = math.cos(psi), math.sin(psi)
    return Directions(c, s, c * R[0, 0] - s * R[1, 0], c * R[0, 1] - s * R[1, 1],
                      c * R[0, 2] - s * R[1, 2], s * R[0, 0] + c * R[1, 0],
                      s * R[0, 1] + c * R[1, 1], s * R[0, 2] + c * R[1, 2])


@njit
def observation(i, na, dirs, cy, gd, cam):  # pragma: no cover - compiled
    """Row ``i`` of :func:`residuals` (an along endpoint below ``na``, else an across
    segment) at ``c_y`` ``cy`` and the :class:`Directions` ``dirs`` of ``psi``, on the
    arrays ``gd`` (a :class:`GNArrays`) through ``cam`` (a :class:`LevelCamera`):
    ``(d r/d psi, d r/d c_y, r)``."""
    c, s, va0, va1, va2, vb0, vb1, vb2 = dirs
    m2x, m2y = cam.R[2, 0], cam.R[2, 1]
    h, f = cam.h_m, cam.f_px
    y, e0, e1, ez, p0, p1 = gd.y, gd.e0, gd.e1, gd.ez, gd.p0, gd.p1
    mx, my, scale_b = gd.mx_b, gd.my_b, gd.scale_b
    if i < na:
        dy = y[i] - cy
        l0 = h * vb0 - dy * m2x
        l1 = h * vb1 - dy * m2y
        q = 1.0 / math.hypot(l0, l1)
        u = (h * (s * e0[i] + c * e1[i]) - dy * ez[i]) * q
        dn_psi = h * (l0 * va0 + l1 * va1) * q
        dn_cy = (l0 * m2x + l1 * m2y) * q
        fq = f * q
        return (h * (c * e0[i] - s * e1[i]) - u * dn_psi) * fq, (ez[i] - u * dn_cy) * fq, u * f
    b = i - na
    bx = vb0 - vb2 * mx[b]
    by = vb1 - vb2 * my[b]
    den = math.hypot(bx, by)
    dden = (bx * (va0 - va2 * mx[b]) + by * (va1 - va2 * my[b])) / den
    num = s * p0[b] + c * p1[b]
    scale = scale_b[b] / den
    return ((c * p0[b] - s * p1[b]) - num * dden / den) * scale, 0.0, num * scale


def gauss_newton_rows(psi_rad: float, camera_y_m: float, gd: GNInputs,
                      setup: CorridorSetup, iterations: int, rates: RowRates
                      ) -> PanOffsetFit:
    """:func:`gauss_newton` for a rolling shutter (``gd`` with row times): each
    observation predicted from ``(psi + w tau, c_y + v tau)`` (first order) with the
    rates ``w, v`` of ``rates`` held fixed (fitting them too lets the frame's own small
    systematic errors pull them: the pose gets worse). The rates' uncertainty is added
    to the covariance of :func:`residual_cov` as a consider term,
    ``S diag(sigma_w^2, sigma_v^2) S^T`` with ``S`` the solution's sensitivity to the
    rates. One compiled call (:func:`rows_steps`)."""
    r = np.empty(gd.e0.size + gd.p0.size)
    C = np.empty((2, 2))
    tau = arr(np.concatenate([gd.tau, gd.tau_b]), np.float64)
    psi, cy, ok = rows_steps(
        (float(psi_rad), float(camera_y_m)), gd.arrays, tau,
        level_camera(setup, setup.R_level_cam), max(1, iterations),
        RowRates(*(float(v) for v in rates)), r, C)
    Cr = residual_cov(psi, cy, gd, setup, rates) if ok else None
    if Cr is not None:
        C = C + Cr
        cov = ((float(C[0, 0]), float(C[0, 1])), (float(C[1, 0]), float(C[1, 1])))
    else:
        nan = float("nan")
        cov = ((np.inf, nan), (nan, np.inf))
    rms_px = math.sqrt(float(r @ r) / r.size) if r.size else float("nan")
    return PanOffsetFit(psi, cy, cov, rms_px, r)


def joint_fit(gd: GNInputs, psi_rad: float, camera_y_m: float, setup: CorridorSetup,
              iterations: int, rates: RowRates | None = None) -> PanOffsetFit:
    """The joint fit of a labeled frame from ``(psi, c_y)`` (rad, m; camera pan and y
    in W), at most ``iterations`` steps: :func:`gauss_newton`, or with a rolling
    shutter's ``rates`` (``gd`` with row times) :func:`gauss_newton_rows`."""
    if rates is None:
        return gauss_newton(psi_rad, camera_y_m, gd, setup, iterations)
    return gauss_newton_rows(psi_rad, camera_y_m, gd, setup, iterations, rates)


@dataclass(frozen=True, eq=False)
class FrameFit:
    """A labeled frame and its joint fit, as the corridor's stages hand it on (the
    consensus or the window search to the model check).

    Attributes:
        lines: the frame's segments (:class:`~.frame.FrameLines`).
        labeling: their families and site lines (:class:`~.hypotheses.Labeling`; after
            the consensus, the segments it left out unmatched).
        gd: the fit's inputs (:class:`GNInputs`) of that labeling.
        fit: the fit (:class:`PanOffsetFit`, :func:`joint_fit`).
    """

    lines: FrameLines
    labeling: Labeling
    gd: GNInputs
    fit: PanOffsetFit


@njit
def rows_steps(start, gd, tau, cam, iterations, rates, r, C):  # pragma: no cover - compiled
    """The steps of :func:`gauss_newton_rows` from ``start (psi, c_y)`` on the arrays
    ``gd`` (a :class:`GNArrays`) with row times ``tau (K + B,)`` s through ``cam`` (a
    :class:`LevelCamera`), at most ``iterations`` (stopping as :func:`huber_steps`
    does), with the :class:`RowRates` ``rates`` (rows of :func:`residuals` with the
    rates' first-order shift ``(J_psi w + J_cy v) tau``, Huber at 1 px):
    ``(psi, c_y, ok)`` with ``r`` the last step's residuals (px) and ``C (2, 2)`` the
    rates' consider term of the covariance (ok False: the normal equations were
    singular, or the term is not finite)."""
    psi, cy = start
    w_rps, v_mps, sigma_w, sigma_v = rates
    R = cam.R
    na, n = gd.e0.size, gd.e0.size + gd.p0.size
    J = np.empty((n, 2))
    hw = np.empty(n)
    h00 = h01 = h10 = h11 = 0.0
    solved = False
    for _ in range(iterations):
        dirs = directions_core(psi, R)
        h00 = h01 = h10 = h11 = g0 = g1 = 0.0
        for i in range(n):
            j0, j1, ri = observation(i, na, dirs, cy, gd, cam)
            J[i, 0], J[i, 1] = j0, j1
            ri += (j0 * tau[i]) * w_rps + (j1 * tau[i]) * v_mps
            r[i] = ri
            hw[i] = min(1.0, 1.0 / max(abs(ri), 1e-9))
            h00 += j0 * hw[i] * j0
            h01 += j0 * hw[i] * j1
            h11 += j1 * hw[i] * j1
            g0 += j0 * hw[i] * ri
            g1 += j1 * hw[i] * ri
        h10 = h01
        det = h00 * h11 - h01 * h10
        solved = det != 0.0
        if not solved:
            break
        d_psi = -(h11 * g0 - h01 * g1) / det
        d_cy = -(h00 * g1 - h10 * g0) / det
        psi, cy = psi + d_psi, cy + d_cy
        if abs(d_psi) < STEP_DONE[0] and abs(d_cy) < STEP_DONE[1]:
            break
    if not solved:
        return psi, cy, False
    # S = -H^-1 (Jw^T Jr): the solution's sensitivity to (w, v)
    det = h00 * h11 - h01 * h10
    i00, i01, i10, i11 = h11 / det, -h01 / det, -h10 / det, h00 / det
    m00 = m01 = m10 = m11 = 0.0
    for i in range(n):
        a0, a1 = J[i, 0] * hw[i], J[i, 1] * hw[i]
        t0, t1 = J[i, 0] * tau[i], J[i, 1] * tau[i]
        m00 += a0 * t0
        m01 += a0 * t1
        m10 += a1 * t0
        m11 += a1 * t1
    s00, s01 = -(i00 * m00 + i01 * m10), -(i00 * m01 + i01 * m11)
    s10, s11 = -(i10 * m00 + i11 * m10), -(i10 * m01 + i11 * m11)
    vw, vv = sigma_w * sigma_w, sigma_v * sigma_v
    C[0, 0] = s00 * vw * s00 + s01 * vv * s01
    C[0, 1] = s00 * vw * s10 + s01 * vv * s11
    C[1, 0] = s10 * vw * s00 + s11 * vv * s01
    C[1, 1] = s10 * vw * s10 + s11 * vv * s11
    return psi, cy, bool(np.all(np.isfinite(C)))


def residual_cov(psi_rad: float, camera_y_m: float, gd: GNInputs, setup: CorridorSetup,
                 rates: RowRates | None = None) -> np.ndarray | None:
    """The ``(2, 2)`` covariance of ``(psi, c_y)`` (rad², rad m, m²) from the frame's own
    residuals at the solution (:func:`residuals`, Huber-weighted at 1 px, with the rows'
    shift of ``rates`` when given): :func:`segment_cov`, in one compiled call
    (:func:`fix_cov`). None where the normal equations are singular."""
    tau = (arr(np.concatenate([gd.tau, gd.tau_b]), np.float64) if rates is not None
           else arr(np.zeros(0), np.float64))
    rates = RowRates(0.0, 0.0, 0.0, 0.0) if rates is None else RowRates(*map(float, rates))
    C = np.empty((2, 2))
    ok = fix_cov((float(psi_rad), float(camera_y_m)), gd.arrays,
                 level_camera(setup, setup.R_rows), tau, rates, C)
    return C if ok else None


HUBER_PX = 1.0
"""The Huber threshold ``k`` (px) of the joint fit's weights (``min(1, k / |r|)``):
a row beyond it pulls the fit by ``k`` px whatever its residual."""

OUTLIER_SIGMAS = 5.0
"""A clipped row is outside the frame's noise beyond this many robust σ of its
residuals (:func:`_clipped_own`): Gaussian noise reaches it once in 1.7 million rows."""

MIN_SHARE_LINES = 4
"""Site lines a frame needs for :func:`segment_cov`'s shares: the fit's 2 parameters
take 2 of the lines' means, and a line's share needs 2 more to be seen."""


class ShareRows(NamedTuple):
    """The weighted rows :func:`share_cov` reads: Jacobian ``J (n, 2)`` and residuals
    ``r (n,)`` (px), the first ``n_a`` the endpoints of forward segments in pairs,
    segment ``k`` on site line ``line[k]`` of ``0..n_lines - 1``, the rest one per
    across segment."""

    J: np.ndarray
    r: np.ndarray
    n_a: int
    line: np.ndarray
    n_lines: int


def segment_cov(J: np.ndarray, r: np.ndarray, n_a: int, line_of: np.ndarray
                ) -> np.ndarray | None:
    """The covariance ``H^-1 M H^-1`` (``H = J^T J``) of a least-squares fit with
    weighted Jacobian ``J (n, 2)`` and residuals ``r (n,)`` (px): the first ``n_a`` the
    endpoints of forward segments in pairs, segment ``k`` on the site line
    ``line_of[k]``; the rest one per across segment. ``M`` is ``J^T Σ J`` for the errors
    the frame's own residuals show (:func:`_part_shares`):

    * a segment's two endpoints come from one line fit: its offset ``(r_0 + r_1) /
      sqrt 2`` and its turn ``(r_0 - r_1) / sqrt 2`` have their own variances (the
      turn's about 3 times the offset's for a uniform fit);
    * the segments of one site line share an error (the line's edge as the image and
      the locator draw it, seen by every piece of it): each of the offset and the turn
      has a share per segment and a share per site line, from the one-way analysis of
      variance of the segments by line;
    * the across rows: one variance;
    * a segment or across row the Huber weights clip and beyond :data:`OUTLIER_SIGMAS`
      robust σ (:func:`_clipped_own`: not the noise the shares describe) by its own
      pull ``g g^T``, the shares from the other rows about their own fit
      (:func:`_kept_rows`). Pooled, its ``|r|`` px² was every row's variance: the
      corridor's fixes on configs/block's tiles, seams crossing blocks and markers,
      read a mean NEES of 1.45 of 2, now 2.06 (docs/methods/corridor.md).

    On fewer than :data:`MIN_SHARE_LINES` site lines the fit takes the lines' means
    (2 parameters), so no line's share shows in the residuals: one variance for every
    residual, ``s^2 H^-1``, whatever else they show (the segments' shares alone covered
    a 2-line frame's error 3x too tight in variance, ``test_edge_point_noise_sweep``).

    Each share's variance is its sum of squares over its degrees of freedom ``nu``
    (the line's share: what the line means hold beyond the segments' share, at least
    0); a segment share or a single variance below :data:`MIN_SIGMA2_PX2` is set to it
    (then a stated value, not an estimate). The sum ``M`` is taken at its Student-t
    variance, times ``nu / (nu - 2)`` (at most 3) of its effective degrees of freedom
    (Welch-Satterthwaite: ``(Σ t_i)^2 / Σ t_i^2 / nu_i``, ``t_i = tr(H^-1 M_i)`` each
    share's part of the sum, a floored share counting none), so that a frame of few
    segments or lines is not taken at its sample variance, and a share estimated from
    few lines weighs on the factor as much as it weighs in the sum (each share at its
    own factor, the rule before, took a small line share from about 2 dof at 3x: the
    corridor's global path 1.2-1.3x wider in variance, docs/methods/honesty.md). One
    compiled call (:func:`share_cov`). None where ``H`` is singular."""
    _, line = np.unique(np.asarray(line_of), return_inverse=True)
    rows = ShareRows(arr(J, np.float64), arr(r, np.float64), int(n_a),
                     arr(line.ravel(), np.int64), int(line.max() + 1) if line.size else 0)
    C = np.empty((2, 2))
    return C if share_cov(rows, C) else None


@njit
def fix_cov(start, gd, cam, tau, rates, C):  # pragma: no cover - compiled
    """:func:`residual_cov` into ``C (2, 2)`` at ``start (psi, c_y)`` on the arrays
    ``gd`` (a :class:`GNArrays`) through ``cam`` (a :class:`LevelCamera`), with the
    rows' shift ``(J_psi w + J_cy v) tau`` of the :class:`RowRates` ``rates`` where the
    row times ``tau (K + B,)`` s are given (empty: none): the rows of :func:`residuals`
    Huber-weighted at 1 px, then :func:`share_cov`. False: ``H`` singular."""
    psi, cy = start
    w_rps, v_mps = rates.w_rps, rates.v_mps
    na, n = gd.e0.size, gd.e0.size + gd.p0.size
    dirs = directions_core(psi, cam.R)
    J = np.empty((n, 2))
    r = np.empty(n)
    for i in range(n):
        j0, j1, ri = observation(i, na, dirs, cy, gd, cam)
        if tau.size:
            ri = ri + ((j0 * tau[i]) * w_rps + (j1 * tau[i]) * v_mps)
        sw = math.sqrt(min(1.0, HUBER_PX / max(abs(ri), 1e-9)))
        J[i, 0], J[i, 1], r[i] = j0 * sw, j1 * sw, ri * sw
    ys = gd.y[0:na:2]
    line = np.zeros(ys.size, np.int64)
    n_lines = 0
    if ys.size:
        u = np.unique(ys)
        line, n_lines = np.searchsorted(u, ys), u.size
    return share_cov(ShareRows(J, r, na, line, n_lines), C)


@njit
def share_cov(rows, C):  # pragma: no cover - compiled
    """:func:`segment_cov` of the :class:`ShareRows` ``rows`` into ``C (2, 2)``: False
    where ``H`` is singular or ``C`` not finite."""
    J, r = rows.J, rows.r
    h00 = h01 = h11 = 0.0
    for i in range(r.size):
        h00 += J[i, 0] * J[i, 0]
        h01 += J[i, 0] * J[i, 1]
        h11 += J[i, 1] * J[i, 1]
    det = h00 * h11 - h01 * h01
    if not abs(det) > 1e-300:
        return False
    Hi = (h11 / det, -h01 / det, h00 / det)
    # acc: M00, M01, M11, Σ t_i, Σ t_i^2 / nu_i (Welch-Satterthwaite)
    acc = np.zeros(5)
    own = _clipped_own(rows, Hi, acc)
    if own.any():
        _kept_shares(_kept_rows(rows, own), Hi, acc)
    else:
        _kept_shares(rows, Hi, acc)
    f = student(acc[3] * acc[3] / acc[4]) if acc[4] > 0.0 else 1.0
    m00, m01, m11 = acc[0] * f, acc[1] * f, acc[2] * f
    i00, i01, i11 = Hi
    a00, a01 = i00 * m00 + i01 * m01, i00 * m01 + i01 * m11      # Hi M
    a10, a11 = i01 * m00 + i11 * m01, i01 * m01 + i11 * m11
    C[0, 0] = a00 * i00 + a01 * i01
    C[1, 1] = a10 * i01 + a11 * i11
    C[0, 1] = C[1, 0] = 0.5 * ((a00 * i01 + a01 * i11) + (a10 * i00 + a11 * i01))
    return math.isfinite(C[0, 0]) and math.isfinite(C[0, 1]) and math.isfinite(C[1, 1])


@njit
def _kept_shares(rows, Hi, acc):  # pragma: no cover - compiled
    """Add the shares of the :class:`ShareRows` ``rows`` to ``acc`` (:func:`share_cov`,
    ``H^-1`` of the whole fit as ``Hi``): on fewer than :data:`MIN_SHARE_LINES` lines
    one variance; else the segments' shares by part and the across rows' variance."""
    J, r, n_a = rows.J, rows.r, rows.n_a
    if rows.n_lines < MIN_SHARE_LINES:
        h00 = h01 = h11 = rr = 0.0
        for i in range(r.size):
            h00 += J[i, 0] * J[i, 0]
            h01 += J[i, 0] * J[i, 1]
            h11 += J[i, 1] * J[i, 1]
            rr += r[i] * r[i]
        nu = max(r.size - 2.0, 1.0)
        _add_share(acc, rr / nu, nu, (h00, h01, h11), Hi)
        return
    if n_a:
        _part_shares(rows, 1.0, Hi, acc)
        _part_shares(rows, -1.0, Hi, acc)
    if r.size > n_a:
        b00 = b01 = b11 = rb = 0.0
        for i in range(n_a, r.size):
            b00 += J[i, 0] * J[i, 0]
            b01 += J[i, 0] * J[i, 1]
            b11 += J[i, 1] * J[i, 1]
            rb += r[i] * r[i]
        nu = max(r.size - n_a - (Hi[0] * b00 + 2.0 * Hi[1] * b01 + Hi[2] * b11), 1.0)
        _add_share(acc, rb / nu, nu, (b00, b01, b11), Hi)


@njit
def _clipped_own(rows, Hi, acc):  # pragma: no cover - compiled
    """The rows outside the frame's noise (``(n,)`` bool): a row the Huber weights clip
    (``|r| > k`` px, :data:`HUBER_PX`) and beyond :data:`OUTLIER_SIGMAS` robust σ of the
    frame's residuals (1.4826 times their median ``|r|``): a piece of a line not drawn
    as the noise draws it, such as a block's or a marker's edge across a seam (where
    the noise itself reaches ``k``, its tail is clipped too but stays in the shares),
    with the other endpoint of its segment. Each clipped segment or across row adds its own term to
    ``acc``, ``g g^T`` with ``g = Σ J_i r_i`` over its rows (its pull on the fit, the
    two endpoints' together: a piece of a line drawn off pulls both ends alike), as a
    stated value (no dof): a clipped row pulls the fit by ``k`` px whatever its
    residual, and pooled with the others its ``|r|`` px² would be every row's
    variance."""
    J, r, n_a = rows.J, rows.r, rows.n_a
    raw = np.abs(r)                                  # |r| px before the weights
    for i in range(r.size):
        if raw[i] > HUBER_PX:
            raw[i] = raw[i] * raw[i] / HUBER_PX
    out = np.zeros(r.size, np.bool_)
    if r.size:
        cut = max(HUBER_PX, OUTLIER_SIGMAS * 1.4826 * np.median(raw))
        out = raw > cut
    own = np.zeros(r.size, np.bool_)
    for s in range(n_a // 2):
        i, j = 2 * s, 2 * s + 1
        if out[i] or out[j]:
            own[i] = own[j] = True
            g0, g1 = J[i, 0] * r[i] + J[j, 0] * r[j], J[i, 1] * r[i] + J[j, 1] * r[j]
            _add_term(acc, 1.0, math.inf, (g0 * g0, g0 * g1, g1 * g1), Hi)
    for i in range(n_a, r.size):
        if out[i]:
            own[i] = True
            g0, g1 = J[i, 0] * r[i], J[i, 1] * r[i]
            _add_term(acc, 1.0, math.inf, (g0 * g0, g0 * g1, g1 * g1), Hi)
    return own


@njit
def _kept_rows(rows, own):  # pragma: no cover - compiled
    """The :class:`ShareRows` of ``rows`` without the rows ``own`` marks (whole
    segments), their site lines numbered again ``0..`` over the lines left, and their
    residuals about their own least-squares fit: the solution the clipped rows pulled
    leaves in the kept rows' residuals ``J_k H_k^-1 g`` (``g`` the clipped rows' pull),
    a pattern of the parameters, not the kept rows' error."""
    keep = np.flatnonzero(~own)
    J, r = rows.J[keep], rows.r[keep]
    h00 = h01 = h11 = g0 = g1 = 0.0
    for i in range(r.size):
        h00 += J[i, 0] * J[i, 0]
        h01 += J[i, 0] * J[i, 1]
        h11 += J[i, 1] * J[i, 1]
        g0 += J[i, 0] * r[i]
        g1 += J[i, 1] * r[i]
    det = h00 * h11 - h01 * h01
    if abs(det) > 1e-300:
        d0, d1 = (h11 * g0 - h01 * g1) / det, (h00 * g1 - h01 * g0) / det
        for i in range(r.size):
            r[i] -= J[i, 0] * d0 + J[i, 1] * d1
    n_a = 0
    while n_a < keep.size and keep[n_a] < rows.n_a:
        n_a += 1
    line = rows.line[keep[0:n_a:2] // 2]
    used = np.zeros(max(rows.n_lines, 1), np.int64)
    for j in line:
        used[j] = 1
    new = np.cumsum(used) - 1
    for s in range(line.size):
        line[s] = new[line[s]]
    return ShareRows(J, r, n_a, line, int(used.sum()))


@njit
def _add_share(acc, s2, nu, m, Hi):  # pragma: no cover - compiled
    """Add a share of variance ``s2`` (px², from ``nu`` dof; below
    :data:`MIN_SIGMA2_PX2` set to it and counted as stated, no dof) on the rows whose
    ``J^T J`` is ``m (m00, m01, m11)`` to ``acc`` (:func:`share_cov`), given ``H^-1``
    as ``Hi (i00, i01, i11)``."""
    floored = s2 < MIN_SIGMA2_PX2
    v = MIN_SIGMA2_PX2 if floored else s2
    _add_term(acc, v, math.inf if floored else nu, m, Hi)


@njit
def _add_term(acc, v, nu, m, Hi):  # pragma: no cover - compiled
    """Add ``v m`` to ``acc``'s sum and its part ``t = v tr(H^-1 m)`` to the
    Welch-Satterthwaite sums (``t^2 / nu`` none for ``nu`` inf)."""
    t = v * (Hi[0] * m[0] + 2.0 * Hi[1] * m[1] + Hi[2] * m[2])
    acc[0] += v * m[0]
    acc[1] += v * m[1]
    acc[2] += v * m[2]
    acc[3] += t
    if math.isfinite(nu):
        acc[4] += t * t / nu


@njit
def _part_shares(rows, sign, Hi, acc):  # pragma: no cover - compiled
    """Add the shares of one part of the segments (``sign`` 1: their offsets, -1: their
    turns; rows ``(J_0 ± J_1) / sqrt 2``, values ``(r_0 ± r_1) / sqrt 2`` px) to ``acc``
    (:func:`share_cov`): ``Σ = s_w^2 I + tau^2 Z Z^T`` (``Z`` the segments' line
    membership), ``s_w^2`` the within-line mean square (``K - L`` dof, a segment share),
    ``tau^2`` = (between-line mean square - ``s_w^2``) / mean segments per line, at
    least 0, its dof ``L`` less the parameters' share of the part (its leverage,
    ``tr(Jg H^-1 Jg^T)``)."""
    J, r, line, n_lines = rows.J, rows.r, rows.line, rows.n_lines
    k = rows.n_a // 2
    h = math.sqrt(0.5)
    cnt = np.zeros(n_lines)
    sr = np.zeros(n_lines)
    g0 = np.zeros(n_lines)
    g1 = np.zeros(n_lines)
    m00 = m01 = m11 = lev = 0.0
    for s in range(k):
        a0 = (J[2 * s, 0] + sign * J[2 * s + 1, 0]) * h
        a1 = (J[2 * s, 1] + sign * J[2 * s + 1, 1]) * h
        j = line[s]
        cnt[j] += 1.0
        sr[j] += (r[2 * s] + sign * r[2 * s + 1]) * h
        g0[j] += a0
        g1[j] += a1
        m00 += a0 * a0
        m01 += a0 * a1
        m11 += a1 * a1
        lev += Hi[0] * a0 * a0 + 2.0 * Hi[1] * a0 * a1 + Hi[2] * a1 * a1
    ssw = 0.0
    for s in range(k):
        d = (r[2 * s] + sign * r[2 * s + 1]) * h - sr[line[s]] / cnt[line[s]]
        ssw += d * d
    nu_b = max(n_lines - lev, 1.0)
    nu_w = float(max(k - n_lines, 1))
    sw2 = ssw / nu_w
    msb = 0.0
    q00 = q01 = q11 = 0.0
    for j in range(n_lines):
        msb += sr[j] * sr[j] / cnt[j]
        q00 += g0[j] * g0[j]
        q01 += g0[j] * g1[j]
        q11 += g1[j] * g1[j]
    tau2 = max(0.0, msb / nu_b - sw2) / (k / n_lines)
    _add_share(acc, sw2, nu_w, (m00, m01, m11), Hi)
    _add_term(acc, tau2, nu_b, (q00, q01, q11), Hi)


def vehicle_pose(fit: PanOffsetFit, setup: CorridorSetup
                 ) -> tuple[float, float, np.ndarray]:
    """``(yaw_rad, y_m, cov (3, 3))`` of the vehicle in W from the camera's pan and y:
    ``yaw = psi - pan``, ``y = c_y - (Rz(yaw) t_VC)_y``; x is unobserved (``cov[0, 0]``
    inf)."""
    yaw = wrap_pi(fit.psi_rad - setup.pan_rad)
    cyaw, syaw = math.cos(yaw), math.sin(yaw)
    t_vc = setup.t_vc
    t_vx = cyaw * t_vc[0] - syaw * t_vc[1]      # (Rz(yaw) t_VC)_x, _y
    t_vy = syaw * t_vc[0] + cyaw * t_vc[1]
    y_m = fit.camera_y_m - t_vy
    (p00, p01), (p10, p11) = fit.cov
    # (yaw, y) = (psi - pan, c_y - t_vy(yaw)): d(yaw, y)/d(psi, c_y) = [[1, 0], [-t_vx, 1]]
    cov = np.zeros((3, 3))
    cov[0, 0] = np.inf
    cov[2, 2] = p00
    cov[1, 2] = cov[2, 1] = p10 - t_vx * p00
    cov[1, 1] = t_vx * t_vx * p00 - t_vx * (p01 + p10) + p11
    return yaw, y_m, cov


@warmer
def _warm() -> None:
    one, none = arr(np.ones(2), np.float64), arr(np.zeros(0), np.float64)
    rates = RowRates(0.1, 0.1, 0.1, 0.1)
    for a, b in ((one, none), (none, one)):          # along endpoints; across segments
        gd = GNArrays(a.size, a, a, a, a, b, b, b, b, b)
        cam = LevelCamera(arr(np.eye(3), np.float64), 2.0, 400.0)
        huber_steps((0.0, 0.0), gd, cam, 1, np.empty(2))
        rows_steps((0.0, 0.0), gd, one, cam, 1, rates, np.empty(2), np.empty((2, 2)))
        for tau in (none, one):                      # global shutter; rows
            fix_cov((0.0, 0.0), gd, cam, tau, rates, np.empty((2, 2)))
    f = np.float64
    seg = arr(np.array([[0.0, 0.0, 0.1, 0.0]]), f)
    on = arr(np.ones(1, bool), np.bool_)
    lines = FrameArrays(seg, arr(np.ones((3, 1)), f), arr(np.zeros(1), f),
                        arr(np.zeros(1), f), arr(np.ones(1), f))
    gn_arrays(lines, on, on, arr(np.zeros(1, np.int64), np.int64), arr(np.zeros(1), f),
              LevelCamera(arr(np.eye(3), f), 2.0, 400.0))
    along_fit(seg, arr(np.zeros(1, np.int64), np.int64), arr(np.zeros(1), f),
              LevelCamera(arr(np.eye(3), f), 2.0, 400.0), 0.0, 0.0, 1)
