"""``ceilrun``: run on the vehicle (camera in, poses out over serial), or replay a recording.

Exit codes: 0 when the run ended (the source ended, ``--frames`` reached, or SIGINT /
SIGTERM asked it to stop: files are closed and complete; during the warm-up of the
compiled loops it stops at once, before anything is written); 1 for a ceilkit error
(one line on stderr); 2 for bad options; 130 for a command other than the live run
(``replay``, ``warm-up``, ...) interrupted by Ctrl-C. A second SIGINT/SIGTERM while
stopping kills the process at once.

The library is imported when a command runs, not when the program is built:
``ceilrun --version`` and ``-h`` load neither numba nor OpenCV.
"""

from __future__ import annotations

import logging
import sys
import textwrap
import time
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from ceilkit.runtime.errors import ConfigError, LinkError

from .common import (
    CAPTURE_OPTION,
    EXPOSURE_OPTION,
    FOURCC_OPTION,
    FPS_OPTION,
    GAIN_OPTION,
    HEIGHT_OPTION,
    HELP_FLAGS,
    TERM_LINE,
    VERSION_OPTION,
    WIDTH_OPTION,
    capture_settings,
    echo_err,
    make_app,
    parse_options,
    quiet_opencv,
    warm_up_progress,
)

if TYPE_CHECKING:
    from ceilkit.runtime.session import LinkConfig

AUTO = "auto"
METHOD_NAMES = ("corridor", "paper-corridor", "lights", "paper-lights", "block",
                "paper-block", "texture")
"""``auto`` and the estimators' names of :mod:`ceilkit.runtime.estimators.registry`
(``AUTO``, ``METHOD_NAMES``), for the help: the registry imports every estimator
(numba, OpenCV: 250 MB, seconds), which ``ceilrun -h`` need not (a test checks that
they agree)."""
METHOD_HELP = (f"Estimator: auto (every method the site supports, fused; on a site with one "
               f"method and no odometry or start pose, that method), or one of "
               f"{', '.join(METHOD_NAMES)}.")
START_HELP = ("Where the vehicle starts: x, y in m, yaw in degrees (any method), and "
              "optionally how far it may be off, 1 sigma in m and degrees (default "
              "0.1,5): the first prior, which chooses among the poses a frame supports "
              "alike (a symmetric corridor's half turn, a light grid's cells) only "
              "within 4 sigma.")


def _start_pose(text: str | None) -> tuple[float, ...] | None:
    from ceilkit.runtime.multi import parse_start_pose

    return None if text is None else parse_start_pose(text)


def _limits(text: str | None) -> tuple[float, float] | None:
    from ceilkit.runtime.multi import parse_limits

    return None if text is None else parse_limits(text)


LIMITS_HELP = ("The vehicle's maximum speed, m/s, and optionally turn rate, degrees/s "
               "(default 2.5,90): no track may move faster between frames, so a twin "
               "farther than that (the next tile, cell or line) is out of reach.")

app = make_app("ceilrun", "Run the localizer on the vehicle, or replay a recording.\n\n"
               "Live: ceilrun --device /dev/video0 --serial /dev/ttyUSB0 --rig rig.yaml "
               "--site site.yaml")

OPTION_HELP = ("An estimator option KEY=VALUE (a field of the method's options, see "
               "docs/methods); repeatable.")


class Protocol(str, Enum):
    nmea = "nmea"
    mavlink = "mavlink"
    mavlink_odometry = "mavlink-odometry"
    nmea_gps = "nmea-gps"


PROTOCOL_HELP = ("Pose stream protocol: " + ", ".join(p.value for p in Protocol)
                 + " (docs/serial.md).")


class MissingX(str, Enum):
    skip = "skip"
    nan = "nan"


class _LineHandler(logging.StreamHandler):
    """Log lines start on a line of their own (after a status or progress line)."""

    def emit(self, record: logging.LogRecord) -> None:
        TERM_LINE.end()
        self.stream = sys.stderr  # the stderr of now (a test runner swaps it)
        super().emit(record)


