"""Global localization from ceiling spot lights: the estimator (facade of the stages).

One frame of spot lights gives the vehicle's full pose ``(x, y, yaw)`` in W with no
prior (after Roh et al., ASCC 2011; see ``docs/methods/lights.md``).

Convention (SPEC §1): ``X_W = Rz(yaw) X_V + (x, y, 0)``; the camera is mounted by
``X_V = R_vehicle_cam X_C + t_vehicle_cam``, so ``R_world_cam = Rz(yaw) R_vehicle_cam``.
Every light centre lies on the ceiling plane ``z = H`` (``site.ceiling_height_m``).

Stages per frame:

1. ``observe`` (:class:`~.observe.SpotObserver`): the detector's spots, checked
   against a light of the known diameter at their place, as ceiling points in V
   (:func:`~.rays.ceiling_points`) with their pixel Jacobians.
2. ``matching`` (:class:`~.matching.PatternMatcher`): with a trusted prior, a local
   association; otherwise pair-distance voting for poses, verified and ranked, with
   every twin of the best (the pose moved by each of the map's symmetries: a grid's
   cells, its half turn). When another pose is explained nearly as well (a regular
   grid), the frame is ``ambiguous`` and carries the poses as ``hypotheses``; a pose
   the prior chose is ``Provenance.PRIOR`` and carries the twins it ruled out.
3. ``refine`` (:func:`~.refine.refine_pose_ceiling`): Gauss-Newton on the pixel
   residuals, one outlier pass; the covariance is ``s² (JᵀJ)⁻¹``, in a frame with
   more grey levels ``s²`` counted without the radial shift the centroids share and
   what that shift moves the pose by added (:func:`~.refine.pattern_cover`). In a two-level
   frame (0/255) a radial shift of every centroid is a fourth unknown
   (:func:`frame_shifts`, :func:`~.refine.with_shifts`), its uncertainty in the
   covariance, which also covers what leaving any one lamp out moves the pose by
   (:func:`~.refine.spot_jackknife`: each lamp's own threshold bias); a lamp whose
   spot reaches further beyond its rectangle than the frame's others (a bloom, a
   fixture merged with it) weighs less (:func:`spot_weights`).
4. quality (:func:`pose_quality`): lights, residuals, lights missed, the margin.

Example::

    est = LightsEstimator(rig, site, LightsOptions(gate_m=0.1)).estimate(grey, t_ns)
    if est:
        print(est.x_m, est.y_m, est.yaw_deg, est.quality)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import (
    AMBIGUOUS,
    Estimate,
    Estimator,
    EstimatorOptions,
    Hypothesis,
    PoseEstimate,
    Provenance,
    elapsed_ms,
)
from ceilkit.runtime.estimators.honesty import (
    DEFAULT_ALPHA,
    MISFIT,
    OUTSIDE_SITE,
    SiteExtent,
    check_options,
    misfit_sum,
    outside_site,
)
from ceilkit.runtime.estimators.lights.matching import (
    Candidate,
    PatternMatcher,
)
from ceilkit.runtime.estimators.lights.observe import (
    BLOOM_CENTRE_SHARE,
    DISC_AREA_MAX,
    RECT_AREA,
    RECT_CUT_REACH,
    BloomPool,
    Observation,
    SpotObserver,
    VisibilityTable,
    bloomed_area,
    fitted_lamp_window,
    fitted_light_bound,
    fitted_spot_params,
)
from ceilkit.runtime.estimators.lights.rays import max_pair_m, nadir_px, view_mask
from ceilkit.runtime.estimators.lights.refine import (
    NoisePool,
    RefinedPose,
    map_cov,
    pattern_cover,
    refine_pose_ceiling,
    with_shifts,
)
from ceilkit.runtime.estimators.lights.track import WindowFix, WindowTracker
from ceilkit.runtime.estimators.lights.twins import (
    MAX_HYPOTHESES,
    MAX_TWIN_CHECKS,
    DetectionRates,
    TwinJudge,
)
from ceilkit.runtime.estimators.prior import (
    allows,
    narrower_than,
    prior_choice,
    prior_distance,
)
from ceilkit.runtime.estimators.rows import ShutterOptions, row_motion
from ceilkit.runtime.features.spots import SpotParams
from ceilkit.runtime.features.working import WORKING_MPX, working_factor
from ceilkit.runtime.geometry.fits import short_median
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.geometry.shutter import row_times_s

NAME = "lights"
DEFAULT_LIGHT_DIAMETER_M = 0.16
"""A light's visible diameter when neither the options nor the site give one."""
TRACK_MIN_SHARE = 0.6  # a prior is trusted when this share of the spots match near it
PRIOR_RESOLVE = (1.0, math.radians(20.0))  # (m, rad): a rival this near the prior wins
EXCESS_SCALE_PX = 1.0
"""A lamp reaching this much (px) further beyond its rectangle than the frame's median
lamp has its residual weighed 1/sqrt(2) (:func:`spot_weights`); measured 0.5, 1 and 2
(docs/methods/lights.md §4)."""
SPOT_STAGES = ("windowed", "full")  # the spot stages (LightsOptions.spot_stage)
OUTLIER_MEDIANS = 4.0  # a residual this many times the median (and > max_residual_px) is out
RECT_MIN_AXIS_RATIO = 0.03  # the detector's shape bound with rectangular lights


PROVENANCE = MappingProxyType({
    "global": Provenance.GLOBAL,          # the frame alone singled the pose out
    "prior_resolved": Provenance.PRIOR,   # the prior chose among equally good poses
    "about_prior": Provenance.PRIOR,      # a local association about the prior
    "window": Provenance.WINDOW,          # the window fix about the prior
})
"""The typed provenance of each of the method's ``mode`` diagnostics."""


