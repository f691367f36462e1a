import numpy as np

from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.sources import Frame, ListSource
from ceilkit.runtime.live import run_live
from ceilkit.runtime.pipeline import ListSink, Pipeline


class FakeEstimator:
    """Succeeds on even frames, fails on odd ones."""

    name = "fake"

    def __init__(self):
        self.priors = []

    def estimate(self, image, t_ns, prior=None):
        self.priors.append(prior)
        k = int(image[0, 0])
        if k % 2:
            return Failure(t_ns, self.name, "odd_frame")
        return PoseEstimate(t_ns, self.name, None, 0.001 * k, 0.0, 0.8)


def _frames(n):
    return [Frame(np.full((4, 4), k, np.uint8), (k + 1) * 10_000_000, k) for k in range(n)]


def test_pipeline_counts_and_publishes_every_frame():
    clock = iter(range(0, 10**9, 1000)).__next__
    sink = ListSink()
    from ceilkit.runtime.tracking import Tracker

    est = FakeEstimator()
    p = Pipeline(est, [sink], Tracker(), clock=clock)
    for f in _frames(6):
        p.process(f, capture_ns=0)
    tel = p.telemetry
    assert tel.frames == 6 and tel.estimated == 3 and tel.failures["odd_frame"] == 3
    assert len(sink.items) == 6 and sink.items[0][1] is True  # first fix
    assert est.priors[0] is None and est.priors[2] is not None
    assert len(tel.summary()) == 3 and "odd_frame 3" in tel.summary()[1]


class _Named:
    """A sink that appends its name to a shared list when it is sent an estimate."""

    def __init__(self, name, order):
        self.name, self.order = name, order

    def send(self, est, relocalized, capture_ns):
        self.order.append(self.name)


def test_build_pipeline_puts_the_link_first_and_the_meter_last():
    from ceilkit.runtime.metrics import MeterSink
    from ceilkit.runtime.pipeline import build_pipeline

    order = []

    class Meter:  # an AccuracyMeter's one method
        def add(self, est):
            order.append("meter")

    def watch(estimator, sinks):
        sinks.append(_Named("view", order))
        return estimator

    p = build_pipeline(FakeEstimator(), None, poses=_Named("poses", order),
                       more=[_Named("more", order)], ros2=_Named("ros2", order),
                       link=_Named("link", order), meter=Meter(), watch=watch)
    p.process(_frames(1)[0], capture_ns=0)
    assert order == ["link", "ros2", "poses", "more", "meter", "view"]
    assert isinstance(p.sinks[4], MeterSink)
    assert build_pipeline(FakeEstimator()).sinks == []


def test_replay_and_live_build_their_pipelines_alike(monkeypatch, tmp_path):
    """Both call the one builder: the link first, the meter last (no loop call)."""
    from ceilkit.runtime import pipeline as pipeline_mod
    from ceilkit.runtime import replay as replay_mod
    from ceilkit.runtime import session as session_mod
    from ceilkit.runtime.session import LinkConfig, SessionConfig, run_session

    calls = []
    real = pipeline_mod.build_pipeline

    def spy(*args, **kw):
        calls.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(replay_mod, "build_pipeline", spy)
    monkeypatch.setattr(session_mod, "build_pipeline", spy)
    run_session(SessionConfig(device="sim:corridor", frames=6, record=tmp_path / "rec",
                              link=LinkConfig(str(tmp_path / "live.nmea")),
                              out=tmp_path / "live"))
    res = replay_mod.replay(tmp_path / "rec", tmp_path / "replay",
                            link=LinkConfig(str(tmp_path / "replay.nmea")))
    live, again = calls
    for kw in (live, again):
        assert kw["link"] is not None and kw["poses"] is not None
        assert kw["meter"] is not None  # the source's truth: metered as a sink
    assert res.accuracy.frames == 6 and res.accuracy.estimated == res.telemetry.estimated
    for name in ("live.nmea", "replay.nmea"):
        assert (tmp_path / name).read_bytes().count(b"$PCEIL") == 6


def test_run_live_stops_at_max_frames_and_records(tmp_path, corridor_rig, corridor_site):
    from ceilkit.runtime.io.recording import Recording, RecordingWriter

    p = Pipeline(FakeEstimator())
    with RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site) as rec:
        res = run_live(ListSource(_frames(10)), p, rec, max_frames=4)
    assert res.telemetry.frames == 4 and res.recorded == 4 and not res.stopped
    assert len(Recording(tmp_path / "rec")) == 4


def test_run_live_stops_on_event():
    import threading

    stop = threading.Event()
    p = Pipeline(FakeEstimator())

    def on_frame(tel):
        if tel.frames == 2:
            stop.set()

    res = run_live(ListSource(_frames(10)), p, stop=stop, on_frame=on_frame)
    assert res.stopped and res.telemetry.frames == 2


