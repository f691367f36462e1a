"""Intrinsics on rendered boards (known lens) and on OpenCV's left*.jpg sample images."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ceilkit.calib.boards import CharucoBoard, ChessBoard, Detection, render_views
from ceilkit.calib.intrinsics import (
    RMS_CONVENTION,
    DetectionCache,
    StopRule,
    calibrate_intrinsics,
    capture_views,
    detect_images,
    image_files,
    write_plots,
)
from ceilkit.runtime.config.camera import load_camera, save_camera
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.io.capture import open_video
from ceilkit.runtime.io.sources import Frame, ListSource

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "opencv_left"
K_TRUE = np.array([[500.0, 0.0, 322.3], [0.0, 502.0, 236.8], [0.0, 0.0, 1.0]])
PLUMB = CameraModel(640, 480, K_TRUE, [-0.25, 0.08, 0.001, -0.0008, 0.0], "plumb_bob")
FISH = CameraModel(640, 480, np.array([[260.0, 0, 321.0], [0, 261.0, 238.0], [0, 0, 1]]),
                   [0.05, -0.02, 0.01, -0.003], "equidistant")
RATIONAL = CameraModel(640, 480, np.array([[420.0, 0, 318.0], [0, 421.0, 243.0], [0, 0, 1]]),
                       [0.4, -0.05, 0.0005, -0.0004, 0.0, 0.75, 0.02, 0.0],
                       "rational_polynomial")
CHESS = ChessBoard(9, 6, 0.03)
CHARUCO = CharucoBoard(8, 6, 0.04, 0.03, "4X4_50")
_CACHE: dict = {}


def views(board, camera, seed, n=15):
    key = (board.spec, camera.model, seed, n)
    if key not in _CACHE:
        _CACHE[key] = render_views(board, camera, n, np.random.default_rng(seed),
                                   noise_sigma=1.0, blur_sigma_px=0.6,
                                   max_tilt_deg=50.0)
    return _CACHE[key]


def detections(board, camera, seed, n=15):
    """Detections of :func:`views`, computed once per module (a fresh list each call)."""
    key = ("det", board.spec, camera.model, seed, n)
    if key not in _CACHE:
        out = [board.detect(img, f"v{i:02d}") for i, (img, _, _) in enumerate(
            views(board, camera, seed, n))]
        _CACHE[key] = [d for d in out if d is not None]
    return list(_CACHE[key])


def test_chessboard_meets_the_targets_with_honest_sigma():
    """Focal length within 0.2 % and principal point within 1 px, over seeds, and the
    normalized errors' RMS near one. 15 views were too few for 1 px: sigma(cy) was
    0.3-0.5 px and one seed landed 1.1 px off (2.4 sigma); with 30 views sigma is
    0.2-0.3 px and every seed is within 0.6 px (no bias: error / sigma has RMS ~1)."""
    z = []
    for seed in (1, 3):
        res = calibrate_intrinsics(detections(CHESS, PLUMB, seed, n=30), "plumb_bob")
        rep = res.report
        assert rep.n_views >= 28
        assert abs(res.camera.fx / PLUMB.fx - 1) < 0.002
        assert abs(res.camera.fy / PLUMB.fy - 1) < 0.002
        assert abs(res.camera.cx - PLUMB.cx) < 1.0 and abs(res.camera.cy - PLUMB.cy) < 1.0
        assert max(rep.sigma("cx"), rep.sigma("cy")) < 0.4
        truth = (PLUMB.fx, PLUMB.fy, PLUMB.cx, PLUMB.cy)
        z += [(p - t) / s for p, t, s in zip(rep.params[:4], truth, rep.sigmas[:4],
                                             strict=True)]
    assert 0.3 < np.sqrt(np.mean(np.square(z))) < 2.0


@pytest.mark.parametrize("board,camera,model", [
    (CHARUCO, PLUMB, "plumb_bob"), (CHESS, FISH, "equidistant"),
    (CHESS, RATIONAL, "rational_polynomial")])
def test_recovers_known_lens(board, camera, model):
    res = calibrate_intrinsics(detections(board, camera, 1, n=20 if model[0] == "r" else 15),
                               model)
    rep = res.report
    assert res.camera.model == model
    assert abs(res.camera.fx / camera.fx - 1) < 0.002
    assert abs(res.camera.fy / camera.fy - 1) < 0.002
    assert abs(res.camera.cx - camera.cx) < 1.0 and abs(res.camera.cy - camera.cy) < 1.0
    # the lens: where the corners reached, the model's pixels match the truth's
    pts = np.concatenate([v.points_px for v in res.views])
    err = np.linalg.norm(res.camera.distort(camera.unproject(pts)) - pts, axis=1)
    assert np.max(err) < 1.0, np.max(err)
    assert rep.rms_px < 0.3 and rep.n_views >= 10
    assert len(rep.params) == len(rep.sigmas) == 4 + camera.dist.size
    assert all(s > 0 for s in rep.sigmas)


def test_reported_sigma_matches_actual_errors():
    z = []
    for seed in (1, 2, 3):
        rep = calibrate_intrinsics(detections(CHARUCO, PLUMB, seed), "plumb_bob").report
        truth = (PLUMB.fx, PLUMB.fy, PLUMB.cx, PLUMB.cy)
        z += [(p - t) / s for p, t, s in zip(rep.params[:4], truth, rep.sigmas[:4],
                                             strict=True)]
    assert np.sqrt(np.mean(np.square(z))) < 2.0


def test_report_contents_and_text():
    res = calibrate_intrinsics(detections(CHESS, PLUMB, 1), "plumb_bob")
    rep = res.report
    assert rep.cross_max_px is not None and rep.cross_rms_px <= rep.cross_max_px
    assert 0 < rep.coverage <= 1
    assert len(rep.view_rms_px) == rep.n_views == len(res.views) == len(res.rvecs)
    worst = rep.worst_views(2)
    assert worst[0][1] == max(rep.view_rms_px)
    text = rep.text()
    assert RMS_CONVENTION in text and "fx" in text and "cross-validation" in text
    assert abs(rep.sigma("fx") - rep.sigmas[0]) == 0


def test_outlier_view_and_corner_are_dropped():
    dets = detections(CHESS, PLUMB, 1)
    rng = np.random.default_rng(5)
    bad_view = dets[3]
    shifted = Detection(bad_view.name, bad_view.image_size, bad_view.ids,
                        bad_view.points_px + rng.normal(0, 4.0, bad_view.points_px.shape),
                        bad_view.points_board)
    one = dets[5].points_px.copy()
    one[7] += (6.0, -4.0)
    bad_corner = Detection(dets[5].name, dets[5].image_size, dets[5].ids, one,
                           dets[5].points_board)
    dets = dets[:3] + [shifted, dets[4], bad_corner] + dets[6:]
    res = calibrate_intrinsics(dets, "plumb_bob")
    assert bad_view.name in res.report.dropped_views
    assert res.report.dropped_corners >= 1
    kept5 = next(v for v in res.views if v.name == dets[5].name)
    assert 7 not in kept5.ids
    assert any("dropped" in w for w in res.report.warnings)
    assert abs(res.camera.fx / PLUMB.fx - 1) < 0.003


def test_too_few_views_and_mixed_sizes_and_bad_model():
    dets = detections(CHESS, PLUMB, 1)
    with pytest.raises(CalibrationError, match="too few views"):
        calibrate_intrinsics(dets[:3])
    odd = Detection("odd", (800, 600), dets[0].ids, dets[0].points_px, dets[0].points_board)
    with pytest.raises(ConfigError, match="mixed image sizes"):
        calibrate_intrinsics(dets + [odd])
    with pytest.raises(ConfigError, match="model"):
        calibrate_intrinsics(dets, "pinhole")


@pytest.fixture
def image_folder(tmp_path):
    folder = tmp_path / "shots"
    folder.mkdir()
    for i, (img, _, _) in enumerate(views(CHESS, PLUMB, 1)):
        cv2.imwrite(str(folder / f"v{i:02d}.png"), img)
    return folder


def test_detect_images_uses_cache(image_folder, tmp_path):
    files = image_files(image_folder)
    cache_path = tmp_path / "det.npz"
    first = detect_images(files, CHESS, cache_path)
    assert cache_path.is_file()
    cache = DetectionCache(cache_path)
    again = detect_images(files, CHESS, cache)
    assert cache.hits == len(files)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a.points_px, b.points_px)
    # a changed file is detected again
    cv2.imwrite(str(files[0]), np.full((480, 640), 128, np.uint8))
    cache = DetectionCache(cache_path)
    third = detect_images(files, CHESS, cache)
    assert cache.hits == len(files) - 1 and len(third) == len(first) - 1


def test_detect_images_errors(image_folder):
    files = image_files(image_folder)
    with pytest.raises(ConfigError, match=r"board: .*did you mean chess:9x6\?"):
        detect_images(files[:2], ChessBoard(8, 6, 0.03))
    bad = image_folder / "zz_corrupt.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(ConfigError, match="zz_corrupt.png"):
        detect_images(image_files(image_folder), CHESS)
    bad.unlink()
    cv2.imwrite(str(image_folder / "zz_big.png"), np.zeros((600, 800), np.uint8))
    with pytest.raises(ConfigError, match="mixed image sizes"):
        detect_images(image_files(image_folder), CHESS)


def test_capture_views_keeps_diverse_frames_and_draws_meter():
    frames = []
    for i, (img, _, _) in enumerate(views(CHESS, PLUMB, 1)):
        for k in range(2):                             # each view twice: one is redundant
            frames.append(Frame(img, (2 * i + k) * 1000, 2 * i + k))
    meter = io.StringIO()
    kept = capture_views(ListSource(frames), CHESS, meter=meter,
                         stop=StopRule(min_views=10, max_views=40))
    names = [d.name for d in kept]
    assert len(kept) <= len(frames) // 2 and len(set(names)) == len(names)
    assert "position [" in meter.getvalue() and "views" in meter.getvalue()
    res = calibrate_intrinsics(kept)
    assert abs(res.camera.fx / PLUMB.fx - 1) < 0.003


def test_capture_views_from_video_file(tmp_path):
    path = tmp_path / "board.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480))
    assert vw.isOpened()
    for img, _, _ in views(CHESS, PLUMB, 1):
        vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    vw.release()
    kept = capture_views(open_video(str(path)), CHESS, meter=None)
    assert len(kept) >= 10 and kept[0].name.startswith("frame")


def test_capture_views_without_board_is_an_error():
    blank = [Frame(np.full((120, 160), 100, np.uint8), i, i) for i in range(3)]
    with pytest.raises(CalibrationError, match="no chess:9x6 board"):
        capture_views(ListSource(blank), CHESS, meter=None)


def test_write_plots(tmp_path):
    res = calibrate_intrinsics(detections(CHESS, PLUMB, 1))
    paths = write_plots(res, tmp_path / "plots")
    assert [p.name for p in paths] == ["views.png", "coverage.png", "distortion.png"]
    for p in paths:
        img = cv2.imread(str(p))
        assert img is not None and img.std() > 5


def test_camera_round_trip(tmp_path):
    res = calibrate_intrinsics(detections(CHESS, PLUMB, 1))
    save_camera(res.camera, tmp_path / "camera.yaml", "# test\n")
    back = load_camera(tmp_path / "camera.yaml")
    np.testing.assert_allclose(back.K, res.camera.K)
    np.testing.assert_allclose(back.dist, res.camera.dist)


# -- OpenCV's sample images left01..14.jpg and their published calibration ------------------
#
# The published calibration (left_intrinsics.yml) is OpenCV's sample: findChessboardCorners,
# cornerSubPix with an 11 x 11 half-window, one focal length, no rejection. In left02.jpg
# the board is foreshortened to 22 px squares and that window moves its corners by up to
# 6 px; the single view pulls fx up by 2.6 px and cy by 1.5 px. These tests show it and
# check that the same procedure agrees with ours within our 1 sigma once that one view is
# measured properly.

def _published():
    text = (FIXTURES / "left_intrinsics.yml").read_text().replace("%YAML:1.0", "")
    text = text.replace("!!opencv-matrix", "")
    return yaml.safe_load(text)


@pytest.fixture(scope="module")
def left(tmp_path_factory):
    """``(ours, sample)``: detections by our default detector and by OpenCV's sample's."""
    folder = tmp_path_factory.mktemp("left")
    for f in FIXTURES.glob("left*.jpg"):
        shutil.copy(f, folder)
    files = image_files(folder)
    return (detect_images(files, ChessBoard(9, 6, 0.025)),
            detect_images(files, ChessBoard(9, 6, 0.025, detector="classic", subpix_half=11)))


def _pose_fit_rms(camera, det):
    """RMS (px) of ``det`` reprojected through ``camera`` with its own best pose."""
    _, rvec, tvec = cv2.solvePnP(det.points_board, det.points_px, camera.K, camera.dist)
    rvec, tvec = cv2.solvePnPRefineLM(det.points_board, det.points_px, camera.K, camera.dist,
                                      rvec, tvec)
    px, _ = cv2.projectPoints(det.points_board, rvec, tvec, camera.K, camera.dist)
    return float(np.sqrt(np.mean(np.sum((px.reshape(-1, 2) - det.points_px) ** 2, axis=1))))


def test_reproduces_published_calibration_of_opencv_samples(left):
    """OpenCV's procedure on its detections gives the published numbers within 0.1 sigma."""
    pub = _published()
    K = np.array(pub["camera_matrix"]["data"]).reshape(3, 3)
    D = np.array(pub["distortion_coefficients"]["data"])
    res = calibrate_intrinsics(left[1], fix_aspect_ratio=True, reject_outliers=False)
    rep = res.report
    assert rep.n_views == pub["nframes"]
    ours = np.array(rep.params)
    theirs = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], D])
    z = (ours - theirs) / np.array(rep.sigmas)
    assert np.all(np.abs(z) < 0.1), z
    assert abs(rep.rms_px - pub["avg_reprojection_error"]) < 0.01
    # with rejection, the sample's worst view (left02, 1.18 px) is dropped
    per_view = np.array(pub["per_view_reprojection_errors"]["data"])
    worst = sorted(f.name for f in FIXTURES.glob("left*.jpg"))[int(np.argmax(per_view))]
    assert worst == "left02.jpg"
    rejected = calibrate_intrinsics(left[1], fix_aspect_ratio=True)
    assert rejected.report.dropped_views == (worst,)


