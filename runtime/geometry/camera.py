"""The camera model: intrinsics and lens distortion (ALL lens math lives here).

Files (ROS ``camera_info`` YAML) are read and written by :mod:`ceilkit.runtime.config.camera`.

Convention: OpenCV camera frame (x right, y down, z along the optical axis); pixel
(u, v) with the origin at the centre of the top-left pixel (SPEC §1). Normalized
coordinates are ``(x/z, y/z)`` of a point in the camera frame, before distortion.

Only feature points are undistorted on the hot path, never whole images.

Example::

    cam = CameraModel.pinhole(640, 480, fx=500.0)
    px = cam.project(np.array([[0.1, 0.0, 1.0]]))      # -> [[370., 239.5]]
    cam.unproject(px)                                   # -> [[0.1, 0.]]
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.jit import arr, njit, warmer

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
N_COEFFS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
# the fast undistortion: a fixed number of OpenCV's iterations, used for a camera whose
# image border (a grid of _FAST_BORDER_NODES per side) reprojects within _FAST_TOL_PX
_FAST_ITERATIONS = 10
_FAST_CRITERIA = (cv2.TERM_CRITERIA_COUNT, _FAST_ITERATIONS, 0.0)
_FAST_TOL_PX = 1e-4
_FAST_BORDER_NODES = (33, 25)
_POLYNOMIAL_MODELS = ("plumb_bob", "rational_polynomial")
FEW_POINTS = 32      # distort: up to this many points, cv2.projectPoints (faster below ~50)
_ZERO3 = np.zeros(3)
JACOBIAN_EPS = 1e-4  # distort_jacobian's normalized step where OpenCV does not project
# the ray table (:func:`subpixel_rays`): the lens inverted exactly every _TABLE_STEP_PX
# pixels (_TABLE_PAD nodes beyond the border), a node whose inverse reprojects more than
# _TABLE_TOL_PX off has no ray
_TABLE_STEP_PX = 2
_TABLE_PAD = 3
_TABLE_TOL_PX = 0.05
LENS_LINEAR, LENS_POLYNOMIAL, LENS_EQUIDISTANT = 0, 1, 2
"""The lens codes of :attr:`CameraModel.lens`: no distortion, OpenCV's polynomial
(plumb_bob, rational_polynomial), OpenCV's fisheye (equidistant)."""
_UNDISTORT_MAX_ITER, _UNDISTORT_EPS = 50, 1e-12   # as _UNDISTORT_CRITERIA


