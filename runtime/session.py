"""The live session: what ``ceilrun`` runs on the vehicle, as one library call.

:func:`run_session` loads the rig and site (the packaged example's for ``sim:NAME``
unless given) and the estimator, checks the outputs (none may exist unless ``force``,
none may be an input of the run), then opens the frame source (``--device``) and the
pose link, waiting for a missing camera or serial port with back-off when ``wait``;
only once both are open does anything appear on disk: the recording (``record``), the
poses file (``out``). It runs the live loop (:func:`~ceilkit.runtime.live.run_live`:
pipeline, tracker, sinks, the link first) until the source ends, ``frames`` ran, or
``stop`` is set; then closes the recording, the poses file, the link and the source,
whatever happened. A full disk pauses the recording and the poses file with one line
each (:class:`~ceilkit.runtime.pipeline.OutputGuard`); the link goes on.

Example (a notebook: thirty simulated frames, poses into a folder)::

    res = run_session(SessionConfig(device="sim:lights", frames=30, out=Path("run")))
    print("\\n".join(res.lines()))
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.devices import open_source, packaged_config
from ceilkit.runtime.errors import CaptureError, ConfigError, LinkError, OutputError
from ceilkit.runtime.fusion import Fusion
from ceilkit.runtime.io.capture import CameraSource
from ceilkit.runtime.io.mcap_rec import McapRecorder, McapSink, McapWriter, is_mcap
from ceilkit.runtime.io.odometry_in import OdometryReceiver
from ceilkit.runtime.io.outputs import (
    FolderLock,
    check_overlaps,
    claim_outputs,
    recording_inputs,
)
from ceilkit.runtime.io.provenance import RUN_METADATA
from ceilkit.runtime.io.recording import (
    LOG_DIR,
    OS_DISK,
    RECORDING_FILES,
    Disk,
    PoseWriter,
    RecordingWriter,
    refuse_existing,
)
from ceilkit.runtime.jit import WarmUpInterrupted, interrupt, stop_when
from ceilkit.runtime.live import AsyncRecorder, LiveResult, run_live
from ceilkit.runtime.metrics import Accuracy, AccuracyMeter, source_truth
from ceilkit.runtime.multi import make_localizer
from ceilkit.runtime.pipeline import (
    OutputGuard,
    PoseFileSink,
    PoseSink,
    Telemetry,
    build_pipeline,
    open_ros2,
)
from ceilkit.runtime.viz.web import open_view

log = logging.getLogger("ceilkit.session")

SIM_FRAMES = 300
"""Frames the simulator renders when ``frames`` is 0."""
WAIT_BACKOFF_S = (0.5, 2.0)
"""``wait``: first and longest delay between attempts to open a camera or port."""
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""Signals that stop a session cleanly (SIGHUP: the ssh session dropped)."""
NUMBERED = "{n}"
"""In ``record``: replaced by the lowest number (1, 2, ...) whose folder does not exist."""


@dataclass(frozen=True)
class LinkConfig:
    """Where and how poses are streamed (see :func:`~ceilkit.runtime.io.link.open_link`).

    Attributes:
        target: a serial port (``/dev/ttyUSB0``), ``-`` for stdout, or a file.
        protocol: a link protocol name (``nmea``, ``mavlink``, ``mavlink-odometry``,
            ``nmea-gps``; the last two need the rig and the site: :meth:`open`).
        baud: serial baud rate.
        system_id, component_id: MAVLink ids.
        unobserved: MAVLink policy for a pose without x (``skip`` or ``nan``).
        origin: MAVLink: a :class:`~ceilkit.runtime.io.link.mavlink.GeoOrigin` to send
            until the autopilot reports one, or ``None``.
    """

    target: str
    protocol: str = "nmea"
    baud: int = 115200
    system_id: int = 1
    component_id: int = 197
    unobserved: str = "skip"
    origin: Any = None

    def check(self, site: Any) -> None:
        """Refuse, before the method's loops load (minutes on a first start), a
        protocol that needs what ``site`` lacks: ``nmea-gps`` places the poses on the
        Earth with the site's ``origin``.

        Raises:
            ConfigError: the site's file and ``origin``.
        """
        if self.protocol == "nmea-gps" and getattr(site, "origin", None) is None:
            raise ConfigError(getattr(site, "source", None), "origin",
                              "missing: the nmea-gps protocol places the poses on the "
                              "Earth with the site's geodetic origin (origin: {lat, lon, "
                              "alt, heading}; docs/serial.md)")

    def open(self, rig: Any = None, site: Any = None):
        """The link, not yet open (use it with ``with``)."""
        from ceilkit.runtime.io.link.transport import open_link

        return open_link(self.target, protocol=self.protocol, baud=self.baud,
                         system_id=self.system_id, component_id=self.component_id,
                         unobserved=self.unobserved, origin=self.origin, rig=rig, site=site)


