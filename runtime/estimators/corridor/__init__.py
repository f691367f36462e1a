"""The corridor method (Yang & Tsai's vanishing lines), in stages.

``setup`` (construction constants) · ``geometry`` (the formulas) · ``frame`` (a frame's
segments and per-frame arrays) · ``hypotheses`` (pan candidates, families, which is
forward) · ``association`` (which site line is which) · ``refine`` (Gauss-Newton on
``(psi, c_y)``) · ``estimator`` (the facade on the Estimator contract) ·
``visibility`` (which lines a pose sees).
"""

from ceilkit.runtime.estimators.corridor.association import OffsetMatch, match_offsets
from ceilkit.runtime.estimators.corridor.estimator import CorridorEstimator, CorridorOptions
from ceilkit.runtime.estimators.corridor.setup import check_setup, default_match_tol_m
from ceilkit.runtime.estimators.corridor.visibility import visible_along_lines

__all__ = ["CorridorEstimator", "CorridorOptions", "OffsetMatch", "check_setup",
           "default_match_tol_m", "match_offsets", "visible_along_lines"]
