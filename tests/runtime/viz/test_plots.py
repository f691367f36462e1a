"""Plots: figures are PNGs with colour scales; --plots of the calibration workflow."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.calib import workflow
from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from ceilkit.runtime.viz import plots
from helpers import CONFIGS, FIXTURES

PNG = b"\x89PNG\r\n\x1a\n"


def _decoded(png: bytes) -> np.ndarray:
    assert png[:8] == PNG
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def test_figures_are_pngs():
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    xy = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.7]])
    img = _decoded(plots.trajectory_png(site, xy, xy + 0.01, np.array([0.2, 0.5, 1.0])))
    assert img.shape[1] == int(plots.SIZE_IN[0] * plots.DPI)
    t = np.arange(3.0)
    _decoded(plots.errors_png(t, {"y error [cm]": np.array([0.1, np.nan, -0.2])}))
    _decoded(plots.quality_error_png(np.array([0.9, 0.1]), np.array([0.5, 9.0]), "e [cm]"))
    _decoded(plots.failures_png(t, ["ok", "no_lights", "ok"]))
    _decoded(plots.histogram_png(np.array([1.0, 2.0, np.nan]), "latency [ms]", "latency"))
    _decoded(plots.mount_png({"a": 0.2, "b": 0.9}, 0.4, ["b"]))
    L = np.asarray(site.lights_m, float)
    _decoded(plots.lightmap_png(L, np.full(len(L), 0.002), np.full(len(L), 4), xy, site))


def test_ellipse_axes():
    pts = plots.ellipse_xy(np.diag([4.0, 1.0]))
    assert np.abs(pts[:, 0]).max() == pytest.approx(2.0, rel=1e-3)
    assert np.abs(pts[:, 1]).max() == pytest.approx(1.0, rel=1e-2)


def test_colour_scale_is_added_on_the_right():
    img = np.zeros((200, 300, 3), np.uint8)
    lut = np.stack([np.arange(256)] * 3, axis=1)
    out = plots.with_colour_scale(img, lut, 0.0, 5.0, "x [px]")
    assert out.shape == (200, 410, 3) and np.array_equal(out[:, :300], img)
    bar = out[32:178, 318]  # inside the bar's frame
    assert bar[0].sum() > bar[-1].sum()  # vmax (bright) at the top


def test_lightmap_plots(tmp_path):
    run = workflow.lightmap(FIXTURES / "lights_rec", tmp_path / "site.yaml", min_views=1,
                            plots=tmp_path / "plots")
    assert run.plots == (tmp_path / "plots" / "lightmap.png",)
    _decoded(run.plots[0].read_bytes())
    assert any("lightmap.png" in line for line in run.lines())


def test_mount_plots(tmp_path):
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    traj = Trajectory(np.arange(5, dtype=np.int64) * 10**8,
                      np.array([0.5, 3.1, 5.3, 7.9, 10.2]), np.array([0.0, 0.3, -0.3, 0.1, -0.1]),
                      np.radians([0.0, 0.0, 0.0, 10.0, -12.0]))
    simulate_recording(rig, site, traj, tmp_path / "pl", SimOptions(), seed=3)
    run = workflow.mount(tmp_path / "pl", CONFIGS / "corridor" / "site.yaml",
                         tmp_path / "rig.yaml", camera=CONFIGS / "corridor" / "camera.yaml",
                         plots=tmp_path / "plots")
    assert run.plots == (tmp_path / "plots" / "mount_residuals.png",)
    _decoded(run.plots[0].read_bytes())
    assert math.isfinite(Rig.load(tmp_path / "rig.yaml").mount.tilt_rad)
