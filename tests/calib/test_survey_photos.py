"""Place recognition across the three lecture rooms' real photos (``../shared/real/``,
no pose truth, skipped when absent): a user photo is never given another room's name."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ceilkit.calib.survey_photos import photo_place, recognise

REAL = Path(__file__).resolve().parents[3] / "shared" / "real"
ROOMS = ("430", "470", "560")
pytestmark = pytest.mark.skipif(not (REAL / "430_db_photo.jpg").exists(),
                                reason=f"no real photos in {REAL}")


def _grey(room: str, kind: str) -> np.ndarray:
    """The photo as stored (4000 x 3000, EXIF orientation ignored) at half size."""
    img = cv2.imread(str(REAL / f"{room}_{kind}_photo.jpg"),
                     cv2.IMREAD_REDUCED_GRAYSCALE_2 | cv2.IMREAD_IGNORE_ORIENTATION)
    assert img is not None
    return img


@pytest.fixture(scope="module")
def results():
    cv2.setRNGSeed(0)
    places = {room: photo_place(_grey(room, "db")) for room in ROOMS}
    return {room: recognise(photo_place(_grey(room, "user")), places) for room in ROOMS}


def test_no_user_photo_is_given_another_room(results):
    for room, r in results.items():
        assert r.site in (room, None), (room, r.inliers)
        assert r.site is not None or r.reason in ("ambiguous", "unmatched")


def test_own_room_gathers_the_most_agreeing_matches(results):
    for room, r in results.items():
        assert max(r.inliers, key=r.inliers.get) == room, (room, r.inliers)
    assert sum(r.site is not None for r in results.values()) >= 1
