"""The latest frame and raw estimate, handed over by reference (no copy, no encoding).

:class:`EstimateTap` wraps an estimator: each ``estimate`` call stores
``(image, estimate)`` in one slot (a single attribute assignment, atomic in CPython)
and returns the estimate unchanged. Readers (overlay writers, the live view's encoder
thread) take the slot when they want; the per-frame path never waits for them.

Example::

    tap = EstimateTap(estimator)
    pipeline = Pipeline(tap, sinks)
    image, est = tap.latest
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ceilkit.runtime.estimators.base import Estimate, Estimator, PoseEstimate


class EstimateTap:
    """An estimator that also keeps its latest ``(image, estimate)``; every other
    attribute is the wrapped estimator's."""

    def __init__(self, estimator: Estimator) -> None:
        self.inner = estimator
        self.latest: tuple[np.ndarray, Estimate] | None = None
        self.count = 0

    def estimate(self, image: np.ndarray, t_ns: int,
                 prior: PoseEstimate | None = None) -> Estimate:
        est = self.inner.estimate(image, t_ns, prior)
        self.latest = (image, est)
        self.count += 1
        return est

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)
