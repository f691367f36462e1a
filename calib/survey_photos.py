"""Which surveyed place a photograph is of, with no calibration: place recognition
between sites (rooms) from single photos (issue 39, item 4).

A site's *photo place* (:func:`photo_place`) is one photograph's SIFT keypoints and
descriptors, in pixels. The photos need no calibration and no known pose: a query is
matched against every site's place by descriptors (ratio test 0.8), and the matches
are checked by the two-view epipolar geometry (a fundamental matrix, MAGSAC, within
:data:`EPIPOLAR_PX` pixels), which holds for any two views of one rigid scene,
beams, ducts and lamps hanging below the ceiling included (a homography would hold
for the ceiling plane alone). :func:`recognise` accepts the site with the most
agreeing matches only when it has at least :data:`MIN_INLIERS` and the runner-up
site has at most 1 / :data:`SINGLE_OUT` of them; otherwise the photo is
``ambiguous`` (or ``unmatched``), never assigned by a guess.

Example::

    places = {room: photo_place(read_grey(db_photo)) for room, db_photo in rooms}
    r = recognise(photo_place(read_grey(user_photo)), places)
    r.site, r.reason, r.inliers          # "470", "", {"430": 34, "470": 137, ...}
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SIFT_FEATURES = 4000
RATIO = 0.8
EPIPOLAR_PX = 1.5
MIN_INLIERS = 30
SINGLE_OUT = 1.5


@dataclass(frozen=True, eq=False)
class PhotoPlace:
    """One photo's keypoints ``(N, 2)`` (px) and SIFT descriptors ``(N, 128)``."""

    points_px: np.ndarray
    descriptors: np.ndarray


@dataclass(frozen=True, eq=False)
class Recognition:
    """The site a photo is of (``site``, None when not singled out: ``reason`` says
    ``ambiguous`` or ``unmatched``) and each site's agreeing matches."""

    site: str | None
    reason: str
    inliers: dict[str, int]


def photo_place(grey: np.ndarray) -> PhotoPlace:
    """The place of a grey photo (8-bit, any size)."""
    kp, desc = cv2.SIFT_create(SIFT_FEATURES).detectAndCompute(grey, None)
    if desc is None:
        return PhotoPlace(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32))
    return PhotoPlace(np.array([k.pt for k in kp], np.float32), desc)


def epipolar_inliers(a: PhotoPlace, b: PhotoPlace) -> int:
    """How many descriptor matches of ``a`` in ``b`` one fundamental matrix explains."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return 0
    pairs = [m for m, n in (p for p in cv2.BFMatcher(cv2.NORM_L2).knnMatch(
        a.descriptors, b.descriptors, k=2) if len(p) == 2) if m.distance < RATIO * n.distance]
    if len(pairs) < 8:
        return 0
    src = a.points_px[[m.queryIdx for m in pairs]]
    dst = b.points_px[[m.trainIdx for m in pairs]]
    _, mask = cv2.findFundamentalMat(src, dst, cv2.USAC_MAGSAC, EPIPOLAR_PX, 0.999, 10000)
    return 0 if mask is None else int(mask.sum())


def recognise(query: PhotoPlace, places: dict[str, PhotoPlace]) -> Recognition:
    """The site of ``query`` among ``places`` (module docstring)."""
    counts = {name: epipolar_inliers(query, p) for name, p in places.items()}
    ranked = sorted(counts.items(), key=lambda kv: -kv[1])
    best, n = ranked[0] if ranked else (None, 0)
    second = ranked[1][1] if len(ranked) > 1 else 0
    if n < MIN_INLIERS:
        return Recognition(None, "unmatched", counts)
    if n < SINGLE_OUT * second:
        return Recognition(None, "ambiguous", counts)
    return Recognition(best, "", counts)
