"""The reference-block method (Xu et al.): the vehicle pose from a known block or marker.

Per frame: markers (``cv2.aruco`` on crops around dark quads) and plain blocks (dark or
bright convex quads) are found (:mod:`.detect`); each is measured on its edges, matched
to the site (a marker by its id, a plain block by its size and shape on the ceiling), and
its pose solved by planar PnP (:mod:`.pnp`: closed form, then Gauss-Newton in pixels).
The best-determined fix (smallest position covariance) is published.

* A marker is unambiguous: its id and its corner order fix the correspondence. An id the
  site does not hold is ignored (``unknown_marker_ids`` in the diagnostics). Where the
  decimated search gives no marker fix (markers down to ``cv2.aruco``'s own limit, about
  3 px per cell, whose one-cell border the decimated, opened mask breaks), ``cv2.aruco``'s
  default detector reads the full frame (option ``marker_fallback``) and the markers it
  reads are measured and solved the same way (``aruco_fallback``: how many it read).
* A plain square block fits its corners in 4 ways, a rectangle in 2: with a prior, the
  fit nearest the prior is taken when it is clearly nearer than the next
  (``resolved_by: prior``, provenance ``PRIOR``, the twins the prior ruled out in
  ``hypotheses`` after the published pose); without one the frame is ``ambiguous``,
  its Failure carrying every fit as a :class:`~ceilkit.runtime.estimators.base.Hypothesis`
  (equal weights), even with the heading cue on. Never silently.
* The heading from the ceiling's parallels alone (a tile grid: known modulo 90°) is a
  heading-only estimate (``x_m = y_m = None``) carrying each branch as a hypothesis:
  never a full pose, never singled out.
* A plain block partly out of the frame or occluded is not used: its outline is then not
  a quadrilateral of the block's shape; when nothing else is seen and such an outline
  (a quad at the frame's edge, or a region of ``PARTIAL_AREA_PX`` or more that is not a
  quad) is, the frame fails with ``partial_block``. (A pose from a partial outline
  would rest on a guess of which corners are real.)

Diagnostics: ``ms``, ``source`` (``marker:ID`` or ``block:ID``), ``rms_px``, ``shape_m``
(the corners' fit on the ceiling), ``n_edge``, ``fixes`` (how many blocks and markers
gave a pose), ``unknown_marker_ids``, ``aruco_fallback`` (markers the fallback read),
and the 6-DoF check ``pnp6_tilt_deg``,
``pnp6_swing_deg``, ``pnp6_height_m`` (:func:`~.pnp.six_dof_check`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import cv2
import numpy as np

from ceilkit.runtime.config.site import check_rig_site
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
from ceilkit.runtime.estimators.block.detect import (
    DECIMATE,
    Sides,
    _cell_read,
    find_quads,
    measure_sides,
    side_lengths_m,
)
from ceilkit.runtime.estimators.block.fallback import MarkerReader
from ceilkit.runtime.estimators.block.parallels import (
    MAX_CHORDS,
    LinedSides,
    ParallelsHeading,
    ParallelsStage,
    _along,
)
from ceilkit.runtime.estimators.block.pnp import (
    RMS_BAD_PX,
    PlanarGeometry,
    PlanarSolver,
    TargetFix,
    _mount_tilt_swing,
    ceiling_points_vehicle,
    six_dof_check,
)
from ceilkit.runtime.estimators.block.twins import (
    BlockTwin,
    fit_hypotheses,
    heading_branches,
    target_twins,
    twin,
    with_twins,
)
from ceilkit.runtime.estimators.block.window import (
    WINDOW,
    OutlineFix,
    Target,
    Windows,
    shape_fits,
    targets_of,
)
from ceilkit.runtime.estimators.odometry import PlaneOdometry, with_increment
from ceilkit.runtime.estimators.prior import prior_choice
from ceilkit.runtime.features.quads import MarkerCodes, Quad, sharpen_quad, signed_area
from ceilkit.runtime.features.working import decimate
from ceilkit.runtime.geometry.rotations import wrap_pi

NO_BLOCK = "no_block"
PARTIAL_BLOCK = "partial_block"
UNKNOWN_MARKER = "unknown_marker"
PARTIAL_AREA_PX = 600.0     # a non-quad region this large may be a block cut short
COARSE_TOL = 0.25          # a coarse quad's perimeter may differ this much from a block's
PARALLELS_AGREE_SIGMA = 4.0  # a parallels heading farther than this many sigma from the
                             # block's is reported, not fused
HEADING_ONLY_QUALITY = 0.5  # quality of a heading-only cue (no position)
WINDOW_CHORDS = MAX_CHORDS  # chords for the parallels on a window fix: as many as the
                            # global path's (12 made the window's position median
                            # +0.011 mm worse, bench_paired clean; issue 38)


@dataclass(frozen=True)
class BlockOptions(EstimatorOptions):
    """Options of the block method.

    Attributes:
        shape_tol: how far (relative to the block's shortest side, RMS on the ceiling) a
            quad's corners may lie from the block's shape and still be that block.
        marker_size_tol: relative tolerance of a dark quad's side on the ceiling for it
            to be read as a marker.
        dark_ratio: a pixel darker than this fraction of the ceiling around it belongs
            to a dark block or a marker's black (the ceiling's seams are lighter).
        bright_ratio: a pixel brighter than this multiple of the ceiling belongs to a
            bright block.
        edge_points: edge stations per side for the refinement.
        six_dof_check: report the unconstrained 6-DoF PnP's disagreement with the rig.
        max_fixes: blocks and markers solved per frame (the best-determined of them is
            published): the dark quads first (markers, dark blocks), the largest in the
            image first, then the bright ones, searched only when the dark gave fewer;
            more cost time, not accuracy.
        parallels: heading from the ceiling's parallels (Xu eqs. 8-10) every frame,
            fused with a block's heading when both are seen.
        parallels_min_px: shortest image segment used as a parallel.
        parallels_gate_deg: a line farther than this from the heading (modulo the
            period) is not a parallel of the ceiling's axes.
        heading_cue: a frame with no block fix but two or more parallels gives a
            heading-only estimate (``x_m = y_m = None``, ``yaw_period_rad``) instead of a
            Failure (its reason is kept as ``diagnostics["no_fix"]``).
        plane_odometry: a frame with no block fix, and the first fix after such
            frames, carries the ceiling-plane odometry since the previous frame
            (:mod:`.odometry`) as ``diagnostics["increment"]`` for the fusion; other
            frames with a fix give no increment but still track the corners (KLT), so
            that the next leg starts from tracks carried at sub-pixel, not from
            fresh whole-pixel corners (docs/methods/block.md).
        window_search: with a prior (a position), measure the blocks and markers the
            prior puts fully in view on their predicted outlines (no search of the
            frame, :meth:`BlockEstimator._tracked`); the global path runs when the
            window check fails (it checks what the global path does: a block's inside
            all of its grey, a marker's code read), and every ``window_full_every``-th
            window fix. On by default (issue 38; docs/methods/block.md). (Formerly
            ``track``.)
        window_px: how far (px) a side may lie from its predicted place. (Formerly
            ``track_window_px``.)
        window_full_every: a global search after this many window fixes (0: only when
            the window check fails). (Formerly ``track_full_every``.)
        marker_fallback: where the decimated search gave no marker fix, run
            ``cv2.aruco``'s default detector (the site's dictionary) on the full frame
            and measure and solve the markers it reads (:meth:`.fallback.MarkerReader.aruco_fixes`):
            markers down to about 3 px per cell, whose one-cell border the decimated
            search loses (about 2-3 ms per frame at 640x480).
    """

    shape_tol: float = 0.08
    marker_size_tol: float = 0.3
    dark_ratio: float = 0.62
    bright_ratio: float = 1.3
    edge_points: int = 12
    six_dof_check: bool = True
    max_fixes: int = 1
    parallels: bool = True
    parallels_min_px: float = 60.0
    parallels_gate_deg: float = 1.0
    heading_cue: bool = True
    plane_odometry: bool = True
    window_search: bool = True
    window_px: float = 4.0
    window_full_every: int = 30
    marker_fallback: bool = True

    ALIASES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "track": "window_search", "track_window_px": "window_px",
        "track_full_every": "window_full_every"})


@dataclass(frozen=True, eq=False)
class _Ambiguous:
    """A symmetric block with no prior to pick its correspondence: every pose it fits."""

    hypotheses: tuple[Hypothesis, ...]


@dataclass
class _Counts:
    """A frame's quads that gave no fix: ambiguous (with the first such block's
    hypotheses), partly seen, not a block's size."""

    ambiguous: int = 0
    partial: int = 0
    skipped: int = 0
    hypotheses: tuple[Hypothesis, ...] = ()


