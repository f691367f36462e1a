"""A ``--device`` value to a frame source: the one place that knows every kind.

* ``/dev/videoN`` or a camera index (``0``): a live camera
  (:class:`~ceilkit.runtime.io.capture.CameraSource`);
* a video file: :class:`~ceilkit.runtime.io.capture.VideoFileSource`;
* a folder holding ``frames.csv``: a SPEC recording
  (:class:`~ceilkit.runtime.io.recording.Recording`); any other folder: its images in
  name order (:class:`~ceilkit.runtime.io.capture.ImageFolderSource`);
* ``sim:`` or ``sim:NAME``: the simulator driving along a corridor (NAME is a packaged
  example: ``corridor``, ``lights``, ``block``, ``office``; default ``corridor``;
  the ``scene.yaml`` beside the site, if any, adds its scatter:
  :mod:`ceilkit.runtime.sim.scatter_file`), with realism knobs after a ``?``:
  ``sim:corridor?preset=realistic&motion_blur_ms=8`` (``preset`` names a preset of
  the ``presets.yaml`` beside the site, then each ``KNOB=VALUE`` sets one
  :class:`~ceilkit.runtime.sim.realism.Realism` field; ``&`` or ``,`` between them).
  ``exposure`` and ``gain`` act as on a camera (see :func:`sim_camera_options`).

This sits above ``io`` and ``sim`` so that neither needs the other.
"""

from __future__ import annotations

import math
from collections.abc import Callable
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
    path = root / name.partition("?")[0]
    if not (path / "rig.yaml").exists():
        choices = sorted(p.name for p in root.iterdir() if (p / "rig.yaml").exists())
        raise CaptureError(f"sim:{name}: no such example (choose from {', '.join(choices)})")
    return path


def open_source(spec: str, rig=None, site=None, width: int = 0, height: int = 0,
                fps: float = 0, fourcc: str = "", exposure: float | None = None,
                gain: float | None = None, frames: int = 300, seed: int = 0,
                pace: Callable[[float], object] | None = None) -> FrameSource:
    """Open a ``--device`` value (see the module docstring).

    ``sim``: ``frames`` frames of a weaving drive at 0.8 m/s along +x from the origin,
    shuttling back and forth (:func:`~ceilkit.runtime.sim.render.straight_drive`'s
    ``length_m``) within the site's features, less :data:`SIM_END_MARGIN_M`, when a
    straight drive would leave them; ``pace``: the frames come at their stamps' pace
    (:class:`~ceilkit.runtime.sim.render.SimSource`), else as fast as they render."""
    if spec.startswith("sim:") or spec == "sim" or spec.startswith("sim?"):
        from ceilkit.runtime.sim.render import SimOptions, SimSource, straight_drive
        from ceilkit.runtime.sim.scatter_file import scene_beside

        if rig is None or site is None:
            raise CaptureError("sim: needs a rig and a site")
        realism = sim_realism(spec, site)
        options = SimOptions()
        if exposure is not None or gain is not None:
            options, realism = sim_camera_options(exposure, gain, realism)
        scatter = scene_beside(site)
        options = options.replace(scatter=scatter)
        traj = straight_drive(frames, fps=fps or 30.0, speed_mps=0.8, y_m=0.1,
                              weave_m=0.15, yaw_wobble_rad=np.radians(4.0),
                              rng=np.random.default_rng(seed),
                              length_m=sim_length_m(site, scatter))
        return SimSource(rig, site, traj, options, seed=seed, realism=realism, pace=pace)
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


SIM_END_MARGIN_M = 1.0
"""How far short of the site's last feature along +x a simulated drive turns back."""


def sim_length_m(site, scatter=None) -> float | None:
    """How far a simulated drive from x = 0 may go along +x and stay on ``site``'s
    features (their extent less :data:`SIM_END_MARGIN_M`); where the site does not
    bound x (a corridor of lines alone), on the ``scatter``'s items
    (:class:`~ceilkit.runtime.sim.scatter.Scatter`, a scene file's), else ``None``."""
    from ceilkit.runtime.estimators.honesty import SiteExtent

    x_hi = SiteExtent.from_site(site).x_hi - SIM_END_MARGIN_M
    if not math.isfinite(x_hi) and scatter is not None and scatter.x_range_m():
        x_hi = scatter.x_range_m()[1] - SIM_END_MARGIN_M
    return x_hi if math.isfinite(x_hi) and x_hi > SIM_END_MARGIN_M else None


SIM_EXPOSURE_REF = 100.0
"""The simulated camera's exposure (driver units of 100 µs, as V4L2's
``exposure_absolute``) at which it renders the nominal radiance: 10 ms."""


def sim_realism(spec: str, site=None):
    """The :class:`~ceilkit.runtime.sim.realism.Realism` a ``sim:NAME?...`` value asks
    for (None: no query). ``preset=NAME`` is looked up beside the site's file (or the
    packaged example's). Raises ConfigError keyed ``device`` on a bad query."""
    from ceilkit.runtime.errors import ConfigError
    from ceilkit.runtime.sim.realism import Realism, load_preset, parse_knobs

    head, q, query = spec.partition("?")
    if not q:
        return None
    pairs = [p for p in query.replace("&", ",").split(",") if p.strip()]
    base = Realism()
    knobs = []
    for pair in pairs:
        name, eq, value = (p.strip() for p in pair.partition("="))
        if name == "preset" and eq:
            site_file = getattr(site, "source", None)
            if site_file is None or not Path(site_file).exists():
                site_file = packaged_config(head.partition(":")[2] or "corridor") / "site.yaml"
            base = load_preset(site_file, value)
        else:
            knobs.append(pair)
    try:
        return parse_knobs(knobs, base, key="device")
    except ConfigError as exc:
        raise ConfigError(None, "device", f"{spec}: {exc.detail}") from None


def sim_camera_options(exposure: float | None, gain: float | None, realism=None):
    """What a camera's manual ``exposure`` (driver units of 100 µs) and ``gain`` (dB)
    do to the simulated one: radiance times ``exposure / SIM_EXPOSURE_REF`` and
    ``10^(gain/20)``; sensor noise ``2 * sqrt((g^2 + scale) / 2)`` grey levels (read
    noise amplified by the gain g, photon noise growing with the signal; 2 at the
    nominal setting); motion blur over the exposure time.

    Returns ``(SimOptions, Realism)``.
    """
    import math

    from ceilkit.runtime.errors import ConfigError
    from ceilkit.runtime.sim.realism import Realism
    from ceilkit.runtime.sim.render import SimOptions

    e = SIM_EXPOSURE_REF if exposure is None else float(exposure)
    g_db = 0.0 if gain is None else float(gain)
    if not (math.isfinite(e) and e > 0):
        raise ConfigError(None, "exposure", f"expected a positive exposure, found {exposure!r}")
    if not (math.isfinite(g_db) and -20.0 <= g_db <= 48.0):
        raise ConfigError(None, "gain", f"expected a gain in -20..48 dB, found {gain!r}")
    g = 10.0 ** (g_db / 20.0)
    scale = e / SIM_EXPOSURE_REF * g
    noise = 2.0 * math.sqrt(0.5 * (g * g + scale))     # read noise, photon noise
    real = (realism or Realism()).replace(motion_blur_ms=e / 10.0)
    return SimOptions(exposure=scale, noise_sigma=noise), real
