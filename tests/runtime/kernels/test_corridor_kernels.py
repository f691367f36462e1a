"""The corridor method's compiled loops against their array readings
(tests/corridor_reference.py): the 1-D association, the pan candidates, the families
and hypotheses, the consensus fit, the rolling shutter's steps, the edge fit of the
segments and the pose's counts must give the same numbers (to float rounding) and the
same decisions as the code they replaced, on random inputs and on the stages' inputs
in rendered frames."""

from __future__ import annotations

import math
from dataclasses import replace

import corridor_reference as ref
import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.corridor import association, consensus, frame, hypotheses
from ceilkit.runtime.estimators.corridor import estimator as cest
from ceilkit.runtime.estimators.corridor.refine import (
    RowRates,
    gauss_newton,
    gauss_newton_rows,
    gn_inputs,
)
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.features.edges import directions, profiles_along, profiles_at
from ceilkit.runtime.features.lines import refine_undistorted
from ceilkit.runtime.geometry.camera import (
    CameraModel,
    _unskewed,
    undistort_fixed_points,
    unproject_many,
)
from ceilkit.runtime.jit import arr
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

TOL = 1e-10

HEADING = {"assume_heading_deg": 0.0}
"""The packaged corridor is symmetric about its centre line: its tests state the
heading, as a user may (a frame alone cannot tell it from the half turn)."""


@pytest.fixture(scope="module")
def seen():
    """The stages' inputs while the corridor estimator (global path, without and with
    a prior) runs on rendered frames of configs/corridor: ``{"refine": [(camera, grey,
    segs_px, half_width, retry)], "pans": [(q, w)], "label": [(psi0, fr, prior,
    prior_psi, ctx)], "fit": [(fr, lab, st, inlier_px, iterations)]}``, and the
    estimator."""
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    est = make_estimator("corridor", rig, site, HEADING)
    out: dict[str, list] = {"refine": [], "pans": [], "label": [], "fit": []}
    mp = pytest.MonkeyPatch()

    def spy(owner, name, key, keep):
        real = getattr(owner, name)

        def f(*a, **k):
            out[key].append(keep(*a, **k))
            return real(*a, **k)

        mp.setattr(owner, name, f)

    spy(frame, "refine_undistorted", "refine",
        lambda cam, g, s, half_width_px, retry_half_width_px: (cam, g, s, half_width_px,
                                                               retry_half_width_px))
    spy(cest, "dominant_pans", "pans", lambda q, w: (q, w))
    spy(hypotheses, "label", "label", lambda *a: a)
    spy(cest, "consensus_fit", "fit",
        lambda fr, lab, st, inlier_px, iterations, rates, tau:
        (fr, lab, st, inlier_px, iterations))
    prior = None
    try:
        for k, pose in enumerate([(2.0, 0.1, 0.02), (4.0, -0.25, -0.06), (6.5, 0.3, 0.1),
                                  (8.0, 0.0, math.pi - 0.05), (9.0, -0.1, 1.2)]):
            img = render_frame(rig, site, *pose, rng=np.random.default_rng(k),
                               options=SimOptions(noise_sigma=2.0, blur_px=0.8))
            got = est.estimate(img, k, None)
            est.estimate(img, k, got if got else prior)
            prior = got or prior
    finally:
        mp.undo()
    assert all(out.values())
    return out, est


def _same_match(got, want):
    assert (got is None) == (want is None)
    if got is None:
        return
    assert np.array_equal(got.assign, want.assign) and got.n_lines == want.n_lines
    assert abs(got.shift_m - want.shift_m) < TOL and abs(got.weight - want.weight) < TOL
    assert abs(got.score - want.score) < TOL
    assert (got.runner_up is None) == (want.runner_up is None)
    if got.runner_up is not None:
        np.testing.assert_allclose(got.runner_up, want.runner_up, rtol=0, atol=TOL)


# ----------------------------------------------------------------------------- association

