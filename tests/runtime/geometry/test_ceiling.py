"""runtime/geometry/ceiling.py: rays to the ceiling plane and back, the frames between
(C, V, W: SPEC §1), the Jacobians, and the compiled loops against numpy."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ceilkit.runtime.geometry import ceiling
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import R_vehicle_cam, rot_z

H = 3.0                                   # the ceiling's height, m
T_VC = np.array([0.3, -0.1, 0.8])         # the camera's centre in V
MOUNTS = {"up": (0.2, 90.0, 10.0), "tilted": (15.0, 30.0, -5.0)}   # pan, tilt, swing (deg)


def mount(name: str) -> np.ndarray:
    return R_vehicle_cam(*(math.radians(a) for a in MOUNTS[name]))


@pytest.fixture(scope="module")
def camera() -> CameraModel:
    return CameraModel.pinhole(640, 480, fx=300.0, dist=[-0.25, 0.08, 0.001, -0.0005, 0.0])


def grid_px(camera: CameraModel, n: int = 9) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(5, camera.width - 6, n), np.linspace(5, camera.height - 6, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("name", sorted(MOUNTS))
def test_pixel_to_ceiling_to_world_and_back_to_the_pixel(camera, name):
    R = mount(name)
    px = grid_px(camera)
    q_v, ok = ceiling.ceiling_points(camera.unproject(px), R, T_VC, H - T_VC[2])
    assert ok.sum() >= 20                              # the tilted view keeps the upper rows
    assert np.isnan(q_v[~ok]).all() and np.isfinite(q_v[ok]).all()
    pose = (2.0, -1.5, math.radians(30.0))
    q_w = ceiling.vehicle_to_world(q_v[ok], *pose)
    # the ceiling point in W, by SPEC §1 directly: X_W = Rz(yaw) X_V + (x, y, 0)
    X_w = (rot_z(pose[2]) @ np.c_[q_v[ok], np.full(ok.sum(), H)].T).T + [pose[0], pose[1], 0]
    np.testing.assert_allclose(q_w, X_w[:, :2], atol=1e-12)
    back = ceiling.project_px(camera, R, T_VC, ceiling.on_ceiling(q_w, H), np.array([pose]))[0]
    np.testing.assert_allclose(back, px[ok], atol=1e-6)
    # the compiled projection gives the same normalized points
    norm = ceiling.ceiling_norm(R, T_VC, H, *pose, q_w, 1e-9)
    np.testing.assert_allclose(norm, camera.unproject(px[ok]), atol=1e-9)


def test_a_ray_that_does_not_rise_misses_the_ceiling():
    R = mount("tilted")
    xy = np.array([[0.0, -0.5], [0.0, 3.0]])           # above, then below the horizon
    off, depth, ok = ceiling.ceiling_rays(xy, R, H - T_VC[2])
    assert ok.tolist() == [True, False]
    assert np.isnan(off[1]).all() and math.isnan(depth[1])
    # the depth is the point's z in C: the ceiling point is depth (x, y, 1) from the centre
    r = R @ np.r_[xy[0], 1.0]
    np.testing.assert_allclose(depth[0] * r, [*off[0], H - T_VC[2]], atol=1e-12)
    # a ray barely rising passes an absolute test and fails one per length
    level = np.array([[0.0, (1e-8 - R[2, 2]) / R[2, 1]]])
    rz = (R @ np.r_[level[0], 1.0])[2]
    assert 0 < rz < 1e-7
    assert ceiling.ceiling_rays(level, R, 1.0, min_rz=0.0)[2][0]
    assert not ceiling.ceiling_rays(level, R, 1.0, min_rz=0.0, min_sin=1e-6)[2][0]


def test_seen_from_puts_a_point_of_the_camera_frame_back_in_it():
    R = mount("tilted")
    X_c = np.array([[0.2, -0.4, 2.0], [-1.0, 0.3, 5.0]])
    poses = np.array([[1.0, 2.0, 0.3], [-4.0, 0.5, -2.0]])
    for k, (x, y, yaw) in enumerate(poses):
        X_w = (rot_z(yaw) @ (R @ X_c.T + T_VC[:, None])).T + [x, y, 0.0]
        np.testing.assert_allclose(ceiling.seen_from(X_w, poses, T_VC)[k] @ R, X_c, atol=1e-12)


@pytest.mark.parametrize("name", sorted(MOUNTS))
def test_the_ceiling_jacobian_matches_finite_differences(camera, name):
    R = mount(name)
    xy = camera.unproject(grid_px(camera, 5))
    J = ceiling.ceiling_jacobian(xy, R, H - T_VC[2])
    ok = ceiling.ceiling_rays(xy, R, H - T_VC[2])[2]
    e = 1e-6
    for j, step in enumerate(([e, 0.0], [0.0, e])):
        hi = ceiling.ceiling_points(xy + step, R, T_VC, H - T_VC[2])[0]
        lo = ceiling.ceiling_points(xy - step, R, T_VC, H - T_VC[2])[0]
        np.testing.assert_allclose(J[ok, :, j], ((hi - lo) / (2 * e))[ok], rtol=1e-5,
                                   atol=1e-6)


@pytest.mark.parametrize("name", sorted(MOUNTS))
def test_the_pixel_jacobian_is_the_lens_times_the_inverse_ceiling_jacobian(camera, name):
    R = mount(name)
    xy = camera.unproject(grid_px(camera, 5))
    q, ok = ceiling.ceiling_points(xy, R, T_VC, H - T_VC[2])
    J_px = ceiling.pixel_jacobian(camera, R, T_VC, H, q[ok])
    chain = camera.distort_jacobian(xy[ok]) @ np.linalg.inv(
        ceiling.ceiling_jacobian(xy[ok], R, H - T_VC[2]))
    scale = np.abs(chain).max(axis=(1, 2))[:, None, None]
    assert np.all(np.abs(J_px - chain) < 0.02 * scale)   # forward differences of 1 mm
    assert ceiling.pixel_jacobian(camera, R, T_VC, H, np.zeros((0, 2))).shape == (0, 2, 2)


@pytest.mark.parametrize("min_rz,min_sin", [(ceiling.MIN_RZ, 0.0), (0.0, 1e-6), (1e-6, 0.0)])
def test_the_compiled_ray_gives_numpys_numbers(camera, min_rz, min_sin):
    R = np.ascontiguousarray(mount("tilted"))
    xy = camera.unproject(grid_px(camera, 11))
    off, _, ok = ceiling.ceiling_rays(xy, R, H - T_VC[2], min_rz=min_rz, min_sin=min_sin)
    assert 0 < ok.sum() < ok.size
    for i in range(xy.shape[0]):
        rises, ox, oy = ceiling.meet_ceiling(R, xy[i, 0], xy[i, 1], H - T_VC[2], min_rz,
                                             min_sin)
        assert rises == ok[i]
        # the same formula (numpy's matrix product may round its last bit otherwise)
        np.testing.assert_allclose([ox, oy], off[i], rtol=1e-14, atol=1e-15)


def test_the_compiled_frame_changes_match_numpys():
    R = np.ascontiguousarray(mount("tilted"))
    x, y, yaw = 1.0, -2.0, 0.7
    p_w = np.array([[3.0, 1.0], [-2.0, 0.5]])
    for k, (wx, wy) in enumerate(p_w):
        vx, vy = ceiling.level_offset(x, y, math.cos(yaw), math.sin(yaw), wx, wy)
        np.testing.assert_allclose(ceiling.vehicle_to_world([[vx, vy]], 0.0, 0.0, yaw)[0]
                                   + [x, y], [wx, wy], atol=1e-12)
        q = ceiling.seen_from(ceiling.on_ceiling(p_w, H), np.array([[x, y, yaw]]), T_VC)[0, k]
        np.testing.assert_allclose([vx - T_VC[0], vy - T_VC[1]], q[:2], atol=1e-12)
        np.testing.assert_allclose(ceiling.to_camera(R, *q), q @ R, atol=1e-12)
    up = np.ascontiguousarray(mount("up"))
    behind = ceiling.ceiling_norm(up, T_VC, T_VC[2] - 1.0, x, y, yaw, p_w, 1e-9)
    assert np.isnan(behind).all()           # a plane below a camera that looks straight up


def test_planar_geometry_of_a_rig_and_site(camera):
    rig = SimpleNamespace(camera=camera,
                          mount=SimpleNamespace(R_vehicle_cam=mount("up"), t_vehicle_cam=T_VC))
    geo = ceiling.PlanarGeometry.of(rig, SimpleNamespace(ceiling_height_m=H))
    assert geo.rise_m == H - T_VC[2]
    xy = camera.unproject(grid_px(camera, 3))
    np.testing.assert_array_equal(ceiling.ceiling_points_vehicle(geo, xy),
                                  ceiling.ceiling_points(xy, mount("up"), T_VC, H - T_VC[2])[0])