def _setup_logging() -> None:
    """Warnings of the runtime (camera lost/back, link lost/back) as lines on stderr."""
    root = logging.getLogger("ceilkit")
    if not any(getattr(h, "_ceilrun", False) for h in root.handlers):
        handler = _LineHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("ceilrun: %(message)s"))
        handler._ceilrun = True  # type: ignore[attr-defined]
        root.addHandler(handler)
        root.setLevel(logging.WARNING)
        root.propagate = False


def _parse_origin(text: str | None):
    if text is None:
        return None
    from ceilkit.runtime.io.link.mavlink import GeoOrigin

    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(None, "--ekf-origin", f"expected LAT,LON,ALT_M in degrees and "
                          f"metres, found {text!r}") from None
    try:
        return GeoOrigin(lat, lon, alt)
    except LinkError as exc:
        raise ConfigError(None, "--ekf-origin", str(exc)) from None


def _link(serial: str | None, protocol: Protocol, baud: int, sysid: int = 1,
          compid: int = 197, missing_x: MissingX = MissingX.skip,
          origin=None) -> LinkConfig | None:
    if serial is None:
        return None
    from ceilkit.runtime.session import LinkConfig

    return LinkConfig(serial, protocol.value, baud, sysid, compid, missing_x.value, origin)


def _err(msg: str) -> None:
    echo_err(msg)


STATUS_EVERY_S = 1.0
"""With ``--serial -`` (poses on stdout), ``--status`` prints a whole line this often."""


def _status_line(status: bool, own_lines: bool):
    """``--status``: each frame's status line rewritten in place on stderr; with the
    poses on stdout (``own_lines``: one terminal for both), a whole line on stderr every
    :data:`STATUS_EVERY_S` instead, so that a status never cuts into a pose sentence."""
    if not status:
        return None
    if not own_lines:
        return lambda tel: TERM_LINE.show(tel.live_line())
    last = [-STATUS_EVERY_S]

    def line(tel) -> None:
        now = time.monotonic()
        if now - last[0] >= STATUS_EVERY_S:
            last[0] = now
            echo_err(f"ceilrun: {tel.live_line()}")

    return line


ROS2_HELP = ("Also run as a ROS 2 node: PoseWithCovarianceStamped on /ceilkit/pose (frame "
             "map), Odometry on /ceilkit/odom, /tf, /tf_static, camera_info, an overlay "
             "image, /diagnostics; /initialpose and --ros2-odometry in (needs the ros2 "
             "extra). Arguments after --ros-args go to ROS (--params-file, -p, -r).")
ROS2_PARAM_HELP = ("A ROS 2 node parameter NAME=VALUE (frame_id, child_frame_id, "
                   "odom_frame_id, camera_frame_id, tf, the *_topic names, image_rate_hz, "
                   "...; docs/integration.md); repeatable.")
ROS_ARGS: list[str] = []
"""What followed ``--ros-args`` on the command line (taken off before typer parses)."""


def _take_ros_args(args: list[str]) -> list[str]:
    """``args`` without ``--ros-args ...`` (kept in :data:`ROS_ARGS` for the node), as a
    launch file's ``Node(executable='ceilkit-ros2', parameters=[...])`` passes them."""
    if "--ros-args" not in args:
        return args
    k = args.index("--ros-args")
    ROS_ARGS[:] = args[k:]
    return args[:k]


def _ros2(enabled: bool, namespace: str, odometry: str, params: list[str] | None = None,
          wait_s: float = 0.0):
    if not enabled:
        return None
    from ceilkit.runtime.io.ros2 import Ros2Config, ros2_config

    values: dict[str, str] = {}
    for item in params or []:
        name, eq, value = item.partition("=")
        if not eq or not name.strip():
            raise ConfigError(None, "--ros2-param", f"expected NAME=VALUE, found {item!r}")
        values[name.strip()] = value.strip()
    return ros2_config(Ros2Config(
        namespace=namespace or "", wait_subscribers_s=wait_s, ros_args=tuple(ROS_ARGS),
        odometry_topic=None if odometry in ("", "none") else odometry), values)


