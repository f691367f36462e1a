"""Place recognition across the three lecture rooms' real photos (``../shared/real/``,
no pose truth, skipped when absent): each user photo is given its own room's name and
no other, and the rotation between the two photos agrees with their line families."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ceilkit.calib.survey_photos import LINE_TOL_DEG, MIN_INLIERS, photo_place, recognise

REAL = Path(__file__).resolve().parents[3] / "shared" / "real"
ROOMS = ("430", "470", "560")

def _grey(room: str, kind: str) -> np.ndarray:
    """The photo as stored (4000 x 3000, EXIF orientation ignored) at half size."""
    img = cv2.imread(str(REAL / f"{room}_{kind}_photo.jpg"),
                     cv2.IMREAD_REDUCED_GRAYSCALE_2 | cv2.IMREAD_IGNORE_ORIENTATION)
    assert img is not None
    return img


@pytest.fixture(scope="module")
def results():
    if not (REAL / "430_db_photo.jpg").exists():
        pytest.skip(f"no real photos in {REAL}")
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


def test_each_user_photo_is_named_as_its_room(results):
    """Measured (agreeing matches, user photo against 430 / 470 / 560): 430: 63 / 13 /
    20; 470: 11 / 121 / 27; 560: 11 / 11 / 35."""
    for room, r in results.items():
        assert r.site == room, (room, r.reason, r.inliers)
    cross = [n for room, r in results.items() for other, n in r.inliers.items()
             if other != room]
    assert max(cross) < MIN_INLIERS, cross


def test_the_rotation_agrees_with_the_line_families(results):
    """Own room: each of the user photo's two strongest line families, turned by the
    rotation the matches imply, lies within 5 deg of one of the database photo's
    (measured at most 3.95 deg); another room's chance match implies a rotation the
    lines refuse (the worse family measured 36.9 deg off or more)."""
    for room, r in results.items():
        for other, c in r.checks.items():
            assert len(c.line_error_deg) == 2, (room, other, c)
            if other == room:
                assert c.lines_agree, (room, c.line_error_deg)
            else:
                assert max(c.line_error_deg) > 3 * LINE_TOL_DEG, (room, other, c)


def _grid_photo(R_cw: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A grid of bright lines on a plane 3 m above the camera (along x and y every
    0.4 m), photographed by a camera turned by ``R_cw`` (world to camera)."""
    img = np.full((size[1], size[0]), 60, np.uint8)
    for along in (0, 1):
        for c in np.arange(-4.0, 4.01, 0.4):
            s = np.linspace(-6.0, 6.0, 400)
            pts = np.zeros((400, 3))
            pts[:, along], pts[:, 1 - along], pts[:, 2] = s, c, 3.0
            cam = pts @ R_cw.T
            front = cam[:, 2] > 0.1
            px = cam[front] @ K.T
            px = px[:, :2] / px[:, 2:]
            cv2.polylines(img, [np.round(px * 16).astype(np.int32)], False, 220, 3,
                          cv2.LINE_AA, shift=4)
    return img


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0])
def test_line_families_are_the_grids_directions(tilt_deg):
    """Synthetic (needs no photo): the two strongest families are the grid's two
    directions in the camera frame, within 0.5 deg."""
    from ceilkit.calib.survey_photos import guessed_K, line_families

    size = (1200, 900)
    K = guessed_K((size[1], size[0]))
    a, t = np.radians(20.0), np.radians(tilt_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    R_cw = Rx @ Rz
    fams, share = line_families(_grid_photo(R_cw, K, size), K)
    assert len(fams) >= 2 and share[0] > 0.2 and share[1] > 0.2, share
    for axis in (R_cw[:, 0], R_cw[:, 1]):
        err = np.degrees(np.arccos(np.clip(np.max(np.abs(fams[:2] @ axis)), 0, 1)))
        assert err < 0.5, (tilt_deg, err)