def _frozen(a: Any, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(a, dtype=np.float64).reshape(shape)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera.

    Attributes:
        width, height: image size in pixels.
        K: 3x3 camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
        dist: distortion coefficients; their count follows ``model``
            (plumb_bob 5: k1 k2 p1 p2 k3; rational_polynomial 8: k1 k2 p1 p2 k3 k4 k5 k6;
            equidistant 4: k1 k2 k3 k4, OpenCV's fisheye model).
        model: one of :data:`DISTORTION_MODELS`.
        name: ``camera_name``.
        R_rect, P: ROS ``rectification_matrix`` and ``projection_matrix``, kept for
            round trips; ceilkit itself does not rectify.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    model: str = "plumb_bob"
    name: str = "camera"
    R_rect: np.ndarray = field(default=None)  # type: ignore[assignment]
    P: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.model not in DISTORTION_MODELS:
            raise ConfigError(None, "model", f"expected one of {', '.join(DISTORTION_MODELS)}, "
                              f"found {self.model!r}")
        object.__setattr__(self, "K", _frozen(self.K, (3, 3)))
        dist = np.array(self.dist, dtype=np.float64).ravel()
        if dist.size != N_COEFFS[self.model]:
            raise ConfigError(None, "dist", f"{self.model} takes {N_COEFFS[self.model]} "
                              f"coefficients, found {dist.size}")
        object.__setattr__(self, "dist", _frozen(dist, (dist.size,)))
        R = np.eye(3) if self.R_rect is None else self.R_rect
        object.__setattr__(self, "R_rect", _frozen(R, (3, 3)))
        P = np.hstack([self.K, np.zeros((3, 1))]) if self.P is None else self.P
        object.__setattr__(self, "P", _frozen(P, (3, 4)))
        object.__setattr__(self, "_key", (self.width, self.height, self.model,
                                          (self.K + 0.0).tobytes(), (self.dist + 0.0).tobytes()))
        object.__setattr__(self, "_distorted", bool(np.any(self.dist != 0.0)))
        object.__setattr__(self, "_opencv_projects",
                           self.model in _POLYNOMIAL_MODELS and float(self.K[0, 1]) == 0.0)
        k8 = np.zeros(8)
        if self.model != "equidistant":
            k8[:dist.size] = dist
        object.__setattr__(self, "_k8", tuple(float(v) for v in k8))
        object.__setattr__(self, "_K_rows", ((float(self.K[0, 0]), float(self.K[0, 1]),
                                               float(self.K[0, 2])),
                                              (float(self.K[1, 1]), float(self.K[1, 2]))))
        # the lens for compiled loops (:func:`undistort_points`): its code and
        # (fx, fy, cx, cy, skew, k0..k7)
        code = (LENS_LINEAR if not self._distorted else
                LENS_EQUIDISTANT if self.model == "equidistant" else LENS_POLYNOMIAL)
        lens = np.zeros(13)
        lens[:5] = (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], self.K[0, 1])
        lens[5:5 + dist.size] = dist
        lens.setflags(write=False)
        object.__setattr__(self, "_lens", (code, lens))
        # which terms of OpenCV's polynomial are there (distort skips the others)
        object.__setattr__(self, "_terms", (bool(np.any(k8[[0, 1, 4]])), bool(np.any(k8[2:4])),
                                            bool(np.any(k8[5:]))))

    # -- identity -------------------------------------------------------------------
    @property
    def key(self) -> tuple:
        """What the lens math depends on: ``(width, height, model, K bytes, dist bytes)``
        (``-0.0`` counted as ``0.0``). Hashing and equality use it (equality also
        compares ``name``, ``R_rect`` and ``P``), so a camera can key a cache
        (``functools.lru_cache``)."""
        return self._key  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (self.key == other.key and self.name == other.name
                and np.array_equal(self.R_rect, other.R_rect) and np.array_equal(self.P, other.P))

    # -- construction -------------------------------------------------------------
    @classmethod
    def pinhole(cls, width: int, height: int, fx: float, fy: float | None = None,
                cx: float | None = None, cy: float | None = None,
                dist: Any = None, model: str = "plumb_bob", name: str = "camera"
                ) -> CameraModel:
        """A camera with the principal point at the image centre unless given."""
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        if dist is None:
            dist = np.zeros(N_COEFFS[model])
        K = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
        return cls(width, height, np.array(K), np.asarray(dist, float), model, name)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height

    @property
    def is_distorted(self) -> bool:
        return self._distorted  # type: ignore[attr-defined]

    @property
    def lens(self) -> tuple[int, np.ndarray]:
        """``(code, params (13,))``: the lens as compiled loops take it
        (:func:`undistort_points`): :data:`LENS_LINEAR`, :data:`LENS_POLYNOMIAL` or
        :data:`LENS_EQUIDISTANT`, and ``(fx, fy, cx, cy, skew, coefficients...)``
        (zero-padded, read-only)."""
        return self._lens  # type: ignore[attr-defined]

    @property
    def opencv_projects(self) -> bool:
        """Whether ``cv2.projectPoints`` (no rotation, no translation) gives this lens's
        pixels: a polynomial model and no skew (OpenCV's projection has no skew term)."""
        return self._opencv_projects  # type: ignore[attr-defined]

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same lens on a sensor resampled to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        K[0, 2] = (self.cx + 0.5) * sx - 0.5
        K[1, 2] = (self.cy + 0.5) * sy - 0.5
        return CameraModel(width, height, K, self.dist, self.model, self.name)

    # -- projection -----------------------------------------------------------------
    def distort(self, xy_norm: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` of normalized points ``(N, 2)`` (through the lens distortion).

        OpenCV's formulas (``cv2.projectPoints``, ``cv2.fisheye.distortPoints``) in
        numpy: fast on millions of points (the simulator's ray grids). A few points
        of a polynomial lens (up to :data:`FEW_POINTS`: a quad's corners, a chord's
        ends) go through ``cv2.projectPoints`` itself, one call instead of twenty (it
        has no skew term: a skewed ``K`` stays in numpy)."""
        xy = np.asarray(xy_norm, dtype=np.float64).reshape(-1, 2)
        d = self.dist
        if xy.shape[0] <= FEW_POINTS and self.opencv_projects:
            return self._cv_project(xy)[0].reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        if self.model == "equidistant":
            r = np.hypot(x, y)
            th = np.arctan(r)
            t2 = th * th
            thd = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
            with np.errstate(divide="ignore", invalid="ignore"):
                sc = np.where(r > 1e-12, thd / r, 1.0)
            xd, yd = x * sc, y * sc
        else:           # the terms of the lens only (a call's cost is its numpy calls)
            k1, k2, p1, p2, k3, k4, k5, k6 = self._k8  # type: ignore[attr-defined]
            radial, tangential, rational = self._terms  # type: ignore[attr-defined]
            xd, yd = x, y
            if radial or rational or tangential:
                r2 = x * x + y * y
            if radial or rational:
                rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)) if radial else 1.0
                if rational:
                    rad = rad / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
                xd, yd = x * rad, y * rad
            if tangential:
                xy2 = 2 * x * y
                xd = xd + p1 * xy2 + p2 * (r2 + 2 * x * x)
                yd = yd + p1 * (r2 + 2 * y * y) + p2 * xy2
        fx, skew, cx = self._K_rows[0]  # type: ignore[attr-defined]
        fy, cy = self._K_rows[1]  # type: ignore[attr-defined]
        out = np.empty((xy.shape[0], 2))
        out[:, 0] = fx * xd + (skew * yd + cx if skew else cx)
        out[:, 1] = fy * yd + cy
        return out

    def distort_jacobian(self, xy_norm: np.ndarray) -> np.ndarray:
        """``(N, 2, 2)`` d(pixel)/d(normalized point) at normalized points ``(N, 2)``:
        ``cv2.projectPoints``' own Jacobian where it projects this lens
        (:attr:`opencv_projects`; with no rotation and the points at z = 1 the pixel's
        derivative by the translation is its derivative by the point), else forward
        differences of :meth:`distort` by :data:`JACOBIAN_EPS`."""
        xy = np.asarray(xy_norm, dtype=np.float64).reshape(-1, 2)
        if xy.shape[0] and self.opencv_projects:
            return self._cv_project(xy)[1][:, 3:5].reshape(-1, 2, 2)
        e = JACOBIAN_EPS
        a, pu, pv = self.distort(np.concatenate([xy, xy + [e, 0.0], xy + [0.0, e]])
                                 ).reshape(3, -1, 2)
        return np.stack([(pu - a) / e, (pv - a) / e], axis=2)

    def _cv_project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.projectPoints`` of normalized points ``(N, 2)`` at z = 1 (no rotation,
        no translation): ``(pixels (N, 1, 2), Jacobian (2N, 10 + coefficients))``."""
        p = np.ones((xy.shape[0], 3))
        p[:, :2] = xy
        return cv2.projectPoints(p, _ZERO3, _ZERO3, self.K, self.dist)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` of 3-D points ``(N, 3)`` in the camera frame.

        Points on or behind the image plane (z <= 0) give NaN.
        """
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = P[:, 2]
        ok = z > 1e-12
        out = np.full((P.shape[0], 2), np.nan)
        if np.any(ok):
            out[ok] = self.distort(P[ok, :2] / z[ok, None])
        return out

    def unproject(self, points_px: np.ndarray) -> np.ndarray:
        """Normalized coordinates ``(N, 2)`` of pixels ``(N, 2)``, distortion removed."""
        px = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.is_distorted:
            x = (px[:, 0, 0] - self.cx - self.K[0, 1] * (px[:, 0, 1] - self.cy) / self.fy)
            return np.stack([x / self.fx, (px[:, 0, 1] - self.cy) / self.fy], axis=1)
        px = _unskewed(self.K, px)
        if self.model == "equidistant":
            out = cv2.fisheye.undistortPoints(px, self.K, self.dist,
                                              criteria=_UNDISTORT_CRITERIA)
        else:
            out = cv2.undistortPoints(px, self.K, self.dist, criteria=_UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def rays(self, points_px: np.ndarray) -> np.ndarray:
        """Unit viewing rays ``(N, 3)`` in the camera frame for pixels ``(N, 2)``."""
        xy = self.unproject(points_px)
        r = np.hstack([xy, np.ones((xy.shape[0], 1))])
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    def unproject_fast(self, points_px: np.ndarray) -> np.ndarray:
        """:meth:`unproject` ``(N, 2)`` for many points per frame: for the polynomial
        models a fixed 10 iterations of OpenCV's undistortion (no convergence test).
        Used only for a camera whose image border reprojects within 1e-4 px after those
        10 iterations (checked once per camera); other cameras go to :meth:`unproject`."""
        px = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        if px.shape[0] == 0 or not _fast_unproject_ok(self):
            return self.unproject(px)
        return self._undistort_fixed(px)

    def _undistort_fixed(self, px: np.ndarray) -> np.ndarray:
        return cv2.undistortPoints(_unskewed(self.K, px.reshape(-1, 1, 2)), self.K, self.dist,
                                   criteria=_FAST_CRITERIA).reshape(-1, 2)


    def reprojects(self, points_px: np.ndarray, xy_norm: np.ndarray, tol_px: float
                   ) -> np.ndarray:
        """``(N,)`` bool: where the normalized points ``xy_norm (N, 2)`` (an inverse of
        ``points_px (N, 2)``) are finite and :meth:`distort` back within ``tol_px`` of
        the pixels (False where the lens has no inverse: a fisheye beyond its range, a
        distortion that folds over)."""
        px = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        xy = np.asarray(xy_norm, dtype=np.float64).reshape(-1, 2)
        good = np.all(np.isfinite(xy), axis=1)
        back = np.full_like(xy, np.nan)
        if np.any(good):
            back[good] = self.distort(xy[good])
        good &= np.linalg.norm(back - px, axis=1) < tol_px
        return good

    def unit_rays(self, points_px: np.ndarray, tol_px: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Unit rays ``(N, 3)`` of pixels ``(N, 2)`` and ``(N,)`` whether the lens
        defines them: inside the image and :meth:`reprojects` within ``tol_px``. A ray
        the lens does not define is the optical axis ``(0, 0, 1)``."""
        px = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        inside = self.in_image(px)
        rays = np.zeros((px.shape[0], 3))
        ok = inside.copy()
        if np.any(inside):
            xy = self.unproject(px[inside])
            good = self.reprojects(px[inside], xy, tol_px)
            r = np.hstack([np.where(good[:, None], xy, 0.0), np.ones((xy.shape[0], 1))])
            rays[inside] = r / np.linalg.norm(r, axis=1, keepdims=True)
            ok[inside] = good
        return rays, ok

    def in_image(self, points_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (by ``margin_px``)."""
        p = np.asarray(points_px).reshape(-1, 2)
        return ((p[:, 0] >= -0.5 + margin_px) & (p[:, 0] <= self.width - 0.5 - margin_px)
                & (p[:, 1] >= -0.5 + margin_px) & (p[:, 1] <= self.height - 0.5 - margin_px))


def _unskewed(K: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 1, 2)`` with ``K``'s skew taken off (OpenCV's inverses ignore it):
    what an unskewed ``K`` shows of the same normalized points."""
    skew = float(K[0, 1])
    if not skew:
        return px
    px = px.copy()
    px[:, 0, 0] -= skew * (px[:, 0, 1] - K[1, 2]) / K[1, 1]
    return px


@functools.lru_cache(maxsize=16)
def _fast_unproject_ok(camera: CameraModel) -> bool:
    """Whether :meth:`CameraModel.unproject_fast` may use the fixed iterations: a
    distorted polynomial lens whose image border reprojects within ``_FAST_TOL_PX``."""
    if not camera.is_distorted or camera.model not in _POLYNOMIAL_MODELS:
        return False
    u = np.linspace(-0.5, camera.width - 0.5, _FAST_BORDER_NODES[0])
    v = np.linspace(-0.5, camera.height - 0.5, _FAST_BORDER_NODES[1])
    border = np.concatenate([np.stack([u, np.full_like(u, v[0])], 1),
                             np.stack([u, np.full_like(u, v[-1])], 1),
                             np.stack([np.full_like(v, u[0]), v], 1),
                             np.stack([np.full_like(v, u[-1]), v], 1)])
    back = camera.distort(camera._undistort_fixed(border))
    return bool(np.all(np.abs(back - border) <= _FAST_TOL_PX))


@njit
def undistort_points(px, code, lens, out):  # pragma: no cover - compiled
    """Into ``out (N, 2)``: :meth:`CameraModel.unproject` of pixels ``px (N, 2)`` for
    a lens ``(code, lens)`` (:attr:`CameraModel.lens`), in a compiled loop: the
    inverse OpenCV converges to (``cv2.undistortPoints``, ``cv2.fisheye.undistortPoints``
    to 1e-12): the same numbers wherever the lens has one, to OpenCV's convergence
    (its polynomial iterations stop up to 1e-6 px off far out on a strong lens, these
    reproject within 1e-12 px; beyond, where the
    distortion folds over, each returns some point that does not reproject: check with
    :meth:`CameraModel.reprojects`). A skewed ``K``'s skew is taken off the pixel
    first (OpenCV's inverses ignore it); a fisheye point whose angle does not converge
    is ``(-1e6, -1e6)``, as OpenCV's."""
    fx, fy, cx, cy, skew = lens[0], lens[1], lens[2], lens[3], lens[4]
    k = lens[5:]
    radial = radial_only(k)
    for n in range(px.shape[0]):
        u, v = px[n, 0], px[n, 1]
        if code == 0:
            out[n, 0] = (u - cx - skew * (v - cy) / fy) / fx
            out[n, 1] = (v - cy) / fy
            continue
        if skew != 0.0:
            u = u - skew * (v - cy) / fy
        if code == 1:
            out[n, 0], out[n, 1] = _undistort_polynomial(u, v, fx, fy, cx, cy, k,
                                                         radial)
        else:
            out[n, 0], out[n, 1] = _undistort_fisheye(u, v, fx, fy, cx, cy, k)


def fixed_iterations(camera: CameraModel) -> int:
    """How many iterations :func:`undistort_fixed_points` takes for ``camera`` when
    :func:`unproject_many` inverts its lens there (a distorted polynomial lens whose
    border it reprojects to within tolerance); 0: it does not (a compiled caller then
    goes through :func:`unproject_many`)."""
    return _FAST_ITERATIONS if _fast_unproject_ok(camera) else 0


def unproject_many(camera: CameraModel, points_px: np.ndarray) -> np.ndarray:
    """:meth:`CameraModel.unproject_fast` ``(N, 2)`` of pixels ``(N, 2)``: where it takes
    OpenCV's fixed iterations, in a compiled loop (:func:`undistort_fixed_points`, the
    same numbers without OpenCV's call)."""
    px = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if px.shape[0] == 0 or not _fast_unproject_ok(camera):
        return camera.unproject_fast(px)
    out = np.empty_like(px)
    undistort_fixed_points(arr(px, np.float64), camera.lens[1], _FAST_ITERATIONS, out)
    return out


@njit
def undistort_fixed_points(px, lens, iterations, out):  # pragma: no cover - compiled
    """Into ``out (N, 2)``: ``cv2.undistortPoints`` of pixels ``px (N, 2)`` for a
    polynomial lens (:attr:`CameraModel.lens`) with a count criterion of
    ``iterations`` (no convergence test), ``K``'s skew taken off first: OpenCV's
    arithmetic in its order (its terms of coefficients these lenses do not have
    dropped: they add zero), the same numbers."""
    fx, fy, cx, cy, skew = lens[0], lens[1], lens[2], lens[3], lens[4]
    ifx, ify = 1.0 / fx, 1.0 / fy
    k = lens[5:]
    for n in range(px.shape[0]):
        u, v = px[n, 0], px[n, 1]
        if skew != 0.0:
            u = u - skew * (v - cy) / fy
        x = (u - cx) * ifx
        y = (v - cy) * ify
        x0, y0 = x, y
        for _ in range(iterations):
            r2 = x * x + y * y
            icdist = ((1 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2)
                      / (1 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2))
            if icdist < 0:
                x, y = x0, y0
                break
            dx = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
            dy = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
            x = (x0 - dx) * icdist
            y = (y0 - dy) * icdist
        out[n, 0], out[n, 1] = x, y


@njit
def distort_points(xy, code, lens, out):  # pragma: no cover - compiled
    """Into ``out (N, 2)``: :meth:`CameraModel.distort` of normalized points ``xy (N, 2)``
    for a lens ``(code, lens)`` (:attr:`CameraModel.lens`), in a compiled loop (its
    formulas: OpenCV's polynomial and fisheye models, ``K`` with its skew)."""
    fx, fy, cx, cy, skew = lens[0], lens[1], lens[2], lens[3], lens[4]
    k = lens[5:]
    for n in range(xy.shape[0]):
        x, y = xy[n, 0], xy[n, 1]
        xd, yd = x, y
        if code == 2:
            r = math.sqrt(x * x + y * y)
            th = math.atan(r)
            t2 = th * th
            thd = th * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
            sc = thd / r if r > 1e-12 else 1.0
            xd, yd = x * sc, y * sc
        elif code == 1:
            r2 = x * x + y * y
            rad = ((1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4])))
                   / (1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))))
            xy2 = 2 * x * y
            xd = x * rad + k[2] * xy2 + k[3] * (r2 + 2 * x * x)
            yd = y * rad + k[2] * (r2 + 2 * y * y) + k[3] * xy2
        out[n, 0] = fx * xd + skew * yd + cx
        out[n, 1] = fy * yd + cy


