"""The estimator contract, and what an estimator returns for one frame.

An estimator is a subclass of :class:`Estimator` with a ``name``, an ``Options``
frozen dataclass (every field a user can set, ``--option KEY=VALUE`` on the CLI), the
site sections it needs, and a ``_estimate(grey, t_ns, prior, t0)`` that the shared
:meth:`Estimator.estimate` calls after the shared frame check and grey conversion.

A frame on which a method cannot estimate is a value, not an exception: a
:class:`Failure` is falsy and carries a short machine reason (counted by the
runtime, one of :data:`FAILURE_REASONS`) and a human detail.

Example::

    est = CorridorEstimator(rig, site, CorridorOptions(detector="lsd"))
    pose = est.estimate(frame.image, frame.t_ns, prior=None)   # PoseEstimate | Failure
    if not pose:
        print(pose.reason, pose.detail)

Convention: the pose is the vehicle's in W (SPEC §1): ``x_m, y_m`` metres,
``yaw_rad`` counter-clockwise from +x. A coordinate the method cannot observe is
``None`` (the corridor method does not observe x).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import sys
import time
import types
import typing
import warnings
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.honesty import MODEL_REASONS
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.jit import arr, njit, warmer


def _empty() -> Mapping[str, Any]:
    return MappingProxyType({})


@dataclass(frozen=True, eq=False)
class PlaneIncrement:
    """The vehicle's motion measured by the camera between two frames (ceiling-plane
    odometry), carried by an estimate (pose or Failure) as its ``increment``.

    Attributes:
        t0_ns: the earlier frame's capture time (the estimate's ``t_ns`` is the later's).
        dx_m, dy_m, dyaw_rad: the motion in V at ``t0_ns`` (forward, left, CCW).
        cov: its ``(3, 3)`` covariance (dx, dy, dyaw).
    """

    t0_ns: int
    dx_m: float
    dy_m: float
    dyaw_rad: float
    cov: np.ndarray


class Provenance(enum.Enum):
    """How an estimate's pose was singled out (typed: modules never read it from
    ``diagnostics``).

    * ``GLOBAL``: by this frame alone, with no help from a prior: the frame rules out
      every other pose (relocalization evidence);
    * ``PRIOR``: the frame supports several poses (``hypotheses``) and the prior chose
      the only one inside its region (:mod:`~ceilkit.runtime.estimators.prior`): right
      only if the prior is;
    * ``WINDOW``: a local search about the prior (the tracked fast path);
    * ``TRACK``: a track's (tracker's or fusion's) output, from several frames.
    """

    GLOBAL = "global"
    PRIOR = "prior"
    WINDOW = "window"
    TRACK = "track"


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """One vehicle pose a frame supports (SPEC §1: metres, radians, W).

    Attributes:
        x_m, y_m: position, ``None`` where unobserved (the corridor method's x).
        yaw_rad: heading.
        cov: ``(3, 3)`` covariance of ``(x, y, yaw)``; unobserved terms inf; or None.
        weight: the hypothesis' share of the frame's likelihood, in [0, 1]: the
            hypotheses of one estimate sum to 1.
        label: what makes it a twin of the others (``half_turn``, ``shift +0.60 m``,
            ``quarter_turn``, ``cell (3.05, 0.00)``): for logs and the site check.
    """

    x_m: float | None
    y_m: float | None
    yaw_rad: float
    cov: np.ndarray | None = None
    weight: float = 1.0
    label: str = ""

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """A vehicle pose from one frame.

    Attributes:
        t_ns: capture time of the frame (integer nanoseconds).
        method: the estimator's name (``corridor``, ``paper-corridor``, ``lights``, ...).
        x_m, y_m: position in W, ``None`` where unobserved.
        yaw_rad: heading in W.
        lateral_m: signed offset left of the corridor's centre line, or ``None``.
        quality: confidence in [0, 1].
        cov: 3x3 covariance of ``(x, y, yaw)`` (m², rad²); unobserved terms are inf.
        diagnostics: method-specific figures (residuals, counts), for logs and reports
            only: no module reads another module's keys (the typed fields below carry
            what crosses a module boundary).
        velocity: ``(vx m/s, vy m/s, yaw rate rad/s)`` in W, or ``None``: what a track's
            prediction (the estimators' prior) knows of the motion; an estimator uses
            it for the rows of a rolling-shutter frame (``readout_ms``,
            :mod:`~ceilkit.runtime.geometry.shutter`). A velocity the track does not
            observe (x on the corridor method alone) is 0.
        provenance: how the pose was singled out (:class:`Provenance`).
        hypotheses: every pose the frame supports, the published one first; empty
            means the pose itself is the only one (an unambiguous fix). A pose with
            ``PRIOR`` provenance carries the twins the prior ruled out.
        cues: ``--method auto``: every method's estimate of the frame.
        increment: ceiling-plane odometry since the previous frame, or None.
        hypotheses_complete: ``hypotheses`` are every pose the frame supports (the
            method enumerated them all): a pose none of them is near is ruled out.
    """

    t_ns: int
    method: str
    x_m: float | None
    y_m: float | None
    yaw_rad: float
    quality: float
    lateral_m: float | None = None
    cov: np.ndarray | None = None
    diagnostics: Mapping[str, Any] = field(default_factory=_empty)
    velocity: tuple[float, float, float] | None = None
    provenance: Provenance = Provenance.GLOBAL
    hypotheses: tuple[Hypothesis, ...] = ()
    cues: tuple[Any, ...] = ()
    increment: PlaneIncrement | None = None
    hypotheses_complete: bool = False

    def __bool__(self) -> bool:
        return True

    @property
    def ok(self) -> bool:
        return True

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)

    @property
    def singled_out(self) -> bool:
        """Whether this frame alone ruled out every other pose (a global fix with no
        twin): what may start or move a track with no other evidence."""
        return self.provenance is Provenance.GLOBAL and len(self.hypotheses) <= 1

    def as_hypothesis(self) -> Hypothesis:
        return Hypothesis(self.x_m, self.y_m, self.yaw_rad, self.cov, 1.0)


@dataclass(frozen=True)
class Failure:
    """A frame the method could not estimate. Falsy.

    Attributes:
        reason: a short stable code (``too_few_lines``, ``blank_frame``, ``ambiguous``, ...).
        detail: one human sentence.
        hypotheses: for ``ambiguous``, the poses the frame supports equally (each with
            its covariance and weight): a multi-hypothesis fusion keeps them.
        cues, increment, hypotheses_complete: as :class:`PoseEstimate`'s.
    """

    t_ns: int
    method: str
    reason: str
    detail: str = ""
    diagnostics: Mapping[str, Any] = field(default_factory=_empty)
    hypotheses: tuple[Hypothesis, ...] = ()
    cues: tuple[Any, ...] = ()
    increment: PlaneIncrement | None = None
    hypotheses_complete: bool = False

    def __bool__(self) -> bool:
        return False

    @property
    def ok(self) -> bool:
        return False


Estimate = PoseEstimate | Failure


# -- failure reasons: stable codes, counted by the runtime and sent on the link ----------
BAD_FRAME = "bad_frame"
BLANK_FRAME = "blank_frame"
SATURATED_FRAME = "saturated_frame"
AMBIGUOUS = "ambiguous"

FAILURE_REASONS: Mapping[str, str] = MappingProxyType({
    BAD_FRAME: "the frame's size or layout is not the camera's, or its file is damaged "
               "(a truncated JPEG or PNG: the detail names the file)",
    BLANK_FRAME: "the frame has no contrast (lens cap, dark room)",
    SATURATED_FRAME: "the frame is saturated",
    AMBIGUOUS: "several poses explain the frame equally well (a symmetric layout)",
    "too_few_lines": "fewer ceiling line segments than a pose needs",
    "no_ceiling_lines": "no segment belongs to the ceiling's line families",
    "no_association": "the lines match no site line",
    "no_lights": "no light found in the frame",
    "too_few_lights": "fewer lights than a pose needs",
    "no_match": "the lights match no place of the light map",
    "no_block": "no block or marker of the site in view",
    "partial_block": "a block is only partly in view (cut by the frame's edge or occluded)",
    "unknown_marker": "the only markers in view are not in the site",
    "too_few_features": "fewer ceiling features than a pose needs (texture)",
    "no_map_match": "the ceiling features match no place of the ceiling map (texture)",
    **MODEL_REASONS,   # the model checks (estimators/honesty.py, docs/methods/honesty.md)
})
"""Every reason an estimator may give, with its meaning (docs/methods list them too)."""

SATURATED_MEAN = 250.0  # grey mean above which a flat frame is saturated, not blank


# -- options ---------------------------------------------------------------------------
def _coerce(name: str, kind: Any, value: Any) -> Any:
    """``value`` (a CLI string or a Python value) as the field type ``kind``."""
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() in ("none", "")):
            return None
        kind = args[0]
    if kind is bool:
        if isinstance(value, str):
            low = value.strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ConfigError(None, f"options.{name}", f"expected true or false, found {value!r}")
        return bool(value)
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(None, f"options.{name}",
                          f"expected {getattr(kind, '__name__', kind)}, found {value!r}") from None


@dataclass(frozen=True)
class EstimatorOptions:
    """Base of every estimator's options: a frozen dataclass of what a user may set.

    ``min_contrast`` is the grey-level spread below which a frame is blank (0: no check).
    """

    min_contrast: float = 8.0

    ALIASES: ClassVar[Mapping[str, str]] = MappingProxyType({})
    """Deprecated option names and the names that replaced them (``{old: new}``):
    still accepted by :meth:`from_mapping`, with a notice naming the new key."""

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | None = None) -> EstimatorOptions:
        """Options from ``{name: value}`` (values may be strings, as typed on a CLI); a
        deprecated name (:attr:`ALIASES`) is read as its new one.

        Raises:
            ConfigError: ``options.NAME`` for an unknown name, a value of the wrong type,
                or an option given both by its old and its new name.
        """
        values = cls.renamed(values)
        hints = typing.get_type_hints(cls)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(None, f"options.{unknown[0]}",
                              f"unknown option (expected one of {', '.join(sorted(known))})")
        return cls(**{k: _coerce(k, hints[k], v) for k, v in values.items()})

    @classmethod
    def renamed(cls, values: Mapping[str, Any] | None) -> dict[str, Any]:
        """``values`` with each deprecated name (:attr:`ALIASES`) replaced by its new
        one, the first use of each in a run noted once (a ``FutureWarning`` naming the
        new key).

        Raises:
            ConfigError: ``options.NEW`` when both the old and the new name are given.
        """
        out = dict(values or {})
        for old, new in cls.ALIASES.items():
            if old not in out:
                continue
            if new in out:
                raise ConfigError(None, f"options.{new}",
                                  f"given twice: as {new} and as its old name {old}")
            out[new] = out.pop(old)
            if old not in _NOTED:
                _NOTED.add(old)
                warnings.warn(f"option {old!r} is deprecated: use {new!r}", FutureWarning,
                              stacklevel=3)
        return out


_NOTED: set[str] = set()  # the deprecated option names already noted in this run


# -- the contract ------------------------------------------------------------------------
def check_frame(grey: np.ndarray, width: int, height: int,
                min_contrast: float) -> tuple[str, str] | None:
    """The shared frame check: ``(reason, detail)`` of a frame no method can use, or None.

    Args:
        grey: ``(H, W)`` uint8 frame (:func:`~ceilkit.runtime.features.grey.to_grey`).
        width, height: the camera's image size, px.
        min_contrast: grey spread (std of a 1-in-16 subsample) below which the frame is
            blank or saturated; 0 disables the check.
    """
    if grey.ndim != 2 or grey.shape != (height, width):
        found = "x".join(str(n) for n in grey.shape[1::-1]) if grey.ndim >= 2 else str(grey.shape)
        return BAD_FRAME, f"frame is {found}, the camera is {width}x{height}"
    if min_contrast > 0:
        mean, std = sample_stats(grey)
        if std < 0.5 * min_contrast:
            if mean >= SATURATED_MEAN:
                return SATURATED_FRAME, "the frame is saturated"
            return BLANK_FRAME, "the frame has no contrast"
    return None


def sample_stats(grey: np.ndarray) -> tuple[float, float]:
    """``(mean, std)`` of the pixels ``grey[::4, ::4]`` of a uint8 frame (the frame
    check's 1-in-16 sample; ``cv2.meanStdDev``'s numbers, from exact integer sums).

    Where the rows are whole 32-bit words (the width a multiple of 4, the buffer
    aligned, a little-endian machine), each word's low byte is the sample: read as
    words, the loop runs on contiguous memory (a quarter of the strided read's time)."""
    g = arr(grey, np.uint8)
    if g.shape[1] % 4 == 0 and g.ctypes.data % 4 == 0 and sys.byteorder == "little":
        return _word_stats(g.view(np.uint32))
    return _sample_stats(g, 4)


@njit
def _word_stats(words):  # pragma: no cover - compiled
    """:func:`_sample_stats` with step 4 of a frame read as ``(H, W / 4)`` uint32
    little-endian words: the low byte of word ``j`` is pixel ``4 j`` (the sums in 64-bit
    integers, as numba widens them)."""
    n = s = ss = 0
    for i in range(0, words.shape[0], 4):
        row = words[i]
        row_s = row_ss = np.int32(0)
        for j in range(row.shape[0]):
            v = np.int32(row[j] & np.uint32(255))
            row_s += v
            row_ss += v * v
        s += row_s
        ss += row_ss
        n += row.shape[0]
    if n == 0:
        return 0.0, 0.0
    return s / n, math.sqrt(max(n * ss - s * s, 0) / (n * n))


@njit
def _sample_stats(grey, step):  # pragma: no cover - compiled
    """``(mean, std)`` of the pixels ``grey[::step, ::step]`` (``cv2.meanStdDev``'s
    numbers: the population deviation), from exact integer sums."""
    n = s = ss = 0
    for i in range(0, grey.shape[0], step):
        row_s = row_ss = 0
        for j in range(0, grey.shape[1], step):
            v = np.int64(grey[i, j])
            row_s += v
            row_ss += v * v
        s += row_s
        ss += row_ss
        n += (grey.shape[1] + step - 1) // step
    if n == 0:
        return 0.0, 0.0
    return s / n, math.sqrt(max(n * ss - s * s, 0) / (n * n))


@warmer
def _warm() -> None:
    _sample_stats(arr(np.zeros((2, 2), np.uint8), np.uint8), 4)
    sample_stats(np.zeros((4, 4), np.uint8))


class Estimator(ABC):
    """A pose estimator: one frame (and an optional predicted pose) in, one estimate out.

    Subclasses set ``name``, ``Options`` and ``site_sections`` (the site sections it
    needs, any one of which suffices), and implement :meth:`_estimate`. Construction
    checks the rig against the site and raises :class:`~ceilkit.runtime.errors.ConfigError`;
    per frame nothing raises.
    """

    name: ClassVar[str]
    Options: ClassVar[type[EstimatorOptions]] = EstimatorOptions
    site_sections: ClassVar[tuple[str, ...]] = ()

    def __init__(self, rig: Any, site: Any,
                 options: EstimatorOptions | Mapping[str, Any] | None = None) -> None:
        if options is None or isinstance(options, Mapping):
            options = self.Options.from_mapping(options)
        elif not isinstance(options, self.Options):
            raise ConfigError(None, "options",
                              f"{self.name} takes {self.Options.__name__}, "
                              f"found {type(options).__name__}")
        if not self.supports(site):
            sections = " or ".join(f"`{s}`" for s in self.site_sections)
            raise ConfigError(site.source, self.site_sections[0] if self.site_sections else None,
                              f"method {self.name!r} needs a {sections} section in the site file")
        self.rig, self.site, self.options = rig, site, options

    @classmethod
    def supports(cls, site: Any) -> bool:
        """Whether ``site`` holds what this method needs."""
        return any(site.has_section(s) for s in cls.site_sections)

    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> Estimate:
        """The vehicle pose in W from one frame.

        Args:
            image: ``(H, W)`` grey or ``(H, W, 3)`` BGR frame as captured (uint8 or uint16).
            t_ns: capture time, integer nanoseconds.
            prior: the tracker's predicted pose for this frame, if any: used to resolve
                ambiguities and to speed up association, never to fabricate a pose.

        Returns:
            :class:`PoseEstimate`, or a falsy :class:`Failure` (reasons: :data:`FAILURE_REASONS`).
        """
        t0 = time.perf_counter()
        img = np.asarray(image)
        cam = self.rig.camera
        if img.ndim not in (2, 3) or img.size == 0:
            return self.fail(t_ns, BAD_FRAME, f"expected a {cam.width}x{cam.height} frame, "
                             f"found shape {img.shape}")
        grey = to_grey(img)
        bad = check_frame(grey, cam.width, cam.height, self.options.min_contrast)
        if bad is not None:
            return self.fail(t_ns, *bad)
        return self._estimate(grey, int(t_ns), prior, t0)

    def forget(self) -> None:  # noqa: B027 - a no-op by default, not abstract
        """Drop what the estimator carries from frame to frame (window-search counters,
        pooled side offsets, the previous image of the ceiling-plane odometry), so the
        next frame is estimated as if it were the first: what a run with no tracker
        does before every frame (``ceilrun replay --no-track``: its rows do not depend
        on the frames' order). The base carries nothing."""

    @abstractmethod
    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        """The estimate from a checked ``(H, W)`` uint8 frame; ``t0`` is
        ``time.perf_counter()`` at entry (for the ``ms`` diagnostic)."""

    def fail(self, t_ns: int, reason: str, detail: str,
             hypotheses: tuple[Hypothesis, ...] = (), complete: bool = False,
             **diagnostics: Any) -> Failure:
        """A :class:`Failure` of this method (``hypotheses``: an ambiguous frame's;
        ``complete``: they are every pose the frame supports)."""
        return Failure(int(t_ns), self.name, reason, detail, MappingProxyType(diagnostics),
                       tuple(hypotheses), hypotheses_complete=complete)


def elapsed_ms(t0: float) -> float:
    """Milliseconds since ``t0`` (a ``time.perf_counter()`` reading): the ``ms`` diagnostic."""
    return 1e3 * (time.perf_counter() - t0)
