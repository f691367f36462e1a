"""Issue 38: the window paths are as honest as the global ones. A corridor window fix
carries the twins the global path would list (the site's symmetries applied to the
fix, each checked on the frame) and is ``Provenance.PRIOR`` when it has any; it defers
to the global path when a twin explains the frame better or lies inside the prior's
region. A block window fix runs the global path's checks (a block's inside, a
marker's code)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Block, MarkerPose, Markers, Site
from ceilkit.runtime.estimators.base import PoseEstimate, Provenance
from ceilkit.runtime.estimators.block.estimator import WINDOW, BlockEstimator
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.sim.marks import BLOCK_GREY
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS, tile_grid

SIM = SimOptions(noise_sigma=2.0, blur_px=0.8)


def corridor_prior(y: float, yaw: float, sigma_m: float = 0.01) -> PoseEstimate:
    return PoseEstimate(0, "track", None, y, yaw, 0.0,
                        cov=np.diag([np.inf, sigma_m ** 2, math.radians(2.0) ** 2]))


def pair(rig, site, **kw):
    """The global path and the window path (no scheduled global search)."""
    return (CorridorEstimator(rig, site, {"window_search": False, **kw}),
            CorridorEstimator(rig, site, {"window_search": True, "window_full_every": 0,
                                          **kw}))


def twins_of(est, label):
    return sorted((round(h.y_m, 3), round(math.degrees(h.yaw_rad)))
                  for h in est.hypotheses if h.label == label and h.y_m is not None)


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> tuple[Rig, Site]:
    return tile_grid(tmp_path_factory.mktemp("tiles"))


def test_a_window_fix_on_a_symmetric_corridor_carries_its_half_turn():
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    glob, win = pair(rig, site)
    rng = np.random.default_rng(3)
    for x, y, yaw in ((3.0, 0.1, 0.05), (5.0, -0.2, 3.1), (7.0, 0.3, -0.1)):
        img = render_frame(rig, site, x, y, yaw, SIM, rng)
        p = corridor_prior(y + 0.003, yaw + 0.001)
        g, w = glob.estimate(img, 0, p), win.estimate(img, 0, p)
        assert w.diagnostics["search"] == "window"
        # the prior chose among twins on both paths: never relocalization evidence
        assert g.provenance is w.provenance is Provenance.PRIOR
        assert w.hypotheses_complete and g.hypotheses_complete
        assert [h.label for h in w.hypotheses] == ["chosen", "half_turn"]
        for a, b in zip(g.hypotheses, w.hypotheses, strict=True):
            assert abs(a.y_m - b.y_m) < 1e-3 and abs(a.yaw_rad - b.yaw_rad) < 1e-3


def test_a_half_turned_prior_on_an_asymmetric_corridor_goes_global(tmp_path):
    """One seam more on one side: the window search about a half-turned prior finds the
    mirrored lines, but the half turn of its fix finds one line more (the seam it did
    not search): the global path decides, and rules the prior's twin out."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    d = yaml.safe_load((CONFIGS / "corridor" / "site.yaml").read_text())
    d["corridor"]["lines_along"] = [-0.45, -0.15, 0.15, 0.45, 0.9]
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(d))
    site = Site.load(tmp_path / "site.yaml")
    _, win = pair(rig, site)
    rng = np.random.default_rng(2)
    for x, y, yaw_deg in ((3.0, 0.2, 4.0), (9.0, 0.3, 184.0), (5.0, -0.1, 176.0)):
        yaw = math.radians(yaw_deg)
        img = render_frame(rig, site, x, y, yaw, SIM, rng)
        flipped = win.estimate(img, 0, corridor_prior(-y, yaw + math.pi))
        assert flipped and flipped.diagnostics["search"] != "window"
        assert flipped.provenance is Provenance.GLOBAL
        assert abs(flipped.y_m - y) < 0.005
        right = win.estimate(img, 0, corridor_prior(y + 0.003, yaw + 0.001))
        # no twin fits this corridor: the window fix stands alone
        assert right.diagnostics["search"] == "window" and not right.hypotheses
        assert right.provenance is Provenance.WINDOW and abs(right.y_m - y) < 0.005