@njit
def magnification_points(xy, code, lens, out):  # pragma: no cover - compiled
    """Into ``out (N,)``: pixels per normalized unit at normalized points ``xy (N, 2)``,
    ``sqrt |det J|`` of the lens ``(code, lens)`` (:attr:`CameraModel.lens`): the
    polynomial model's Jacobian in closed form (``K``'s skew leaves the determinant
    alone), a fisheye's by forward differences of :data:`JACOBIAN_EPS` (as
    :meth:`CameraModel.distort_jacobian`)."""
    fx, fy = lens[0], lens[1]
    k = lens[5:]
    one, a = np.empty((1, 2)), np.empty((3, 2))
    for n in range(xy.shape[0]):
        x, y = xy[n, 0], xy[n, 1]
        if code == 0:
            det = fx * fy
        elif code == 1:
            _, _, ja, jb, jc, jd = _polynomial_step(x, y, 0.0, 0.0, k, False)
            det = fx * fy * (ja * jd - jb * jc)
        else:
            for j in range(3):
                one[0, 0] = x + (JACOBIAN_EPS if j == 1 else 0.0)
                one[0, 1] = y + (JACOBIAN_EPS if j == 2 else 0.0)
                distort_points(one, code, lens, a[j:j + 1])
            det = ((a[1, 0] - a[0, 0]) * (a[2, 1] - a[0, 1])
                   - (a[2, 0] - a[0, 0]) * (a[1, 1] - a[0, 1])) / (JACOBIAN_EPS * JACOBIAN_EPS)
        out[n] = math.sqrt(abs(det))


