"""Which surveyed place a photograph is of, with no calibration: place recognition
between sites (rooms) from single photos (issue 39, item 4).

A site's *photo place* (:func:`photo_place`) is one photograph's RootSIFT keypoints and
descriptors (SIFT, each descriptor L1-normalised and square-rooted: Arandjelović and
Zisserman's RootSIFT, whose Euclidean distance is the Hellinger kernel), in pixels, and
its *line families*: the 3-D directions (camera frame) shared by most of its straight
edges (lamp rows, beams, ducts, window frames), each a vanishing point found by RANSAC
over the segments' interpretation planes. The camera is not calibrated: it is taken as
a pinhole whose focal length is the photo's 35 mm-equivalent one (:data:`FOCAL_35MM`,
the diagonal of a 36 x 24 mm frame: f = 26 / 43.3 of the diagonal in pixels), centred.

A query is matched against every site's place by descriptors (ratio test 0.8); the
matches are checked by the two-view epipolar geometry (a fundamental matrix, MAGSAC,
within :data:`EPIPOLAR_PX` pixels), which holds for any two views of one rigid scene,
beams, ducts and lamps hanging below the ceiling included (a homography would hold for
the ceiling plane alone). The rotation between the two views (the essential matrix of
those inliers with the guessed focal length, the cheirality-checked decomposition) is
then checked against what the lines say: each of the query's two strongest line
families, turned by it, must fall within :data:`LINE_TOL_DEG` of one of the site's
(:func:`verify`). A chance fundamental matrix between two rooms implies a rotation the
lines refuse.

:func:`recognise` names the site with the most agreeing matches only when it has at
least :data:`MIN_INLIERS`, its line families agree, and no other site has more than
1 / :data:`SINGLE_OUT` of its matches; otherwise the photo is ``unmatched``,
``lines disagree`` or ``ambiguous``, never assigned by a guess.

Example::

    places = {room: photo_place(read_grey(db_photo)) for room, db_photo in rooms}
    r = recognise(photo_place(read_grey(user_photo)), places)
    r.site, r.reason, r.inliers          # "470", "", {"430": 11, "470": 121, ...}
    r.checks["470"].line_error_deg       # (0.5, 0.8): the rotation agrees with the lines
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

SIFT_FEATURES = 8000
RATIO = 0.8
EPIPOLAR_PX = 1.5
MIN_INLIERS = 30
SINGLE_OUT = 1.5
FOCAL_35MM = 26.0
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
MIN_SEGMENT_PX = 30
FAMILY_TOL_DEG = 1.0
LINE_TOL_DEG = 5.0
FAMILIES = 3
VP_TRIALS = 2000


@dataclass(frozen=True, eq=False)
class PhotoPlace:
    """One photo's keypoints ``(N, 2)`` (px), RootSIFT descriptors ``(N, 128)``, the
    guessed intrinsics ``K`` (3, 3), and its line families ``(F, 3)`` (unit directions
    in the camera frame, strongest first) with each one's share of the segments'
    length ``(F,)``."""

    points_px: np.ndarray
    descriptors: np.ndarray
    K: np.ndarray
    families: np.ndarray
    family_share: np.ndarray


@dataclass(frozen=True, eq=False)
class PairCheck:
    """A query against one place: ``inliers`` (matches one fundamental matrix explains),
    ``rotation_deg`` (the angle of the rotation between the views, NaN when none),
    ``line_error_deg`` (each of the query's two strongest families, turned by that
    rotation, from the nearest of the place's: degrees) and whether they agree."""

    inliers: int
    rotation_deg: float = math.nan
    line_error_deg: tuple[float, ...] = ()

    @property
    def lines_agree(self) -> bool:
        return bool(self.line_error_deg) and max(self.line_error_deg) <= LINE_TOL_DEG


@dataclass(frozen=True, eq=False)
class Recognition:
    """The site a photo is of (``site``, None when not singled out: ``reason`` says
    ``unmatched``, ``lines disagree`` or ``ambiguous``), each site's agreeing matches
    and each site's :class:`PairCheck`."""

    site: str | None
    reason: str
    inliers: dict[str, int]
    checks: dict[str, PairCheck]


def guessed_K(shape: tuple[int, ...], focal_35mm: float = FOCAL_35MM) -> np.ndarray:
    """A centred pinhole for an image of ``shape`` (rows, cols) from its 35 mm-equivalent
    focal length (mm)."""
    h, w = shape[:2]
    f = focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(w, h)
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def line_families(grey: np.ndarray, K: np.ndarray, count: int = FAMILIES
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` strongest line families of a photo: ``(directions (F, 3), share
    (F,))``, each the direction (camera frame) whose vanishing point the segments'
    interpretation planes meet within :data:`FAMILY_TOL_DEG`, chosen by RANSAC over
    pairs of segments (length-weighted, seeded) and refined by least squares; each
    family's segments are removed before the next is sought."""
    seg = cv2.ximgproc.createFastLineDetector(MIN_SEGMENT_PX).detect(grey)
    if seg is None or len(seg) < 2:
        return np.zeros((0, 3)), np.zeros(0)
    seg = seg.reshape(-1, 4).astype(float)
    Ki = np.linalg.inv(K)
    n = np.cross(np.c_[seg[:, :2], np.ones(len(seg))] @ Ki.T,
                 np.c_[seg[:, 2:], np.ones(len(seg))] @ Ki.T)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    w = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    tol = math.sin(math.radians(FAMILY_TOL_DEG))
    rng = np.random.default_rng(0)
    alive = np.ones(len(seg), bool)
    dirs, shares = [], []
    for _ in range(count):
        idx = np.flatnonzero(alive)
        if len(idx) < 2:
            break
        pick = rng.choice(idx, (VP_TRIALS, 2), p=w[idx] / w[idx].sum())
        cand = np.cross(n[pick[:, 0]], n[pick[:, 1]])
        norm = np.linalg.norm(cand, axis=1)
        cand = cand[norm > 1e-9] / norm[norm > 1e-9, None]
        support = (np.abs(n[idx] @ cand.T) < tol).T @ w[idx]
        d = cand[int(np.argmax(support))]
        members = idx[np.abs(n[idx] @ d) < tol]
        d = np.linalg.svd(n[members] * w[members, None])[2][-1]
        members = idx[np.abs(n[idx] @ d) < tol]
        dirs.append(d)
        shares.append(float(w[members].sum() / w.sum()))
        alive[members] = False
    return np.array(dirs).reshape(-1, 3), np.array(shares)


def photo_place(grey: np.ndarray, focal_35mm: float = FOCAL_35MM) -> PhotoPlace:
    """The place of a grey photo (8-bit, any size; the focal length its 35 mm-equivalent
    one, mm)."""
    K = guessed_K(grey.shape, focal_35mm)
    fams, share = line_families(grey, K)
    kp, desc = cv2.SIFT_create(SIFT_FEATURES).detectAndCompute(grey, None)
    if desc is None:
        return PhotoPlace(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), K,
                          fams, share)
    desc = np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-9)).astype(np.float32)
    return PhotoPlace(np.array([k.pt for k in kp], np.float32), desc, K, fams, share)


def _rotation(a: PhotoPlace, b: PhotoPlace, src: np.ndarray, dst: np.ndarray
              ) -> np.ndarray | None:
    """The rotation from ``a``'s camera frame to ``b``'s of the inlier matches (the
    essential matrix with the guessed intrinsics, its cheirality-checked decomposition),
    or None."""
    if len(src) < 5:
        return None
    sn = cv2.undistortPoints(src.reshape(-1, 1, 2), a.K, None).reshape(-1, 2)
    dn = cv2.undistortPoints(dst.reshape(-1, 1, 2), b.K, None).reshape(-1, 2)
    E, mask = cv2.findEssentialMat(sn, dn, np.eye(3), cv2.USAC_MAGSAC, 0.999,
                                   EPIPOLAR_PX / a.K[0, 0])
    if E is None or E.shape != (3, 3):
        return None
    _, R, _, _ = cv2.recoverPose(E, sn, dn, np.eye(3), mask=mask)
    return R


def verify(a: PhotoPlace, b: PhotoPlace) -> PairCheck:
    """Query ``a`` against place ``b`` (module docstring)."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return PairCheck(0)
    pairs = [m for m, n in (p for p in cv2.BFMatcher(cv2.NORM_L2).knnMatch(
        a.descriptors, b.descriptors, k=2) if len(p) == 2) if m.distance < RATIO * n.distance]
    if len(pairs) < 8:
        return PairCheck(0)
    src = a.points_px[[m.queryIdx for m in pairs]]
    dst = b.points_px[[m.trainIdx for m in pairs]]
    _, mask = cv2.findFundamentalMat(src, dst, cv2.USAC_MAGSAC, EPIPOLAR_PX, 0.999, 10000)
    if mask is None:
        return PairCheck(0)
    ok = mask.ravel().astype(bool)
    R = _rotation(a, b, src[ok], dst[ok])
    if R is None or not len(a.families) or not len(b.families):
        return PairCheck(int(ok.sum()))
    turned = a.families[:2] @ R.T
    err = np.degrees(np.arccos(np.clip(np.max(np.abs(turned @ b.families.T), axis=1), 0, 1)))
    angle = math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    return PairCheck(int(ok.sum()), angle, tuple(round(float(e), 2) for e in err))


def epipolar_inliers(a: PhotoPlace, b: PhotoPlace) -> int:
    """How many descriptor matches of ``a`` in ``b`` one fundamental matrix explains."""
    return verify(a, b).inliers


def recognise(query: PhotoPlace, places: dict[str, PhotoPlace]) -> Recognition:
    """The site of ``query`` among ``places`` (module docstring)."""
    checks = {name: verify(query, p) for name, p in places.items()}
    counts = {name: c.inliers for name, c in checks.items()}
    ranked = sorted(counts.items(), key=lambda kv: -kv[1])
    best, n = ranked[0] if ranked else (None, 0)
    second = ranked[1][1] if len(ranked) > 1 else 0
    if n < MIN_INLIERS:
        return Recognition(None, "unmatched", counts, checks)
    if not checks[best].lines_agree:
        return Recognition(None, "lines disagree", counts, checks)
    if n < SINGLE_OUT * second:
        return Recognition(None, "ambiguous", counts, checks)
    return Recognition(best, "", counts, checks)
