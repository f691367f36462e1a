"""Honesty as model checking: whether a method's model explains the image, before it
publishes a pose, and how much its covariance must grow when the fit is worse than
the noise it assumes.

The one decision (see ``docs/methods/honesty.md``): an estimator returns a
:class:`~ceilkit.runtime.estimators.base.PoseEstimate` only when every check of its
model passes; otherwise a :class:`~ceilkit.runtime.estimators.base.Failure` whose
reason names the first check that failed (:data:`MODEL_REASONS`). Everything
downstream follows from that one value: NMEA ``A`` / ``V``, the MAVLink and ROS
covariance (a Failure sends none), ``poses.csv``, the tracker and the fusion.

The checks (each method uses those that apply):

* :func:`misfit`: the residuals against their expected noise ``sigma_px``, a
  chi-square test at ``1 - alpha`` with the fit's degrees of freedom (not a fixed RMS).
  The statistic is the fit's own robust cost, ``sum 2 rho(r / sigma)`` with the Huber
  ``rho`` at ``huber_px``, which is the plain chi-square when every ``|r| <= huber_px``.
* :func:`covariance_inflation`: a fit that passes but whose reduced chi-square exceeds
  1 has its covariance scaled: by how much the robust weights hid (raw over weighted
  squared residuals) and by the design effect of residuals that share one systematic
  error (the endpoints of segments on one site line are not independent:
  ``1 + (m - 1) rho``, ``m`` residuals per group, ``rho`` the share of the residual
  energy the group means carry). A fit whose reduced chi-square is at most 1 keeps its
  covariance exactly.
* :class:`SiteExtent`: the pose inside the site's extent (what the site holds:
  corridor lines, lamps, lights, blocks, markers) plus a margin.
* angle checks (the vanishing line against the calibrated mount, the vanishing-point
  heading against the refined one) and feature counts and spread: plain comparisons in
  the estimators, with the thresholds in their options.

Example::

    m = misfit(r_px, sigma_px=1.0, n_params=2, groups=line_of_each_residual)
    if not m.passed:
        return self.fail(t_ns, MISFIT, m.detail())
    cov = cov * m.inflation
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from types import MappingProxyType
from typing import Any

import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.ekf import chi2_quantile
from ceilkit.runtime.jit import arr, njit, warmer

MISFIT = "misfit"
VANISHING_LINE = "vanishing_line"
HEADING_DISAGREES = "heading_disagrees"
OUTSIDE_SITE = "outside_site"
WEAK_GEOMETRY = "weak_geometry"

MODEL_REASONS: Mapping[str, str] = MappingProxyType({
    MISFIT: "the residuals exceed their expected noise (chi-square test): the model does "
            "not explain the image",
    VANISHING_LINE: "the line families' vanishing points are off the vanishing line the "
                    "calibrated mount predicts",
    HEADING_DISAGREES: "the refined heading moved away from the one the vanishing point "
                       "gives",
    OUTSIDE_SITE: "the pose lies outside the site's extent (with a margin)",
    WEAK_GEOMETRY: "too few matched features, or too little spread over the image, to "
                   "check the model",
})
"""The model-check failure reasons (merged into ``base.FAILURE_REASONS``)."""

DEFAULT_ALPHA = 1e-3
"""The chi-square test's false-alarm rate on a fit whose residuals are the assumed noise."""


@lru_cache(maxsize=1024)
def _f_quantile(p: float, dfn: int, dfd: int) -> float:
    """The ``p`` quantile of the F distribution (``scipy.stats.f.ppf``, cached: a
    frame's fit asks for the same few degrees of freedom again and again)."""
    from scipy.stats import f as f_dist

    return float(f_dist.ppf(p, dfn, dfd))


