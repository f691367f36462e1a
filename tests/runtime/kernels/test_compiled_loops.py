"""The compiled loops (runtime/jit.py users) against plain numpy readings of the same
method, on random and edge-case inputs.

Each reference below is the array formulation the loop replaced (kept here, short, as
the oracle): the loops must give the same numbers (to float rounding) and the same
decisions (which points, which windows, which chords)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.block import pnp
from ceilkit.runtime.estimators.block.pnp import PlanarGeometry
from ceilkit.runtime.estimators.corridor import track
from ceilkit.runtime.estimators.lights.refine import refine_pose_ceiling
from ceilkit.runtime.features import edges, quads, spots, windows
from ceilkit.runtime.features.spots import FLAT_MIN_AREA_PX, flattened
from helpers import CONFIGS

# ----------------------------------------------------------------------------- windows


def window_stats_reference(grey, corner, side, rect=None):
    """One window at a time: border mean, half-peak object, flattened plateau, moments."""
    rows, ok, contrast = [], [], []
    mid = side // 2
    for n, (x0, y0) in enumerate(corner):
        g = grey[y0:y0 + side, x0:x0 + side].astype(np.float64)
        border = np.ones((side, side), bool)
        border[1:-1, 1:-1] = False
        i_b = g[border].mean()
        inside = np.zeros((side, side), bool)
        if rect is None:
            inside[:] = True
        else:
            x_a, y_a, x_b, y_b = rect[n]
            inside[max(y_a, 0):y_b + 1, max(x_a, 0):x_b + 1] = True
        peak = g[inside].max() if inside.any() else 0.0
        obj = (g > 0.5 * (i_b + peak)) & inside
        area = int(obj.sum())
        i_o = g[obj].sum() / max(area, 1)
        if area >= FLAT_MIN_AREA_PX:
            flat = flattened(grey[y0:y0 + side, x0:x0 + side], obj.astype(np.float32),
                             float(i_o - i_b))
            if flat is not None:
                g = flat.astype(np.float64)
        w = np.maximum(g - (i_b + windows.CORE * (i_o - i_b)), 0.0) * inside
        y, x = np.mgrid[0:side, 0:side] - mid
        m00 = w.sum()
        good = not (obj & border).any() and area > 0 and m00 > 0
        d = m00 if good else 1.0
        cx, cy = (w * x).sum() / d, (w * y).sum() / d
        rows.append([x0 + mid + cx, y0 + mid + cy, i_o, i_b, (w * x * x).sum() / d - cx * cx,
                     (w * x * y).sum() / d - cx * cy, (w * y * y).sum() / d - cy * cy, area])
        ok.append(good)
        contrast.append(peak - i_b)
    return np.array(rows), np.array(ok), np.array(contrast)


def spots_image(rng, shape=(160, 200), n=6, tilt=0.0):
    """Gaussian and flat-topped (vignetted) lights on a noisy background."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = np.full(shape, 35.0)
    centres = rng.uniform([20, 20], [w - 20, h - 20], (n, 2))
    for k, (u, v) in enumerate(centres):
        r2 = (xx - u) ** 2 + (yy - v) ** 2
        if k % 2:
            img += 150.0 * np.exp(-r2 / (2 * rng.uniform(1.5, 3.0) ** 2))
        else:      # a large plateau with a linear gain across it (vignetting)
            gain = 1.0 + tilt * (xx - u) / 20.0
            img += 170.0 * gain / (1.0 + np.exp(np.sqrt(r2) - rng.uniform(11, 14)))
    img += rng.normal(0.0, 1.5, shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), centres


@pytest.mark.parametrize("seed", range(4))
def test_window_stats_equals_the_per_window_reading(seed):
    rng = np.random.default_rng(seed)
    img, centres = spots_image(rng, tilt=0.15 * seed)
    for side in (21, 41):
        corner = np.clip(np.rint(centres).astype(np.int64) - side // 2, 0,
                         (img.shape[1] - side, img.shape[0] - side))
        corner = np.vstack([corner, [[0, 0]]])          # a flat window too
        for rect in (None, np.column_stack([rng.integers(-2, 6, (len(corner), 2)),
                                            rng.integers(side - 6, side + 2,
                                                         (len(corner), 2))])):
            want = window_stats_reference(img, corner, side, rect)
            got = windows.window_stats(img, corner, side, rect)
            np.testing.assert_array_equal(got[1], want[1])
            np.testing.assert_allclose(got[2], want[2], atol=1e-9)
            np.testing.assert_allclose(got[0][got[1]], want[0][want[1]], rtol=1e-7,
                                       atol=1e-6)
    # the large lights were flattened (the plateau's slope moved their centroids)
    assert seed == 0 or any(window_stats_reference(img, corner, 41)[0][:, 7]
                            >= FLAT_MIN_AREA_PX)


# ----------------------------------------------------------------------------- edges

def classify_reference(prof, offs, min_step, min_depth):
    sl, sr, inner, inv_l, inv_r = edges.profile_parts(offs)
    left, right = prof[:, sl].sum(1) * inv_l, prof[:, sr].sum(1) * inv_r
    step = right - left
    pin = prof[:, inner]
    dip = np.minimum(left, right) - pin.min(1)
    bump = pin.max(1) - np.maximum(left, right)
    valley = dip >= bump
    depth = np.where(valley, dip, bump)
    k = np.where(valley, pin.argmin(1), pin.argmax(1))
    thin = (depth >= min_depth) & (depth > abs(step)) & (k > 0) & (k < pin.shape[1] - 1)
    is_step = (abs(step) >= min_step) & (abs(step) > np.maximum(depth, 0))
    pol = np.where(thin, 0.0, np.where(is_step, np.sign(step), np.nan))
    shift = np.full(len(pol), np.nan)
    for r in np.flatnonzero(thin):
        kk = k[r]
        shift[r] = offs[inner][kk] + edges.PROFILE_STEP_PX * edges.vertex(
            pin[r, kk - 1:kk], pin[r, kk:kk + 1], pin[r, kk + 1:kk + 2])[0]
    return pol, shift