def test_a_window_fix_on_tiles_lists_the_global_paths_twins(tiles):
    rig, site = tiles
    glob, win = pair(rig, site)
    rng = np.random.default_rng(3)
    windowed = 0
    for x, y, yaw in ((1.0, 0.1, 0.3), (0.5, 0.7, 2.0), (1.3, -0.4, -1.0)):
        img = render_frame(rig, site, x, y, yaw, SIM, rng)
        p = corridor_prior(y + 0.003, yaw + 0.001)
        g, w = glob.estimate(img, 0, p), win.estimate(img, 0, p)
        windowed += w.diagnostics["search"] == "window"
        if w.diagnostics["search"] != "window":
            # a shift at the grid's end that misses fewer lines: the global path decides
            assert w.provenance is g.provenance and w.y_m == g.y_m
            continue
        assert w.provenance is Provenance.PRIOR and w.diagnostics["ambiguous"]
        assert w.quality == pytest.approx(g.quality, abs=0.05)
        # the lateral shifts and half turns: every one of the global path's but one
        # at the grid's end at most (the two paths count its lines in view apart)
        for label in ("shift", "half_turn"):
            a, b = set(twins_of(g, label)), set(twins_of(w, label))
            assert len(a ^ b) <= 2 and len(a & b) >= len(a) - 1
        # both quarter turns, their lateral not measured: the list is not complete
        quarter = [h for h in w.hypotheses if h.label == "quarter_turn"]
        assert len(quarter) == 2 and all(h.y_m is None for h in quarter)
        assert not w.hypotheses_complete
        # a prior whose region holds several shifts: ambiguous, as on the global path
        wide = corridor_prior(y, yaw, sigma_m=0.3)
        gw, ww = glob.estimate(img, 0, wide), win.estimate(img, 0, wide)
        assert not gw and not ww and gw.reason == ww.reason == "ambiguous"
    assert windowed >= 2


RECT = np.array([[2.0, -0.2], [2.6, -0.2], [2.6, 0.2], [2.0, 0.2]])


def painted(img: np.ndarray, corner: int, share: float) -> np.ndarray:
    """``img`` with a ``share`` by ``share`` corner of the block's box painted with the
    ceiling's grey."""
    v, u = np.nonzero(img < (BLOCK_GREY + 150) / 2)
    out = img.copy()
    hv, hu = int((v.max() - v.min()) * share), int((u.max() - u.min()) * share)
    rows = slice(v.min(), v.min() + hv) if corner < 2 else slice(v.max() - hv, v.max() + 1)
    cols = slice(u.min(), u.min() + hu) if corner % 2 == 0 else slice(u.max() - hu, u.max() + 1)
    out[rows, cols] = 150
    return out


def test_a_block_window_fix_is_refused_where_the_global_path_refuses():
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site(3.0, blocks=(Block("A", RECT, "dark"),))
    opts = {"heading_cue": False, "plane_odometry": False, "window_full_every": 0}
    glob = BlockEstimator(rig, site, {**opts, "window_search": False})
    win = BlockEstimator(rig, site, {**opts, "window_search": True})
    x, y, yaw = 2.2, 0.0, 0.0
    base = render_frame(rig, site, x, y, yaw, SimOptions(noise_sigma=2.0, blur_px=1.0))
    prior = PoseEstimate(0, "prior", x, y, yaw, 1.0)
    clean = win.estimate(base, 0, prior)
    # a symmetric block: its prior chose the correspondence, on the window path too
    assert clean.diagnostics["mode"] == WINDOW and clean.provenance is Provenance.PRIOR
    refused = 0
    for corner in range(4):
        for share in (0.25, 0.5):
            img = painted(base, corner, share)
            g, w = glob.estimate(img, 0, prior), win.estimate(img, 0, prior)
            assert bool(g) == bool(w), (corner, share, g, w)
            refused += not g
    assert refused >= 6


def test_a_marker_window_fix_reads_its_code():
    """The site puts marker 3 where the frame shows marker 7: the outline fits, the
    code does not; the window path leaves the frame to the global path, which reads
    7 (not in the site)."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    shown = Site(3.0, markers=Markers("DICT_APRILTAG_36h11", 0.25,
                                      (MarkerPose(7, 2.3, 0.0, 0.0, 0.25),)))
    told = Site(3.0, markers=Markers("DICT_APRILTAG_36h11", 0.25,
                                     (MarkerPose(3, 2.3, 0.0, 0.0, 0.25),)))
    img = render_frame(rig, shown, 2.2, 0.0, 0.0, SimOptions(noise_sigma=2.0, blur_px=1.0))
    prior = PoseEstimate(0, "prior", 2.2, 0.0, 0.0, 1.0)
    opts = {"plane_odometry": False, "window_full_every": 0, "heading_cue": False}
    right = BlockEstimator(rig, shown, opts).estimate(img, 0, prior)
    assert right and right.diagnostics["mode"] == WINDOW
    wrong = BlockEstimator(rig, told, opts).estimate(img, 0, prior)
    assert not wrong and wrong.reason == "unknown_marker"
