"""The exposure assistant: sweep a camera's manual exposure and gain, keep the best.

Every setting of the sweep (exposures x gains) is opened as a frame source (a live
camera with that manual exposure and gain, or the simulator's camera model), its first
``settle`` frames are skipped (the driver applies a setting a few frames late) and the
next ``frames`` are scored by what the method needs:

* **lights** (spot lights): the spots' contrast ``peak - background`` (grey levels;
  peak: the brightest 3x3 mean, background: the frame's median) over the sensor noise,
  refused when more than ``MAX_SATURATED`` of the spot pixels (brighter than half-way
  from background to peak) are saturated (>= 254: bloom, the centre lost);
* **corridor** (and the block method): the edge contrast: the median gradient
  magnitude (Sobel, grey levels per px) of the strongest ``EDGE_SHARE`` of pixels
  over the noise, refused when more than ``MAX_SATURATED`` of those edge pixels touch
  a saturated pixel (a lamp clipped: its edge is no longer where it is).

The noise is estimated from the frame itself (median absolute response of a
second-difference kernel, which edges barely move), at least ``NOISE_FLOOR`` grey
levels. A frame too dark to hold a spot or an edge scores low by itself. The best
setting is the admissible one with the highest median score over its frames; ties go
to the lower gain (less noise for the same signal).

Example::

    result = sweep(lambda e, g: open_source("/dev/video0", exposure=e, gain=g),
                   "lights", exposures=(25, 50, 100, 200), gains=(0, 6))
    print(result.table())
    write_capture(result, "capture.yaml")      # ceilrun --capture capture.yaml
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.capture import CaptureFile, save_capture
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.sources import FrameSource

METHODS = ("lights", "corridor", "block")
SATURATED = 254            # grey level counted as clipped
MAX_SATURATED = 0.05       # share of spot / edge pixels that may be clipped
EDGE_SHARE = 0.02          # the strongest share of gradient pixels that are "edges"
NOISE_FLOOR = 0.5          # grey levels: quantisation and a flat, noise-free render
DEFAULT_EXPOSURES = (12.5, 25.0, 50.0, 100.0, 200.0, 400.0)   # V4L2 units of 100 us
DEFAULT_GAINS = (0.0, 6.0, 12.0)                               # dB


@dataclass(frozen=True)
class Score:
    """One frame's score: ``value`` (contrast over noise, 0 when refused), the
    ``contrast`` (grey levels, or grey levels per px for edges), ``noise`` (grey
    levels), the ``saturated`` share and ``reason`` (empty, ``saturated`` or ``dark``)."""

    value: float
    contrast: float
    noise: float
    saturated: float
    reason: str = ""


@dataclass(frozen=True)
class Setting:
    """A setting of the sweep with its median score over its frames."""

    exposure: float
    gain: float
    score: Score


@dataclass(frozen=True)
class ExposureResult:
    """The sweep: every setting in order and the best one (None: none admissible)."""

    method: str
    settings: tuple[Setting, ...]
    best: Setting | None

    def table(self) -> str:
        """A text table of the sweep, the best setting marked ``*``."""
        unit = "grey levels" if self.method == "lights" else "grey levels per px"
        lines = [f"exposure sweep for {self.method}: score = contrast ({unit}) / noise "
                 f"(grey levels); * the best",
                 f"  {'exposure':>9} {'gain':>6} {'score':>8} {'contrast':>9} "
                 f"{'noise':>6} {'clipped':>8}"]
        for s in self.settings:
            mark = "*" if s is self.best else " "
            why = f"  {s.score.reason}" if s.score.reason else ""
            lines.append(f"{mark} {s.exposure:>9g} {s.gain:>6g} {s.score.value:>8.2f} "
                         f"{s.score.contrast:>9.1f} {s.score.noise:>6.2f} "
                         f"{100 * s.score.saturated:>7.1f}%{why}")
        return "\n".join(lines)


def noise_sigma(grey: np.ndarray) -> float:
    """The sensor noise of ``grey`` (grey levels): 1.4826 median |r| / 6 of the
    response r to the kernel [[1,-2,1],[-2,4,-2],[1,-2,1]] (norm 6; flat areas and
    straight edges give no response), at least :data:`NOISE_FLOOR`."""
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(grey.astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT)
    unclipped = (grey > 0) & (grey < SATURATED)
    vals = np.abs(r[unclipped]) if np.count_nonzero(unclipped) > grey.size // 10 else np.abs(r)
    return max(NOISE_FLOOR, 1.4826 * float(np.median(vals)) / 6.0)


def _flat_reason(grey: np.ndarray) -> str:
    """Why a frame holds no contrast: ``saturated`` when most of it is clipped, else
    ``dark``."""
    return "saturated" if np.mean(grey >= SATURATED) > 0.5 else "dark"


def score_lights(image: np.ndarray) -> Score:
    """The spots' contrast over noise (see the module docstring)."""
    grey = to_grey(image)
    noise = noise_sigma(grey)
    smooth = cv2.blur(grey.astype(np.float32), (3, 3))
    bg = float(np.median(grey))
    peak = float(smooth.max())
    contrast = peak - bg
    if contrast < 5 * noise:
        return Score(0.0, contrast, noise, 0.0, _flat_reason(grey))
    spot = smooth > bg + 0.5 * contrast
    sat = float(np.mean(grey[spot] >= SATURATED)) if spot.any() else 0.0
    if sat > MAX_SATURATED:
        return Score(0.0, contrast, noise, sat, "saturated")
    return Score(contrast / noise, contrast, noise, sat)


