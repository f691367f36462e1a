"""The ``texture`` method: global localization on a ceiling map of natural features.

Stages, one module each: ``ceilmap`` (the map, its file, rectifying a frame onto the
ceiling plane, features, building a map from frames with known poses), ``match`` (the
descriptor index, distinctive matches, two-point RANSAC, the refined rigid fit),
``track`` (the tracked fast path: the map's features followed from a tight prior),
``estimator`` (the facade on the Estimator contract). See ``docs/methods/texture.md``.
"""

from ceilkit.runtime.estimators.texture.ceilmap import (
    CeilingMap,
    build_map,
    features,
    rectify,
)
from ceilkit.runtime.estimators.texture.estimator import TextureEstimator, TextureOptions

__all__ = ["CeilingMap", "TextureEstimator", "TextureOptions", "build_map", "features",
           "rectify"]