def is_marker_size(pv: np.ndarray, sizes_m: np.ndarray, tol: float) -> bool:
    """A quad (coarse corners ``pv`` (4, 2) on the ceiling, V) of about the side of a
    marker of ``sizes_m``, within the share ``tol``."""
    side = float(np.mean(side_lengths_m(pv)))
    return bool(np.any(np.abs(side / sizes_m - 1.0) < tol))


class BlockEstimator(Estimator):
    """The vehicle pose from a reference block or a marker on the ceiling (see module)."""

    name = "block"
    Options = BlockOptions
    Solver = PlanarSolver      # the solve stage (:class:`.pnp.PlanarSolver`'s signature)
    site_sections = ("blocks", "markers")

    def __init__(self, rig: Any, site: Any,
                 options: BlockOptions | dict[str, Any] | None = None) -> None:
        site = _usable(site)
        super().__init__(rig, site, options)
        check_rig_site(rig, site)
        o = self.options
        _check_options(o)
        self.geo = PlanarGeometry.of(rig, site)
        markers = site.markers if site.has_section("markers") else None
        self._markers = markers
        self._codes = MarkerCodes(markers.dictionary) if markers else None
        if markers is not None:
            for k, p in enumerate(markers.poses):
                if not p.size_m > 0:
                    raise ConfigError(site.source, f"markers.poses[{k}].size",
                                      f"expected a side > 0 m, found {p.size_m}")
        self._sizes_m = np.array([p.size_m for p in markers.poses]) if markers else np.zeros(0)
        self._perimeters = [(float(np.sum(side_lengths_m(b.corners_m))), b.appearance != "bright")
                            for b in site.blocks]
        self._bright = any(b.appearance == "bright" for b in site.blocks)
        targets = targets_of(site, markers, o.shape_tol)
        # per polarity (dark?): whether every block of it is symmetric (4 or 2 ways)
        blocks = [t for t in targets if t.source.startswith("block:")]
        self._symmetric_only = {d: any(t.dark == d for t in blocks)
                                and all(t.symmetric for t in blocks if t.dark == d)
                                for d in (True, False)}
        self._dark = markers is not None or any(b.appearance != "bright" for b in site.blocks)
        self._heading = ParallelsStage(self.geo, site, o.parallels_min_px,
                                       o.parallels_gate_deg)
        self._lined = LinedSides(self._heading.corridor)
        self._solver = self.Solver(self.geo, self._lined)
        self._odo = PlaneOdometry(self.geo, site) if o.plane_odometry else None
        self._fixed = True      # the previous frame had a fix (no track to carry yet)
        self.windows = Windows(self.geo, targets, o, self._lined, self._codes)
        self._reader = (MarkerReader(self.geo, markers, self._codes, o.edge_points,
                                     self._solver) if markers is not None else None)
        self._fallback = self._reader if o.marker_fallback else None
        self._window_fixes = 0  # window fixes since the last global search
        # the small tables frame 0 made (issue 37): the marker read's samples and codes,
        # the site lines' array, the rig's mount angles
        if self._codes is not None:
            _cell_read(self._codes)
        if self._heading.corridor is not None:
            _along(tuple(self._heading.corridor.lines_along_m))
        _mount_tilt_swing(np.asarray(self.geo.R_vehicle_cam, np.float64).tobytes())

    def forget(self) -> None:  # Estimator.forget: pooled offsets, odometry image, counter
        self._solver.pooled.reset()
        self._fixed, self._window_fixes = True, 0
        if self._odo is not None:
            self._odo.reset()

    def _parallels(self, grey: np.ndarray, hint: float | None,
                   pose: np.ndarray | None = None, max_chords: int = MAX_CHORDS
                   ) -> ParallelsHeading | None:
        """The heading from the frame's ceiling parallels (:class:`.parallels.ParallelsStage`)."""
        return self._heading(grey, hint, pose, max_chords)

    # -- per frame ---------------------------------------------------------------------
    def _estimate(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
                  t0: float) -> Estimate:
        known = prior is not None and prior.x_m is not None and prior.y_m is not None
        got = self._tracked(grey, t_ns, prior, t0) if self.options.window_search and known else None
        if got is None:
            got = self._frame(grey, t_ns, prior, t0)
        if self._odo is None:
            return got
        fixed, gap = bool(got) and got.x_m is not None, not self._fixed
        self._fixed = fixed
        return with_increment(self._odo, got, grey, t_ns, not fixed or gap, prior, t0)

    def _frame(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate | None,
               t0: float) -> Estimate:
        o = self.options
        others: list[np.ndarray] = []
        small = decimate(grey, DECIMATE)
        fixes: list[TargetFix] = []
        unknown: list[int] = []
        n = _Counts()
        later: list[tuple[Quad, bool]] = []
        found = 0
        # the dark search flags the marker-sized spots the fallback reads (fallback.py)
        spots = self._fallback.spots() if self._fallback is not None and self._dark else None
        # the dark quads first (markers: an id, never ambiguous), the bright ones only
        # when those gave fewer than max_fixes fixes (their search is half the cost)
        for dark, wanted, ratio in ((True, self._dark, o.dark_ratio),
                                    (False, self._bright, o.bright_ratio)):
            if not wanted or len(fixes) >= o.max_fixes:
                continue
            quads = find_quads(grey, dark, ratio, others, small, spots if dark else None)
            found += len(quads)
            self._fixes(grey, [(q, dark) for q in sorted(quads, key=lambda q: -q.area_px)],
                        prior, fixes, unknown, n, later)
        fallback = 0      # cv2.aruco on the spots where the decimated search gave no marker
        if self._fallback is not None and len(fixes) < o.max_fixes and \
                not any(f.source.startswith("marker:") for f in fixes):
            fallback = self._fallback.aruco_fixes(grey, fixes, unknown, o.max_fixes, spots)
        for q, is_dark in later if not fixes else ():
            if len(fixes) >= o.max_fixes:
                break
            _count_block(self._block_fix(grey, sharpen_quad(q), is_dark, prior), fixes, n)
        diag = {"unknown_marker_ids": tuple(unknown), "quads": found,
                "quads_skipped": n.skipped, "aruco_fallback": fallback}
        if not fixes:
            got = self._fail(t_ns, n, unknown, others, diag, t0)
            if not self.options.parallels or got.hypotheses:
                return got    # a symmetric block's poses say more than the parallels' heading
            known = bool(prior) and prior.x_m is not None and prior.y_m is not None
            h = self._parallels(grey, prior.yaw_rad if prior else None,
                                np.array([prior.x_m, prior.y_m, prior.yaw_rad])
                                if known else None)
            if h is None or not self.options.heading_cue:
                return got
            cov = np.diag([np.inf, np.inf, h.sigma_rad ** 2])
            diag.update(no_fix=got.reason, yaw_period_rad=h.period_rad,
                        parallels_mode=self._heading.mode,
                        parallels_n=h.n_lines, parallels_sigma_rad=h.sigma_rad,
                        ms=elapsed_ms(t0))
            # known modulo the period only: every branch a hypothesis, never singled out
            return PoseEstimate(t_ns, self.name, None, None, h.yaw_rad,
                                HEADING_ONLY_QUALITY, cov=cov, diagnostics=diag,
                                hypotheses=heading_branches(h.yaw_rad, h.period_rad, cov))
        return self._publish(t_ns, fixes, diag, t0, grey)

    def _fixes(self, grey: np.ndarray, cands: list[tuple[Quad, bool]],
               prior: PoseEstimate | None, fixes: list[TargetFix], unknown: list[int],
               counts: _Counts, later: list[tuple[Quad, bool]]) -> None:
        """The quads ``(quad, dark)`` in their order, up to ``max_fixes`` fixes: their
        fixes, the marker ids not in the site and the counts added to ``fixes``,
        ``unknown``, ``counts``. Without a prior a quad that can only be a symmetric
        block (every block of its polarity fits itself turned, within ``shape_tol``)
        goes to ``later``, measured by the caller only when nothing else gave a fix:
        it is then ``ambiguous`` (or, for a block symmetric only within the tolerance,
        a fit by shape alone), so a marker beside it is preferred and costs no wasted
        measurement; the frame's reason is the same."""
        known = bool(prior) and prior.x_m is not None and prior.y_m is not None
        # every quad's coarse corners on the ceiling in one pass through the lens
        pvs = ceiling_points_vehicle(self.geo, self.geo.camera.unproject_fast(
            np.concatenate([q.corners_px for q, _ in cands]))).reshape(-1, 4, 2) \
            if cands else np.zeros((0, 4, 2))
        for (q, is_dark), pv in zip(cands, pvs, strict=True):
            if len(fixes) >= self.options.max_fixes:
                break
            if not np.isfinite(pv).all():
                continue
            if is_dark and self._codes is not None and \
                    is_marker_size(pv, self._sizes_m, self.options.marker_size_tol):
                q = sharpen_quad(q)
                got = self._reader.quad_fix(grey, q)
                if isinstance(got, (TargetFix, int)):
                    (fixes if isinstance(got, TargetFix) else unknown).append(got)
                    continue
            if not _may_be_block(self._perimeters, pv, is_dark):
                counts.skipped += 1
                if q.at_border:
                    counts.partial += any(d == is_dark for _, d in self._perimeters)
            elif not known and self._symmetric_only[is_dark]:
                later.append((q, is_dark))
            else:
                _count_block(self._block_fix(grey, sharpen_quad(q), is_dark, prior),
                             fixes, counts)

    # -- the window path (option window_search) ----------------------------------------
    def _tracked(self, grey: np.ndarray, t_ns: int, prior: PoseEstimate,
                 t0: float) -> PoseEstimate | None:
        """The fix from the targets measured where the prior puts them, or None (the
        global path decides): nothing in view, every window check failed
        (:meth:`.window.Windows.fix`), the fix lies outside the prior's region or a twin
        of it inside (a kidnap), or a global search is due."""
        o = self.options
        if o.window_full_every > 0 and self._window_fixes >= o.window_full_every:
            self._window_fixes = 0
            return None
        fixes, tried = self.windows.fixes(
            grey, np.array([prior.x_m, prior.y_m, prior.yaw_rad], float), self._window_fix,
            o.max_fixes)
        self._window_fixes = self._window_fixes + 1 if fixes else 0
        if not fixes:
            return None
        diag = {"unknown_marker_ids": (), "quads": tried, "quads_skipped": 0}
        out = self._publish(t_ns, fixes, diag, t0, grey, WINDOW)
        poses = [(h.x_m, h.y_m, h.yaw_rad, None) for h in out.hypotheses or (out,)]
        return out if prior_choice(prior, poses) == 0 else None     # estimators/prior.py

    def _window_fix(self, tgt: Target, got: OutlineFix) -> TargetFix:
        """A fix that passed the window check (:meth:`.window.Windows.fix`), pooled; a
        symmetric target's turns that also fit its shape are its twins (the prior chose)."""
        twins = target_twins(tgt.corners_w, self.options.shape_tol * tgt.min_side_m) \
            if tgt.symmetric else ()
        return TargetFix(tgt.source, self._solver.pooled(tgt.source, got.refined), got.shape_m,
                    got.sides.corners_norm, tgt.corners_w,
                    "prior" if tgt.symmetric else WINDOW, twins)

    def _fail(self, t_ns: int, n: _Counts, unknown: list[int],
              others: list[np.ndarray], diag: dict[str, Any], t0: float) -> Estimate:
        """The Failure of a frame with no fix, the most telling reason first."""
        ms = elapsed_ms(t0)
        if n.ambiguous:
            return self.fail(t_ns, AMBIGUOUS, "a symmetric block fits in several ways "
                             "and no prior tells them apart", hypotheses=n.hypotheses,
                             ms=ms, **diag)
        if n.partial or any(cv2.contourArea(c) >= PARTIAL_AREA_PX for c in others):
            return self.fail(t_ns, PARTIAL_BLOCK, "a block is only partly in view",
                             ms=ms, **diag)
        if unknown:
            return self.fail(t_ns, UNKNOWN_MARKER, f"marker ids {unknown} are not in "
                             "the site", ms=ms, **diag)
        return self.fail(t_ns, NO_BLOCK, "no block or marker of the site in view",
                         ms=ms, **diag)

    def _publish(self, t_ns: int, fixes: list[TargetFix], diag: dict[str, Any],
                 t0: float, grey: np.ndarray, mode: str = "global") -> PoseEstimate:
        """The published estimate of the best fix (``mode``: ``global`` or
        :data:`WINDOW`; the 6-DoF check of the mount runs on global fixes only)."""
        best = min(fixes, key=lambda f: f.refined.cov[0, 0] + f.refined.cov[1, 1])
        r = best.refined
        pose, cov = np.array(r.pose, float), np.array(r.cov, float)
        h = (self._parallels(grey, float(pose[2]), pose,
                             max_chords=WINDOW_CHORDS if mode == WINDOW else MAX_CHORDS)
             if self.options.parallels else None)
        if h is not None:
            diag.update(parallels_n=h.n_lines, parallels_yaw_rad=h.yaw_rad,
                        parallels_sigma_rad=h.sigma_rad, block_yaw_rad=float(pose[2]),
                        parallels_mode=self._heading.mode)
            diag["parallels_fused"] = _agrees(pose, cov, h)
            if diag["parallels_fused"]:
                pose, cov = _heading_update(pose, cov, h)
        diag.update(source=best.source, rms_px=r.rms_px, shape_m=best.shape_m,
                    n_edge=r.n, fixes=len(fixes), resolved_by=best.resolved_by,
                    corners_norm=best.corners_norm, corners_w=best.corners_w)  # overlays
        diag["mode"] = mode
        if self.options.six_dof_check and mode != WINDOW:
            diag.update(six_dof_check(self.geo, best.corners_norm, best.corners_w,
                                      float(r.pose[2])))
        quality = min(max(1.0 - float(r.rms_px) / RMS_BAD_PX, 0.0), 1.0)
        if best.resolved_by == "prior":
            quality = min(quality, 0.7)
        diag["ms"] = elapsed_ms(t0)
        # a correspondence its prior chose among twins is the prior's, on either path
        provenance = (Provenance.PRIOR if best.resolved_by == "prior" else
                      Provenance.WINDOW if mode == WINDOW else Provenance.GLOBAL)
        return PoseEstimate(t_ns, self.name, float(pose[0]), float(pose[1]),
                            wrap_pi(float(pose[2])), quality, cov=cov, diagnostics=diag,
                            provenance=provenance, hypotheses=with_twins(pose, cov, best.twins))

    def _block_fix(self, grey: np.ndarray, quad: Quad, dark: bool,
                   prior: PoseEstimate | None) -> TargetFix | _Ambiguous | str | None:
        """A fix from a plain quad, every pose it fits when no prior picks one
        (:class:`_Ambiguous`), the reason it gave none (``partial_block``) or None (not
        a block of the site)."""
        sides = measure_sides(grey, quad.corners_px, self.geo, self.options.edge_points,
                              passes=1)
        if sides is None:
            return PARTIAL_BLOCK if quad.at_border else None
        pv = ceiling_points_vehicle(self.geo, sides.corners_norm)
        if not np.all(np.isfinite(pv)):
            return None
        # the camera sees the ceiling mirrored: counter-clockwise from above is wanted
        cn = sides.corners_norm
        if signed_area(pv) < 0:
            pv, cn = pv[::-1].copy(), cn[::-1].copy()
            sides = Sides(cn, sides.edge_norm, (2 - sides.side) % 4, sides.stations)
        fits = shape_fits(self.site.blocks, pv, dark, self.options.shape_tol)
        if not fits:
            return PARTIAL_BLOCK if quad.at_border else None
        every = [b.corners_m[(np.arange(4) + k) % 4] for b, k, _, _ in fits]
        twins: tuple[BlockTwin, ...] = ()
        if len(fits) > 1:
            pick = _pick_by_prior(fits, prior)
            if pick is None:     # every fit a hypothesis; None: the edges do not fit (as a fix)
                hyps = fit_hypotheses(self.geo, sides, fits, every, self._lined(every[0]),
                                      RMS_BAD_PX)
                return _Ambiguous(hyps) if hyps else PARTIAL_BLOCK if quad.at_border else None
            twins = tuple(twin(every[pick], c) for k, c in enumerate(every) if k != pick)
            blk, shift, _, _ = fits[pick]
            resolved = "prior"
        else:
            blk, shift, _, _ = fits[0]
            resolved = "shape"
        corners_w = blk.corners_m[(np.arange(4) + shift) % 4]
        got = self._solver(sides, corners_w, f"block:{blk.id}", resolved)
        if got is not None and twins:
            got = dataclasses.replace(got, twins=twins)
        return PARTIAL_BLOCK if got is None and quad.at_border else got