@app.callback(invoke_without_command=True)
def live(
    ctx: typer.Context,
    device: str = typer.Option("/dev/video0", help="Camera (/dev/videoN or index), video "
                               "file, image folder, recording, or sim[:corridor|lights|block]."),
    serial: str = typer.Option(None, help="Serial port for the pose stream "
                               "(e.g. /dev/ttyUSB0), - for stdout, or a file to write the "
                               "same bytes to."),
    baud: int = typer.Option(115200, help="Serial baud rate."),
    protocol: Protocol = typer.Option(Protocol.nmea, metavar="NAME", help=PROTOCOL_HELP),
    sysid: int = typer.Option(1, help="MAVLink system id."),
    compid: int = typer.Option(197, help="MAVLink component id."),
    mavlink_missing_x: MissingX = typer.Option(
        MissingX.skip, help="MAVLink, a pose without x (corridor method): skip sends "
        "nothing (safe for ArduPilot); nan sends x = NaN (PX4 fuses y and yaw)."),
    ekf_origin: str = typer.Option(None, metavar="LAT,LON,ALT", help="MAVLink: send "
                                   "SET_GPS_GLOBAL_ORIGIN until the autopilot reports its "
                                   "origin (ArduPilot needs one). Off by default."),
    rig: Path = typer.Option(None, help="rig.yaml (default for sim: the example's)."),
    site: Path = typer.Option(None, help="site.yaml (default for sim: the example's)."),
    method: str = typer.Option(AUTO, help=METHOD_HELP),
    start_pose: str = typer.Option(None, "--start-pose", metavar="X,Y,YAW[,SM,SDEG]",
                                  help=START_HELP),
    max_speed: str = typer.Option(None, "--max-speed", metavar="MPS[,DEGPS]",
                                  help=LIMITS_HELP),
    link_odometry: bool = typer.Option(False, "--link-odometry", help="Read wheel odometry "
                                       "back from --serial ($PCEIO, MAVLink ODOMETRY or "
                                       "WHEEL_DISTANCE) into the fusion (--method auto)."),
    wheel_track: float = typer.Option(None, "--wheel-track", metavar="M", help="Wheel "
                                      "track of a differential drive, m (WHEEL_DISTANCE)."),
    option: list[str] = typer.Option(None, "--option", metavar="KEY=VALUE",
                                     help=OPTION_HELP),
    record: Path = typer.Option(None, help="Write a SPEC recording of the run here (a "
                                "folder), or an MCAP recording (a name ending in .mcap)."),
    out: Path = typer.Option(None, help="Write poses.csv into this folder."),
    frames: int = typer.Option(0, help="Stop after this many frames (0: run until stopped; "
                               "sim: 300)."),
    width: int = WIDTH_OPTION,
    height: int = HEIGHT_OPTION,
    fps: float = FPS_OPTION,
    fourcc: str = FOURCC_OPTION,
    exposure: float = EXPOSURE_OPTION,
    gain: float = GAIN_OPTION,
    capture: Path = CAPTURE_OPTION,
    status: bool = typer.Option(False, "--status", help="Print a live status line on "
                                "stderr (with --serial -: a line a second, whole lines "
                                "between the poses)."),
    realtime: bool = typer.Option(True, "--realtime/--no-realtime", help="sim: the "
                                  "frames at their stamps' pace, as a camera's; "
                                  "--no-realtime: as fast as they render."),
    force: bool = typer.Option(False, "--force", help="Replace an existing poses.csv or "
                               "recording (refused otherwise)."),
    wait: bool = typer.Option(False, "--wait", help="Wait for a camera or serial port "
                              "that is not there yet, with back-off (for services)."),
    fsync_every: float = typer.Option(1.0, "--fsync-every", metavar="S", help="fsync the "
                                      "recording every S seconds: a power cut loses at "
                                      "most that (0: off)."),
    view: str = typer.Option(None, "--view", metavar="[HOST:]PORT", help="Serve the live web "
                             "view here (host 127.0.0.1 unless given), read-only."),
    view_token: str = typer.Option(None, "--view-token", help="Require this token of "
                                   "every view request (?token=...); 403 without."),
    ros2: bool = typer.Option(False, "--ros2", help=ROS2_HELP),
    ros2_namespace: str = typer.Option("", "--ros2-namespace", metavar="NS",
                                       help="ROS 2 namespace of the node."),
    ros2_odometry: str = typer.Option("/odom", "--ros2-odometry", metavar="TOPIC",
                                      help="ROS 2 wheel odometry in (nav_msgs/Odometry) "
                                      "for the fusion; none: off."),
    ros2_param: list[str] = typer.Option(None, "--ros2-param", metavar="NAME=VALUE",
                                         help=ROS2_PARAM_HELP),
    version: bool = VERSION_OPTION,
) -> None:
    """Run live: frames from --device, poses to --serial."""
    if ctx.invoked_subcommand is not None:
        return
    from ceilkit.runtime.session import SessionConfig, run_session, stop_on_signals

    _setup_logging()
    config = SessionConfig(
        device, rig, site, method, parse_options(option),
        _link(serial, protocol, baud, sysid, compid, mavlink_missing_x,
              _parse_origin(ekf_origin)),
        record, out, frames, capture_settings(capture, width, height, fps, fourcc, exposure,
                                          gain),
        view=view, view_token=view_token, force=force, wait=wait, fsync_every_s=fsync_every,
        start_pose=_start_pose(start_pose), link_odometry=link_odometry,
        wheel_track_m=wheel_track, limits=_limits(max_speed),
        ros2=_ros2(ros2, ros2_namespace, ros2_odometry, ros2_param), realtime=realtime)
    with stop_on_signals() as stop:
        result = run_session(config, stop, _status_line(status, serial == "-"))
    _err("ceilrun: " + "\n".join(result.lines()))