@contextlib.contextmanager
def opened_link(config: LinkConfig | None, rig: Any = None, site: Any = None
                ) -> Iterator[Any]:
    """``with opened_link(cfg) as link``: the open link, or ``None`` without a config."""
    if config is None:
        yield None
        return
    with config.open(rig, site) as link:
        yield link


def link_lines(link: Any) -> list[str]:
    """The link's counters as report lines (none without a link)."""
    if link is None:
        return []
    c = link.counters
    out = [f"link {link.describe()}: sent {c.sent}, dropped {c.dropped}, skipped "
           f"{c.skipped}, lost {c.lost}, reconnects {c.reconnects}, received {c.received}"
           + (" (disconnected at the end)" if "disconnected" in (
               link.state, getattr(link, "state_at_close", "")) else "")]
    odo = link.on_receive
    if isinstance(odo, OdometryReceiver):
        out.append(f"link odometry: {odo.rows} rows received, {odo.refused} refused (out of "
                   f"a vehicle's reach), {odo.bad} malformed")
    syncs = getattr(link.protocol, "timesyncs", 0)  # MAVLink only
    if syncs:
        out.append(f"answered {syncs} TIMESYNC requests")
    return out


@dataclass(frozen=True)
class CaptureSettings:
    """A camera's requested format (0, empty or ``None``: the driver's default)."""

    width: int = 0
    height: int = 0
    fps: float = 0.0
    fourcc: str = ""
    exposure: float | None = None
    gain: float | None = None

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(None, name, f"expected an integer >= 0 (0: the driver's), "
                                  f"found {v!r}")
        if not (isinstance(self.fps, (int, float)) and 0 <= self.fps < float("inf")):
            raise ConfigError(None, "fps", f"expected a rate >= 0 (0: the driver's), "
                              f"found {self.fps!r}")
        if self.fourcc and not (len(self.fourcc) == 4 and self.fourcc.isascii()
                                and self.fourcc.isprintable()):
            raise ConfigError(None, "fourcc", f"expected 4 characters (MJPG, YUYV, ...) or "
                              f"nothing (the driver's), found {self.fourcc!r}")