def test_default_pipeline_keeps_every_sample_view(left):
    rep = calibrate_intrinsics(left[0]).report
    assert rep.n_views == 13 and not rep.dropped_views and rep.dropped_corners == 0
    pub_rms = _published()["avg_reprojection_error"]
    assert rep.rms_px < 0.5 * pub_rms
    per_view = dict(zip(rep.view_names, rep.view_rms_px, strict=True))
    assert per_view["left02.jpg"] < 1.5 * np.median(rep.view_rms_px)


def test_published_calibration_is_biased_by_one_misdetected_view(left):
    """The evidence, all on these 13 images:

    1. left02's corners by the sample's 11 px window sit up to 6 px off the board that the
       other 12 views calibrate (its best pose leaves > 1 px RMS); ours sit within 0.3 px;
    2. the published values are over 5 of our sigmas from ours in fx (and 3 in cy);
    3. held out one at a time, the views are predicted better by our calibrations of
       the other twelve than by the sample procedure's (mean RMS 0.180 vs 0.192 px);
    4. the sample procedure with only left02's corners re-detected agrees with our
       default within 2 sigma (ours) in fx, fy, cx and cy.
    """
    ours_d, sample_d = left
    pub = _published()
    K = np.array(pub["camera_matrix"]["data"]).reshape(3, 3)
    name = "left02.jpg"
    others = calibrate_intrinsics([d for d in ours_d if d.name != name],
                                  reject_outliers=False).camera
    i02 = next(i for i, d in enumerate(ours_d) if d.name == name)
    assert _pose_fit_rms(others, sample_d[i02]) > 1.0
    assert _pose_fit_rms(others, ours_d[i02]) < 0.3

    rep = calibrate_intrinsics(ours_d).report
    sig = np.array(rep.sigmas[:4])
    z_pub = (np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]) - rep.params[:4]) / sig
    assert z_pub[0] > 5 and z_pub[1] > 5 and z_pub[3] > 3, z_pub

    held_ours, held_sample = [], []
    for i, d in enumerate(ours_d):
        a = calibrate_intrinsics(ours_d[:i] + ours_d[i + 1:], fix_aspect_ratio=True).camera
        b = calibrate_intrinsics(sample_d[:i] + sample_d[i + 1:], fix_aspect_ratio=True,
                                 reject_outliers=False).camera
        held_ours.append(_pose_fit_rms(a, d))
        held_sample.append(_pose_fit_rms(b, d))
    held_ours, held_sample = np.array(held_ours), np.array(held_sample)
    assert np.mean(held_ours) < 0.95 * np.mean(held_sample)
    assert np.sum(held_ours < held_sample) >= 10

    fixed = [o if o.name == name else s for o, s in zip(ours_d, sample_d, strict=True)]
    sample_fixed = calibrate_intrinsics(fixed, fix_aspect_ratio=True, reject_outliers=False)
    z = (np.array(sample_fixed.report.params[:4]) - rep.params[:4]) / sig
    assert np.all(np.abs(z) <= 2.0), z