def locate_reference(prof, pol, offs, inner):
    i0, i1 = inner.start + 1, inner.stop + 1
    out = np.full(prof.shape[:2], np.nan)
    for s in range(prof.shape[0]):
        for a in range(prof.shape[1]):
            g = prof[s, a]
            if abs(pol[s]) == 1:
                gs = g * pol[s]
                mid = 0.25 * (gs[0] + gs[1] + gs[-2] + gs[-1])
                k = i0 + int(np.argmax(gs[i0 + 1:i1 + 1] - gs[i0 - 1:i1 - 1]))
                lo = gs[k] - mid > 0
                h0, h1 = (gs[k - 1] - mid, gs[k] - mid) if lo else (gs[k] - mid,
                                                                     gs[k + 1] - mid)
                o = offs[k - lo] + edges.PROFILE_STEP_PX * -h0 / (h1 - h0 if h1 > h0 else 1)
                if h0 <= 0 < h1 and abs(o) <= offs[i1 - 1]:
                    out[s, a] = o
            elif pol[s] == 0:
                side = 0.5 * (prof[s, :, 0] + prof[s, :, -1]).mean()
                inn = prof[s, :, i0:i1]
                sgn = -1.0 if side - inn.min(1).mean() >= inn.max(1).mean() - side else 1.0
                gt = g[i0:i1] * sgn
                w = np.maximum(gt - 0.5 * (sgn * side + gt.max()), 0)
                k = int(np.argmax(gt))
                if w.sum() > 0 and 0 < k < gt.size - 1:
                    out[s, a] = (w * offs[i0:i1]).sum() / w.sum()
    return out


def random_profiles(rng, n, n_along, offs):
    """Steps, dark and bright thin lines, and flat noise, at random places."""
    kind = rng.integers(0, 4, n)
    centre = rng.uniform(-2.5, 2.5, (n, 1, 1))
    o = offs[None, None, :] - centre - rng.normal(0, 0.3, (n, n_along, 1))
    step = 60.0 / (1.0 + np.exp(-o / 0.7)) * rng.choice([-1.0, 1.0], (n, 1, 1))
    line = 50.0 * np.exp(-o ** 2 / 0.8)
    base = np.select([kind[:, None, None] == 0, kind[:, None, None] == 1,
                      kind[:, None, None] == 2], [step, -line, line], 0.0)
    return 100.0 + base * rng.uniform(0.2, 1.5, (n, 1, 1)) + rng.normal(0, 2.0,
                                                                        (n, n_along, offs.size))


@pytest.mark.parametrize("half_width", [4.0, 6.0])
def test_classify_and_locate_equal_the_array_reading(half_width):
    rng = np.random.default_rng(7)
    offs, t, inner = edges.edge_grid(8, half_width)
    prof = random_profiles(rng, 400, t.size, offs)
    mean = prof.mean(axis=1)
    pol, shift = edges.classify(mean, offs, 20.0, 8.0)
    want_pol, want_shift = classify_reference(mean, offs, 20.0, 8.0)
    np.testing.assert_array_equal(pol, want_pol)
    np.testing.assert_allclose(shift, want_shift, atol=1e-12)
    assert {0.0, 1.0, -1.0} <= set(pol[np.isfinite(pol)].tolist()) and np.isnan(pol).any()
    loc = edges.locate(prof, pol, offs, inner)
    np.testing.assert_allclose(loc, locate_reference(prof, pol, offs, inner), atol=1e-12)
    assert np.isfinite(loc).mean() > 0.3


def fit_reference(x, y, good, f_px):
    lines, kept = [], good.copy()
    for r in range(x.shape[0]):
        for _ in range(2):
            w = kept[r]
            cx, cy = x[r, w].mean() if w.any() else 0.0, y[r, w].mean() if w.any() else 0.0
            dx, dy = x[r, w] - cx, y[r, w] - cy
            th = 0.5 * math.atan2(2 * (dx * dy).sum(), (dx * dx).sum() - (dy * dy).sum())
            a, b = -math.sin(th), math.cos(th)
            res = x[r] * a + y[r] * b - (a * cx + b * cy)
            sig = math.sqrt((res[w] ** 2).sum() / max(w.sum(), 1))
            drop = w & ~(np.abs(res) <= max(edges.OUTLIER_SIGMAS * sig,
                                            edges.OUTLIER_FLOOR_PX / f_px))
            if _ == 0 and drop.any():
                kept[r] &= ~drop
                continue
            lines.append([a, b, -(a * cx + b * cy)])
            break
    return np.array(lines), kept


def test_robust_line_fit_equals_the_array_reading():
    rng = np.random.default_rng(3)
    n, m = 200, 20
    th = rng.uniform(0, np.pi, (n, 1))
    s = rng.uniform(-1, 1, (n, m))
    off = np.where(rng.random((n, m)) < 0.03, 0.05, 0.0) + rng.normal(0, 1e-3, (n, m))
    x = 0.3 + s * np.cos(th) - off * np.sin(th)              # outliers across the line
    y = -0.2 + s * np.sin(th) + off * np.cos(th)
    good = rng.random((n, m)) < 0.9
    line, res, cnt, ssr, kept = edges.fit_lines_robust(x, y, good, 500.0)
    want_line, want_kept = fit_reference(x, y, good, 500.0)
    np.testing.assert_array_equal(kept, want_kept)
    sign = np.sign((line[:, :2] * want_line[:, :2]).sum(axis=1))[:, None]
    np.testing.assert_allclose(line, want_line * sign, atol=1e-9)
    np.testing.assert_array_equal(cnt, kept.sum(axis=1))
    np.testing.assert_allclose(ssr, ((res * kept) ** 2).sum(axis=1), rtol=1e-9, atol=1e-18)
    assert not np.array_equal(kept, good)                   # the outliers were dropped


# ----------------------------------------------------------------------------- quads

