import numpy as np

from ceilkit.runtime.estimate import Failure, PoseEstimate
from ceilkit.runtime.live import run_live
from ceilkit.runtime.pipeline import ListSink, Pipeline
from ceilkit.runtime.sources import Frame, ListSource


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


def test_run_live_stops_at_max_frames_and_records(tmp_path, corridor_rig, corridor_site):
    from ceilkit.runtime.recording import Recording, RecordingWriter

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
