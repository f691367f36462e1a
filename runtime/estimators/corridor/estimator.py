"""The corridor estimator: heading and lateral position from the ceiling's two line families.

After Yang & Tsai, "Viewing corridors as right parallelepipeds": the ceiling carries
lines along the corridor (W's x, at ``y = site.corridor.lines_along``) and
optionally lines across it (W's y). Their vanishing points lie on the ceiling's
vanishing line, which depends on the calibrated tilt and swing only; where the
forward vanishing point sits on it gives the camera's pan in W, and the image
lines of the forward family give the lateral position (formulas: :mod:`.geometry`).

The stages, in a frame's order: :mod:`.frame` (segments, edge kinds, per-frame
arrays), :mod:`.hypotheses` (pan candidates, families, which is forward),
:mod:`.association` (which site line is which), :mod:`.refine` (joint Gauss-Newton on
``(psi, c_y)``, the vehicle pose). This module orchestrates them.

Output: the vehicle's ``yaw_rad`` and ``y_m`` in W, ``x_m = None`` (not observed),
``lateral_m = y_m - site.corridor.axis_y_m``.

Example::

    est = CorridorEstimator(rig, site, CorridorOptions(detector="lsd"))
    pose = est.estimate(grey, t_ns)       # PoseEstimate, or a falsy Failure
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import (
    AMBIGUOUS,
    Estimate,
    Estimator,
    Hypothesis,
    PoseEstimate,
    Provenance,
    elapsed_ms,
)
from ceilkit.runtime.estimators.corridor.consensus import consensus_fit
from ceilkit.runtime.estimators.corridor.frame import (
    FrameLines,
    frame_lines,
    frame_segments,
    labeled_counts,
    undistorted,
)
from ceilkit.runtime.estimators.corridor.geometry import (
    vanishing_line_check,
    vanishing_line_dict,
)
from ceilkit.runtime.estimators.corridor.hypotheses import (
    LabelContext,
    Labeling,
    LabelingTwin,
    Unresolved,
    best_labeling,
    dominant_pans,
)
from ceilkit.runtime.estimators.corridor.refine import (
    FrameFit,
    PanOffsetFit,
    RowRates,
    camera_y_speed,
    gn_inputs,
    joint_fit,
    vehicle_pose,
)
from ceilkit.runtime.estimators.corridor.setup import (
    CorridorSetup,
    check_setup,
    default_match_tol_m,
    mirror_line,
)
from ceilkit.runtime.estimators.corridor.track import (
    ChordFit,
    LineMeasurement,
    LineTracker,
    WindowFit,
    labeling_twins,
    window_applies,
    window_twins,
    without_ignored,
)
from ceilkit.runtime.estimators.honesty import (
    DEFAULT_ALPHA,
    HEADING_DISAGREES,
    MISFIT,
    OUTSIDE_SITE,
    VANISHING_LINE,
    WEAK_GEOMETRY,
    Misfit,
    SiteExtent,
    check_options,
    misfit,
    outside_site,
)
from ceilkit.runtime.estimators.ignore import IgnoreRegions
from ceilkit.runtime.estimators.prior import prior_choice
from ceilkit.runtime.estimators.rows import ShutterOptions, row_motion
from ceilkit.runtime.features.lines import SegmentDetector
from ceilkit.runtime.features.working import WORKING_MPX, working_factor
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.geometry.shutter import row_times_s
from ceilkit.runtime.jit import arr

MIN_LENGTH_SHARE = 0.04
"""The default shortest segment, as a share of the image width."""

COARSE_FACTOR = 2
"""The coarse search's decimation (``coarse_search``)."""
COARSE_MIN_MPX = 0.25
"""The coarse search runs on frames of at least this many megapixels (640x480 is 0.31):
a smaller frame decimated by 2 leaves seams and lamp ends too few pixels."""
COARSE_HALF_WIDTH_PX = 4.0
"""The edge fit's profile half-width (full-resolution px) after the coarse search: the
full-resolution one (a segment found at half resolution lies within about a pixel of
its edge; the wider :func:`~ceilkit.runtime.features.lines.edge_half_width_px` of 10
reaches the pipe beside a lamp edge: on the first clutter frame it published a pose 0.7 m
off, 0.9 m at 6 px, where 4 px does not)."""
COARSE_MIN_QUALITY = 0.5
"""A coarse search's pose below this quality (or its failure) is searched again at full
resolution: a published valid pose (``quality >= 0.5``) comes from either search."""

REMEASURE_PX = 0.02
"""A tracked fit that moves the predicted lines further than this (px) is searched
again about itself. A chord located about a prediction that misses its edge by
``delta`` carries an error that depends on ``delta`` (the profile's samples are 0.5 px
apart: the thin line's centroid gains or loses a sample with the phase, up to 0.03 px
at a tile seam; and the edge model leans towards the profile's middle), the same on
every chord of the fix, so the fix followed its prior by a share no residual shows:
on bench_ambiguity's tiles loop (noise 2) its y 41 um off from a prior 0.2 px
(1.1 mm) off, 1 um from the truth as prior, against a 1 sigma of 16 um; the track's
predictions 0.44 px off (median), its mean NEES 5.47 against its band [0.96, 3.42]
with 1 px here, 1.88 [1.53, 2.54] with 0.02 px (a second search on nearly every
frame; issue 36, docs/methods/corridor.md)."""
HORIZONTAL_NORMAL = 0.2
"""Segments whose level normal's horizontal part is below this weigh less in the pan
histogram (they are near the horizon or point at the vanishing line)."""