def edge_points_reference(grey, corners, per_side, search_px):
    offs, t = quads.edge_stations(per_side, search_px)
    h, w = grey.shape
    g = grey.astype(np.float32)
    pts, sides = [], []
    for s in range(4):
        p0, p1 = corners[s], corners[(s + 1) % 4]
        d = p1 - p0
        nrm = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9)
        found = []
        for tj in t:
            base = p0 + tj * d
            smp = (base + offs[:, None] * nrm).astype(np.float32)
            prof = cv2.remap(g, smp[None, :, :], None, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)[0].astype(float)
            grad = np.abs(np.diff(prof))
            k = int(np.argmax(grad))
            mid = 0.25 * (prof[0] + prof[1] + prof[-1] + prof[-2])
            d0, d1 = prof[k] - mid, prof[k + 1] - mid
            frac = d0 / (d0 - d1) if abs(d0 - d1) > 1e-6 else 0.5
            p = base + (offs[0] + (k + np.clip(frac, -1, 2)) * quads.EDGE_STEP_PX) * nrm
            ok = 0 < k < grad.size - 1 and -1 < frac < 2 and 0 < p[0] < w - 1 \
                and 0 < p[1] < h - 1
            found.append((p, grad[k], ok))
        med = np.median([f[1] for f in found])
        for p, st, ok in found:
            if ok and st > 0.25 * med:
                pts.append(p)
                sides.append(s)
    return np.array(pts).reshape(-1, 2), np.array(sides, int)


@pytest.mark.parametrize("seed", range(3))
def test_edge_points_equal_the_array_reading(seed):
    rng = np.random.default_rng(seed)
    img = np.full((240, 320), 200.0)
    quad = np.array([[100, 60], [230, 75], [220, 190], [90, 170]], float) \
        + rng.normal(0, 3, (4, 2))
    mask = np.zeros_like(img, np.uint8)
    cv2.fillConvexPoly(mask, np.rint(quad * 16).astype(np.int32), 1, cv2.LINE_AA, 4)
    img[mask > 0] = 60.0
    img = cv2.GaussianBlur(img, (0, 0), 1.0) + rng.normal(0, 2.0, img.shape)
    grey = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    coarse = quad + rng.normal(0, 1.0, (4, 2))
    pts, side = quads.edge_points(grey, coarse, 12, 3.0)
    want, want_side = edge_points_reference(grey, coarse, 12, 3.0)
    np.testing.assert_array_equal(side, want_side)
    # the reference samples on OpenCV's 1/32 px grid, the loop exactly
    np.testing.assert_allclose(pts, want, atol=0.03)
    assert len(pts) >= 44
    # a quad reaching past the frame: points outside are dropped, none is NaN
    off = coarse + np.array([-120.0, 0.0])
    p2, _ = quads.edge_points(grey, off, 12, 3.0)
    assert np.all((p2[:, 0] > 0) & (p2[:, 0] < 319))
    empty, s_empty = quads.edge_points(grey, np.full((4, 2), np.nan), 12, 3.0)
    assert empty.shape == (0, 2) and s_empty.shape == (0,)


# ----------------------------------------------------------------------------- corridor

def cut_chords_reference(px, vis):
    chords, lines = [], []
    for j in range(vis.shape[0]):
        runs, a = [], None
        for i, on in enumerate(list(vis[j]) + [False]):
            if on and a is None:
                a = i
            elif not on and a is not None:
                runs.append((a, i))
                a = None
        if not runs:
            continue
        a, b = max(runs, key=lambda r: (r[1] - r[0], -r[0]))
        if b - a < 2:
            continue
        seg = np.diff(px[j, a:b], axis=0)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        if arc[-1] < track.MIN_CHORD_PX:
            continue
        n = max(1, int(round(arc[-1] / track.CHORD_PX)))
        cut = arc[-1] * np.arange(n + 1) / n
        ends = np.stack([np.interp(cut, arc, px[j, a:b, 0]),
                         np.interp(cut, arc, px[j, a:b, 1])], axis=1)
        chords.append(np.concatenate([ends[:-1], ends[1:]], axis=1))
        lines += [j] * n
    if not chords:
        return np.zeros((0, 4)), np.zeros(0, int)
    return np.concatenate(chords), np.array(lines)


def test_cut_chords_equal_the_array_reading():
    rng = np.random.default_rng(11)
    for _ in range(300):
        n_lines, n_s = rng.integers(1, 7), rng.integers(2, 90)
        px = np.cumsum(rng.uniform(0, rng.choice([3.0, 12.0, 70.0]), (n_lines, n_s, 2)),
                       axis=1)
        vis = rng.random((n_lines, n_s)) < rng.choice([0.6, 0.95, 1.0])
        got, line = track._cut_chords(px, vis)
        want, want_line = cut_chords_reference(px, vis)
        np.testing.assert_array_equal(line, want_line)
        np.testing.assert_allclose(got, want, atol=1e-9)


# ----------------------------------------------------------------------------- block pnp

@pytest.mark.parametrize("noise_px", [0.0, 0.2])
def test_block_gauss_newton_equals_its_numpy_reading(monkeypatch, noise_px):
    """The compiled Gauss-Newton and the numpy one (the fallback on a singular step)
    reach the same pose, covariance and residuals; a singular step takes the fallback."""
    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    geo = PlanarGeometry.of(rig, Site(3.0))
    square = np.array([[2.0, -0.2], [2.4, -0.2], [2.4, 0.2], [2.0, 0.2]])
    truth = np.array([2.1, 0.05, math.radians(12.0)])
    t = np.linspace(0.15, 0.85, 12)
    pts = np.concatenate([square[k] + t[:, None] * (square[(k + 1) % 4] - square[k])
                          for k in range(4)])
    side = np.repeat(np.arange(4), t.size)
    norm = pnp.project_norm(geo, truth, pts)
    norm = norm + np.random.default_rng(5).normal(0, noise_px / 450.0, norm.shape)
    scale = pnp.magnification(rig.camera, norm)
    start = (2.12, 0.04, math.radians(12.5))
    got = pnp.refine(geo, start, square, norm, side, scale)
    monkeypatch.setattr(pnp, "_gauss_newton", lambda *a: False)
    want = pnp.refine(geo, start, square, norm, side, scale)
    np.testing.assert_allclose(got.pose, want.pose, atol=1e-10)
    np.testing.assert_allclose(got.cov, want.cov, rtol=1e-6, atol=1e-18)
    assert abs(got.rms_px - want.rms_px) < 1e-9 and got.n == want.n
    if noise_px == 0:
        np.testing.assert_allclose(got.pose, truth, atol=1e-9)