@njit
def _undistort_polynomial(u, v, fx, fy, cx, cy, k, radial
                          ):  # pragma: no cover - compiled
    """The normalized point whose distortion is pixel ``(u, v)`` (OpenCV's polynomial
    lens, no tilt, no thin prism): Newton's steps on the distortion from the distorted
    point, until the point reprojects within 1e-12 px or a step moves it less (50 at
    most), the
    inverse ``cv2.undistortPoints`` converges to. A step that does not bring the
    point nearer its pixel, or crosses a fold of the distortion (far out, where the
    Jacobian's determinant turns negative: a second, outer preimage), is halved.
    ``radial``: the lens has no tangential or rational terms (:func:`radial_only`;
    :func:`_polynomial_step`'s)."""
    x0 = (u - cx) / fx
    y0 = (v - cy) / fy
    x, y = x0, y0
    ex, ey, a, b, c, d = _polynomial_step(x, y, x0, y0, k, radial)
    err = ex * ex + ey * ey
    f2 = max(fx, fy) ** 2
    for _ in range(_UNDISTORT_MAX_ITER):
        if err * f2 < _UNDISTORT_EPS * _UNDISTORT_EPS:     # reprojects within 1e-12 px
            break
        det = a * d - b * c
        if not (math.isfinite(det) and det != 0.0):
            break
        sx = (d * ex - b * ey) / det
        sy = (a * ey - c * ex) / det
        t = 1.0
        for _ in range(30):
            xn, yn = x - t * sx, y - t * sy
            exn, eyn, an, bn, cn, dn = _polynomial_step(xn, yn, x0, y0, k, radial)
            errn = exn * exn + eyn * eyn
            if errn <= err and an * dn - bn * cn > 0:     # nearer, and not past a fold
                break
            t *= 0.5
        else:
            break
        x, y, ex, ey, a, b, c, d, err = xn, yn, exn, eyn, an, bn, cn, dn, errn
        if max(abs(t * sx) * fx, abs(t * sy) * fy) < _UNDISTORT_EPS:
            break
    return x, y


