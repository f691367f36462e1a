"""The rig: a camera and its mount on the vehicle (SPEC §1 and §2, ``rig.yaml``).

``rig.yaml``::

    camera: camera.yaml            # path relative to this file, or the mapping inline
    mount: {pan: 0.0, tilt: 45.0, swing: 0.0, x: 0.30, y: 0.0, z: 0.80}

Angles are degrees in the file and radians in :class:`Mount`; lengths are metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ceilkit.runtime.config.camera import camera_from_node, camera_to_dict, load_camera
from ceilkit.runtime.config.yaml import Node, atomic_write_text, dump_yaml, load_yaml
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import R_level_cam, R_vehicle_cam, rot_z

MOUNT_KEYS = ("pan", "tilt", "swing", "x", "y", "z")


@dataclass(frozen=True)
class Mount:
    """The camera's pose on the vehicle: ``X_V = R_vehicle_cam @ X_C + t_vehicle_cam``.

    Attributes:
        pan_rad: camera heading relative to the vehicle's, about the vertical.
        tilt_rad: elevation of the optical axis above the horizontal (pi/2 looks up).
        swing_rad: rotation about the optical axis.
        x_m, y_m, z_m: the optical centre in V; ``z_m`` is its height above the floor.
    """

    pan_rad: float = 0.0
    tilt_rad: float = math.pi / 2
    swing_rad: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.5

    @property
    def R_vehicle_cam(self) -> np.ndarray:
        return R_vehicle_cam(self.pan_rad, self.tilt_rad, self.swing_rad)

    @property
    def R_level_cam(self) -> np.ndarray:
        """``Ry(-tilt) R0 Rz(swing)``: the mount without its pan."""
        return R_level_cam(self.tilt_rad, self.swing_rad)

    @property
    def t_vehicle_cam(self) -> np.ndarray:
        return np.array([self.x_m, self.y_m, self.z_m])

    def R_world_cam(self, yaw_rad: float) -> np.ndarray:
        """Camera-to-world rotation for a vehicle at heading ``yaw_rad``."""
        return rot_z(yaw_rad) @ self.R_vehicle_cam

    def camera_position(self, x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
        """The optical centre in W for a vehicle pose."""
        return rot_z(yaw_rad) @ self.t_vehicle_cam + np.array([x_m, y_m, 0.0])

    def to_dict(self) -> dict[str, float]:
        return {
            "pan": round(math.degrees(self.pan_rad), 9),
            "tilt": round(math.degrees(self.tilt_rad), 9),
            "swing": round(math.degrees(self.swing_rad), 9),
            "x": round(self.x_m, 9), "y": round(self.y_m, 9), "z": round(self.z_m, 9),
        }

    @classmethod
    def from_node(cls, node: Node) -> Mount:
        node.mapping(MOUNT_KEYS, required=("tilt", "z"))
        return cls(
            pan_rad=math.radians(node.get("pan", 0.0).number(-180.0, 180.0, what=" degrees")),
            tilt_rad=math.radians(node.get("tilt").number(0.0, 90.0, what=" degrees")),
            swing_rad=math.radians(node.get("swing", 0.0).number(-180.0, 180.0,
                                                                 what=" degrees")),
            x_m=node.get("x", 0.0).number(-100.0, 100.0, what=" m"),
            y_m=node.get("y", 0.0).number(-100.0, 100.0, what=" m"),
            z_m=node.get("z").number(0.0, 100.0, lo_open=True, what=" m"),
        )


@dataclass(frozen=True)
class Rig:
    """A camera and its mount. ``source`` is the file it was read from, if any."""

    camera: CameraModel
    mount: Mount
    source: str | None = None
    camera_file: str | None = None

    def with_mount(self, mount: Mount) -> Rig:
        return replace(self, mount=mount)

    def to_dict(self, camera_ref: str | None = None) -> dict[str, Any]:
        cam: Any = camera_ref if camera_ref is not None else camera_to_dict(self.camera)
        return {"camera": cam, "mount": self.mount.to_dict()}

    def save(self, path: str | Path, header: str = "", camera_ref: str | None = None) -> None:
        """Write ``rig.yaml`` atomically, the camera inline unless ``camera_ref`` names
        a file (relative to ``path``) that already holds it."""
        atomic_write_text(path, dump_yaml(self.to_dict(camera_ref), header))

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """Read ``rig.yaml``; the camera is a path relative to it or an inline mapping."""
        path = Path(path)
        node = load_yaml(path).mapping(("camera", "mount"), required=("camera", "mount"))
        cnode = node.get("camera")
        camera_file = None
        if isinstance(cnode.value, str):
            cpath = Path(cnode.value)
            if not cpath.is_absolute():
                cpath = path.parent / cpath
            if not cpath.exists():
                raise cnode.error(f"camera file {cpath} not found")
            camera = load_camera(cpath)
            camera_file = str(cpath)
        elif isinstance(cnode.value, dict):
            camera = camera_from_node(cnode)
        else:
            raise cnode.expected("a camera file path or a camera_info mapping")
        mount = Mount.from_node(node.get("mount"))
        return cls(camera, mount, str(path), camera_file)
