"""``--method auto``: every method the site supports, on each frame, for the fusion.

:class:`AutoEstimator` runs each method of
:func:`~ceilkit.runtime.estimators.registry.site_methods` with the same prior (the
fusion's track when it is confident: the cheap tracked path; none when it is not: the
lights/block global search) and returns the best-determined estimate with every
method's result in its ``cues``, which :class:`~ceilkit.runtime.fusion.Fusion`
fuses.

:func:`make_localizer` builds the estimator and its tracker for a ``--method``:
an explicit name is today's single method behind the constant-velocity
:class:`~ceilkit.runtime.tracking.Tracker` (one emitting ceiling-plane odometry,
``block`` with ``plane_odometry``, behind the fusion, which chains it between
fixes); ``auto`` is the fusion, except on a site with one method, no odometry and no
start pose, where it is that method as ``--method NAME`` runs it.

Example::

    estimator, tracker = make_localizer("auto", rig, site, start_pose=(0.0, 0.0, 0.0))
    pipeline = Pipeline(estimator, sinks, tracker)
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Estimate, Estimator, PoseEstimate
from ceilkit.runtime.estimators.prior import DEFAULT_PRIOR_SIGMA, MAX_TURN_RPS
from ceilkit.runtime.estimators.registry import AUTO, make_estimator, site_methods
from ceilkit.runtime.fusion import Fusion, FusionOptions
from ceilkit.runtime.jit import WarmUpProgress, reporting, warm_up
from ceilkit.runtime.tracking import Tracker, TrackerOptions


class AutoEstimator:
    """Every method the site supports, on one frame (see the module docstring)."""

    name = AUTO

    def __init__(self, rig: Rig, site: Site, options: Mapping[str, Any] | None = None):
        names = site_methods(site)
        if not names:
            raise ConfigError(site.source, None, "the site has no section any method uses")
        opts = dict(options or {})
        self.estimators: list[Estimator] = []
        for n in names:
            est = make_estimator(n, rig, site)
            fields = {f.name for f in dataclasses.fields(est.Options)} | set(est.Options.ALIASES)
            mine = {k: v for k, v in opts.items() if k in fields}
            self.estimators.append(make_estimator(n, rig, site, mine) if mine else est)
        known = {f.name for e in self.estimators for f in dataclasses.fields(e.Options)}
        unknown = sorted(set(opts) - known - {k for e in self.estimators
                                              for k in e.Options.ALIASES})
        if unknown:
            raise ConfigError(None, f"options.{unknown[0]}",
                              f"unknown option (expected one of {', '.join(sorted(known))})")
        self.rig, self.site = rig, site

    def forget(self) -> None:
        """Every method's :meth:`~ceilkit.runtime.estimators.base.Estimator.forget`."""
        for e in self.estimators:
            e.forget()

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.estimators)

    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> Estimate:
        """Each method's estimate; the one that observes most is returned, with all of
        them as its ``cues``."""
        cues = tuple(e.estimate(image, t_ns, prior) for e in self.estimators)
        best = max(cues, key=_observes)
        return dataclasses.replace(best, cues=cues)


def _observes(est: Estimate) -> int:
    if not isinstance(est, PoseEstimate):
        return 0
    return 1 + (est.y_m is not None) + (est.x_m is not None)


def regular_spacing_m(site: Site) -> float | None:
    """The smallest distance between two lights of the site (its cell on a grid)."""
    pts = np.asarray(site.lights_m, float) if site.has_section("lights") else np.zeros((0, 2))
    if len(pts) < 2:
        return None
    return float(min(np.hypot(*(a - b)) for a, b in itertools.combinations(pts, 2)))


