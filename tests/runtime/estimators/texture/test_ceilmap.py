"""The ceiling map: rectifying a frame onto the ceiling plane, its file round trip, bad
files refused in one line, and the site key that names it."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.texture.ceilmap import (
    CeilingMap,
    appearance_ncc,
    explains,
    merge_features,
    part_ncc,
    patch_points_v,
    patch_size,
    pyramid_level,
    rectify,
)
from ceilkit.runtime.geometry.ceiling import on_ceiling, project_px
from helpers import CONFIGS


def _map(n=5) -> CeilingMap:
    rng = np.random.default_rng(0)
    mosaic = rng.integers(0, 255, (40, 60), dtype=np.uint8)
    cover = np.ones((40, 60), bool)
    return CeilingMap(0.01, (1.0, -0.2), mosaic, cover, rng.normal(size=(n, 2)),
                      rng.integers(0, 255, (n, 32), dtype=np.uint8), np.full(n, 0.002),
                      2.7, "orb", "truth")


def test_save_load_round_trip(tmp_path):
    m = _map()
    back = CeilingMap.load(m.save(tmp_path / "m.npz"))
    for k in ("mosaic", "coverage", "points_xy", "descriptors", "sigma_m"):
        assert np.array_equal(getattr(back, k), getattr(m, k)), k
    assert (back.resolution_m, back.origin_xy, back.ceiling_height, back.anchor,
            back.version) == (0.01, (1.0, -0.2), 2.7, "truth", 1)


def test_bad_files_refused_in_one_line(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(ConfigError, match="junk.npz: not a ceiling map") as e:
        CeilingMap.load(junk)
    assert "\n" not in str(e.value)
    m = _map()
    arrays = {k: getattr(m, k) for k in ("mosaic", "coverage", "points_xy", "descriptors",
                                         "sigma_m")}
    head = {"format": "ceilkit-ceiling-map", "version": 2, "resolution_m": 0.01,
            "origin_xy": [0, 0], "ceiling_height": 2.7}
    np.savez(tmp_path / "v2.npz", header=np.array(json.dumps(head)), **arrays)
    with pytest.raises(ConfigError, match=r"v2.npz: header.version: .*found 2"):
        CeilingMap.load(tmp_path / "v2.npz")
    head["version"] = 1
    arrays["sigma_m"] = np.zeros(3)
    np.savez(tmp_path / "short.npz", header=np.array(json.dumps(head)), **arrays)
    with pytest.raises(ConfigError, match="short.npz: sigma_m"):
        CeilingMap.load(tmp_path / "short.npz")
    with pytest.raises(ConfigError, match="gone.npz: no such ceiling map"):
        CeilingMap.load(tmp_path / "gone.npz")


@pytest.mark.parametrize("model,dist", [("plumb_bob", [-0.1, 0.03, 0.0, 0.0, 0.0]),
                                        ("rational_polynomial", [-0.1, 0.03, 0, 0, 0, 0.01,
                                                                 0, 0]),
                                        ("equidistant", [0.02, -0.01, 0.0, 0.0])])
def test_rectify_samples_the_ceiling_point_each_pixel_stands_for(model, dist):
    """A frame whose grey level is a function of the pixel: each patch pixel must read
    the value of the pixel its ceiling point projects to, for every lens model."""
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    cam = type(rig.camera)(rig.camera.width, rig.camera.height, rig.camera.K, dist, model)
    rig = type(rig)(cam, rig.mount)
    u = np.arange(cam.width)
    grey = np.tile((u % 200).astype(np.uint8), (cam.height, 1))
    patch, valid = rectify(grey, rig, 2.7, 0.02, 1.0, level=0)
    n = patch_size(0.02, 1.0)
    assert patch.shape == valid.shape == (n, n) and valid.mean() > 0.5
    px = project_px(cam, rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam,
                    on_ceiling(patch_points_v(0.02, n), 2.7), np.zeros((1, 3)))[0]
    inner = valid.ravel() & (px[:, 0] % 200 > 2) & (px[:, 0] % 200 < 197)
    assert np.max(np.abs(patch.ravel()[inner] - px[inner, 0] % 200)) <= 1.0


def test_rectify_samples_the_pyramid_level_whose_pixel_is_the_patch_s():
    """The office rig sees 4.9 mm of ceiling a pixel at the image centre: a 1 cm patch
    is sampled from the frame's first pyramid level, a 2 cm one from the second; on a
    smooth frame each level reads what the frame itself does (the same geometry)."""
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    cam = rig.camera
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    grey = (40 + 0.2 * u + 0.15 * v).astype(np.uint8)
    for res, level in ((0.01, 1), (0.02, 2)):
        n = patch_size(res, 1.0)
        lv = pyramid_level(*_patch_px(rig, res, n))
        assert lv == level
        fine, valid = rectify(grey, rig, 2.7, res, 1.0, level=0)
        auto, valid_auto = rectify(grey, rig, 2.7, res, 1.0)
        inner = cv2.erode(valid.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        assert np.array_equal(valid, valid_auto)
        assert np.max(np.abs(auto[inner].astype(int) - fine[inner])) <= 2


def _patch_px(rig, res, n):
    px = project_px(rig.camera, rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam,
                    on_ceiling(patch_points_v(res, n), 2.7), np.zeros((1, 3)))[0]
    ok = (px[:, 0] >= 0) & (px[:, 0] <= rig.camera.width - 1) & (px[:, 1] >= 0) & \
        (px[:, 1] <= rig.camera.height - 1)
    return px.reshape(n, n, 2), ok.reshape(n, n)


def test_mosaic_explains_itself_and_not_a_shifted_pose():
    m = _map()
    n = 21
    pose = (1.3, 0.0, 0.0)      # mosaic (col 30, row 20): the patch's centre
    patch = m.mosaic[10:31, 20:41].copy()
    valid = np.ones((n, n), bool)
    assert appearance_ncc(m, patch, valid, pose) > 0.99
    assert appearance_ncc(m, patch, valid, (1.35, 0.0, 0.0)) < 0.3
    assert math.isnan(appearance_ncc(m, patch, valid, (9.0, 9.0, 0.0)))


def test_merge_features_pools_observations():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 5, (30, 2))
    desc = rng.integers(0, 255, (30, 32), dtype=np.uint8)
    pts = np.concatenate([truth + rng.normal(0, 0.003, truth.shape) for _ in range(4)])
    views = np.repeat(np.arange(4), 30)
    p, d, s = merge_features(pts, np.tile(desc, (4, 1)), views, 0.01, min_views=2)
    assert len(p) == 30
    nearest = np.min(np.hypot(*(p[:, None, :] - truth[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert np.max(nearest) < 0.006
    assert 0.0008 < np.median(s) < 0.003          # 3 mm / sqrt(4) = 1.5 mm


def test_site_names_its_ceiling_map(tmp_path):
    _map().save(tmp_path / "map.npz")
    text = "ceiling_height: 2.7\nceiling_map: map.npz\n"
    (tmp_path / "site.yaml").write_text(text)
    site = Site.load(tmp_path / "site.yaml")
    assert site.has_section("ceiling_map")
    assert CeilingMap.load(site.ceiling_map).anchor == "truth"
    (tmp_path / "bad.yaml").write_text(text.replace("map.npz", "none.npz"))
    with pytest.raises(ConfigError, match="bad.yaml: ceiling_map: no such file"):
        Site.load(tmp_path / "bad.yaml")


def test_keyframe_error_is_shared_not_divided_and_round_trips(tmp_path):
    """A survey's keyframe 1σ moves every feature its keyframe placed together: the
    pose on 50 such features carries that 1σ whole (not / sqrt(50)); a map of known
    poses (zeros, or none in the file) adds nothing; the arrays survive the file."""
    import dataclasses
    m = dataclasses.replace(_map(), keyframe_poses=np.array([[1.0, 0.0, 0.0], [9.0, 0.0, 0.0]]),
                            keyframe_sigma=np.array([[0.004, 0.003, 0.0], [0.05, 0.05, 0.0]]))
    pts = np.random.default_rng(1).normal([1.0, 0.0], 0.3, (50, 2))
    C = m.placement_cov(pts, (1.2, 0.1, 0.0))
    assert np.allclose(np.sqrt(np.diag(C)[:2]), [0.004, 0.003])
    back = CeilingMap.load(m.save(tmp_path / "k.npz"))
    assert np.array_equal(back.keyframe_sigma, m.keyframe_sigma)
    assert not np.any(_map().placement_cov(pts, (1.2, 0.1, 0.0)))
    bad = dataclasses.replace(m, keyframe_sigma=-m.keyframe_sigma)
    assert bad.shape_problem()[0] == "keyframe_sigma"


def _blurred_mosaic(rng: np.random.Generator) -> tuple[CeilingMap, tuple, int]:
    """A 2 x 2 m map of blurred noise at 1 cm, a pose at its middle and a patch size."""
    mosaic = cv2.GaussianBlur(rng.integers(0, 255, (200, 200), dtype=np.uint8), (5, 5), 1.5)
    m = CeilingMap(0.01, (0.0, 0.0), mosaic, np.ones_like(mosaic, bool), np.zeros((0, 2)),
                   np.zeros((0, 32), np.uint8), np.zeros(0), 2.7)
    return m, (1.0, 1.0, 0.0), 91


def test_a_pose_must_explain_each_part_of_the_frame():
    """A patch that is the mosaic in one third and unrelated texture elsewhere: the whole
    patch's correlation is carried by the matching third, its parts' median is not."""
    rng = np.random.default_rng(4)
    m, pose, n = _blurred_mosaic(rng)
    from ceilkit.runtime.estimators.texture.ceilmap import predicted_patch
    same, _ = predicted_patch(m, pose, n)
    other = cv2.GaussianBlur(rng.integers(0, 255, (n, n), dtype=np.uint8), (5, 5), 1.5)
    valid = np.ones((n, n), bool)
    assert part_ncc(m, same, valid, pose) > 0.9
    mixed = (0.3 * other.astype(float) + 90).astype(np.uint8)    # fainter, unrelated
    third = 2.0 * (same[:, : n // 3].astype(float) - same.mean()) + 128
    mixed[:, : n // 3] = np.clip(third, 0, 255).astype(np.uint8)  # the matching third
    assert appearance_ncc(m, mixed, valid, pose) > 0.5
    assert part_ncc(m, mixed, valid, pose) < 0.3


def _flat_reference(a: np.ndarray, b: np.ndarray, blocks: int = 3) -> float:
    """flat_ncc by hand on two whole square patches: each block of each less its
    least-squares plane, the residuals pooled into one correlation."""
    n, taa, tbb, tab = a.shape[0], 0.0, 0.0, 0.0
    edges = [(k * n + blocks - 1) // blocks for k in range(blocks + 1)]
    for i in range(blocks):
        for j in range(blocks):
            r, c = np.mgrid[edges[i]:edges[i + 1], edges[j]:edges[j + 1]]
            X = np.c_[np.ones(r.size), r.ravel(), c.ravel()]
            ra, rb = (v[r, c].ravel().astype(float) for v in (a, b))
            ra = ra - X @ np.linalg.lstsq(X, ra, rcond=None)[0]
            rb = rb - X @ np.linalg.lstsq(X, rb, rcond=None)[0]
            taa, tbb, tab = taa + ra @ ra, tbb + rb @ rb, tab + ra @ rb
    return tab / math.sqrt(taa * tbb)


def test_explains_is_the_flat_and_the_parts_correlation():
    """One pass for the whole frame's (each block less its plane, pooled: flat_ncc) and
    the parts' correlations: the first as computed by hand on the mosaic resampled at
    the pose, at strides 1 and 3; NaN off the mosaic."""
    rng = np.random.default_rng(5)
    mosaic = cv2.GaussianBlur(rng.integers(0, 255, (160, 200), dtype=np.uint8), (5, 5), 1.5)
    cover = np.ones_like(mosaic, bool)
    cover[:, 150:] = False
    m = CeilingMap(0.01, (0.0, 0.0), mosaic, cover, np.zeros((0, 2)),
                   np.zeros((0, 32), np.uint8), np.zeros(0), 2.7)
    n = 61
    from ceilkit.runtime.estimators.texture.ceilmap import flat_ncc, predicted_patch
    for pose in ((0.8, 0.7, 0.3), (0.75, 0.8, -1.0)):
        patch, _ = predicted_patch(m, (pose[0] + 0.01, pose[1], pose[2] + 0.02), n)
        patch = np.clip(patch.astype(float) + rng.normal(0, 4, patch.shape), 0, 255)
        patch = patch.astype(np.uint8)
        for stride in (1, 3):
            got = explains(m, patch, np.ones((n, n), bool), pose, stride)
            seen, _ = predicted_patch(m, pose, n, stride)
            want = _flat_reference(patch[::stride, ::stride], seen)
            assert abs(got[0] - want) < 0.01, (got, want, stride)
            assert got == (flat_ncc(m, patch, np.ones((n, n), bool), pose, stride),
                           part_ncc(m, patch, np.ones((n, n), bool), pose, stride))
    assert np.isnan(explains(m, patch, np.ones((n, n), bool), (5.0, 5.0, 0.0))).all()


def test_the_flat_correlation_leaves_the_lenss_shading_out():
    """A faint texture under a lens's falloff (issue 39's seeds 2 and 3): the whole
    frame's raw correlation with the mosaic is carried by the shading, and falls under
    min_ncc at the true pose; less each block's plane it reads the texture, high at the
    pose and low a texture's width off it."""
    rng = np.random.default_rng(6)
    m, pose, n = _blurred_mosaic(rng)
    from ceilkit.runtime.estimators.texture.ceilmap import flat_ncc, predicted_patch
    seen, _ = predicted_patch(m, pose, n)
    r2 = np.hypot(*(np.mgrid[:n, :n] - n // 2)) ** 2 / (n / 2) ** 2
    faint = 0.5 * (seen.astype(float) - seen.mean())       # std 8 under a 70 falloff
    shaded = np.clip(200 * (1 - 0.35 * r2) + faint + rng.normal(0, 2, (n, n)), 0, 255)
    patch, valid = shaded.astype(np.uint8), np.ones((n, n), bool)
    assert appearance_ncc(m, patch, valid, pose) < 0.5
    assert flat_ncc(m, patch, valid, pose) > 0.8
    assert flat_ncc(m, patch, valid, (1.1, 1.0, 0.0)) < 0.3