@pytest.mark.parametrize("seed", range(4))
def test_match_offsets_equals_the_array_reading(seed):
    """Offsets of site lines (missing, extra, shifted, NaN) with and without edge
    compatibility, lamp anchors and a prior: the same match, runner-up and score."""
    rng = np.random.default_rng(seed)
    for _ in range(150):
        nj = int(rng.integers(1, 12))
        ys = np.sort(rng.uniform(-2, 2, nj)) + np.arange(nj) * 0.05
        tol = float(rng.uniform(0.02, 0.09))
        n = int(rng.integers(0, 25))
        shift = rng.normal(0, 0.5)
        offs = rng.choice(ys, n) - shift + rng.normal(0, rng.choice([0.003, 0.03]), n)
        extra = rng.random(n) < 0.2
        offs[extra] = rng.uniform(-2.5, 2.5, np.count_nonzero(extra))
        offs[rng.random(n) < 0.05] = np.nan
        w = rng.uniform(20, 400, n)
        compat = None
        if rng.random() < 0.7:
            compat = rng.choice([0.0, association.SEAM_STEP, 1.0], (n, nj), p=[0.2, 0.2, 0.6])
        anchors = rng.normal(shift, 0.05, int(rng.integers(1, 4))) if rng.random() < 0.3 else None
        prior = shift + rng.normal(0, 0.1) if rng.random() < 0.4 else None
        want = ref.match_offsets(offs, w, ys, tol, prior, anchors, compat)
        got = association.match_offsets(offs, w, ys, tol, prior, anchors, compat)
        _same_match(got, want)


def test_edge_compat_and_lamp_anchors_equal_the_array_reading(seen):
    out, est = seen
    st = est.setup
    rng = np.random.default_rng(2)
    pol = rng.choice([np.nan, -1.0, 0.0, 1.0], 40)
    ceil_len = rng.uniform(0, 4, 40)
    assert np.array_equal(association.edge_compat(pol, ceil_len, st),
                          ref.edge_compat(pol, ceil_len, st))
    for psi0, fr, *_ in out["label"]:
        for sel in (fr.len_n > 0, rng.random(fr.len_n.size) < 0.5):
            np.testing.assert_allclose(
                association.lamp_anchors(st, fr.lamp_end, fr.ceil_sx, fr.ceil_sy, sel, psi0),
                ref.lamp_anchors(st, fr.lamp_end, fr.ceil_sx, fr.ceil_sy, sel, psi0),
                rtol=0, atol=TOL)


# ----------------------------------------------------------------------------- hypotheses