@dataclass(frozen=True)
class Misfit:
    """The chi-square test of a fit's residuals.

    Attributes:
        chi2: the robust statistic ``sum 2 rho(r / sigma)``. dof: residuals minus
            parameters. reduced: ``chi2 / dof``. limit: the ``1 - alpha`` quantile.
        sigma_px: the assumed noise. rms_px: the residuals' RMS.
        inflation: the covariance factor (:func:`covariance_inflation`; 1 when
            ``reduced <= 1``).
    """

    chi2: float
    dof: int
    reduced: float
    limit: float
    sigma_px: float
    rms_px: float
    inflation: float

    @property
    def passed(self) -> bool:
        """Whether the residuals are consistent with the noise (``chi2 <= limit``)."""
        return self.chi2 <= self.limit

    def detail(self) -> str:
        """One sentence for a Failure."""
        return (f"residual RMS {self.rms_px:.2f} px against {self.sigma_px:g} px noise: "
                f"chi-square {self.chi2:.1f} over {self.dof} dof, above {self.limit:.1f}")

    def diagnostics(self) -> dict[str, Any]:
        return {"chi2": self.chi2, "chi2_dof": self.dof, "chi2_reduced": self.reduced,
                "chi2_limit": self.limit, "cov_inflation": self.inflation}


def huber_cost(r: np.ndarray, k: float) -> np.ndarray:
    """``2 rho(r)`` per residual: ``r^2`` for ``|r| <= k``, ``2 k |r| - k^2`` beyond."""
    a = np.abs(r)
    if not math.isfinite(k):
        return a * a
    return np.where(a <= k, a * a, 2.0 * k * a - k * k)


def design_effect(r: np.ndarray, groups: np.ndarray | None, level: float = 0.99) -> float:
    """``1 + (m - 1) rho`` for residuals ``r (N,)`` in groups ``(N,)`` (ints) that share
    a systematic error: ``m = N / G`` residuals per group and ``rho`` the lower
    ``level`` confidence bound of their intraclass correlation (one-way ANOVA about zero:
    ``F = MS_between / MS_within`` against the ``F(G, N - G)`` quantile; 0 when ``F`` is
    not significant, so independent noise gives 1 but for a ``1 - level`` share of
    fits). 1 without groups, or for one residual per group."""
    n = r.size
    if groups is None or n == 0:
        return 1.0
    _, inv, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
    g = counts.size
    if g >= n:
        return 1.0
    means = np.bincount(inv, weights=r, minlength=g) / counts
    ms_b = float(counts @ (means * means)) / g
    ms_w = float(np.sum((r - means[inv]) ** 2)) / (n - g)
    m = n / g
    if not ms_b > 0:
        return 1.0
    if not ms_w > 0:
        return m
    ratio = (ms_b / ms_w) / _f_quantile(level, g, n - g)
    if ratio <= 1.0:
        return 1.0
    rho = (ratio - 1.0) / (ratio + m - 1.0)
    return 1.0 + (m - 1.0) * rho


def covariance_inflation(r: np.ndarray, reduced: float, sigma_px: float, huber_px: float,
                         groups: np.ndarray | None) -> float:
    """The factor on a fit's covariance ``s^2 (J^T W J)^-1``: 1 when ``reduced <= 1``;
    above, ``1 + (G - 1) min(1, reduced - 1)`` (continuous in ``reduced``) with
    ``G = (sum r^2 / sum w r^2) x design_effect``: what the Huber weights ``w`` hid and
    the residuals' shared systematic error (:func:`design_effect`)."""
    if not reduced > 1.0:
        return 1.0
    rs = r / sigma_px
    w = np.minimum(1.0, (huber_px / sigma_px) / np.maximum(np.abs(rs), 1e-12))
    raw = float(rs @ rs)
    weighted = float(w @ (rs * rs))
    hidden = raw / weighted if weighted > 0 else 1.0
    big = max(1.0, hidden) * design_effect(r, groups)
    return 1.0 + (big - 1.0) * min(1.0, reduced - 1.0)