def test_set_fault_reaches_sinks_that_hear_it():
    from ceilkit.runtime.io.link import MemoryLink, nmea

    with MemoryLink("nmea") as link:
        p = Pipeline(FakeEstimator(), [ListSink(), link])
        p.set_fault("camera_lost")
        p.set_fault(None)
    first, cleared = [nmea.decode(ln + b"\r\n") for ln in bytes(link.written).split(b"\r\n")
                      if ln]
    assert first.faulted and first.reason == "camera_lost" and not cleared.faulted


def test_async_recorder_keeps_every_frame_and_reports_errors(tmp_path, corridor_rig,
                                                            corridor_site):
    from ceilkit.runtime.io.recording import Recording, RecordingWriter
    from ceilkit.runtime.live import AsyncRecorder

    with AsyncRecorder(RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site),
                       max_queue=2) as rec:
        for f in _frames(9):
            rec.write(f)
    assert rec.count == 9 and len(Recording(tmp_path / "rec")) == 9
    import shutil

    import pytest

    bad = AsyncRecorder(RecordingWriter(tmp_path / "bad", corridor_rig, corridor_site))
    shutil.rmtree(tmp_path / "bad" / "frames")  # the disk went away
    bad.write(_frames(1)[0])

    from ceilkit.runtime.errors import OutputError

    with pytest.raises(OutputError, match="cannot write"):
        bad.close()
    assert bad.writer.closed  # files closed all the same


def test_run_live_reports_a_lost_camera_and_records_every_frame(tmp_path, corridor_rig,
                                                                corridor_site):
    """A camera unplugged mid-run: the link says camera_lost, the run goes on, and every
    frame processed is in the recording. No timer: the unplug moves the run's clock on
    by 10 s (the camera and the loop share it), and the camera is plugged back in when
    the sinks hear camera_lost."""
    import threading
    import time

    from ceilkit.runtime.io.capture import CameraSource, FakeCamera
    from ceilkit.runtime.io.link import MemoryLink, nmea
    from ceilkit.runtime.io.recording import Recording, RecordingWriter

    images = [np.full((4, 4), 2 * k, np.uint8) for k in range(4)]  # even: estimated
    cam = FakeCamera(images, fps=100)
    events = []
    stop = threading.Event()
    offset = [0]

    def clock():
        return time.monotonic_ns() + offset[0]

    def on_frame(tel):
        if tel.frames == 10:
            cam.unplug()
            offset[0] += 10 * 10**9
        if tel.frames == 20:
            stop.set()
        events.append(tel.camera_losses)

    class Replug:
        """Plugs the camera back in when told it is lost."""

        def send(self, est, relocalized, capture_ns):
            pass

        def set_fault(self, reason):
            events.append(reason)
            if reason == "camera_lost":
                cam.replug()

    with CameraSource("/dev/video5", open_capture=cam.open, max_backoff_s=0.05,
                      clock=clock) as src, MemoryLink("nmea") as link:
        p = Pipeline(FakeEstimator(), [link, Replug()])
        res = run_live(src, p, RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site),
                       stop=stop, on_frame=on_frame, clock=clock, fault_after_s=5.0)
    assert res.stopped and res.telemetry.frames == 20 and res.telemetry.camera_losses == 1
    assert [e for e in events if not isinstance(e, int)] == ["camera_lost", None]
    assert res.recorded == 20 and len(Recording(tmp_path / "rec")) == 20
    lines = [nmea.decode(ln + b"\r\n") for ln in bytes(link.written).split(b"\r\n") if ln]
    faults = [d for d in lines if isinstance(d, nmea.NmeaStatus)]
    assert faults and all(d.faulted and d.reason == "camera_lost" for d in faults)
    assert sum(isinstance(d, nmea.NmeaPose) for d in lines) == 20
    assert src.reopens == 1


def test_no_track_rows_do_not_depend_on_the_frames_order():
    """With no tracker every frame is estimated as if it were the first (the block
    method pools side offsets across frames otherwise): shuffled frames give the same
    row for each frame, to the bit."""
    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site
    from ceilkit.runtime.estimators.registry import make_estimator
    from ceilkit.runtime.io.sources import Frame
    from ceilkit.runtime.pipeline import Pipeline
    from ceilkit.runtime.sim.render import SimOptions, render_frame
    from helpers import CONFIGS

    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    frames = [Frame(k, k * 10**8, render_frame(rig, site, 0.5 + 0.4 * k, 0.05 * k - 0.1,
                                                0.05 * k, SimOptions(supersample=1),
                                                np.random.default_rng(k)))
              for k in range(6)]

    def rows(order):
        pipe = Pipeline(make_estimator("block", rig, site), [])
        out = {}
        for k in order:
            e = pipe.process(frames[k])
            out[k] = (e.x_m, e.y_m, e.yaw_rad, e.cov.tobytes()) if e else e.reason
        return out

    assert rows(range(6)) == rows([3, 0, 5, 1, 4, 2])


def test_a_run_of_only_ambiguous_frames_says_what_singles_them_out():
    from ceilkit.runtime.pipeline import Telemetry

    tel = Telemetry()
    tel.frames, tel.failures["ambiguous"] = 3, 3
    assert any("--start-pose" in line for line in tel.summary())
    tel.estimated = 1
    assert not any("--start-pose" in line for line in tel.summary())
