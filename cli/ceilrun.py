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
from ceilkit.runtime.estimators.registry import METHOD_NAMES
from ceilkit.runtime.replay import replay as run_replay
from ceilkit.runtime.session import (
    CaptureSettings,
    LinkConfig,
    SessionConfig,
    run_session,
    stop_on_signals,
)

from .common import make_app, parse_options, quiet_opencv

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


def _setup_logging() -> None:
    """Warnings of the runtime (camera lost/back, link lost/back) as lines on stderr."""
    root = logging.getLogger("ceilkit")
    if not any(getattr(h, "_ceilrun", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
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
    typer.echo(msg, err=True)


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
    method: str = typer.Option(None, help=f"Estimator: {', '.join(METHOD_NAMES)} "
                                          "(default: what the site holds)."),
    option: list[str] = typer.Option(None, "--option", metavar="KEY=VALUE",
                                     help=OPTION_HELP),
    record: Path = typer.Option(None, help="Write a SPEC recording of the run here."),
    out: Path = typer.Option(None, help="Write poses.csv into this folder."),
    frames: int = typer.Option(0, help="Stop after this many frames (0: run until stopped; "
                               "sim: 300)."),
    width: int = typer.Option(0, help="Capture width (0: driver default)."),
    height: int = typer.Option(0, help="Capture height."),
    fps: float = typer.Option(0.0, help="Capture rate."),
    fourcc: str = typer.Option("", help="Pixel format, e.g. MJPG or YUYV."),
    exposure: float = typer.Option(None, help="Manual exposure (turns auto-exposure off)."),
    gain: float = typer.Option(None, help="Manual gain."),
    status: bool = typer.Option(False, "--status", help="Print a live status line."),
    view: str = typer.Option(None, "--view", metavar="[HOST:]PORT", help="Serve the live web "
                             "view here (host 127.0.0.1 unless given), read-only."),
    view_token: str = typer.Option(None, "--view-token", help="Require this token of "
                                   "every view request (?token=...); 403 without."),
) -> None:
    """Run live: frames from --device, poses to --serial."""
    if ctx.invoked_subcommand is not None:
        return
    _setup_logging()
    config = SessionConfig(
        device, rig, site, method, parse_options(option),
        _link(serial, protocol, baud, sysid, compid, mavlink_missing_x,
              _parse_origin(ekf_origin)),
        record, out, frames, CaptureSettings(width, height, fps, fourcc, exposure, gain),
        view=view, view_token=view_token)

    def show(tel):
        if status:
            sys.stderr.write("\r" + tel.live_line())
            sys.stderr.flush()

    with stop_on_signals() as stop:
        result = run_session(config, stop, show)
    if status:
        _err("")
    _err("ceilrun: " + "\n".join(result.lines()))


@app.command()
def replay(
    recording: Path = typer.Argument(..., help="A SPEC recording folder."),
    out: Path = typer.Option(None, help="Output folder (default RECORDING/replay)."),
    rig: Path = typer.Option(None, help="Use this rig.yaml instead of the recording's."),
    site: Path = typer.Option(None, help="Use this site.yaml instead of the recording's."),
    method: str = typer.Option(None, help=f"Estimator: {', '.join(METHOD_NAMES)}."),
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
    overlays: Path = typer.Option(None, "--overlays", metavar="DIR", help="Write each "
                                  "frame's overlay here as NNNNNN.png."),
    overlays_only_failures: bool = typer.Option(
        False, "--overlays-only-failures", help="Overlays only of failures and frames of "
        "quality below 0.5."),
    report: bool = typer.Option(False, "--report", help="Also write OUT/report.html: "
                                "plots and the worst frames' overlays, self-contained."),
) -> None:
    """Replay a recording through the pipeline; write poses.csv; print errors vs truth.csv."""
    show = sys.stderr.isatty() if progress is None else progress

    def bar(done: int, total: int) -> None:
        if show and (done == total or done % 10 == 0):
            n = int(30 * done / max(total, 1))
            sys.stderr.write(f"\r[{'#' * n}{'.' * (30 - n)}] {done}/{total}")
            sys.stderr.flush()

    _setup_logging()
    res = run_replay(recording, out, rig, site, method, tum=tum, realtime=realtime,
                     track=not no_track, progress=bar, options=parse_options(option),
                     link=_link(serial, protocol, baud, missing_x=mavlink_missing_x),
                     overlays=overlays, overlays_only_failures=overlays_only_failures,
                     report=report)
    if show:
        _err("")
    # the report goes to stderr when the poses themselves stream to stdout
    echo = _err if serial == "-" else typer.echo
    echo("\n".join(res.lines()))


def main() -> None:
    quiet_opencv()
    app(prog_name="ceilrun")


if __name__ == "__main__":
    main()
