"""The ``texture`` method: a global pose from one frame by matching the ceiling's
natural features (vents, sprinklers, panels, stains, seams), rectified onto the
ceiling plane, against the site's ceiling map (docs/methods/texture.md).

Per frame: rectify (:func:`.ceilmap.rectify`), detect and describe (ORB,
:func:`.ceilmap.features`), match to the map (an LSH index over its descriptors, or,
with a prior, the map features near it only), two-point RANSAC for the rigid 2-D pose,
least squares on its inliers (its covariance the fit's plus the map's own error,
shared by the features a keyframe placed: :meth:`.ceilmap.CeilingMap.placement_cov`);
the mosaic at the pose must explain the frame as a whole and in most of its parts
(``min_ncc``, ``min_part_ncc``: :func:`.ceilmap.explains`). With a tight prior (its
region cannot hold a twin ``window_twin_m`` away) the fast path of :mod:`.track` runs
first: the map's features followed from the prior into the frame, no detection. A pose
whose inliers hold too few distinctive matches (:func:`.match.distinctive`) is not
singled out. The same search run again without the best pose's inliers and outside
its basin gives the runner-up: when the mosaic explains the frame nearly as well there
(``twin_ncc``), over the whole frame and where the two poses' mosaics differ
(:func:`where_they_differ`), the frame supports two poses and the estimate is an
``ambiguous`` Failure carrying both (a prior may choose one, by
:mod:`~ceilkit.runtime.estimators.prior`'s rule). Between fixes the ceiling-plane
odometry (:mod:`~ceilkit.runtime.estimators.odometry`) gives the increment.

Example::

    est = TextureEstimator(rig, site)                 # site.yaml: ceiling_map: map.npz
    pose = est.estimate(grey, t_ns)                   # PoseEstimate | Failure
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

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
from ceilkit.runtime.estimators.honesty import MISFIT, check_options
from ceilkit.runtime.estimators.odometry import PlaneOdometry, with_increment
from ceilkit.runtime.estimators.prior import (
    allows,
    narrower_than,
    prior_choice,
    prior_cov,
)
from ceilkit.runtime.estimators.rows import ShutterOptions
from ceilkit.runtime.estimators.texture.ceilmap import (
    CeilingMap,
    Rectifier,
    explains,
    features,
    flat_ncc,
    footprint_half_extent,
    predicted_patch,
    warm_features,
)
from ceilkit.runtime.estimators.texture.match import (
    BASIN,
    DescriptorIndex,
    MapFit,
    ransac_rigid,
    refine,
    residuals,
)
from ceilkit.runtime.estimators.texture.shutter import Readout, refit
from ceilkit.runtime.estimators.texture.track import MapTracker
from ceilkit.runtime.geometry.ceiling import PlanarGeometry

TOO_FEW_FEATURES = "too_few_features"
NO_MAP_MATCH = "no_map_match"
MAX_WINDOW_M = 3.0       # a prior vaguer than this (3σ, m) is searched globally
NCC_STRIDE = 3           # flat_ncc over every 3rd row and column of the patch
TRACK_LEVELS = 1         # the fast path's patch and mosaic: 2^L times coarser than the map
TRACK_MIN_SHARE = 0.5    # ... its pose fits at least this share of the features followed
DIFFER_Z = 1.0           # two poses' mosaics differ where they are > 1 std apart ...
DIFFER_MIN_SHARE = 0.05  # ... on at least this share of the pixels all three hold, or
#                          the two cannot be told apart by the frame (twins)
TWIN_SUPPORT = 3         # a pose's twin candidate: this many of its alike matches agree
MAX_TWINS = 8            # candidates judged at most (more: the twins are not all listed)
REPEAT_SHARE = 0.5       # a map repeat is a twin when this share of the inliers recur
TRACK_VAR_FACTOR = 1.2
"""The fast path's measured / fitted variance: its fit's ``s² (JᵀJ)⁻¹`` scaled by it.
On the 60-frame office drive of bench_texture (supersample 2, a prior 1 cm and 0.5°
off) its position errors (median 0.45 mm, worst 1.3 mm) gave an unscaled NEES (2 dof)
median of 1.62 where the law's is 1.39; scaled, 1.35. (The global path's, unscaled,
was 1.53.)"""


@dataclass(frozen=True)
class TextureOptions(ShutterOptions):
    """What a user may set (``--option KEY=VALUE``).

    Attributes:
        half_extent_m: half the rectified patch's side, m (0: the frame's footprint).
        n_features: ORB keypoints per frame, at most.
        knn: map candidates per frame feature (a repeated feature has many twins).
        max_hamming: a candidate's largest descriptor distance, bits (of 256).
        tol_px: a correspondence is an inlier within this many map pixels.
        iterations: RANSAC two-point samples per search.
        min_inliers: distinct frame features a pose needs.
        min_inlier_share: inliers / frame features a pose needs.
        min_unique: inliers a pose needs whose match is distinctive (one place of the
            map, :func:`.match.distinctive`): fewer, and the pose rests on features
            that match their twins alike (a tile grid's seam crossings): ``ambiguous``.
        max_rms_px: the inliers' RMS residual a pose may have, map pixels.
        min_ncc: the least normalized cross-correlation of the rectified frame with the
            map's mosaic at the pose, each of the 3 x 3 blocks less its plane
            (:func:`.ceilmap.flat_ncc`: the model explains the whole frame, shading
            left out). Issue 39's held-out drives: true poses 0.72 or more, random
            poses' 99.9th percentile 0.38 (docs/methods/texture.md, "The whole-frame gate
            without the shading").
        min_part_ncc: the least median over the frame's 3 x 3 blocks of their correlation
            with the mosaic at the pose (:func:`.ceilmap.part_ncc`: the model explains
            most parts of the frame, not only one). Issue 39's held-out pose off the
            mapped place: 0.22; right poses: 0.64 or more (bench_survey's second drive
            under the realistic preset; 0.83 with noise and blur), 0.74 or more on the
            held-out drives, 0.82 between two rows of a map seen only obliquely.
        twin_ncc: a runner-up pose with ``min_inliers`` whose mosaic correlates with the
            frame within this of the best's (or cannot be checked: off the mosaic),
            over the whole frame and where the two mosaics differ
            (:func:`where_they_differ`; or they differ too little to tell), makes the
            frame ``ambiguous``.
        window_m: with a prior, the map is searched within the frame's footprint plus
            this plus the prior's 3σ of its position.
        window_twin_m: the tracked fast path (:mod:`.track`: the map's features followed
            from the prior, no detection) is taken only when the prior's region is too
            narrow to hold a pose this far away (m; a twin of the pose must lie at
            least this far: half the 0.6 m tile of a drop ceiling); so too a prior's
            choice among twins listed for non-distinctive matches (:func:`_twin_free`).
        plane_odometry: carry the ceiling-plane odometry between fixes.
        seed: the RANSAC's random seed (with the frame's stamp).
        readout_ms, rate_sigma_dps, speed_sigma_mps, unknown_rate_dps,
            unknown_speed_mps: (inherited) a rolling shutter
            (:class:`~ceilkit.runtime.estimators.rows.ShutterOptions`): each feature put
            back to the stamp by the prior's velocity (:mod:`.shutter`), the fit's
            covariance grown by the velocity's sigmas; without a velocity the frame's
            own fitted with the pose where its rows determine it
            (:func:`.shutter.joint_fit`), else the features taken as seen at the stamp
            with the ``unknown_*`` sigmas.
    """

    half_extent_m: float = 0.0
    n_features: int = 400
    knn: int = 2
    max_hamming: int = 64
    tol_px: float = 3.0
    iterations: int = 200
    min_inliers: int = 12
    min_inlier_share: float = 0.05
    min_unique: int = 6
    max_rms_px: float = 1.5
    min_ncc: float = 0.5
    min_part_ncc: float = 0.4
    twin_ncc: float = 0.2
    window_m: float = 0.3
    window_twin_m: float = 0.3
    plane_odometry: bool = True
    seed: int = 0


@dataclass(frozen=True, eq=False)
class _Search:
    """The best pose and its runner-up among one set of correspondences."""

    best: MapFit | None
    count: int
    runner: MapFit | None
    runner_count: int
    ncc: float
    runner_ncc: float
    unique: int = 0
    differ_ncc: tuple[float, float] = (math.nan, math.nan)
    twins: tuple[MapFit, ...] = ()
    judged: int = 0
    singled: bool = False
    part: float = dataclasses.field(kw_only=True)  # the best's part_ncc (.ceilmap.explains)

    @property
    def listed(self) -> bool:
        """Every twin looked for is known: none was, or all were listed (not past
        :data:`MAX_TWINS`; a pose with distinctive matches and more of the map's repeats
        about it than that is not singled out by the few judged)."""
        return self.singled or not self.judged


class TextureEstimator(Estimator):
    """Global localization on the site's ceiling map (see the module docstring)."""

    name = "texture"
    Options = TextureOptions
    site_sections = ("ceiling_map",)

    def __init__(self, rig: Any, site: Any,
                 options: TextureOptions | dict[str, Any] | None = None) -> None:
        super().__init__(rig, site, options)
        o: TextureOptions = self.options  # type: ignore[assignment]
        check_options(o)
        self.map = CeilingMap.load(site.ceiling_map)
        if abs(self.map.ceiling_height - site.ceiling_height_m) > 1e-6:
            raise ConfigError(site.ceiling_map, "header.ceiling_height",
                              f"the map was made at {self.map.ceiling_height:g} m, the site's "
                              f"ceiling is at {site.ceiling_height_m:g} m")
        self.index = DescriptorIndex(self.map.points_xy, self.map.descriptors)
        self._tracker = MapTracker(self.map, TRACK_LEVELS)
        self.half_m = o.half_extent_m or footprint_half_extent(rig, site.ceiling_height_m)
        self._track_rectify = Rectifier.of(rig, site.ceiling_height_m,
                                           self._tracker.map.resolution_m, self.half_m)
        # the global search's tables too, before the first frame (made on it, frame 0
        # took 160 ms against 16 ms for the same work once they were there)
        self._rectify = Rectifier.of(rig, site.ceiling_height_m, self.map.resolution_m,
                                     self.half_m)
        # the ORB detector and both paths' eroded masks too (made on frame 0: issue 37)
        warm_features(self._rectify.valid, self.map.resolution_m, o.n_features)
        self._tracker.inner(self._track_rectify.valid)
        self.sigma_floor_m = float(np.median(self.map.sigma_m[np.unique(self.index.place)])) \
            if len(self.map.sigma_m) else self.map.resolution_m
        self._odo = PlaneOdometry(PlanarGeometry.of(rig, site), site) if o.plane_odometry \
            else None
        self._fixed = True

    def forget(self) -> None:
        self._fixed = True
        if self._odo is not None:
            self._odo.reset()

    # -- per frame ---------------------------------------------------------------------
    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        got = self._frame(grey, t_ns, prior, t0)
        if self._odo is None:
            return got
        fixed, gap = bool(got), not self._fixed
        self._fixed = fixed
        return with_increment(self._odo, got, grey, t_ns, not fixed or gap, prior, t0)

    def _frame(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
               t0: float) -> Estimate:
        o: TextureOptions = self.options  # type: ignore[assignment]
        res = self.map.resolution_m
        near = prior is not None and prior.x_m is not None and prior.y_m is not None
        if near and narrower_than(prior, o.window_twin_m):  # type: ignore[arg-type]
            fast = self._tracked(grey, prior, t_ns, t0)  # type: ignore[arg-type]
            if fast is not None:
                return fast
        patch, valid = self._rectify(grey)
        q, desc = features(patch, valid, res, n_features=o.n_features)
        if len(q) < o.min_inliers:
            return self.fail(t_ns, TOO_FEW_FEATURES, f"{len(q)} ceiling features, a pose "
                             f"needs {o.min_inliers}", features=len(q), ms=elapsed_ms(t0))
        rng = np.random.default_rng([o.seed, t_ns & 0x7FFFFFFFFFFFFFFF])
        rows = self._rows(q, prior)
        if rows is not None:   # the RANSAC's features turned back to the stamp
            q = rows[0].unrolled(q, rows[2], None)
        if near:
            radius = self._window_radius(prior)  # type: ignore[arg-type]
            if radius is not None:
                qi, mj, uq = self.index.near(desc, (prior.x_m, prior.y_m),  # type: ignore
                                             radius, o.knn, o.max_hamming)
                got = self._decide(q, qi, self._search(q, desc, (qi, mj, uq), rng,
                                                       (patch, valid), rows),
                                   prior, t_ns, t0, local=True)
                if got is not None:
                    return got
        qi, mj, uq = self.index.match(desc, o.knn, o.max_hamming)
        return self._decide(q, qi, self._search(q, desc, (qi, mj, uq), rng, (patch, valid),
                                                rows), prior, t_ns, t0, local=False)

    def _tracked(self, grey: np.ndarray, prior: PoseEstimate, t_ns: int, t0: float
                 ) -> PoseEstimate | None:
        """The fast path (:mod:`.track`): the map's features followed from the prior into
        the frame rectified at :data:`TRACK_LEVELS` coarser than the map (the mosaic
        alike); its pose when it explains the frame (as the global path's checks, the
        same tolerances in metres) and the prior's region holds it, else None (the
        searches follow)."""
        o: TextureOptions = self.options  # type: ignore[assignment]
        res = self.map.resolution_m
        if self._tracker.grid is None:
            return None
        cmap = self._tracker.map
        patch, valid = self._track_rectify(grey)
        got = self._tracker.follow(patch, valid,
                                   (float(prior.x_m), float(prior.y_m), float(prior.yaw_rad)),
                                   o.tol_px * res, self.sigma_floor_m, o.min_inliers,
                                   Readout.of(self.rig, self.site.ceiling_height_m, o, prior))
        if got is None:
            return None
        r = got.refined
        fit = dataclasses.replace(r, cov=r.cov * TRACK_VAR_FACTOR
                                  + self.map.placement_cov(got.inlier_xy, r.pose))
        ncc, part = explains(cmap, patch, valid, fit.pose, NCC_STRIDE)
        if fit.rms_m > o.max_rms_px * res or not ncc >= o.min_ncc or \
                part < o.min_part_ncc or \
                len(fit.used) < TRACK_MIN_SHARE * got.followed or \
                not allows(prior, (*fit.pose, fit.cov)):
            return None
        diag = {"features": got.predicted, "matches": got.followed, "inliers": len(fit.used),
                "runner_up": 0, "search": "tracked", "rms_px": fit.rms_m / res, "ncc": ncc,
                "runner_up_ncc": math.nan, **_velocity_diag(fit)}
        return self._pose(t_ns, _Search(fit, len(fit.used), None, 0, ncc, math.nan, part=part),
                          Provenance.WINDOW, (), diag, t0)

    def _window_radius(self, prior: PoseEstimate) -> float | None:
        """The radius about the prior's position the map is searched within, or None
        when the prior is too vague for a local search (:data:`MAX_WINDOW_M`)."""
        spread = 3.0 * math.sqrt(max(_largest_eigenvalue(prior_cov(prior)[:2, :2]), 0.0))
        if not spread <= MAX_WINDOW_M:
            return None
        return math.sqrt(2.0) * self.half_m + self.options.window_m + spread  # type: ignore

    def _search(self, q: np.ndarray, desc: np.ndarray,
                pairs: tuple[np.ndarray, np.ndarray, np.ndarray], rng: np.random.Generator,
                frame: tuple[np.ndarray, np.ndarray], rows: _Rows | None = None) -> _Search:
        """The best pose among the correspondences ``pairs`` (``qi, mj, unique``:
        :meth:`.match.DescriptorIndex.match`) and the runner-up (the same search
        without the best's inliers, outside its basin), each with how well the mosaic
        at it explains the frame (``frame``: the rectified patch, its valid mask;
        :func:`.ceilmap.explains`, the runner-up's :func:`.ceilmap.flat_ncc`);
        with too few distinctive inliers, the best's twins (:meth:`_twins`). With a
        rolling shutter (``rows``: :meth:`_rows`) each fit is :meth:`_refined`'s."""
        o: TextureOptions = self.options  # type: ignore[assignment]
        (qi, mj, unique), (patch, valid) = pairs, frame
        tol = o.tol_px * self.map.resolution_m
        qq, pp = q[qi], self.map.points_xy[mj]
        sub = None if rows is None else (rows[0], rows[1][qi], rows[2][qi])
        first = ransac_rigid(qq, pp, qi, tol, o.iterations, rng)
        best = None if first is None else self._refined(qq, pp, qi, first.pose, sub)
        if best is None:
            return _Search(None, 0, None, 0, math.nan, math.nan, part=math.nan)
        rest = np.ones(len(qi), bool)
        rest[best.used] = False
        second = ransac_rigid(qq[rest], pp[rest], qi[rest], tol, o.iterations, rng,
                              avoid=best.pose)
        # a runner-up RANSAC found with under half of min_inliers is no twin (refining
        # it, about its pose again, does not double it): its least squares is skipped
        runner = None if second is None or 2 * second.count < o.min_inliers else \
            self._refined(qq[rest], pp[rest], qi[rest], second.pose,
                          None if sub is None else (sub[0], sub[1][rest], sub[2][rest]))
        ncc, part = explains(self.map, patch, valid, best.pose, NCC_STRIDE)
        ncc2 = math.nan if runner is None or len(runner.used) < o.min_inliers else \
            flat_ncc(self.map, patch, valid, runner.pose, NCC_STRIDE)
        differ = where_they_differ(self.map, patch, valid, best.pose, runner.pose) \
            if math.isfinite(ncc2) and not ncc2 < ncc - o.twin_ncc else (math.nan, math.nan)
        s = _Search(best, len(best.used), runner, 0 if runner is None else len(runner.used),
                    ncc, ncc2, int(np.count_nonzero(unique[best.used])), differ, part=part)
        if s.unique >= o.min_unique:
            return _with_repeats(self.index, self.map, s, mj[best.used], frame, o)
        twins, judged, singled = self._twins(q, desc, qi[best.used][~unique[best.used]], best,
                                             mj[best.used], ncc, frame, rows)
        if _runner_twin(s, o):    # every twin listed for _decide's prior, the runner-up once
            twins = tuple(t for t in twins if not _same_basin(t.pose, runner.pose))
        return dataclasses.replace(s, twins=twins, judged=judged, singled=singled)

    def _twins(self, q: np.ndarray, desc: np.ndarray, feats: np.ndarray, best: MapFit,
               used: np.ndarray, ncc: float, frame: tuple[np.ndarray, np.ndarray],
               rows: _Rows | None) -> tuple[tuple[MapFit, ...], int, bool]:
        """``(twins, judged, complete)``: the poses other than ``best`` that its
        non-distinctive matches (query features ``feats``) support alike, the frame does
        not rule out. Each feature is paired with every place of the map the ratio test
        cannot tell from its nearest (:meth:`.match.DescriptorIndex.alike`, exact), its
        place at ``best`` left out; the pose the most of them agree on (every two
        pairs a sample: :func:`.match.ransac_rigid`, exhaustive; outside ``best``'s
        basin), refined, is a candidate while :data:`TWIN_SUPPORT` features agree on
        it, its pairs then left out, :data:`MAX_TWINS` at most. Then the map's own
        repeats about ``best`` (:func:`add_repeats`: ``used``, the map features of its
        inliers, recurring elsewhere in the map), which the frame's descriptors need
        not show. A candidate is ruled out as the runner-up is (:func:`_told_apart`,
        ``twin_ncc``). ``complete``: every alike place was listed and fewer than
        :data:`MAX_TWINS` candidates were found; otherwise the twins are not all
        known."""
        o: TextureOptions = self.options  # type: ignore[assignment]
        tol = o.tol_px * self.map.resolution_m
        qi, mj, complete = self.index.alike(desc[feats], o.max_hamming)
        qi = feats[qi]
        qq, pp = q[qi], self.map.points_xy[mj]
        keep = residuals(best.pose, qq, pp) >= tol
        found: list[MapFit] = []
        while np.count_nonzero(keep) >= 2:
            k = np.flatnonzero(keep)
            got = ransac_rigid(qq[k], pp[k], qi[k], tol, 0, None,  # type: ignore[arg-type]
                               avoid=best.pose, exhaustive=True)
            if got is None or got.count < TWIN_SUPPORT:
                break
            if len(found) == MAX_TWINS:
                complete = False
                break
            fit = self._refined(qq[k], pp[k], qi[k], got.pose,
                                None if rows is None else (rows[0], rows[1][qi[k]], rows[2][qi[k]]))
            found.append(fit if fit is not None else
                         MapFit(got.pose, best.cov, np.flatnonzero(got.inliers), math.nan))
            keep[k[got.inliers]] = False
        complete = add_repeats(self.index, best, used, found, o.max_hamming) and complete
        return _standing(self.map, frame, best.pose, ncc, found, o), len(found), complete

    def _rows(self, q: np.ndarray, prior: PoseEstimate | None) -> _Rows | None:
        """With a rolling shutter (``readout_ms`` > 0): the frame's row model
        (:class:`.shutter.Readout`, the prior's velocity), the features as observed
        and their row times; None for a global shutter."""
        ro = Readout.of(self.rig, self.site.ceiling_height_m,
                        self.options, prior)  # type: ignore[arg-type]
        return None if ro is None else (ro, q, ro.times(q))

    def _refined(self, qq: np.ndarray, pp: np.ndarray, qi: np.ndarray,
                 pose: tuple[float, float, float], rows: _Rows | None) -> MapFit | None:
        """:func:`.match.refine` from a RANSAC ``pose``; with a rolling shutter
        (``rows`` over these pairs) :func:`.shutter.refit`'s (the prior's velocity, or
        the frame's own where it determines it, or the ``unknown_*`` sigmas). Its
        covariance holds the map's own error too (:meth:`.CeilingMap.placement_cov`:
        shared by a keyframe's features, not divided by their count)."""
        tol = self.options.tol_px * self.map.resolution_m  # type: ignore[attr-defined]
        fit = refine(qq, pp, qi, pose, tol, self.sigma_floor_m) if rows is None else \
            refit(*rows, pp, qi, pose, tol, self.sigma_floor_m)
        if fit is None:
            return None
        return dataclasses.replace(fit, cov=fit.cov + self.map.placement_cov(pp[fit.used],
                                                                             fit.pose))

    def _decide(self, q: np.ndarray, qi: np.ndarray, s: _Search,
                prior: PoseEstimate | None, t_ns: int, t0: float, local: bool
                ) -> Estimate | None:
        """The estimate a search gives (None: a local search that found nothing the
        prior allows; the global search follows). The pose must explain the frame as a
        whole and each part of it (``s.ncc``, ``s.part``: :func:`.ceilmap.explains`)."""
        o: TextureOptions = self.options  # type: ignore[assignment]
        res = self.map.resolution_m
        diag = {"features": len(q), "matches": len(qi), "inliers": s.count,
                "runner_up": s.runner_count, "search": "local" if local else "global"}
        if s.best is None or s.count < o.min_inliers:
            return None if local else self.fail(
                t_ns, NO_MAP_MATCH, f"{s.count} features agree on a pose, it needs "
                f"{o.min_inliers}", **diag, ms=elapsed_ms(t0))
        diag.update(rms_px=s.best.rms_m / res, ncc=s.ncc, runner_up_ncc=s.runner_ncc,
                    **_velocity_diag(s.best))
        part = s.part
        diag["part_ncc"] = part
        if s.count < o.min_inlier_share * len(q) or s.best.rms_m > o.max_rms_px * res \
                or not s.ncc >= o.min_ncc or part < o.min_part_ncc:
            return None if local else self.fail(
                t_ns, MISFIT, f"{s.count} of {len(q)} features fit, RMS "
                f"{s.best.rms_m / res:.2f} px, the mosaic correlates {s.ncc:.2f} "
                f"({part:.2f} over the frame's parts)", **diag, ms=elapsed_ms(t0))
        diag["unique"] = s.unique
        diag.update(differ_ncc=s.differ_ncc[0], runner_up_differ_ncc=s.differ_ncc[1])
        twin = _runner_twin(s, o)
        if local and s.unique >= o.min_unique:      # the map's repeats the prior rules out
            s = dataclasses.replace(s, twins=tuple(
                t for t in s.twins if allows(prior, (*t.pose, t.cov))))
        if s.unique < o.min_unique or s.judged:
            diag.update(twins=s.judged, twins_left=len(s.twins))
        if not twin and (s.unique < o.min_unique or s.twins or not s.listed) \
                and not (s.singled and not s.twins):
            return None if local else self.fail(
                t_ns, AMBIGUOUS, _why_ambiguous(s, o), _hypotheses(s), **diag,
                ms=elapsed_ms(t0))
        if not twin:
            if local and not allows(prior, (*s.best.pose, s.best.cov)):
                return None
            return self._pose(t_ns, s, Provenance.WINDOW if local else Provenance.GLOBAL,
                              (), diag, t0)
        hyps = _hypotheses(s)
        k = prior_choice(prior, [(h.x_m, h.y_m, h.yaw_rad, h.cov) for h in hyps]) \
            if s.unique >= o.min_unique and s.listed or s.singled and _twin_free(prior, o) else None
        if k is not None and k < 2:   # a listed twin's fit is not checked here: none chosen
            chosen = dataclasses.replace(s, best=s.runner, runner=s.best) if k == 1 else s
            return self._pose(t_ns, chosen, Provenance.PRIOR,
                              (hyps[k], *(h for i, h in enumerate(hyps) if i != k)), diag, t0)
        if local:
            return None
        return self.fail(t_ns, AMBIGUOUS, f"two poses fit {s.count} and {s.runner_count} "
                         f"features, the mosaic correlates {s.ncc:.2f} and "
                         f"{s.runner_ncc:.2f}", hyps, **diag, ms=elapsed_ms(t0))

    def _pose(self, t_ns: int, s: _Search, provenance: Provenance,
              hyps: tuple[Hypothesis, ...], diag: dict[str, Any], t0: float) -> PoseEstimate:
        best = s.best
        assert best is not None
        x, y, yaw = best.pose
        tol = self.options.tol_px * self.map.resolution_m  # type: ignore[attr-defined]
        q_n = 1.0 - math.exp(-s.count / 15.0)
        q_sep = 1.0 if s.runner is None or not math.isfinite(s.runner_ncc) else \
            min(1.0, max(0.0, (s.ncc - s.runner_ncc) / max(s.ncc, 1e-9)))
        q_res = math.exp(-0.5 * (best.rms_m / (0.5 * tol)) ** 2)
        return PoseEstimate(t_ns, self.name, x, y, yaw,
                            float(q_n * q_sep * q_res * max(s.ncc, 0.0)),
                            cov=best.cov, diagnostics={**diag, "ms": elapsed_ms(t0)},
                            provenance=provenance, hypotheses=hyps)


