"""Which of a survey's stable bright spots are lamps: their shape on the ceiling.

A spot light (SPEC: ``light_diameter``, round lamps) gives a round spot wherever the
camera sees it from: its extent on the ceiling (:func:`~ceilkit.calib.lightmap.
spot_extents_m`, the two principal axes of each detection met with the ceiling plane)
has a minor / major ratio near 1. Many of the other things that stay put from frame to
frame (a sprinkler's rim, a detector, the lit part of a panel's frame) give elongated
spots. :func:`lamp_shapes` measures every surveyed light's spots; a light whose median
ratio is under :data:`MIN_LAMP_ROUNDNESS` is not written as a lamp.

Measured on the ``bench_survey.py --against-known`` loop (eight 0.12 m spot lights under
the office scatter): the eight lamps' median ratios were 0.94-1.00; 12 of the 20 other
stable spots were 0.29-0.87. The size does not separate the rest: the lamps measure
157-171 mm across (their soft edge), round non-lamps 57, 118, 130 and 325 mm, so a check
against the site's 0.12 m would keep two impostors and drop every lamp.

Example::

    roundness, major_m, views = lamp_shapes(rec, poses_w, lights_xy, 2.7)
    lamps = roundness >= MIN_LAMP_ROUNDNESS
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.estimators.lights import ceiling_centroids, view_mask
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.features.spots import detect_spots
from ceilkit.runtime.geometry.ceiling import vehicle_to_world
from ceilkit.runtime.io.recording import Recording

from .lightmap import spot_extents_m

MIN_LAMP_ROUNDNESS = 0.9
"""A lamp's spots' median minor / major extent, at least (measured above)."""
NEAR_M = 0.015
"""A detection belongs to the light within this of it (the survey's spread limit)."""
MAX_VIEW_ANGLE_DEG = 60.0


def lamp_shapes(rec: Recording, frames: np.ndarray, poses: np.ndarray,
                lights_xy: np.ndarray, height_m: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(roundness (L,), major_m (L,), views (L,))``: for each light ``lights_xy``
    ``(L, 2)`` in W, the median minor / major extent of its spots on the ceiling and the
    median major extent (m) over the ``frames`` of ``rec`` (positions) at vehicle poses
    ``poses`` ``(F, 3)`` in W, and how many spots that is (NaN ratios where none)."""
    n = len(lights_xy)
    rows: list[list[tuple[float, float]]] = [[] for _ in range(n)]
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, int)
    tree = cKDTree(np.asarray(lights_xy, float))
    valid = view_mask(rec.rig, math.radians(MAX_VIEW_ANGLE_DEG))
    for k, pose in zip(frames, poses, strict=True):
        spots = detect_spots(to_grey(rec.frame(int(k)).image), None, valid)
        if len(spots) == 0:
            continue
        q, ok = ceiling_centroids(rec.rig, height_m, spots.centroids_px, spots.cov_px)
        d, j = tree.query(vehicle_to_world(np.nan_to_num(q), *pose))
        ext = spot_extents_m(rec.rig, height_m, spots)
        for s in np.flatnonzero(ok & (d <= NEAR_M) & np.all(np.isfinite(ext), axis=1)):
            rows[j[s]].append((ext[s, 1] / ext[s, 0], ext[s, 0]))
    views = np.array([len(r) for r in rows], int)
    med = np.array([np.median(r, axis=0) if r else (math.nan, math.nan) for r in rows])
    return med[:, 0], med[:, 1], views


__all__ = ["MIN_LAMP_ROUNDNESS", "lamp_shapes"]
