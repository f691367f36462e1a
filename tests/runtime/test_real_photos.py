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