@app.command()
def replay(
    recording: Path = typer.Argument(..., help="A SPEC recording folder, or an MCAP "
                                     "recording (.mcap)."),
    out: Path = typer.Option(None, help="Output folder (default RECORDING/replay)."),
    rig: Path = typer.Option(None, help="Use this rig.yaml instead of the recording's."),
    site: Path = typer.Option(None, help="Use this site.yaml instead of the recording's."),
    method: str = typer.Option(AUTO, help=METHOD_HELP),
    start_pose: str = typer.Option(None, "--start-pose", metavar="X,Y,YAW[,SM,SDEG]",
                                  help=START_HELP),
    max_speed: str = typer.Option(None, "--max-speed", metavar="MPS[,DEGPS]",
                                  help=LIMITS_HELP),
    odometry: Path = typer.Option(None, "--odometry", metavar="FILE", help="Wheel odometry "
                                  "(odometry.csv layout) instead of the recording's own; "
                                  "fed to the fusion (--method auto)."),
    option: list[str] = typer.Option(None, "--option", metavar="KEY=VALUE",
                                     help=OPTION_HELP),
    no_track: bool = typer.Option(False, "--no-track", help="Write the estimator's own "
                                  "output for every frame: no tracking, gating or fusion, "
                                  "no prior (SPEC §3)."),
    tum: bool = typer.Option(False, "--tum", help="Also write poses.tum (for evo)."),
    realtime: bool = typer.Option(False, "--realtime", help="Replay at recorded timing."),
    serial: str = typer.Option(None, help="Also stream the poses to this port (or -)."),
    protocol: Protocol = typer.Option(Protocol.nmea, metavar="NAME", help=PROTOCOL_HELP),
    baud: int = typer.Option(115200, help="Serial baud rate."),
    mavlink_missing_x: MissingX = typer.Option(
        MissingX.skip, help="MAVLink, a pose without x: skip (default) or nan."),
    progress: bool = typer.Option(None, "--progress/--no-progress",
                                  help="Progress bar (default: on a terminal)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing poses.csv "
                               "(refused otherwise)."),
    overlays: Path = typer.Option(None, "--overlays", metavar="DIR", help="Write each "
                                  "frame's overlay here as NNNNNN.png."),
    overlays_only_failures: bool = typer.Option(
        False, "--overlays-only-failures", help="Overlays only of failures and frames of "
        "quality below 0.5."),
    report: bool = typer.Option(False, "--report", help="Also write OUT/report.html: "
                                "plots and the worst frames' overlays, self-contained."),
    ros2: bool = typer.Option(False, "--ros2", help=ROS2_HELP + " Stamps are the "
                              "recording's."),
    ros2_namespace: str = typer.Option("", "--ros2-namespace", metavar="NS",
                                       help="ROS 2 namespace of the node."),
    ros2_odometry: str = typer.Option("/odom", "--ros2-odometry", metavar="TOPIC",
                                      help="ROS 2 wheel odometry in; none: off."),
    ros2_param: list[str] = typer.Option(None, "--ros2-param", metavar="NAME=VALUE",
                                         help=ROS2_PARAM_HELP),
    ros2_wait: float = typer.Option(10.0, "--ros2-wait", metavar="S", help="Before the "
                                    "first frame, wait up to S s for a subscriber to the "
                                    "poses (DDS discovery: a replay would otherwise publish "
                                    "its first frames to no one); 0: do not wait."),
) -> None:
    """Replay a recording through the pipeline; write poses.csv; print errors vs truth.csv."""
    show = sys.stderr.isatty() if progress is None else progress

    def bar(done: int, total: int) -> None:
        if show and (done == total or done % 10 == 0):
            n = int(30 * done / max(total, 1))
            TERM_LINE.show(f"[{'#' * n}{'.' * (30 - n)}] {done}/{total}")

    from ceilkit.runtime.replay import replay as run_replay

    _setup_logging()
    res = run_replay(recording, out, rig, site, method, tum=tum, realtime=realtime,
                     track=not no_track, progress=bar, options=parse_options(option),
                     link=_link(serial, protocol, baud, missing_x=mavlink_missing_x),
                     overlays=overlays, overlays_only_failures=overlays_only_failures,
                     report=report, start_pose=_start_pose(start_pose), odometry=odometry,
                     limits=_limits(max_speed),
                     ros2=_ros2(ros2, ros2_namespace, ros2_odometry, ros2_param, ros2_wait),
                     force=force)
    TERM_LINE.end()
    # the report goes to stderr when the poses themselves stream to stdout
    echo = _err if serial == "-" else typer.echo
    echo("\n".join(res.lines()))


