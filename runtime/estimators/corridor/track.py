"""The tracked fast path of ``corridor``: 1-D edge searches across the predicted lines.

With a prior (the tracker's or the fusion's predicted yaw and y), every site line
``y = y_j`` of ``lines_along`` is projected through the rig (camera pan
``psi = yaw + pan``, camera y ``c_y``; SPEC §1) and its visible stretch (in the image,
in the lens's field, within :data:`REACH_M` of the camera on the ceiling) is cut into
short pixel chords. On each chord the edge is located on cross profiles by the one
edge-profile measurement (:func:`~ceilkit.runtime.features.lines.refine_undistorted`:
kind, sub-pixel location, a line fitted in undistorted coordinates), within
``search_px`` of the prediction. No full-frame line detector runs.

Only the places whose own profile shows the edge, away from a lamp's end, are used
(:data:`LOCAL_SHARE`: a lamp row's edge is broken by its gaps). A chord counts when its
edge is of the kind the site says (a lamp's long edge is a step, a seam a thin line)
and fits well (its points' scatter within
:data:`MAX_CHORD_RMS_PX` and :data:`CHORD_RMS_MEDIANS` times the frame's median);
the association is known (a chord is its line's), so the located chords go straight
to the joint Gauss-Newton on ``(psi, c_y)`` (:func:`~.refine.gauss_newton`, started
at the prior) as forward segments.
The window check: at least two site lines found, the fit's rms within ``inlier_px``,
the refined pose within the search's reach of the prior. Anything else returns
``None`` and the estimator runs its global path (the fallback and the check).

Example::

    lt = LineTracker(setup, camera, search_px=5.0, inlier_px=2.5)
    m = lt.measure(grey, psi_rad, camera_y_m)     # LineMeasurement | None
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.corridor.association import ABSENCE_PENALTY
from ceilkit.runtime.estimators.corridor.frame import (
    FrameLines,
    _frame_arrays,
    counts_core,
    frame_lines,
)
from ceilkit.runtime.estimators.corridor.geometry import _vanishing_line
from ceilkit.runtime.estimators.corridor.hypotheses import TWIN_RATIO, Labeling, LabelingTwin
from ceilkit.runtime.estimators.corridor.refine import (
    FrameArrays,
    FrameFit,
    GNArrays,
    LevelCamera,
    PanOffsetFit,
    RowRates,
    along_fit,
    along_steps,
    fix_cov,
    gn_arrays,
    gn_inputs,
    huber_steps,
    joint_fit,
    level_camera,
    pan_offset_fit,
)
from ceilkit.runtime.estimators.corridor.setup import CorridorSetup
from ceilkit.runtime.features.edges import PROFILE_STEP_PX, edge_grid, part_indices
from ceilkit.runtime.features.lines import ProfileGrid, ProfileKind, refine_chords_core
from ceilkit.runtime.geometry.camera import CameraModel, distort_points
from ceilkit.runtime.jit import arr, njit, warmer

REACH_M = 8.0
"""Ceiling points further than this from the camera are not searched (tiny, blurred)."""

CHORD_PX = 48.0
"""Pixel length of a chord of a predicted line (short: a curved image line is straight
on it to a fraction of a pixel)."""

MIN_CHORD_PX = 20.0
"""A visible stretch shorter than this is not searched."""

SAMPLES = 121
"""Samples along each site line (W's x, over ``±REACH_M`` of the camera)."""

N_ALONG = 16
"""Cross profiles per chord (every 3 px of a 48 px chord; twice
:func:`~ceilkit.runtime.features.lines.refine_undistorted`'s 8): the places beside a
lamp's end are left out (:data:`LOCAL_SHARE`), and a chord over lamp ends keeps enough
on the lamps (corridor0 of bench_heldout_lines: 692 chords kept over 60 frames, 280
with 8 places)."""

FIRST_ALONG = 8
"""Cross profiles per chord of the first search of a frame (every 6 px of a 48 px
chord), whose fit only says where the second, with :data:`N_ALONG`, searches again
(:meth:`LineTracker.measure`, ``first``): with :data:`FIRST_STRIDE` a quarter of the
profiles and points of a full search, about 0.45x its time (issue 38)."""

FIRST_STRIDE = 2
"""... and of every this many chords of a line (its first always)."""

MIN_STEP, MIN_DEPTH = 20.0, 8.0
"""A chord's edge kind: the least step and thin-line depth (grey levels; as
:func:`~ceilkit.runtime.features.lines.refine_undistorted`'s defaults)."""

LOCAL_SHARE = 0.5
"""A place along a chord is located only where its own profile, and its neighbours',
are of the chord's kind at this share of :data:`MIN_STEP` / :data:`MIN_DEPTH`
(:func:`~ceilkit.runtime.features.lines.refine_chords`' ``local_share``), and the chord
ends at its first and last such place. A chord over a lamp row's long edge covers lamp
ends and gaps: its places in a gap located the noise, those beside a lamp's end its
blur (bench_heldout_lines' corridor0, chords about the true pose: their middles 0.49 px
rms off their line before, 0.028 px now, the global path's segments 0.021; issue 38,
docs/methods/corridor.md)."""

PROBE_CHORDS = 2
"""Chords of a line a twin puts where the window fix searched none that are looked at
(:meth:`LineTracker.probe`)."""

MAX_CHORD_RMS_PX = 1.0
"""A chord whose located points scatter more than this about their line is dropped."""

CHORD_RMS_MEDIANS = 3.0
"""... and so is one scattering more than this many times the frame's median chord
scatter: a chord over a lamp's end or a neighbouring edge fits worse than the clean
chords by far (on renders, clean chords 0.02-0.14 px, the others 0.4-0.95), and the
few such chords biased the fit (corridor_60 of bench_all: yaw error median/p95 0.0054/0.021 deg with
them, 0.0017/0.0058 without, the global path's 0.0023/0.0061)."""


@dataclass(frozen=True, eq=False)
class LineMeasurement:
    """The located chords of one frame.

    Attributes:
        segs_n: ``(K, 4)`` undistorted normalized chords (the fitted edge).
        segs_px: ``(K, 4)`` the predicted pixel chords searched.
        line: ``(K,)`` the site line (index into ``setup.site_y``) of each chord.
        polarity: ``(K,)`` the located kind (``+-1`` step, ``0`` thin line).
        rms_px: ``(K,)`` the located points' scatter about each chord's fit (px).
        searched: chords searched (before the checks).
    """

    segs_n: np.ndarray
    segs_px: np.ndarray
    line: np.ndarray
    polarity: np.ndarray
    rms_px: np.ndarray
    searched: int

    @property
    def n_lines(self) -> int:
        """How many site lines hold a chord."""
        return int(_count_distinct(arr(self.line, np.int64)))


class ChordView(NamedTuple):
    """Where a predicted chord may lie, as the compiled loops take it: the ceiling's
    height above the camera ``h_m`` (m), the lens's field radius ``field_r``
    (normalized), the margin ``margin_px`` kept inside the image, the image rows
    searched ``row0 .. row1``, the image's ``width`` and ``height`` and the focal
    length ``f_px`` (px; all floats)."""

    h_m: float
    field_r: float
    margin_px: float
    row0: float
    row1: float
    width: float
    height: float
    f_px: float


class ChordSearch(NamedTuple):
    """What :func:`_measure` and :func:`_predict` read, made once per tracker
    (read-only arrays): the camera's ``R_level_cam (3, 3)``, the site's lines along
    ``site_y (J,)`` (m, W's y) and their ``edge_kind (J,)``, the samples along each
    line ``along_m (S,)`` (m, W's x from the camera), the cross profiles ``grid``
    (:class:`~ceilkit.runtime.features.lines.ProfileGrid`; ``first_grid`` the first
    search's, :data:`FIRST_ALONG` places), the lens ``lens_code``,
    ``lens`` (:attr:`~ceilkit.runtime.geometry.camera.CameraModel.lens`) and the
    image ``bounds`` (:class:`ChordView`)."""

    R_level_cam: np.ndarray
    site_y: np.ndarray
    edge_kind: np.ndarray
    along_m: np.ndarray
    grid: ProfileGrid
    first_grid: ProfileGrid
    lens_code: int
    lens: np.ndarray
    bounds: ChordView


def chord_search(setup: CorridorSetup, camera: CameraModel, search_px: float
                 ) -> ChordSearch:
    """The :class:`ChordSearch` of a site's lines seen through ``camera``, cross
    profiles ``search_px`` to either side of a prediction (px)."""
    f = np.float64
    bounds = ChordView(float(setup.ceiling_above_cam_m), float(setup.field_radius),
                       float(search_px + 2.0), float(setup.rows[0]), float(setup.rows[1]),
                       float(camera.width), float(camera.height), float(setup.f_px))
    return ChordSearch(arr(setup.R_level_cam, f), arr(setup.site_y, f),
                       arr(setup.edge_kind, f), arr(np.linspace(-REACH_M, REACH_M, SAMPLES), f),
                       _profile_grid(N_ALONG, search_px), _profile_grid(FIRST_ALONG, search_px),
                       *camera.lens, bounds)


def _profile_grid(n_along: int, search_px: float) -> ProfileGrid:
    """The :class:`~ceilkit.runtime.features.lines.ProfileGrid` of ``n_along`` cross
    profiles ``search_px`` to either side of a chord."""
    offs, t, inner = edge_grid(n_along, search_px)
    il, ir, ii = part_indices(offs)
    f = np.float64
    return ProfileGrid(arr(offs, f), arr(t, f), arr(il, np.int64), arr(ir, np.int64),
                       arr(ii, np.int64), np.int64(inner.start + 1), np.int64(inner.stop + 1))


def flat_search(s: ChordSearch) -> tuple:
    """``s`` as plain nested tuples, the form the compiled entries take (numba types a
    named tuple argument field by field in Python: about 8 us a call here, against its
    own fast path for a plain tuple); :func:`_unflat` makes ``s`` of it again inside."""
    return (s.R_level_cam, s.site_y, s.edge_kind, s.along_m,
            tuple(s.grid[:5]) + (int(s.grid.i0), int(s.grid.i1)),
            tuple(s.first_grid[:5]) + (int(s.first_grid.i0), int(s.first_grid.i1)),
            int(s.lens_code), s.lens, tuple(float(v) for v in s.bounds))


def _measurement(found: tuple) -> LineMeasurement | None:
    """The :class:`LineMeasurement` of :func:`_measure`'s output, None where not found."""
    ok, segs_n, chords, line, pol, rms, n = found
    return LineMeasurement(segs_n, chords, line, pol, rms, n) if ok else None


class WindowFix(NamedTuple):
    """What the estimator reads of a frame's window path (:meth:`LineTracker.fix`,
    :func:`_window_fix`): the chords the frame's fit takes, ``segs_n (K, 4)``
    undistorted normalized, on site lines ``line (K,)`` (``n_lines`` distinct), searched
    about camera pan ``psi`` and y ``cy``; the fit ``fit`` ``(psi, c_y, cov_ok, C (2, 2),
    r)`` (:meth:`ChordFit.kept`), its rows' site y ``y (2K,)``, ``n_a`` along rows and
    ``n_b`` across rows (:class:`~.refine.GNInputs`' ``y``, ``n_a``, ``p0.size``); the
    model check's vanishing line ``vl`` (:func:`~.geometry.vanishing_line_dict`'s
    numbers) and ``counts`` (:func:`~.frame.labeled_counts`), and the ``twins``
    (:func:`labeling_twins`' arguments)."""

    segs_n: np.ndarray
    line: np.ndarray
    n_lines: int
    psi: float
    cy: float
    fit: tuple
    y: np.ndarray
    n_a: int
    n_b: int
    vl: tuple
    counts: tuple
    twins: tuple


@dataclass(frozen=True, eq=False)
class WindowFit:
    """A window fix before its model check: the located ``chords``
    (:class:`LineMeasurement`) and the ``frame`` fitted on them
    (:class:`~.refine.FrameFit`: the chords as forward segments, each labeled with its
    site line)."""

    chords: LineMeasurement
    frame: FrameFit


class ChordFit:
    """How the window path fits the chords it located (a stage of the estimator, its
    constants made once): the chords as forward segments, each on its site line, fitted
    by the joint Gauss-Newton on ``(psi, c_y)`` from where they were searched, and kept
    when the fit's rms is within what a chord meets (``inlier_px`` and
    :data:`MAX_CHORD_RMS_PX`, docs/methods/corridor.md) and the fit within ``reach``
    (:meth:`LineTracker.reach`).

    Args:
        setup: the estimator's :class:`~.setup.CorridorSetup`.
        angle_tol_rad, inlier_px: the frame's family gate (:func:`~.frame.frame_lines`).
        iterations: the Gauss-Newton's steps at most.
        reach: ``(psi_rad, c_y m)`` how far a kept fit may move from its start.
        times: the row times ``(N, 2)`` of a frame's segments for a rolling shutter's
            rates (None: a global shutter): the estimator's.
    """

    def __init__(self, setup: CorridorSetup, angle_tol_rad: float, inlier_px: float,
                 iterations: int, reach: tuple[float, float],
                 times: Callable[[FrameLines, RowRates | None], np.ndarray | None]) -> None:
        self.setup, self.angle_tol_rad, self.inlier_px = setup, angle_tol_rad, inlier_px
        self.iterations, self.reach, self.times = iterations, reach, times
        self.cam = level_camera(setup, setup.R_level_cam)
        self.site_y = arr(setup.site_y, np.float64)
        self.kernel = ((self.cam.R, self.cam.h_m, self.cam.f_px), self.site_y,
                       (min(inlier_px, MAX_CHORD_RMS_PX), float(reach[0]), float(reach[1])),
                       int(max(1, iterations)),
                       (arr(setup.lamp_width_m, np.float64), float(angle_tol_rad),
                        float(inlier_px)))
        """What :func:`_window_core` takes of the fit: the camera, the site's lines,
        the checks of :meth:`ok`, the steps and the frame's
        (:func:`~.frame.frame_lines`: the lamps' widths, the family gate)."""

    def ok(self, fit: tuple[float, float, float], psi: float, cy: float) -> bool:
        """Whether a fit ``(psi, c_y, rms_px)`` started at ``(psi, cy)`` is kept."""
        reach_psi, reach_cy = self.reach
        return not (fit[2] > min(self.inlier_px, MAX_CHORD_RMS_PX)
                    or abs(math.remainder(fit[0] - psi, 2 * math.pi)) > reach_psi
                    or abs(fit[1] - cy) > reach_cy)

    def first(self, m: LineMeasurement, psi: float, cy: float, rates: RowRates | None
              ) -> tuple[float, float] | None:
        """``(psi, c_y)`` of :meth:`frame`'s fit, None where it is None; with a global
        shutter from one compiled call (:func:`~.refine.along_fit`: the same numbers,
        without the frame's arrays, the covariance and the objects): the fit whose only
        use is where to search again."""
        if rates is not None:
            found = self.frame(m, psi, cy, rates)
            return None if found is None else (found.frame.fit.psi_rad,
                                               found.frame.fit.camera_y_m)
        fit = along_fit(m.segs_n, m.line, self.site_y, self.cam, psi, cy,
                        self.iterations)
        return fit[:2] if self.ok(fit, psi, cy) else None

    def kept(self, fx: tuple, psi: float, cy: float) -> PanOffsetFit | None:
        """The :class:`~.refine.PanOffsetFit` of the compiled fit ``fx`` ``(psi, c_y,
        cov_ok, C, r)`` (:func:`_frame_fit`'s) started at ``(psi, cy)``, None: not kept
        (:meth:`ok`)."""
        fit_psi, fit_cy, cov_ok, C, r = fx
        fit = pan_offset_fit(fit_psi, fit_cy, C if cov_ok else None, r)
        return fit if self.ok((fit.psi_rad, fit.camera_y_m, fit.rms_px), psi, cy) else None

    def frame(self, m: LineMeasurement, psi: float, cy: float, rates: RowRates | None
              ) -> WindowFit | None:
        """The :class:`WindowFit` of chords ``m`` searched about camera pan ``psi`` and
        camera y ``cy`` with a rolling shutter's ``rates`` (None: a global shutter), or
        None: not kept."""
        st = self.setup
        n, n_lines = m.segs_n.shape[0], m.n_lines
        fr = frame_lines(m.segs_n, m.polarity, st, self.angle_tol_rad, self.inlier_px)
        along, across = np.ones(n, bool), np.zeros(n, bool)
        lab = Labeling((n_lines, float(n)), psi, cy, along, across, m.line, n_lines,
                       False, "window")
        gd = gn_inputs(fr, along, across, m.line, st, self.times(fr, rates))
        fit = joint_fit(gd, psi, cy, st, self.iterations, rates)
        if not self.ok((fit.psi_rad, fit.camera_y_m, fit.rms_px), psi, cy):
            return None
        return WindowFit(m, FrameFit(fr, lab, gd, fit))


def window_applies(readout_ms: float, prior: PoseEstimate | None) -> bool:
    """Whether a frame may take the window path: a prior with a lateral position, and
    with a rolling shutter (``readout_ms`` > 0) one that carries a velocity (a track's
    prediction once it has measured one; the fusion's once its velocity is known).

    Without a velocity the rows' motion is unknown (:func:`~..rows.row_motion`: zero,
    with the ``unknown_*`` sigmas) on either path, and each path's lateral error is
    that motion seen through where its evidence lies in the frame: on bench_paired's
    rolling-shutter drive (25 ms) both errors are linear in the truth's lateral speed
    and yaw rate to 0.22 mm (global) and 0.07 mm (window) rms of 5.2 and 5.7, the
    window's chords 27 mm of lateral per rad/s of yaw rate against the global path's
    segments' 25 (its p95 0.75 mm larger). Such a frame goes to the global path, the
    one the default was measured against (docs/methods/corridor.md)."""
    if prior is None or prior.y_m is None:
        return False
    return readout_ms <= 0 or prior.velocity is not None


def without_ignored(m: LineMeasurement | None, regions, pose) -> LineMeasurement | None:
    """``m`` without the chords inside the site's ``ignore`` regions seen from ``pose``
    (:class:`~ceilkit.runtime.estimators.ignore.IgnoreRegions`; SPEC §2), None when
    fewer than two site lines keep a chord; ``m`` itself with no region or no pose."""
    keep = None if m is None or regions is None else regions.keep_segments(m.segs_n, pose)
    if keep is None or keep.all():
        return m
    if np.unique(m.line[keep]).size < 2:
        return None
    return dataclasses.replace(m, segs_n=m.segs_n[keep], segs_px=m.segs_px[keep],
                               line=m.line[keep], polarity=m.polarity[keep],
                               rms_px=m.rms_px[keep])


class LineTracker:
    """Edge searches across the site lines predicted from a prior (module doc).

    Args:
        setup: the estimator's :class:`~.setup.CorridorSetup`.
        camera: the intrinsics.
        search_px: half-width of the cross profiles (px): how far an edge may be from
            its prediction (the prior's error in pixels, plus a pixel).
    """

    def __init__(self, setup: CorridorSetup, camera: CameraModel, search_px: float) -> None:
        self.setup, self.camera = setup, camera
        self.search_px = float(search_px)
        self.search = chord_search(setup, camera, self.search_px)
        self.flat = flat_search(self.search)
        self.kernel_lines = (self.search.site_y, arr(np.abs(setup.edge_kind), np.float64))

    def predicted_chords(self, psi_rad: float, camera_y_m: float
                         ) -> tuple[np.ndarray, np.ndarray]:
        """``(chords (K, 4) px, line (K,))``: the visible stretches of every site line
        for camera pan ``psi_rad`` and camera y ``camera_y_m``, cut into chords of about
        :data:`CHORD_PX` (:func:`_predict`)."""
        return _predict(float(psi_rad), float(camera_y_m), self.search.site_y, self.search)

    def measure(self, grey: np.ndarray, psi_rad: float, camera_y_m: float,
                first: bool = False) -> LineMeasurement | None:
        """The chords located on a ``(H, W)`` uint8 frame around the site lines
        predicted for ``(psi_rad, camera_y_m)``; ``None`` when fewer than two site lines
        hold a located chord of the right kind. One compiled call (:func:`_measure`);
        ``first``: a frame's first search, :data:`FIRST_ALONG` places on every
        :data:`FIRST_STRIDE`-th chord of a line (its fit only says where to search
        again), else :data:`N_ALONG` places on every chord."""
        return _measurement(_measure_flat(arr(grey, np.uint8), float(psi_rad),
                                          float(camera_y_m), self.flat,
                                          FIRST_STRIDE if first else 0))

    def fix(self, grey: np.ndarray, psi_rad: float, camera_y_m: float, fit: tuple,
            remeasure_px: float, mirror_y_m: float | None = None) -> WindowFix | None:
        """A frame's searches, with a global shutter and no ignore region, as one compiled
        call (:func:`_window_fix`, :func:`_window_core`): the first search (:meth:`measure`,
        ``first``), its fit (:meth:`ChordFit.first`; a full first search where the quarter
        gives none), the full search about that fit (about ``(psi_rad, camera_y_m)`` where
        it moves the lines at most ``remeasure_px``, :meth:`shift_px`), the frame's fit of
        its chords (:meth:`ChordFit.frame`'s numbers), the fix's checks and its twins
        (:func:`window_twins`, ``mirror_y_m``): the estimator's reading, the same numbers,
        without the calls between; ``fit``: :attr:`ChordFit.kernel`. What the estimator
        reads of it (:class:`WindowFix`), None where no chords are kept: only those arrays
        go back to Python (each array handed back costs its boxing, about a microsecond:
        8 arrays, against 29 for the whole of :func:`_window_core`'s output)."""
        found, *rest = _window_fix(arr(grey, np.uint8), float(psi_rad), float(camera_y_m),
                                   self.flat, fit, (float(remeasure_px), FIRST_STRIDE),
                                   (self.kernel_lines[1], _mirror(mirror_y_m)))
        return WindowFix(*rest) if found else None

    def shift_px(self, d_psi_rad: float, d_cy_m: float) -> float:
        """How far (px, at the image's scale) a change of the camera's pan and y moves
        the predicted lines: the larger of its two parts."""
        f = self.setup.f_px
        return max(abs(d_psi_rad) * f, abs(d_cy_m) * f / self.setup.ceiling_above_cam_m)

    def chords_at(self, psi_rad: float, camera_y_m: float,
                  site_y: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predicted_chords` of the lines at W's y = ``site_y`` (default the
        site's ``lines_along``): ``(chords (K, 4) px, line (K,))``, ``line`` indexing
        ``site_y``; a line with no chord is not in view."""
        ys = self.search.site_y if site_y is None else arr(site_y, np.float64)
        return _predict(float(psi_rad), float(camera_y_m), ys, self.search)

    def probe(self, grey: np.ndarray, chords: np.ndarray, line: np.ndarray,
              kinds: np.ndarray, asked: np.ndarray) -> np.ndarray:
        """``(L,)`` bool: whether an edge of the kind ``kinds[l]`` (0 a thin line, else a
        step) lies on line ``l`` (of those ``asked``) at :data:`PROBE_CHORDS` of its
        chords ``chords``/``line`` (:meth:`chords_at`), spread along it: a chord of the
        right kind whose points scatter at most :data:`MAX_CHORD_RMS_PX` (a look, not
        a measurement: one compiled call of the edge profiles)."""
        out = np.zeros(kinds.size, bool)
        pick = _probe_chords(line, arr(asked, np.bool_), PROBE_CHORDS)
        if pick.size == 0:
            return out
        s = self.search
        _, pol, rms = refine_chords_core(arr(grey, np.uint8), arr(chords[pick], np.float64),
                                         s.grid, ProfileKind(MIN_STEP, MIN_DEPTH, PROFILE_STEP_PX),
                                         s.lens_code, s.lens, s.bounds.f_px, LOCAL_SHARE)
        ln = line[pick]
        step = kinds[ln] != 0
        ok = np.isfinite(rms) & (rms <= MAX_CHORD_RMS_PX) & np.where(
            step, np.abs(pol) == 1.0, pol == 0.0)
        out[ln[ok]] = True
        return out

    def reach(self) -> tuple[float, float]:
        """``(psi_rad, c_y m)``: how far from the prior a refined fit may move and still
        be what the searches saw (about ``search_px`` at the image's scale)."""
        f = self.setup.f_px
        return (math.atan2(self.search_px, f) * 2.0,
                self.search_px / f * self.setup.ceiling_above_cam_m * 2.0)


@njit
def _predict(psi, cam_y, site_y, search):  # pragma: no cover - compiled
    """``(chords (K, 4) px, line (K,))`` of :meth:`LineTracker.predicted_chords`: every
    line ``y = site_y[j]`` (m, W) sampled at ``search.along_m`` (W's x from the camera;
    ``search``: a :class:`ChordSearch`), seen from the camera rotation
    ``R_cw = R_level_camᵀ Rz(-psi)`` at ``h = search.bounds.h_m`` below the ceiling; a
    sample is visible in front of the camera, within :data:`REACH_M` on the ceiling,
    inside the lens's field and the margin inside the image's rows searched
    (:class:`ChordView`); each line's longest visible run is cut into chords
    (:func:`_chords_of_runs`)."""
    R_lc, u, v = search.R_level_cam, search.along_m, search.bounds
    h, field_r, m = v.h_m, v.field_r, v.margin_px
    row0, row1, w, hh = v.row0, v.row1, v.width, v.height
    c, s = math.cos(-psi), math.sin(-psi)
    R = np.empty((3, 3))
    for i in range(3):                     # R_lcᵀ Rz(-psi)
        R[i, 0] = R_lc[0, i] * c + R_lc[1, i] * s
        R[i, 1] = -R_lc[0, i] * s + R_lc[1, i] * c
        R[i, 2] = R_lc[2, i]
    n_j, n_s = site_y.size, u.size
    xy = np.empty((n_j * n_s, 2))
    front = np.empty((n_j, n_s), np.bool_)
    n_f = 0
    for j in range(n_j):
        dy = site_y[j] - cam_y
        for i in range(n_s):
            d0 = u[i] * R[0, 0] + (dy * R[0, 1] + h * R[0, 2])
            d1 = u[i] * R[1, 0] + (dy * R[1, 1] + h * R[1, 2])
            d2 = u[i] * R[2, 0] + (dy * R[2, 1] + h * R[2, 2])
            f = d2 > 1e-6 and u[i] * u[i] + dy * dy <= REACH_M * REACH_M
            z = d2 if f else 1.0
            x, y = d0 / z, d1 / z
            front[j, i] = f and x * x + y * y <= field_r * field_r
            if front[j, i]:
                xy[n_f, 0], xy[n_f, 1] = x, y
                n_f += 1
    # only the samples in front are distorted (the lens maps each point alone; the
    # others are not visible, and _chords_of_runs reads the pixels of visible runs only)
    px_f = np.empty((n_f, 2))
    distort_points(xy[:n_f], search.lens_code, search.lens, px_f)
    px = np.zeros((n_j, n_s, 2))
    vis = np.zeros((n_j, n_s), np.bool_)
    lo_v, hi_v = max(m, row0), min(hh - 1 - m, row1)
    k = 0
    for j in range(n_j):
        for i in range(n_s):
            if not front[j, i]:
                continue
            pu, pv = px_f[k, 0], px_f[k, 1]
            k += 1
            px[j, i, 0], px[j, i, 1] = pu, pv
            vis[j, i] = m <= pu <= w - 1 - m and lo_v <= pv <= hi_v
    return _chords_of_runs(px, vis, CHORD_PX, MIN_CHORD_PX)


@njit
def _measure(grey, psi, cam_y, s, grid, stride):  # pragma: no cover - compiled
    """:meth:`LineTracker.measure` (``s``: the tracker's :class:`ChordSearch`, ``grid``
    its ``grid`` or ``first_grid``, every ``stride``-th chord of a line):
    ``(found, segs_n, chords, line, polarity, rms, searched)``. The chords of
    :func:`_predict` are measured by
    :func:`~ceilkit.runtime.features.lines.refine_chords`' loop; then the chords of the
    wrong kind or a poor fit are dropped (:data:`MAX_CHORD_RMS_PX`,
    :data:`CHORD_RMS_MEDIANS`). ``found`` is False when fewer than two site lines are
    predicted or keep a chord."""
    chords, line = _predict(psi, cam_y, s.site_y, s)
    if stride > 1:
        pick = _every(line, stride)
        chords, line = chords[pick], line[pick]
    n = chords.shape[0]
    empty = (False, np.empty((0, 4)), np.empty((0, 4)), np.empty(0, np.int64),
             np.empty(0), np.empty(0), n)
    if _distinct(line) < 2:
        return empty
    kind = ProfileKind(MIN_STEP, MIN_DEPTH, PROFILE_STEP_PX)
    ends, pol, rms = refine_chords_core(grey, chords, grid, kind, s.lens_code, s.lens,
                                        s.bounds.f_px, LOCAL_SHARE)
    ok = np.zeros(n, np.bool_)
    for r in range(n):
        kind_ok = abs(pol[r]) == 1.0 if s.edge_kind[line[r]] != 0 else pol[r] == 0.0
        ok[r] = math.isfinite(rms[r]) and rms[r] <= MAX_CHORD_RMS_PX and kind_ok
    if ok.any():
        limit = CHORD_RMS_MEDIANS * np.median(rms[ok])
        for r in range(n):
            ok[r] = ok[r] and rms[r] <= limit
    if _distinct(line[ok]) < 2:
        return empty
    return True, ends[ok], chords[ok], line[ok], pol[ok], rms[ok], n


@njit
def _unflat(f):  # pragma: no cover - compiled
    """The :class:`ChordSearch` of :func:`flat_search`'s tuple ``f``."""
    g, q, b = f[4], f[5], f[8]
    return ChordSearch(f[0], f[1], f[2], f[3],
                       ProfileGrid(g[0], g[1], g[2], g[3], g[4], g[5], g[6]),
                       ProfileGrid(q[0], q[1], q[2], q[3], q[4], q[5], q[6]), f[6], f[7],
                       ChordView(b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]))


@njit
def _measure_flat(grey, psi, cam_y, flat, stride):  # pragma: no cover - compiled
    """:func:`_measure` of :func:`flat_search`'s ``flat``: a first search on every
    ``stride``-th chord of a line (its ``first_grid``), a full one where ``stride`` is 0."""
    s = _unflat(flat)
    if stride > 0:
        return _measure(grey, psi, cam_y, s, s.first_grid, stride)
    return _measure(grey, psi, cam_y, s, s.grid, 1)


@njit
def _window_core(grey, psi, cam_y, flat, fit, how, twin):  # pragma: no cover - compiled
    """:meth:`LineTracker.window` (``fit``: :attr:`ChordFit.kernel`; ``how``: the
    shift searched again about itself, px, and :data:`FIRST_STRIDE`; ``twin``:
    :func:`_twins_core`'s ``kind_abs`` and ``mirror``):
    ``(found, psi, c_y, measured, fitted)``, ``measured`` as :func:`_measure`'s,
    ``fitted`` as :func:`_frame_fit`'s (of no chords where not found)."""
    s = _unflat(flat)
    m = _measure(grey, psi, cam_y, s, s.first_grid, how[1])
    ok, psi1, cy1 = _first_fit(m, psi, cam_y, fit)
    if not ok:                  # the quarter missed (a prior pixels off): a full one
        m = _measure(grey, psi, cam_y, s, s.grid, 1)
        ok, psi1, cy1 = _first_fit(m, psi, cam_y, fit)
    if ok:
        b = s.bounds           # LineTracker.shift_px (Python's max: the first unless above)
        a, c = abs(psi1 - psi) * b.f_px, abs(cy1 - cam_y) * b.f_px / b.h_m
        if (c if c > a else a) <= how[0]:
            psi1, cy1 = psi, cam_y
        m = _measure(grey, psi1, cy1, s, s.grid, 1)
    found = ok and m[0]
    k = m[1].shape[0] if found else 0
    fitted = _frame_fit(m[1][:k], m[3][:k], m[4][:k], m[5][:k], psi1, cy1, fit)
    fx = fitted[2]
    refused, psi_t, cy_t, shift = _twins_of(grey, fx[0], fx[1], s, twin[0], m[3][:k],
                                            twin[1])
    return found, psi1, cy1, m, fitted + ((refused or k == 0, psi_t, cy_t, shift),)


@njit
def _window_fix(grey, psi, cam_y, flat, fit, how, twin):  # pragma: no cover - compiled
    """:meth:`LineTracker.fix`: :func:`_window_core`'s ``(found, segs_n, line, n_lines,
    psi, c_y, fit, y, n_a, n_b, vanishing line, counts, twins)`` (:class:`WindowFix`
    after ``found``), the chords and rows of none where not found."""
    found, psi1, cy1, m, fitted = _window_core(grey, psi, cam_y, flat, fit, how, twin)
    k = m[1].shape[0] if found else 0
    line = m[3][:k]
    _, g, fx, vl, counts, twins = fitted
    return (found, m[1][:k], line, _count_distinct(line), psi1, cy1, fx, g[1], g[0],
            g[5].size, vl, counts, twins)


@njit
def _frame_fit(segs, line, pol, rms, psi, cam_y, fit):  # pragma: no cover - compiled
    """:meth:`ChordFit.frame`'s numbers (a global shutter) for chords ``segs (K, 4)``
    on site lines ``line (K,)``, of kinds ``pol`` and scatters ``rms (K,)``, searched
    about ``(psi, cam_y)`` (``fit``: :attr:`ChordFit.kernel`): ``(frame, gn, (psi,
    c_y, cov_ok, C (2, 2), r), vanishing line, counts)``, the arrays of
    :func:`~.frame._frame_arrays`, those of :func:`~.refine.gn_arrays` (every chord
    forward on its line), then :func:`~.refine.gauss_newton`'s compiled calls
    (:func:`~.refine.huber_steps`, :func:`~.refine.fix_cov`) on them, and the model
    check's :func:`~.geometry._vanishing_line` and :func:`~.frame.counts_core`: the
    same numbers in the same order."""
    (R, h, f), site_y, _, iterations, (lamp_w, angle_tol, inlier_px) = fit
    cam = LevelCamera(R, h, f)
    out = _frame_arrays(segs, R, h, lamp_w, angle_tol, inlier_px, f)
    n = segs.shape[0]
    along, across = np.ones(n, np.bool_), np.zeros(n, np.bool_)
    g = gn_arrays(FrameArrays(segs, out[0], out[2], out[3], out[1]), along, across, line,
                  site_y, cam)
    vl = _vanishing_line(out[0], out[1], along, across, R)
    counts = counts_core(segs, pol, along, across, line, rms)
    gd = GNArrays(g.e0.size, g.y, g.e0, g.e1, g.ez, g.p0, g.p1, g.mx_b, g.my_b, g.scale_b)
    r = np.empty(gd.e0.size + gd.p0.size)
    C = np.empty((2, 2))
    cov_ok = False
    if n == 0:
        return out, tuple(g), (psi, cam_y, cov_ok, C, r), vl, counts
    hf = huber_steps((psi, cam_y), gd, cam, iterations, r)
    if abs(hf.h00 * hf.h11 - hf.h01 * hf.h10) > 1e-300:
        cov_ok = fix_cov((hf.psi, hf.cy), gd, cam, np.empty(0), RowRates(0.0, 0.0, 0.0, 0.0),
                         C)
    return out, tuple(g), (hf.psi, hf.cy, cov_ok, C, r), vl, counts


@njit
def _first_fit(m, psi, cam_y, fit):  # pragma: no cover - compiled
    """:meth:`ChordFit.first` (a global shutter) of :func:`_measure`'s ``m``:
    ``(kept, psi, c_y)`` of :func:`~.refine.along_steps` from ``(psi, cam_y)``, kept as
    :meth:`ChordFit.ok` says (its rms summed in order: it is only compared)."""
    if not m[0]:
        return False, psi, cam_y
    (R, h, f), site_y, (most_px, reach_psi, reach_cy), iterations, _ = fit
    segs, line = m[1], m[3]
    r = np.empty(2 * segs.shape[0])
    psi1, cy1 = along_steps(segs, line, site_y, LevelCamera(R, h, f), (psi, cam_y),
                            iterations, r)
    ss = 0.0
    for v in r:
        ss += v * v
    rms = math.sqrt(ss / r.size) if r.size else math.nan
    d = np.fmod(psi1 - psi, 2.0 * math.pi)  # math.remainder's size, exactly
    if d > math.pi:
        d -= 2.0 * math.pi
    elif d < -math.pi:
        d += 2.0 * math.pi
    refused = rms > most_px or abs(d) > reach_psi or abs(cy1 - cam_y) > reach_cy
    return not refused, psi1, cy1


TWIN_EPS_M = 1e-4
"""Two site lines that a twin and the window fix put within this of each other (m,
across) lie on the same image line: the twin's line is measured by the fix's."""


def window_twins(lt: LineTracker, grey: np.ndarray, m: LineMeasurement, psi_rad: float,
                 camera_y_m: float, mirror_y_m: float | None = None
                 ) -> tuple[LabelingTwin, ...] | None:
    """The other poses of the same heading family a window fix's frame supports as
    well as the fix (camera pan ``psi_rad``, camera y ``camera_y_m``, its chords
    ``m``): the lateral shifts and half turns that put site lines where the fix's
    found lines lie (the site's symmetries applied to the fix; on a corridor symmetric
    about ``mirror_y_m`` the half turn is always among them), each scored as the
    global path scores a labeling: its site lines found, less
    :data:`~.association.ABSENCE_PENALTY` per line it puts in view that is not
    (:data:`~.hypotheses.TWIN_RATIO` of the fix's score makes a twin).

    A twin's lines that lie on the fix's searched lines take the fix's measurement;
    those in view where the fix searched none are looked at (a few chords each,
    :meth:`LineTracker.probe`) when they could make it a twin.
    None when a twin explains the frame better than the fix (the fix followed its
    prior onto a twin: a half-turned start pose on a corridor that is not symmetric),
    or a lateral shift matching about as many lines misses fewer in view (the global
    path's absence test would choose it against the prior): the global path decides
    the frame then. Quarter turns are not examined here."""
    return labeling_twins(*_twins_core(
        arr(grey, np.uint8), float(psi_rad), float(camera_y_m), lt.flat, lt.kernel_lines[1],
        m.line, _mirror(mirror_y_m)))


def _mirror(mirror_y_m: float | None) -> float:
    """The compiled calls' ``mirror``: NaN for none."""
    return np.nan if mirror_y_m is None else float(mirror_y_m)


def labeling_twins(refused: bool, psi_t: np.ndarray, cy_t: np.ndarray, shift: np.ndarray
                   ) -> tuple[LabelingTwin, ...] | None:
    """:func:`window_twins`' answer from :func:`_twins_core`'s."""
    if refused:
        return None
    return tuple(LabelingTwin(p, c, "shift" if t else "half_turn")
                 for p, c, t in zip(psi_t.tolist(), cy_t.tolist(), shift.tolist(), strict=True))


@njit
def _twins_core(grey, psi, cam_y, flat, kind_abs, line, mirror):  # pragma: no cover - compiled
    """:func:`_twins_of` of the search as :func:`flat_search` makes it."""
    return _twins_of(grey, psi, cam_y, _unflat(flat), kind_abs, line, mirror)


@njit
def _twins_of(grey, psi, cam_y, s, kind_abs, line, mirror):  # pragma: no cover - compiled
    """:func:`window_twins` in one call (the arguments of :func:`_twin_scores`):
    ``(refused, psi_t (T,), cy_t (T,), shift (T,) bool)``: the twins' camera pan and y
    (a lateral shift's pan is ``psi``'s; a half turn's ``psi + pi`` wrapped into
    [-pi, pi)), in the order of :func:`_twin_maps`' maps; ``refused`` when the global
    path decides the frame (a shift settled by absence, or a twin scoring above the
    fix's over :data:`~.hypotheses.TWIN_RATIO`)."""
    cands, score, n_all, own, settled = _twin_scores(grey, psi, cam_y, s, kind_abs, line,
                                                     mirror)
    n_c = cands.shape[0]
    psi_t, cy_t, shift = np.empty(n_c), np.empty(n_c), np.empty(n_c, np.bool_)
    n = 0
    for c in range(n_c):
        if settled or not (n_all[c] >= 2 and score[c] >= TWIN_RATIO * own):
            continue
        if score[c] > own / TWIN_RATIO:
            return True, psi_t[:0], cy_t[:0], shift[:0]
        sign, g = cands[c, 0], cands[c, 1]
        half = psi + math.pi
        psi_t[n] = psi if sign > 0 else (half + math.pi) % (2.0 * math.pi) - math.pi
        cy_t[n] = cam_y - g if sign > 0 else g - cam_y
        shift[n] = sign > 0
        n += 1
    return settled, psi_t[:n], cy_t[:n], shift[:n]


@njit
def _twin_scores(grey, psi, cam_y, s, kind_abs, line, mirror):  # pragma: no cover - compiled
    """:func:`window_twins`' numbers in one call (``s``: the tracker's
    :class:`ChordSearch`, ``kind_abs (J,)`` ``|edge_kind|``, ``line``: the fix's chords'
    site lines, ``mirror`` NaN for none): ``(cands (C, 2), score (C,), n_all (C,), own,
    settled)``: the maps of :func:`_twin_maps`, each scored with its lines where the fix
    searched none looked at (:func:`_probe_hits`), the fix's own score, and whether a
    lateral shift matching about as many lines misses fewer in view (then the global
    path decides the frame)."""
    n_j = s.site_y.size
    found = np.zeros(n_j, np.bool_)
    for i in range(line.size):
        found[line[i]] = True
    vis = found.copy()
    _, in_view = _predict(psi, cam_y, s.site_y, s)
    for i in range(in_view.size):
        vis[in_view[i]] = True
    n_own, n_gone = 0, 0
    for j in range(n_j):
        n_own += found[j]
        n_gone += vis[j] and not found[j]
    own = float(n_own - ABSENCE_PENALTY * n_gone)
    cands, n_found, n_missing, where, ws, kinds = _twin_maps(
        (s.site_y, kind_abs), found, vis, mirror, TWIN_EPS_M)
    score = n_found - ABSENCE_PENALTY * n_missing
    hit = np.full(ws.size, -1, np.int64)            # per unsearched line: 1, 0, -1 unseen
    if ws.size:
        chords, c_line = _predict(psi, cam_y, ws, s)
        seen = np.zeros(ws.size, np.bool_)
        for i in range(c_line.size):
            seen[c_line[i]] = True
            hit[c_line[i]] = 0
        ask = _asked(where, seen, score - TWIN_RATIO * own)
        if ask.any():
            _probe_hits(grey, chords, c_line, kinds, ask, s, hit)
    n_hit, n_seen = _tally(where, hit)
    score = score + n_hit - ABSENCE_PENALTY * (n_seen - n_hit)
    # a lateral shift matching as many lines and missing fewer is the one the global
    # path's absence test settles on (association.settle_by_absence): against the
    # prior's, it says ambiguous
    n_all = n_found + n_hit
    least = max(2.0, TWIN_RATIO * n_own)
    settled = False
    for c in range(cands.shape[0]):
        if (cands[c, 0] > 0 and n_all[c] >= least
                and n_missing[c] + n_seen[c] - n_hit[c] < n_gone):
            settled = True
    return cands, score, n_all, own, settled


@njit
def _probe_hits(grey, chords, line, kinds, asked, s, hit):  # pragma: no cover - compiled
    """:meth:`LineTracker.probe` into ``hit``: 1 for each ``asked`` line an edge of its
    kind lies on."""
    pick = _probe_chords(line, asked, PROBE_CHORDS)
    if pick.size == 0:
        return
    _, pol, rms = refine_chords_core(grey, chords[pick], s.grid,
                                     ProfileKind(MIN_STEP, MIN_DEPTH, PROFILE_STEP_PX),
                                     s.lens_code, s.lens, s.bounds.f_px, LOCAL_SHARE)
    for i in range(pick.size):
        ln = line[pick[i]]
        kind_ok = abs(pol[i]) == 1.0 if kinds[ln] != 0 else pol[i] == 0.0
        if math.isfinite(rms[i]) and rms[i] <= MAX_CHORD_RMS_PX and kind_ok:
            hit[ln] = 1


@njit
def _twin_maps(lines, found, vis, mirror, eps):  # pragma: no cover - compiled
    """:func:`window_twins`' candidate maps ``w = sign * y + g`` of the site lines
    ``lines = (site_y, |edge_kind|)`` onto W's y (a shift: sign +1, ``g = y_j - y_k``,
    the identity left out; a half turn: sign -1, ``g = y_j + y_k``, and ``2 mirror``
    when not NaN; ``y_j`` a ``found`` line), each once (within ``eps``):
    ``(cands (C, 2), n_found (C,), n_missing (C,), where (C, J), ws (U,), kinds (U,))``.
    Of a map's lines, those on a line the fix searched (a site line within ``eps``, in
    view ``vis``) count as found (``found``, of the same kind: step or thin line) or
    missing (not found, or of another kind); the others lie where the fix searched
    none: ``where[c, k]`` indexes them in ``ws``, ``kinds`` (-1: not such a line)."""
    site_y, kind = lines
    n_j = site_y.size
    raw = np.empty((2 * n_j * n_j + 1, 2))
    n = 0
    for j in range(n_j):
        if not found[j]:
            continue
        for k in range(n_j):
            if abs(site_y[j] - site_y[k]) > eps:
                raw[n, 0], raw[n, 1] = 1.0, site_y[j] - site_y[k]
                n += 1
            raw[n, 0], raw[n, 1] = -1.0, site_y[j] + site_y[k]
            n += 1
    if math.isfinite(mirror):
        raw[n, 0], raw[n, 1] = -1.0, 2.0 * mirror
        n += 1
    cands = np.empty((n, 2))
    m = 0
    for i in range(n):
        new = True
        for q in range(m):
            if cands[q, 0] == raw[i, 0] and abs(cands[q, 1] - raw[i, 1]) < eps:
                new = False
                break
        if new:
            cands[m, 0], cands[m, 1] = raw[i, 0], raw[i, 1]
            m += 1
    cands = cands[:m]
    n_found = np.zeros(m, np.int64)
    n_missing = np.zeros(m, np.int64)
    where = np.full((m, n_j), -1, np.int64)
    ws = np.empty(m * n_j)
    kinds = np.empty(m * n_j)
    u = 0
    for c in range(m):
        for k in range(n_j):
            w = cands[c, 0] * site_y[k] + cands[c, 1]
            at = -1
            for j in range(n_j):
                if abs(site_y[j] - w) < eps:
                    at = j
                    break
            if at >= 0:
                if vis[at] and found[at] and kind[at] == kind[k]:
                    n_found[c] += 1
                elif vis[at]:
                    n_missing[c] += 1
                continue
            for q in range(u):
                if abs(ws[q] - w) < eps and kinds[q] == kind[k]:
                    at = q
                    break
            if at < 0:
                ws[u], kinds[u] = w, kind[k]
                at = u
                u += 1
            where[c, k] = at
    return cands, n_found, n_missing, where, ws[:u], kinds[:u]


@njit
def _asked(where, seen, bound):  # pragma: no cover - compiled
    """``(U,)`` bool: the lines where the fix searched none (:func:`_twin_maps`'
    ``where``) in view (``seen``) of the maps that would be twins were all of theirs
    found (``bound``: a map's score less the twin's share of the fix's)."""
    ask = np.zeros(seen.size, np.bool_)
    for c in range(where.shape[0]):
        n = 0
        for k in range(where.shape[1]):
            if where[c, k] >= 0 and seen[where[c, k]]:
                n += 1
        if n > 0 and bound[c] + n >= 0:
            for k in range(where.shape[1]):
                if where[c, k] >= 0 and seen[where[c, k]]:
                    ask[where[c, k]] = True
    return ask


@njit
def _tally(where, hit):  # pragma: no cover - compiled
    """Per map: its lines where the fix searched none that were found (``hit`` 1) and
    those in view (``hit`` >= 0)."""
    n_c = where.shape[0]
    n_hit = np.zeros(n_c, np.int64)
    n_seen = np.zeros(n_c, np.int64)
    for c in range(n_c):
        for k in range(where.shape[1]):
            q = where[c, k]
            if q >= 0 and hit[q] >= 0:
                n_seen[c] += 1
                n_hit[c] += hit[q]
    return n_hit, n_seen


@njit
def _probe_chords(line, asked, most):  # pragma: no cover - compiled
    """Indices of up to ``most`` chords of each ``asked`` line (``line`` sorted),
    spread evenly along its run."""
    out = np.empty(line.size, np.int64)
    n, a = 0, 0
    while a < line.size:
        b = a
        while b < line.size and line[b] == line[a]:
            b += 1
        if asked[line[a]]:
            k = b - a
            take = min(most, k)
            for i in range(take):
                out[n] = a + (k * (2 * i + 1)) // (2 * take)
                n += 1
        a = b
    return out[:n]


@njit
def _count_distinct(line):  # pragma: no cover - compiled
    """How many distinct values a non-negative ``line`` holds (in any order)."""
    if line.size == 0:
        return 0
    seen = np.zeros(line.max() + 1, np.bool_)
    k = 0
    for v in line:
        k += not seen[v]
        seen[v] = True
    return k


@njit
def _every(line, stride):  # pragma: no cover - compiled
    """Indices of every ``stride``-th chord of each line's run (``line`` sorted), its
    first always."""
    out = np.empty(line.size, np.int64)
    n, k = 0, 0
    for i in range(line.size):
        k = k + 1 if i > 0 and line[i] == line[i - 1] else 0
        if k % stride == 0:
            out[n] = i
            n += 1
    return out[:n]


@njit
def _distinct(line):  # pragma: no cover - compiled
    """How many distinct values a sorted ``line`` holds."""
    k = 0
    for i in range(line.size):
        if i == 0 or line[i] != line[i - 1]:
            k += 1
    return k


def _cut_chords(px: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(chords (K, 4), line (K,))``: each line's longest run of visible samples
    (``px (J, S, 2)``, ``vis (J, S)``; the first of equal runs), cut into chords of
    about :data:`CHORD_PX` of arc length (ends interpolated along the arc as
    ``np.interp``); runs shorter than :data:`MIN_CHORD_PX` are left out."""
    return _chords_of_runs(arr(px, np.float64), arr(vis, np.bool_), CHORD_PX, MIN_CHORD_PX)


@njit
def _chords_of_runs(px, vis, chord_px, min_chord_px):  # pragma: no cover - compiled
    """:func:`_cut_chords`: ``(chords, line)``."""
    n_lines, n_s = vis.shape
    runs = np.zeros((n_lines, 2), np.int64)
    for j in range(n_lines):
        best_a, best_len, a = 0, 0, -1
        for i in range(n_s + 1):
            on = i < n_s and vis[j, i]
            if on and a < 0:
                a = i
            elif not on and a >= 0:
                if i - a > best_len:
                    best_a, best_len = a, i - a
                a = -1
        runs[j, 0], runs[j, 1] = best_a, best_a + best_len
    arc = np.zeros((n_lines, n_s))           # arc length along each run from its start
    count = np.zeros(n_lines, np.int64)      # chords of each line
    for j in range(n_lines):
        a, b = runs[j, 0], runs[j, 1]
        if b - a < 2:
            continue
        for i in range(a + 1, b):
            arc[j, i - a] = arc[j, i - a - 1] + math.hypot(px[j, i, 0] - px[j, i - 1, 0],
                                                           px[j, i, 1] - px[j, i - 1, 1])
        if arc[j, b - a - 1] >= min_chord_px:
            count[j] = max(1, int(np.rint(arc[j, b - a - 1] / chord_px)))
    chords = np.empty((count.sum(), 4))
    line = np.empty(count.sum(), np.int64)
    n = 0                                    # chords written
    for j in range(n_lines):
        k = count[j]
        if k == 0:
            continue
        a, b = runs[j, 0], runs[j, 1]
        m = b - a
        total = arc[j, m - 1]
        seg = 0
        pu, pv = px[j, a, 0], px[j, a, 1]
        for c in range(1, k + 1):
            x = total * (c / k)
            while seg < m - 2 and arc[j, seg + 1] <= x:
                seg += 1
            if x >= total:
                u, v = px[j, b - 1, 0], px[j, b - 1, 1]
            else:
                t = (x - arc[j, seg]) / (arc[j, seg + 1] - arc[j, seg])
                u = px[j, a + seg, 0] + t * (px[j, a + seg + 1, 0] - px[j, a + seg, 0])
                v = px[j, a + seg, 1] + t * (px[j, a + seg + 1, 1] - px[j, a + seg, 1])
            chords[n, 0], chords[n, 1], chords[n, 2], chords[n, 3] = pu, pv, u, v
            line[n] = j
            n += 1
            pu, pv = u, v
    return chords, line


@warmer
def _warm() -> None:
    px = np.stack([np.linspace(0.0, 100.0, 5), np.zeros(5)], axis=1)[None]
    _cut_chords(px, np.ones((1, 5), bool))
    cam = CameraModel.pinhole(64, 48, 50.0)
    f = np.float64
    toy = SimpleNamespace(ceiling_above_cam_m=2.0, field_radius=1.0, rows=(0, 48), f_px=50.0,
                          R_level_cam=np.eye(3), site_y=np.array([-1.0, 1.0]),
                          edge_kind=np.zeros(2))
    s = chord_search(toy, cam, 4.0)
    g = arr(np.zeros((48, 64), np.uint8), np.uint8)
    flat = flat_search(s)
    _measure_flat(g, 0.0, 0.0, flat, 0)
    _measure_flat(g, 0.0, 0.0, flat, 2)
    cam_fit = ((s.R_level_cam, 2.0, 50.0), s.site_y, (1.0, 0.1, 0.1), 6,
               (arr(np.array([0.3]), f), 0.03, 2.5))
    _window_core(g, 0.0, 0.0, flat, cam_fit, (0.02, 2), (arr(np.zeros(2), f), 0.0))
    _window_fix(g, 0.0, 0.0, flat, cam_fit, (0.02, 2), (arr(np.zeros(2), f), 0.0))
    _predict(0.0, 0.0, s.site_y, s)       # also called alone (chords_at)
    _count_distinct(arr(np.array([0, 1]), np.int64))
    lines = (arr([-1.0, 1.0], f), arr([0.0, 0.0], f))
    maps = _twin_maps(lines, np.ones(2, np.bool_), np.ones(2, np.bool_), 0.0, 1e-4)
    hit = np.zeros(maps[4].size, np.int64)
    _asked(maps[3], hit >= 0, np.zeros(maps[0].shape[0]))
    _tally(maps[3], hit)
    _probe_chords(np.array([0, 0, 1]), arr(np.ones(2, np.bool_), np.bool_), 2)
    _twins_core(g, 0.0, 0.0, flat,
                arr(np.zeros(2), f), np.array([0, 1]), 0.0)


__all__ = ["CHORD_PX", "CHORD_RMS_MEDIANS", "ChordFit", "ChordSearch", "ChordView",
           "LineMeasurement", "LineTracker", "REACH_M", "WindowFit", "WindowFix", "chord_search",
           "window_applies", "window_twins"]
