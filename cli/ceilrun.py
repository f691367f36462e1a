"""``ceilrun``: run on the vehicle (camera in, poses out over serial), or replay a recording.

Exit codes: 0 when the run ended (the source ended, ``--frames`` reached, or SIGINT /
SIGTERM asked it to stop: files are closed and complete); 1 for a ceilkit error
(one line on stderr); 2 for bad options. A second SIGINT/SIGTERM while stopping
kills the process at once.
"""

from __future__ import annotations

import logging
import sys
from enum import Enum
from pathlib import Path

import typer

from ceilkit.runtime.errors import ConfigError, LinkError
from ceilkit.runtime.estimators.registry import AUTO, METHOD_NAMES
from ceilkit.runtime.io.mcap_rec import convert_recording
from ceilkit.runtime.io.recording import LOG_DIR, Recording, repair_recording
from ceilkit.runtime.multi import parse_start_pose
from ceilkit.runtime.replay import replay as run_replay
from ceilkit.runtime.session import (
    LinkConfig,
    SessionConfig,
    run_session,
    stop_on_signals,
)

from .common import (
    CAPTURE_OPTION,
    EXPOSURE_OPTION,
    FOURCC_OPTION,
    FPS_OPTION,
    GAIN_OPTION,
    HEIGHT_OPTION,
    TERM_LINE,
    WIDTH_OPTION,
    capture_settings,
    echo_err,
    make_app,
    parse_options,
    quiet_opencv,
)

METHOD_HELP = (f"Estimator: auto (every method the site supports, fused; on a site with one "
               f"method and no odometry or start pose, that method), or one of "
               f"{', '.join(METHOD_NAMES)}.")
START_HELP = ("Where the vehicle starts: x, y in m, yaw in degrees (any method): the "
              "first prior, which chooses among the poses a frame supports alike (a "
              "symmetric corridor's half turn, a light grid's cells).")


def _start_pose(text: str | None) -> tuple[float, float, float] | None:
    return None if text is None else parse_start_pose(text)

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
    return LinkConfig(serial, protocol.value, baud, sysid, compid, missing_x.value, origin)


def _err(msg: str) -> None:
    echo_err(msg)


ROS2_HELP = ("Also run as a ROS 2 node: PoseWithCovarianceStamped on /ceilkit/pose (frame "
             "map), Odometry on /ceilkit/odom, /diagnostics; /initialpose and --ros2-odometry "
             "in (needs the ros2 extra).")


def _ros2(enabled: bool, namespace: str, odometry: str):
    if not enabled:
        return None
    from ceilkit.runtime.io.ros2 import Ros2Config

    return Ros2Config(namespace=namespace or "",
                      odometry_topic=None if odometry in ("", "none") else odometry)


@app.callback(invoke_without_command=True)
def live(
    ctx: typer.Context,
    device: str = typer.Option("/dev/video0", help="Camera (/dev/videoN or index), video "
                               "file, image folder, recording, or sim[:corridor|lights|block]."),
    serial: str = typer.Option(None, help="Serial port for the pose stream "
                               "(e.g. /dev/ttyUSB0), - for stdout, or a file to write the "
                               "same bytes to."),
    baud: int = typer.Option(115200, help="Serial baud rate."),
    protocol: Protocol = typer.Option(Protocol.nmea, help="Pose stream protocol."),
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
    start_pose: str = typer.Option(None, "--start-pose", metavar="X,Y,YAW", help=START_HELP),
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
    status: bool = typer.Option(False, "--status", help="Print a live status line."),
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
) -> None:
    """Run live: frames from --device, poses to --serial."""
    if ctx.invoked_subcommand is not None:
        return
    _setup_logging()
    config = SessionConfig(
        device, rig, site, method, parse_options(option),
        _link(serial, protocol, baud, sysid, compid, mavlink_missing_x,
              _parse_origin(ekf_origin)),
        record, out, frames, capture_settings(capture, width, height, fps, fourcc, exposure,
                                          gain),
        view=view, view_token=view_token, force=force, wait=wait, fsync_every_s=fsync_every,
        start_pose=_start_pose(start_pose), link_odometry=link_odometry,
        wheel_track_m=wheel_track, ros2=_ros2(ros2, ros2_namespace, ros2_odometry))

    def show(tel):
        if status:
            TERM_LINE.show(tel.live_line())

    with stop_on_signals() as stop:
        result = run_session(config, stop, show)
    _err("ceilrun: " + "\n".join(result.lines()))


@app.command()
def replay(
    recording: Path = typer.Argument(..., help="A SPEC recording folder, or an MCAP "
                                     "recording (.mcap)."),
    out: Path = typer.Option(None, help="Output folder (default RECORDING/replay)."),
    rig: Path = typer.Option(None, help="Use this rig.yaml instead of the recording's."),
    site: Path = typer.Option(None, help="Use this site.yaml instead of the recording's."),
    method: str = typer.Option(AUTO, help=METHOD_HELP),
    start_pose: str = typer.Option(None, "--start-pose", metavar="X,Y,YAW", help=START_HELP),
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
    protocol: Protocol = typer.Option(Protocol.nmea, help="Pose stream protocol."),
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
) -> None:
    """Replay a recording through the pipeline; write poses.csv; print errors vs truth.csv."""
    show = sys.stderr.isatty() if progress is None else progress

    def bar(done: int, total: int) -> None:
        if show and (done == total or done % 10 == 0):
            n = int(30 * done / max(total, 1))
            TERM_LINE.show(f"[{'#' * n}{'.' * (30 - n)}] {done}/{total}")

    _setup_logging()
    res = run_replay(recording, out, rig, site, method, tum=tum, realtime=realtime,
                     track=not no_track, progress=bar, options=parse_options(option),
                     link=_link(serial, protocol, baud, missing_x=mavlink_missing_x),
                     overlays=overlays, overlays_only_failures=overlays_only_failures,
                     report=report, start_pose=_start_pose(start_pose), odometry=odometry,
                     ros2=_ros2(ros2, ros2_namespace, ros2_odometry), force=force)
    TERM_LINE.end()
    # the report goes to stderr when the poses themselves stream to stdout
    echo = _err if serial == "-" else typer.echo
    echo("\n".join(res.lines()))


@app.command()
def repair(
    recording: Path = typer.Argument(..., help="A recording a killed run left."),
) -> None:
    """Write the frames a killed run left in RECORDING/frames.wal as PNGs and rows."""
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
    n = convert_recording(src, dst, force=force)
    typer.echo(f"{src} -> {dst}: {n} frames")


def main() -> None:
    quiet_opencv()
    app(prog_name="ceilrun")


def ros2_main() -> None:
    """``ceilkit-ros2``: ``ceilrun --ros2`` (``ceilkit-ros2 replay REC``: ``ceilrun replay
    REC --ros2``), every other option as ceilrun's."""
    args = sys.argv[1:]
    args = ["replay", "--ros2", *args[1:]] if args[:1] == ["replay"] else ["--ros2", *args]
    quiet_opencv()
    app(args=args, prog_name="ceilkit-ros2")


if __name__ == "__main__":
    main()
