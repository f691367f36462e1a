"""Blocks and markers on the simulated ceiling: their grey, their place through the lens,
the marker corner convention of SPEC §2 as cv2.aruco reads it back."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Block, MarkerPose, Markers, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.features.quads import MarkerDetector, marker_cells
from ceilkit.runtime.sim import marks
from ceilkit.runtime.sim.render import SimOptions, render_frame, render_radiance
from helpers import CONFIGS

CLEAN = SimOptions(noise_sigma=0.0, blur_px=0.0, vignetting=0.0, texture=0.0)
DICT = "DICT_APRILTAG_36h11"


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.load(CONFIGS / "block" / "rig.yaml")


def project_world(rig: Rig, pts_w: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    R = rig.mount.R_world_cam(yaw)
    c = rig.mount.camera_position(x, y, yaw)
    return rig.camera.project((np.asarray(pts_w, float) - c) @ R)


def ceiling(pts_xy: np.ndarray, h: float) -> np.ndarray:
    return np.hstack([pts_xy, np.full((len(pts_xy), 1), h)])


@pytest.mark.parametrize("appearance, grey", [(None, marks.BLOCK_GREY), ("dark", marks.BLOCK_GREY),
                                              ("bright", marks.BLOCK_BRIGHT_GREY)])
def test_block_grey_follows_its_appearance(rig, appearance, grey):
    blk = Block("A", np.array([[0.3, -0.2], [0.9, -0.2], [0.9, 0.2], [0.3, 0.2]]), appearance)
    site = Site(3.0, blocks=(blk,))
    img = render_radiance(rig, site, 0.0, 0.0, 0.0, CLEAN)
    u, v = np.rint(project_world(rig, ceiling(np.array([[0.6, 0.0]]), 3.0), 0, 0, 0)[0])
    assert img[int(v), int(u)] == pytest.approx(grey)


@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 90.0, -150.0])
def test_marker_reads_back_with_the_spec_corners(rig, yaw_deg):
    pose = MarkerPose(7, 0.35, 0.2, math.radians(yaw_deg), 0.25)
    site = Site(3.0, markers=Markers(DICT, 0.25, (pose,)))
    img = render_frame(rig, site, 0.0, 0.0, 0.1, SimOptions(noise_sigma=1.0))
    ids, corners = MarkerDetector(DICT).detect(img)
    assert ids.tolist() == [7]
    truth = project_world(rig, ceiling(pose.corners_m(), 3.0), 0.0, 0.0, 0.1)
    assert np.max(np.linalg.norm(corners[0] - truth, axis=1)) < 0.6


def test_marker_cells_are_the_printed_image():
    cells = marker_cells(DICT, 7)
    assert cells.shape == (8, 8)
    assert not cells[0].any() and not cells[:, 0].any()     # the black border
    assert cells[1:-1, 1:-1].any()


def test_bad_marker_inputs_are_one_line_errors():
    with pytest.raises(ConfigError, match="unknown aruco dictionary 'DICT_NOPE'"):
        marker_cells("DICT_NOPE", 0)
    with pytest.raises(ConfigError, match="not in DICT_4X4_50"):
        marker_cells("DICT_4X4_50", 50)


def test_packaged_block_site_shows_blocks_and_markers(rig):
    site = Site.load(CONFIGS / "block" / "site.yaml")
    assert site.has_section("blocks") and site.has_section("markers")
    assert site.has_section("corridor")
    assert {b.appearance for b in site.blocks} == {"dark", "bright"}
    p = site.markers.poses[0]
    img = render_frame(rig, site, p.x_m, p.y_m, 0.0)
    assert MarkerDetector(site.markers.dictionary).detect(img)[0].tolist() == [p.id]


def test_marks_leave_the_rest_of_the_frame_alone(rig):
    site = Site(3.0)
    blk = Block("A", np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]]))
    far = dataclasses.replace(site, blocks=(blk,),
                              markers=Markers(DICT, 0.2, (MarkerPose(1, -5.0, 0, 0, 0.2),)))
    a = render_radiance(rig, site, 0.0, 0.0, 0.0, CLEAN)
    b = render_radiance(rig, far, 0.0, 0.0, 0.0, CLEAN)
    assert np.array_equal(a, b)