@app.command()
def repair(
    recording: Path = typer.Argument(..., help="A recording a killed run left."),
) -> None:
    """Write the frames a killed run left in RECORDING/frames.wal as PNGs and rows."""
    from ceilkit.runtime.io.recording import LOG_DIR, Recording, repair_recording

    n = repair_recording(recording)
    typer.echo(f"{recording}: {n} frames written from {LOG_DIR}/; "
               f"{len(Recording(recording))} frames in all")


@app.command()
def convert(
    src: Path = typer.Argument(..., help="A SPEC recording folder, or an .mcap recording."),
    dst: Path = typer.Argument(..., help="The .mcap to write (from a folder), or the "
                               "folder (from an .mcap)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing DST."),
) -> None:
    """Convert a SPEC recording folder to MCAP (ROS 2 messages) or an MCAP back."""
    from ceilkit.runtime.io.mcap_rec import convert_recording

    n = convert_recording(src, dst, force=force)
    typer.echo(f"{src} -> {dst}: {n} frames")


@app.command("warm-up")
def warm_up_cmd() -> None:
    """Compile every method's per-frame loops now, once for this machine (numba's cache
    keeps them): for an installer or a Dockerfile, so that no later start compiles."""
    from ceilkit.runtime.multi import warm_up_all

    done = warm_up_all()   # its progress: main()'s warm_up_progress
    typer.echo(f"{done.done} compiled loops ready ({done.compiled} compiled now, the "
               f"rest from numba's cache) in {done.elapsed_s:.1f} s")


