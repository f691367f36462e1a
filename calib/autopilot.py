"""Autopilot parameters for ceilkit's external navigation, generated from the calibrated rig.

What ``ceilcal autopilot`` writes: the settings ArduPilot (EKF3, ``VISO_*``) or PX4
(EKF2, ``EKF2_EV_*``) needs to fuse the ``mavlink-odometry`` stream (docs/integration.md).

The sensor offset is the camera's optical centre (the rig's mount, SPEC §1, in V: x
forward, y left, z up from the vehicle's reference point on the floor) relative to the
autopilot (its IMU, ``autopilot_V_m`` in V), in the autopilots' body frame FRD (x
forward, y right, z down)::

    (X, Y, Z)_FRD = (mx - ax, -(my - ay), -(mz - az))

ODOMETRY carries that point's position (``mavlink.OdometrySettings.sensor_V_m``), which
is what ``VISO_POS_*`` / ``EKF2_EV_POS_*`` describe.

Example::

    >>> from ceilkit.runtime.config.rig import Mount
    >>> sensor_offset_frd(Mount(x_m=0.3, y_m=0.1, z_m=0.8), (0.0, 0.0, 0.2))
    (0.3, -0.1, -0.6)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ceilkit.runtime.config.rig import Mount
from ceilkit.runtime.config.yaml import atomic_write_text
from ceilkit.runtime.errors import ConfigError

TARGETS = ("ardupilot", "px4")
DEFAULT_DELAY_MS = 50.0
POS_NOISE_FLOOR_M = 0.05     # VISO_POS_M_NSE / EKF2_EVP_NOISE: the message's sigma is floored
YAW_NOISE_FLOOR_RAD = 0.05   # VISO_YAW_M_NSE / EKF2_EVA_NOISE
MAV_PARAM_TYPE_INT32 = 6     # the type column of a QGroundControl .params file
MAV_PARAM_TYPE_REAL32 = 9
OFFSET_DECIMALS = 4          # 0.1 mm


@dataclass(frozen=True)
class Param:
    """One autopilot parameter: its name, value (an int is an integer parameter) and why."""

    name: str
    value: int | float
    why: str


def sensor_offset_frd(mount: Mount, autopilot_V_m: Sequence[float] = (0.0, 0.0, 0.0)
                      ) -> tuple[float, float, float]:
    """The camera's optical centre relative to the autopilot, body FRD, metres."""
    ax, ay, az = (float(v) for v in autopilot_V_m)
    return tuple(round(v, OFFSET_DECIMALS) + 0.0 for v in (
        mount.x_m - ax, -(mount.y_m - ay), -(mount.z_m - az)))  # type: ignore[return-value]


def ardupilot_params(mount: Mount, *, autopilot_V_m: Sequence[float] = (0.0, 0.0, 0.0),
                     corridor: bool = False, delay_ms: float = DEFAULT_DELAY_MS) -> list[Param]:
    """ArduPilot 4.x (Rover, Copter) external navigation from ODOMETRY, EKF3.

    ``corridor``: the site gives no x (the corridor method): the position must not be
    fused (ArduPilot folds x, y, z into one error, so a huge x variance would also drown
    y): ``EK3_SRC1_POSXY`` = 0 and the heading is all ArduPilot takes.
    """
    x, y, z = sensor_offset_frd(mount, autopilot_V_m)
    return [
        Param("VISO_TYPE", 1, "MAVLink: accept ODOMETRY / VISION_POSITION_ESTIMATE (reboot)"),
        Param("VISO_POS_X", x, "camera optical centre forward of the autopilot, m"),
        Param("VISO_POS_Y", y, "camera optical centre right of the autopilot, m"),
        Param("VISO_POS_Z", z, "camera optical centre below the autopilot, m"),
        Param("VISO_ORIENT", 0, "forward: ODOMETRY is already in the vehicle's body frame"),
        Param("VISO_DELAY_MS", round(float(delay_ms)), "capture-to-arrival latency, ms "
              "(poses.csv latency_ms)"),
        Param("VISO_POS_M_NSE", POS_NOISE_FLOOR_M, "position noise floor, m"),
        Param("VISO_YAW_M_NSE", YAW_NOISE_FLOOR_RAD, "yaw noise floor, rad"),
        Param("AHRS_EKF_TYPE", 3, "EKF3"),
        Param("EK3_SRC1_POSXY", 0 if corridor else 6,
              "None: the corridor gives no x" if corridor else "ExternalNav"),
        Param("EK3_SRC1_VELXY", 0, "None: ODOMETRY's velocity is NaN (unknown)"),
        Param("EK3_SRC1_POSZ", 1, "Baro: z is not measured"),
        Param("EK3_SRC1_VELZ", 0, "None"),
        Param("EK3_SRC1_YAW", 6, "ExternalNav: W's +x is the EKF's north"),
        Param("COMPASS_USE", 0, "the compass disagrees with the site frame indoors"),
        Param("COMPASS_USE2", 0, "second compass"),
        Param("COMPASS_USE3", 0, "third compass"),
        Param("GPS_TYPE", 0, "no GPS indoors (GPS1_TYPE on 4.6 and later)"),
    ]


