import functools

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.camera import load_camera, save_camera
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel, subpixel_rays

MODELS = [
    ("plumb_bob", [-0.25, 0.08, 0.001, -0.0005, -0.01]),
    ("rational_polynomial", [0.3, -0.1, 0.0005, 0.0002, 0.01, 0.6, -0.05, 0.02]),
    ("equidistant", [0.05, -0.01, 0.002, -0.0005]),
]


def test_pinhole_projects_principal_point_and_known_pixel():
    cam = CameraModel.pinhole(640, 480, fx=500.0)
    assert np.allclose(cam.project(np.array([[0.0, 0.0, 2.0]])), [[319.5, 239.5]])
    assert np.allclose(cam.project(np.array([[0.1, -0.2, 1.0]])), [[369.5, 139.5]])
    assert np.isnan(cam.project(np.array([[0.0, 0.0, -1.0]]))).all()


@pytest.mark.parametrize("model,dist", MODELS)
def test_project_unproject_round_trip(model, dist):
    cam = CameraModel.pinhole(640, 480, fx=300.0, dist=dist, model=model)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.8, 0.8, size=(300, 2))
    px = cam.project(np.hstack([xy, np.ones((300, 1))]))
    assert np.allclose(cam.unproject(px), xy, atol=1e-9)
    rays = cam.rays(px)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    assert np.allclose(rays[:, :2] / rays[:, 2:], xy, atol=1e-9)


@pytest.mark.parametrize("model,dist", MODELS)
def test_save_load_round_trip(tmp_path, model, dist):
    cam = CameraModel.pinhole(800, 600, fx=410.0, fy=412.0, cx=401.0, cy=297.5, dist=dist,
                              model=model, name="cam0")
    save_camera(cam, tmp_path / "camera.yaml", header="# test\n")
    back = load_camera(tmp_path / "camera.yaml")
    assert back.model == model and back.name == "cam0" and back.size == (800, 600)
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
    assert np.array_equal(back.P, cam.P)


def test_scaled_keeps_the_field_of_view():
    cam = CameraModel.pinhole(640, 480, fx=400.0)
    big = cam.scaled(1280, 960)
    p = np.array([[0.3, 0.2, 1.0]])
    assert np.allclose((big.project(p) + 0.5) / 2.0 - 0.5, cam.project(p))


GOOD = """image_width: 640
image_height: 480
camera_name: c
camera_matrix: {rows: 3, cols: 3, data: [400, 0, 319.5, 0, 400, 239.5, 0, 0, 1]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}
"""


@pytest.mark.parametrize("old,new,key,words", [
    ("camera_name: c", "camera_nam: c", "camera_nam", "unknown key"),
    ("image_width: 640", "image_width: -3", "image_width", "integer"),
    ("image_width: 640", "image_width: wide", "image_width", "integer"),
    ("data: [400, 0, 319.5", "data: [-400, 0, 319.5", "camera_matrix", "positive"),
    ("319.5, 0, 400, 239.5", "919.5, 0, 400, 239.5", "camera_matrix", "outside"),
    ("rows: 1, cols: 5, data: [0, 0, 0, 0, 0]", "rows: 1, cols: 4, data: [0, 0, 0, 0]",
     "distortion_coefficients", "5 coefficients"),
    ("distortion_model: plumb_bob", "distortion_model: fisheye", "distortion_model",
     "plumb_bob"),
    ("rows: 3, cols: 3, data: [400, 0, 319.5, 0, 400, 239.5, 0, 0, 1]",
     "rows: 3, cols: 3, data: [400, 0, 319.5, 0, 400, 239.5, 0, 0]", "camera_matrix.data",
     "9 numbers"),
])
def test_bad_camera_files_name_file_and_key(tmp_path, old, new, key, words):
    path = tmp_path / "camera.yaml"
    assert old in GOOD
    path.write_text(GOOD.replace(old, new))
    with pytest.raises(ConfigError) as err:
        load_camera(path)
    msg = str(err.value)
    assert str(path) in msg and key in msg and words in msg
    assert "\n" not in msg


