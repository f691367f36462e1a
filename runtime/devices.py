"""A ``--device`` value to a frame source: the one place that knows every kind.

* ``/dev/videoN`` or a camera index (``0``): a live camera
  (:class:`~ceilkit.runtime.io.capture.CameraSource`);
* a video file: :class:`~ceilkit.runtime.io.capture.VideoFileSource`;
* a folder holding ``frames.csv``: a SPEC recording
  (:class:`~ceilkit.runtime.io.recording.Recording`); any other folder: its images in
  name order (:class:`~ceilkit.runtime.io.capture.ImageFolderSource`);
* ``sim:`` or ``sim:NAME``: the simulator driving along a corridor (NAME is a packaged
  example: ``corridor``, ``lights``, ``block``; default ``corridor``).

This sits above ``io`` and ``sim`` so that neither needs the other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ceilkit.runtime.errors import CaptureError
from ceilkit.runtime.io.capture import (
    VIDEO_SUFFIXES,
    CameraSource,
    ImageFolderSource,
    VideoFileSource,
)
from ceilkit.runtime.io.sources import FrameSource


def packaged_config(name: str) -> Path:
    """The folder of a packaged example (``corridor``, ``lights``, ``block``)."""
    from importlib.resources import files

    root = Path(str(files("ceilkit.configs")))
    path = root / name
    if not (path / "rig.yaml").exists():
        choices = sorted(p.name for p in root.iterdir() if (p / "rig.yaml").exists())
        raise CaptureError(f"sim:{name}: no such example (choose from {', '.join(choices)})")
    return path


def open_source(spec: str, rig=None, site=None, width: int = 0, height: int = 0,
                fps: float = 0, fourcc: str = "", exposure: float | None = None,
                gain: float | None = None, frames: int = 300, seed: int = 0) -> FrameSource:
    """Open a ``--device`` value (see the module docstring)."""
    if spec.startswith("sim:") or spec == "sim":
        from ceilkit.runtime.sim.render import SimSource, straight_drive

        if rig is None or site is None:
            raise CaptureError("sim: needs a rig and a site")
        traj = straight_drive(frames, fps=fps or 30.0, speed_mps=0.8, y_m=0.1,
                              weave_m=0.15, yaw_wobble_rad=np.radians(4.0),
                              rng=np.random.default_rng(seed))
        return SimSource(rig, site, traj, seed=seed)
    if spec.isdigit():
        return CameraSource(int(spec), width, height, fps, fourcc, exposure, gain)
    if spec.startswith("/dev/"):
        return CameraSource(spec, width, height, fps, fourcc, exposure, gain)
    path = Path(spec)
    if path.is_dir():
        if (path / "frames.csv").exists():
            from ceilkit.runtime.io.recording import Recording

            return Recording(path, rig=rig, site=site)
        return ImageFolderSource(path, fps or 30.0)
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        return VideoFileSource(path)
    if path.exists():
        raise CaptureError(f"{spec}: not a camera, video ({', '.join(VIDEO_SUFFIXES)}), "
                           "image folder or recording")
    raise CaptureError(f"{spec}: no such device or file")