@njit
def radial_only(k):  # pragma: no cover - compiled
    """Whether a polynomial lens's coefficients ``k`` (``(k1, k2, p1, p2, k3, k4, k5,
    k6, ...)``) have no tangential (``p1``, ``p2``) and no rational (``k4..k6``) terms:
    then :func:`_polynomial_step` leaves out their terms, which add exact zeros (and
    divide by an exact 1)."""
    return k[2] == 0.0 and k[3] == 0.0 and k[5] == 0.0 and k[6] == 0.0 and k[7] == 0.0


@njit
def _polynomial_step(x, y, x0, y0, k, radial):  # pragma: no cover - compiled
    """``(ex, ey, dxd/dx, dxd/dy, dyd/dx, dyd/dy)``: the distortion of the normalized
    point ``(x, y)`` minus ``(x0, y0)``, and its Jacobian. ``radial``
    (:func:`radial_only`): without the terms that are exact zeros there (``p1``,
    ``p2``) and the division by the rational denominator, an exact 1: the same numbers
    (for finite ``r2``; the sign of an exact zero aside), in 2 divisions fewer a step
    (the lens's inverse is most of a window search's points: issue 38)."""
    r2 = x * x + y * y
    if radial:
        rad = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
        drad = k[0] + r2 * (2 * k[1] + 3 * k[4] * r2)
        xy2 = 2 * x * y * drad
        return (x * rad - x0, y * rad - y0, rad + 2 * x * x * drad, xy2, xy2,
                rad + 2 * y * y * drad)
    num = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    den = 1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))
    dnum = k[0] + r2 * (2 * k[1] + 3 * k[4] * r2)
    dden = k[5] + r2 * (2 * k[6] + 3 * k[7] * r2)
    rad = num / den
    drad = (dnum * den - num * dden) / (den * den)     # d rad / d r2
    p1, p2 = k[2], k[3]
    ex = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - x0
    ey = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - y0
    xy2 = 2 * x * y * drad
    a = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    b = xy2 + 2 * p1 * x + 2 * p2 * y
    d = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return ex, ey, a, b, b, d