@dataclass(frozen=True)
class SessionConfig:
    """What a live session runs (every field is a ``ceilrun`` option).

    Attributes:
        device: a camera, video file, image folder, recording, or ``sim[:NAME]``
            (:func:`~ceilkit.runtime.devices.open_source`).
        rig, site: the files (or loaded objects); for ``sim:NAME`` the example's by
            default, else required.
        method: an estimator name, ``auto`` (fused, :mod:`~ceilkit.runtime.multi`), or
            ``None`` for the site's default.
        start_pose: ``(x_m, y_m, yaw_rad)`` where the vehicle starts (any method: the first prior;
            two more numbers: its 1σ, m and rad).
        limits: the vehicle's stated maximum speed and turn rate ``(m/s, rad/s)``
            (``--max-speed``), or ``None`` for the defaults (docs/config.md).
        link_odometry: read wheel odometry back from the link (``$PCEIO``, MAVLink
            ODOMETRY, WHEEL_DISTANCE with ``wheel_track_m``) into the fusion (``auto``).
        options: the estimator's options by name (values may be strings).
        link: where poses are streamed, or ``None``.
        record: a folder for a SPEC recording of the run, or ``None``.
        out: a folder for ``poses.csv``, or ``None``.
        frames: stop after this many frames (0: until the source ends or ``stop``; the
            simulator then renders :data:`SIM_FRAMES`).
        capture: the camera's requested format.
        force: replace an existing ``poses.csv`` or recording (else a ConfigError).
        wait: wait for a camera or serial port that cannot be opened yet, with back-off
            (:data:`WAIT_BACKOFF_S`), instead of failing (a service started before its
            USB devices appear).
        fsync_every_s: fsync the recording at this period, bounding what a power cut
            loses (0: the operating system's write-back, ~30 s on Linux).
        view: serve the live web view at ``[HOST:]PORT`` (host 127.0.0.1 by default;
            :mod:`~ceilkit.runtime.viz.web`), or ``None``. view_token: required of
            the view's every request when set.
        ros2: a :class:`~ceilkit.runtime.io.ros2.Ros2Config`: also run the ROS 2 node
            (poses, odometry, diagnostics out; ``/initialpose`` and odometry in), or
            ``None``. ``record`` ending in ``.mcap``: an MCAP recording
            (:mod:`~ceilkit.runtime.io.mcap_rec`) instead of a SPEC folder.
        realtime: ``sim``: the frames come at their stamps' pace, as a camera's
            would (``ceilrun``'s default); ``False``: as fast as they render.
    """

    device: str = "/dev/video0"
    rig: Rig | Path | None = None
    site: Site | Path | None = None
    method: str | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    link: LinkConfig | None = None
    record: Path | None = None
    out: Path | None = None
    frames: int = 0
    capture: CaptureSettings = CaptureSettings()
    force: bool = False
    wait: bool = False
    fsync_every_s: float = 1.0
    view: str | None = None
    view_token: str | None = None
    start_pose: tuple[float, ...] | None = None
    link_odometry: bool = False
    wheel_track_m: float | None = None
    ros2: Any = None
    realtime: bool = False
    limits: tuple[float, float] | None = None


@dataclass(frozen=True, eq=False)
class SessionResult:
    """How a session went.

    Attributes:
        config: what ran.
        method: the estimator's name.
        run: the live loop's telemetry, frames recorded, elapsed time, ``stopped``.
        link: report lines of the link's counters (empty without a link).
        camera_reopens: times a camera was reopened after it was lost.
        accuracy: errors against the source's ground truth (sim, a recording), or None.
    """

    config: SessionConfig
    method: str
    run: LiveResult
    link: tuple[str, ...]
    camera_reopens: int
    accuracy: Accuracy | None
    record: Path | None = None
    outputs: tuple[str, ...] = ()

    @property
    def telemetry(self) -> Telemetry:
        return self.run.telemetry

    def lines(self) -> list[str]:
        """The end-of-run report: a heading, then indented details (``no frame
        estimated`` for a run that had none)."""
        out = [f"{self.method} on {self.config.device}: {self.run.elapsed_s:.1f} s"
               + (" (stopped by a signal)" if self.run.stopped else "")]
        tel = self.telemetry
        if tel.frames or tel.dropped:
            out += ["  " + line for line in tel.summary()]
        else:
            out.append("  no frame estimated: " + ("stopped before the first frame"
                                                   if self.run.stopped else
                                                   "the source gave none"))
        out += ["  " + line for line in self.link]
        if self.camera_reopens:
            out.append(f"  camera reopened {self.camera_reopens}x")
        if self.accuracy is not None and self.accuracy.frames:
            out.append("  against the source's ground truth:")
            out += ["    " + line for line in self.accuracy.lines()]
        out += ["  " + line for line in self.outputs]
        if self.record is not None:
            out.append(f"  recorded {self.run.recorded} frames in {self.record}")
            if self.run.left_in_log:
                out.append(f"  {self.run.left_in_log} of them only in {LOG_DIR}/ (they "
                           "replay; `ceilrun repair` writes them as PNGs)")
        return out


