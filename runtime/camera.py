"""The camera model: intrinsics and lens distortion, in ROS ``camera_info`` YAML.

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
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .config import Node, atomic_write_text, dump_yaml, load_yaml
from .errors import ConfigError

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
_N_COEFFS = {"plumb_bob": (5,), "rational_polynomial": (8,), "equidistant": (4,)}
CAMERA_KEYS = (
    "image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
    "distortion_coefficients", "rectification_matrix", "projection_matrix",
)
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
        if dist.size not in _N_COEFFS[self.model]:
            raise ValueError(f"{self.model} takes {_N_COEFFS[self.model][0]} coefficients")
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
            dist = np.zeros(_N_COEFFS[model][0])
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

    # -- files ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The ROS ``camera_info`` YAML mapping."""
        def mat(a: np.ndarray, rows: int, cols: int) -> dict[str, Any]:
            return {"rows": rows, "cols": cols, "data": [float(v) for v in a.ravel()]}

        return {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": self.name,
            "camera_matrix": mat(self.K, 3, 3),
            "distortion_model": self.model,
            "distortion_coefficients": mat(self.dist, 1, self.dist.size),
            "rectification_matrix": mat(self.R_rect, 3, 3),
            "projection_matrix": mat(self.P, 3, 4),
        }

    def save(self, path: str | Path, header: str = "") -> None:
        """Write ``camera.yaml`` atomically, after ``header`` (YAML comment lines)."""
        atomic_write_text(path, dump_yaml(self.to_dict(), header))

    @classmethod
    def load(cls, path: str | Path) -> CameraModel:
        """Read a ROS ``camera_info`` YAML file; every problem is a ConfigError."""
        return cls.from_node(load_yaml(path))

    @classmethod
    def from_node(cls, node: Node) -> CameraModel:
        node.mapping(CAMERA_KEYS, required=("image_width", "image_height", "camera_matrix",
                                            "distortion_coefficients"))
        width = node.get("image_width").integer(1, 100_000)
        height = node.get("image_height").integer(1, 100_000)
        nn = node.get("camera_name", "camera")
        if isinstance(nn.value, (int, float)) and not isinstance(nn.value, bool):
            name = str(nn.value)          # `camera_name: 0042` is a name, as ROS reads it
        else:
            name = nn.string()
        if node.has("distortion_model"):
            model = node.get("distortion_model").string(DISTORTION_MODELS)
        else:
            # files from before ROS wrote distortion_model: ROS reads 5 coefficients as
            # plumb_bob and 8 as rational_polynomial; anything else must say
            data = node.get("distortion_coefficients").get("data", None).value
            n_coeffs = len(data) if isinstance(data, list) else 0
            model = {5: "plumb_bob", 8: "rational_polynomial"}.get(n_coeffs, "")
            if not model:
                raise ConfigError(node.path, "distortion_model",
                                  f"missing required key (it can be left out only with 5 "
                                  f"or 8 distortion_coefficients, found {n_coeffs})")
        K = _read_matrix(node.get("camera_matrix"), 3, 3)
        kn = node.get("camera_matrix")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise kn.error(f"focal lengths must be positive, found fx={K[0, 0]:g}, "
                           f"fy={K[1, 1]:g}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise kn.error("expected an upper-triangular matrix with K[2][2] = 1")
        if not (-0.5 <= K[0, 2] <= width - 0.5 and -0.5 <= K[1, 2] <= height - 0.5):
            raise kn.error(f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the "
                           f"{width}x{height} image")
        dn = node.get("distortion_coefficients")
        want = _N_COEFFS[model][0]
        dist = _read_matrix(dn, 1, None)
        if dist.size != want:
            raise dn.error(f"{model} takes {want} coefficients, found {dist.size}")
        R = (_read_matrix(node.get("rectification_matrix"), 3, 3)
             if node.has("rectification_matrix") else None)
        P = (_read_matrix(node.get("projection_matrix"), 3, 4)
             if node.has("projection_matrix") else None)
        return cls(width, height, K, dist.ravel(), model, name, R, P)


def _read_matrix(node: Node, rows: int, cols: int | None) -> np.ndarray:
    node.mapping(("rows", "cols", "data"), required=("data",))
    data = node.get("data").numbers()
    r = node.get("rows", rows).integer(1, 64)
    c = node.get("cols", cols if cols is not None else len(data)).integer(0, 64)
    if r != rows or (cols is not None and c != cols):
        raise node.error(f"expected a {rows}x{cols if cols is not None else 'N'} matrix, "
                         f"found {r}x{c}")
    if len(data) != r * c:
        raise node.get("data").error(f"expected {r * c} numbers for a {r}x{c} matrix, "
                                     f"found {len(data)}")
    return np.array(data, dtype=np.float64).reshape(r, c)


def check_camera_file(path: str | Path) -> None:
    """Raise a ConfigError if ``path`` is not a valid camera file."""
    CameraModel.load(path)


__all__ = ["CameraModel", "DISTORTION_MODELS", "ConfigError", "check_camera_file"]