def test_missing_and_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_camera(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("image_width: [640\n")
    with pytest.raises(ConfigError, match="invalid YAML at line"):
        load_camera(tmp_path / "bad.yaml")
    (tmp_path / "missing.yaml").write_text(GOOD.replace("image_height: 480\n", ""))
    with pytest.raises(ConfigError, match="image_height: missing required key"):
        load_camera(tmp_path / "missing.yaml")


# What ROS camera_calibration writes (its `ost.yaml`): block style, the 8 keys, numbers
# printed with %8f, a camera_name with a slash.
ROS_OST = """image_width: 640
image_height: 480
camera_name: narrow_stereo/left
camera_matrix:
  rows: 3
  cols: 3
  data: [402.130000, 0.000000, 321.250000, 0.000000, 401.870000, 238.600000, 0.000000, \
0.000000, 1.000000]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.081000, 0.019000, 0.000400, -0.000300, 0.000000]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.000000, 0.000000, 0.000000, 0.000000, 1.000000, 0.000000, 0.000000, 0.000000, \
1.000000]
projection_matrix:
  rows: 3
  cols: 4
  data: [395.200000, 0.000000, 321.900000, 0.000000, 0.000000, 397.100000, 238.200000, \
0.000000, 0.000000, 0.000000, 1.000000, 0.000000]
"""


def test_reads_ros_camera_calibration_output(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_OST.replace("\n", "\r\n"))           # a Windows copy, too
    cam = load_camera(path)
    assert cam.size == (640, 480) and cam.name == "narrow_stereo/left"
    assert cam.model == "plumb_bob" and cam.fx == 402.13 and cam.cy == 238.6
    np.testing.assert_array_equal(cam.dist, [-0.081, 0.019, 0.0004, -0.0003, 0.0])
    assert cam.P[0, 0] == 395.2                 # kept for round trips, not used
    save_camera(cam, tmp_path / "back.yaml")
    back = load_camera(tmp_path / "back.yaml")
    np.testing.assert_array_equal(back.P, cam.P)
    np.testing.assert_array_equal(back.K, cam.K)


@pytest.mark.parametrize("coeffs,model", [
    ("[-0.08, 0.02, 0.0, 0.0, 0.0]", "plumb_bob"),
    ("[-0.08, 0.02, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0]", "rational_polynomial"),
])
def test_old_ros_files_without_distortion_model(tmp_path, coeffs, model):
    """ROS files from before `distortion_model` existed: ROS reads 5 coefficients as
    plumb_bob and 8 as rational_polynomial, and so do we."""
    text = ROS_OST.replace("distortion_model: plumb_bob\n", "").replace(
        "cols: 5\n  data: [-0.081000, 0.019000, 0.000400, -0.000300, 0.000000]",
        f"cols: {coeffs.count(',') + 1}\n  data: {coeffs}")
    (tmp_path / "c.yaml").write_text(text)
    assert load_camera(tmp_path / "c.yaml").model == model
    (tmp_path / "d.yaml").write_text(text.replace(coeffs, "[0.1, 0.0, 0.0, 0.0]")
                                     .replace(f"cols: {coeffs.count(',') + 1}", "cols: 4"))
    with pytest.raises(ConfigError, match="distortion_model: missing required key"):
        load_camera(tmp_path / "d.yaml")


@pytest.mark.parametrize("extra,key", [
    ("header: {frame_id: cam}\n", "header"),               # a camera_info message dump
    ("binning_x: 0\n", "binning_x"),
    ("distortion_coefficents:\n  rows: 1\n  cols: 0\n  data: []\n", "distortion_coefficents"),
])
def test_unknown_keys_beside_the_ros_ones_are_errors(tmp_path, extra, key):
    (tmp_path / "c.yaml").write_text(ROS_OST + extra)
    with pytest.raises(ConfigError, match=f"{key}: unknown key") as err:
        load_camera(tmp_path / "c.yaml")
    assert "c.yaml" in str(err.value)


def test_numeric_camera_name_is_a_name(tmp_path):
    (tmp_path / "c.yaml").write_text(ROS_OST.replace("narrow_stereo/left", "12345"))
    assert load_camera(tmp_path / "c.yaml").name == "12345"


# -- identity (hashable, value-based equality) ----------------------------------------------
def test_equal_cameras_hash_alike_and_key_caches():
    a = CameraModel.pinhole(640, 480, 400.0, dist=[-0.1, 0.02, 0.0, 0.0, 0.0])
    b = CameraModel(640, 480, a.K.copy(), list(a.dist), "plumb_bob")
    assert a == b and hash(a) == hash(b) and a.key == b.key
    assert a != a.scaled(320, 240) and a != CameraModel.pinhole(640, 480, 400.0)
    assert a != CameraModel(640, 480, a.K, a.dist, "plumb_bob", name="other")
    negzero = CameraModel(640, 480, a.K, [-0.1, 0.02, -0.0, 0.0, 0.0])
    assert negzero == a and hash(negzero) == hash(a)
    calls = []

    @functools.lru_cache(maxsize=4)
    def cached(cam):
        calls.append(cam)
        return cam.fx

    cached(a)
    cached(b)
    assert len(calls) == 1
    assert len({a, b, a.scaled(320, 240)}) == 2


def test_bad_model_and_coefficients_are_config_errors():
    with pytest.raises(ConfigError, match="model: expected one of plumb_bob"):
        CameraModel(640, 480, np.eye(3), np.zeros(5), "fisheye")
    with pytest.raises(ConfigError, match="dist: plumb_bob takes 5 coefficients, found 4"):
        CameraModel(640, 480, np.eye(3), np.zeros(4), "plumb_bob")


# -- lens math ------------------------------------------------------------------------------
DISTORT_CAMS = [
    CameraModel.pinhole(100, 80, 90.0, dist=[-0.1, 0.03, 0.001, -0.002, 0.01]),
    CameraModel.pinhole(100, 80, 90.0, dist=[0.05, -0.01, 0.002, 0.0], model="equidistant"),
    CameraModel.pinhole(100, 80, 90.0, dist=[0.1, -0.05, 0.001, -0.002, 0.01, 0.02, -0.01,
                                             0.003], model="rational_polynomial"),
]


@pytest.mark.parametrize("cam", DISTORT_CAMS, ids=lambda c: c.model)
def test_distort_matches_opencv(cam):
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.2, 1.2, (500, 2))
    if cam.model == "equidistant":
        ref = cv2.fisheye.distortPoints(xy.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    else:
        pts = np.hstack([xy, np.ones((xy.shape[0], 1))])
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        ref = ref.reshape(-1, 2)
    np.testing.assert_allclose(cam.distort(xy), ref, atol=1e-8)
    assert cam.distort(np.zeros((0, 2))).shape == (0, 2)


@pytest.mark.parametrize("dist", [[0, 0, 0, 0, 0], [-0.1, 0.03, 0, 0, 0],
                                  [0, 0, 0.002, -0.001, 0], [0, 0, 0, 0, 0.01],
                                  [0, 0, 0, 0, 0, 0.02, 0, 0], [0.1, 0, 0, 0, 0, 0, 0, 0.003]],
                         ids=["none", "radial", "tangential", "k3", "k4", "k1+k6"])
def test_distort_with_some_terms_zero_matches_opencv(dist):
    """distort leaves out the lens terms that are zero: each subset is OpenCV's pixels,
    with a skewed K too."""
    model = "plumb_bob" if len(dist) == 5 else "rational_polynomial"
    xy = np.random.default_rng(4).uniform(-1.2, 1.2, (200, 2))
    pts = np.hstack([xy, np.ones((xy.shape[0], 1))])
    for skew in (0.0, 2.5):
        cam = CameraModel(100, 80, np.array([[90.0, skew, 49.5], [0.0, 88.0, 39.5],
                                             [0.0, 0.0, 1.0]]), np.array(dist, float), model)
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        ref = ref.reshape(-1, 2)
        if skew:                     # OpenCV has no skew: add it to the unskewed pixels
            ref[:, 0] += skew * (ref[:, 1] - 39.5) / 88.0
        np.testing.assert_allclose(cam.distort(xy), ref, atol=1e-8)


@pytest.mark.parametrize("cam", DISTORT_CAMS, ids=lambda c: c.model)
def test_a_few_points_give_the_pixels_of_many(cam):
    """Up to FEW_POINTS points go through one cv2.projectPoints call, more through numpy:
    the same pixels either way, NaN where the numpy path gives NaN; a skewed K stays
    in numpy (OpenCV's projection has no skew term)."""
    from ceilkit.runtime.geometry.camera import FEW_POINTS
    rng = np.random.default_rng(5)
    xy = rng.uniform(-1.0, 1.0, (3 * FEW_POINTS, 2))
    xy[7] = np.nan
    many = cam.distort(xy)
    few = np.concatenate([cam.distort(xy[k:k + FEW_POINTS])
                          for k in range(0, len(xy), FEW_POINTS)])
    np.testing.assert_allclose(few, many, atol=1e-9)
    assert np.isnan(few[7]).all() and np.isnan(many[7]).all()
    K = cam.K.copy()
    K[0, 1] = 2.5
    skewed = CameraModel(cam.width, cam.height, K, cam.dist, cam.model)
    np.testing.assert_allclose(skewed.distort(xy[:4]), skewed.distort(xy)[:4], atol=1e-9)
    assert not np.allclose(skewed.distort(xy[:4]), cam.distort(xy[:4]))


def test_unproject_fast_matches_unproject():
    cam = CameraModel.pinhole(640, 480, 400.0, dist=[-0.08, 0.02, 0.001, -0.001, 0])
    px = np.random.default_rng(0).uniform([-0.5, -0.5], [639.5, 479.5], (200, 2))
    assert np.allclose(cam.unproject_fast(px), cam.unproject(px), atol=1e-9)
    plain = CameraModel.pinhole(640, 480, 400.0)
    assert np.allclose(plain.unproject_fast(px), plain.unproject(px))
    assert cam.unproject_fast(np.zeros((0, 2))).shape == (0, 2)
    fish = CameraModel.pinhole(640, 480, 300.0, dist=[0.05, -0.01, 0.002, -0.0005],
                               model="equidistant")
    assert np.array_equal(fish.unproject_fast(px), fish.unproject(px))


def test_unit_rays_and_where_the_lens_defines_them():
    cam = CameraModel.pinhole(320, 240, 150.0, dist=[0.05, -0.01, 0.002, -0.0005],
                              model="equidistant")
    px = np.array([[160.0, 120.0], [10.0, 5.0], [-3.0, 10.0], [319.4, 239.4]])
    rays, ok = cam.unit_rays(px, 1e-3)
    assert ok.tolist() == [True, True, False, True]
    assert np.allclose(np.linalg.norm(rays[ok], axis=1), 1.0)
    assert np.allclose(rays[ok], cam.rays(px[ok]))
    assert rays[2].tolist() == [0.0, 0.0, 0.0]                      # outside the image
    # a plumb_bob lens that folds over: far pixels have no inverse
    fold = CameraModel.pinhole(320, 240, 60.0, dist=[-0.6, 0.0, 0.0, 0.0, 0.0])
    xy = np.array([[0.0, 0.0], [2.0, 1.5]])
    good = fold.reprojects(fold.distort(xy) * 0 + [[160.0, 120.0], [0.0, 0.0]],
                           fold.unproject([[160.0, 120.0], [0.0, 0.0]]), 1e-3)
    assert good[0]
    assert not fold.reprojects([[0.0, 0.0]], [[np.nan, 0.0]], 1e-3)[0]


@pytest.mark.parametrize("model,dist", MODELS)
def test_subpixel_rays_match_the_exact_inverse(model, dist):
    cam = CameraModel.pinhole(320, 240, 250.0, dist=dist, model=model)
    rays = subpixel_rays(cam, 1)
    assert rays.shape == (240, 320, 3) and not rays.flags.writeable
    assert subpixel_rays(CameraModel(320, 240, cam.K.copy(), cam.dist.copy(), model), 1) \
        is rays                                                       # cached by value
    uu, vv = np.meshgrid(np.arange(320.0), np.arange(240.0))
    px = np.stack([uu.ravel(), vv.ravel()], axis=1)
    ok = np.isfinite(rays[..., 0]).ravel()
    assert ok.all() and np.all(rays[..., 2] == 1.0)
    err_px = np.linalg.norm(cam.distort(rays[..., :2].reshape(-1, 2)) - px, axis=1)
    assert np.median(err_px) < 1e-3 and err_px.max() < 0.02
    small = subpixel_rays(CameraModel.pinhole(16, 12, 20.0), 3)
    assert small.shape == (36, 48, 3)
    # the sub-pixel centres (k + 0.5) / 3 - 0.5 px from pixel (0, 0) of a pinhole; OpenCV's
    # bicubic kernel (a = -0.75) does not reproduce a linear field: up to 0.1 px between
    # the nodes (kept: the board renders stay as they were)
    assert np.allclose(small[:3, 0, 1], ((np.arange(3) + 0.5) / 3 - 0.5 - 5.5) / 20.0,
                       atol=0.1 / 20.0)


@pytest.mark.parametrize("model,dist", [("plumb_bob", [-0.2, 0.05, 0.001, -0.002, 0.0]),
                                        ("equidistant", [0.05, -0.01, 0.002, 0.0])])
def test_unproject_inverts_distort_with_a_skewed_k(model, dist):
    """OpenCV's inverses ignore K's skew; unproject takes it off the pixels first, so a
    skewed distorted lens round-trips (it was off by up to 0.003 in x/z)."""
    K = np.array([[300.0, 2.0, 320.0], [0.0, 310.0, 240.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(640, 480, K, dist, model=model)
    xy = np.array([[0.3, 0.4], [-0.5, 0.2], [0.0, -0.6], [0.0, 0.0]])
    np.testing.assert_allclose(cam.unproject(cam.distort(xy)), xy, atol=1e-10)