_Rows = tuple[Readout, np.ndarray, np.ndarray]
"""A rolling-shutter frame's row model, its features ``(N, 2)`` in V as observed and their
row times ``(N,)`` s (:meth:`TextureEstimator._rows`; indexed as the pairs they go with)."""


def _with_repeats(index: DescriptorIndex, cmap: CeilingMap, s: _Search, used: np.ndarray,
                  frame: tuple[np.ndarray, np.ndarray], o: TextureOptions) -> _Search:
    """A search ``s`` whose matches are distinctive, with the map's own repeats about
    its pose that the frame does not rule out as its ``twins`` (:func:`add_repeats`
    over the global index: a small map of a repeated ceiling holds a few copies, each
    with other descriptors, so the matches look distinctive; ``bench_heldout_texture.py
    --seed 10``'s repeated control, surveyed into 6 keyframes, published 15 poses a
    tile off so)."""
    assert s.best is not None
    found: list[MapFit] = []
    complete = add_repeats(index, s.best, used, found, o.max_hamming, exact=False)
    if not found:
        return s
    return dataclasses.replace(s, twins=_standing(cmap, frame, s.best.pose, s.ncc, found, o),
                               judged=len(found), singled=complete)


def add_repeats(index: DescriptorIndex, best: MapFit, used: np.ndarray,
                found: list[MapFit], max_hamming: int, exact: bool = True) -> bool:
    """Add to ``found`` (the twins listed so far, :meth:`TextureEstimator._twins`) the
    poses where the map repeats what ``best`` explains: ``best`` moved by each shift
    under which at least :data:`REPEAT_SHARE` of its inliers' map features ``used``
    (and :data:`TWIN_SUPPORT`) recur (:meth:`.match.DescriptorIndex.repeats`), outside
    the basins of ``best`` and of those listed; False when :data:`MAX_TWINS` would be
    passed (the twins are not all known). On a repeated ceiling the frame's
    descriptors match a few of the copies alike and the others not (each copy was
    surveyed from other views: ``bench_heldout_texture.py --seed 5``'s repeated
    control, a kidnap, published 6 poses 2.25 m off, three tiles by two, with its two
    listed twins ruled out and the true copy never listed)."""
    need = max(TWIN_SUPPORT, math.ceil(REPEAT_SHARE * len(np.unique(index.place[used]))))
    shifts, support = index.repeats(used, max_hamming, need, exact=exact)
    x, y, yaw = best.pose
    for d, n in zip(shifts, support, strict=True):
        pose = (x + float(d[0]), y + float(d[1]), yaw)
        if any(_same_basin(pose, f.pose) for f in (best, *found)):
            continue            # (every shift returned has the support ``need``)
        if len(found) == MAX_TWINS:
            return False
        found.append(MapFit(pose, best.cov, np.arange(int(n)), math.nan))
    return True