def load_rig_site(device: str, rig: Rig | Path | None,
                  site: Site | Path | None) -> tuple[Rig, Site]:
    """The rig and site of a session, checked against each other; ``sim:NAME`` defaults
    to the packaged example's files.

    Raises:
        ConfigError: ``rig`` or ``site`` missing, or a file that does not load.
    """
    if device.startswith("sim"):
        example = packaged_config(device.partition(":")[2] or "corridor")
        rig = rig or example / "rig.yaml"
        site = site or example / "site.yaml"
    if rig is None:
        raise ConfigError(None, "rig", "missing: give the rig file (ceilcal writes it)")
    if site is None:
        raise ConfigError(None, "site", "missing: give the site file")
    r = rig if isinstance(rig, Rig) else Rig.load(rig)
    s = site if isinstance(site, Site) else Site.load(site)
    check_rig_site(r, s)
    return r, s


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT, SIGTERM or SIGHUP (:data:`STOP_SIGNALS`, on the main
    thread): the loop finishes its frame and closes files; the compiled loops' warm-up
    before the first frame (a first start: minutes) stops at once, helper processes and
    all (:func:`~ceilkit.runtime.jit.interrupt`). A second signal while stopping kills
    the process at once. A SIGHUP the process was started ignoring (``nohup ceilrun``,
    a session that must outlive its terminal) stays ignored."""
    stop = threading.Event()
    previous = {}

    def handler(signum, _frame):
        if stop.is_set():  # asked twice: stop now
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        stop.set()
        interrupt()        # a first start's compiling stops now (run_session)

    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            if sig == signal.SIGHUP and signal.getsignal(sig) is signal.SIG_IGN:
                continue                  # nohup: the terminal's hang-up is not a stop
            previous[sig] = signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)


def record_folder(record: Path) -> Path:
    """``record`` with :data:`NUMBERED` replaced by the lowest free number."""
    text = str(record)
    if NUMBERED not in text:
        return Path(record)
    n = 1
    while Path(text.replace(NUMBERED, str(n))).exists():
        n += 1
    return Path(text.replace(NUMBERED, str(n)))


def _resolved(path: Path | str) -> Path:
    return Path(os.path.realpath(path))


def session_inputs(config: SessionConfig, rig: Rig) -> list[Path]:
    """The files and folders a session reads."""
    out = [Path(p) for p in (config.rig, config.site, rig.camera_file)
           if isinstance(p, str | Path)]
    if not config.device.startswith("sim") and Path(config.device).exists():
        device = Path(config.device)  # a recording: its files (outputs may go beside)
        out += recording_inputs(device) if (device / "frames.csv").exists() else [device]
    return out


check_outputs = check_overlaps
"""Refuse outputs that are inputs of the same run, lie inside an input folder, or are
another output (:func:`~ceilkit.runtime.io.outputs.check_overlaps`)."""


def _session_outputs(config: SessionConfig, record: Path | None) -> dict[str, list[Path]]:
    out: dict[str, list[Path]] = {}
    if record is not None:
        out["record"] = [record] if is_mcap(record) else [record / name
                                                          for name in RECORDING_FILES]
    if config.out is not None:
        out["out"] = [config.out / "poses.csv", config.out / RUN_METADATA]
    link = config.link
    if link is not None and link.target != "-":
        from ceilkit.runtime.io.link.transport import is_serial_path

        if not is_serial_path(link.target):
            out["link"] = [Path(link.target)]
    return out


def _check_config(config: SessionConfig) -> None:
    if config.frames < 0:
        raise ConfigError(None, "frames", f"expected an integer >= 0 (0: until stopped), "
                          f"found {config.frames}")
    if not config.fsync_every_s >= 0:
        raise ConfigError(None, "fsync_every_s", f"expected seconds >= 0 (0: off), found "
                          f"{config.fsync_every_s}")
    if config.link_odometry:
        _check_link_odometry(config.link)


def _check_link_odometry(link: LinkConfig | None) -> None:
    """Odometry is read back from the pose link: it must be a serial port (stdout and
    a regular file are only written)."""
    from ceilkit.runtime.io.link.transport import is_serial_path

    if link is None:
        raise ConfigError(None, "link_odometry", "odometry is read back from the serial "
                          "port the poses go to (--serial PORT), and there is none")
    if link.target == "-" or not is_serial_path(link.target):
        to = "stdout (-)" if link.target == "-" else f"the file {link.target}"
        raise ConfigError(None, "link_odometry", "odometry is read back from a serial "
                          f"port (--serial PORT); the poses go to {to}, which is only written")


def hook_link_odometry(config: SessionConfig, link: Any, tracker: Any, method: str,
                       recorder: Any = None) -> OdometryReceiver | None:
    """With ``link_odometry``: the link's receive hook feeding the fusion (and the
    recording's ``odometry.csv``, SPEC folders), or ``None`` with one line on the log
    when the run's method has no fusion to use it."""
    if not config.link_odometry or link is None:
        return None
    if not isinstance(tracker, Fusion):
        log.warning("odometry from the link (--link-odometry) is not used: method %s runs "
                    "without the fusion (--method auto fuses it); it is not read", method)
        return None
    writer = getattr(recorder, "writer", None)
    write = getattr(writer, "write_odometry", None)

    def sink(t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float) -> bool:
        taken = tracker.add_odometry(t_ns, dx_m, dy_m, dyaw_rad)
        if write is not None:
            try:
                write(t_ns, dx_m, dy_m, dyaw_rad)  # as received: the replay refuses alike
            except OutputError as exc:   # the recording's guard says it for the frames
                log.debug("odometry.csv: %s", exc)
        return taken

    link.on_receive = OdometryReceiver(sink, config.wheel_track_m)
    return link.on_receive