@dataclass(frozen=True)
class LightsOptions(ShutterOptions):
    """What a user may set for ``lights`` (``--option KEY=VALUE``).

    Attributes:
        min_contrast: the shared blank-frame check (0: off; a blank frame is then
            ``no_lights``, as the detector finds nothing).
        light_diameter_m: a light's visible diameter; predicts each spot's area and
            shape at its place in the image (0 turns these checks off). ``None``: the
            site's ``light_diameter``, else :data:`DEFAULT_LIGHT_DIAMETER_M`.
        gate_m: largest ceiling distance of a matched light from its map position.
        ambiguity_margin: a different pose whose score is within this of the best makes
            the frame ``ambiguous`` (score: inliers - 0.5 x lights missed).
        min_inliers: fewest matched lights for a pose without a prior (>= 3).
        max_residual_px: a matched light with a larger reprojection residual is dropped.
        spot_params: :class:`~ceilkit.runtime.features.spots.SpotParams` (defaults if ``None``).
        prior_gate_m: association gate around a prior pose (default: 0.4 x the closest
            light spacing, at most 1 m).
        max_view_angle_deg: spots seen further than this from the vertical are ignored
            (tiny, poorly resolved, and the edge of a fisheye image circle).
        max_spots: examine at most this many candidate regions, nearest the nadir first.
        noise_px: the expected standard deviation of a light's centroid, per image axis
            (px): the chi-square test of the refined fit (``misfit``) is against it.
        misfit_alpha: the chi-square test's false-alarm rate on a fit that is noise.
        site_margin_m: the pose may lie at most this far outside the site's extent
            (the lights' bounding box; ``outside_site``).
        window_search: with a prior, look for the lights only in windows around their
            predicted pixels (:mod:`~.track`); the global path runs when the window
            check fails and every ``window_full_every``-th window fix. On by default
            (issue 38: ``benchmarks/bench_paired.py``). (Formerly ``track``.)
        window_px: how far (px) a light may lie from its predicted pixel. (Formerly
            ``track_window_px``.)
        window_full_every: a global search after this many window fixes (0: only when
            the window check fails). (Formerly ``track_full_every``.)
        working_mpx: a frame larger than this (megapixels) is searched for spots
            decimated by an integer factor and its centroids refined at full resolution
            (:mod:`~ceilkit.runtime.features.working`; ``spot_params`` are then in
            pixels of the decimated frame); 0: always at full resolution.
        readout_ms, rate_sigma_dps, speed_sigma_mps, unknown_rate_dps,
            unknown_speed_mps: (inherited) a rolling shutter
            (:class:`~ceilkit.runtime.estimators.rows.ShutterOptions`): each light is
            predicted from the pose at its spot's row time, moved by the prior's
            velocity; what the velocity's uncertainty does to the pose is added to the
            covariance (the global and prior-associated paths; the window tracker
            does not model it, so with ``readout_ms`` > 0 ``window_search`` is not used).
        spot_stage: at working resolution, ``full`` (the Niblack mask and region
            statistics of the whole frame) or ``windowed`` (the mask and regions of the
            frame decimated by 2, each region's spot read at full resolution in a
            window around it: :func:`~ceilkit.runtime.features.windows.detect_spots_windowed`).
        twins: without a prior, look for every placement of the best pose's spots on
            the map's lights (other cells of a grid, quarter and half turns) and score
            them alike (:meth:`LightsEstimator._candidate`); off: only the poses the
            pair-length vote verifies (faster on a large irregular map).
    """

    min_contrast: float = 0.0
    light_diameter_m: float | None = None
    gate_m: float = 0.1
    ambiguity_margin: float = 1.0
    min_inliers: int = 3
    max_residual_px: float = 3.0
    spot_params: SpotParams | None = None
    prior_gate_m: float | None = None
    max_view_angle_deg: float = 75.0
    max_spots: int = 12
    noise_px: float = 1.0
    misfit_alpha: float = DEFAULT_ALPHA
    site_margin_m: float = 1.5
    window_search: bool = True
    window_px: float = 10.0
    window_full_every: int = 30
    working_mpx: float = WORKING_MPX
    spot_stage: str = "full"
    twins: bool = True

    ALIASES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "track": "window_search", "track_window_px": "window_px",
        "track_full_every": "window_full_every"})


def light_diameter_m(options: LightsOptions, site: Site) -> float:
    """The diameter the spot checks assume: the option, else the site's, else
    :data:`DEFAULT_LIGHT_DIAMETER_M`."""
    if options.light_diameter_m is not None:
        return options.light_diameter_m
    if site.light_diameter_m is not None:
        return site.light_diameter_m
    return DEFAULT_LIGHT_DIAMETER_M