def _standing(cmap: CeilingMap, frame: tuple[np.ndarray, np.ndarray],
              best: tuple[float, float, float], ncc: float, found: list[MapFit],
              o: TextureOptions) -> tuple[MapFit, ...]:
    """The candidates ``found`` the frame (its rectified patch and valid mask) does not
    rule out against the best pose (whole-frame correlation ``ncc``): as the runner-up
    is (:func:`_told_apart`, ``twin_ncc``)."""
    patch, valid = frame
    return tuple(f for f in found if not _told_apart(
        ncc, flat_ncc(cmap, patch, valid, f.pose, NCC_STRIDE),
        lambda f=f: where_they_differ(cmap, patch, valid, best, f.pose),
        o.twin_ncc, o.min_ncc))


def where_they_differ(cmap: CeilingMap, patch: np.ndarray, valid: np.ndarray,
                      a: tuple[float, float, float], b: tuple[float, float, float]
                      ) -> tuple[float, float]:
    """``(ncc_a, ncc_b)``: how well the mosaic at pose ``a`` and at pose ``b`` explain a
    rectified patch where the two differ (every :data:`NCC_STRIDE`-th pixel the patch and
    both hold, each standardized over them; those more than :data:`DIFFER_Z` apart): the
    frame's evidence between two poses, which the whole patch's correlation dilutes by
    what both show alike (a tile grid's seams seen from a pose turned 90°). NaN, NaN
    where they differ on less than :data:`DIFFER_MIN_SHARE` of those pixels (twins:
    the frame cannot tell them apart)."""
    n = patch.shape[0]
    f = patch[::NCC_STRIDE, ::NCC_STRIDE].astype(float)
    pa, ca = predicted_patch(cmap, a, n, NCC_STRIDE)
    pb, cb = predicted_patch(cmap, b, n, NCC_STRIDE)
    both = valid[::NCC_STRIDE, ::NCC_STRIDE] & ca & cb  # type: ignore[operator]
    if np.count_nonzero(both) < 3:
        return math.nan, math.nan
    za, zb = (_standard(x.astype(float), both) for x in (pa, pb))
    differ = both & (np.abs(za - zb) > DIFFER_Z)
    if np.count_nonzero(differ) < max(3.0, DIFFER_MIN_SHARE * np.count_nonzero(both)):
        return math.nan, math.nan
    fa = f[differ]
    return _ncc(fa, za[differ]), _ncc(fa, zb[differ])


