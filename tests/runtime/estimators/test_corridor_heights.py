"""Lines along the corridor below the ceiling (pipes, ducts, cable trays): they share the
forward vanishing point but not the ceiling's lateral geometry, and must never pull the
lateral estimate (runtime/estimators/corridor/consensus.py, issue 16)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor import CorridorEstimator
from ceilkit.runtime.estimators.corridor.consensus import ceiling_consensus, endpoint_distances
from ceilkit.runtime.estimators.corridor.refine import GNInputs, residuals
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.sim import render as sim

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "corridor"
POSE = (0.3, 0.1, 0.2)                                  # x, y, yaw of the vehicle

HEADING = {"assume_heading_deg": 0.0}
"""The packaged corridor is symmetric about its centre line: its accuracy tests state
the heading, as a user may (a frame alone cannot tell it from the half turn)."""



@pytest.fixture

def rig(corridor_rig: Rig) -> Rig:
    return corridor_rig


@pytest.fixture
def site(corridor_site: Site) -> Site:
    return corridor_site


def projected(rig: Rig, pose: tuple[float, float, float],
              lines_w: list[tuple[tuple[float, float, float], tuple[float, float, float]]]
              ) -> np.ndarray:
    """Pixel segments ``(N, 4)``: the visible stretch of each world segment (a, b)
    projected exactly through the rig at ``pose`` (those shorter than 30 px dropped)."""
    cam, m = rig.camera, rig.mount
    R_wc, C = m.R_world_cam(pose[2]), m.camera_position(*pose)
    out = []
    for a, b in lines_w:
        t = np.linspace(0.0, 1.0, 2000)[:, None]
        P = np.asarray(a) + t * (np.asarray(b) - np.asarray(a))
        px = cam.project((P - C) @ R_wc)
        i = np.flatnonzero(np.isfinite(px[:, 0]) & cam.in_image(px, 2.0))
        if i.size >= 2 and math.hypot(*(px[i[-1]] - px[i[0]])) >= 30:
            out.append(np.r_[px[i[0]], px[i[-1]]])
    return np.array(out).reshape(-1, 4)


def ceiling_lines(site: Site, x: float) -> list:
    """The example site's seams and lamp edges around ``x``, at the ceiling."""
    H = site.ceiling_height_m
    out = []
    for yj in site.corridor.lines_along_m:
        if abs(yj) < 0.2:                                  # lamp long edges
            out += [((-0.6 + 2.4 * k, yj, H), (0.6 + 2.4 * k, yj, H)) for k in range(-3, 5)]
        else:                                              # seams
            out.append(((x - 20.0, yj, H), (x + 20.0, yj, H)))
    return out


def pipe_lines(rig: Rig, site: Site, pose, drop_m: float,
               seen_at: tuple[float, ...]) -> list:
    """Lines along x ``drop_m`` below the ceiling whose images are those of ceiling
    lines at ``seen_at`` (m): y' = c_y + (y - c_y) h' / h."""
    H = site.ceiling_height_m
    C = rig.mount.camera_position(*pose)
    h = H - C[2]
    out = []
    for y_seen in seen_at:
        y = C[1] + (y_seen - C[1]) * (h - drop_m) / h
        out.append(((pose[0] - 20.0, y, H - drop_m), (pose[0] + 20.0, y, H - drop_m)))
    return out


def thin_and_steps(n_ceiling: int, n_pipes: int) -> np.ndarray:
    """Polarities: the ceiling's segments unknown (NaN), the pipes' edges steps."""
    return np.r_[np.full(n_ceiling, np.nan), np.ones(n_pipes)]


def test_endpoint_distances_are_the_residuals_of_the_joint_fit(rig, site):
    """The consensus's distances over many camera y are the joint fit's residuals."""
    est = CorridorEstimator(rig, site, HEADING)
    rng = np.random.default_rng(3)
    k = 12
    gd = GNInputs(n_a=k // 2, y=np.repeat(rng.choice(est.setup.site_y, k // 2), 2),
                  e0=rng.normal(0, 0.3, k), e1=rng.normal(0, 0.3, k),
                  ez=rng.normal(0.7, 0.1, k), p0=np.zeros(0), p1=np.zeros(0),
                  mx_b=np.zeros(0), my_b=np.zeros(0), scale_b=np.zeros(0))
    cys = np.array([-0.3, 0.05, 0.4])
    d = endpoint_distances(0.3, cys, gd, est.setup)
    for c, row in zip(cys, d, strict=True):
        np.testing.assert_allclose(row, residuals(0.3, c, gd, est.setup)[:, 2], atol=1e-9)


def test_consensus_prefers_tight_lines_to_more_lines():
    """Three lines hit to 0.05 px beat four missed by 1.5 px (a pipe taken for a seam)."""

    class Flat:                                            # distances given directly
        pass

    import ceilkit.runtime.estimators.corridor.consensus as cc

    d = np.array([[0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 5.0, 5.0],     # true: 3 lines
                  [1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 0.0, 0.0]])          # shifted: 4 lines
    orig = cc.endpoint_distances
    cc.endpoint_distances = lambda psi, c, gd, st: d[:len(c)]
    try:
        gd = GNInputs(4, *(np.zeros(8),) * 4, *(np.zeros(0),) * 5)
        r = ceiling_consensus(0.0, np.array([0.1, 0.2]), np.array([0, 1, 2, 3]), gd, Flat(),
                              gate_px=1.0)
    finally:
        cc.endpoint_distances = orig
    assert r.camera_y_m == 0.1 and r.n_lines == 3
    assert r.inlier.tolist() == [True, True, True, False]