def px4_params(mount: Mount, *, autopilot_V_m: Sequence[float] = (0.0, 0.0, 0.0),
               corridor: bool = False, delay_ms: float = DEFAULT_DELAY_MS) -> list[Param]:
    """PX4 (v1.14+) external vision from ODOMETRY, EKF2.

    ``corridor`` changes nothing here: PX4 weighs each axis by its own variance, so the
    huge x variance ODOMETRY carries leaves y and the yaw usable.
    """
    x, y, z = sensor_offset_frd(mount, autopilot_V_m)
    ctrl_why = "horizontal position (bit 0) + yaw (bit 3)"
    if corridor:
        ctrl_why += "; x arrives with a (1 km)^2 variance"
    return [
        Param("EKF2_EV_CTRL", 1 + 8, ctrl_why),
        Param("EKF2_HGT_REF", 0, "Baro: z is not measured"),
        Param("EKF2_EV_DELAY", float(delay_ms), "capture-to-arrival latency, ms"),
        Param("EKF2_EV_POS_X", x, "camera optical centre forward of the IMU, m"),
        Param("EKF2_EV_POS_Y", y, "camera optical centre right of the IMU, m"),
        Param("EKF2_EV_POS_Z", z, "camera optical centre below the IMU, m"),
        Param("EKF2_EV_NOISE_MD", 0, "use the message's covariance"),
        Param("EKF2_EVP_NOISE", POS_NOISE_FLOOR_M, "position noise floor, m"),
        Param("EKF2_EVA_NOISE", YAW_NOISE_FLOOR_RAD, "angle noise floor, rad"),
        Param("EKF2_MAG_TYPE", 5, "None: yaw from vision, not the compass"),
        Param("EKF2_GPS_CTRL", 0, "no GPS"),
    ]


def autopilot_params(mount: Mount, target: str, **kw) -> list[Param]:
    """The parameters for ``target`` (``ardupilot`` or ``px4``); see the two above."""
    if target == "ardupilot":
        return ardupilot_params(mount, **kw)
    if target == "px4":
        return px4_params(mount, **kw)
    raise ConfigError(None, "--for", f"expected one of {', '.join(TARGETS)}, found {target!r}")


def _value_text(value: int | float) -> str:
    if isinstance(value, int):
        return str(value)
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


ORIGIN_STEP = {
    "ardupilot": ["EKF origin: ArduPilot fuses external navigation only once its EKF has "
                  "an origin.",
                  "ceilrun --protocol mavlink-odometry sends SET_GPS_GLOBAL_ORIGIN (the "
                  "site's origin, or --ekf-origin)",
                  "until the autopilot reports GPS_GLOBAL_ORIGIN; or use 'Set EKF Origin "
                  "Here' in Mission Planner."],
    "px4": ["EKF origin: PX4 runs on the local frame without one; for a global position "
            "ceilrun sends",
            "SET_GPS_GLOBAL_ORIGIN (the site's origin, or --ekf-origin) until PX4 reports "
            "GPS_GLOBAL_ORIGIN."],
}


def format_params(params: Sequence[Param], target: str, header: str = "") -> str:
    """The parameter file's text.

    ``ardupilot``: ``NAME,VALUE`` lines, each after a ``#`` comment line (the format
    Mission Planner saves and MAVProxy's ``param load`` reads). ``px4``: QGroundControl's
    ``.params`` (tab-separated ``vehicle component NAME VALUE TYPE``, type 6 = int32,
    9 = float), which QGroundControl loads ("Parameters > Tools > Load from file").
    ``header`` is comment lines (``# ...``) put first.
    """
    lines = [ln for ln in header.splitlines() if ln]
    lines += [f"# {ln}" for ln in ORIGIN_STEP[target]]
    if target == "px4":
        lines += ["#", "# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    for p in params:
        lines.append(f"# {p.name}: {p.why}")
        if target == "px4":
            kind = MAV_PARAM_TYPE_INT32 if isinstance(p.value, int) else MAV_PARAM_TYPE_REAL32
            lines.append(f"1\t1\t{p.name}\t{_value_text(p.value)}\t{kind}")
        else:
            lines.append(f"{p.name},{_value_text(p.value)}")
    return "\n".join(lines) + "\n"


def write_params(path: str | Path, params: Sequence[Param], target: str,
                 header: str = "") -> None:
    """Write the parameter file atomically."""
    atomic_write_text(path, format_params(params, target, header))


def parse_autopilot_at(text: str | None) -> tuple[float, float, float]:
    """``X,Y,Z`` (metres, in V) of the autopilot; ``None`` is V's origin."""
    if text is None:
        return (0.0, 0.0, 0.0)
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= 100.0 for v in values):
        raise ConfigError(None, "--autopilot-at", f"expected X,Y,Z in metres (|v| <= 100) "
                          f"in V, found {text!r}")
    return values  # type: ignore[return-value]