def _is_camera(device: str) -> bool:
    return device.isdigit() or device.startswith("/dev/")


def open_waiting(open_fn: Callable[[], Any], what: str, wait: bool,
                 stop: threading.Event) -> Any:
    """``open_fn()``; with ``wait``, retried with back-off (:data:`WAIT_BACKOFF_S`) while
    it raises CaptureError or LinkError, saying so once per new reason; ``None`` when
    ``stop`` is set meanwhile."""
    delay, said = WAIT_BACKOFF_S[0], ""
    while True:
        try:
            return open_fn()
        except (CaptureError, LinkError) as exc:
            if not wait:
                raise
            if str(exc) != said:
                said = str(exc)
                log.warning("waiting for %s: %s (retrying with back-off)", what, said)
        if stop.wait(delay):
            return None
        delay = min(2 * delay, WAIT_BACKOFF_S[1])


def _open_link(config: LinkConfig | None, rig: Rig, site: Site, wait: bool,
               stop: threading.Event, stack: contextlib.ExitStack) -> tuple[Any, bool]:
    """The open link (or ``None``) and whether ``stop`` came while waiting for it."""
    if config is None:
        return None, False
    link = config.open(rig, site)
    from ceilkit.runtime.io.link.transport import SerialLink

    opened = open_waiting(link.open, f"serial port {config.target}",
                          wait and isinstance(link, SerialLink), stop)
    if opened is None:
        return None, True
    stack.callback(link.close)
    return link, False