def test_solve3_is_gesv_and_reports_a_singular_matrix():
    rng = np.random.default_rng(0)
    x = np.empty(3)
    for _ in range(50):
        A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
        assert pnp._solve3(A, b, x)
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-9, atol=1e-12)
    assert not pnp._solve3(np.zeros((3, 3)), np.ones(3), x)


# ----------------------------------------------------------------------------- warm-up

def _loop_modules():
    from ceilkit.runtime.estimators.block import detect, parallels
    from ceilkit.runtime.estimators.block import window as bwindow
    from ceilkit.runtime.estimators.corridor import refine as cref
    from ceilkit.runtime.estimators.lights import refine
    from ceilkit.runtime.features import lines
    from ceilkit.runtime.geometry import camera, fits

    return (windows, spots, quads, edges, lines, track, pnp, refine, parallels, cref,
            detect, bwindow, camera, fits)


def _loops():
    """``{module.name: dispatcher}`` of every compiled loop of the per-frame path."""
    import numba

    return {f"{m.__name__}.{name}": obj for m in _loop_modules()
            for name, obj in vars(m).items()
            if isinstance(obj, numba.core.registry.CPUDispatcher)
            and obj.py_func.__module__ == m.__name__}


def test_warm_up_makes_every_loop_before_the_first_frame():
    """Every compiled loop is made by :func:`jit.warm_up` (each module's warmer covers its
    loops): frames of the three methods, tracked and not, one of them a read-only
    buffer, compile nothing more, so no frame pays numba's start or a compile."""
    from ceilkit.runtime import jit
    from ceilkit.runtime.multi import make_localizer
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    loops = _loops()
    assert len(loops) >= 30
    jit.warm_up()
    # a loop called only from other loops is compiled into them, not on its own
    inner = {c for d in loops.values() for c in d.py_func.__code__.co_names}
    cold = [k for k, d in loops.items() if k.rsplit(".", 1)[1] not in inner
            and not d.signatures]
    assert not cold, cold
    before = {k: set(d.signatures) for k, d in loops.items()}
    for method in ("block", "lights", "corridor"):
        rig = Rig.load(CONFIGS / method / "rig.yaml")
        site = Site.load(CONFIGS / method / "site.yaml")
        start = ((site.markers.poses[0].x_m, site.markers.poses[0].y_m)
                 if method == "block" else (3.0, 0.0))
        # (the packaged corridor is symmetric: its heading is stated)
        stated = {"assume_heading_deg": 0.0} if method == "corridor" else {}
        for opts in ({"window_search": True, **stated}, {"window_search": False, **stated}):
            est, tracker = make_localizer(method, rig, site, opts)
            for k in range(4):
                img = render_frame(rig, site, start[0] + 0.02 * k, start[1], 0.01 * k,
                                   options=SimOptions(noise_sigma=2.0, blur_px=0.8),
                                   rng=np.random.default_rng(k))
                img.setflags(write=k != 1)        # a frame from a read-only buffer
                out = est.estimate(img, k * 33_000_000, tracker.predict(k * 33_000_000))
                tracker.update(out)
                assert out
    grown = {k: set(d.signatures) - before[k] for k, d in loops.items()}
    assert not any(grown.values()), {k: v for k, v in grown.items() if v}


def side_fit_reference(contour, poly, outwards_px=0.5):
    """Each side's middle fitted by cv2.fitLine (L2), moved outwards, met."""
    m = len(contour)
    i0 = [int(np.flatnonzero((contour == v).all(axis=1))[0]) for v in poly]
    cx, cy = poly.mean(axis=0)
    ring = np.concatenate([contour, contour]).astype(np.float32)
    lines = []
    for k in range(4):
        run = (i0[(k + 1) % 4] - i0[k]) % m
        first = round(run * (0.5 - quads.SIDE_FIT_KEEP / 2))
        n = round(run * (0.5 + quads.SIDE_FIT_KEEP / 2)) - first
        start = (i0[k] + first) % m
        vx, vy, mx, my = cv2.fitLine(ring[start:start + n], cv2.DIST_L2, 0, 0.01, 0.01).ravel()
        a, b = -vy, vx
        if a * (mx - cx) + b * (my - cy) < 0:
            a, b = -a, -b
        lines.append([a, b, -(a * mx + b * my) - outwards_px])
    return quads.line_corners(np.array(lines, float))


@pytest.mark.parametrize("seed", range(3))
def test_side_fit_corners_equal_opencvs_line_fit(seed):
    rng = np.random.default_rng(seed)
    img = np.zeros((200, 260), np.uint8)
    quad = np.array([[60, 40], [200, 55], [190, 160], [50, 150]], float) + rng.normal(0, 4, (4, 2))
    cv2.fillConvexPoly(img, np.rint(quad * 16).astype(np.int32), 255, cv2.LINE_8, 4)
    (found,) = quads.detect_quads(img, False, 500.0, sharpen=False)
    got = quads._side_fit_corners(found.contour_px, found.corners_px)
    want = side_fit_reference(found.contour_px, found.corners_px)
    np.testing.assert_allclose(got, want, atol=1e-3)      # OpenCV's fit is float32
    assert not np.array_equal(got, found.corners_px)
    # a vertex not on the contour: the vertices as they are
    off = found.corners_px + [[0.5, 0.0], [0, 0], [0, 0], [0, 0]]
    np.testing.assert_array_equal(quads._side_fit_corners(found.contour_px, off), off)


# ----------------------------------------------------------------------------- corridor GN