def _run(args: list[str], prog: str) -> None:
    """``app`` on ``args``: with the warm-up's progress line and OpenCV's warnings off,
    unless only a help or the version is asked for (neither loads the library)."""
    if set(HELP_FLAGS) & set(args) or "--version" in args:
        app(args=args, prog_name=prog)
        return
    quiet_opencv()
    with warm_up_progress(prog):
        app(args=args, prog_name=prog)


def main() -> None:
    """The ``ceilrun`` entry point."""
    _run(_take_ros_args(sys.argv[1:]), "ceilrun")


ROS2_INTRO = ("ceilrun as a ROS 2 node: `ceilkit-ros2 [OPTIONS]` runs `ceilrun --ros2 "
              "[OPTIONS]` (live), `ceilkit-ros2 replay RECORDING [OPTIONS]` runs `ceilrun "
              "replay RECORDING --ros2 [OPTIONS]`; every other option is ceilrun's "
              "(`ceilrun --help`, `ceilrun replay --help`). The node: ")


def ros2_help() -> str:
    """``ceilkit-ros2 --help``: what it is, and its ROS 2 options (live and replay)."""
    group = typer.main.get_command(app)
    rows: dict[str, tuple[str, str]] = {}
    for where, cmd in (("", group), (" (replay)", group.commands["replay"])):
        for p in cmd.params:
            opts = [o for o in p.opts if o.startswith("--ros2-") or o == "--ros-args"]
            if opts and opts[0] not in rows:
                meta = "" if getattr(p, "is_flag", False) else f" {p.metavar or 'VALUE'}"
                rows[opts[0]] = (f"{opts[0]}{meta}", f"{p.help or ''}{where}")
    rows["-h"] = ("-h, --help", "Show this message and exit.")
    rows["--version"] = ("--version", "Print the version and exit.")
    width = max(len(name) for name, _ in rows.values()) + 4
    intro = ROS2_INTRO + ROS2_HELP.removeprefix("Also run as a ROS 2 node: ")
    out = ["Usage: ceilkit-ros2 [OPTIONS]", "       ceilkit-ros2 replay RECORDING [OPTIONS]",
           "", *textwrap.wrap(intro, 88), "", "ROS 2 options:"]
    for name, text in rows.values():
        lines = textwrap.wrap(text, 88 - width) or [""]
        out.append(f"  {name.ljust(width - 2)}{lines[0]}")
        out += [" " * width + line for line in lines[1:]]
    return "\n".join(out) + "\n"


def ros2_main() -> None:
    """``ceilkit-ros2``: ``ceilrun --ros2`` (``ceilkit-ros2 replay REC``: ``ceilrun replay
    REC --ros2``), every other option as ceilrun's; ``-h``: its own help
    (:func:`ros2_help`)."""
    args = _take_ros_args(sys.argv[1:])
    if set(HELP_FLAGS) & set(args):
        typer.echo(ros2_help(), nl=False)
        return
    args = ["replay", "--ros2", *args[1:]] if args[:1] == ["replay"] else ["--ros2", *args]
    _run(args, "ceilkit-ros2")


if __name__ == "__main__":
    main()