def test_dominant_pans_equal_the_array_reading(seen):
    """The frames' candidates, and random directions (peaks across the histogram's wrap,
    zero weights, a lone segment)."""
    cases = list(seen[0]["pans"])
    rng = np.random.default_rng(4)
    for n in (0, 1, 2, 7, 60, 120):
        q = rng.normal(size=(n, 3))
        q[: n // 2, :2] = [0.01, 1.0] + rng.normal(0, 0.01, (n // 2, 2))   # about 0 deg
        cases.append((q, rng.uniform(0, 100, n) * (rng.random(n) < 0.9)))
    for q, w in cases:
        np.testing.assert_allclose(hypotheses.dominant_pans(q, w), ref.dominant_pans(q, w),
                                   rtol=0, atol=TOL)


def test_families_and_hypotheses_equal_the_array_reading(seen):
    """label's families about each pan candidate (and candidates off by up to a few
    degrees), and every labeling k of them with and without a prior's shift."""
    out, est = seen
    st = est.setup
    rng = np.random.default_rng(5)
    n_ok = 0
    for psi0, fr, _, _, ctx in out["label"]:
        for dpsi in (0.0, *rng.normal(0, 0.03, 3)):
            n = fr.len_n.size
            along, across = np.empty(n, bool), np.empty(n, bool)
            got = hypotheses.families_core(fr.arrays, ctx.kernel_setup, psi0 + dpsi,
                                           ctx.angle_tol_rad, along, across)
            want = ref.label_families(psi0 + dpsi, fr, ctx.angle_tol_rad, st)
            assert got[0] == want[0]
            if not got[0]:
                continue
            n_ok += 1
            assert abs(got[1] - want[1]) < TOL
            assert np.array_equal(along, want[2]) and np.array_equal(across, want[3])
            assert abs(got[2] - want[4]) < TOL and abs(got[3] - want[5]) < TOL
            for k in range(4):
                for prior_y in (None, rng.normal(0, 0.3)):
                    prior = None if prior_y is None else _prior(prior_y)
                    h = hypotheses.hypothesis(k, got[1], along, across, fr, (got[2], got[3]),
                                              prior, ctx)
                    shift = None
                    if prior is not None:
                        shift = prior.y_m + float((hypotheses.rot_z(hypotheses.wrap_pi(
                            h.psi_rad - st.pan_rad)) @ st.t_vc)[1])
                    offs, wa, compat, m = ref.hypothesis_arrays(h.psi_rad, h.fa, h.fb, fr, st,
                                                               ctx.match_tol_m, shift)
                    np.testing.assert_allclose(h.offsets_m, offs, rtol=0, atol=TOL)
                    np.testing.assert_allclose(h.weights, wa, rtol=0, atol=TOL)
                    assert np.array_equal(h.compat, compat)
                    _same_match(h.match, m)
    assert n_ok


def _prior(y_m):
    from ceilkit.runtime.estimators.base import PoseEstimate
    return PoseEstimate(0, "corridor", None, y_m, 0.0, 1.0, y_m, np.eye(3), {})


# ----------------------------------------------------------------------------- consensus

def _labelings(out, rng):
    """The frames' labelings, and each with some matched segments moved to a
    neighbouring site line and some unmatched ones matched (to exercise the gates)."""
    for fr, lab, st, inlier_px, iterations in out["fit"]:
        yield fr, lab, st, inlier_px, iterations
        for _ in range(3):
            a = lab.assign.copy()
            ia = np.flatnonzero(lab.along & (a >= 0))
            move = ia[rng.random(ia.size) < 0.2]
            a[move] = np.clip(a[move] + rng.choice([-1, 1], move.size), 0, st.site_y.size - 1)
            free = np.flatnonzero(lab.along & (a < 0))
            a[free] = rng.integers(0, st.site_y.size, free.size)
            yield fr, replace(lab, assign=a, camera_y_m=lab.camera_y_m + rng.normal(0, 0.02)), \
                st, inlier_px, iterations


@pytest.mark.parametrize("rolling", [False, True])
def test_consensus_fit_equals_the_array_reading(seen, rolling):
    """The compiled rounds against the array reading with its callbacks (the GN inputs,
    gauss_newton or the array gauss_newton_rows): the same segments left out, the same
    fit."""
    out, _ = seen
    rng = np.random.default_rng(6)
    n = 0
    for fr, lab, st, inlier_px, iterations in _labelings(out, rng):
        rates = tau = None
        if rolling:
            rates = RowRates(rng.normal(0, 0.3), rng.normal(0, 0.3), 0.05, 0.05)
            tau = rng.uniform(0, 0.03, (fr.len_n.size, 2))

        def inputs(assign, fr=fr, lab=lab, st=st, tau=tau):
            return gn_inputs(fr, lab.along, lab.across, assign, st, tau)

        def solve_ref(gd, psi, cy, st=st, iterations=iterations, rates=rates):
            if rates is None:
                return gauss_newton(psi, cy, gd, st, iterations)
            return ref.gauss_newton_rows(psi, cy, gd, st, iterations, rates)

        ff = consensus.consensus_fit(fr, lab, st, inlier_px, iterations, rates, tau)
        got_lab, got_gd, got = ff.labeling, ff.gd, ff.fit
        want_lab, want_gd, want = ref.consensus_fit(fr, lab, st, inlier_px, inputs, solve_ref,
                                                    rates)
        assert np.array_equal(got_lab.assign, want_lab.assign)
        for k in ("y", "e0", "e1", "ez", "p0", "p1", "mx_b", "my_b", "scale_b", "tau", "tau_b"):
            g, w = getattr(got_gd, k), getattr(want_gd, k)
            assert (g is None) == (w is None) and (g is None or np.array_equal(g, w)), k
        assert got_lab.n_lines == want_lab.n_lines
        assert got_lab.n_off_ceiling == want_lab.n_off_ceiling
        assert abs(got.psi_rad - want.psi_rad) < TOL
        assert abs(got.camera_y_m - want.camera_y_m) < TOL
        np.testing.assert_allclose(got.residuals_px, want.residuals_px, rtol=0, atol=1e-8)
        np.testing.assert_allclose(got.cov, want.cov, rtol=1e-8, atol=0)
        n += got_lab.n_off_ceiling > 0
    assert n                         # some segments were left out


def test_gauss_newton_rows_equals_the_array_reading(seen):
    """The compiled rolling-shutter steps and covariance, on the frames' GN inputs with
    random row times and rates (and one singular: no along endpoints)."""
    out, _ = seen
    rng = np.random.default_rng(7)
    for fr, lab, st, _, iterations in out["fit"]:
        tau = rng.uniform(0, 0.03, (fr.len_n.size, 2))
        for assign in (lab.assign, np.full_like(lab.assign, -1)):
            gd = gn_inputs(fr, lab.along, lab.across, assign, st, tau)
            rates = RowRates(rng.normal(0, 0.5), rng.normal(0, 0.5), 0.1, 0.2)
            start = (lab.psi_rad + 0.01, lab.camera_y_m - 0.03)
            got = gauss_newton_rows(*start, gd, st, iterations, rates)
            want = ref.gauss_newton_rows(*start, gd, st, iterations, rates)
            assert abs(got.psi_rad - want.psi_rad) < TOL
            assert abs(got.camera_y_m - want.camera_y_m) < TOL
            np.testing.assert_allclose(got.residuals_px, want.residuals_px, rtol=0, atol=1e-8)
            np.testing.assert_allclose(got.cov, want.cov, rtol=1e-8, atol=0)


# ----------------------------------------------------------------------------- edge fit

def test_refine_undistorted_equals_the_array_reading(seen):
    """The frames' segments (with the estimator's widths and retry), and random ones
    reaching past the frame's border: the same kinds, lines and fit rms."""
    out, _ = seen
    rng = np.random.default_rng(8)
    cases = list(out["refine"])
    cam, grey = cases[0][:2]
    h, w = grey.shape
    s = np.column_stack([rng.uniform(-5, w + 5, (60, 2)), rng.uniform(-5, h + 5, (60, 2))])
    cases.append((cam, grey, s[:, [0, 2, 1, 3]], 4.0, 6.0))
    for cam, grey, segs, half, retry in cases:
        got = refine_undistorted(cam, grey, segs, half_width_px=half, retry_half_width_px=retry)
        want = ref.refine_undistorted(cam, grey, segs, half_width_px=half,
                                      retry_half_width_px=retry)
        for g, wv in zip(got, want, strict=True):
            np.testing.assert_array_equal(np.isnan(g), np.isnan(wv))
            np.testing.assert_allclose(g, wv, rtol=0, atol=1e-12)


def test_refine_undistorted_one_call_equals_its_stages(seen, monkeypatch):
    """The edge fit in one compiled call (``_refine_fixed``, a lens inverted by fixed
    iterations, the retry inside) gives the numbers of its stages called one by one
    (the path of any other lens), bit for bit, on the frames' segments."""
    from ceilkit.runtime.features import lines

    out, _ = seen
    cam, grey, segs = out["refine"][0][:3]
    cases = out["refine"] + [(cam, grey, segs, 4.0, None), (cam, grey, segs, 4.0, 3.0),
                             (cam, grey, segs[:1], 10.0, 15.0), (cam, grey, segs[:0], 4.0, 6.0)]
    assert lines.fixed_iterations(cam) > 0
    fused = [refine_undistorted(c, g, s, half_width_px=h, retry_half_width_px=r)
             for c, g, s, h, r in cases]
    monkeypatch.setattr(lines, "fixed_iterations", lambda camera: 0)
    for (c, g, s, h, r), got in zip(cases, fused, strict=True):
        want = refine_undistorted(c, g, s, half_width_px=h, retry_half_width_px=r)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    assert any(np.isnan(refine_undistorted(c, g, s, half_width_px=h,
                                           retry_half_width_px=None)[1]).any()
               for c, g, s, h, r in cases)          # the retry had rows to look at


@pytest.mark.skipif("*AVX2" not in cv2.getCPUFeaturesLine(),
                    reason="OpenCV's remap without its AVX2 (fused multiply-add) code")
def test_profiles_along_equal_opencv_remap():
    """The compiled bilinear samples are cv2.remap's, bit for bit: random frames and
    segments, inside, across and beyond the border, on and off the 1/64 px grid."""
    rng = np.random.default_rng(9)
    for k in range(40):
        h, w = (int(v) for v in rng.integers(4, 90, 2))
        grey = rng.integers(0, 256, (h, w)).astype(np.uint8)
        if k % 2:
            grey = (grey // 64 * 64).astype(np.uint8)
        segs = np.column_stack([rng.uniform(-4, w + 3, (30, 2)), rng.uniform(-4, h + 3, (30, 2))])
        segs = segs[:, [0, 2, 1, 3]]
        if k % 3 == 0:
            segs = np.round(segs * 64) / 64
        d, nrm = directions(segs)
        offs, t = np.arange(-4.0, 4.01, 0.5), np.linspace(0.05, 0.95, 8)
        base = segs[:, :2].T[:, :, None] + t * d.T[:, :, None]
        np.testing.assert_array_equal(profiles_along(grey, segs, d, nrm, offs, t),
                                      profiles_at(grey, base, nrm.T[:, :, None], offs))


def test_undistort_fixed_points_equal_opencv():
    """OpenCV's fixed ten iterations, bit for bit: plumb-bob and rational lenses, with
    and without skew; through unproject_many, the camera's own call."""
    rng = np.random.default_rng(10)
    for k in range(30):
        fx = rng.uniform(300, 900)
        skew = rng.uniform(-2, 2) if k % 2 else 0.0
        nd = 8 if k % 3 == 0 else 5
        dist = rng.normal(0, 0.1, nd) * np.array([1, 0.5, 0.05, 0.05, 0.2, 0.5, 0.3, 0.2][:nd])
        K = np.array([[fx, skew, rng.uniform(300, 340)],
                      [0.0, fx * rng.uniform(0.95, 1.05), rng.uniform(220, 260)],
                      [0.0, 0.0, 1.0]])
        lens = np.zeros(13)
        lens[:5] = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        lens[5:5 + nd] = dist
        px = rng.uniform(-5, 645, (500, 2))
        want = cv2.undistortPoints(_unskewed(K, px.reshape(-1, 1, 2)), K, dist,
                                   criteria=(cv2.TERM_CRITERIA_COUNT, 10, 0.0)).reshape(-1, 2)
        got = np.empty_like(px)
        undistort_fixed_points(arr(px, np.float64), arr(lens, np.float64), 10, got)
        np.testing.assert_array_equal(got, want)
    cam = CameraModel.pinhole(640, 480, 400.0, dist=[-0.08, 0.02, 0.0, 0.0, 0.0])
    px = rng.uniform(0, 480, (50, 2))
    np.testing.assert_array_equal(unproject_many(cam, px), cam.unproject_fast(px))


# ----------------------------------------------------------------------------- pose

def test_labeled_counts_equal_the_array_reading(seen):
    """The pose's counts, median fit rms and matched span, on the frames' labelings and
    with none matched, none finite."""
    out, _ = seen
    rng = np.random.default_rng(11)
    for fr, lab, *_ in out["fit"]:
        n = fr.len_n.size
        for assign, rms in ((lab.assign, rng.uniform(0, 1, n)),
                            (np.full(n, -1), np.full(n, np.nan)),
                            (lab.assign, np.where(rng.random(n) < 0.5, np.nan, rng.random(n)))):
            got = frame.labeled_counts(fr, lab.along, lab.across, assign, rms)
            want = ref.labeled_counts(fr, lab.along, lab.across, assign, rms)
            assert got[:4] == want[:4]
            assert (math.isnan(got[4]) and math.isnan(want[4])) or got[4] == want[4]
            assert abs(got[5] - want[5]) < TOL