def make_localizer(method: str | None, rig: Rig, site: Site,
                   options: Mapping[str, Any] | None = None,
                   start_pose: tuple[float, float, float] | None = None,
                   odometry: bool = False,
                   fusion: FusionOptions | None = None,
                   limits: tuple[float, float] | None = None
                   ) -> tuple[Estimator | AutoEstimator, Tracker | Fusion]:
    """The estimator and its tracker for ``--method`` (see the module docstring).

    Args:
        method: an estimator name, ``auto``, or ``None`` (the site's default method).
        start_pose: ``(x_m, y_m, yaw_rad)`` where the vehicle starts (and, as two more
            numbers, its 1σ in m and rad): the track's first prior, which chooses among
            the poses a frame supports alike only inside its region
            (:mod:`~ceilkit.runtime.estimators.prior`).
        odometry: wheel odometry will be fed to the tracker (auto only).
        fusion: the fusion's options (default: :class:`FusionOptions` with the site's
            light spacing as ``cell_m``).
        limits: the vehicle's stated maximum speed and turn rate ``(m/s, rad/s)``
            (``--max-speed``; :func:`parse_limits`) for the tracker and the fusion
            (default :data:`~ceilkit.runtime.estimators.prior.MAX_SPEED_MPS`,
            :data:`~ceilkit.runtime.estimators.prior.MAX_TURN_RPS`).

    The compiled loops the chosen estimators and their tracker use are loaded here
    (:func:`~.jit.warm_up` from their modules), not on the first frame; the other
    methods' loops are not (``ceilrun warm-up`` makes every loop).

    Raises:
        ConfigError: a bad method or option.
    """
    fusion = fusion or FusionOptions(cell_m=regular_spacing_m(site))
    if limits is not None:
        fusion = dataclasses.replace(fusion, max_speed_mps=limits[0],
                                     max_turn_rps=limits[1])
    if method != AUTO:
        out = _single(make_estimator(method, rig, site, options), fusion, start_pose)
    else:
        auto = AutoEstimator(rig, site, options)
        if len(auto.estimators) == 1 and start_pose is None and not odometry:
            out = _single(auto.estimators[0], fusion)
        else:
            pose, sigma = split_start_pose(start_pose)
            out = auto, Fusion(fusion, start_pose=pose, start_sigma=sigma)
    chosen = out[0].estimators if isinstance(out[0], AutoEstimator) else [out[0]]
    warm_up(roots=[type(o) for o in (*chosen, out[1])])
    return out


def warm_up_all() -> WarmUpProgress:
    """Make every method's compiled loops now (``ceilrun warm-up``: once per machine,
    numba's cache keeps them, so that no later start compiles): how many, how many of
    them were compiled (not in the cache), and the seconds it took."""
    steps: list[WarmUpProgress] = []
    with reporting(steps.append):
        seconds = warm_up()   # every estimator's modules are imported (the registry)
    return steps[-1] if steps else WarmUpProgress(0, 0, "", 0, seconds)


def _single(est: Estimator, fusion: FusionOptions,
            start_pose: tuple[float, float, float] | None = None
            ) -> tuple[Estimator, Tracker | Fusion]:
    """One method and its tracker: the constant-velocity one (with the fusion's vehicle
    limits and motion model), or the fusion for a method emitting ceiling-plane
    odometry (it chains the increments between fixes); either starts from
    ``start_pose`` when given."""
    pose, sigma = split_start_pose(start_pose)
    if not getattr(est.options, "plane_odometry", False):
        limits = TrackerOptions(max_speed_mps=fusion.max_speed_mps,
                                max_turn_rps=fusion.max_turn_rps, noise=fusion.noise)
        return est, Tracker(limits, start_pose=pose, start_sigma=sigma)
    return est, Fusion(fusion, start_pose=pose, start_sigma=sigma)


def _numbers(text: str) -> list[float]:
    """The comma-separated numbers of ``text``; empty when one is not a number."""
    try:
        return [float(t) for t in text.split(",")]
    except ValueError:
        return []