class LightsEstimator(Estimator):
    """Full vehicle pose from one frame of ceiling spot lights, with no prior.

    Args:
        rig: camera and mount (any tilt whose view reaches the ceiling).
        site: needs ``lights`` (and ``ceiling_height``).
        options: :class:`LightsOptions`, a mapping of them, or ``None``.

    Raises:
        ConfigError: no lights in the site, an impossible option, a ceiling below the camera.
    """

    name = NAME
    Options: ClassVar[type[EstimatorOptions]] = LightsOptions
    site_sections = ("lights",)

    def __init__(self, rig: Rig, site: Site,
                 options: LightsOptions | Mapping[str, Any] | None = None) -> None:
        if not site.has_lights:
            raise ConfigError(site.source, "lights",
                              "the lights method needs at least one light in the site map")
        super().__init__(rig, site, options)
        o = self.options
        check_rig_site(rig, site)
        diameter_m = light_diameter_m(o, site)
        if o.min_inliers < 3:
            raise ConfigError(None, "options.min_inliers", f"expected >= 3, found {o.min_inliers}")
        if o.gate_m <= 0 or diameter_m < 0:
            raise ConfigError(None, "options.gate_m",
                              "expected gate_m > 0 and light_diameter_m >= 0")
        check_options(o)
        if o.spot_stage not in SPOT_STAGES:
            raise ConfigError(None, "options.spot_stage",
                              f"expected one of {', '.join(SPOT_STAGES)}, found {o.spot_stage!r}")
        self.extent = SiteExtent.from_site(site)
        self.ceiling_height_m = site.ceiling_height_m
        self.site_ids, self.lights_w, self.spacing_m = map_lights(site)
        self.prior_gate_m = (o.prior_gate_m if o.prior_gate_m is not None
                             else max(o.gate_m, min(1.0, 0.4 * self.spacing_m)))
        self.valid_mask = view_mask(rig, math.radians(o.max_view_angle_deg))
        self.nadir_px = nadir_px(rig)
        # rectangular lights (the site's light_size), unless the option asks for discs
        self.light_size_m = (site.light_size_m if o.light_diameter_m is None else None)
        self.observer, self.visibility = observe_stages(
            rig, self.ceiling_height_m, self.lights_w, o, diameter_m, self.light_size_m,
            self.valid_mask, self.nadir_px, self.spacing_m)
        self.matcher = PatternMatcher(self.lights_w, o.gate_m,
                                      max_pair_m(rig, self.ceiling_height_m, o.gate_m),
                                      visible=self.visibility)
        # the map's rigid self-similarities (a grid's cells): every pose's twins
        self.judge = TwinJudge(self.lights_w, self.matcher, self.extent, o,
                               present_m(diameter_m, self.light_size_m, o.gate_m),
                               site.light_yaw_rad if self.light_size_m else None)
        # the window tracker reads discs: rectangular lights take the global path
        self.windows = None if not o.window_search or self.light_size_m else WindowTracker(
            rig, self.ceiling_height_m, self.lights_w, self.observer, self.visibility,
            o.window_px, (o.spot_params or SpotParams()).min_contrast,
            TRACK_MIN_SHARE, o.max_residual_px, OUTLIER_MEDIANS, self.prior_gate_m,
            PRIOR_RESOLVE[1])
        # the last fit's own [SSR, ν] in [2:] (refine.NoisePool); the run's window fixes,
        # pixel noise, blooms (observe.BloomPool), detection rates (twins): forget()
        self._noise = NoisePool().array()
        self.forget()

    def forget(self) -> None:  # Estimator.forget: the window counter, the pools, the rates
        self._window_fixes, self._pool, self._blooms = 0, NoisePool(), BloomPool()
        self._detect = DetectionRates()

    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        """The vehicle pose in W from a checked frame (see the module doc).

        Returns:
            :class:`PoseEstimate` (``lateral_m`` None) or a Failure with reason
            ``no_lights``, ``too_few_lights``, ``no_match``, ``ambiguous``, or a model
            check's (:meth:`checked`): ``misfit``, ``outside_site``.
        """
        # the window tracker models no rolling shutter (with readout_ms the global path
        # decides) and finds no twins (a prior that could hold one goes global too)
        if self.windows is not None and prior is not None and prior.x_m is not None \
                and prior.y_m is not None and self.options.readout_ms <= 0 \
                and narrower_than(prior, self.spacing_m):
            fast = self._tracked(grey, t_ns, prior, t0)
            if fast is not None:
                return fast
        obs = self.observer.observe(grey, self._blooms).outside(self.site, prior)  # §2 ignore
        self._blooms = self._blooms.added(obs.blooms_seen)
        obs = dataclasses.replace(obs, detect=self._detect) if self._detect.missed else obs
        diag = spot_diag(obs)
        short = too_few(len(obs.spots), self.options.min_inliers)
        if short is not None:
            return self.fail(t_ns, *short, **diag)
        found = self._candidate(obs, prior, t_ns, diag)
        if not isinstance(found, Chosen):
            return found
        cand, runner, mode, twins = found.best, found.runner_up, found.mode, found.twins
        if cand.present > cand.inliers:
            return self.fail(t_ns, "misfit", unmeasured(cand), **diag)
        pairs, x, y, yaw, cov, res = self._refine(obs, cand, prior)
        k = pairs.shape[0]
        min_k = 2 if mode == "about_prior" else self.options.min_inliers
        if k < min_k or not np.all(np.isfinite(cov)):
            return self.fail(t_ns, "no_match", f"only {k} lights fit after refinement",
                             **diag)
        rms = math.sqrt(float((res * res).sum()) / res.size)
        quality = pose_quality(k, rms, cand, runner, mode)
        site_pairs = np.column_stack([pairs[:, 0], self.site_ids[pairs[:, 1]]])
        diag.update({"inliers": k, "matched_lights": tuple(site_pairs[:, 1].tolist()),
                     "pairs": site_pairs,  # (spot index in spots_px, light index in the site)
                     "rms_px": rms, "mode": mode, "score": cand.score,
                     "runner_up_score": None if runner is None else runner.score,
                     "ms": elapsed_ms(t0)})
        out = self.checked(t_ns, x, y, yaw, quality, cov, res, diag)
        if isinstance(out, PoseEstimate):
            if pools(obs, self.options):
                self._pool = self._pool.added(self._noise[2:])
            self._detect = self._detect.added(*self.judge.detections(obs, cand))
        if twins and isinstance(out, PoseEstimate):
            # a prior-resolved pose: the published one first, then the twins it ruled out
            hyps = self._hypotheses(obs, [cand, *twins], prior, out.cov)
            first = Hypothesis(out.x_m, out.y_m, out.yaw_rad, out.cov, hyps[0].weight,
                               "published")
            out = dataclasses.replace(out, hypotheses=(first,) + hyps[1:],
                                      hypotheses_complete=found.complete)
        return out

    def checked(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float, quality: float,
                cov: np.ndarray, res_px: np.ndarray, diag: dict[str, Any]) -> Estimate:
        """The pose, once the model check passes (docs/methods/honesty.md), else the
        Failure of the first check that fails: ``misfit`` (the chi-square of the
        refined residual norms ``res_px (K,)`` against ``noise_px``; each norm split
        evenly over u and v gives the same statistic over the 2K residuals, 3 fitted:
        :func:`~ceilkit.runtime.estimators.honesty.misfit_sum`), ``outside_site``. A
        least-squares fit of independent residuals has an inflation of 1: a passing
        fit's covariance is the refinement's and the map's own error's (:func:`map_error`)."""
        o = self.options
        res = np.asarray(res_px, float)
        mf = misfit_sum(float(res @ res), 2 * res.size, o.noise_px, 3, o.misfit_alpha)
        diag.update(mf.diagnostics())
        if not mf.passed:
            return self.fail(t_ns, MISFIT, mf.detail(), **diag)
        out = outside_site(self.extent, x_m, y_m, o.site_margin_m)
        if out is not None:
            return self.fail(t_ns, OUTSIDE_SITE, out, **diag)
        cov = cov + map_error(self.site, diag["matched_lights"], x_m, y_m)
        return PoseEstimate(t_ns, NAME, x_m, y_m, yaw_rad, quality, None, cov, diag,
                            provenance=PROVENANCE[diag.get("mode", "global")])

    def _tracked(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate,
                 t0: float) -> PoseEstimate | None:
        """The window fix around ``prior`` (:mod:`~.track`), or ``None``: the window
        check or the model check (:meth:`checked`) failed, the fix lies outside the
        prior's region (a kidnap), or a global search is due
        (``window_full_every``)."""
        every = self.options.window_full_every
        if every > 0 and self._window_fixes >= every:
            self._window_fixes = 0
            return None
        fix = self.windows.observe(grey, float(prior.x_m), float(prior.y_m), prior.yaw_rad,
                                   self._pool)
        if fix is None or not allows(prior, (fix.x_m, fix.y_m, fix.yaw_rad, None)):
            self._window_fixes = 0
            return None
        self._window_fixes += 1
        k = fix.pairs.shape[0]
        rms = math.sqrt(float((fix.res_px * fix.res_px).sum()) / k)
        cand = Candidate(fix.x_m, fix.y_m, fix.yaw_rad, fix.pairs, float(k), 0.0,
                         fix.predicted - fix.found)
        quality = pose_quality(k, rms, cand, None, "about_prior")
        diag = window_diag(fix, self.site_ids, rms, elapsed_ms(t0))
        # the same model check as the global path; a window fix that fails it is not
        # published: the global search decides the frame
        out = self.checked(t_ns, fix.x_m, fix.y_m, fix.yaw_rad, quality, fix.cov,
                           fix.res_px, diag)
        if isinstance(out, PoseEstimate):
            self._pool = self._pool.added(fix.noise)
        return out if isinstance(out, PoseEstimate) else None

    def _candidate(self, obs: Observation, prior: PoseEstimate | None, t_ns: int,
                   diag: dict[str, Any]) -> Chosen | Estimate:
        """The pose a frame's association singles out (:class:`Chosen`), or its Failure.
        Its ``mode``: ``about_prior`` (a local association around a trusted prior:
        :meth:`_about_prior`), ``global`` or ``prior_resolved`` (the prior picked one of
        several equally good poses, ``twins`` the others).

        Without a prior the best pose must be singled out: every twin of it (the pose
        moved by each symmetry of the map, :class:`.twins.TwinJudge`, with the
        matcher's own candidates; those outside the site dropped, ``outside_site`` when
        only from outside is the frame explained best) is scored by the same evidence;
        one within ``ambiguity_margin`` of the best makes the frame ``ambiguous``, with
        the poses as hypotheses, and so do more twins than were checked. At least
        ``min_inliers`` of the best's spots must be strong (not near an edge)."""
        n = len(obs.spots)
        if prior is not None and prior.x_m is not None and prior.y_m is not None:
            tracked = self._about_prior(obs, prior, n)
            if tracked is not None:
                return tracked
        min_inliers = self.options.min_inliers
        if n < min_inliers:
            return self.fail(t_ns, "too_few_lights",
                             f"{n} lights found, a global fix needs {min_inliers}", **diag)
        cands = [self.judge.present(obs, c) for c in self.matcher.match(obs.q_v, obs.order)
                 if c.inliers >= min_inliers]
        diag["verified"] = len(cands)
        if not cands:
            return self.fail(t_ns, "no_match", f"{n} lights match no place of the map", **diag)
        weights = obs.weights()
        complete = False
        if self.options.twins:
            cands, complete = self.judge.ranked(obs, cands, weights)
            if not cands:
                return self.fail(t_ns, OUTSIDE_SITE, f"{n} lights fit the map best from "
                                 f"a pose outside the site", **diag)
        if obs.weak is not None:
            strong = int(np.count_nonzero(weights[cands[0].pairs[:, 0]] >= 1.0))
            if strong < min_inliers:
                return self.fail(t_ns, "no_match",
                                 f"the best pose fits {cands[0].inliers} lights, only "
                                 f"{strong} of them well inside the view (a global fix "
                                 f"needs {min_inliers})", hypotheses=() if prior is None
                                 else self._hypotheses(obs, cands, prior), **diag)
        best_e = self.judge.evidence(cands[0], weights)
        cand, mode = cands[0], "global"
        margin = self.options.ambiguity_margin
        rivals = [c for c in cands[1:] if self.judge.evidence(c, weights) >= best_e - margin]
        if not rivals and self.judge.searched and not complete and prior is None:
            # more twins than were checked (a large grid): not singled out
            return self.fail(t_ns, AMBIGUOUS,
                             f"the map repeats about the best pose more often than the "
                             f"{MAX_TWIN_CHECKS} twins checked",
                             hypotheses=self._hypotheses(obs, cands[:MAX_HYPOTHESES],
                                                         prior), **diag)
        twins = []
        if rivals and prior is not None and prior.x_m is not None:
            # the prior chooses only the one pose it allows (estimators/prior.py)
            every = [cand] + rivals
            k = prior_choice(prior, [(c.x_m, c.y_m, c.yaw_rad, None) for c in every])
            if k is not None:
                twins = [c for c in every if c is not every[k]]
                cand, rivals, mode = every[k], [], "prior_resolved"
        if rivals:
            r = rivals[0]
            diag["runner_up"] = (r.x_m, r.y_m, math.degrees(r.yaw_rad), r.inliers)
            return self.fail(t_ns, AMBIGUOUS,
                             f"{len(rivals) + 1} poses fit {cand.inliers} lights equally "
                             f"well (e.g. ({cand.x_m:.2f}, {cand.y_m:.2f}) and "
                             f"({r.x_m:.2f}, {r.y_m:.2f})): a symmetric layout",
                             hypotheses=self._hypotheses(obs, [cand] + rivals, prior),
                             complete=complete and len(rivals) < MAX_HYPOTHESES, **diag)
        return Chosen(cand, cands[1] if len(cands) > 1 else None, mode, tuple(twins),
                      complete and len(twins) < MAX_HYPOTHESES)

    def _about_prior(self, obs: Observation, prior: PoseEstimate, n: int) -> Chosen | None:
        """The association about ``prior`` (:meth:`_candidate`'s, mode ``about_prior``), or
        None: the prior is not trusted, the pose found about it lies outside the
        region it allows (:func:`~ceilkit.runtime.estimators.prior.allows`: a kidnap, a
        wrong start pose), or the frame prefers one of its twins."""
        c = self.matcher.verify(obs.q_v, prior.yaw_rad,
                                np.array([float(prior.x_m), float(prior.y_m)]),
                                self.prior_gate_m)
        # scored as its twins are (TwinJudge.present): trusted when most spots, and most
        # lights it shows where the frame is dark, match (a stale prior must not pull a
        # local false match) and it measures as many as it shows unkept (`unmeasured`)
        c = None if c is None else self.judge.refitted(obs, self.judge.present(obs, c))
        if (c is not None and c.inliers >= max(2, math.ceil(TRACK_MIN_SHARE * n))
                and c.missing - c.unseen <= max(1, c.inliers // 2) and c.present <= c.inliers
                and allows(prior, (c.x_m, c.y_m, c.yaw_rad, fit_cov(c, self.lights_w)))):
            if not self.options.twins:
                return Chosen(c, None, "about_prior", (), False)
            if c.inliers < self.options.min_inliers:
                # too few spots to list their twins: trusted only where the prior's
                # region cannot hold a pose one light spacing away (a track coasting
                # since its start pose put two unmapped lights on map lights 1.5 m off)
                return (Chosen(c, None, "about_prior", (), False)
                        if narrower_than(prior, self.spacing_m) else None)
            return prior_twins(self.judge, obs, c, prior, self.options.ambiguity_margin)
        return None

    def _hypotheses(self, obs: Observation, cands: list[Candidate],
                    prior: PoseEstimate | None, cov: np.ndarray | None = None
                    ) -> tuple[Hypothesis, ...]:
        """:meth:`.twins.TwinJudge.hypotheses` of ``cands``, sharing ``cov`` or the
        first's refinement (:meth:`_refine`): a twin is the same spots moved rigidly.
        With a prior, those nearest it first (a list cut at ``MAX_HYPOTHESES`` keeps them)."""
        if prior is not None and len(cands) > 2:
            cands = [cands[0]] + sorted(cands[1:], key=lambda c: prior_distance(
                prior, (c.x_m, c.y_m, c.yaw_rad, None))[0])
        if cov is None:
            try:
                cov = self._refine(obs, cands[0], prior).cov
            except (np.linalg.LinAlgError, ValueError):
                cov = None
        return self.judge.hypotheses(obs, cands, cov)

    def _refine(self, obs: Observation, cand: Candidate, prior: PoseEstimate | None = None
                ) -> RefinedPose:
        """:func:`refine_candidate` with this estimator's map, options and camera."""
        self._noise = self._pool.array()
        return refine_candidate(obs, cand, self.lights_w, self.options,
                                self.rig.camera.height, prior, self._noise)


@dataclass(frozen=True, eq=False)
class Chosen:
    """The pose a frame's association singled out, before its refinement
    (:meth:`LightsEstimator._candidate`).

    Attributes:
        best: the chosen :class:`~.matching.Candidate`.
        runner_up: the next best of the global search (None: none, or ``about_prior``).
        mode: ``about_prior``, ``global`` or ``prior_resolved``.
        twins: the equally good poses the prior ruled out (published as hypotheses).
        complete: whether ``twins`` are every twin of ``best``.
    """

    best: Candidate
    runner_up: Candidate | None
    mode: str
    twins: tuple[Candidate, ...]
    complete: bool


def map_lights(site: Site) -> tuple[np.ndarray, np.ndarray, float]:
    """``(site_ids, lights_w, spacing_m)``: the site's lights the method uses (those in
    an ignore region, SPEC §2, are not in the map it matches, expects or refines
    against; ``site_ids`` maps back), and their smallest spacing.

    Raises:
        ConfigError: every light ignored, or two at one place.
    """
    all_w = np.asarray(site.lights_m, float)
    keep = ~site.ignored(all_w)
    if not keep.any():
        raise ConfigError(site.source, "ignore", "every light of the map lies in an "
                          "ignore region: the lights method has nothing to use")
    lights_w = all_w[keep]
    spacing_m = _min_spacing(lights_w)
    if spacing_m < 1e-3:
        raise ConfigError(site.source, "lights", "duplicate light: two lights at the same place")
    return np.flatnonzero(keep), lights_w, spacing_m


def spot_diag(obs: Observation) -> dict[str, Any]:
    """A frame's diagnostics before any pose: spots kept, regions examined, and for
    overlays (references) the spots used, the regions examined and which were kept."""
    return {"spots": len(obs.spots), "candidates": obs.spots.n_candidates,
            "spots_px": obs.spots.centroids_px, "candidates_px": obs.candidates_px,
            "kept": obs.kept}


def too_few(n: int, min_inliers: int) -> tuple[str, str] | None:
    """``(reason, detail)`` of a frame of ``n`` spots too few for any pose (2 with a
    prior), or None."""
    if n == 0:
        return "no_lights", "no light found in the frame"
    if n < 2:
        return ("too_few_lights", f"{n} light found, a pose needs 2 with a prior, "
                f"{min_inliers} without")
    return None


def unmeasured(c: Candidate) -> str:
    """Why a pose that shows more lights where the frame has regions the checks did not
    keep than it measures is not explained (``misfit``): the lights are there but do not
    look like the site's lights (bloomed into ovals, merged, cut), so the few that pass
    are imaged by the same unmodelled effect and their centroids are not to be trusted
    (held-out ``lamps1`` of seed 7: rim slivers of bloomed lamps, 3 of about a dozen,
    carried a prior 10-14 cm off in three frames)."""
    return (f"{c.present} lights this pose shows are there but fit no light's shape, "
            f"{c.inliers} measured: the frame's lights are not measurable")


def prior_twins(judge: TwinJudge, obs: Observation, c: Candidate, prior: PoseEstimate,
                margin: float) -> Chosen | None:
    """``c``, found about ``prior``, chosen with the twins the prior rules out (other
    cells: none inside its region; :class:`Chosen`, mode ``about_prior``), or None: the
    frame itself prefers one of them by more than ``margin`` (then the global search
    decides) or the prior allows another."""
    weights = obs.weights()
    own = judge.evidence(c, weights)
    rivals, complete = judge.rivals(obs, c)
    twins = [t for t in rivals if judge.evidence(t, weights) >= own - margin]
    if all(judge.evidence(t, weights) <= own + margin for t in twins) and prior_choice(
            prior, [(t.x_m, t.y_m, t.yaw_rad, None) for t in [c] + twins]) == 0:
        twins.sort(key=lambda t: -judge.evidence(t, weights))
        return Chosen(c, None, "about_prior", tuple(twins),
                      complete and len(twins) < MAX_HYPOTHESES)
    return None


def present_m(diameter_m: float, rect: tuple[float, float] | None, gate_m: float) -> float:
    """How near a map light's ceiling point a region the observer did not keep shows
    the light there (:meth:`.twins.TwinJudge.present`): half the light's extent (a
    rectangle's diagonal, a disc's diameter) and the association's gate: a bloomed
    lamp's region is centred on it, a fragment of a cut one lies within it."""
    extent = math.hypot(*rect) if rect is not None else diameter_m
    return 0.5 * extent + gate_m


def observe_stages(rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                   o: LightsOptions, diameter_m: float,
                   rect: tuple[float, float] | None, valid_mask: np.ndarray,
                   nadir: np.ndarray, spacing_m: float = math.inf
                   ) -> tuple[SpotObserver, VisibilityTable]:
    """The spot observer and the visibility table of the lights ``lights_w`` (m, W):
    discs of ``diameter_m``, or rectangles ``rect`` (length, width; m). A rectangle seen
    at a wide angle is a sliver: its shape is checked against the projected rectangle
    (:mod:`.observe`), not against the detector's round-spot bound; a lamp cut by the
    view's edge is not counted missing within :data:`~.observe.RECT_CUT_REACH` of it. A
    lamp's region may be its rectangle bloomed by up to half the narrowest gap between
    two lamps (``spacing_m``, the map's smallest distance between two lights, less the
    rectangle's diagonal): a wider bloom would have merged the two."""
    factor = working_factor((rig.camera.height, rig.camera.width), o.working_mpx)
    spot_params = o.spot_params
    if spot_params is None and rect is None:    # the Niblack window fitted to the discs
        spot_params = fitted_spot_params(SpotParams(), rig, ceiling_height_m, diameter_m,
                                         valid_mask, factor)
    elif spot_params is None:   # rectangles: a window grown to them took their halo in,
        # so the grown window's regions are used only where they hold no clipped plateau
        spot_params = fitted_lamp_window(SpotParams(min_axis_ratio=RECT_MIN_AXIS_RATIO), rig,
                                         ceiling_height_m, rect[0], valid_mask, factor)
    bloom_max_m = 0.0 if rect is None else max(
        0.0, 0.5 * (min(spacing_m, 1e6) - math.hypot(*rect)))
    if o.spot_params is None:   # a light's core larger than the glare bound is kept
        area_m2, upper = (rect[0] * rect[1], RECT_AREA[1]) if rect is not None else \
            (0.25 * math.pi * diameter_m ** 2, DISC_AREA_MAX)
        if rect is not None and bloom_max_m > 0:   # ... and a lamp bloomed its farthest
            upper = max(upper, bloomed_area(*rect, bloom_max_m) / area_m2)
        spot_params = fitted_light_bound(spot_params, rig, ceiling_height_m, area_m2, upper,
                                         valid_mask, factor)
    observer = SpotObserver(rig, ceiling_height_m, 0.5 * diameter_m, spot_params,
                            valid_mask, nadir, o.max_spots, factor, o.spot_stage,
                            light_size_m=rect, bloom_max_m=bloom_max_m)
    visibility = VisibilityTable(
        rig, ceiling_height_m, lights_w, valid_mask, nadir, o.max_spots, 0.5 * diameter_m,
        reach_m=None if rect is None else RECT_CUT_REACH * 0.5 * math.hypot(*rect))
    return observer, visibility


def refine_candidate(obs: Observation, cand: Candidate, lights_w: np.ndarray,
                     o: LightsOptions, height_px: int, prior: PoseEstimate | None = None,
                     noise: np.ndarray | None = None) -> RefinedPose:
    """The inlier pairs and :func:`refine_pose_ceiling` of a candidate (its spots on the
    map's ``lights_w``) as a :class:`~.refine.RefinedPose`, after one pass that drops
    residuals beyond ``max(max_residual_px, 4 x median)``; with a rolling shutter
    (``readout_ms``, rows of a ``height_px`` frame) each light seen from its row's pose
    (:func:`fit_rows`); a frame with more grey levels with the run's pixel noise
    ``noise`` (:meth:`~.refine.NoisePool.array`, :func:`pools`)."""
    motion = row_motion(o, prior)
    pairs = cand.pairs
    rows = (obs, lights_w, o.readout_ms, height_px)
    fit = fit_rows(*rows, pairs, (cand.x_m, cand.y_m, cand.yaw_rad), motion, noise)
    res = fit[4]
    bad = res > max(o.max_residual_px, OUTLIER_MEDIANS * short_median(res))
    if bad.any() and pairs.shape[0] - int(bad.sum()) >= 2:
        pairs = pairs[~bad]
        fit = fit_rows(*rows, pairs, fit[:3], motion, noise)
    grown = None if obs.bloom_m is None else obs.bloom_m[pairs[:, 0]]
    if grown is not None and np.any(grown > 0):
        # a bloomed lamp's centre keeps an error of its own for the frame, a share of how
        # far it bloomed (observe.BLOOM_CENTRE_SHARE): added as a map error of that light
        # is (checked: map_error)
        cov = fit[3] + map_cov(lights_w[pairs[:, 1]], fit[0], fit[1],
                               BLOOM_CENTRE_SHARE * grown)
        fit = (*fit[:3], cov, fit[4])
    return RefinedPose(pairs, *fit)


def map_error(site: Site, ids: Sequence[int], x_m: float, y_m: float) -> np.ndarray:
    """``(3, 3)``: what the map error of the lights ``ids`` (their ``site.light_sigma_m``,
    a surveyed map's) does to a fix at ``(x_m, y_m)`` (:func:`~.refine.map_cov`); zeros
    when the site gives none (the lights exact)."""
    if site.light_sigma_m is None:
        return np.zeros((3, 3))
    i = np.asarray(ids, int)
    return map_cov(site.lights_m[i], x_m, y_m, site.light_sigma_m[i])


def fit_rows(obs: Observation, lights_w: np.ndarray, readout_ms: float, height_px: int,
             pairs: np.ndarray, start: tuple[float, float, float],
             motion: tuple[tuple[float, float, float], tuple[float, float, float]] | None,
             noise: np.ndarray | None = None
             ) -> tuple[float, float, float, np.ndarray, np.ndarray]:
    """:func:`refine_pose_ceiling` of ``pairs`` from ``start``. With ``motion``
    (:func:`~ceilkit.runtime.estimators.rows.row_motion`) a spot at row time ``tau``
    saw the lights from the pose moved by ``(dx, dy, dyaw) = velocity tau``: to first
    order the light ``L`` seen from the stamp's pose ``t`` at
    ``L - (dx, dy) - dyaw perp(L - t)``; each velocity component moved by its sigma
    refits once, and the moves' outer products are added to the covariance (what
    the velocity's uncertainty does to the pose). A frame with more grey levels and no
    ``motion`` takes the run's pixel noise ``noise`` (:func:`~.refine.pattern_cover`)."""
    q, jac = obs.q_v[pairs[:, 0]], obs.jac_px[pairs[:, 0]]
    lights = lights_w[pairs[:, 1]]
    if motion is None:
        fit = refine_pose_ceiling(q, jac, lights, *start)
        if obs.centre_px is None and obs.principal_px is not None:   # more grey levels
            return pattern_cover(q, jac, lights,
                                 obs.spots.centroids_px[pairs[:, 0]] - obs.principal_px, fit,
                                 noise)
        if obs.centre_px is None or obs.excess_px is None:   # every weight 1
            return with_shifts(q, jac, lights, frame_shifts(obs, pairs[:, 0]), fit)
        w = spot_weights(obs, pairs[:, 0])[:, None, None]
        out = with_shifts(q, jac * w, lights, frame_shifts(obs, pairs[:, 0]) * w, fit)
        # residual norms back in pixels (the outlier pass and the quality read them)
        return out if out is fit else (*out[:4], out[4] / w[:, 0, 0])
    tau = row_times_s(obs.spots.centroids_px[pairs[:, 0], 1], height_px, readout_ms / 1e3)
    velocity, sigma = motion

    def refit(v: tuple[float, float, float], p0: tuple[float, float, float]
              ) -> tuple[float, float, float, np.ndarray, np.ndarray]:
        rel = lights - np.array(p0[:2])
        moved = (lights - tau[:, None] * np.array(v[:2])
                 - (tau * v[2])[:, None] * np.stack([-rel[:, 1], rel[:, 0]], axis=1))
        return refine_pose_ceiling(q, jac, moved, *p0)

    fit = refit(velocity, start)
    p = np.array(fit[:3])
    cov = np.array(fit[3], float)
    for j in range(3):
        v = list(velocity)
        v[j] += sigma[j]
        d = np.array(refit(tuple(v), tuple(fit[:3]))[:3]) - p
        d[2] = wrap_pi(d[2])
        cov = cov + np.outer(d, d)
    return fit[0], fit[1], fit[2], cov, fit[4]


def fit_cov(c: Candidate, lights_w: np.ndarray) -> np.ndarray | None:
    """The covariance of a candidate's own pose, the association's unweighted rigid fit
    on the map's ``lights_w``: its residual (``rms_m``, per axis over ``2K - 3`` degrees
    of freedom) each light's error (:func:`~.refine.map_cov`). A pose found about a prior
    lies in the prior's region within its own error. None with fewer than 3 pairs."""
    k = c.inliers
    if k < 3 or not math.isfinite(c.rms_m):
        return None
    sigma = c.rms_m * math.sqrt(k / (2 * k - 3))    # per axis: 2K residuals
    return map_cov(lights_w[c.pairs[:, 1]], c.x_m, c.y_m, np.full(k, sigma))


def window_diag(fix: WindowFix, site_ids: np.ndarray, rms_px: float, ms: float
                ) -> dict[str, Any]:
    """A window fix's diagnostics (:meth:`LightsEstimator._tracked`), the global path's
    keys; ``pairs`` (spot index in ``spots_px``, light index in the site)."""
    k = fix.pairs.shape[0]
    site_pairs = fix.pairs.copy()
    ids = site_pairs[:, 1] = site_ids[fix.pairs[:, 1]]
    return {"spots": fix.found, "candidates": fix.predicted,
            "spots_px": fix.centroids_px, "candidates_px": fix.predicted_px,
            "kept": None, "inliers": k, "matched_lights": tuple(ids.tolist()),
            "pairs": site_pairs, "rms_px": rms_px, "mode": "window", "score": float(k),
            "runner_up_score": None, "ms": ms}


def pools(obs: Observation, o: LightsOptions) -> bool:
    """Whether a fix of ``obs`` takes and feeds the run's pixel noise
    (:class:`~.refine.NoisePool`): a frame with more grey levels (a two-level frame's
    fit weighs its lamps and has its own rule, :func:`~.refine.with_shifts`) and no
    rolling shutter modelled. Window fixes always do (:mod:`~.track`)."""
    return obs.centre_px is None and obs.principal_px is not None and o.readout_ms <= 0


def frame_shifts(obs: Observation, spots: np.ndarray) -> np.ndarray:
    """``(K, m, 2)`` the centroid shifts the frame's lights ``spots`` may share
    (:func:`~.refine.with_shifts`): in a two-level frame the radial one about the
    principal point (``p_i - c``: :func:`~.observe.two_level`), else none (``m`` 0).
    (Each rectangle's centroid offset as a second pattern, a lamp imaged larger or
    smaller than its map size, was measured and left out: the held-out ``lamps2``
    fit's mean NEES 9.0 -> 24.6.)"""
    if obs.centre_px is None:
        return np.zeros((len(spots), 0, 2))
    return (obs.spots.centroids_px[spots] - obs.centre_px)[:, None, :]


def spot_weights(obs: Observation, spots: np.ndarray) -> np.ndarray:
    """``(K,)`` each light's weight in a two-level frame's fit (:func:`~.refine.with_shifts`
    on rows scaled by it): ``1 / sqrt(1 + (x_i / EXCESS_SCALE_PX)²)``, ``x_i`` how much
    further lamp ``i``'s spot reaches beyond its rectangle than the frame's median lamp
    (:attr:`~.observe.Observation.excess_px`, px; none below the median). A lamp's
    centroid error is taken as growing with that excess: a bloomed lamp's region, cut by
    the threshold where its halo crosses it under the lens's fall-off, or a fixture
    merged with a lamp, moves its centroid by a share of it, on every frame (held-out
    drives, the lamps' centres at the true pose: per-axis rms 0.2-0.3 px below the top
    eighth of excess, 0.8-1.3 px within it; docs/methods/lights.md §4). Ones in a frame
    with more grey levels or of round lights."""
    if obs.centre_px is None or obs.excess_px is None or len(spots) == 0:
        return np.ones(len(spots))
    x = obs.excess_px[spots]
    over = np.maximum(x - np.median(x), 0.0) / EXCESS_SCALE_PX
    return 1.0 / np.sqrt(1.0 + over * over)


def pose_quality(k: int, rms_px: float, best: Candidate, runner: Candidate | None,
                 mode: str) -> float:
    """Confidence in [0, 1]: more lights, smaller residuals, a clear margin.

    Args:
        k: matched lights after refinement; ``rms_px``: their pixel residual.
        best, runner: the chosen candidate and the runner-up (``None``: none).
        mode: ``about_prior`` (the margin is not known: 0.9), ``global`` or
            ``prior_resolved``.
    """
    q_n = 1.0 - math.exp(-(k - 2) / 2.5)
    q_res = math.exp(-0.5 * (rms_px / 1.5) ** 2)
    # lights the pose says should be seen but were not (off, occluded, or a wrong pose)
    q_vis = (best.inliers / (best.inliers + best.missing)) ** 2
    if mode == "about_prior":
        q_sep = 0.9
    else:
        rival = runner.score if runner is not None else 2.0
        q_sep = 1.0 - math.exp(-max(best.score - rival, 0.0) / 1.5)
    return float(min(1.0, max(0.0, q_n * q_res * q_sep * q_vis)))


def _min_spacing(lights_w: np.ndarray) -> float:
    """The smallest distance between two lights (m; inf for fewer than two): each
    light's nearest other by a k-d tree, ``O(M log M)`` (not all pairs)."""
    if lights_w.shape[0] < 2:
        return math.inf
    d, nb = cKDTree(lights_w).query(lights_w, 2)
    i = int(np.argmin(d[:, 1]))
    return float(np.linalg.norm(lights_w[i] - lights_w[nb[i, 1]]))


__all__ = ["DEFAULT_LIGHT_DIAMETER_M", "LightsEstimator", "LightsOptions", "light_diameter_m",
           "pose_quality"]
