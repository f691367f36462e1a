import threading
import time

import cv2
import numpy as np
import pytest

from ceilkit.runtime.devices import open_source, packaged_config
from ceilkit.runtime.errors import CaptureError
from ceilkit.runtime.io.capture import (
    CameraSource,
    FakeCamera,
    ImageFolderSource,
    VideoFileSource,
    open_video,
)


class FakeCapture:
    """A camera that delivers ``n`` frames, then fails (unplugged)."""

    def __init__(self, n, opened=True, period_s=0.002):
        self.n, self.opened, self.period_s, self.k = n, opened, period_s, 0
        self.grabbed = threading.Event()   # set once ``wanted`` frames were handed over
        self.wanted = n + 1

    def isOpened(self):
        return self.opened

    def read(self):
        if self.k >= self.wanted:  # the grabber is back for more: frame k-1 is stored
            self.grabbed.set()
        if self.k >= self.n:
            return False, None
        time.sleep(self.period_s)
        self.k += 1
        return True, np.full((4, 4), self.k % 256, np.uint8)

    def release(self):
        self.opened = False


def test_camera_reopens_after_unplug_and_keeps_going():
    opened = []

    def open_capture(dev):
        cap = FakeCapture(5)
        opened.append(cap)
        return cap

    with CameraSource("/dev/video9", open_capture=open_capture, max_backoff_s=0.02) as cam:
        seen = []
        deadline = time.monotonic() + 5
        while len(opened) < 3 and time.monotonic() < deadline:
            f = cam.read(timeout_s=2.0)
            seen.append(f.index)
        assert cam.reopens >= 2
        assert seen == sorted(seen) and len(set(seen)) == len(seen)


def test_latest_frame_policy_counts_drops():
    """A slow estimator: while it works on one frame, the grabber replaces the newest
    one three times; the next read gets the last, the two between are dropped."""
    fake = FakeCapture(10_000, period_s=0.0005)
    with CameraSource(0, open_capture=lambda d: fake) as cam:
        first = cam.read()
        fake.wanted = first.index + 4  # grabbed when frame first.index + 3 is stored
        assert fake.grabbed.wait(30)
        second = cam.read()
        assert second.index >= first.index + 3
        assert second.index > first.index + 1
        assert cam.dropped >= second.index - first.index - 1 - 1
        assert second.t_ns > first.t_ns


def test_camera_that_cannot_open():
    with pytest.raises(CaptureError, match="/dev/video7: cannot open the camera"):
        CameraSource("/dev/video7", open_capture=lambda d: FakeCapture(0, opened=False))


def test_image_folder_and_video(tmp_path):
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"{k:03d}.png"), np.full((8, 8), 10 * k, np.uint8))
    src = ImageFolderSource(tmp_path, fps=10)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2] and frames[2].t_ns == 200_000_000
    video = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20, (32, 24))
    for k in range(5):
        w.write(np.full((24, 32, 3), 40 * k, np.uint8))
    w.release()
    with VideoFileSource(video) as v:
        got = list(v)
    assert len(got) == 5 and got[1].t_ns == 50_000_000


def test_open_source_errors(tmp_path):
    with pytest.raises(CaptureError, match="no such device or file"):
        open_source(str(tmp_path / "nothing"))
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(CaptureError, match="not a camera"):
        open_source(str(tmp_path / "x.txt"))
    with pytest.raises(CaptureError, match="no images"):
        open_source(str(tmp_path))
    with pytest.raises(CaptureError, match="choose from"):
        packaged_config("nope")


def test_read_after_close_returns_none():
    cam = CameraSource(0, open_capture=lambda d: FakeCapture(10_000))
    cam.close()
    assert cam.read(timeout_s=0.2) is None


def _images(n=3):
    return [np.full((4, 6), 10 * k, np.uint8) for k in range(n)]


def test_fake_camera_unplugged_is_a_state_not_an_error():
    cam = FakeCamera(_images(), fps=200)
    with CameraSource("/dev/video3", open_capture=cam.open, max_backoff_s=0.02) as src:
        first = src.wait_frame(2.0)
        assert first is not None and first.image.shape == (4, 6)
        cam.unplug()
        deadline = time.monotonic() + 5
        while src.status != "lost" and time.monotonic() < deadline:
            src.wait_frame(0.01)
        assert src.status == "lost" and src.losses == 1
        assert src.wait_frame(0.05) is None  # no frame, no exception
        with pytest.raises(CaptureError, match="camera lost"):
            src.read(timeout_s=0.05)
        cam.replug()
        back = None
        while back is None and time.monotonic() < deadline:
            back = src.wait_frame(0.05)
        assert back is not None and back.index > first.index and back.t_ns > first.t_ns
        assert src.reopens == 1 and src.status == "running" and cam.opens >= 2
    assert src.closed and src.wait_frame(0.01) is None


def test_fake_camera_serves_images_in_a_loop_at_its_rate():
    cam = FakeCamera(_images(2), fps=500)
    cap = cam.open()
    got = [int(cap.read()[1][0, 0]) for _ in range(5)]
    assert got == [0, 10, 0, 10, 0] and cam.served == 5
    cap.release()
    assert cap.read() == (False, None)
    with pytest.raises(CaptureError):
        FakeCamera([], fps=30)
    with pytest.raises(CaptureError):
        FakeCamera(_images(), fps=0)


def test_open_video_takes_only_cameras_and_videos(tmp_path):
    with pytest.raises(CaptureError, match="no such video file"):
        open_video(str(tmp_path / "nope.mp4"))
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(CaptureError, match="not a video"):
        open_video(str(tmp_path / "a.txt"))
    video = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for k in range(3):
        w.write(np.full((24, 32, 3), 40 * k, np.uint8))
    w.release()
    with open_video(str(video)) as v:
        assert isinstance(v, VideoFileSource) and len(list(v)) == 3


def test_every_source_declares_live_and_dropped():
    """The live loop reads ``live`` and ``dropped`` of any source, never by getattr."""
    from ceilkit.runtime.io.capture import CameraSource, ImageFolderSource, VideoFileSource
    from ceilkit.runtime.io.recording import Recording
    from ceilkit.runtime.io.sources import FrameSource, ListSource, LiveSource
    from ceilkit.runtime.sim.render import SimSource

    for cls, live in ((CameraSource, True), (VideoFileSource, False),
                      (ImageFolderSource, False), (Recording, False), (SimSource, False),
                      (ListSource, False)):
        assert cls.live is live and cls.dropped == 0, cls
    assert isinstance(ListSource([]), FrameSource)
    assert not isinstance(ListSource([]), LiveSource)
    cam = FakeCamera([np.zeros((4, 4), np.uint8)])
    with CameraSource("fake", open_capture=cam.open) as src:
        assert isinstance(src, LiveSource)