def run_session(config: SessionConfig, stop: threading.Event | None = None,
                on_frame: Callable[[Telemetry], None] | None = None,
                disk: Disk = OS_DISK) -> SessionResult:
    """Run the live session ``config`` describes (see the module docstring).

    Args:
        config: what to run.
        stop: set it (from a signal handler, another thread) to stop after the frame
            in hand, or, before the first frame, the warm-up of the compiled loops
            between two modules (at once from :func:`stop_on_signals`' handler): the
            result then has no frame and nothing was written.
        on_frame: called after each frame with the telemetry (a status line).
        disk: how the recording and poses are written (a fake in tests).

    Raises:
        ConfigError: bad rig, site, method, options or frames; an output that exists
            (without ``force``) or is an input.
        CaptureError, LinkError, OutputError: a source, link or output that cannot be
            opened (without ``wait``) or created. Nothing is on disk then. Frames that
            cannot be estimated are not errors; a write failing mid-run pauses that
            output (announced) and the run goes on.
    """
    _check_config(config)
    stop = stop or threading.Event()
    start = time.monotonic()
    rig, site = load_rig_site(config.device, config.rig, config.site)
    record = record_folder(config.record) if config.record is not None else None
    _check_free(config, rig, record)  # before the method's loops load (seconds)
    check_inputs(rig, site, config.link)
    if (made := _localizer(config, rig, site, stop)) is None:  # stopped meanwhile
        return _stopped(config, config.method or "the site's method", start)
    estimator, tracker = made
    cap = config.capture
    start = time.monotonic()
    source = open_waiting(
        lambda: open_source(config.device, rig, site, cap.width, cap.height, cap.fps,
                            cap.fourcc, cap.exposure, cap.gain,
                            frames=config.frames or SIM_FRAMES,
                            pace=stop.wait if config.realtime else None),
        f"camera {config.device}", config.wait and _is_camera(config.device), stop)
    if source is None:  # stopped while waiting
        return _stopped(config, estimator.name, start)
    truth = source_truth(source)
    meter = AccuracyMeter(truth) if truth is not None else None
    guards: list[OutputGuard] = []
    with contextlib.ExitStack() as stack:
        stack.enter_context(source)
        link, stopped = _open_link(config.link, rig, site, config.wait, stop, stack)
        result = None
        if not stopped:  # every resource is open: now the outputs appear on disk
            claim_session_outputs(config, rig, record, stack)  # locked, checked again
            view = open_view(config.view, config.view_token, rig, site, stack,
                             lambda: link_lines(link))
            ros2 = None if config.ros2 is None else open_ros2(
                config.ros2, tracker, stack, getattr(source, "live", False), rig, site)
            poses = None
            if config.out is not None:
                writer = stack.enter_context(PoseWriter(config.out / "poses.csv", disk=disk))
                guards.append(OutputGuard("poses.csv", config.out, unit="row"))
                poses = PoseFileSink(writer, guard=guards[-1])
            recorder, more = None, []
            if record is not None:
                guards.append(OutputGuard("recording", record))
                recorder = _open_recorder(config, record, rig, site, truth, disk,
                                          guards[-1], stack, more)
            hook_link_odometry(config, link, tracker, estimator.name, recorder)
            pipeline = build_pipeline(estimator, tracker, link=link, ros2=ros2, poses=poses,
                                      more=more, meter=meter,
                                      watch=view.watch if view is not None else None)
            if view is not None:
                view.attach(pipeline.telemetry)
            result = run_live(source, pipeline, recorder, stop, config.frames,
                              _status(on_frame, link),
                              camera_size=(rig.camera.width, rig.camera.height))
    if result is None:
        result = LiveResult(Telemetry(), 0, time.monotonic() - start, True)
    return SessionResult(config, estimator.name, result, tuple(link_lines(link)),
                         source.reopens if isinstance(source, CameraSource) else 0,
                         meter.result() if meter is not None else None, record,
                         tuple(line for g in guards for line in g.lines()))


def check_inputs(rig: Rig, site: Site, link: LinkConfig | None) -> None:
    """The rig against the site (:func:`~ceilkit.runtime.config.site.check_rig_site`)
    and the link's protocol against the site (:meth:`LinkConfig.check`), before the
    method's loops load."""
    check_rig_site(rig, site)
    if link is not None:
        link.check(site)