@pytest.mark.parametrize("drop_m", [0.25, 0.45])
def test_pipes_near_the_seams_do_not_pull_the_lateral(rig, site, drop_m):
    """Pipes below the ceiling whose images fall 2-4 cm beside the seams (inside the
    1-D association's gate): the estimate is the one without them, to 1e-6."""
    x, y, yaw = POSE
    ceil = projected(rig, POSE, ceiling_lines(site, x))
    pipes = projected(rig, POSE, pipe_lines(rig, site, POSE, drop_m, (0.48, -0.425, 0.42)))
    est = CorridorEstimator(rig, site, HEADING)
    clean = est.estimate_segments(ceil, 0, polarity=thin_and_steps(len(ceil), 0))
    r = est.estimate_segments(np.vstack([ceil, pipes]), 0,
                              polarity=thin_and_steps(len(ceil), len(pipes)))
    assert clean and r, (clean, r)
    assert abs(clean.y_m - y) < 1e-6
    assert abs(r.y_m - clean.y_m) < 1e-6
    assert abs(wrap_pi(r.yaw_rad - clean.yaw_rad)) < 1e-7
    assert r.diagnostics["n_off_ceiling"] >= 2
    assert r.diagnostics["n_lines_matched"] == clean.diagnostics["n_lines_matched"]


def test_a_step_hugging_a_seam_is_left_out(rig, site):
    """A pipe's edge (a step) whose image lies within a pixel of a seam's (a seam is a
    thin line): a step on a seam must fit three times better than the gate
    (association.SEAM_STEP), so it does not pull the lateral."""
    lines = ceiling_lines(site, POSE[0])
    seams = projected(rig, POSE, [ab for ab in lines if abs(ab[0][1]) > 0.2])
    lamps = projected(rig, POSE, [ab for ab in lines if abs(ab[0][1]) < 0.2])
    pipes = projected(rig, POSE, pipe_lines(rig, site, POSE, 0.35, (0.452,)))
    ceil = np.vstack([seams, lamps])
    pol = np.r_[np.zeros(len(seams)), np.full(len(lamps), np.nan)]     # seams thin
    est = CorridorEstimator(rig, site, HEADING)
    clean = est.estimate_segments(ceil, 0, polarity=pol)
    r = est.estimate_segments(np.vstack([ceil, pipes]), 0,
                              polarity=np.r_[pol, np.ones(len(pipes))])
    assert clean and r, (clean, r)
    assert r.diagnostics["n_off_ceiling"] == len(pipes) >= 1
    assert abs(r.y_m - clean.y_m) < 1e-6


def test_only_lines_at_another_height_in_view_fail(rig, site):
    """Only pipes in view, one seen beside a seam, one between the site's lines: a
    Failure with a reason, never a lateral."""
    pipes = projected(rig, POSE, pipe_lines(rig, site, POSE, 0.35, (0.48, -0.30)))
    r = CorridorEstimator(rig, site, HEADING).estimate_segments(pipes, 0,
                                                      polarity=np.ones(len(pipes)))
    assert not r, r
    assert r.reason in ("weak_geometry", "no_association", "too_few_lines"), r


@pytest.mark.parametrize("seen_at", [(0.48, -0.42), (0.48, -0.40), (0.47, 0.17, -0.42)])
def test_pipes_that_mimic_two_site_lines_are_a_known_limit(rig, site, seen_at):
    """Pipes alone whose images fall within the association's gate of two site lines
    (3-4 cm off them): two lines fit ``(psi, c_y)`` whatever their heights, so one
    frame cannot tell them from the ceiling's (the known limit, docs/methods/
    corridor.md). What holds: two lines never reach quality 0.5."""
    pipes = projected(rig, POSE, pipe_lines(rig, site, POSE, 0.35, seen_at))
    r = CorridorEstimator(rig, site, HEADING).estimate_segments(pipes, 0,
                                                      polarity=np.ones(len(pipes)))
    assert not r or (r.diagnostics["n_lines_matched"] == 2 and r.quality < 0.5), r


@pytest.mark.parametrize("knob", ["pipes", "trays"])
def test_rendered_pipes_and_trays_match_the_clean_render(rig, site, knob):
    """The realistic preset's pipes and duct (or its cable tray) alone, on the bench's
    drive: every frame estimated as on the clean render (was: `misfit` on every frame
    with pipes, on 12 of 30 with the tray)."""
    from ceilkit.runtime.sim.realism import load_preset

    real = load_preset(CONFIGS / "site.yaml", "realistic").only(knob)
    traj = sim.straight_drive(9, 30.0, rng=np.random.default_rng(5), speed_mps=0.8,
                              x0_m=0.0, y_m=0.1, weave_m=0.25,
                              yaw_wobble_rad=math.radians(4.0))
    clean = sim.SimSource(rig, site, traj, seed=5)
    dirty = sim.SimSource(rig, site, traj, seed=5, realism=real)
    est = CorridorEstimator(rig, site, HEADING)
    for k in range(0, 9, 2):
        a = est.estimate(clean.render(k).image, 0)
        b = est.estimate(dirty.render(k).image, 0)
        assert isinstance(a, PoseEstimate) and isinstance(b, PoseEstimate), (k, a, b)
        assert abs(b.y_m - a.y_m) < 1e-3, (k, b.y_m - a.y_m)
        assert abs(math.degrees(wrap_pi(b.yaw_rad - a.yaw_rad))) < 0.03, k
        assert b.diagnostics["n_off_ceiling"] > 0