@njit
def _undistort_fisheye(u, v, fx, fy, cx, cy, k):  # pragma: no cover - compiled
    """OpenCV's ``fisheye::undistortPoints`` for one pixel: Newton steps on the angle
    ``theta`` until a step is below 1e-12; ``(-1e6, -1e6)`` when they do not converge
    or the angle changes sign."""
    wx, wy = (u - cx) / fx, (v - cy) / fy
    theta_d = min(max(-math.pi / 2, math.sqrt(wx * wx + wy * wy)), math.pi / 2)
    theta = theta_d
    converged = False
    scale = 1.0
    if abs(theta_d) > _UNDISTORT_EPS:
        for _ in range(_UNDISTORT_MAX_ITER):
            t2 = theta * theta
            t4 = t2 * t2
            t6 = t4 * t2
            t8 = t6 * t2
            fix = ((theta * (1 + k[0] * t2 + k[1] * t4 + k[2] * t6 + k[3] * t8) - theta_d)
                   / (1 + 3 * k[0] * t2 + 5 * k[1] * t4 + 7 * k[2] * t6 + 9 * k[3] * t8))
            theta = theta - fix
            if abs(fix) < _UNDISTORT_EPS:
                converged = True
                break
        scale = math.tan(theta) / theta_d
    else:
        converged = True
    flipped = (theta_d < 0 and theta > 0) or (theta_d > 0 and theta < 0)
    if converged and not flipped:
        return wx * scale, wy * scale
    return -1e6, -1e6


