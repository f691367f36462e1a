"""`calib/checksite.py`: where on a site one frame is ambiguous (issue 36, item 4).

Small synthetic sites under an upward pinhole camera (fast), and the packaged configs
on coarse grids."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ceilkit.calib.checksite import (
    AMBIGUOUS,
    BLIND,
    HALF_TURN,
    QUARTER_TURN,
    SHIFT,
    UNDERDETERMINED,
    UNIQUE,
    CheckOptions,
    check_site,
    with_markers,
)
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import AcrossLines, Corridor, LampRow, Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from helpers import CONFIGS

COARSE = CheckOptions(step_m=1.0, heading_step_deg=90.0)


@pytest.fixture(scope="module")
def up_rig() -> Rig:
    """A small upward pinhole camera 2 m below a 2.5 m ceiling: it sees about
    3.2 x 2.4 m of the ceiling."""
    return Rig(CameraModel.pinhole(160, 120, 100.0), Mount(tilt_rad=math.pi / 2, z_m=0.5))


@pytest.fixture(scope="module")
def wide_rig() -> Rig:
    """The same, wider: it sees about 5.3 x 4 m (a handful of lights)."""
    return Rig(CameraModel.pinhole(160, 120, 60.0), Mount(tilt_rad=math.pi / 2, z_m=0.5))


def corridor_site(count: int = 6) -> Site:
    """A corridor symmetric about its centre line: seams and a lamp row down the middle."""
    return Site(2.5, Corridor((-0.6, -0.15, 0.15, 0.6)),
                lamps=(LampRow(0.0, 0.0, 1.2, 0.3, 2.4, count),))


def light_grid(dx: float = 2.0, dy: float = 2.5, nx: int = 7, ny: int = 5) -> np.ndarray:
    return np.array([[i * dx, j * dy] for i in range(nx) for j in range(ny)], float)


def seen(cell, xy, reach_m: float) -> bool:
    return math.hypot(cell.x_m - xy[0], cell.y_m - xy[1]) <= reach_m


def test_symmetric_corridor_is_ambiguous_by_a_half_turn_everywhere(up_rig):
    check = check_site(up_rig, corridor_site(), dataclasses.replace(COARSE, search_m=14.0))
    looked = [c for c in check.cells if c.status != BLIND]
    assert looked and all(c.status == AMBIGUOUS for c in looked)
    assert all(HALF_TURN in c.kinds for c in looked)
    for c in looked:                  # the twin: the half turn about a lamp row's centre
        t = next(t for t in c.twins if t.kind == HALF_TURN)
        assert t.y_m == pytest.approx(-c.y_m, abs=1e-6)
        assert abs(math.remainder(t.yaw_rad - c.yaw_rad - math.pi, 2 * math.pi)) < 1e-6
    assert check.share_kind(HALF_TURN) == pytest.approx(check.share_ambiguous)
    assert not check.x_unobserved
    # the suggestion, checked: synthetic markers single every ambiguous pose out
    assert check.regions
    for r in check.regions:
        assert r.markers_m and r.singled_out == r.n_checked == r.n_poses
        assert "would single it out" in r.suggestion


def test_one_marker_singles_out_the_poses_that_see_it(up_rig):
    site = with_markers(corridor_site(), [(6.0, 0.3)], 0.2)
    check = check_site(up_rig, site, dataclasses.replace(COARSE, search_m=14.0),
                       suggest=False)
    near = [c for c in check.cells if seen(c, (6.0, 0.3), 0.6)]
    far = [c for c in check.cells if not seen(c, (6.0, 0.3), 4.0) and c.status != BLIND]
    assert near and all(c.status == UNIQUE for c in near)
    assert far and all(c.status == AMBIGUOUS for c in far)


def test_a_marker_in_an_ignore_region_is_not_counted(up_rig):
    site = with_markers(corridor_site(), [(6.0, 0.3)], 0.2)
    site = dataclasses.replace(site, ignore_m=(np.array([[5.85, 0.18], [6.15, 0.18],
                                                         [6.15, 0.42], [5.85, 0.42]]),))
    check = check_site(up_rig, site, dataclasses.replace(COARSE, search_m=14.0),
                       suggest=False)
    near = [c for c in check.cells if seen(c, (6.0, 0.3), 0.6)]
    assert near and all(c.status == AMBIGUOUS for c in near)


def test_corridor_of_lines_along_only_leaves_x_unobserved(up_rig):
    site = Site(2.5, Corridor((-0.6, -0.15, 0.15, 0.6)))
    check = check_site(up_rig, site, COARSE)
    assert check.x_unobserved and len(check.xs_m) == 1
    assert any("x is never observed" in n for n in check.notes)
    assert any("x is never observed" in line for line in check.lines())
    for c in check.cells:               # symmetric about y = 0: the half turn only
        assert c.status == AMBIGUOUS and c.kinds == (HALF_TURN,)
        assert all(t.x_m == c.x_m for t in c.twins)
    # lines not symmetric about any centre: no twin, x still unobserved
    check = check_site(up_rig, Site(2.5, Corridor((-0.6, -0.1, 0.5))), COARSE,
                       suggest=False)
    assert all(c.status == UNIQUE for c in check.cells)


def test_regular_light_grid_is_ambiguous_by_cell_shifts(wide_rig):
    site = Site(2.5, lights_m=light_grid())
    check = check_site(wide_rig, site, COARSE, suggest=False)
    inner = [c for c in check.cells if 2.0 <= c.x_m <= 10.0 and 2.0 <= c.y_m <= 8.0
             and c.status not in (BLIND, UNDERDETERMINED)]      # one light alone
    assert inner
    ambiguous = [c for c in inner if c.status == AMBIGUOUS]
    assert len(ambiguous) >= 0.9 * len(inner)
    shifts = [t for c in ambiguous for t in c.twins if t.kind == SHIFT]
    assert shifts
    pitch = {2.0, 2.5, round(math.hypot(2.0, 2.5), 3)}
    for c in ambiguous:
        for t in c.twins:
            if t.kind == SHIFT:
                assert round(math.hypot(t.x_m - c.x_m, t.y_m - c.y_m), 3) in pitch


def test_an_irregular_light_singles_out_the_poses_near_it(wide_rig):
    lights = light_grid()
    odd = np.array([6.5, 5.0])              # (6, 5) moved by half a metre
    lights[np.argmin(np.linalg.norm(lights - [6.0, 5.0], axis=1))] = odd
    check = check_site(wide_rig, Site(2.5, lights_m=lights), COARSE, suggest=False)
    near = [c for c in check.cells if seen(c, odd, 0.75)]
    assert near and all(c.status == UNIQUE for c in near)
    far = [c for c in check.cells if 2.0 <= c.x_m <= 10.0 and 2.0 <= c.y_m <= 8.0
           and not seen(c, odd, 4.5) and c.status not in (BLIND, UNDERDETERMINED)]
    assert far and sum(c.status == AMBIGUOUS for c in far) >= 0.9 * len(far)


def test_square_tile_grid_has_quarter_turns_and_pitch_shifts(up_rig):
    along = tuple(round(-3.0 + 0.6 * k, 6) for k in range(11))
    site = Site(2.5, Corridor(along, AcrossLines(0.0, 0.6)))
    check = check_site(up_rig, site, CheckOptions(step_m=1.5), suggest=False)
    inner = [c for c in check.cells if abs(c.y_m) < 1.0]
    assert inner and all(c.status == AMBIGUOUS for c in inner)
    assert all(QUARTER_TURN in c.kinds and SHIFT in c.kinds and HALF_TURN in c.kinds
               for c in inner)
    for c in inner:
        for t in c.twins:
            if t.kind == SHIFT:
                d = math.hypot(t.x_m - c.x_m, t.y_m - c.y_m)
                assert d == pytest.approx(0.6, abs=1e-6) or d == pytest.approx(0.6 * 2 ** .5)


def test_nothing_in_view_is_blind_not_unique(up_rig):
    site = Site(2.5, lights_m=np.array([[0.0, 0.0], [20.0, 0.0]]))
    check = check_site(up_rig, site, CheckOptions(step_m=5.0), suggest=False)
    mid = [c for c in check.cells if 5.0 <= c.x_m <= 15.0]
    assert mid and all(c.status == BLIND for c in mid)


def test_packaged_lights_config_is_unambiguous():
    rig = Rig.load(CONFIGS / "lights" / "rig.yaml")
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    check = check_site(rig, site, CheckOptions(step_m=3.0))
    assert check.share_ambiguous == 0.0 and not check.regions
    assert check.share(UNIQUE) == 1.0


def test_packaged_corridor_config_has_its_half_turn():
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    site = dataclasses.replace(site, lamps=(dataclasses.replace(site.lamps[0], count=12),))
    check = check_site(rig, site, CheckOptions(step_m=3.0), suggest=False)
    # along the corridor, away from the lamp row's ends (the camera sees 10 m ahead)
    forward = [c for c in check.cells if abs(math.cos(c.yaw_rad)) > 0.99
               and 10.0 <= c.x_m <= 16.0]
    assert forward and all(HALF_TURN in c.kinds for c in forward)
    text = "\n".join(check.lines())
    assert "half turn" in text and "ambiguous:" in text


def test_packaged_block_config_is_mostly_singled_out_by_its_markers():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    check = check_site(rig, site, CheckOptions(step_m=1.5), suggest=False)
    assert check.share(UNIQUE) > 0.8
    near_marker = [c for c in check.cells
                   if any(seen(c, (m.x_m, m.y_m), 0.5) for m in site.markers.poses)]
    assert near_marker and all(c.status == UNIQUE for c in near_marker)
    # without its markers and blocks the same tiles repeat everywhere
    bare = dataclasses.replace(site, markers=None, blocks=())
    check = check_site(rig, bare, CheckOptions(step_m=1.5), suggest=False)
    inner = [c for c in check.cells if abs(c.y_m) < 0.5]
    assert inner and all(c.status == AMBIGUOUS for c in inner)


def test_figures_and_options():
    with pytest.raises(ConfigError, match="step_m"):
        CheckOptions(step_m=0.0)
    with pytest.raises(ConfigError, match="no feature"):
        check_site(Rig(CameraModel.pinhole(160, 120, 100.0), Mount(tilt_rad=math.pi / 2)),
                   Site(2.5))
