"""What an estimator returns for one frame: a pose, or a failure with its reason.

A frame on which a method cannot estimate is a value, not an exception: a
:class:`Failure` is falsy and carries a short machine reason (counted by the
runtime) and a human detail.

Convention: the pose is the vehicle's in W (SPEC §1): ``x_m, y_m`` metres,
``yaw_rad`` counter-clockwise from +x. A coordinate the method cannot observe is
``None`` (the corridor method does not observe x).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np


def _empty() -> Mapping[str, Any]:
    return MappingProxyType({})


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
        diagnostics: method-specific figures (residuals, counts), for logs and reports.
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

    def __bool__(self) -> bool:
        return True

    @property
    def ok(self) -> bool:
        return True

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)

    def with_time(self, t_ns: int) -> PoseEstimate:
        return replace(self, t_ns=t_ns)


@dataclass(frozen=True)
class Failure:
    """A frame the method could not estimate. Falsy.

    Attributes:
        reason: a short stable code (``too_few_lines``, ``blank_frame``, ``ambiguous``, ...).
        detail: one human sentence.
    """

    t_ns: int
    method: str
    reason: str
    detail: str = ""
    diagnostics: Mapping[str, Any] = field(default_factory=_empty)

    def __bool__(self) -> bool:
        return False

    @property
    def ok(self) -> bool:
        return False


Estimate = PoseEstimate | Failure