def _may_be_block(perimeters: list[tuple[float, bool]], pv: np.ndarray, dark: bool) -> bool:
    """The coarse quad ``pv`` (V) is about the size of a block of its polarity: its
    perimeter on the ceiling within :data:`COARSE_TOL` (relative) of one of
    ``perimeters`` ``(perimeter, dark)`` (a cheap gate before its edges are measured)."""
    per = float(np.sum(side_lengths_m(pv)))
    return any(abs(per / p - 1.0) < COARSE_TOL for p, d in perimeters if d == dark)


def _count_block(got: Any, fixes: list[TargetFix], counts: _Counts) -> None:
    """A block's outcome: its fix kept, or counted (ambiguous, with the first such
    block's hypotheses; partial)."""
    if isinstance(got, TargetFix):
        fixes.append(got)
    elif isinstance(got, _Ambiguous):
        counts.ambiguous += 1
        if not counts.hypotheses:
            counts.hypotheses = got.hypotheses
    elif got == PARTIAL_BLOCK:
        counts.partial += 1


def _check_track_options(o: BlockOptions) -> None:
    """ConfigError naming ``options.KEY`` of the first impossible window-path option."""
    for key, ok, want in (("window_px", o.window_px > 0, "a number > 0"),
                          ("window_full_every", o.window_full_every >= 0, "an integer >= 0")):
        if not ok:
            raise ConfigError(None, f"options.{key}",
                              f"expected {want}, found {getattr(o, key)!r}")