def test_corridor_gauss_newton_equals_the_residuals_reading(monkeypatch):
    """The compiled Huber steps against the loop over :func:`refine.residuals` on the
    packaged corridor rig (its frame's lines from a rendered frame)."""
    from ceilkit.runtime.estimators.corridor import refine as cref
    from ceilkit.runtime.estimators.registry import make_estimator
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    est = make_estimator("corridor", rig, site, {"assume_heading_deg": 0.0})  # symmetric
    seen = []
    real = cref.gauss_newton

    def spy(psi, cy, gd, setup, iterations):
        seen.append((psi, cy, gd, setup, iterations))
        return real(psi, cy, gd, setup, iterations)

    monkeypatch.setattr(cref, "gauss_newton", spy)   # what refine.joint_fit calls
    for k, pose in enumerate([(3.0, 0.1, 0.02), (6.0, -0.2, -0.05)]):
        img = render_frame(rig, site, *pose, rng=np.random.default_rng(k),
                           options=SimOptions(noise_sigma=2.0, blur_px=0.8))
        assert est.estimate(img, k, None)
    monkeypatch.undo()
    assert seen
    for psi0, cy0, gd, setup, iterations in seen:
        got = cref.gauss_newton(psi0 + 0.01, cy0 - 0.02, gd, setup, iterations)
        psi, cy = psi0 + 0.01, cy0 - 0.02
        for _ in range(max(1, iterations)):
            A = cref.residuals(psi, cy, gd, setup)
            w = np.minimum(1.0, 1.0 / np.maximum(np.abs(A[:, 2]), 1e-9))
            H = (A[:, :2] * w[:, None]).T @ A[:, :2]
            d = -np.linalg.solve(H, (A[:, :2] * w[:, None]).T @ A[:, 2])
            psi, cy = psi + d[0], cy + d[1]
            if abs(d[0]) < cref.STEP_DONE[0] and abs(d[1]) < cref.STEP_DONE[1]:
                break
        assert abs(got.psi_rad - psi) < 1e-12 and abs(got.camera_y_m - cy) < 1e-12
        np.testing.assert_allclose(got.residuals_px, A[:, 2], atol=1e-9)


# ----------------------------------------------------------------------------- spots

@pytest.mark.parametrize("seed", range(3))
def test_lone_regions_equal_the_one_by_one_reading_with_flattened_plateaus(seed):
    """Large vignetted lights (their plateaus flattened) measured by the compiled loop
    are what :func:`_region_stats` (OpenCV, :func:`flattened`) measures."""
    from ceilkit.runtime.features.spots import (
        _alone,
        _lone_region_stats,
        _region_stats,
        niblack_mask,
    )

    rng = np.random.default_rng(seed)
    img, _ = spots_image(rng, shape=(220, 300), n=6, tilt=0.2)
    mask = niblack_mask(img, 41, 0.8, 10.0, 0.2)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = np.array([cv2.boundingRect(c) for c in contours])
    boxes = boxes[_alone(boxes)]
    stats, ok = _lone_region_stats(img, mask, boxes, True)
    assert (stats[ok, 7] >= FLAT_MIN_AREA_PX).any()
    for row, b, good in zip(stats, boxes, ok, strict=True):
        if not good:
            continue
        u, v, i_o, i_b, cov, area = _region_stats(img, mask, None, *b, True)
        assert (row[2], row[3], row[7]) == (i_o, i_b, area)
        np.testing.assert_allclose(row[:2], [u, v], atol=1e-6)
        np.testing.assert_allclose(row[4:7], [cov[0, 0], cov[0, 1], cov[1, 1]],
                                   rtol=1e-6, atol=1e-9)


# ----------------------------------------------------------------------------- block view

def test_ceiling_norm_equals_the_matrix_reading():
    """Ceiling points to normalized image points (the block's predictions): as
    ``(p - c) @ Rz(yaw) R`` with NaN behind the camera."""
    from ceilkit.runtime.geometry.rotations import rot_z

    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    geo = PlanarGeometry.of(rig, Site(3.0))
    rng = np.random.default_rng(4)
    for _ in range(20):
        x, y, yaw = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi)
        pts = np.column_stack([x, y]) + rng.uniform(-4, 4, (30, 2))
        rz = rot_z(yaw)
        c = rz @ geo.t_vehicle_cam + [x, y, 0.0]
        pc = (np.column_stack([pts, np.full(30, geo.ceiling_m)]) - c) @ (rz @ geo.R_vehicle_cam)
        want = np.where(pc[:, 2:] > 1e-9, pc[:, :2] / pc[:, 2:], np.nan)
        got = pnp.project_norm(geo, (x, y, yaw), pts)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        assert np.isnan(got).any() == np.isnan(want).any()


def robust_reference(p1, p2, R, hint, gate, w_extra, period=np.pi / 2):
    from ceilkit.runtime.estimators.block.parallels import MIN_LINES, SIGMA_FLOOR_RAD

    ln = np.column_stack([p1[:, 1] - p2[:, 1], p2[:, 0] - p1[:, 0],
                          p1[:, 0] * p2[:, 1] - p1[:, 1] * p2[:, 0]])
    m = ln @ R.T
    m /= np.linalg.norm(m, axis=1)[:, None]
    phi, w = np.arctan2(m[:, 0], m[:, 1]), (m[:, 0] ** 2 + m[:, 1] ** 2) * w_extra
    ok = np.isfinite(phi) & (w > 1e-12)
    if ok.sum() < MIN_LINES:
        return None, np.zeros(len(phi), bool)
    wrap = lambda a: np.remainder(a + period / 2, period) - period / 2      # noqa: E731
    k = 2 * np.pi / period

    def mean(sel):
        z = np.sum(w[sel] * np.exp(1j * k * phi[sel]))
        return math.atan2(z.imag, z.real) / k

    ref = hint if hint is not None else mean(ok)
    if hint is None:
        sel = ok & (np.abs(wrap(phi - ref)) < 3 * gate)
        if sel.sum() >= MIN_LINES:
            ref = mean(sel)
    kept = ok & (np.abs(wrap(phi - ref)) < gate)
    if kept.sum() < MIN_LINES:
        return None, kept
    yaw = mean(kept)
    res = wrap(phi[kept] - yaw)
    sigma = max(math.sqrt(np.sum(w[kept] * res ** 2) / w[kept].sum()
                          / max(kept.sum() - 1, 1)), SIGMA_FLOOR_RAD)
    return (yaw, sigma), kept


