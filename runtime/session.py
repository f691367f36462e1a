"""The live session: what ``ceilrun`` runs on the vehicle, as one library call.

:func:`run_session` opens, in this order, the rig and site (the packaged example's for
``sim:NAME`` unless given), the estimator, the frame source (``--device``), the
recording (``record``), the poses file (``out``), and the pose link; runs the live
loop (:func:`~ceilkit.runtime.live.run_live`: pipeline, tracker, sinks, the link
first) until the source ends, ``frames`` ran, or ``stop`` is set; then closes the
recording, the poses file, the link and the source, whatever happened.

Example (a notebook: thirty simulated frames, poses into a folder)::

    res = run_session(SessionConfig(device="sim:lights", frames=30, out=Path("run")))
    print("\\n".join(res.lines()))
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.devices import open_source, packaged_config
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.capture import CameraSource
from ceilkit.runtime.io.recording import PoseWriter, RecordingWriter
from ceilkit.runtime.live import LiveResult, run_live
from ceilkit.runtime.metrics import Accuracy, AccuracyMeter, MeterSink, source_truth
from ceilkit.runtime.pipeline import Pipeline, PoseFileSink, PoseSink, Telemetry
from ceilkit.runtime.tracking import Tracker
from ceilkit.runtime.viz.web import open_view

SIM_FRAMES = 300
"""Frames the simulator renders when ``frames`` is 0."""


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
           f"{c.skipped}, reconnects {c.reconnects}, received {c.received}"]
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


@dataclass(frozen=True)
class SessionConfig:
    """What a live session runs (every field is a ``ceilrun`` option).

    Attributes:
        device: a camera, video file, image folder, recording, or ``sim[:NAME]``
            (:func:`~ceilkit.runtime.devices.open_source`).
        rig, site: the files (or loaded objects); for ``sim:NAME`` the example's by
            default, else required.
        method: an estimator name, or ``None`` for the site's default.
        options: the estimator's options by name (values may be strings).
        link: where poses are streamed, or ``None``.
        record: a folder for a SPEC recording of the run, or ``None``.
        out: a folder for ``poses.csv``, or ``None``.
        frames: stop after this many frames (0: until the source ends or ``stop``; the
            simulator then renders :data:`SIM_FRAMES`).
        capture: the camera's requested format.
        view: serve the live web view at ``[HOST:]PORT`` (host 127.0.0.1 by default;
            :mod:`~ceilkit.runtime.viz.web`), or ``None``. view_token: required of
            the view's every request when set.
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
    view: str | None = None
    view_token: str | None = None


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

    @property
    def telemetry(self) -> Telemetry:
        return self.run.telemetry

    def lines(self) -> list[str]:
        """The end-of-run report: a heading, then indented details."""
        out = [f"{self.method} on {self.config.device}: {self.run.elapsed_s:.1f} s"
               + (" (stopped by a signal)" if self.run.stopped else "")]
        out += ["  " + line for line in self.telemetry.summary() + list(self.link)]
        if self.camera_reopens:
            out.append(f"  camera reopened {self.camera_reopens}x")
        if self.accuracy is not None:
            out.append("  against the source's ground truth:")
            out += ["    " + line for line in self.accuracy.lines()]
        if self.config.record is not None:
            out.append(f"  recorded {self.run.recorded} frames in {self.config.record}")
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
    """An event set by SIGINT or SIGTERM (on the main thread): the loop finishes its
    frame and closes files. A second signal while stopping kills the process at once."""
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


def run_session(config: SessionConfig, stop: threading.Event | None = None,
                on_frame: Callable[[Telemetry], None] | None = None) -> SessionResult:
    """Run the live session ``config`` describes (see the module docstring).

    Args:
        config: what to run.
        stop: set it (from a signal handler, another thread) to stop after the frame
            in hand; :func:`stop_on_signals` gives one.
        on_frame: called after each frame with the telemetry (a status line).

    Raises:
        ConfigError: bad rig, site, method or options.
        CaptureError, LinkError, OutputError: a source, link or output that cannot be
            opened or written. Frames that cannot be estimated are not errors.
    """
    rig, site = load_rig_site(config.device, config.rig, config.site)
    estimator = make_estimator(config.method, rig, site, config.options)
    cap = config.capture
    source = open_source(config.device, rig, site, cap.width, cap.height, cap.fps,
                         cap.fourcc, cap.exposure, cap.gain,
                         frames=config.frames or SIM_FRAMES)
    truth = source_truth(source)
    meter = AccuracyMeter(truth) if truth is not None else None
    with contextlib.ExitStack() as stack:
        stack.enter_context(source)
        recorder = None
        if config.record is not None:
            recorder = stack.enter_context(
                RecordingWriter(config.record, rig, site, truth_of=truth))
        writer = (stack.enter_context(PoseWriter(config.out / "poses.csv"))
                  if config.out is not None else None)
        link = stack.enter_context(opened_link(config.link, rig, site))
        sinks: list[PoseSink] = [s for s in (link, PoseFileSink(writer) if writer else None)
                                 if s is not None]
        if meter is not None:
            sinks.append(MeterSink(meter))
        view = open_view(config.view, config.view_token, rig, site, stack,
                         lambda: link_lines(link))
        pipeline = Pipeline(view.watch(estimator, sinks) if view else estimator, sinks,
                            Tracker())
        if view is not None:
            view.attach(pipeline.telemetry)
        result = run_live(source, pipeline, recorder, stop, config.frames, on_frame)
    return SessionResult(config, estimator.name, result, tuple(link_lines(link)),
                         source.reopens if isinstance(source, CameraSource) else 0,
                         meter.result() if meter is not None else None)