@dataclass(frozen=True)
class CorridorOptions(ShutterOptions):
    """What a user may set (``--option KEY=VALUE``).

    Attributes:
        detector: ``fld``, ``lsd``, ``hough`` or ``ed`` (see
            :mod:`~ceilkit.runtime.features.lines`).
        refine: sub-pixel refinement of segments on image gradients in pixel space
            (``lines.refine_segments``).
        edge_fit: locate each segment's edge on cross profiles, fit it in undistorted
            coordinates and tell steps from thin lines (``lines.refine_undistorted``).
            Lamp edges are steps whose bright side is the lamp: this settles which site
            line a forward line is.
        min_length_px: shortest segment used (None: 4 % of the image width).
        max_segments: only the longest ones are kept.
        angle_tol_deg: family membership gate about the vanishing point.
        match_tol_m: 1-D association gate for lateral offsets (None: a quarter of the
            closest spacing of ``lines_along``, at most 0.08 m).
        inlier_px: endpoint distance (px) gate of the final fit.
        gn_iterations: most joint Gauss-Newton steps on ``(psi, c_y)``.
        min_elevation_deg: image rows whose rays all rise less than this above the
            horizon hold no useful ceiling and are not searched.
        noise_px: the expected standard deviation of a fitted endpoint (px): the
            chi-square test of the fit's residuals (``misfit``) is against it.
        misfit_alpha: the chi-square test's false-alarm rate on a fit that is noise.
        max_vp_elevation_deg: the forward family's free vanishing point may lie at
            most this far off the vanishing line the calibrated mount predicts
            (``vanishing_line``).
        max_vanishing_line_deg: the line through both families' free vanishing points
            may be at most this far from the predicted one (``vanishing_line``; larger:
            the across family is often two short segments, whose vanishing point is
            poorly determined).
        max_heading_change_deg: the refinement may move the heading at most this far
            from the vanishing point's (``heading_disagrees``).
        min_lines: fewest distinct site lines matched (``weak_geometry``).
        min_spread: the matched forward endpoints must span at least this share of
            the image width (``weak_geometry``).
        site_margin_m: the pose may lie at most this far outside the site's extent
            (``outside_site``).
        consensus: leave out the matched forward segments the ceiling does not explain
            (:mod:`~.consensus`: pipes, ducts, cable trays at another height); False
            fits every matched segment (the former behaviour, for comparisons).
        window_search: with a prior, search for the site lines only across their
            predicted image lines (:mod:`~.track`: 1-D edge searches, no line
            detector); the global path runs when that check fails, when a twin of the
            fix explains the frame better or lies inside the prior's region too
            (:func:`~.track.window_twins`), and every ``window_full_every``-th window
            fix; with a rolling shutter (``readout_ms`` > 0) only when the prior
            carries a velocity (:func:`~.track.window_applies`). On by default since
            issue 38 (no less accurate than the global path on every bench case,
            docs/methods/corridor.md). (Formerly ``track``.)
        window_px: half-width of the searches (px): how far a line may lie from its
            prediction. (Formerly ``track_search_px``.)
        window_full_every: a global search after this many window fixes (0: only when
            the check fails). (Formerly ``track_full_every``.)
        coarse_search: look for segments first on the frame decimated by 2 (a quarter of
            the pixels), refit them on the full frame (the edge fit), and search the
            full frame only when that gives no pose of quality >= 0.5 and is not
            ``ambiguous`` between turns of the pose (:func:`turned_twins`: a tile
            grid's, a symmetric corridor's). Only with ``edge_fit`` (the refit is
            what makes the coarse segments exact), on frames of 0.25 megapixels or
            more whose working resolution is the full frame
            (``working_mpx`` > 0 and the frame below about 2.25 times it: 640x480 to
            1920x1080 at the default).
        working_mpx: a frame larger than this (megapixels) is searched for segments
            decimated by an integer factor (:mod:`~ceilkit.runtime.features.working`);
            the segments are refitted on the full frame with a profile half-width of
            :func:`~ceilkit.runtime.features.lines.edge_half_width_px`; 0: always at
            full resolution.
        readout_ms, rate_sigma_dps, speed_sigma_mps, unknown_rate_dps,
            unknown_speed_mps: (inherited) a rolling shutter
            (:class:`~ceilkit.runtime.estimators.rows.ShutterOptions`): each endpoint
            is predicted from the pose at its row's time, moved by the prior's yaw
            rate and lateral speed; their uncertainty is added to the covariance.
        min_contrast: (inherited) grey-level spread below which a frame is blank.
        assume_heading_deg: what the user states of the vehicle's heading when the
            frame cannot tell (a corridor symmetric about its centre line looks the
            same driven either way): within 90 deg of this (degrees in W). A prior,
            not evidence: a pose it chooses has ``Provenance.PRIOR``. None (the
            default): such a frame is ``ambiguous`` unless a prior chooses.
    """

    detector: str = "fld"
    refine: bool = False
    edge_fit: bool = True
    min_length_px: float | None = None
    max_segments: int = 120
    angle_tol_deg: float = 2.0
    match_tol_m: float | None = None
    inlier_px: float = 2.5
    gn_iterations: int = 6
    min_elevation_deg: float = 3.0
    consensus: bool = True
    window_search: bool = True
    window_px: float = 5.0
    window_full_every: int = 30
    coarse_search: bool = True
    working_mpx: float = WORKING_MPX
    noise_px: float = 1.0
    misfit_alpha: float = DEFAULT_ALPHA
    max_vp_elevation_deg: float = 5.0
    max_vanishing_line_deg: float = 10.0
    max_heading_change_deg: float = 2.0
    min_lines: int = 2
    min_spread: float = 0.1
    site_margin_m: float = 1.5
    assume_heading_deg: float | None = None

    ALIASES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "track": "window_search", "track_search_px": "window_px",
        "track_full_every": "window_full_every"})