def misfit(residuals_px: np.ndarray, sigma_px: float, n_params: int,
           groups: np.ndarray | None = None, alpha: float = DEFAULT_ALPHA,
           huber_px: float = math.inf) -> Misfit:
    """The chi-square test of ``residuals_px (N,)`` against noise ``sigma_px`` with
    ``N - n_params`` degrees of freedom at false-alarm rate ``alpha``, and the
    covariance inflation of a passing fit.

    Args:
        residuals_px: the fit's residuals (px); non-finite ones count as failing.
        sigma_px: the residuals' expected standard deviation (px), > 0.
        n_params: the fitted parameters.
        groups: ``(N,)`` the systematic-error group of each residual (None: independent).
        huber_px: the fit's Huber threshold (px); inf for least squares.

    With no degrees of freedom left (``N <= n_params``) the test cannot fail (limit
    inf): the estimator's feature-count check must refuse such a fit.
    """
    r = arr(residuals_px, np.float64).ravel()
    n = r.size
    dof = n - int(n_params)
    ssr, finite, chi2 = _sums(r, float(sigma_px), float(huber_px))
    rms = math.sqrt(ssr / n) if n else float("nan")
    if n and not finite:
        return Misfit(math.inf, dof, math.inf, 0.0, sigma_px, rms, math.inf)
    if dof < 1:
        return Misfit(chi2, dof, float("nan"), math.inf, sigma_px, rms, 1.0)
    reduced = chi2 / dof
    limit = chi2_quantile(1.0 - alpha, dof)
    return Misfit(chi2, dof, reduced, limit, sigma_px, rms,
                  covariance_inflation(r, reduced, sigma_px, huber_px, groups))


@njit
def _sums(r, sigma, huber):  # pragma: no cover - compiled
    """``(sum r², all finite, sum huber_cost(r / sigma, huber / sigma))`` in one loop."""
    ssr = chi2 = 0.0
    finite = True
    k = huber / sigma
    for i in range(r.size):
        ssr += r[i] * r[i]
        finite = finite and math.isfinite(r[i])
        a = abs(r[i] / sigma)
        chi2 += a * a if a <= k else 2.0 * k * a - k * k
    return ssr, finite, chi2


@warmer
def _warm() -> None:
    _sums(arr(np.ones(2), np.float64), 1.0, math.inf)
    # scipy.stats (seconds to import on a slow machine) now, not on the first frame
    chi2_quantile(1.0 - DEFAULT_ALPHA, 1)
    _f_quantile(0.5, 1, 1)


def misfit_sum(sum_sq_px: float, n: int, sigma_px: float, n_params: int,
               alpha: float = DEFAULT_ALPHA) -> Misfit:
    """:func:`misfit` of ``n`` independent least-squares residuals (no groups, no
    Huber) given by their sum of squares ``sum_sq_px`` (px²): the same test in a few
    scalar operations, for a fit whose residuals are already summed. Its inflation is
    1: least squares hides nothing, and independent residuals carry no design effect.
    """
    dof = n - int(n_params)
    rms = math.sqrt(sum_sq_px / n) if n else float("nan")
    if n and not math.isfinite(sum_sq_px):
        return Misfit(math.inf, dof, math.inf, 0.0, sigma_px, rms, math.inf)
    chi2 = sum_sq_px / (sigma_px * sigma_px) if n else 0.0
    if dof < 1:
        return Misfit(chi2, dof, float("nan"), math.inf, sigma_px, rms, 1.0)
    return Misfit(chi2, dof, chi2 / dof, chi2_quantile(1.0 - alpha, dof), sigma_px, rms, 1.0)