@pytest.mark.parametrize("hint", [None, 0.3])
def test_robust_heading_equals_the_array_reading(hint):
    from ceilkit.runtime.estimators.block.parallels import robust_heading
    from ceilkit.runtime.geometry.rotations import wrap_pi

    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    R = rig.mount.R_vehicle_cam
    rng = np.random.default_rng(8)
    for _ in range(30):
        n = rng.integers(1, 15)
        p1 = rng.uniform(-0.5, 0.5, (n, 2))
        ang = 0.3 + rng.choice([0.0, np.pi / 2], n) + rng.normal(0, 0.004, n)
        ang[rng.random(n) < 0.2] += rng.uniform(0.1, 1.0)             # off the axes
        p2 = p1 + 0.3 * np.column_stack([np.cos(ang), np.sin(ang)])
        w_extra = rng.uniform(0.5, 2.0, n)
        got, kept = robust_heading(p1, p2, R, hint, math.radians(1.0), w_extra)
        want, want_kept = robust_reference(p1, p2, R, hint, math.radians(1.0), w_extra)
        np.testing.assert_array_equal(kept, want_kept)
        assert (got is None) == (want is None)
        if got is not None:
            yaw = want[0] if hint is None else hint + math.remainder(want[0] - hint,
                                                                     np.pi / 2)
            assert abs(math.remainder(got.yaw_rad - wrap_pi(yaw), 2 * np.pi)) < 1e-12
            assert abs(got.sigma_rad - want[1]) < 1e-12 and got.n_lines == kept.sum()


def test_edge_stations_far_outside_the_frame_read_its_edge():
    """A quad corner far off the frame (a refine pass's corners from nearly parallel
    sides) samples the frame's edge, as OpenCV's remap does, not the opposite edge."""
    g = np.zeros((40, 60), np.uint8)
    g[:, 59] = 200                                  # the right edge bright, the left dark
    assert quads.bilinear(g, 1e20, 20.0, 60, 40) == 200.0
    assert quads.bilinear(g, -1e20, 20.0, 60, 40) == 0.0
    assert quads.bilinear(g, 59.0, 1e20, 60, 40) == 200.0


def test_lights_refine_with_a_nan_point_has_no_covariance():
    """A ceiling point that is NaN (a ray that does not rise) leaves the fit without a
    covariance (inf), as before the compiled loop, never NaN."""
    rng = np.random.default_rng(0)
    L = rng.normal(0, 3, (3, 2))
    q = L + rng.normal(0, 0.01, (3, 2))
    q[0, 0] = np.nan
    J = rng.normal(0, 300, (3, 2, 2))
    *_, cov, _ = refine_pose_ceiling(q, J, L, 0.1, -0.1, 0.05)
    assert np.all(np.isinf(cov))


# ------------------------------------------------------------------------------- lens