def _largest_eigenvalue(P: np.ndarray) -> float:
    """The larger eigenvalue of a symmetric ``(2, 2)``, its lower triangle read as
    ``np.linalg.eigvalsh`` reads it, in closed form (eigvalsh took 0.1 ms of a frame
    0's window search); inf when an entry is not finite."""
    a, b_up, b, c = P.ravel().tolist()
    if not all(map(math.isfinite, (a, b_up, b, c))):
        return math.inf
    return 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)


def _velocity_diag(fit: MapFit) -> dict[str, Any]:
    """The diagnostics of a fit that estimated the velocity from the frame's rows
    (:func:`.shutter.joint_fit`): ``velocity`` and ``velocity_sigma`` (W; m/s, m/s,
    rad/s); none otherwise."""
    if fit.velocity is None:
        return {}
    return {"velocity": fit.velocity, "velocity_sigma": fit.velocity_sigma}


def _why_ambiguous(s: _Search, o: TextureOptions) -> str:
    """The detail of an ``ambiguous`` frame whose listed twins stand or are not all
    known (:meth:`TextureEstimator._decide`)."""
    why = f"{len(s.twins)} of the {s.judged} poses they support alike explain the " \
          f"frame as well" if s.singled else "their twins could not all be listed"
    if s.unique >= o.min_unique:
        return f"{s.count} features fit, {s.unique} of them distinctive, but the map " \
               f"repeats about the pose: {why}"
    return f"{s.count} features fit, {s.unique} of them match one place of the map " \
           f"(it needs {o.min_unique}) and {why}"


