"""Closed-form 2-D point-set fits: rigid (rotation + translation) and similarity.

Convention: point pairs ``q (N, 2)`` and ``p (N, 2)`` in metres; the fitted transform
maps ``q`` onto ``p``: ``p ≈ s R(θ) q + t`` with ``R(θ) = [[cos, -sin], [sin, cos]]``
(counter-clockwise, as a yaw about W's z, SPEC §1). Least squares over the pairs
(Umeyama / Horn in 2-D): the means are matched, the angle is the phase of
``Σ conj(a) b`` of the centred points, the scale ``|Σ conj(a) b| / Σ |a|²``.

Example::

    yaw, t = fit_rigid_2d(q_v, p_w)            # p_w ≈ R(yaw) q_v + t
    s, theta, t = fit_similarity_2d(q, p)      # p ≈ s R(theta) q + t
"""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.jit import njit, warmer


def _centred_sums(q: np.ndarray, p: np.ndarray, w: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
    """``(q mean, p mean, Σ w a·b, Σ w a×b, a)`` of the pairs, ``a, b`` centred."""
    if w is None:
        qm, pm = q.mean(0), p.mean(0)
        a, b = q - qm, p - pm
        s_cos = (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]).sum()
        s_sin = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
        return qm, pm, s_cos, s_sin, a
    w_sum = w.sum()
    qm = (w[:, None] * q).sum(0) / w_sum
    pm = (w[:, None] * p).sum(0) / w_sum
    a, b = q - qm, p - pm
    s_cos = (w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])).sum()
    s_sin = (w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])).sum()
    return qm, pm, s_cos, s_sin, a


def _rotate(angle_rad: float, xy: np.ndarray) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([c * xy[0] - s * xy[1], s * xy[0] + c * xy[1]])


def fit_rigid_2d(q: np.ndarray, p: np.ndarray, w: np.ndarray | None = None
                 ) -> tuple[float, np.ndarray]:
    """Least-squares ``(yaw, t)`` with ``p ≈ R(yaw) q + t`` for point pairs ``(N, 2)``.

    The scale is known (metres on both sides): the rigid case of the similarity fit
    (Roh et al. Eq. 15 with ``s = 1``), closed form, N >= 2.

    Args:
        q, p: ``(N, 2)`` pairs; ``w``: optional ``(N,)`` weights (all 1 if ``None``).

    Returns:
        ``(yaw_rad, t (2,))``.
    """
    w = np.ones(q.shape[0]) if w is None else np.asarray(w, float)
    qm, pm, s_cos, s_sin, _ = _centred_sums(q, p, w)
    yaw = math.atan2(s_sin, s_cos)
    return yaw, pm - _rotate(yaw, qm)


def rigid_fit_rms(q: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray, float]:
    """:func:`fit_rigid_2d` of ``q`` onto ``p`` ``(N, 2)`` and the fit's RMS residual:
    ``(yaw_rad, t (2,), rms)``."""
    yaw, t = fit_rigid_2d(q, p)
    c, s = math.cos(yaw), math.sin(yaw)
    r = q @ np.array([[c, s], [-s, c]]) + t - p
    return yaw, t, float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def fit_rigid_2d_complex(q_c: np.ndarray, p_c: np.ndarray) -> tuple[complex, complex]:
    """:func:`fit_rigid_2d` (unweighted) on points as complex numbers ``x + iy``.

    The per-frame form (a few complex sums, no 2-D arrays): ``p ≈ rot q + t`` with
    ``rot = e^{i yaw}``; ``rot = 1`` when the centred points give no direction.

    Args:
        q_c, p_c: ``(N,)`` complex pairs, N >= 2.

    Returns:
        ``(rot, t)``, complex; ``yaw = atan2(rot.imag, rot.real)``.
    """
    n = q_c.shape[0]
    qm, pm = q_c.sum() / n, p_c.sum() / n
    sc = complex((np.conj(q_c - qm) * (p_c - pm)).sum())
    rot = sc / abs(sc) if abs(sc) > 0 else 1.0 + 0j
    return rot, complex(pm - rot * qm)