@pytest.mark.parametrize("model,dist,skew", [
    ("plumb_bob", [0.0] * 5, 1.5),
    ("plumb_bob", [-0.3, 0.1, 0.001, -0.002, 0.0], 0.0),
    ("plumb_bob", [-0.25, 0.06, 0.001, -0.002, -0.005], 2.0),
    ("rational_polynomial", [0.2, 0.05, 0.001, -0.002, 0.01, 0.3, 0.02, 0.01], 0.0),
    ("equidistant", [0.05, -0.01, 0.002, 0.0], 0.0),
    ("equidistant", [-0.3, 0.2, -0.1, 0.02], 1.5),
])
def test_undistort_points_is_opencvs_inverse(model, dist, skew):
    """The compiled lens inverse is OpenCV's (CameraModel.unproject) wherever that
    reprojects, over and beyond the image: within OpenCV's own convergence (far out on
    a strong polynomial lens its iterations stop up to 1e-6 px off), and itself exact
    to 1e-9 px there."""
    from ceilkit.runtime.geometry.camera import CameraModel, undistort_points

    K = np.array([[300.0, skew, 320.0], [0.0, 310.0, 240.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(640, 480, K, dist, model=model)
    rng = np.random.default_rng(3)
    px = np.stack([rng.uniform(-40, 680, 3000), rng.uniform(-40, 520, 3000)], 1)
    px[:4] = [[320.0, 240.0], [0.0, 0.0], [639.0, 479.0], [320.0, 0.0]]
    ref = cam.unproject(px)
    out = np.empty_like(px)
    undistort_points(px, *cam.lens, out)
    has_inverse = cam.reprojects(px, ref, 1e-6)
    assert has_inverse[0] and has_inverse.mean() > 0.8
    assert np.abs(out - ref)[has_inverse].max() * 300.0 < 1e-5           # px
    assert cam.reprojects(px, out, 1e-9)[has_inverse].all()


@pytest.mark.parametrize("dist", [[-0.08, 0.02, 0.0, 0.0, 0.0], [-0.3, 0.1, 0.0, 0.0, 0.05],
                                  [0.2, -0.05, 0.0, 0.0, 0.01], [-0.5, 0.3, 0.0, 0.0, -0.1]])
def test_radial_lens_inverse_is_the_general_one(dist):
    """A polynomial lens without tangential or rational terms is inverted with their
    terms left out (camera.radial_only: they add exact zeros and divide by an exact 1):
    the same numbers as the general step to the last bit, over and far beyond the image
    (where the steps fold and halve), on the principal point's row and column and on
    1/32 px positions (the located points' rounding), and NaN and infinite pixels."""
    from ceilkit.runtime.geometry.camera import (
        CameraModel,
        _undistort_polynomial,
        radial_only,
    )

    cam = CameraModel.pinhole(640, 480, 400.0, dist=dist)
    code, lens = cam.lens
    fx, fy, cx, cy, k = lens[0], lens[1], lens[2], lens[3], lens[5:]
    assert code == 1 and radial_only(k)
    assert not radial_only(CameraModel.pinhole(640, 480, 400.0,
                                               dist=[-0.3, 0.1, 0.001, 0.0, 0.0]).lens[1][5:])
    rng = np.random.default_rng(5)
    px = np.concatenate([rng.uniform([-320.0, -240.0], [960.0, 720.0], (20000, 2)),
                         np.round(rng.uniform([0.0, 0.0], [640.0, 480.0], (5000, 2)) * 32) / 32,
                         [[cx, cy], [cx, 10.0], [10.0, cy], [np.nan, 1.0], [np.inf, 2.0],
                          [1e300, -1e300]]])
    for u, v in px:
        a = _undistort_polynomial(u, v, fx, fy, cx, cy, k, True)
        b = _undistort_polynomial(u, v, fx, fy, cx, cy, k, False)
        assert np.array_equal(np.array(a).view(np.int64), np.array(b).view(np.int64)), (u, v)


def test_frame_check_statistics_equal_opencvs():
    """The frame check's mean and deviation of the 1-in-16 sample are
    cv2.meanStdDev's, for frame sizes that are and are not multiples of the step, read
    as words or pixel by pixel (a frame at an odd address), both ways equal."""
    from ceilkit.runtime.estimators.base import _sample_stats, sample_stats

    rng = np.random.default_rng(2)
    for shape in ((480, 640), (720, 1280), (481, 643), (482, 644), (5, 3), (1, 1), (3, 4)):
        g = rng.integers(0, 256, shape).astype(np.uint8)
        odd = np.empty(g.size + 1, np.uint8)[1:].reshape(shape)  # at an odd address
        odd[:] = g
        mean, std = (float(np.ravel(v)[0]) for v in cv2.meanStdDev(g[::4, ::4]))
        for got in (sample_stats(g), sample_stats(odd), _sample_stats(g, 4)):
            assert got[0] == pytest.approx(mean, abs=1e-9)
            assert got[1] == pytest.approx(std, abs=1e-9)
        assert sample_stats(g) == _sample_stats(g, 4)         # the same integer sums
    white = np.full((480, 640), 255, np.uint8)                # the sums' largest terms
    assert sample_stats(white) == (255.0, 0.0)


@pytest.mark.parametrize("model,dist,skew", [
    ("plumb_bob", [0.0] * 5, 1.5),
    ("plumb_bob", [-0.3, 0.1, 0.001, -0.002, -0.02], 2.0),
    ("plumb_bob", [0.1, 0.0, 0.0, 0.0, 0.0], 0.0),
    ("rational_polynomial", [0.2, 0.05, 0.001, -0.002, 0.01, 0.3, 0.02, 0.01], 0.0),
    ("equidistant", [-0.3, 0.2, -0.1, 0.02], 1.5),
])
def test_distort_points_is_the_camera_models(model, dist, skew):
    from ceilkit.runtime.geometry.camera import CameraModel, distort_points

    K = np.array([[300.0, skew, 320.0], [0.0, 310.0, 240.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(640, 480, K, dist, model=model)
    xy = np.random.default_rng(4).uniform(-1.2, 1.2, (500, 2))
    xy[0] = 0.0
    out = np.empty_like(xy)
    distort_points(xy, *cam.lens, out)
    np.testing.assert_allclose(out, cam.distort(xy), rtol=0, atol=1e-9)
    np.testing.assert_allclose(out[:8], cam.distort(xy[:8]), rtol=0, atol=1e-9)  # OpenCV's


# --------------------------------------------------------------------------- corridor


def frame_lines_reference(segs, R, h, lamp_w, angle_tol, inlier_px, f_px):
    """The array reading of frame_lines (before its loop)."""
    from ceilkit.runtime.estimators.corridor.frame import LAMP_END_TOL, MAX_CEILING_LENGTH_M

    dx, dy = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
    len_n = np.hypot(dx, dy)
    inv = 1.0 / np.maximum(len_n, 1e-300)
    lines_t = np.stack([-dy * inv, dx * inv, (segs[:, 0] * segs[:, 3]
                                             - segs[:, 2] * segs[:, 1]) * inv])
    p = segs.reshape(-1, 2) @ R.T[:2] + R.T[2]
    up = p[:, 2:3] > 1e-6
    X = np.where(up, p[:, :2] * (h / np.where(up, p[:, 2:3], 1.0)), np.nan).reshape(-1, 4)
    full = np.hypot(X[:, 2] - X[:, 0], X[:, 3] - X[:, 1])
    ceil_len = np.minimum(full, MAX_CEILING_LENGTH_M)
    ceil_len[~(ceil_len >= 0)] = 0.0
    lamp_end = np.isfinite(full)[None] & (np.abs(full[None] - lamp_w[:, None])
                                          < LAMP_END_TOL * lamp_w[:, None])
    tol = np.minimum(angle_tol, 2 * inlier_px / np.maximum(len_n * f_px, 1))
    return (lines_t, len_n, 0.5 * (segs[:, 0] + segs[:, 2]), 0.5 * (segs[:, 1] + segs[:, 3]),
            lines_t.T @ R.T, ceil_len, X[:, 0] + X[:, 2], X[:, 1] + X[:, 3], lamp_end, tol)


def test_frame_arrays_equal_the_array_reading():
    from ceilkit.runtime.estimators.corridor.frame import _frame_arrays
    from ceilkit.runtime.geometry.rotations import R_vehicle_cam

    rng = np.random.default_rng(8)
    R = R_vehicle_cam(0.0, 0.6, 0.05)
    lamp_w = np.array([0.3, 1.2])
    for n in (0, 1, 7, 40):
        segs = rng.uniform(-1.5, 1.5, (n, 4))
        if n:
            segs[0, 2:] = segs[0, :2]                       # a zero-length segment
        got = _frame_arrays(segs, R, 2.5, lamp_w, 0.05, 2.0, 500.0)
        want = frame_lines_reference(segs, R, 2.5, lamp_w, 0.05, 2.0, 500.0)
        for g, w in zip(got, want, strict=True):
            assert g.shape == w.shape and np.array_equal(np.isnan(g), np.isnan(w))
            if g.dtype == bool:
                assert np.array_equal(g, w)
            else:
                np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12)


def test_vanishing_line_equals_the_eigenvector_reading():
    """The compiled mount check gives the batched eigh's numbers (either sign of an
    eigenvector), with one family, two, and too few segments."""
    from ceilkit.runtime.estimators.corridor.geometry import mount_from_vanishing_line
    from ceilkit.runtime.estimators.corridor.geometry import vanishing_line_check as check
    from ceilkit.runtime.geometry.rotations import R_vehicle_cam

    R = R_vehicle_cam(0.0, 0.5, 0.05)
    rng = np.random.default_rng(9)
    for n, share in ((12, 0.5), (12, 1.0), (3, 0.5), (1, 1.0)):
        lines = rng.normal(size=(n, 3))
        lines /= np.hypot(lines[:, 0], lines[:, 1])[:, None]
        len_n = rng.uniform(0.05, 0.5, n)
        along = rng.random(n) < share
        across = ~along
        got = check(lines, len_n, along, across, R)
        w = len_n ** 2
        fams = [f for f in (along, across) if f.sum() >= 2]
        if along.sum() < 2:
            assert all(math.isnan(v) for v in got.values())
            continue
        v = [np.linalg.eigh((lines * (w * f)[:, None]).T @ lines)[1][:, 0] for f in fams]
        assert got["vp_along_elevation_deg"] == pytest.approx(
            math.degrees(math.asin(min(1.0, abs(R[2] @ v[0])))), abs=1e-9)
        if len(fams) == 2:
            nv = np.cross(v[0], v[1])
            nv /= np.linalg.norm(nv)
            tilt, swing = mount_from_vanishing_line(nv)
            assert got["implied_tilt_deg"] == pytest.approx(math.degrees(tilt), abs=1e-9)
            assert got["implied_swing_deg"] == pytest.approx(math.degrees(swing), abs=1e-9)
            assert got["vanishing_line_residual_deg"] == pytest.approx(
                math.degrees(math.acos(min(1.0, abs(nv @ R[2])))), abs=1e-9)
        else:
            assert math.isnan(got["vanishing_line_residual_deg"])


def test_gn_inputs_equal_the_array_reading(corridor_rig, corridor_site):
    """gn_inputs' compiled arrays are the array reading's: matched forward endpoints
    through R with their site line's y, across lines through R, row times kept."""
    from ceilkit.runtime.estimators.corridor.frame import frame_lines
    from ceilkit.runtime.estimators.corridor.refine import gn_inputs
    from ceilkit.runtime.estimators.corridor.setup import CorridorSetup

    st = CorridorSetup.build(corridor_rig, corridor_site, math.radians(5.0))
    R = st.R_level_cam
    rng = np.random.default_rng(12)
    for n in (0, 1, 9, 30):
        segs = rng.uniform(-1, 1, (n, 4))
        fr = frame_lines(segs, np.zeros(n), st, 0.05, 2.0)
        along = rng.random(n) < 0.6
        across = ~along & (rng.random(n) < 0.7)
        assign = np.where(rng.random(n) < 0.8, rng.integers(0, st.site_y.size, n), -1)
        tau = rng.random((n, 2))
        got = gn_inputs(fr, along, across, assign, st, tau)
        ia, ib = np.flatnonzero(along & (assign >= 0)), np.flatnonzero(across)
        ep = segs[ia].reshape(-1, 2) @ R[:, :2].T + R[:, 2]
        lb = fr.lines[ib] @ R[:2].T
        want = {"y": np.repeat(st.site_y[assign[ia]], 2), "e0": ep[:, 0], "e1": ep[:, 1],
                "ez": ep[:, 2], "p0": lb[:, 0], "p1": lb[:, 1], "mx_b": fr.mx[ib],
                "my_b": fr.my[ib], "scale_b": fr.len_n[ib] * st.f_px / math.sqrt(2.0),
                "tau": tau[ia].ravel(), "tau_b": tau[ib].mean(axis=1)}
        assert got.n_a == ia.size
        for k, w in want.items():
            np.testing.assert_allclose(getattr(got, k), w, rtol=1e-12, atol=1e-14, err_msg=k)


def test_refine_chords_reads_as_refine_undistorted():
    """The compiled chord refinement (profiles bilinear in float, the exact lens
    inverse) gives refine_undistorted's kinds and, on blurred steps and seams through a
    distorted lens, its lines to a few hundredths of a pixel (the remap's samples are
    rounded to 1/32 px and to grey levels)."""
    from ceilkit.runtime.features.lines import refine_chords, refine_undistorted
    from ceilkit.runtime.geometry.camera import CameraModel

    cam = CameraModel.pinhole(320, 240, 260.0, dist=[-0.1, 0.02, 0.0, 0.0, 0.0])
    yy, xx = np.mgrid[0:240, 0:320].astype(float)
    img = 60.0 + 120.0 / (1.0 + np.exp(-(xx - 0.12 * yy - 140.0) / 0.8))      # a step
    img -= 70.0 * np.exp(-((yy - 0.05 * xx - 60.0) ** 2) / (2 * 1.2 ** 2))      # a seam
    img += np.random.default_rng(5).normal(0.0, 1.0, img.shape)
    grey = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    chords = np.array([[140.0 + 0.12 * 100, 100.0, 140.0 + 0.12 * 150, 150.0],
                       [140.0 + 0.12 * 180, 180.0, 140.0 + 0.12 * 230, 230.0],
                       [100.0, 65.0, 150.0, 67.5], [200.0, 70.0, 250.0, 72.5],
                       [300.0, 10.0, 330.0, 12.0]])                 # past the frame's edge
    want = refine_undistorted(cam, grey, chords, retry_half_width_px=None)
    got = refine_chords(cam, grey, chords)
    np.testing.assert_array_equal(np.isnan(got[1]), np.isnan(want[1]))
    fin = np.isfinite(want[1]) & np.isfinite(want[2])
    assert fin[:4].all()
    np.testing.assert_array_equal(got[1][fin], want[1][fin])
    np.testing.assert_allclose(got[0][fin] * cam.fx, want[0][fin] * cam.fx, atol=0.05)
    np.testing.assert_allclose(got[2][fin], want[2][fin], atol=0.05)
