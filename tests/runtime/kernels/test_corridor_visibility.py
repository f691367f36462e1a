"""The corridor method on busy ceilings (issue 38): the compiled in-view test against its
array reading, and a tile grid's turn twins settled by the coarse search alone."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import AMBIGUOUS
from ceilkit.runtime.estimators.corridor.estimator import CorridorEstimator, turned_twins
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.estimators.corridor.visibility import IN_VIEW_LENGTHS, lines_in_view
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.rotations import rot_z
from ceilkit.runtime.sim.render import SimOptions, render_frame

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def lines_in_view_array(setup: CorridorSetup, cam: CameraModel, min_length_px: float,
                        psi_rad: float, camera_y_m: tuple[float, ...]) -> np.ndarray:
    """The array reading of :func:`lines_in_view` (every sample of every line projected)."""
    u = setup.view_u_m
    R_cw = setup.R_level_cam.T @ rot_z(-psi_rad)
    J = setup.site_y.size
    dy = (setup.site_y[None, :] - np.asarray(camera_y_m, dtype=float)[:, None]).reshape(-1, 1)
    h = setup.ceiling_above_cam_m
    d0, d1, d2 = (u * R[0] + (dy * R[1] + h * R[2]) for R in R_cw)
    front = d2 > 1e-6
    z = np.where(front, d2, 1.0)
    x, y = d0 / z, d1 / z
    front &= np.hypot(x, y) <= setup.field_radius
    px = cam.distort(np.stack([x.ravel(), y.ravel()], axis=1)).reshape(*x.shape, 2)
    vis = front & cam.in_image(px.reshape(-1, 2), 2.0).reshape(x.shape)
    step = np.hypot(*np.diff(px, axis=1).transpose(2, 0, 1))
    both = vis[:, 1:] & vis[:, :-1]
    length_px = np.sum(np.where(both, step, 0.0), axis=1).reshape(-1, J)
    stretch_m = (np.sum(both, axis=1) * (u[1] - u[0])).reshape(-1, J)
    return (length_px >= IN_VIEW_LENGTHS * min_length_px) & (stretch_m >= setup.lamp_pitch_m)


def tiles_site(tmp: Path) -> Site:
    """A plain 0.6 m drop-tile grid (bench_ambiguity's ``tiles``)."""
    p = tmp / "tiles.yaml"
    p.write_text(yaml.safe_dump({
        "ceiling_height": 3.0,
        "corridor": {"lines_along": [round(-3.0 + 0.6 * i, 2) for i in range(11)],
                     "lines_across": {"first": 0.0, "spacing": 0.6}}}))
    return Site.load(p)


@pytest.mark.parametrize("config", ["block", "corridor", "office"])
def test_lines_in_view_equals_the_array_reading(config, tmp_path):
    rig = Rig.load(CONFIGS / config / "rig.yaml")
    site = tiles_site(tmp_path) if config == "block" else Site.load(
        CONFIGS / config / "site.yaml")
    est = CorridorEstimator(rig, site)
    rng = np.random.default_rng(3)
    seen = 0
    for _ in range(150):
        psi = rng.uniform(-math.pi, math.pi)
        ys = tuple(rng.uniform(-3.0, 3.0, 2))
        got = lines_in_view(est.setup, rig.camera, est.detector.min_length_px, psi, ys)
        want = lines_in_view_array(est.setup, rig.camera, est.detector.min_length_px, psi, ys)
        assert np.array_equal(got, want)
        seen += int(want.sum())
    assert seen > 50          # the draws put lines in view, not only out of it


def test_tile_turns_are_settled_by_the_coarse_search(tmp_path):
    """A plain tile grid without a prior is ``ambiguous`` between turns; the coarse search
    says so, and the full-resolution search, which is then not run, would say the same."""
    rig, site = Rig.load(CONFIGS / "block" / "rig.yaml"), tiles_site(tmp_path)
    est = CorridorEstimator(rig, site)
    assert est.coarse_detector is not None
    rng = np.random.default_rng(1)
    for k in range(4):
        a = 2 * math.pi * k / 4
        grey = render_frame(rig, site, 1.0 + 1.5 * math.cos(a), 1.5 * math.sin(a),
                            a + math.pi / 2, SimOptions(noise_sigma=2.0, blur_px=0.8), rng)
        out = est.estimate(grey, 0)
        assert not out and out.reason == AMBIGUOUS and turned_twins(out)
        assert out.diagnostics["search"] == "coarse"
        full = est._global(grey, 0, None, time.perf_counter(), "fallback")
        assert not full and turned_twins(full)
