"""Frame sources at the edge: cameras, video files and image folders.

:func:`ceilkit.runtime.devices.open_source` turns a ``--device`` value into one of
these, a recording or the simulator:

* ``/dev/videoN`` or a camera index (``0``): a live camera through OpenCV (V4L2),
  with size, rate, pixel format and manual exposure/gain; frames stamped at grab
  with ``time.monotonic_ns``; a background grabber keeps only the latest frame
  (a slow estimator never works on stale frames; the skipped ones are counted);
  a camera that vanishes is reopened with back-off while the run goes on.
* a video file: read in order (nothing dropped), stamped from its frame times.
* a folder holding ``frames.csv``: a SPEC recording; any other folder: its
  images in name order.
* ``sim:`` or ``sim:NAME``: the simulator driving along a corridor (NAME is a
  packaged example: ``corridor``, ``lights``, ``block``; default ``corridor``).

Each source declares ``live`` (its stamps are on ``time.monotonic_ns``) and
``dropped`` (frames skipped by the latest-frame policy), as
:class:`~ceilkit.runtime.io.sources.FrameSource` asks; :class:`CameraSource` is a
:class:`~ceilkit.runtime.io.sources.LiveSource`.

:func:`open_video` opens only a camera or a video file (what a calibration tool
needs); :class:`FakeCamera` is a ``cv2.VideoCapture``-like fake device that serves
given images at a fixed rate and can be unplugged and re-plugged (tests, benchmarks).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.errors import CaptureError
from ceilkit.runtime.io.images import read_image
from ceilkit.runtime.io.sources import Frame, SourceBase

log = logging.getLogger("ceilkit.capture")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (by suffix, :data:`IMAGE_SUFFIXES`), in name order."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".mjpg", ".mjpeg")


class ImageFolderSource(SourceBase):
    """Images of a folder in name order, stamped ``index / fps`` seconds; a file that
    is no whole image (a truncated JPEG) is a damaged frame naming it
    (:meth:`Frame.damaged <ceilkit.runtime.io.sources.Frame.damaged>`), not an error."""

    live = False
    dropped = 0

    def __init__(self, folder: str | Path, fps: float = 30.0):
        self.folder = Path(folder)
        self.files = list_images(self.folder)
        if not self.files:
            raise CaptureError(f"{self.folder}: no images found "
                               f"({', '.join(IMAGE_SUFFIXES)})")
        self.fps = fps
        self._i = 0

    def read(self) -> Frame | None:
        if self._i >= len(self.files):
            return None
        path = self.files[self._i]
        image, damage = read_image(path)
        t_ns = int(round(self._i * 1e9 / self.fps))
        f = Frame(image, t_ns, self._i) if image is not None else \
            Frame.damaged(damage, t_ns, self._i)
        self._i += 1
        return f


class VideoFileSource(SourceBase):
    """A video file read frame by frame, stamped from the container's frame times."""

    live = False
    dropped = 0

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.cap = cv2.VideoCapture(str(self.path))
        if not self.cap.isOpened():
            raise CaptureError(f"{self.path}: cannot open the video")
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or 30.0
        self._i = 0

    def read(self) -> Frame | None:
        ok, image = self.cap.read()
        if not ok:
            return None
        f = Frame(image, int(round(self._i * 1e9 / self.fps)), self._i)
        self._i += 1
        return f

    def close(self) -> None:
        self.cap.release()


