"""``ceilrun``: run on the vehicle (camera in, poses out over serial), or replay a recording.

Exit codes: 0 when the run ended (the source ended, ``--frames`` reached, or SIGINT /
SIGTERM asked it to stop: files are closed and complete); 1 for a ceilkit error
(one line on stderr); 2 for bad options. A second SIGINT/SIGTERM while stopping
kills the process at once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from enum import Enum
from pathlib import Path

import typer

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.devices import open_source, packaged_config
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.registry import METHOD_NAMES, make_estimator
from ceilkit.runtime.io.recording import PoseWriter, RecordingWriter
from ceilkit.runtime.metrics import AccuracyMeter, MeterSink, source_truth
from ceilkit.runtime.pipeline import Pipeline, PoseFileSink
from ceilkit.runtime.replay import replay as run_replay
from ceilkit.runtime.tracking import Tracker

from .common import make_app, quiet_opencv

app = make_app("ceilrun", "Run the localizer on the vehicle, or replay a recording.\n\n"
               "Live: ceilrun --device /dev/video0 --serial /dev/ttyUSB0 --rig rig.yaml "
               "--site site.yaml")


class Protocol(str, Enum):
    nmea = "nmea"
    mavlink = "mavlink"


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
    from ceilkit.runtime.errors import LinkError

    try:
        return GeoOrigin(lat, lon, alt)
    except LinkError as exc:
        raise ConfigError(None, "--ekf-origin", str(exc)) from None


def _check_method(name: str | None) -> str | None:
    if name is not None and name not in METHOD_NAMES:
        raise typer.BadParameter(f"unknown method {name!r} (choose from "
                                 f"{', '.join(METHOD_NAMES)})")
    return name


def _err(msg: str) -> None:
    typer.echo(msg, err=True)


@contextlib.contextmanager
def _stop_on_signals():
    """An event set by SIGINT or SIGTERM: the loop finishes its frame and closes files."""
    stop = threading.Event()
    previous = {}

    def handler(signum, _frame):
        if stop.is_set():  # asked twice: stop now
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        stop.set()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)


def _load_rig_site(device: str, rig: Path | None, site: Path | None) -> tuple[Rig, Site]:
    if device.startswith("sim"):
        example = packaged_config(device.partition(":")[2] or "corridor")
        rig = rig or example / "rig.yaml"
        site = site or example / "site.yaml"
    if rig is None:
        raise ConfigError(None, "--rig", "missing: give the rig file (ceilcal writes it)")
    if site is None:
        raise ConfigError(None, "--site", "missing: give the site file")
    r, s = Rig.load(rig), Site.load(site)
    check_rig_site(r, s)
    return r, s


def _open_link(serial: str | None, protocol: Protocol, baud: int, sysid: int, compid: int,
               missing_x: MissingX = MissingX.skip, origin=None):
    if serial is None:
        return contextlib.nullcontext(None)
    from ceilkit.runtime.io.link.transport import open_link

    return open_link(serial, protocol=protocol.value, baud=baud, system_id=sysid,
                     component_id=compid, unobserved=missing_x.value, origin=origin)


def _link_lines(link) -> list[str]:
    if link is None:
        return []
    c = link.counters
    out = [f"link {link.describe()}: sent {c.sent}, dropped {c.dropped}, skipped "
           f"{c.skipped}, reconnects {c.reconnects}, received {c.received}"]
    syncs = getattr(link.protocol, "timesyncs", 0)
    if syncs:
        out.append(f"answered {syncs} TIMESYNC requests")
    return out


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
    method: str = typer.Option(None, callback=_check_method,
                               help=f"Estimator: {', '.join(METHOD_NAMES)} "
                                    "(default: what the site holds)."),
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
) -> None:
    """Run live: frames from --device, poses to --serial."""
    if ctx.invoked_subcommand is not None:
        return
    _setup_logging()
    origin = _parse_origin(ekf_origin)
    r, s = _load_rig_site(device, rig, site)
    estimator = make_estimator(method, r, s)
    sim_frames = frames or 300
    source = open_source(device, r, s, width, height, fps, fourcc, exposure, gain,
                         frames=sim_frames)
    recorder = (RecordingWriter(record, r, s, truth_of=source_truth(source))
                if record is not None else None)
    writer = PoseWriter(out / "poses.csv") if out is not None else None
    try:
        with source, _open_link(serial, protocol, baud, sysid, compid, mavlink_missing_x,
                                origin) as link, _stop_on_signals() as stop:
            sinks = [x for x in (link, PoseFileSink(writer) if writer else None) if x]
            truth = source_truth(source)
            meter = AccuracyMeter(truth) if truth is not None else None
            if meter is not None:
                sinks.append(MeterSink(meter))
            pipeline = Pipeline(estimator, sinks, Tracker())
            from ceilkit.runtime.live import run_live

            def show(tel):
                if status:
                    sys.stderr.write("\r" + tel.live_line())
                    sys.stderr.flush()

            result = run_live(source, pipeline, recorder, stop, frames, show)
    finally:
        if recorder is not None:
            recorder.close()
        if writer is not None:
            writer.close()
    if status:
        _err("")
    _err(f"ceilrun: {estimator.name} on {device}: {result.elapsed_s:.1f} s"
         + (" (stopped by a signal)" if result.stopped else ""))
    for line in result.telemetry.summary() + _link_lines(link):
        _err("  " + line)
    if getattr(source, "reopens", 0):
        _err(f"  camera reopened {source.reopens}x")
    if meter is not None:
        _err("  against the source's ground truth:")
        for line in meter.result().lines():
            _err("    " + line)
    if recorder is not None:
        _err(f"  recorded {result.recorded} frames in {record}")


@app.command()
def replay(
    recording: Path = typer.Argument(..., help="A SPEC recording folder."),
    out: Path = typer.Option(None, help="Output folder (default RECORDING/replay)."),
    rig: Path = typer.Option(None, help="Use this rig.yaml instead of the recording's."),
    site: Path = typer.Option(None, help="Use this site.yaml instead of the recording's."),
    method: str = typer.Option(None, callback=_check_method,
                               help=f"Estimator: {', '.join(METHOD_NAMES)}."),
    tum: bool = typer.Option(False, "--tum", help="Also write poses.tum (for evo)."),
    realtime: bool = typer.Option(False, "--realtime", help="Replay at recorded timing."),
    serial: str = typer.Option(None, help="Also stream the poses to this port (or -)."),
    protocol: Protocol = typer.Option(Protocol.nmea, help="Pose stream protocol."),
    baud: int = typer.Option(115200, help="Serial baud rate."),
    mavlink_missing_x: MissingX = typer.Option(
        MissingX.skip, help="MAVLink, a pose without x: skip (default) or nan."),
    progress: bool = typer.Option(None, "--progress/--no-progress",
                                  help="Progress bar (default: on a terminal)."),
) -> None:
    """Replay a recording through the pipeline; write poses.csv; print errors vs truth.csv."""
    show = sys.stderr.isatty() if progress is None else progress

    def bar(done: int, total: int) -> None:
        if show and (done == total or done % 10 == 0):
            n = int(30 * done / max(total, 1))
            sys.stderr.write(f"\r[{'#' * n}{'.' * (30 - n)}] {done}/{total}")
            sys.stderr.flush()

    _setup_logging()
    with _open_link(serial, protocol, baud, 1, 197, mavlink_missing_x) as link:
        res = run_replay(recording, out, rig, site, method, tum=tum, realtime=realtime,
                         sinks=[link] if link is not None else (), progress=bar)
    if show:
        _err("")
    # the report goes to stderr when the poses themselves stream to stdout
    echo = _err if serial == "-" else typer.echo
    tel = res.telemetry
    echo(f"replay {res.recording} with {res.method}: {tel.frames} frames in "
               f"{res.elapsed_s:.2f} s -> {res.poses_path}")
    for line in tel.summary() + _link_lines(link):
        echo("  " + line)
    if res.accuracy is not None:
        echo("  against truth.csv:")
        for line in res.accuracy.lines():
            echo("    " + line)


def main() -> None:
    quiet_opencv()
    app(prog_name="ceilrun")


if __name__ == "__main__":
    main()