def _stopped(config: SessionConfig, method: str, start: float) -> SessionResult:
    """A session stopped before its first frame, at ``start`` (monotonic seconds)."""
    return SessionResult(config, method,
                         LiveResult(Telemetry(), 0, time.monotonic() - start, True),
                         (), 0, None)


def _localizer(config: SessionConfig, rig: Rig, site: Site,
               stop: threading.Event) -> tuple[Any, Any] | None:
    """The estimator and tracker, their loops made (a first start compiles them:
    minutes); ``None`` when ``stop`` came meanwhile (:func:`~.jit.stop_when`)."""
    try:
        with stop_when(stop):
            return make_localizer(config.method, rig, site, config.options,
                                  config.start_pose, config.link_odometry,
                                  limits=config.limits)  # --ros2: the same method
    except WarmUpInterrupted:
        return None


def _check_free(config: SessionConfig, rig: Any, record: Path | None) -> None:
    """Refuse, before anything is opened, an output that is an input or that exists
    (without ``force``)."""
    claim_session_outputs(config, rig, record)
    if record is not None and not config.force:
        if is_mcap(record) and record.exists():
            raise refuse_existing(record, "a recording is")
        if not is_mcap(record):
            RecordingWriter.check_free(record)


def claim_session_outputs(config: SessionConfig, rig: Any, record: Path | None,
                          stack: contextlib.ExitStack | None = None) -> None:
    """:func:`~ceilkit.runtime.io.outputs.claim_outputs` of a session: ``poses.csv`` in
    ``out`` (refused when it exists, without ``force``), the recording, a ``--serial``
    file; with ``stack``, ``out`` and the recording's folder (an MCAP file's own lock
    beside it) locked until it closes. Whether a recording is already there is checked
    by :meth:`RecordingWriter.check_free` and :class:`McapWriter` (they name a recording
    as one)."""
    inputs = session_inputs(config, rig)
    outputs = _session_outputs(config, record)
    folders = {} if config.out is None else {"out": [config.out]}
    check_overlaps(inputs, outputs)
    if stack is not None:  # again under the locks: the link file is open (ours) by now
        outputs.pop("link", None)
    if record is not None:
        outputs.pop("record")
        if not is_mcap(record):
            folders["record"] = [record]
        elif stack is not None:
            stack.enter_context(FolderLock(record.parent, f".{record.name}.lock"))
    claim_outputs(outputs, folders=folders, inputs=inputs, force=config.force, stack=stack)


def _open_recorder(config: SessionConfig, record: Path, rig: Any, site: Any, truth: Any,
                   disk: Disk, guard: OutputGuard, stack: contextlib.ExitStack,
                   sinks: list[PoseSink]) -> Any:
    """The recorder of ``record`` (an MCAP file, or a SPEC folder written by a thread),
    opened and closed by ``stack``; an MCAP recording's pose sink joins ``sinks``."""
    if is_mcap(record):
        mcap = stack.enter_context(McapWriter(record, rig, site, config.force,
                                              truth_of=truth))
        sinks.append(McapSink(mcap, guard))
        return McapRecorder(mcap, guard)
    return AsyncRecorder(
        stack.enter_context(RecordingWriter(record, rig, site, truth_of=truth,
                                            force=config.force, disk=disk)),
        fsync_every_s=config.fsync_every_s, guard=guard)


def _status(on_frame: Callable[[Telemetry], None] | None,
            link: Any) -> Callable[[Telemetry], None] | None:
    """``on_frame`` with the link's state (stalled, disconnected) in the telemetry."""
    if on_frame is None or link is None:
        return on_frame

    def status(tel: Telemetry) -> None:
        tel.link_state = ("stalled" if getattr(link, "stalled", False)
                          else "" if link.state == "connected" else link.state)
        on_frame(tel)

    return status
