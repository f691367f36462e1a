"""The mount in the forms integrators paste: a URDF joint, a ROS 2 static transform and
ArduPilot's ``VISO_POS_X/Y/Z``, written beside rig.yaml with its provenance header.

Frames (SPEC §1, docs/conventions.md): the vehicle frame V (x forward, y left, z up,
origin at the reference point on the floor) is REP-103's ``base_link``; the camera
frame C (OpenCV: x right, y down, z along the optical axis) is REP-103's optical frame
(``camera_optical_frame``: z forward, x right, y down). So the transform from
``base_link`` to ``camera_optical_frame`` is the mount itself, with no axis swap::

    X_base_link = R_VC X_optical + (mx, my, mz)

URDF's ``rpy`` is fixed-axis roll about x, then pitch about y, then yaw about z:
``R = Rz(yaw) Ry(pitch) Rx(roll)``; tf2's quaternion is ``(qx, qy, qz, qw)``. ArduPilot
takes the camera's optical centre in the body frame FRD (x forward, y right, z down),
relative to the autopilot (``autopilot_V_m``, default V's origin):
:func:`ceilkit.calib.autopilot.sensor_offset_frd`.

Example::

    >>> m = Mount(pan_rad=0.0, tilt_rad=math.pi / 2, swing_rad=0.0, z_m=0.5)  # looks up
    >>> static_transform_args(m)[6:14]         # the optical frame: x right, y back
    ['--qx', '0', '--qy', '0', '--qz', '-0.707107', '--qw', '0.707107']
    >>> viso_pos(Mount(x_m=0.3, y_m=0.1, z_m=0.8))
    (0.3, -0.1, -0.8)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from scipy.spatial.transform import Rotation

from ceilkit.runtime.config.rig import Mount
from ceilkit.runtime.config.yaml import atomic_write_text

from .autopilot import sensor_offset_frd

PARENT_FRAME = "base_link"
CHILD_FRAME = "camera_optical_frame"
JOINT_NAME = "ceilkit_camera_optical_joint"
DECIMALS = 6


def _num(value: float) -> str:
    """``value`` to 1 um / 1 urad, without trailing zeros or a ``-0``."""
    text = f"{round(float(value), DECIMALS) + 0.0:.{DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def mount_rpy(mount: Mount) -> tuple[float, float, float]:
    """URDF ``rpy`` (rad) of ``R_VC``: ``R_VC = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = Rotation.from_matrix(mount.R_vehicle_cam).as_euler("xyz")
    return float(r), float(p), float(y)


def mount_quaternion(mount: Mount) -> tuple[float, float, float, float]:
    """``(qx, qy, qz, qw)`` of ``R_VC`` (qw >= 0)."""
    q = Rotation.from_matrix(mount.R_vehicle_cam).as_quat()
    q = -q if q[3] < 0 else q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def urdf_joint(mount: Mount, parent: str = PARENT_FRAME, child: str = CHILD_FRAME,
               name: str = JOINT_NAME) -> str:
    """A fixed URDF joint from ``parent`` (V) to ``child`` (the optical frame C)."""
    xyz = " ".join(_num(v) for v in mount.t_vehicle_cam)
    rpy = " ".join(_num(v) for v in mount_rpy(mount))
    return (f'<joint name="{name}" type="fixed">\n'
            f'  <parent link="{parent}"/>\n'
            f'  <child link="{child}"/>\n'
            f'  <origin xyz="{xyz}" rpy="{rpy}"/>\n'
            '</joint>\n')


def static_transform_args(mount: Mount, parent: str = PARENT_FRAME,
                          child: str = CHILD_FRAME) -> list[str]:
    """The arguments of ``ros2 run tf2_ros static_transform_publisher`` (ROS 2 Humble
    and later: named ``--x ... --qw``, ``--frame-id``, ``--child-frame-id``)."""
    t = mount.t_vehicle_cam
    q = mount_quaternion(mount)
    out: list[str] = []
    for key, value in zip(("x", "y", "z", "qx", "qy", "qz", "qw"), (*t, *q), strict=True):
        out += [f"--{key}", _num(value)]
    return out + ["--frame-id", parent, "--child-frame-id", child]


