"""`ceilcal blockmap`: markers placed from a drive of known poses (calib/blockmap.py):
accuracy against the simulator's truth, the refusals, the written site file, the CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.calib.blockmap import (
    MIN_VIEWS,
    PlacedMarker,
    RefusedMarker,
    Sighting,
    fit_marker,
    frames_with_poses,
    map_markers,
    place_marker,
)
from ceilkit.calib.poses import StampedPoses
from ceilkit.calib.simulate import simulate_recording
from ceilkit.cli.ceilcal import app
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import MarkerPose, Site
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from helpers import CONFIGS

N_FRAMES = 24


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """configs/block (0.6 m tiles, two blocks, four 0.25 m AprilTags), a weaving drive
    from x = -0.5 to 9 m, a frame every 0.4 m, noise 2, blur 0.8."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    s = np.linspace(0.0, 1.0, N_FRAMES)
    traj = Trajectory(np.arange(N_FRAMES, dtype=np.int64) * 100_000_000, -0.5 + 9.5 * s,
                      0.3 * np.sin(2 * np.pi * s), 0.3 * np.sin(3 * np.pi * s))
    out = tmp_path_factory.mktemp("blockmap") / "rec"
    simulate_recording(rig, site, traj, out, SimOptions(noise_sigma=2.0, blur_px=0.8),
                       seed=1)
    rec = Recording(out)
    bm = map_markers(frames_with_poses(rec, StampedPoses.from_truth(rec.truth)), rec.rig,
                     site.ceiling_height_m, site.markers.dictionary)
    return out, site, bm


def _sightings(bm_site, mid: int, drive_path) -> list[Sighting]:
    """The sightings of marker ``mid`` in the drive, from the true poses."""
    from ceilkit.calib.blockmap import frame_sightings
    from ceilkit.runtime.features.grey import to_grey
    from ceilkit.runtime.geometry.ceiling import PlanarGeometry

    rec = Recording(drive_path)
    geo = PlanarGeometry.of(rec.rig, bm_site)
    out = []
    for k, image, pose in frames_with_poses(rec, StampedPoses.from_truth(rec.truth)):
        out += [sg for i, sg in frame_sightings(to_grey(image), k, pose, geo,
                                                bm_site.markers.dictionary) if i == mid]
    return out


def test_every_marker_placed_within_a_millimetre_and_its_sigma(drive):
    _, site, bm = drive
    assert [m.id for m in bm.placed] == [p.id for p in site.markers.poses]
    assert bm.refused == () and bm.frames_used == N_FRAMES
    for m in bm.placed:
        truth = site.markers.pose(m.id)
        d = np.linalg.norm(m.corners_m - truth.corners_m(), axis=1)
        assert d.max() < 1e-3, (m.id, d)
        assert len(m.frames) >= MIN_VIEWS
        assert abs(m.pose.size_m - truth.size_m) < 1e-3
        # the centre within its covariance: Mahalanobis (2 dof) under the 99.9 % bound
        e = np.array([m.pose.x_m - truth.x_m, m.pose.y_m - truth.y_m])
        assert e @ np.linalg.solve(m.cov[:2, :2], e) < 13.8, (m.id, e, m.cov[:2, :2])
        dyaw = math.remainder(m.pose.yaw_rad - truth.yaw_rad, 2 * math.pi)
        assert abs(dyaw) < 3.3 * math.sqrt(m.cov[2, 2]), (m.id, dyaw)
        assert 0 < m.corner_sigma_m < 5e-4


def test_fit_is_exact_on_noiseless_sightings():
    truth = MarkerPose(5, 1.2, -0.4, math.radians(30.0), 0.2)
    cov = np.broadcast_to(np.eye(2) * 1e-6, (4, 2, 2))
    rng = np.random.default_rng(3)
    sightings = [Sighting(k, truth.corners_m() + rng.normal(0.0, 1e-4, (4, 2)), cov)
                 for k in range(6)]
    m = fit_marker(5, sightings)
    assert np.linalg.norm(m.corners_m - truth.corners_m(), axis=1).max() < 2e-4
    sx, sy, syaw, ss = m.sigmas
    assert 1e-5 < sx < 1e-4 and 1e-5 < ss < 2e-4      # 0.1 mm noise, 24 corners
    exact = fit_marker(5, [Sighting(k, truth.corners_m(), cov) for k in range(3)])
    assert abs(exact.pose.x_m - 1.2) < 1e-12 and abs(exact.pose.size_m - 0.2) < 1e-12
    assert abs(exact.pose.yaw_rad - math.radians(30.0)) < 1e-12