def _same_basin(a: tuple[float, float, float], b: tuple[float, float, float]) -> bool:
    """Whether two poses lie in one RANSAC basin (:data:`.match.BASIN`): one hypothesis."""
    turn = math.atan2(math.sin(a[2] - b[2]), math.cos(a[2] - b[2]))
    return math.hypot(a[0] - b[0], a[1] - b[1]) <= BASIN[0] and abs(turn) <= BASIN[1]


def _runner_twin(s: _Search, o: TextureOptions) -> bool:
    """Whether the runner-up is the best's twin: ``min_inliers`` features, and the frame
    does not rule it out (``twin_ncc``: over the whole frame, and where they differ when
    the best explains the frame there, ``min_ncc``)."""
    a, b = s.differ_ncc
    return s.runner is not None and s.runner_count >= o.min_inliers and \
        not s.runner_ncc < s.ncc - o.twin_ncc and \
        not (a >= o.min_ncc and b < a - o.twin_ncc)


def _twin_free(prior: PoseEstimate | None, o: TextureOptions) -> bool:
    """Whether a prior's region is too narrow to hold two twins ``window_twin_m`` apart
    (its radius under half that: :func:`.prior.narrower_than`; two poses on either
    side of the prior fit a region of radius under ``window_twin_m``, review of stop
    51), so that it may choose among a pose's listed
    twins when its matches are not distinctive. The listing (:meth:`TextureEstimator._twins`)
    finds the twins the best's own features support alike; a twin whose copies of
    *other* features the map holds with other descriptors (a repeated ceiling whose
    rows were surveyed on other passes) is not among them, and a wider region may hold
    it: ``bench_heldout_texture.py --seed 1``'s repeated control from the right start
    pose, frame 30 (the prior 5 mm off, 1σ 0.19 m; the true pose unlisted, the mosaic
    explaining it as well: 0.95 against 0.96) published a tile off."""
    return prior is not None and prior.x_m is not None and prior.y_m is not None and \
        narrower_than(prior, 0.5 * o.window_twin_m)


