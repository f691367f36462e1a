"""A survey anchored by markers of known pose or placed on the Earth by a geodetic point:
accepted only when singled out, its residual reported, refused in one line otherwise."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.calib.blockmap import map_markers
from ceilkit.calib.simulate import simulate_recording
from ceilkit.calib.survey_files import Anchors, survey_site
from ceilkit.calib.survey_geo import origin_from_start, parse_geodetic, start_pose_from_geodetic
from ceilkit.calib.survey_markers import (
    SurveyedMarker,
    anchor_by_markers,
    parse_anchor_marker,
    survey_markers,
)
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import MarkerPose, Markers, Site, SiteOrigin
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.io.recording import Recording
from ceilkit.runtime.sim.render import SimOptions, straight_drive
from ceilkit.runtime.sim.scatter_file import scene_beside
from helpers import CONFIGS

LIGHTS = np.array([[3.4, -0.5], [4.2, 1.0], [4.9, -0.2]])
KNOWN = (MarkerPose(3, 3.6, 0.8, math.radians(30.0), 0.2),
         MarkerPose(5, 4.6, -0.3, math.radians(-100.0), 0.2))


def _surveyed(motion=(0.4, np.array([-1.0, 2.0])), known=KNOWN, **kw) -> list[SurveyedMarker]:
    """The known markers as a survey would place them in a frame ``motion`` away."""
    yaw, t = motion
    c, s = math.cos(yaw), math.sin(yaw)
    back = np.array([[c, s], [-s, c]])                  # Rz(-yaw): S = Rz(-yaw) (W - t)
    cov = np.tile(1e-6 * np.eye(2), (4, 1, 1))
    return [SurveyedMarker(k.id, (k.corners_m() - t) @ back.T, kw.get("views", 6),
                           kw.get("places", 1), 0.001, cov) for k in known]


def test_markers_give_the_motion_back():
    a = anchor_by_markers(_surveyed(), KNOWN)
    assert a and a.ids == (3, 5)
    assert a.yaw_rad == pytest.approx(0.4) and a.t_m == pytest.approx([-1.0, 2.0])
    assert np.all(a.residual_m < 1e-9) and a.size_m == pytest.approx([0.2, 0.2])


def test_a_marker_not_seen_is_one_line():
    a = anchor_by_markers(_surveyed()[:1], (KNOWN[1],))
    assert not a and a.reason.startswith("marker(s) 5 not seen") and "3" in a.reason


def test_an_id_at_two_places_is_ambiguous():
    a = anchor_by_markers(_surveyed(places=2), KNOWN)
    assert not a and a.reason.startswith("ambiguous: marker 3")


def test_a_marker_of_another_size_is_refused():
    small = tuple(dataclasses.replace(k, size_m=0.15) for k in KNOWN)
    a = anchor_by_markers(_surveyed(), small)
    assert not a and "measures 0.200 m" in a.reason and "0.150 m" in a.reason
    unsized = tuple(dataclasses.replace(k, size_m=math.nan) for k in KNOWN)
    assert anchor_by_markers(_surveyed(), unsized)          # no side given: unchecked


def test_markers_that_disagree_are_refused():
    moved = (KNOWN[0], dataclasses.replace(KNOWN[1], x_m=KNOWN[1].x_m + 0.1))
    a = anchor_by_markers(_surveyed(), moved)
    assert not a and a.reason.startswith("the markers disagree")
    assert a.residual_m.max() > 0.02


def test_a_moved_marker_turns_its_covariance():
    cov = np.tile(np.diag([4e-6, 1e-6]), (4, 1, 1))
    m = dataclasses.replace(_surveyed()[0], fit_cov_m2=cov, pose_sigma_m=5e-4)
    t = np.array([1.0, -2.0])
    moved = m.moved(math.pi / 2, t)
    assert moved.corners_m == pytest.approx(m.corners_m @ np.array([[0, 1], [-1, 0]]) + t)
    assert moved.fit_cov_m2[0] == pytest.approx(np.diag([1e-6, 4e-6]))
    assert moved.sigma_m == pytest.approx(m.sigma_m) == pytest.approx(
        math.sqrt(2.5e-6 + 2.5e-7))
    assert moved.pose().size_m == pytest.approx(m.size_m)


def test_anchor_marker_option():
    p = parse_anchor_marker("7, 2.0, 0.5, 90")
    assert (p.id, p.x_m, p.y_m) == (7, 2.0, 0.5) and p.yaw_rad == pytest.approx(math.pi / 2)
    assert math.isnan(p.size_m)
    assert parse_anchor_marker("7,2,0.5,90", {7: 0.25}).size_m == 0.25
    assert parse_anchor_marker("7,2,0.5,90,0.3", {7: 0.25}).size_m == 0.3
    for bad in ("7,2,0.5", "x,2,0.5,90", "-1,2,0.5,90", "7,2,0.5,90,0", "7,2,0.5,90,1,2",
                "7,nan,0,0"):
        with pytest.raises(ConfigError, match="--anchor-marker"):
            parse_anchor_marker(bad)


def test_geodetic_point_and_origin_agree():
    origin = SiteOrigin(52.0, 4.0, 3.0, 30.0)
    start = start_pose_from_geodetic(origin, (52.0001, 4.0002, 75.0))
    assert start[2] == pytest.approx(math.radians(30.0 - 75.0))
    back = origin_from_start((52.0001, 4.0002, 75.0), start, alt_m=3.0)
    assert back.heading_deg == pytest.approx(30.0)
    # the same W: 18 m from the start the two tangent planes differ by far below 1 mm
    assert back.lat_deg == pytest.approx(52.0, abs=1e-8)     # 1e-8 deg: 1.1 mm
    assert back.lon_deg == pytest.approx(4.0, abs=1e-8)
    assert parse_geodetic(None) is None
    for bad in ("52,4", "95,4,0", "52,200,0", "52,4,inf"):
        with pytest.raises(ConfigError, match="--anchor-geodetic"):
            parse_geodetic(bad)


@pytest.fixture(scope="module")
def marker_drive(tmp_path_factory):
    """A 2 m straight drive under the office scatter with two markers and three spot
    lights beside its path (noise 2, blur 0.8), and the site that lists the markers."""
    rig = Rig.load(CONFIGS / "office" / "rig.yaml")
    office = Site.load(CONFIGS / "office" / "site.yaml")
    site = dataclasses.replace(office, markers=Markers("DICT_APRILTAG_36h11", 0.2, KNOWN))
    base = tmp_path_factory.mktemp("survey_markers")
    traj = straight_drive(20, fps=5.0, speed_mps=0.5, x0_m=3.0, y_m=0.3)
    lit = dataclasses.replace(site, lights_m=LIGHTS, light_diameter_m=0.12)
    simulate_recording(rig, lit, traj, base / "rec", SimOptions(
        noise_sigma=2.0, blur_px=0.8, supersample=1, scatter=scene_beside(office)), seed=3)
    site.save(base / "known.yaml")
    return base


def _errors(run, rec: Recording) -> tuple[float, float]:
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad][run.result.frame]
    pos = np.hypot(*(run.result.poses[:, :2] - truth[:, :2]).T)
    yaw = np.abs((run.result.poses[:, 2] - truth[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    return float(pos.max()), math.degrees(float(yaw.max()))


def test_survey_anchored_by_the_sites_markers(marker_drive, tmp_path):
    """Started at the origin (3 m from the truth), the markers move it onto W."""
    run = survey_site(CONFIGS / "office" / "rig.yaml", [marker_drive / "rec"], tmp_path,
                      site=marker_drive / "known.yaml")
    pos, yaw = _errors(run, Recording(marker_drive / "rec"))
    assert pos < 0.002 and yaw < 0.05, (pos, yaw)         # measured 0.18 mm, 0.004 deg
    assert run.result.anchor.startswith("markers: 2 of known pose")
    assert "anchor: markers" in (tmp_path / "site.yaml").read_text()
    # the lights, with the poses the markers anchored, where ceilcal lightmap puts them
    # from the true poses (the clusters that stay put on both sides), within their 1σ
    from scipy.spatial import cKDTree

    from ceilkit.calib.lightmap import survey_lights
    from ceilkit.calib.survey_files import LIGHT_SPREAD_M

    known = survey_lights(Recording(marker_drive / "rec"), ceiling_height_m=2.7)
    keep = known.spread_m <= LIGHT_SPREAD_M
    lights = run.lights
    # the survey keeps of those the round ones (survey_lamps): 9 of 11 here, the three
    # lamps among them (below)
    assert lights is not None and 3 <= len(lights.lights_m) <= int(keep.sum())
    d, j = cKDTree(known.lights_m[keep]).query(lights.lights_m)
    z = d / np.hypot(lights.sigma_m, known.sigma_m[keep][j])
    assert np.median(z) < 1.0 and z.max() < 4.0, z
    assert cKDTree(lights.lights_m).query(LIGHTS)[0].max() < 0.005    # the three lamps
    # each light's 1σ per axis written for the runtime (light_sigma: the map's own error
    # in the lights fix, issue 36): the radial 1σ over sqrt 2, in the lights' order
    written = Site.load(tmp_path / "site.yaml")
    np.testing.assert_allclose(written.lights_m, np.round(lights.lights_m, 4))
    np.testing.assert_allclose(written.light_sigma_m, lights.sigma_m / math.sqrt(2.0),
                               atol=1e-6)


def test_anchor_marker_and_geodetic_write_the_sections(marker_drive, tmp_path):
    """One marker by the option (its side unchecked), no site: the surveyed markers and
    the origin the geodetic point gives are written."""
    k = KNOWN[0]
    anchors = Anchors(markers=(dataclasses.replace(k, size_m=math.nan),),
                      geodetic=(52.0, 4.0, 10.0))
    run = survey_site(CONFIGS / "office" / "rig.yaml", [marker_drive / "rec"], tmp_path,
                      anchors=anchors, ceiling_height_m=2.7)
    pos, _ = _errors(run, Recording(marker_drive / "rec"))
    # one marker's yaw: measured 0.22 mm (4.0 mm when its corners were cornerSubPix's)
    assert pos < 0.002, pos
    assert "yaw 1-sigma" in run.result.anchor
    site = Site.load(tmp_path / "site.yaml")
    got = {p.id: p for p in site.markers.poses}
    assert set(got) == {3, 5} and site.markers.dictionary == "DICT_APRILTAG_36h11"
    assert np.hypot(got[5].x_m - KNOWN[1].x_m, got[5].y_m - KNOWN[1].y_m) < 0.002  # 0.22 mm
    assert abs(got[5].size_m - 0.2) <= 0.002
    start = start_pose_from_geodetic(site.origin, (52.0, 4.0, 10.0))
    assert np.hypot(start[0] - run.result.poses[0, 0], start[1] - run.result.poses[0, 1]) \
        < 1e-4


def test_geodetic_point_on_the_sites_origin_is_the_start(marker_drive, tmp_path):
    site = Site.load(marker_drive / "known.yaml")
    site = dataclasses.replace(site, markers=None, origin=SiteOrigin(52.0, 4.0, 0.0, 0.0))
    site.save(tmp_path / "geo.yaml")
    rec = Recording(marker_drive / "rec")
    plane_start = (float(rec.truth.x_m[0]), float(rec.truth.y_m[0]),
                   float(rec.truth.yaw_rad[0]))
    o = origin_from_start((52.0, 4.0, 0.0), (0.0, 0.0, 0.0))
    from ceilkit.runtime.geometry.geodesy import LocalTangentPlane
    lat, lon, _ = LocalTangentPlane.of(o).geodetic_from_world(*plane_start[:2])
    heading = LocalTangentPlane.of(o).heading_from_yaw(plane_start[2])
    run = survey_site(CONFIGS / "office" / "rig.yaml", [marker_drive / "rec"],
                      tmp_path / "out", site=tmp_path / "geo.yaml",
                      anchors=Anchors(geodetic=(lat, lon, heading)))
    pos, yaw = _errors(run, rec)
    assert pos < 0.002 and yaw < 0.05, (pos, yaw)
    with pytest.raises(ConfigError, match="not both"):
        survey_site(CONFIGS / "office" / "rig.yaml", [marker_drive / "rec"],
                    tmp_path / "out2", site=tmp_path / "geo.yaml",
                    anchors=Anchors(start_pose=(0, 0, 0), geodetic=(lat, lon, heading)))


def test_a_marker_the_drive_did_not_see_writes_nothing(marker_drive, tmp_path):
    far = MarkerPose(9, 20.0, 0.0, 0.0, 0.2)
    with pytest.raises(CalibrationError, match=r"marker\(s\) 9 not seen"):
        survey_site(CONFIGS / "office" / "rig.yaml", [marker_drive / "rec"], tmp_path,
                    anchors=Anchors(markers=(far,)), ceiling_height_m=2.7)
    assert not (tmp_path / "site.yaml").exists()


def test_survey_markers_are_measured_as_blockmap_measures_them(marker_drive):
    """From the same frames and poses, the survey's markers are blockmap's (the edges
    met, one square fitted), with the poses' 1σ added to the corners' covariance."""
    rec = Recording(marker_drive / "rec")
    truth = np.c_[rec.truth.x_m, rec.truth.y_m, rec.truth.yaw_rad]
    frames = [(k, rec.frame(k).image, truth[k]) for k in range(len(rec))]
    bm = {m.id: m for m in map_markers(frames, rec.rig, 2.7, "DICT_APRILTAG_36h11").placed}
    got = survey_markers(((to_grey(im), p) for _, im, p in frames), rec.rig, 2.7,
                         "DICT_APRILTAG_36h11", pose_sigma_m=4e-4)
    assert [m.id for m in got] == sorted(bm) == [3, 5]
    for m in got:
        b = bm[m.id]
        assert m.views == len(b.frames) and m.places == 1
        assert m.corners_m == pytest.approx(b.corners_m, abs=1e-9)
        assert m.corner_cov == pytest.approx(b.corner_cov + 1.6e-7 * np.eye(2))
        assert m.sigma_m == pytest.approx(math.hypot(b.corner_sigma_m, 4e-4))
        known = {k.id: k for k in KNOWN}[m.id]
        # from the true poses, measured 0.007-0.031 mm from the printed corners (17 and
        # 14 views); each corner's 1σ 0.53 mm, the 0.4 mm given for the poses in it
        assert np.linalg.norm(m.corners_m - known.corners_m(), axis=1).max() < 2e-4