def fit_similarity_2d(q: np.ndarray, p: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Least-squares ``(s, θ, t)`` with ``p ≈ s R(θ) q + t`` (Roh et al. Eq. 15).

    Args:
        q, p: ``(N, 2)`` point pairs, N >= 2.

    Returns:
        ``(scale, theta_rad, t (2,))``.
    """
    qm, pm, s_cos, s_sin, a = _centred_sums(q, p, None)
    theta = math.atan2(s_sin, s_cos)
    s = math.hypot(s_cos, s_sin) / max((a ** 2).sum(), 1e-12)
    return s, theta, pm - s * _rotate(theta, qm)


def short_median(x: np.ndarray) -> float:
    """``np.median`` of a short 1-D array (a fit's residuals): the same
    number for a fraction of its call."""
    s = np.sort(x)
    n = s.size
    return float(s[n // 2]) if n % 2 else float((s[n // 2 - 1] + s[n // 2]) / 2)


@njit
def median_of(x):  # pragma: no cover - compiled
    """:func:`short_median` in a compiled loop (NaN of an empty array)."""
    n = x.size
    if n == 0:
        return np.nan
    s = np.sort(x)
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


@njit
def scaled_inverse3(N, scale, out):  # pragma: no cover - compiled
    """``out = scale N⁻¹`` for a symmetric ``(3, 3)`` ``N`` by cofactors (``scale (C /
    det)``); False, ``out`` untouched, when ``N`` is singular or not finite."""
    a, b, c, d, e, f = N[0, 0], N[0, 1], N[0, 2], N[1, 1], N[1, 2], N[2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    if not (math.isfinite(det) and abs(det) > 1e-300):
        return False
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    r = 1.0 / det
    out[0, 0], out[0, 1], out[0, 2] = scale * (A * r), scale * (B * r), scale * (C * r)
    out[1, 0], out[1, 1], out[1, 2] = scale * (B * r), scale * (D * r), scale * (E * r)
    out[2, 0], out[2, 1], out[2, 2] = scale * (C * r), scale * (E * r), scale * (F * r)
    return True


@njit
def student(nu):  # pragma: no cover - compiled
    """``nu / (nu - 2)``, at most 3 (``nu`` at most 3): the variance of a unit Student-t
    error of ``nu`` degrees of freedom, the factor on a variance estimated from ``nu``
    values that makes its mean NEES right (the corridor's and the block's fix
    covariances, the parallels' heading)."""
    return nu / (nu - 2.0) if nu > 3.0 else 3.0


@warmer
def _warm() -> None:
    median_of(np.ones(2))
    student(5.0)


def covering(C: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The least covariance that covers both ``C`` and ``D`` along every direction of
    ``C``'s whitened frame: ``L V max(Λ, 1) Vᵀ Lᵀ``, ``C = L Lᵀ``, ``V Λ Vᵀ`` the
    eigen-decomposition of ``L⁻¹ D L⁻ᵀ``; ``C`` itself when either is not finite or
    ``C`` is not positive definite (never less than ``C``)."""
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(D))):
        return C
    try:
        L = np.linalg.cholesky(0.5 * (C + C.T))
    except np.linalg.LinAlgError:
        return C
    Li = np.linalg.inv(L)
    w, V = np.linalg.eigh(Li @ (0.5 * (D + D.T)) @ Li.T)
    if w.max() <= 1.0:
        return C
    B = L @ V
    return B @ np.diag(np.maximum(w, 1.0)) @ B.T


__all__ = ["covering", "fit_rigid_2d", "fit_rigid_2d_complex", "fit_similarity_2d", "median_of",
           "scaled_inverse3", "short_median", "student"]