class CorridorEstimator(Estimator):
    """Heading and lateral position from the ceiling's along/across line families.

    Args:
        rig: the camera and its mount (tilt and swing are used as calibrated).
        site: needs ``corridor``; ``ceiling_height_m`` must exceed ``mount.z_m``.
        options: :class:`CorridorOptions`, a mapping of its fields, or None.
    """

    name = "corridor"
    Options = CorridorOptions
    site_sections = ("corridor",)

    def __init__(self, rig: Rig, site: Site,
                 options: CorridorOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(rig, site, options)
        check_setup(rig, site)
        o: CorridorOptions = self.options
        cam = rig.camera
        self.setup = CorridorSetup.build(rig, site, math.radians(o.min_elevation_deg))
        self.match_tol_m = (default_match_tol_m(self.setup.site_y) if o.match_tol_m is None
                            else float(o.match_tol_m))
        min_length_px = (MIN_LENGTH_SHARE * cam.width if o.min_length_px is None
                         else float(o.min_length_px))
        factor = working_factor((cam.height, cam.width), o.working_mpx)
        self.detector = SegmentDetector(o.detector, min_length_px, rows=self.setup.rows,
                                        merge=False, factor=factor)
        self.coarse_detector = (
            SegmentDetector(o.detector, min_length_px, rows=self.setup.rows, merge=False,
                            factor=COARSE_FACTOR)
            if (o.coarse_search and o.edge_fit and o.working_mpx > 0 and factor == 1
                and cam.width * cam.height >= COARSE_MIN_MPX * 1e6)
            else None)
        self.angle_tol_rad = math.radians(o.angle_tol_deg)
        check_options(o)
        self.extent = SiteExtent.from_site(site)
        if o.assume_heading_deg is not None and not math.isfinite(o.assume_heading_deg):
            raise ConfigError(None, "options.assume_heading_deg",
                              f"expected a finite heading in degrees, found "
                              f"{o.assume_heading_deg!r}")
        self._ctx = LabelContext(
            self.setup, cam, self.angle_tol_rad, self.match_tol_m,
            self.detector.min_length_px, across_seams=across_seams(site),
            mirror_y_m=mirror_line(self.setup), square_grid=square_grid(site),
            assume_heading_rad=(None if o.assume_heading_deg is None
                                else math.radians(o.assume_heading_deg)))
        self.lines_track = (LineTracker(self.setup, cam, o.window_px) if o.window_search
                            else None)
        self._chord_fit = None if self.lines_track is None else ChordFit(
            self.setup, self.angle_tol_rad, o.inlier_px, o.gn_iterations,
            self.lines_track.reach(), self._segment_times)
        self._tracked_fixes = 0  # tracked fixes since the last global search
        self._ignore = IgnoreRegions.of(rig, site)

    def forget(self) -> None:
        """See :meth:`Estimator.forget`: the tracked-fix counter."""
        self._tracked_fixes = 0

    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        """Estimate ``(y, yaw)`` of the vehicle from a checked frame (see
        :meth:`Estimator.estimate`); ``prior`` chooses among the 90/180 deg and
        line-shift hypotheses when the frame alone cannot. Failure reasons besides the
        frame check's: ``too_few_lines``, ``no_ceiling_lines``, ``no_association``,
        ``ambiguous``."""
        # with a rolling shutter, only a prior with a velocity (track.window_applies)
        if self.lines_track is not None and window_applies(self.options.readout_ms, prior):
            fast = self._tracked(grey, t_ns, prior, t0)
            if fast is not None:
                return fast
        if self.coarse_detector is not None:
            out = self._global(grey, t_ns, prior, t0, "coarse")
            if (out and out.quality >= COARSE_MIN_QUALITY) or turned_twins(out):
                return out
            return self._global(grey, t_ns, prior, t0, "fallback")
        return self._global(grey, t_ns, prior, t0, "full")

    def _global(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None, t0: float,
                search: str) -> Estimate:
        """The global path: the frame's segments (``search`` ``coarse``: found on the
        frame decimated by :data:`COARSE_FACTOR`, refitted over profiles
        :data:`COARSE_HALF_WIDTH_PX` wide; ``full``: at the working resolution, and
        ``fallback`` the same after a coarse search that gave no pose of quality
        :data:`COARSE_MIN_QUALITY`; :func:`~.frame.frame_segments`), outside the
        ignore regions, to the estimate (:meth:`_from_segments`)."""
        o = self.options
        coarse = search == "coarse"
        segs, len_px, pol, fit_rms = frame_segments(
            grey, self.rig.camera, self.coarse_detector if coarse else self.detector,
            o.max_segments, o.refine, o.edge_fit, COARSE_HALF_WIDTH_PX if coarse else None)
        keep = None if self._ignore is None else self._ignore.keep_segments(segs, prior)
        if keep is not None:        # SPEC §2: nothing inside an ignore region is used
            segs, len_px, pol, fit_rms = segs[keep], len_px[keep], pol[keep], fit_rms[keep]
        return self._from_segments(segs, len_px, t_ns, prior, fit_rms, pol, t0, search)

    def _tracked(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate,
                 t0: float) -> Estimate | None:
        """The fix from edge searches across the lines predicted by ``prior``
        (:mod:`~.track`), refined and checked as the global path's (:meth:`_pose`),
        with the twins the global path would list (:func:`fit_twins`: a fix with
        twins is ``Provenance.PRIOR``, the prior chose it), or ``None``: the searches
        or the check failed, a twin explains the frame better, the fix lies outside
        the prior's region (a kidnap) or a twin inside it, or a global search is due."""
        o, st = self.options, self.setup
        if o.window_full_every > 0 and self._tracked_fixes >= o.window_full_every:
            self._tracked_fixes = 0
            return None
        yaw = prior.yaw_rad
        psi = yaw + st.pan_rad
        cy = float(prior.y_m) + math.sin(yaw) * st.t_vc[0] + math.cos(yaw) * st.t_vc[1]
        # a fit that moved the lines from where they were searched was measured off
        # centre (the locator's error depends on the edge's offset from the profile's
        # middle, alike on every chord): measured again about itself (REMEASURE_PX;
        # bench_paired, priors 1 and 3 cm off: lateral p95 0.59 and 7.5 mm before,
        # 0.18 and 0.19 mm after, the global path's 0.27). The first fit only says
        # where (:meth:`~.track.ChordFit.first`); the frame is fitted on the chords
        # that count, always from a full search (the first reads a quarter of its
        # profiles: track.FIRST_ALONG, FIRST_STRIDE).
        rates = self._rates(prior)
        if rates is None and self._ignore is None:      # all of it in one compiled call
            out = window_pose(self, grey, t_ns, psi, cy, t0)
        else:
            out = searched_pose(self, grey, t_ns, prior, psi, cy, rates, t0)
        # outside the prior's region (a kidnap), or a twin inside it (estimators/prior.py)
        if out and prior_choice(prior, [(None, h.y_m, h.yaw_rad, None)
                                        for h in out.hypotheses or (out,)]) != 0:
            out = None
        if not out:                 # not found, or the model check failed: go global
            self._tracked_fixes = 0
            return None
        self._tracked_fixes += 1
        return out

    def _window_chords(self, grey: np.ndarray, psi: float, cy: float,
                       prior: PoseEstimate, first: bool = False) -> LineMeasurement | None:
        """The chords located across the lines predicted for camera pan ``psi`` and
        camera y ``cy`` (:meth:`~.track.LineTracker.measure`; ``first``: the frame's
        first search), outside the ignore regions; None: fewer than two site lines
        found."""
        return without_ignored(self.lines_track.measure(grey, psi, cy, first), self._ignore,
                               prior)

    def estimate_segments(self, segs_px: np.ndarray, t_ns: int,
                          prior: PoseEstimate | None = None,
                          fit_rms: np.ndarray | None = None,
                          t0: float | None = None,
                          polarity: np.ndarray | None = None) -> Estimate:
        """The estimate from segments ``(N, 4)`` in pixels (already detected); only
        their endpoints are undistorted. ``polarity`` ``(N,)``: as
        :func:`~ceilkit.runtime.features.lines.edge_polarity` (None: unknown)."""
        t0 = time.perf_counter() if t0 is None else t0
        segs, len_px, pol = undistorted(self.rig.camera, segs_px, polarity)
        return self._from_segments(segs, len_px, int(t_ns), prior, fit_rms, pol, t0,
                                   "segments")

    def _from_segments(self, segs: np.ndarray, len_px: np.ndarray, t_ns: int,
                       prior: PoseEstimate | None, fit_rms: np.ndarray | None,
                       pol: np.ndarray, t0: float, search: str) -> Estimate:
        """The estimate from undistorted normalized segments ``(N, 4)``, their pixel
        lengths ``(N,)`` and polarities ``(N,)``; ``search`` names where the segments
        came from (the ``search`` diagnostic: ``coarse``, ``full``, ``fallback``,
        ``segments``), on failures too."""
        n_seg = segs.shape[0]
        fit_rms = np.zeros(n_seg) if fit_rms is None else fit_rms
        if n_seg < 2:
            return self.fail(t_ns, "too_few_lines", f"{n_seg} line segments found",
                             n_segments=n_seg, search=search)
        fr = frame_lines(segs, pol, self.setup, self.angle_tol_rad, self.options.inlier_px)
        qxy = np.hypot(fr.q[:, 0], fr.q[:, 1])
        pans = dominant_pans(fr.q, len_px * np.minimum(1.0, qxy / HORIZONTAL_NORMAL))
        if not pans:
            return self.fail(t_ns, "no_ceiling_lines", "no dominant ceiling direction",
                             n_segments=n_seg, segments_n=segs, search=search)
        best = best_labeling(pans, fr, prior, self._ctx)
        if best is None:
            return self.fail(t_ns, "too_few_lines",
                             "fewer than two forward ceiling lines could be associated",
                             n_segments=n_seg, segments_n=segs, search=search)
        if isinstance(best, Unresolved):
            hyps = twin_hypotheses(self.setup, self.match_tol_m, best.twins, None)
            return self.fail(t_ns, best.reason, best.detail, hypotheses=hyps,
                             complete=complete_twins(best.twins),
                             n_segments=n_seg, segments_n=segs, search=search)
        return self._pose(t_ns, self._fit_labeling(fr, best, prior), fit_rms, t0, search)

    def _rates(self, prior: PoseEstimate | None) -> RowRates | None:
        """A rolling shutter's rates (:func:`~ceilkit.runtime.estimators.rows.row_motion`
        as :class:`~.refine.RowRates`), or None (a global shutter)."""
        motion = row_motion(self.options, prior)
        if motion is None:
            return None
        (_, vy, w), (_, s_v, s_w) = motion
        yaw = prior.yaw_rad if prior is not None else 0.0
        # the camera's y speed adds the turn's sweep of the mount offset; its sigma too
        t_vx = abs(camera_y_speed(yaw, 0.0, 1.0, self.setup))
        return RowRates(w, camera_y_speed(yaw, vy, w, self.setup), s_w,
                        math.hypot(s_v, t_vx * s_w))

    def _fit_labeling(self, fr: FrameLines, lab: Labeling, prior: PoseEstimate | None
                      ) -> FrameFit:
        """The joint fit (:func:`~.refine.joint_fit`) of a labeled frame on the matched
        forward segments that lie on the site's ceiling lines
        (:func:`~.consensus.consensus_fit`: a pipe or a cable tray matched by the 1-D
        association is left out; all of them with ``consensus`` off)."""
        o = self.options
        rates = self._rates(prior)
        tau = self._segment_times(fr, rates)
        if not o.consensus:
            gd = gn_inputs(fr, lab.along, lab.across, lab.assign, self.setup, tau)
            return FrameFit(fr, lab, gd, joint_fit(gd, lab.psi_rad, lab.camera_y_m,
                                                   self.setup, o.gn_iterations, rates))
        return consensus_fit(fr, lab, self.setup, o.inlier_px, o.gn_iterations, rates, tau)

    def _segment_times(self, fr: FrameLines, rates: RowRates | None
                       ) -> np.ndarray | None:
        """The row times ``(N, 2)`` (s) of the segments' endpoints with a rolling shutter
        (``rates`` not None), else None."""
        if rates is None:
            return None
        v_px = self.rig.camera.distort(fr.segs.reshape(-1, 2))[:, 1].reshape(-1, 2)
        return row_times_s(v_px, self.rig.camera.height, self.options.readout_ms / 1e3)

    def _pose(self, t_ns: int, ff: FrameFit, fit_rms: np.ndarray, t0: float,
              search: str) -> Estimate:
        """The pose, its quality and diagnostics from the fitted frame ``ff``, or the
        Failure of the first model check it does not pass (:func:`model_failure`);
        ``fit_rms (N,)``: each segment's edge-fit scatter (px); ``search``: the
        ``search`` diagnostic (``window`` on the tracked path). The check itself is
        :meth:`_checked` (the window path's :func:`window_pose` calls it with the same
        numbers from its compiled call)."""
        fr, best, gd = ff.lines, ff.labeling, ff.gd
        vl = vanishing_line_check(fr.lines, fr.len_n, best.along, best.across,
                                  self.setup.R_level_cam)
        counts = labeled_counts(fr, best.along, best.across, best.assign, fit_rms)
        groups = np.concatenate([gd.y, 1e9 + np.arange(gd.p0.size)])
        return self._checked(t_ns, fr.segs, best, ff.fit, (groups, gd.n_a), (vl, counts), t0,
                             search)

    def _checked(self, t_ns: int, segs: np.ndarray, best: Labeling, fit: PanOffsetFit,
                 rows: tuple[np.ndarray, int], checks: tuple, t0: float, search: str
                 ) -> Estimate:
        """:meth:`_pose` of its numbers: the frame's segments ``segs (N, 4)``, their
        labeling ``best``, the fit, its rows' systematic-error groups and along rows
        ``rows`` (the misfit's ``groups``, :class:`~.refine.GNInputs`' ``n_a``) and
        ``checks``, the vanishing line's dict and the counts."""
        groups, n_a = rows
        vl, (n_along, n_across, n_steps, n_thin, fit_rms_px, span) = checks
        yaw, y_m, cov = vehicle_pose(fit, self.setup)
        mf = misfit(fit.residuals_px, self.options.noise_px, 2, groups,
                    self.options.misfit_alpha, huber_px=1.0)
        quality = (min(1.0, best.n_lines / 3.0) * min(1.0, n_a / 4.0)
                   / (1.0 + (fit.rms_px / 1.5) ** 2))
        if best.ambiguous:
            quality *= 0.5
        diag = {
            "n_segments": segs.shape[0],
            "n_along": n_along,
            "n_across": n_across,
            "n_lines_matched": int(best.n_lines),
            "n_off_ceiling": int(best.n_off_ceiling),
            "n_steps": n_steps,
            "n_thin": n_thin,
            "rms_px": fit.rms_px,
            "segment_fit_rms_px": fit_rms_px,
            "psi_deg": math.degrees(fit.psi_rad),
            "camera_y_m": fit.camera_y_m,
            "ambiguous": bool(best.ambiguous),
            "hypothesis": best.how,
            "search": search,
            "heading_change_deg": math.degrees(wrap_pi(fit.psi_rad - best.psi_rad)),
            "spread": span * self.setup.f_px / self.rig.camera.width,
            **vl, **mf.diagnostics(),
            # for overlays (references, no copies): the undistorted normalized segments,
            # the two families and the site line of each forward segment (-1: none)
            "segments_n": segs, "along": best.along, "across": best.across,
            "assign": best.assign,
            "ms": elapsed_ms(t0),
        }
        failed = model_failure(self.options, self.extent, mf, diag, y_m)
        if failed is not None:
            return self.fail(t_ns, *failed, **diag)
        if mf.inflation != 1.0:
            cov = cov * mf.inflation
        twins = twin_hypotheses(self.setup, self.match_tol_m, best.twins, cov)
        # a pose its prior chose among twins is the prior's, on either path
        provenance = (Provenance.PRIOR if twins or best.ambiguous or "stated" in best.how
                      else Provenance.WINDOW if search == "window" else Provenance.GLOBAL)
        if twins:
            twins = (Hypothesis(None, y_m, yaw, cov, twins[0].weight, "chosen"),) + twins
        return PoseEstimate(int(t_ns), self.name, None, y_m, yaw,
                            min(max(float(quality), 0.0), 1.0), y_m - self.setup.axis_y_m,
                            cov, diag, provenance=provenance, hypotheses=twins,
                            hypotheses_complete=complete_twins(best.twins))


def window_pose(est: CorridorEstimator, grey: np.ndarray, t_ns: int, psi: float, cy: float,
                t0: float) -> Estimate | None:
    """``est``'s window fix about camera pan ``psi`` and y ``cy`` with a global shutter
    and no ignore region, from one compiled call (:meth:`~.track.LineTracker.fix`),
    checked (:meth:`CorridorEstimator._checked`) with its twins
    (:func:`with_quarter_turns`), or None: no fix kept, or the global path decides the
    frame. The numbers of :func:`searched_pose` without its objects: no frame arrays,
    fit inputs or window fit are made, only the labeling the check reads."""
    fx = est.lines_track.fix(grey, psi, cy, est._chord_fit.kernel, REMEASURE_PX,
                             est._ctx.mirror_y_m)
    fit = None if fx is None else est._chord_fit.kept(fx.fit, fx.psi, fx.cy)
    if fit is None:
        return None
    twins = with_quarter_turns(est._ctx, fit.psi_rad, labeling_twins(*fx.twins))
    if twins is None:
        return None
    n = fx.segs_n.shape[0]
    lab = Labeling((fx.n_lines, float(n)), fx.psi, fx.cy, np.ones(n, bool), np.zeros(n, bool),
                   fx.line, fx.n_lines, any(t.label == "shift" for t in twins), "window",
                   twins=twins)
    groups = np.concatenate([fx.y, 1e9 + np.arange(fx.n_b)])
    return est._checked(t_ns, arr(fx.segs_n, np.float64), lab, fit, (groups, fx.n_a),
                        (vanishing_line_dict(*fx.vl), fx.counts), t0, "window")


def searched_pose(est: CorridorEstimator, grey: np.ndarray, t_ns: int, prior: PoseEstimate,
                  psi: float, cy: float, rates: RowRates | None, t0: float
                  ) -> Estimate | None:
    """``est``'s window fix about camera pan ``psi`` and y ``cy`` from the calls one by
    one (:func:`searched`: with the ignore regions or a rolling shutter's ``rates``),
    checked (:meth:`CorridorEstimator._pose`) with its twins (:func:`fit_twins`), or
    None."""
    found = searched(est, grey, psi, cy, prior, rates)
    twins = None if found is None else fit_twins(est.lines_track, est._ctx, grey, found)
    if twins is None:
        return None
    lab = dataclasses.replace(found.frame.labeling, twins=twins,
                              ambiguous=any(t.label == "shift" for t in twins))
    return est._pose(t_ns, dataclasses.replace(found.frame, labeling=lab),
                     found.chords.rms_px, t0, "window")


def searched(est: CorridorEstimator, grey: np.ndarray, psi: float, cy: float,
             prior: PoseEstimate, rates: RowRates | None) -> WindowFit | None:
    """The window fit about camera pan ``psi`` and y ``cy`` (``est``'s
    :meth:`~CorridorEstimator._tracked` searches and fits, one by one: with the ignore
    regions or a rolling shutter's ``rates``; :meth:`~.track.LineTracker.window`
    otherwise), or None."""
    fitter = est._chord_fit
    m = est._window_chords(grey, psi, cy, prior, first=True)
    first = None if m is None else fitter.first(m, psi, cy, rates)
    if first is None:           # the quarter missed (a prior pixels off): a full one
        m = est._window_chords(grey, psi, cy, prior)
        first = None if m is None else fitter.first(m, psi, cy, rates)
    if first is None:
        return None
    if est.lines_track.shift_px(first[0] - psi, first[1] - cy) <= REMEASURE_PX:
        first = (psi, cy)
    m = est._window_chords(grey, first[0], first[1], prior)
    return None if m is None else fitter.frame(m, first[0], first[1], rates)


def fit_twins(lt: LineTracker, ctx: LabelContext, grey: np.ndarray, found: WindowFit
              ) -> tuple[LabelingTwin, ...] | None:
    """The twins of a window fit ``found`` (:meth:`~.track.ChordFit.frame`) the
    global path would list: the lateral shifts and half turns the frame supports as
    well (:func:`~.track.window_twins`) and, where the site's ``lines_across`` are
    seams (``ctx.across_seams``), both quarter turns (their camera y not measured:
    ``exact`` False, so the list is not complete); None when the global path must
    decide the frame."""
    fit = found.frame.fit
    twins = window_twins(lt, grey, found.chords, fit.psi_rad, fit.camera_y_m, ctx.mirror_y_m)
    return with_quarter_turns(ctx, fit.psi_rad, twins)


def with_quarter_turns(ctx: LabelContext, psi_rad: float,
                       twins: tuple[LabelingTwin, ...] | None
                       ) -> tuple[LabelingTwin, ...] | None:
    """A window fix's ``twins`` (:func:`~.track.window_twins`; None: the global path
    decides) with both quarter turns of its camera pan ``psi_rad`` where the site's
    ``lines_across`` are seams (``ctx.across_seams``; :func:`fit_twins`)."""
    if twins is None or not ctx.across_seams:
        return twins
    return twins + tuple(LabelingTwin(wrap_pi(psi_rad + d), math.nan, "quarter_turn",
                                      False) for d in (-0.5 * math.pi, 0.5 * math.pi))


def twin_hypotheses(setup: CorridorSetup, match_tol_m: float, twins: tuple[LabelingTwin, ...],
                    cov: np.ndarray | None) -> tuple[Hypothesis, ...]:
    """The vehicle poses of labelings ``twins`` (camera pan and y in W), each with
    ``cov`` (the chosen fit's; None, an unfitted frame: the association's own sigma,
    a third of the 1-D gate ``match_tol_m``, as its scores take an offset's misfit),
    weighted alike (the frame supports them alike, the chosen one too). With the
    whole gate as the sigma (before, 2026-12-07) a twin 0.19 m off a corridor track's
    prediction (1σ 4 cm) still lay inside its region: the frame after a kidnap did not
    contradict the track, and the prior then chose that twin (29 poses wrong on
    ``bench_heldout_lines.py``'s tiles0 kidnap)."""
    if not twins:
        return ()
    st = setup
    if cov is None:
        cov = np.diag([np.inf, (match_tol_m / 3.0) ** 2, math.radians(1.0) ** 2])
    w = 1.0 / (len(twins) + (0 if twins[0].label == "chosen" else 1))
    out = []
    # the mount's offset as floats once (the same IEEE products as numpy's scalars)
    pan, tx, ty = float(st.pan_rad), float(st.t_vc[0]), float(st.t_vc[1])
    for t in twins:
        yaw = wrap_pi(t.psi_rad - pan)
        y = t.camera_y_m - (math.sin(yaw) * tx + math.cos(yaw) * ty)
        if not math.isfinite(y):        # not measured (a window fix's quarter turn)
            c = np.array(cov, float)
            c[1, :] = c[:, 1] = np.inf
            out.append(Hypothesis(None, None, float(yaw), c, w, t.label))
            continue
        out.append(Hypothesis(None, float(y), float(yaw), cov, w, t.label))
    return tuple(out)


TURN_LABELS = ("half_turn", "quarter_turn")
"""The twins a turn of the ceiling makes (:func:`turned_twins`)."""


def turned_twins(out: Estimate) -> bool:
    """Whether ``out`` is ``ambiguous`` between turns of the pose (a half or a quarter
    turn): the ceiling in view looks the same turned, which more segments of the same
    lines do not change. The coarse search's segments are refitted on the full frame
    (the edge fit): its full-resolution search is not run for such a frame (on 240
    such frames of six simulated drives it found turn twins again on every one and a
    valid pose on none, at about three times the coarse search's cost on a tile grid:
    docs/methods/corridor.md)."""
    return (not out and out.reason == AMBIGUOUS
            and any(h.label in TURN_LABELS for h in out.hypotheses))


def complete_twins(twins: tuple[LabelingTwin, ...]) -> bool:
    """Whether the labelings ``twins`` are every pose the frame supports: the half and
    quarter turns are each examined, and every lateral shift of each that the frame's
    lines fit as well (a tile grid has as many as it has seams in view:
    :func:`~.hypotheses.alike_shifts`) is listed."""
    return all(t.exact for t in twins)


def across_seams(site: Site) -> bool:
    """Whether the site's ``lines_across`` include seams (lines from wall to wall, as a
    tile grid's), not only the ends of its lamps: then the families can swap under a
    quarter turn with nothing in the frame's ceiling lengths to tell."""
    across = site.corridor.lines_across
    if across is None:
        return False
    s = across.spacing_m
    for row in site.lamps:
        # every grid line a lamp end: the lamps are one spacing long, one spacing apart
        start = row.x_m - 0.5 * row.length_m
        if (abs(math.remainder(start - across.first_m, s)) < 1e-6
                and abs(row.length_m - s) < 1e-6
                and (row.count == 1 or abs(row.pitch_m - row.length_m - s) < 1e-6)):
            return False
    return True


def square_grid(site: Site, tol_m: float = 1e-6) -> bool:
    """Whether the site is a square tile grid: ``lines_across`` are seams
    (:func:`across_seams`), no lamps, and ``lines_along`` (two or more) are one
    ``lines_across`` spacing apart. A quarter turn about a tile corner then maps the
    grid onto itself (within its extent): the frame's families can swap with nothing
    on the ceiling to tell, however many lines of each the frame's aspect shows."""
    c = site.corridor
    if c.lines_across is None or site.lamps or len(c.lines_along_m) < 2 \
            or not across_seams(site):
        return False
    d = np.diff(np.sort(np.asarray(c.lines_along_m, float)))
    return bool(np.all(np.abs(d - c.lines_across.spacing_m) <= tol_m))


def model_failure(o: CorridorOptions, extent: SiteExtent, mf: Misfit,
                  diag: Mapping[str, Any], y_m: float) -> tuple[str, str] | None:
    """Whether the model explains the frame (docs/methods/honesty.md): ``(reason,
    detail)`` of the first check that fails, in this order: ``misfit`` (chi-square of
    the residuals against ``noise_px``), ``vanishing_line`` (the free vanishing points
    against the calibrated mount), ``heading_disagrees`` (refined against
    vanishing-point heading), ``weak_geometry`` (site lines matched, spread),
    ``outside_site``; None when all pass."""
    if not mf.passed:
        return MISFIT, mf.detail()
    for key, what, most in (
            ("vp_along_elevation_deg", "the forward vanishing point is",
             o.max_vp_elevation_deg),
            ("vanishing_line_residual_deg", "the vanishing line is",
             o.max_vanishing_line_deg)):
        v = diag[key]
        if math.isfinite(v) and abs(v) > most:
            return VANISHING_LINE, (f"{what} {abs(v):.1f} deg off the calibrated mount's "
                                    f"vanishing line (at most {most:g}): the mount's tilt "
                                    f"and swing are wrong, or the lines are not the site's")
    change = abs(diag["heading_change_deg"])
    if change > o.max_heading_change_deg:
        return HEADING_DISAGREES, (f"the refinement moved the heading {change:.1f} deg from "
                                   f"the vanishing point's (at most "
                                   f"{o.max_heading_change_deg:g})")
    if diag["n_lines_matched"] < o.min_lines or diag["spread"] < o.min_spread:
        off = diag["n_off_ceiling"]
        return WEAK_GEOMETRY, (f"{diag['n_lines_matched']} site lines matched (at least "
                               f"{o.min_lines}), spanning {diag['spread']:.2f} of the image "
                               f"width (at least {o.min_spread:g})"
                               + (f"; {off} forward segments off the site's ceiling lines "
                                  f"(pipes, trays: lines at another height?)" if off else ""))
    out = outside_site(extent, None, y_m, o.site_margin_m)
    return None if out is None else (OUTSIDE_SITE, out)


def _median_finite(a: np.ndarray) -> float:
    """The median of the finite values of ``a`` (NaN if none); as ``np.median``, without
    its overhead on a few values (the reading of :func:`.frame.counts_core`'s)."""
    v = np.sort(a[np.isfinite(a)])
    m = v.size // 2
    if v.size == 0:
        return float("nan")
    return float(v[m]) if v.size % 2 else float(0.5 * (v[m - 1] + v[m]))
