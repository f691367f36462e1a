"""Camera files: the ROS ``camera_info`` YAML layout (SPEC §2), read strictly.

Example::

    cam = load_camera("camera.yaml")            # every problem is a ConfigError
    save_camera(cam, "copy.yaml", header="# copied")
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ceilkit.runtime.config.yaml import Node, atomic_write_text, dump_yaml, load_yaml
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import DISTORTION_MODELS, N_COEFFS, CameraModel

CAMERA_KEYS = (
    "image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
    "distortion_coefficients", "rectification_matrix", "projection_matrix",
)


def camera_to_dict(camera: CameraModel) -> dict[str, Any]:
    """The ROS ``camera_info`` YAML mapping."""
    def mat(a: np.ndarray, rows: int, cols: int) -> dict[str, Any]:
        return {"rows": rows, "cols": cols, "data": [float(v) for v in a.ravel()]}

    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera.name,
        "camera_matrix": mat(camera.K, 3, 3),
        "distortion_model": camera.model,
        "distortion_coefficients": mat(camera.dist, 1, camera.dist.size),
        "rectification_matrix": mat(camera.R_rect, 3, 3),
        "projection_matrix": mat(camera.P, 3, 4),
    }

def save_camera(camera: CameraModel, path: str | Path, header: str = "") -> None:
    """Write ``camera.yaml`` atomically, after ``header`` (YAML comment lines)."""
    atomic_write_text(path, dump_yaml(camera_to_dict(camera), header))

def load_camera(path: str | Path) -> CameraModel:
    """Read a ROS ``camera_info`` YAML file; every problem is a ConfigError."""
    return camera_from_node(load_yaml(path))

def camera_from_node(node: Node) -> CameraModel:
    """The camera described by a ``camera_info`` mapping (a file's root or inline)."""
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
    want = N_COEFFS[model]
    dist = _read_matrix(dn, 1, None, DISTORTION_LIMIT)
    if dist.size != want:
        raise dn.error(f"{model} takes {want} coefficients, found {dist.size}")
    R = (_read_matrix(node.get("rectification_matrix"), 3, 3)
         if node.has("rectification_matrix") else None)
    P = (_read_matrix(node.get("projection_matrix"), 3, 4)
         if node.has("projection_matrix") else None)
    return CameraModel(width, height, K, dist.ravel(), model, name, R, P)



MATRIX_LIMIT = 1e6
"""The largest magnitude of a camera or projection matrix entry (px: focal lengths,
principal points), bounded before any arithmetic."""

DISTORTION_LIMIT = 1e3
"""The largest magnitude of a distortion coefficient (real lenses: below 10; a fit's
rational terms: below a few hundred)."""


def _read_matrix(node: Node, rows: int, cols: int | None,
                 limit: float = MATRIX_LIMIT) -> np.ndarray:
    node.mapping(("rows", "cols", "data"), required=("data",))
    data = node.get("data").numbers(lo=-limit, hi=limit)
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
    load_camera(path)