def _heading_update(pose: np.ndarray, cov: np.ndarray, h: ParallelsHeading
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One Kalman update of the block's ``(x, y, yaw)`` by the parallels' heading."""
    s2 = cov[2, 2] + h.sigma_rad ** 2
    gain = cov[:, 2] / s2
    pose = pose + gain * math.remainder(h.yaw_rad - pose[2], 2 * math.pi)
    cov = cov - np.outer(gain, cov[2, :])
    return pose, 0.5 * (cov + cov.T)


def _check_options(o: BlockOptions) -> None:
    """One-line errors for the options that cannot work (the window path's too)."""
    for key in ("shape_tol", "marker_size_tol", "dark_ratio", "bright_ratio"):
        if not getattr(o, key) > 0:
            raise ConfigError(None, f"options.{key}", f"expected > 0, found {getattr(o, key)}")
    if o.max_fixes < 1:
        raise ConfigError(None, "options.max_fixes",
                          f"expected at least 1, found {o.max_fixes}")
    if not o.parallels_min_px > 0 or not o.parallels_gate_deg > 0:
        raise ConfigError(None, "options.parallels_gate_deg",
                          "expected parallels_min_px and parallels_gate_deg > 0")
    if o.edge_points < 4:
        raise ConfigError(None, "options.edge_points",
                          f"expected at least 4, found {o.edge_points}")
    _check_track_options(o)


def _usable(site: Any) -> Any:
    """The site without the blocks and markers reaching into an ``ignore`` region (SPEC
    §2: no method uses them); a ConfigError when none is left."""
    used = site.without_ignored()
    if site.ignore_m and not (used.has_section("blocks") or used.has_section("markers")):
        raise ConfigError(site.source, "ignore", "every block and marker reaches into an "
                          "ignore region: the block method has nothing to use")
    return used


def _pick_by_prior(fits: list, prior: PoseEstimate | None) -> int | None:
    """Index of the only fit the prior allows (:func:`~..prior.prior_choice`), or None
    (no prior, none allowed: the frame contradicts it, or several)."""
    if prior is None or not prior or prior.x_m is None or prior.y_m is None:
        return None
    return prior_choice(prior, [(x, y, yaw, None) for _, _, _, (x, y, yaw) in fits])


def _agrees(pose: np.ndarray, cov: np.ndarray, h: ParallelsHeading) -> bool:
    """Whether the parallels' heading is within :data:`PARALLELS_AGREE_SIGMA` of a
    block's (their combined sigma): only then is it fused."""
    dyaw = math.remainder(h.yaw_rad - pose[2], 2 * math.pi)
    return abs(dyaw) <= PARALLELS_AGREE_SIGMA * math.sqrt(cov[2, 2] + h.sigma_rad ** 2)