def parse_limits(text: str) -> tuple[float, float]:
    """``SPEED[,TURN]`` (m/s, degrees/s) as ``(m/s, rad/s)``: the vehicle's stated
    limits (``--max-speed``); the turn rate defaults to
    :data:`~ceilkit.runtime.estimators.prior.MAX_TURN_RPS`.

    Raises:
        ConfigError: ``max_speed`` unless one or two finite numbers, the speed in
            (0, 100] m/s and the turn rate in (0, 3600] degrees/s.
    """
    v = _numbers(text)
    if len(v) not in (1, 2):
        raise ConfigError(None, "max_speed", "expected SPEED (m/s) or SPEED,TURN (m/s, "
                          f"degrees/s), found {text!r}")
    if not (math.isfinite(v[0]) and 0 < v[0] <= 100.0) or (
            len(v) == 2 and not (math.isfinite(v[1]) and 0 < v[1] <= 3600.0)):
        raise ConfigError(None, "max_speed", "expected a speed in (0, 100] m/s and a turn "
                          f"rate in (0, 3600] degrees/s, found {text!r}")
    return v[0], (math.radians(v[1]) if len(v) == 2 else MAX_TURN_RPS)


def split_start_pose(start_pose: tuple[float, ...] | None
                     ) -> tuple[tuple[float, float, float] | None, tuple[float, float]]:
    """``(pose, sigma)`` of a start pose of 3 or 5 numbers (:func:`parse_start_pose`):
    the 1σ :data:`~ceilkit.runtime.estimators.prior.DEFAULT_PRIOR_SIGMA` when not given."""
    if start_pose is None:
        return None, DEFAULT_PRIOR_SIGMA
    v = tuple(float(t) for t in start_pose)
    return (v[0], v[1], v[2]), ((v[3], v[4]) if len(v) == 5 else DEFAULT_PRIOR_SIGMA)


def parse_start_pose(text: str) -> tuple[float, ...]:
    """``X,Y,YAW`` (m, m, degrees) as ``(x_m, y_m, yaw_rad)``, or ``X,Y,YAW,SIGMA_M,
    SIGMA_DEG`` (the start pose's 1σ: how far it may be off; default
    :data:`~ceilkit.runtime.estimators.prior.DEFAULT_PRIOR_SIGMA`) as
    ``(x_m, y_m, yaw_rad, sigma_m, sigma_rad)``.

    Raises:
        ConfigError: ``start_pose`` unless three (or five) finite numbers, |x|, |y| at
            most :data:`START_POSE_LIMIT_M`, |yaw| at most 360 degrees, the sigmas in
            (0, 100] m and (0, 180] degrees.
    """
    v = _numbers(text)
    if len(v) not in (3, 5):
        raise ConfigError(None, "start_pose", "expected X,Y,YAW (m, m, degrees) or "
                          f"X,Y,YAW,SIGMA_M,SIGMA_DEG, found {text!r}")
    if not all(np.isfinite(v)):
        raise ConfigError(None, "start_pose", f"expected finite numbers, found {text!r}")
    x, y, yaw = v[:3]
    if max(abs(x), abs(y)) > START_POSE_LIMIT_M or abs(yaw) > 360.0:
        raise ConfigError(None, "start_pose", f"expected |x|, |y| <= {START_POSE_LIMIT_M:g} m "
                          f"and |yaw| <= 360 degrees, found {text!r}")
    if len(v) == 5 and not (0 < v[3] <= 100.0 and 0 < v[4] <= 180.0):
        raise ConfigError(None, "start_pose", "expected SIGMA_M in (0, 100] m and SIGMA_DEG "
                          f"in (0, 180] degrees, found {text!r}")
    return (x, y, float(np.radians(yaw))) + (
        (v[3], float(np.radians(v[4]))) if len(v) == 5 else ())


START_POSE_LIMIT_M = 1e6
"""The largest |x| or |y| of a start pose, m (bounded before it reaches the filter)."""


__all__ = ["AutoEstimator", "make_localizer", "parse_limits", "parse_start_pose",
           "regular_spacing_m",
           "split_start_pose",
           "warm_up_all"]
