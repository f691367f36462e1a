"""Real ceiling photographs (``../shared/real/``, read from there, never copied; no pose
truth): what can be checked without truth (issue 16). Skipped when absent."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.registry import make_estimator

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "real"
CONFIGS = ROOT / "configs"
PHOTOS = sorted(REAL.glob("*_photo.jpg")) if REAL.is_dir() else []
pytestmark = pytest.mark.skipif(not PHOTOS, reason=f"no real photos in {REAL}")


def _frame(path: Path, size: tuple[int, int]) -> np.ndarray:
    """The photo as stored (EXIF orientation ignored: 4000 x 3000), decoded at a quarter
    and resized to the rig camera's ``(width, height)``."""
    img = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_4 | cv2.IMREAD_IGNORE_ORIENTATION)
    assert img is not None, path
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("method", ["corridor", "lights"])
def test_no_valid_pose_from_a_site_that_does_not_fit(method):
    """The packaged example site is not these rooms: no photo may give a valid pose
    (quality >= 0.5, NMEA A with a confident covariance)."""
    rig = Rig.load(CONFIGS / method / "rig.yaml")
    site = Site.load(CONFIGS / method / "site.yaml")
    est = make_estimator(method, rig, site)
    for p in PHOTOS:
        e = est.estimate(_frame(p, (rig.camera.width, rig.camera.height)), 0)
        assert not (isinstance(e, PoseEstimate) and e.quality >= 0.5), (p.name, e)
        assert isinstance(e, PoseEstimate) or e.reason != "bad_frame", (p.name, e)


def test_lamps_are_found_as_bright_regions():
    """Each photo holds rows of fluorescent lamps: the spot detector finds bright
    regions in every one (at the lights rig's working size)."""
    from ceilkit.runtime.features.spots import detect_spots

    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    for p in PHOTOS:
        grey = _frame(p, (rig.camera.width, rig.camera.height))
        spots = detect_spots(grey)
        assert len(spots) >= 5, (p.name, len(spots))
        # they are bright: most centroids on pixels well above the frame's median (some
        # are windows, reflections or a lamp's darker end: the map rejects those)
        c = np.round(spots.centroids_px).astype(int)
        assert np.median(grey[c[:, 1], c[:, 0]]) > np.median(grey) + 15, p.name


# --- line families against an independent vanishing-point estimate (issue 16 item 5) ---
# Camera: no calibration is published (README beside the photos); a pinhole with the EXIF
# focal length, f = 3000 px at 4000 x 3000, so 750 px at the quarter-size decode, the
# principal point at the centre, no distortion.
F_QUARTER_PX = 750.0
VP_TOL_DEG = 1.5  # measured worst 0.56 deg (430_user, 2nd family); under the 2 deg band


def _normalized_segments(path: Path) -> np.ndarray:
    from ceilkit.runtime.features.lines import SegmentDetector

    img = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_4 | cv2.IMREAD_IGNORE_ORIENTATION)
    assert img is not None, path
    segs = SegmentDetector("fld", min_length_px=40)(img)
    h, w = img.shape
    s = segs.copy()
    s[:, 0::2] = (s[:, 0::2] - (w - 1) / 2) / F_QUARTER_PX
    s[:, 1::2] = (s[:, 1::2] - (h - 1) / 2) / F_QUARTER_PX
    return s


def _project_families(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The corridor method's code: dominant pan and families (camera taken as level,
    10 deg), then free vanishing points of each family, regrouped at 2 deg (4 rounds).
    Returns the two VPs ``(2, 3)`` and each family's share of segment length."""
    from ceilkit.runtime.estimators.corridor.geometry import free_vanishing_points, vanishing_angles
    from ceilkit.runtime.estimators.corridor.hypotheses import dominant_pans, families
    from ceilkit.runtime.features.lines import segment_lengths, segment_lines

    L, w = segment_lines(s), segment_lengths(s)
    mx, my = (s[:, 0] + s[:, 2]) / 2, (s[:, 1] + s[:, 3]) / 2
    psi = dominant_pans(L, w)[0]
    ang, _ = vanishing_angles(psi, np.eye(3), np.ascontiguousarray(L.T), mx, my)
    along, across = families(ang, np.deg2rad(10.0))
    for _ in range(4):
        V = free_vanishing_points(L, np.vstack([w * along, w * across]))
        vz = V[:, 2:]
        den = np.maximum(np.hypot(V[:, :1] - vz * mx, V[:, 1:2] - vz * my), 1e-12)
        along, across = families(np.abs(V @ L.T) / den, np.deg2rad(2.0))
    return V, np.array([w[along].sum(), w[across].sum()]) / w.sum()


def _ransac_vps(s: np.ndarray, k: int = 2, n_iter: int = 1500, tol_deg: float = 1.5,
                seed: int = 0) -> list[tuple[np.ndarray, float]]:
    """Independent estimate: sequential RANSAC over pairs of segments; a candidate is
    the cross product of their lines, its support the length of segments pointing at
    it (angle between a segment and the ray from its midpoint to the point). Returns
    ``k`` (unit VP, share of length) pairs, strongest first."""
    rng = np.random.default_rng(seed)
    p1 = np.hstack([s[:, :2], np.ones((len(s), 1))])
    p2 = np.hstack([s[:, 2:], np.ones((len(s), 1))])
    lines = np.cross(p1, p2)
    d = s[:, 2:] - s[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    d = d / length[:, None]
    mid = (s[:, :2] + s[:, 2:]) / 2

    def angles(v: np.ndarray) -> np.ndarray:
        t = v[:2] - v[2] * mid
        t = t / np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-12)[:, None]
        return np.degrees(np.arcsin(np.clip(np.abs(t[:, 0] * d[:, 1] - t[:, 1] * d[:, 0]),
                                            0, 1)))

    alive = np.ones(len(s), bool)
    out = []
    for _ in range(k):
        idx = np.flatnonzero(alive)
        best, best_score = None, -1.0
        for _ in range(n_iter):
            i, j = rng.choice(idx, 2, replace=False)
            v = np.cross(lines[i], lines[j])
            if np.linalg.norm(v) < 1e-12:
                continue
            v = v / np.linalg.norm(v)
            score = length[alive & (angles(v) < tol_deg)].sum()
            if score > best_score:
                best, best_score = v, score
        inl = alive & (angles(best) < tol_deg)
        out.append((best, float(length[inl].sum() / length.sum())))
        alive &= ~inl
    return out


def test_line_families_agree_with_an_independent_vanishing_point_estimate():
    """The lamp rows and beams form two line families; the corridor method's family
    grouping and vanishing points agree with a plain RANSAC's (angle between the VP
    directions through the pinhole) within 1.5 deg. The dominant family is checked on
    every photo; the second where the project's grouping gives it at least 15 % of the
    segment length (not the 470 photos: the level-camera seed 90 deg from the dominant
    pan catches only 6-10 % there, and its VP drifts 3.4 and 15 deg off RANSAC's)."""
    checked_second = 0
    for p in PHOTOS:
        s = _normalized_segments(p)
        V, share = _project_families(s)
        for k, (v, ransac_share) in enumerate(_ransac_vps(s)):
            err = min(np.degrees(np.arccos(min(1.0, abs(float(v @ u))))) for u in V)
            if k == 0:
                assert ransac_share > 0.5, (p.name, ransac_share)
                assert err < VP_TOL_DEG, (p.name, "dominant", err)
            elif min(share) >= 0.15:
                checked_second += 1
                assert err < VP_TOL_DEG, (p.name, "second", err)
    assert checked_second >= 3 or len(PHOTOS) < 6, checked_second
