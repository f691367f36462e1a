"""Autopilot parameters for ceilkit's external navigation, generated from the calibrated rig.

What ``ceilcal autopilot`` writes: the settings ArduPilot (EKF3, ``VISO_*``) or PX4
(EKF2, ``EKF2_EV_*``) needs to fuse the ``mavlink-odometry`` stream (docs/integration.md).

Parameter names follow the firmware (:data:`ARDUPILOT_FIRMWARES`): ArduPilot 4.6 moved
the GPS parameters into per-instance groups, so the first GPS's type is ``GPS_TYPE`` up
to 4.5 and ``GPS1_TYPE`` from 4.6 (ArduPilot's ``libraries/AP_GPS/AP_GPS_Params.cpp``;
PR 27933 notes "renamed in 4.6" on the old names); a file for the wrong release sets a
parameter that does not exist and leaves the GPS on. The other names written here
(``VISO_*``, ``AHRS_EKF_TYPE``, ``EK3_SRC1_*``, ``COMPASS_USE*``) are the same in 4.5,
4.6 and 4.7 (``libraries/AP_VisualOdom/AP_VisualOdom.cpp``; the wiki's "Parameter Name
Changes" page lists no rename of them for 4.7).

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
ARDUPILOT_FIRMWARES = {"ardupilot-4.5": "GPS_TYPE", "ardupilot-4.6": "GPS1_TYPE",
                       "ardupilot-4.7": "GPS1_TYPE"}
"""``--firmware`` -> the name of the first GPS's type parameter in that release."""
DEFAULT_DELAY_MS = 50.0
DELAY_RANGE_MS = (0.0, 250.0)
"""``VISO_DELAY_MS``'s range (ArduPilot); PX4's ``EKF2_EV_DELAY`` takes 0-300 ms."""
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
                     corridor: bool = False, delay_ms: float = DEFAULT_DELAY_MS,
                     firmware: str = "ardupilot-4.6") -> list[Param]:
    """ArduPilot (Rover, Copter) external navigation from ODOMETRY, EKF3, with the
    parameter names of ``firmware`` (:data:`ARDUPILOT_FIRMWARES`).

    ``corridor``: the site gives no x (the corridor method): the position must not be
    fused (ArduPilot folds x, y, z into one error, so a huge x variance would also drown
    y): ``EK3_SRC1_POSXY`` = 0 and the heading is all ArduPilot takes.
    """
    gps_type = ARDUPILOT_FIRMWARES[check_firmware(firmware)]
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
        Param(gps_type, 0, f"no GPS indoors (the first GPS's type in {firmware})"),
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


def check_firmware(firmware: str) -> str:
    """``firmware`` if it is one of :data:`ARDUPILOT_FIRMWARES` (else ``--firmware``)."""
    if firmware not in ARDUPILOT_FIRMWARES:
        raise ConfigError(None, "--firmware", f"expected one of "
                          f"{', '.join(ARDUPILOT_FIRMWARES)}, found {firmware!r}")
    return firmware


def resolve_target(target: str | None, firmware: str | None) -> tuple[str, str | None]:
    """``(target, firmware)`` from ``--for`` and ``--firmware``: a firmware implies its
    autopilot; ArduPilot needs one (its parameter names changed in 4.6), PX4 takes none.

    Raises:
        ConfigError: keyed ``--for`` or ``--firmware``, naming what to give.
    """
    if target is not None and target not in TARGETS:
        raise ConfigError(None, "--for", f"expected one of {', '.join(TARGETS)}, "
                          f"found {target!r}")
    if firmware is not None:
        check_firmware(firmware)
        if target == "px4":
            raise ConfigError(None, "--firmware", f"{firmware} is ArduPilot firmware; "
                              f"--for px4 takes no --firmware")
        return "ardupilot", firmware
    if target == "ardupilot":
        raise ConfigError(None, "--firmware", "ArduPilot renamed GPS_TYPE to GPS1_TYPE "
                          "in 4.6: give the release the autopilot runs (Mission Planner's "
                          "title bar, MAVProxy's 'version'): "
                          f"{' or '.join(ARDUPILOT_FIRMWARES)}")
    if target is None:
        raise ConfigError(None, "--for", f"expected one of {', '.join(TARGETS)} (or "
                          f"--firmware {' or '.join(ARDUPILOT_FIRMWARES)})")
    return target, None


def check_delay_ms(delay_ms: float) -> float:
    """The capture-to-arrival latency, ms, if in :data:`DELAY_RANGE_MS` (else
    ``--delay-ms``)."""
    lo, hi = DELAY_RANGE_MS
    if not (math.isfinite(delay_ms) and lo <= delay_ms <= hi):
        raise ConfigError(None, "--delay-ms", f"expected a latency of {lo:g} to {hi:g} ms "
                          f"(poses.csv latency_ms), found {delay_ms!r}")
    return float(delay_ms)


def autopilot_params(mount: Mount, target: str, firmware: str | None = None,
                     **kw) -> list[Param]:
    """The parameters for ``target`` (``ardupilot`` with its ``firmware``, or ``px4``);
    see the two above. ``delay_ms`` is checked (:func:`check_delay_ms`)."""
    target, firmware = resolve_target(target, firmware)
    if "delay_ms" in kw:
        kw["delay_ms"] = check_delay_ms(kw["delay_ms"])
    if target == "ardupilot":
        return ardupilot_params(mount, firmware=firmware or "", **kw)
    return px4_params(mount, **kw)


def default_param_path(rig_path: str | Path, target: str, firmware: str | None) -> Path:
    """Beside the rig, named by what it is for: ``rig.ardupilot-4.6.param`` (Mission
    Planner / MAVProxy) or ``rig.px4.params`` (QGroundControl)."""
    stem = Path(rig_path).with_suffix("")
    return Path(f"{stem}.{firmware}.param") if target == "ardupilot" else \
        Path(f"{stem}.px4.params")


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


def purpose_lines(target: str, firmware: str | None) -> list[str]:
    """The file's first words: what it is for, and that it is the one to load."""
    what = firmware if target == "ardupilot" else "PX4 v1.14 and later"
    out = [f"ceilkit external navigation for {what}: the whole set; load this file"]
    if target == "ardupilot":
        out.append("(rig.viso.param, which ceilcal mount / calibrate write beside the rig, "
                   "holds VISO_POS_X/Y/Z alone for an autopilot at V's origin: not needed "
                   "with this one)")
    return out


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
