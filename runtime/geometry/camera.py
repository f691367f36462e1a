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

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
N_COEFFS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


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
            raise ValueError(f"unknown distortion model {self.model!r}")
        object.__setattr__(self, "K", _frozen(self.K, (3, 3)))
        dist = np.array(self.dist, dtype=np.float64).ravel()
        if dist.size != N_COEFFS[self.model]:
            raise ValueError(f"{self.model} takes {N_COEFFS[self.model]} coefficients")
        object.__setattr__(self, "dist", _frozen(dist, (dist.size,)))
        R = np.eye(3) if self.R_rect is None else self.R_rect
        object.__setattr__(self, "R_rect", _frozen(R, (3, 3)))
        P = np.hstack([self.K, np.zeros((3, 1))]) if self.P is None else self.P
        object.__setattr__(self, "P", _frozen(P, (3, 4)))

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
        return bool(np.any(self.dist != 0.0))

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
        """Pixels of normalized points ``(N, 2)`` (through the lens distortion)."""
        xy = np.asarray(xy_norm, dtype=np.float64).reshape(-1, 2)
        if xy.shape[0] == 0:
            return np.zeros((0, 2))
        if self.model == "equidistant":
            out = cv2.fisheye.distortPoints(xy.reshape(-1, 1, 2), self.K, self.dist)
            return out.reshape(-1, 2)
        pts = np.hstack([xy, np.ones((xy.shape[0], 1))])
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return out.reshape(-1, 2)

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

    def in_image(self, points_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (by ``margin_px``)."""
        p = np.asarray(points_px).reshape(-1, 2)
        return ((p[:, 0] >= -0.5 + margin_px) & (p[:, 0] <= self.width - 0.5 - margin_px)
                & (p[:, 1] >= -0.5 + margin_px) & (p[:, 1] <= self.height - 0.5 - margin_px))


__all__ = ["CameraModel", "DISTORTION_MODELS"]