@warmer
def _warm() -> None:
    px = np.zeros((1, 2))
    px.setflags(write=False)
    for cam in (CameraModel.pinhole(4, 4, 2.0),
                CameraModel.pinhole(4, 4, 2.0, dist=[0.1, 0, 0, 0, 0]),
                CameraModel.pinhole(4, 4, 2.0, dist=[0.1, 0, 0, 0], model="equidistant")):
        undistort_points(px, *cam.lens, np.empty((1, 2)))
        distort_points(px, *cam.lens, np.empty((1, 2)))
        magnification_points(px, *cam.lens, np.empty(1))


@functools.lru_cache(maxsize=8)
def subpixel_rays(camera: CameraModel, ss: int) -> np.ndarray:
    """``(H*ss, W*ss, 3)`` rays (z = 1, NaN where the lens has no inverse) of the
    ``ss x ss`` sub-pixels of every pixel (sub-pixel centres at ``(k + 0.5) / ss - 0.5``
    px from the pixel centre), read-only.

    The lens is inverted exactly on a grid every 2 pixels (nodes at even pixels from row
    and column 0) and interpolated (OpenCV's bicubic remap) between. A pixel's centre
    (``ss = 1``), and the mean of its ``ss x ss`` samples, reproject within about 1e-3 px
    (median 0.4e-3 px, largest 2e-3 to 0.01 px on 320x240 test lenses of each model);
    each sample alone lies up to 0.13 px nearer its pixel's centre than asked (median
    0.09 px at ``ss = 3``, a pinhole too: the remap's kernel and its 1/32-node steps),
    so the samples span a slightly smaller footprint than the pixel.
    """
    step, pad = _TABLE_STEP_PX, _TABLE_PAD
    gu = np.arange(-pad * step, camera.width + pad * step + 1, step, dtype=np.float64)
    gv = np.arange(-pad * step, camera.height + pad * step + 1, step, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    px = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xy = camera.unproject(px)
    bad = ~camera.reprojects(px, xy, _TABLE_TOL_PX)                  # no inverse there
    grid = xy.reshape(gv.size, gu.size, 2).astype(np.float32)
    badg = bad.reshape(gv.size, gu.size).astype(np.float32)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(camera.width)[:, None] + off[None, :]).ravel()
    v = (np.arange(camera.height)[:, None] + off[None, :]).ravel()
    mu, mv = np.meshgrid((u - gu[0]) / step, (v - gv[0]) / step)
    mu, mv = mu.astype(np.float32), mv.astype(np.float32)
    xy_sub = cv2.remap(grid, mu, mv, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    bad_sub = cv2.remap(badg, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) > 0
    xy_sub = xy_sub.astype(np.float64)
    xy_sub[bad_sub] = np.nan
    rays = np.concatenate([xy_sub, np.ones(xy_sub.shape[:2] + (1,))], axis=2)
    rays.setflags(write=False)
    return rays


__all__ = ["CameraModel", "DISTORTION_MODELS", "LENS_EQUIDISTANT", "LENS_LINEAR",
           "LENS_POLYNOMIAL", "distort_points", "fixed_iterations", "magnification_points",
           "subpixel_rays", "undistort_fixed_points", "undistort_points", "unproject_many"]
