"""The ``lights`` method: global localization from ceiling spot lights.

Stages, one module each: ``rays`` (image <-> ceiling plane), ``observe`` (spots as
ceiling points, the visibility table), ``matching`` (point-pattern matching to the
map), ``refine`` (Gauss-Newton in pixels), ``estimator`` (the facade on the Estimator
contract). See ``docs/methods/lights.md``.
"""

from ceilkit.runtime.estimators.lights.estimator import (
    DEFAULT_LIGHT_DIAMETER_M,
    LightsEstimator,
    LightsOptions,
    light_diameter_m,
    pose_quality,
)
from ceilkit.runtime.estimators.lights.matching import Candidate, PatternMatcher
from ceilkit.runtime.estimators.lights.observe import (
    Observation,
    SpotObserver,
    VisibilityTable,
)
from ceilkit.runtime.estimators.lights.rays import (
    ceiling_centroids,
    ceiling_points,
    interp_grid,
    jacobian_grid,
    pixel_scale,
    project_lights,
    view_mask,
)
from ceilkit.runtime.estimators.lights.refine import refine_pose, refine_pose_ceiling

__all__ = ["DEFAULT_LIGHT_DIAMETER_M", "Candidate", "LightsEstimator", "LightsOptions",
           "Observation", "PatternMatcher", "SpotObserver", "VisibilityTable",
           "ceiling_centroids", "ceiling_points", "interp_grid", "jacobian_grid",
           "light_diameter_m", "pixel_scale", "pose_quality", "project_lights", "refine_pose",
           "refine_pose_ceiling", "view_mask"]