@dataclass(frozen=True)
class SiteExtent:
    """The box in W that a site's ceiling features span (m); ``inf`` bounds where the
    site does not bound a coordinate (a corridor's lines run on along x).

    Example::

        ext = SiteExtent.from_site(site)
        ext.outside_m(x_m, None)        # 0.0 inside, else how far outside (m)
    """

    x_lo: float
    x_hi: float
    y_lo: float
    y_hi: float

    @classmethod
    def from_site(cls, site: Any) -> SiteExtent:
        """The extent of every section the site holds: corridor ``lines_along`` (y
        only), lamps, lights, blocks, markers (corners)."""
        xs: list[np.ndarray] = []
        ys: list[np.ndarray] = []
        corridor = getattr(site, "corridor", None)
        if corridor is not None and len(corridor.lines_along_m):
            ys.append(np.asarray(corridor.lines_along_m, dtype=float))
        lamps = site.lamp_rectangles() if getattr(site, "lamps", ()) else np.zeros((0, 4, 2))
        pts = [np.asarray(lamps, dtype=float).reshape(-1, 2)]
        if site.has_lights:
            pts.append(np.asarray(site.lights_m, dtype=float).reshape(-1, 2))
        for b in getattr(site, "blocks", ()) or ():
            pts.append(np.asarray(b.corners_m, dtype=float).reshape(-1, 2))
        markers = getattr(site, "markers", None)
        if markers is not None and markers.poses:
            pts.append(np.asarray(markers.corners_m(), dtype=float).reshape(-1, 2))
        p = np.concatenate(pts) if pts else np.zeros((0, 2))
        if p.size:
            xs.append(p[:, 0])
            ys.append(p[:, 1])
        x = np.concatenate(xs) if xs else np.zeros(0)
        y = np.concatenate(ys) if ys else np.zeros(0)
        x_lo, x_hi = (float(x.min()), float(x.max())) if x.size else (-math.inf, math.inf)
        y_lo, y_hi = (float(y.min()), float(y.max())) if y.size else (-math.inf, math.inf)
        return cls(x_lo, x_hi, y_lo, y_hi)

    def outside_m(self, x_m: float | None, y_m: float | None) -> float:
        """How far ``(x_m, y_m)`` lies outside the box (m, 0 inside); a ``None``
        coordinate (unobserved) is not checked."""
        d = 0.0
        if x_m is not None:
            d = max(d, self.x_lo - x_m, x_m - self.x_hi)
        if y_m is not None:
            d = max(d, self.y_lo - y_m, y_m - self.y_hi)
        return float(d) if math.isfinite(d) else math.inf

    def describe(self) -> str:
        """``x in [a, b], y in [c, d]`` (unbounded coordinates left out)."""
        parts = [f"{n} in [{lo:.2f}, {hi:.2f}] m" for n, lo, hi in
                 (("x", self.x_lo, self.x_hi), ("y", self.y_lo, self.y_hi))
                 if math.isfinite(lo) and math.isfinite(hi)]
        return ", ".join(parts) or "unbounded"


def outside_site(extent: SiteExtent, x_m: float | None, y_m: float | None,
                 margin_m: float) -> str | None:
    """The detail of a pose outside ``extent`` by more than ``margin_m``, or None."""
    d = extent.outside_m(x_m, y_m)
    if d <= margin_m:
        return None
    where = ", ".join(f"{n} = {v:.2f} m" for n, v in (("x", x_m), ("y", y_m)) if v is not None)
    return (f"the pose ({where}) is {d:.2f} m outside the site ({extent.describe()}; "
            f"margin {margin_m:g} m)")


def check_options(options: Any) -> None:
    """The model-check options an estimator's options hold are possible: ``noise_px`` >
    0, ``misfit_alpha`` in (0, 1), every other one a finite number >= 0.

    Raises:
        ConfigError: ``options.NAME`` of the first that is not.
    """
    for name in ("noise_px", "misfit_alpha", "max_vp_elevation_deg", "max_vanishing_line_deg",
                 "max_heading_change_deg", "min_lines", "min_spread", "site_margin_m",
                 "working_mpx", "readout_ms", "rate_sigma_dps", "speed_sigma_mps",
                 "unknown_rate_dps", "unknown_speed_mps"):
        if not hasattr(options, name):
            continue
        v = float(getattr(options, name))
        if name == "noise_px":
            ok, want = math.isfinite(v) and v > 0, "a number > 0"
        elif name == "misfit_alpha":
            ok, want = 0.0 < v < 1.0, "a number in (0, 1)"
        else:
            ok, want = math.isfinite(v) and v >= 0, "a number >= 0"
        if not ok:
            raise ConfigError(None, f"options.{name}", f"expected {want}, found {v!r}")


__all__ = ["DEFAULT_ALPHA", "HEADING_DISAGREES", "MISFIT", "MODEL_REASONS", "Misfit",
           "OUTSIDE_SITE", "SiteExtent", "VANISHING_LINE", "WEAK_GEOMETRY", "check_options",
           "chi2_quantile", "covariance_inflation", "design_effect", "huber_cost", "misfit",
           "misfit_sum", "outside_site"]