class CameraSource(SourceBase):
    """A live camera with a latest-frame grabber thread and reopen-with-back-off.

    Args:
        device: ``/dev/videoN`` or an index.
        width, height, fps: requested capture format (0: the driver's default).
        fourcc: pixel format such as ``MJPG`` or ``YUYV`` (empty: default).
        exposure: manual exposure in the driver's units (auto-exposure is turned off);
            ``None`` leaves exposure alone.
        gain: manual gain, or ``None``.
        open_capture: how to open the device (a fake in tests).
    """

    live = True
    dropped = 0  # counted per instance by the grabber

    def __init__(self, device: str | int, width: int = 0, height: int = 0, fps: float = 0,
                 fourcc: str = "", exposure: float | None = None, gain: float | None = None,
                 open_capture: Callable[[str | int], object] | None = None,
                 clock: Callable[[], int] = time.monotonic_ns,
                 max_backoff_s: float = 2.0):
        self.device = device
        self.settings = (width, height, fps, fourcc, exposure, gain)
        self._open_capture = open_capture or self._open_v4l2
        self.clock = clock
        self.max_backoff_s = max_backoff_s
        self.dropped = 0
        self.reopens = 0
        self.losses = 0
        self.status = "starting"
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._taken = -1
        self._stop = threading.Event()
        self._cap = self._open_or_fail()
        self._thread = threading.Thread(target=self._grab_loop, name="ceilkit-grab",
                                        daemon=True)
        self._thread.start()

    def _open_v4l2(self, device: str | int) -> object:
        width, height, fps, fourcc, exposure, gain = self.settings
        api = cv2.CAP_V4L2 if isinstance(device, str) and device.startswith("/dev/") \
            else cv2.CAP_ANY
        cap = cv2.VideoCapture(device, api)
        if not cap.isOpened():
            return cap
        if fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc[:4].ljust(4)))
        if width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if exposure is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
            cap.set(cv2.CAP_PROP_EXPOSURE, exposure)
        if gain is not None:
            cap.set(cv2.CAP_PROP_GAIN, gain)
        return cap

    def _open_or_fail(self):
        cap = self._try_open()
        if cap is None or not cap.isOpened():
            raise CaptureError(f"{self.device}: cannot open the camera "
                               "(is it plugged in, and not used by another program?)")
        self.status = "running"
        return cap

    def _try_open(self):
        try:
            return self._open_capture(self.device)
        except Exception as exc:  # noqa: BLE001 - a driver may raise instead of failing
            log.debug("camera %s: open failed: %s", self.device, exc)
            return None

    def _grab_loop(self) -> None:
        index = 0
        backoff = 0.1
        while not self._stop.is_set():
            try:
                ok, image = self._cap.read() if self._cap is not None else (False, None)
            except Exception:  # noqa: BLE001 - a vanished device may raise
                ok, image = False, None
            t_ns = self.clock()
            if ok and image is not None:
                if self.status != "running":
                    self.status = "running"
                    self.reopens += 1
                    log.warning("camera %s back (reopened)", self.device)
                backoff = 0.1
                with self._cond:
                    if self._latest is not None and self._latest.index != self._taken:
                        self.dropped += 1  # never read: a newer frame replaces it
                    self._latest = Frame(image, t_ns, index)
                    self._cond.notify_all()
                index += 1
                continue
            # the camera vanished: reopen with back-off, the run goes on
            if self.status == "running":
                self.status = "lost"
                self.losses += 1
                log.warning("camera %s lost; reopening with back-off", self.device)
            if self._cap is not None:
                try:
                    self._cap.release()
                except Exception:  # noqa: BLE001 - a driver may fail on release
                    pass
            if self._stop.wait(backoff):
                break
            backoff = min(2 * backoff, self.max_backoff_s)
            cap = self._try_open()
            self._cap = cap if cap is not None and cap.isOpened() else None

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called (no frame will come any more)."""
        return self._stop.is_set()

    def wait_frame(self, timeout_s: float) -> Frame | None:
        """The newest frame not yet returned, waiting at most ``timeout_s``.

        Returns ``None`` when none came in time (the camera may be lost and being
        reopened: see ``status``) or the source is closed; never raises.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._stop.is_set():
                if self._latest is not None and self._latest.index != self._taken:
                    self._taken = self._latest.index
                    return self._latest
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(min(left, 0.1))
        return None

    def read(self, timeout_s: float = 5.0) -> Frame | None:
        """The newest frame not yet returned; waits for one. ``None`` once closed.

        Raises:
            CaptureError: no frame for ``timeout_s`` (the live loop uses
                :meth:`wait_frame` instead and keeps running while the camera is lost).
        """
        frame = self.wait_frame(timeout_s)
        if frame is None and not self.closed:
            raise CaptureError(f"{self.device}: no frame for {timeout_s:g} s "
                               f"(camera {self.status})")
        return frame

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout=2.0)
        if self._cap is not None:
            try:
                self._cap.release()
            except Exception:  # noqa: BLE001
                pass


def open_video(device: str | int, width: int = 0, height: int = 0, fps: float = 0,
               fourcc: str = "", exposure: float | None = None,
               gain: float | None = None) -> SourceBase:
    """A camera (``/dev/videoN``, an index, ``"0"``) or a video file, nothing else.

    Cameras get :class:`CameraSource` (stamped at grab, latest-frame policy, reopened
    with back-off); files get :class:`VideoFileSource` (every frame, in order).

    Raises:
        CaptureError: no such file, not a video, or a camera that cannot be opened.
    """
    if isinstance(device, int) or str(device).isdigit():
        return CameraSource(int(device), width, height, fps, fourcc, exposure, gain)
    spec = str(device)
    if spec.startswith("/dev/"):
        return CameraSource(spec, width, height, fps, fourcc, exposure, gain)
    path = Path(spec)
    if not path.is_file():
        raise CaptureError(f"{spec}: no such video file")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise CaptureError(f"{spec}: not a video ({', '.join(VIDEO_SUFFIXES)})")
    return VideoFileSource(path)


class FakeCamera:
    """A fake camera device: ``open`` gives a ``cv2.VideoCapture``-like object.

    The capture serves ``images`` in a loop at ``fps`` (``read()`` sleeps until the
    next frame is due, as a driver blocks until the sensor delivers), so
    ``CameraSource(dev, open_capture=cam.open)`` runs its real grabber, stamping and
    latest-frame policy on it. :meth:`unplug` makes reads and opens fail (the USB
    cable pulled) until :meth:`replug`.

    Args:
        images: the frames, ``(H, W)`` or ``(H, W, 3)`` uint8, served in order, looping.
        fps: delivery rate (frames per second).
    """

    def __init__(self, images: list[np.ndarray], fps: float = 30.0):
        if not images:
            raise CaptureError("FakeCamera needs at least one image")
        if fps <= 0:
            raise CaptureError(f"FakeCamera: fps must be > 0, found {fps}")
        self.images = list(images)
        self.period_s = 1.0 / fps
        self.plugged = True
        self.opens = 0
        self.served = 0

    def open(self, device: str | int = 0) -> _FakeCapture:
        self.opens += 1
        return _FakeCapture(self)

    def unplug(self) -> None:
        self.plugged = False

    def replug(self) -> None:
        self.plugged = True


class _FakeCapture:
    def __init__(self, cam: FakeCamera):
        self.cam = cam
        self.opened = cam.plugged
        self._due = time.monotonic()

    def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
        return self.opened

    def read(self) -> tuple[bool, np.ndarray | None]:
        cam = self.cam
        if not (self.opened and cam.plugged):
            self.opened = False
            return False, None
        self._due += cam.period_s
        wait = self._due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        else:
            self._due = time.monotonic()  # late: do not burst to catch up
        if not cam.plugged:
            self.opened = False
            return False, None
        image = cam.images[cam.served % len(cam.images)]
        cam.served += 1
        return True, image

    def release(self) -> None:
        self.opened = False
