"""A rolling shutter in the estimators: the options every method that models it shares,
and the motion it assumes for a frame's rows.

Each row of a rolling-shutter frame is exposed at its own time
(:func:`~ceilkit.runtime.geometry.shutter.row_times_s`); a method predicts what a row
shows from the pose at that time, moved from the stamp's pose by the prior's velocity
(``PoseEstimate.velocity``: the tracker's or the fusion's). That velocity is uncertain
(and unknown without a prior): the methods add what its uncertainty does to the pose
to their covariance.

Example::

    motion = row_motion(options, prior)     # None for a global shutter
    if motion is not None:
        velocity, sigma = motion            # (vx, vy, w) in W and their 1-sigma
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ceilkit.runtime.estimators.base import EstimatorOptions, PoseEstimate


@dataclass(frozen=True)
class ShutterOptions(EstimatorOptions):
    """The rolling-shutter options (``--option KEY=VALUE``) of the methods that model it.

    Attributes:
        readout_ms: the camera's readout time, top row to bottom row, ms (0: a global
            shutter, nothing modelled). The simulator's ``rolling_shutter_ms`` means the
            same (docs/conventions.md, "Frame stamps").
        rate_sigma_dps, speed_sigma_mps: the 1-sigma of the prior's velocity: yaw rate
            (deg/s) and each horizontal speed component (m/s).
        unknown_rate_dps, unknown_speed_mps: the same when no velocity is known (no
            prior, or a track that has not measured one yet): the vehicle is taken at
            rest with these.
    """

    readout_ms: float = 0.0
    rate_sigma_dps: float = 3.0
    speed_sigma_mps: float = 0.05
    unknown_rate_dps: float = 30.0
    unknown_speed_mps: float = 0.5


SHUTTER_OPTIONS = ("readout_ms", "rate_sigma_dps", "speed_sigma_mps", "unknown_rate_dps",
                   "unknown_speed_mps")
"""The options above (each a finite number >= 0, ``honesty.check_options``)."""


def row_motion(options: ShutterOptions, prior: PoseEstimate | None
               ) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """``(velocity, sigma)``: the motion a frame's rows are predicted with, ``(vx m/s,
    vy m/s, yaw rate rad/s)`` in W and their 1-sigma; None for a global shutter
    (``readout_ms`` 0)."""
    if options.readout_ms <= 0:
        return None
    if prior is not None and prior.velocity is not None:
        s, w = options.speed_sigma_mps, math.radians(options.rate_sigma_dps)
        vx, vy, vw = (float(v) for v in prior.velocity)
        return (vx, vy, vw), (s, s, w)
    s, w = options.unknown_speed_mps, math.radians(options.unknown_rate_dps)
    return (0.0, 0.0, 0.0), (s, s, w)


__all__ = ["SHUTTER_OPTIONS", "ShutterOptions", "row_motion"]