def viso_pos(mount: Mount, autopilot_V_m: Sequence[float] = (0.0, 0.0, 0.0)
             ) -> tuple[float, float, float]:
    """ArduPilot ``VISO_POS_X/Y/Z``: the optical centre relative to the autopilot, FRD, m."""
    return sensor_offset_frd(mount, autopilot_V_m)


@dataclass(frozen=True)
class Exports:
    """The files written beside a rig.yaml."""

    urdf: Path
    static_tf: Path
    ardupilot: Path

    def paths(self) -> tuple[Path, ...]:
        return (self.urdf, self.static_tf, self.ardupilot)


def export_paths(rig_path: str | Path) -> Exports:
    """``rig.yaml`` -> ``rig.urdf.xml``, ``rig.static_tf.sh``, ``rig.viso.param``."""
    p = Path(rig_path)
    stem = p.with_suffix("")
    return Exports(Path(f"{stem}.urdf.xml"), Path(f"{stem}.static_tf.sh"),
                   Path(f"{stem}.viso.param"))


def write_exports(mount: Mount, rig_path: str | Path, header: str) -> Exports:
    """Write the three forms of ``mount`` beside ``rig_path``, each opened by ``header``
    (the rig.yaml's ``#`` provenance lines; as an XML comment in the URDF snippet).
    The ArduPilot file holds VISO_POS_X/Y/Z with the autopilot at V's origin (give
    ``ceilcal autopilot --autopilot-at`` for the full parameter set elsewhere)."""
    paths = export_paths(rig_path)
    lines = [line[2:] if line.startswith("# ") else line.lstrip("#")
             for line in header.splitlines()]
    xml_lines = [line.replace("--", "- -") for line in lines]
    atomic_write_text(paths.urdf, "<!--\n" + "\n".join(f"  {x}" for x in xml_lines)
                      + f"\n  frames: {PARENT_FRAME} = V (SPEC §1), {CHILD_FRAME} = C "
                        "(OpenCV / REP-103 optical)\n-->\n" + urdf_joint(mount))
    args = " ".join(static_transform_args(mount))
    atomic_write_text(paths.static_tf, "#!/bin/sh\n" + header
                      + f"# {PARENT_FRAME} = V (SPEC §1), {CHILD_FRAME} = C (optical)\n"
                      + f"ros2 run tf2_ros static_transform_publisher {args}\n")
    x, y, z = viso_pos(mount)
    atomic_write_text(paths.ardupilot, header
                      + "# VISO_POS_X/Y/Z alone, to update an autopilot already set up; for "
                        "a first setup load instead the whole set that ceilcal autopilot "
                        f"--rig {Path(rig_path).name} --firmware ardupilot-4.6 writes "
                        f"({Path(rig_path).with_suffix('').name}"
                        ".ardupilot-4.6.param; it holds these three too)\n"
                      + "# camera optical centre in the body frame FRD, m (autopilot at "
                        "V's origin: subtract its position otherwise)\n"
                      + "# for --protocol mavlink-odometry (ODOMETRY carries the camera's "
                        "position); with --protocol mavlink (VISION_POSITION_ESTIMATE, "
                        "the vehicle's reference point) VISO_POS is 0, 0, 0 instead\n"
                      + f"VISO_POS_X,{_num(x)}\nVISO_POS_Y,{_num(y)}\nVISO_POS_Z,{_num(z)}\n")
    return paths


__all__ = ["CHILD_FRAME", "Exports", "PARENT_FRAME", "export_paths", "mount_quaternion",
           "mount_rpy", "static_transform_args", "urdf_joint",
           "viso_pos", "write_exports"]