def _told_apart(ncc: float, ncc2: float, differ: Any, twin_ncc: float,
                min_ncc: float) -> bool:
    """Whether the frame rules out a second pose (mosaic correlation ``ncc2``) against
    the best (``ncc``): more than ``twin_ncc`` below over the whole frame, or, called
    only when not, where the two mosaics differ (``differ()``: :func:`where_they_differ`)
    when the best explains the frame there (at least ``min_ncc``: a frame whose differing
    pixels are hidden or changed tells the two apart by chance, 5-11 % of random
    patches in review). NaN there, or off the mosaic: not ruled out."""
    if ncc2 < ncc - twin_ncc:
        return True
    if not math.isfinite(ncc2):
        return False
    a, b = differ()
    return bool(a >= min_ncc and b < a - twin_ncc)


def _standard(x: np.ndarray, where: np.ndarray) -> np.ndarray:
    v = x[where]
    return (x - v.mean()) / max(float(v.std()), 1e-9)


def _ncc(x: np.ndarray, y: np.ndarray) -> float:
    x, y = x - x.mean(), y - y.mean()
    d = math.sqrt(float(np.dot(x, x) * np.dot(y, y)))
    return float(np.dot(x, y) / d) if d > 0 else math.nan


def _hypotheses(s: _Search) -> tuple[Hypothesis, ...]:
    """The best pose, the runner-up and the best's twins the frame did not rule out
    (:meth:`TextureEstimator._twins`), weighted by their inlier counts."""
    fits = ((s.best, s.count, "best"), (s.runner, s.runner_count, "runner-up"),
            *((t, len(t.used), f"twin {i + 1}") for i, t in enumerate(s.twins)))
    total = float(sum(n for fit, n, _ in fits if fit is not None))
    out = []
    for fit, n, label in fits:
        if fit is None:
            continue
        out.append(Hypothesis(fit.pose[0], fit.pose[1], fit.pose[2], fit.cov, n / total, label))
    return tuple(out)


__all__ = ["NO_MAP_MATCH", "TOO_FEW_FEATURES", "TextureEstimator", "TextureOptions",
           "where_they_differ"]