def test_refused_too_few_frames_disagreeing_sightings_and_wrong_side(drive):
    path, site, _ = drive
    sg = _sightings(site, 1, path)
    assert len(sg) >= 4
    few = place_marker(1, sg[:2])
    assert isinstance(few, RefusedMarker) and few.views == 2
    assert "seen in 2 frames" in few.reason and "fewer than 3" in few.reason
    moved = [*sg[:-1], Sighting(sg[-1].frame, sg[-1].corners_m + [0.3, 0.0], sg[-1].cov_m2)]
    bad = place_marker(1, moved)
    assert isinstance(bad, RefusedMarker) and "disagree" in bad.reason
    assert f"frame {sg[-1].frame} lies" in bad.reason and "span 300 mm" in bad.reason
    side = place_marker(1, sg, size_m=0.20)
    assert isinstance(side, RefusedMarker) and "0.2500 m" in side.reason
    assert isinstance(place_marker(1, sg, size_m=0.25), PlacedMarker)


def test_cli_writes_markers_keeps_other_sections_and_never_overwrites(drive, tmp_path):
    path, site, bm = drive
    out = tmp_path / "site.yaml"
    res = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "4 markers (0, 1, 2, 3)" in res.output
    new = Site.load(out)
    assert [b.id for b in new.blocks] == ["A", "B"] and new.corridor == site.corridor
    assert np.array_equal(new.blocks[0].corners_m, site.blocks[0].corners_m)
    for p in site.markers.poses:
        got = new.markers.pose(p.id)
        assert np.linalg.norm(got.corners_m() - p.corners_m(), axis=1).max() < 1e-3
    text = out.read_text()
    assert text.startswith("# ceilcal blockmap") and "sx_mm" in text and "id 3:" in text
    again = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out)])
    assert again.exit_code == 1 and "already there" in again.output
    assert out.read_text() == text
    sized = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out), "--size",
                                     "0.25", "--force"])
    assert sized.exit_code == 0, sized.output
    assert all(p.size_m == 0.25 for p in Site.load(out).markers.poses)


def test_cli_refuses_in_one_line(drive, tmp_path):
    path, _, _ = drive
    out = tmp_path / "site.yaml"
    res = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out), "--size",
                                   "0.2"])
    assert res.exit_code == 1 and not out.exists()
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "no marker placed" in lines[0]
    assert "marker 0: measures 0.2500 m" in lines[0] and "nothing written" in lines[0]
    bad = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out),
                                   "--dictionary", "DICT_NOPE"])
    assert bad.exit_code == 1 and "--dictionary" in bad.output and not out.exists()
    inside = CliRunner().invoke(app, ["blockmap", str(path), "--out",
                                      str(path / "site.yaml"), "--force"])
    assert inside.exit_code == 1 and "input" in inside.output


def test_no_poses_is_one_line(tmp_path):
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    traj = Trajectory(np.arange(2, dtype=np.int64), np.array([0.5, 0.6]), np.zeros(2),
                      np.zeros(2))
    rec = simulate_recording(rig, site, traj, tmp_path / "rec")
    (rec / "truth.csv").unlink()
    res = CliRunner().invoke(app, ["blockmap", str(rec), "--out", str(tmp_path / "s.yaml")])
    assert res.exit_code == 1 and "truth.csv" in res.output and "--poses" in res.output
    assert len(res.output.strip().splitlines()) == 1


def test_cli_names_a_refused_marker_and_writes_the_others(drive, tmp_path):
    path, _, bm = drive
    frames = {m.id: m.frames for m in bm.placed}
    assert frames[3][:2] == (19, 20) and max(frames[2]) <= 20   # the drive's premise
    rows = (path / "truth.csv").read_text().splitlines()
    poses = tmp_path / "truth.csv"
    poses.write_text("\n".join(rows[:22]) + "\n")       # header + frames 0..20
    out = tmp_path / "site.yaml"
    res = CliRunner().invoke(app, ["blockmap", str(path), "--out", str(out), "--poses",
                                   str(poses)])
    assert res.exit_code == 0, res.output
    assert (f"ceilcal: refused: {path}: marker 3: seen in 2 frames (19, 20), fewer "
            "than 3") in res.output
    assert [p.id for p in Site.load(out).markers.poses] == [0, 1, 2]
    assert "from 21 frames" in res.output and "refused: " in out.read_text()