def score_edges(image: np.ndarray) -> Score:
    """The lamp (and seam) edges' contrast over noise (see the module docstring)."""
    grey = to_grey(image)
    noise = noise_sigma(grey)
    f = grey.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0     # grey levels per px
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.hypot(gx, gy)
    cut = float(np.quantile(mag, 1.0 - EDGE_SHARE))
    edge = mag >= max(cut, 1e-6)
    contrast = float(np.median(mag[edge])) if edge.any() else 0.0
    if contrast < 2 * noise:
        return Score(0.0, contrast, noise, 0.0, _flat_reason(grey))
    clipped = cv2.dilate((grey >= SATURATED).astype(np.uint8), np.ones((3, 3), np.uint8))
    sat = float(np.mean(clipped[edge] > 0))
    if sat > MAX_SATURATED:
        return Score(0.0, contrast, noise, sat, "saturated")
    return Score(contrast / noise, contrast, noise, sat)


SCORERS: dict[str, Callable[[np.ndarray], Score]] = {
    "lights": score_lights, "corridor": score_edges, "block": score_edges}


def _median_score(scores: Sequence[Score]) -> Score:
    """The frame whose value is the median (the lower middle one for an even count)."""
    order = sorted(scores, key=lambda s: s.value)
    return order[(len(order) - 1) // 2]


def score_setting(source: FrameSource, method: str, settle: int = 3, frames: int = 3
                  ) -> Score:
    """The median :class:`Score` of ``frames`` frames of ``source`` after ``settle``.

    Raises:
        CalibrationError: the source ended before a frame was scored.
    """
    scorer = SCORERS[method]
    scores: list[Score] = []
    with source:
        for k in range(settle + frames):
            frame = source.read()
            if frame is None:
                break
            if k >= settle:
                scores.append(scorer(frame.image))
    if not scores:
        raise CalibrationError(f"the camera gave fewer than {settle + 1} frames at one "
                               f"setting: nothing to score")
    return _median_score(scores)


def check_sweep(method: str, exposures: Sequence[float], gains: Sequence[float]) -> None:
    """Raise ConfigError (key ``method``, ``exposures`` or ``gains``) on a bad sweep."""
    if method not in METHODS:
        raise ConfigError(None, "method", f"expected one of {', '.join(METHODS)}, "
                          f"found {method!r}")
    if not exposures or not all(math.isfinite(e) and e > 0 for e in exposures):
        raise ConfigError(None, "exposures", f"expected positive exposures, found "
                          f"{list(exposures)}")
    if not gains or not all(math.isfinite(g) for g in gains):
        raise ConfigError(None, "gains", f"expected finite gains, found {list(gains)}")


def sweep(open_at: Callable[[float, float], FrameSource], method: str,
          exposures: Sequence[float] = DEFAULT_EXPOSURES,
          gains: Sequence[float] = DEFAULT_GAINS, settle: int = 3, frames: int = 3,
          progress: Callable[[Setting], None] | None = None) -> ExposureResult:
    """Score every ``(exposure, gain)`` for ``method`` and pick the best.

    Args:
        open_at: opens the camera at a manual exposure (driver units) and gain (dB).
        method: ``lights``, ``corridor`` or ``block``.
        exposures, gains: the values to sweep (every pair).
        settle, frames: frames skipped, then scored, per setting.
        progress: called with each scored setting.

    Returns:
        :class:`ExposureResult`; ``best`` is None when every setting was refused.

    Raises:
        ConfigError: a bad method or sweep. CaptureError: the camera cannot be opened.
    """
    check_sweep(method, exposures, gains)
    out: list[Setting] = []
    for g in gains:
        for e in exposures:
            s = Setting(float(e), float(g), score_setting(open_at(float(e), float(g)), method,
                                                          settle, frames))
            out.append(s)
            if progress is not None:
                progress(s)
    ok = [s for s in out if not s.score.reason]
    best = max(ok, key=lambda s: (s.score.value, -s.gain)) if ok else None
    return ExposureResult(method, tuple(out), best)


def write_capture(result: ExposureResult, path: str | Path, command: str = "") -> Path:
    """Write the best setting as a capture file (``exposure``, ``gain``) that ``ceilrun
    --capture`` reads, the sweep's table in its header; atomic.

    Raises:
        CalibrationError: no setting was admissible (nothing is written).
    """
    if result.best is None:
        raise CalibrationError(f"no setting of the sweep suits {result.method}: every one "
                               f"was too dark or saturated (widen --exposures/--gains)")
    header = [f"written by {command}" if command else "written by ceilcal exposure",
              *result.table().splitlines()]
    return save_capture(CaptureFile(result.best.exposure, result.best.gain), path, header)


@dataclass(frozen=True)
class ExposureRun:
    """What ``ceilcal exposure`` did: the sweep, its best setting and the capture file
    written."""

    result: ExposureResult
    best: Setting
    out: Path

    def lines(self) -> list[str]:
        best = self.best
        return [*self.result.table().splitlines(),
                f"best for {self.result.method}: exposure {best.exposure:g}, gain "
                f"{best.gain:g}; written to {self.out} (ceilrun --capture {self.out})"]


def method_for_site(site: Site) -> str:
    """The method a site is scored for: ``block`` when it has blocks, else ``corridor``
    when it has corridor lines or lamps, else ``lights``; ConfigError keyed ``method``
    otherwise (block and corridor are both scored by their edges)."""
    if site.has_section("blocks"):
        return "block"
    if site.has_section("corridor") or site.has_section("lamps"):
        return "corridor"
    if site.has_lights:
        return "lights"
    raise ConfigError(getattr(site, "source", None), "method", "the site has no corridor, "
                      "lamps, lights or blocks: give --method")


def assist(device: str, out: str | Path, method: str | None = None,
           rig: Path | None = None, site: Path | None = None,
           exposures: Sequence[float] = DEFAULT_EXPOSURES,
           gains: Sequence[float] = DEFAULT_GAINS, settle: int = 3, frames: int = 3,
           size: tuple[int, int, float, str] = (0, 0, 0.0, ""),
           progress: Callable[[Setting], None] | None = None,
           command: str = "", force: bool = False) -> ExposureRun:
    """``ceilcal exposure``: sweep ``device`` (``/dev/videoN``, an index, or ``sim:NAME``
    whose camera follows the simulator's exposure model) and write the best setting.

    ``method`` defaults to the site's (:func:`method_for_site`; a ``sim:`` device
    defaults to its example's rig and site). ``size``: the capture's width, height,
    fps and fourcc (0, "": the driver's default), as ``ceilrun`` requests them.
    ``force``: replace an existing ``out`` (refused otherwise, before the sweep).

    Raises:
        ConfigError: a bad sweep or method, or no method and no site; ``out`` exists
            (without ``force``) or is an input.
        CaptureError: the camera cannot be opened.
        CalibrationError: no setting suits the method (nothing is written).
    """
    from ceilkit.runtime.devices import open_source, packaged_config
    from ceilkit.runtime.io.outputs import claimed

    with claimed({"out": [Path(out)]}, force=force,  # locked until written
                 inputs=[Path(p) for p in (rig, site) if p is not None]):
        rig_obj = site_obj = None
        if device.startswith("sim"):
            example = packaged_config(device.partition(":")[2] or "corridor")
            rig_obj = Rig.load(rig or example / "rig.yaml")
            site_obj = Site.load(site or example / "site.yaml")
        elif site is not None:
            site_obj = Site.load(site)
        if method is None:
            if site_obj is None:
                raise ConfigError(None, "method", "give --method (lights, corridor or block) or "
                                  "--site")
            method = method_for_site(site_obj)
        check_sweep(method, exposures, gains)
        if settle < 0 or frames < 1:
            raise ConfigError(None, "frames", f"expected settle >= 0 and frames >= 1, found "
                              f"{settle} and {frames}")
        width, height, fps, fourcc = size

        def open_at(e: float, g: float) -> FrameSource:
            return open_source(device, rig_obj, site_obj, width, height, fps, fourcc,
                               exposure=e, gain=g, frames=settle + frames)

        result = sweep(open_at, method, exposures, gains, settle, frames, progress)
        path = write_capture(result, out, command)
        return ExposureRun(result, result.best, path)  # type: ignore[arg-type]


__all__ = ["DEFAULT_EXPOSURES", "DEFAULT_GAINS", "METHODS", "SCORERS", "ExposureResult",
           "ExposureRun", "assist", "method_for_site",
           "Score", "Setting", "check_sweep", "noise_sigma", "score_edges", "score_lights",
           "score_setting", "sweep", "write_capture"]
