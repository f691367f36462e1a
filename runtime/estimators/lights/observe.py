"""What one frame shows of the lights: spots, their ceiling points, and which map
lights a pose should show.

:class:`SpotObserver` runs the detector, keeps the spots whose size and shape fit a
light of the known diameter at their place in the image (or, for rectangular lamps
(``light_size``), the lamp's rectangle projected at the spot's own orientation, its
centroid offset taken off, lamps cut by the frame or the lens's edge dropped and
those near it marked weak: :meth:`SpotObserver._rectangles`; in a raw frame the lens's
fall-off divided out first: :func:`falloff_gain`), and gives each its ceiling
point in V (:func:`~ceilkit.runtime.estimators.lights.rays.ceiling_points`) and its
pixel Jacobian (from a table). :class:`VisibilityTable` answers, for a pose, which
map lights the detector should report (a lookup, not a projection).

Convention: ceiling points ``(x, y)`` in V, metres; pixels distorted (SPEC §1).

Example::

    obs = SpotObserver(rig, 3.0, 0.08, SpotParams(), mask, nadir, 12).observe(grey)
    obs.q_v, obs.jac_px, obs.order            # (N, 2), (N, 2, 2), (N,)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.estimators.ignore import ignored_from
from ceilkit.runtime.estimators.lights.rays import (
    GridTable,
    ceiling_points,
    ceiling_points_core,
    grid_row,
    jacobian_grid,
    mount_arrays,
    project_lights,
)
from ceilkit.runtime.features.spots import SpotParams, Spots
from ceilkit.runtime.features.windows import detect_spots_windowed
from ceilkit.runtime.features.working import decimated_mask, detect_spots_working
from ceilkit.runtime.geometry.ceiling import KernelMount, PlanarGeometry, kernel_mount
from ceilkit.runtime.jit import arr, njit, warmer

JAC_STEP_PX = 8  # node spacing of the per-pixel spot table
VIEW_MARGIN_PX = 12.0  # a light's centre this far inside the image border is reported
RIM_MARGIN_PX = 1.5  # ... and a disc of RIM_REACH x its radius this far: nearer the
RIM_REACH = 1.6      # border its centroid is pulled inwards (a cut light, or one whose outer
# part the local threshold loses: the frame's mirrored border raises it), 1-7 px on the
# corridor rig's 18 px lights within 10 px of the border, 0.1 px beyond (bench_fusion mixed)
MAX_BUDGET_FACTOR = 4  # regions examined at most: this many times max_spots
DISC_POINTS = 24  # a light's outline, for its image centroid
WEAK_WEIGHT = 0.5
"""A weak spot's weight as evidence (:meth:`Observation.weights`): a light near the
frame's or the lens's edge may be a fragment, a reflection or a cut lamp."""
RECT_SIDE_POINTS = 8  # points per side of a rectangular light's outline (a fisheye bends it)
RECT_CUT_REACH = 1.15  # a rectangle this much larger must lie inside the frame and the view
RECT_WEAK_REACH = 1.8  # ... and this much larger, else the spot is weak
RECT_BLUR_PX2 = 0.8  # the optics' blur in the observed second moments, px²
RECT_AREA = (0.4, 2.2)  # observed / predicted area of a rectangle's spot
DISC_AREA_MAX = 5.0  # most a disc's spot area exceeds its prediction (plausible_spot)
RECT_MOMENTS = (0.3, 3.0)  # eigenvalues of C_pred⁻¹ S_obs (whitened second moments)
# A region that falls short of its rectangle by more than this (px: the area missing over
# the perimeter) is a fragment of its lamp: part of it under the threshold (a lamp clipped
# at one end and not at the other, whose unclipped part the Niblack window hollowed).
# Over 15 raw held-out lamp drives, kept spots short by 0.5-1.5 px lay 0.5 cm median (1.0
# max) from their lamps, by 1.5-3 px 1.0 cm (3.0 max: 19 spots), by more than 3 px 4-30
# cm (19 spots; held-out lamps1 of seed 31: two of them turned a pose 2.8 deg). A
# thresholded edge moves by about a pixel: no two-level spot was short by more than 1.5.
RECT_SHORT_PX = 1.5
RECT_ITERATIONS = 2  # centroid-offset corrections of a rectangle's centre
AXIS_MIN_ELONGATION = 1.5  # a spot shows its lamp's axis when its second moments' ratio
# (on the ceiling) is at least this: see twins.TwinJudge.aligned
BLOOM_ARC_POINTS = 4  # points per rounded corner of a bloomed lamp's outline (bloom_outline)
BLOOM_STEPS = 2  # corrections of a bloom's dilation to the spot's area (SpotObserver._bloomed)
# A frame's blooms share one dilation, smooth across the view (the threshold cuts every
# lamp's halo alike, the lens's fall-off changes it slowly): held-out 0/255 and raw drives
# (bench_heldout_lights seeds 13 and 19, lamps0 and lamps2, every 10th frame) put each
# single lamp's bloom at 0.76-1.25 times its frame's median, two lamps (or a lamp and a
# light) merged into one region at 1.85-1.94 times. A bloom is kept within BLOOM_SPREAD
# times the median of at least BLOOM_MIN_SPOTS blooms in its frame.
BLOOM_SPREAD = 1.5
BLOOM_MIN_SPOTS = 3
# ... counted with the run's recent blooms (BloomPool): under a pinhole one or two lamps
# are in view, and bloom beyond their rectangle's size check one at a time (held-out
# lamps0 of seed 7: one bloom in 21 of 22 frames measured)
BLOOM_MEMORY = 32
# A two-level frame's lamp whose region reaches this far beyond its rectangle (px: the
# area beyond it over its perimeter) is tried as a bloom even when the rectangle's size
# check passes: the threshold cut its halo nearer the lamp on the side away from the
# image centre, and its rectangle's centroid was 5-10 cm off (held-out lamps0 of seed 7,
# 13,000-15,000 px regions of 7,000 px lamps). Unbloomed two-level lamps reach -0.7 to
# 0.5 px (10th-90th percentile, the rc drives of seeds 7 and 13).
BLOOM_MIN_PX = 2.0
BLOOM_CENTRE_SHARE = 0.045
"""A bloomed lamp's centre error, per axis on the ceiling, as a share of its dilation
(its frame's error of that light, added to the fit's covariance in ``refine.map_cov``'s
form as a map error is: estimator.refine_candidate):
the held-out bloomed drives (seed 13 ``lamps0``, seed 19 ``lamps0`` and ``lamps2``; every
5th frame at the true pose, 702 spots) put it at 0.027, 0.024 and 0.070 rms of the
dilation, 0.045 pooled."""
EDGE_FIT_MIN = 4  # spots a two-level frame's threshold shift across the frame is fitted on
EDGE_SHIFT_MAX_PX = 1.0  # most a spot's centroid is moved for that shift (px)
FALLOFF_STEP = 4  # a raw frame's fall-off is read on every 4th pixel each way (falloff_gain)
FALLOFF_BINS = 16  # ... in this many rings of equal rho² width
FALLOFF_QUANTILE = 25.0  # ... each ring's ceiling grey: this percentile of its pixels
FALLOFF_MIN_PX = 40  # ... of a ring that holds at least this many
FALLOFF_MIN_RINGS = 6  # ... at least this many rings explained by the fit
FALLOFF_MAX_RESIDUAL = 0.03  # ... the fit leaving no ring further off (of the centre's level)
VIEW_PATCHES = (8, 6)
"""The image's patches (across, down) a light's detection rate is learned in
(:class:`~.twins.DetectionRates`): a tilted lens images the ceiling at one distance from
its centre near on one side and far on the other, so the rate goes by place, not radius."""
WINDOW_LIGHTS = 1.6  # the Niblack window spans at least this many of a light's typical image


@dataclass(frozen=True, eq=False)
class Observation:
    """The usable spots of one frame.

    Attributes:
        spots: the detected spots that passed the size and shape checks (N).
        q_v: ``(N, 2)`` their ceiling points in V, metres.
        order: ``(N,)`` a reliability order, nearest the camera first.
        jac_px: ``(N, 2, 2)`` d(pixel)/d(ceiling point in V) at each spot, px per metre.
    """

    spots: Spots
    q_v: np.ndarray
    order: np.ndarray
    jac_px: np.ndarray
    candidates_px: np.ndarray | None = None  # every examined spot's centroid (overlays)
    kept: np.ndarray | None = None  # which of them passed the checks (None: all)
    weak: np.ndarray | None = None  # (N,) bool: near the frame's or the lens's edge
    # (N,) a rectangle's long side in V, rad (mod pi); NaN where the spot is too round to
    # show it (its second moments' ratio under AXIS_MIN_ELONGATION)
    axis_v: np.ndarray | None = None
    # the principal point (px) when the frame holds two grey levels only (stored as
    # 0/255): its spots' centroids may share a radial shift (see two_level)
    centre_px: np.ndarray | None = None
    # (N,) how far a rectangular lamp's spot reaches beyond its projected rectangle (px:
    # the area beyond it over its perimeter; SpotObserver._rectangles): a bloom, a
    # fixture merged with the lamp
    excess_px: np.ndarray | None = None
    # the principal point (px) of every frame: the centre of the radial shift its
    # intensity-weighted centroids share (refine.pattern_cover)
    principal_px: np.ndarray | None = None
    # (R,) the ceiling points in V of the regions examined and not kept, as x + iy: a
    # bright region where a light may be that the checks could not measure (a bloomed
    # or cut lamp), so a map light there is not missing (twins.TwinJudge.present)
    rejected_v: np.ndarray | None = None
    # (N,) the dilation (m) a bloomed lamp's centre error is a share of
    # (BLOOM_CENTRE_SHARE): its region's reach beyond its rectangle on the ceiling
    # (SpotObserver._bloomed), at least the median of the frame's and the run's blooms
    # (one cut short by the fall-off is no better placed); 0 for a spot its rectangle fits
    bloom_m: np.ndarray | None = None
    # the frame's blooms for the run's pool (BloomPool.added): (u, s) of every spot
    # tried as a bloomed lamp whose dilation lies within bounds, kept or not
    blooms_seen: tuple[np.ndarray, np.ndarray] | None = None
    # the run's detection rates across the view (twins.DetectionRates): how likely a map
    # light the frame should show is found; None until the run has missed one
    detect: Any = None

    def weights(self) -> np.ndarray:
        """``(N,)`` each spot's weight as evidence: 1, :data:`WEAK_WEIGHT` for a weak
        one (a light near the frame's or the lens's edge)."""
        w = np.ones(len(self.spots))
        if self.weak is not None:
            w[self.weak] = WEAK_WEIGHT
        return w

    def outside(self, site, pose) -> Observation:
        """Without the spots whose ceiling point lies in one of the site's ``ignore``
        regions seen from ``pose`` (``x_m``, ``y_m``, ``yaw_rad``: a prior; SPEC §2),
        itself when there is none or the pose has no position."""
        hit = ignored_from(site, self.q_v, pose)
        if hit is None or not hit.any():
            return self
        keep = ~hit
        new = np.cumsum(keep) - 1
        kept = self.kept
        if self.candidates_px is not None:      # the overlays: an ignored one is rejected
            kept = np.ones(len(self.candidates_px), bool) if kept is None else kept.copy()
            kept[np.flatnonzero(kept)[~keep]] = False
        return dataclasses.replace(self, spots=self.spots.select(keep), q_v=self.q_v[keep],
                                   order=new[self.order[keep[self.order]]],
                                   jac_px=self.jac_px[keep], kept=kept,
                                   weak=None if self.weak is None else self.weak[keep],
                                   axis_v=None if self.axis_v is None else self.axis_v[keep],
                                   excess_px=None if self.excess_px is None
                                   else self.excess_px[keep],
                                   bloom_m=None if self.bloom_m is None else self.bloom_m[keep])


@dataclass(frozen=True, eq=False)
class BloomPool:
    """A run's recent blooms (:meth:`SpotObserver._bloomed`): each spot's ``u`` (its
    squared distance from the principal point over the half diagonal's) and dilation
    ``s`` (m), the last :data:`BLOOM_MEMORY`. A frame's blooms are judged with them: the
    median a bloom must lie near and the slope of the dilation across the view are
    the run's, which one lamp in view cannot give. Held by the estimator between
    frames (``LightsEstimator.forget`` empties it); empty, a frame is judged alone."""

    u: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def added(self, seen: tuple[np.ndarray, np.ndarray] | None) -> BloomPool:
        """The pool with a frame's ``blooms_seen`` added (the oldest dropped past
        :data:`BLOOM_MEMORY`); itself when there are none."""
        if seen is None or seen[0].size == 0:
            return self
        return BloomPool(np.concatenate([self.u, seen[0]])[-BLOOM_MEMORY:],
                         np.concatenate([self.s, seen[1]])[-BLOOM_MEMORY:])


class GridArrays(NamedTuple):
    """The spot table as the compiled loops read it: a :class:`~.rays.GridTable`'s
    ``coef`` and ``limits`` (read-only float64; :func:`~.rays.grid_row`)."""

    coef: np.ndarray
    limits: np.ndarray


class SpotChecks(NamedTuple):
    """The checks :func:`examine_core` applies to a spot: the light's ``radius_m``
    (0: none), the frame's ``width`` and ``height`` (px), and :func:`uncut_spot`'s
    ``rim_reach`` (:data:`RIM_REACH`) and ``rim_margin_px`` (:data:`RIM_MARGIN_PX`)."""

    radius_m: float
    width: int
    height: int
    rim_reach: float
    rim_margin_px: float


def kernel_rig(rig: Rig, ceiling_height_m: float) -> KernelMount:
    """The rig and the ceiling's height (W's z, m) as the compiled loops take them
    (:class:`~ceilkit.runtime.geometry.ceiling.KernelMount`; the mount's arrays those of
    :func:`~.rays.mount_arrays`)."""
    R_vc, t_vc = mount_arrays(rig.mount)
    return kernel_mount(PlanarGeometry(rig.camera, R_vc, t_vc, float(ceiling_height_m)))


def disc_offsets(rig: Rig, ceiling_height_m: float, light_radius_m: float,
                 step_px: int = JAC_STEP_PX) -> np.ndarray:
    """``(GH, GW, 2)`` on the table's nodes: the area centroid of a light's disc
    (radius ``light_radius_m``, centred on the node's ceiling point) as the camera sees
    it, minus the node. Perspective moves a disc's image centroid off the image of its
    centre, towards the side seen larger (for a camera tilted 45 deg, 2.5 m below 8 cm
    lights, up to about a pixel); the observed centroid minus this is the image of the
    light's centre. Zero for ``light_radius_m`` 0; NaN where no ray rises."""
    cam = rig.camera
    us = np.arange(0, cam.width - 1 + step_px, step_px, dtype=float)
    vs = np.arange(0, cam.height - 1 + step_px, step_px, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    px = np.stack([uu.ravel(), vv.ravel()], 1)
    out = np.zeros((px.shape[0], 2))
    if light_radius_m > 0:
        q, ok = ceiling_points(rig, ceiling_height_m, px)
        th = np.linspace(0.0, 2 * math.pi, DISC_POINTS, endpoint=False)
        ring = light_radius_m * np.stack([np.cos(th), np.sin(th)], 1)
        pts = (q[:, None, :2] + ring[None]).reshape(-1, 2)
        img = project_lights(rig, ceiling_height_m, pts, 0.0, 0.0, 0.0).reshape(-1, th.size, 2)
        out = polygon_centroids(img) - px
        out[~ok] = np.nan
    return out.reshape(vs.size, us.size, 2)


def rectangle_outline(length_m: float, width_m: float,
                      per_side: int = RECT_SIDE_POINTS) -> np.ndarray:
    """``(4 per_side, 2)`` points around a ``length x width`` rectangle centred on 0,
    its long side along x, counter-clockwise."""
    t = np.arange(per_side) / per_side
    hl, hw = 0.5 * length_m, 0.5 * width_m
    sides = [np.stack([-hl + 2 * hl * t, np.full_like(t, -hw)], 1),
             np.stack([np.full_like(t, hl), -hw + 2 * hw * t], 1),
             np.stack([hl - 2 * hl * t, np.full_like(t, hw)], 1),
             np.stack([np.full_like(t, -hl), hw - 2 * hw * t], 1)]
    return np.concatenate(sides)


def bloom_outline(length_m: float, width_m: float, per_side: int = RECT_SIDE_POINTS,
                  arc: int = BLOOM_ARC_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """``(base, out)``, each ``(4 (per_side + arc), 2)``: the ``length x width``
    rectangle (centred on 0, long side along x) dilated by ``s`` is ``base + s out``,
    counter-clockwise: its sides moved out by ``s`` (:func:`rectangle_outline`'s points
    along their normals) and its corners rounded with radius ``s`` (``arc`` points a
    quarter circle). At ``s = 0`` it is the rectangle (the corners repeated)."""
    sides = rectangle_outline(length_m, width_m, per_side).reshape(4, per_side, 2)
    hl, hw = 0.5 * length_m, 0.5 * width_m
    normals = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    ends = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])  # each side's last corner
    base, out = [], []
    for k in range(4):
        phi = math.atan2(normals[k, 1], normals[k, 0]) + 0.5 * math.pi * np.arange(arc) / arc
        base += [sides[k], np.repeat(ends[k:k + 1], arc, axis=0)]
        out += [np.repeat(normals[k:k + 1], per_side, axis=0),
                np.stack([np.cos(phi), np.sin(phi)], axis=1)]
    return np.concatenate(base), np.concatenate(out)


def bloomed_area(length_m: float, width_m: float, s_m: float) -> float:
    """Area (m²) of a ``length_m x width_m`` rectangle dilated by ``s_m`` (Steiner's
    formula: its sides moved out, its corners rounded; :func:`bloom_outline`)."""
    return length_m * width_m + 2.0 * (length_m + width_m) * s_m + math.pi * s_m * s_m


def _project_rectangles(rig: Rig, ceiling_height_m: float, q_v: np.ndarray,
                        theta: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """``(K, P, 2)`` pixels of ``K`` rectangles on the ceiling: ``outline`` (``(P, 2)``,
    or ``(K, P, 2)`` one each) turned by ``theta (K,)`` about ceiling points ``q_v (K,
    2)`` in V."""
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    o = np.broadcast_to(outline, (q_v.shape[0],) + outline.shape[-2:])
    pts = np.stack([q_v[:, 0:1] + c * o[..., 0] - s * o[..., 1],
                    q_v[:, 1:2] + s * o[..., 0] + c * o[..., 1]], -1)
    k, p = pts.shape[:2]
    if k == 0:
        return np.zeros((0, p, 2))
    return project_lights(rig, ceiling_height_m, pts.reshape(-1, 2), 0.0, 0.0,
                          0.0).reshape(k, p, 2)


def polygon_moments(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(area (N,), cov (N, 2, 2))`` of ``N`` closed polygons ``(N, K, 2)``: the area
    (px²) and the central second moments per unit area (px²) of each (Green's theorem;
    either orientation)."""
    x, y = p[..., 0], p[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * yn - xn * y
    a = 0.5 * cr.sum(axis=1)
    mx, my = polygon_centroids(p).T
    with np.errstate(invalid="ignore", divide="ignore"):
        a_safe = np.where(np.abs(a) > 1e-12, a, np.nan)
        sxx = ((x * x + x * xn + xn * xn) * cr).sum(axis=1) / (12 * a_safe) - mx * mx
        syy = ((y * y + y * yn + yn * yn) * cr).sum(axis=1) / (12 * a_safe) - my * my
        sxy = ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * cr).sum(axis=1) \
            / (24 * a_safe) - mx * my
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    return np.abs(a), cov


def polygon_centroids(p: np.ndarray) -> np.ndarray:
    """``(N, 2)`` area centroids of ``N`` closed polygons ``(N, K, 2)`` (shoelace)."""
    x, y = p[..., 0], p[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * yn - xn * y
    a = cr.sum(axis=1)
    a = np.where(np.abs(a) > 1e-12, a, np.nan)
    return np.stack([((x + xn) * cr).sum(axis=1) / (3 * a),
                     ((y + yn) * cr).sum(axis=1) / (3 * a)], axis=1)


def two_level(grey: np.ndarray) -> bool:
    """Whether a uint8 frame holds only the levels 0 and 255 (thresholded before it was
    stored). A fixed threshold cuts a lamp where its blurred edge crosses it, and the
    lens's fall-off (vignetting) dims the lamp's outer edge: every centroid moves
    towards the image centre, by more the further out it lies. Measured (the RC-car
    scene of ``benchmarks/bench_rect_lamps.py``, 0/255 at 200, the simulator's
    vignetting 0.3): the lamps' true centre errors put 1.7x the variance per degree of
    freedom into the pose's directions as into the residuals', the fit's mean NEES 5.5
    for 3; with the vignetting at 0, 1.0 and 3.5; raw frames (intensity-weighted
    centroids), 1.0 and 3.3."""
    g = np.asarray(grey)
    if g.dtype != np.uint8:
        return False
    sample = g[::16, ::16]   # a raw frame shows mid levels nearly everywhere: settled here
    if np.any((sample > 0) & (sample < 255)):
        return False
    return not np.any((g > 0) & (g < 255))


class FalloffRings(NamedTuple):
    """Where a raw frame's fall-off is read (:func:`falloff_rings`, :func:`falloff_gain`)."""

    rho2: np.ndarray      # (H, W) float32: (distance from the principal point / half diagonal)²
    sample: np.ndarray    # (M,) flat pixel indices read, ring by ring
    starts: np.ndarray    # (R + 1,) each ring's first index into sample, and the end
    x: np.ndarray         # (R,) each ring's mean rho2


def falloff_rings(rig: Rig, valid_mask: np.ndarray) -> FalloffRings:
    """The rings a frame's fall-off is read in: every :data:`FALLOFF_STEP`-th pixel each
    way inside ``valid_mask``, in :data:`FALLOFF_BINS` rings of equal ``rho²`` width
    (``rho``: the distance from the principal point over the half diagonal; a lens's
    fall-off is a function of it), the rings of fewer than :data:`FALLOFF_MIN_PX` left
    out."""
    cam = rig.camera
    h, w = cam.height, cam.width
    u = (np.arange(w, dtype=np.float32) - np.float32(cam.cx))[None, :]
    v = (np.arange(h, dtype=np.float32) - np.float32(cam.cy))[:, None]
    rho2 = (u * u + v * v) / np.float32(0.25 * (w * w + h * h))
    grid = np.zeros((h, w), bool)
    grid[::FALLOFF_STEP, ::FALLOFF_STEP] = True
    sample = np.flatnonzero(grid & (valid_mask > 0))
    r2 = rho2.reshape(-1)[sample]
    hi = float(r2.max()) if r2.size else 1.0
    ring = np.minimum((r2 * (FALLOFF_BINS / max(hi, 1e-9))).astype(int), FALLOFF_BINS - 1)
    keep = np.bincount(ring, minlength=FALLOFF_BINS)[ring] >= FALLOFF_MIN_PX
    order = np.argsort(ring[keep], kind="stable")
    sample, r2, ring = sample[keep][order], r2[keep][order], ring[keep][order]
    starts = np.flatnonzero(np.r_[True, ring[1:] != ring[:-1], True])
    x = np.add.reduceat(r2, starts[:-1]) / np.diff(starts) if r2.size else np.zeros(0)
    return FalloffRings(rho2, sample, starts, x.astype(float))


def falloff_gain(grey: np.ndarray, rings: FalloffRings) -> tuple[float, float] | None:
    """``(b, c)`` of the frame's fall-off ``g = 1 + b rho² + c rho⁴`` (vignetting about
    the principal point; :func:`falloff_rings`), read off its ceiling: each ring's
    :data:`FALLOFF_QUANTILE` percentile (the ceiling's grey where lamps and their halos
    cover less than the rest of a ring), fitted by least squares weighted by the square
    root of the rings' counts; a ring the fit leaves more than
    :data:`FALLOFF_MAX_RESIDUAL` of the centre's level off is left out (the worst
    first: the dark corners beyond a fisheye's image, a wall) and the fit made again.
    ``None`` when fewer than :data:`FALLOFF_MIN_RINGS` rings are left (not a radial
    fall-off: a ceiling of two greys) or when the gain is outside (0.3, 1.05] in a kept
    ring (not what a lens does)."""
    g = grey.reshape(-1)[rings.sample]
    st = rings.starts
    ya = np.empty(len(st) - 1)
    for i in range(len(st) - 1):
        seg = g[st[i]:st[i + 1]]
        kth = int(FALLOFF_QUANTILE / 100.0 * (seg.size - 1))
        ya[i] = np.partition(seg, kth)[kth]
    xa, wa = rings.x, np.sqrt(np.diff(st).astype(float))
    while xa.size >= FALLOFF_MIN_RINGS:
        A = np.stack([np.ones_like(xa), xa, xa * xa], axis=1)
        coef = np.linalg.lstsq(A * wa[:, None], ya * wa, rcond=None)[0]
        if not coef[0] > 0:
            return None
        res = np.abs(ya - A @ coef)
        if res.max() <= FALLOFF_MAX_RESIDUAL * coef[0]:
            gain = A @ coef / coef[0]
            if gain.min() <= 0.3 or gain.max() > 1.05:
                return None
            return float(coef[1] / coef[0]), float(coef[2] / coef[0])
        keep = np.arange(xa.size) != int(np.argmax(res))     # the worst ring left out
        xa, ya, wa = xa[keep], ya[keep], wa[keep]
    return None


def deshaded(grey: np.ndarray, rho2: np.ndarray, bc: tuple[float, float]) -> np.ndarray:
    """``grey`` (uint8) divided by the fall-off ``1 + b rho² + c rho⁴``
    (:func:`falloff_gain`), rounded; a clipped pixel (255) stays 255 and no other
    reaches it (at most 254): which lamps hold a clipped plateau is the sensor's
    (``spots.lamp_mask`` reads it; made clipped, the unclipped 248-grey lamps of
    held-out ``lamps1`` of seed 3 were hollowed again)."""
    gain = rho2 * np.float32(bc[1])
    gain += np.float32(bc[0])
    gain *= rho2
    gain += np.float32(1.0)
    np.maximum(gain, np.float32(0.3), out=gain)
    out = cv2.min(cv2.divide(grey, gain, dtype=cv2.CV_8U), 254)
    return cv2.bitwise_or(out, cv2.compare(grey, 254, cv2.CMP_GT))


def edge_shift_px(p: np.ndarray, area_px: np.ndarray, centre_px: np.ndarray,
                  use: np.ndarray) -> np.ndarray:
    """``(N, 2)`` how far a fixed threshold moved each spot's centroid (px), for ``N``
    projected outlines ``p (N, K, 2)`` whose spots cover ``area_px (N,)`` in a
    two-level frame (:func:`two_level`).

    Each outline's edge is taken to have moved inwards by ``d_i = (A_i - area_i) /
    P_i`` (its area ``A_i`` less the spot's, over its perimeter ``P_i``), and ``d``
    to grow across the frame as ``a + b (r / r_max)²`` (``r`` from the principal point
    ``centre_px``; the lens's fall-off), fitted over the spots ``use`` (at least
    :data:`EDGE_FIT_MIN`, else no shift). Across an outline ``d`` then changes by
    ``g = 2 b r / r_max²`` per pixel outwards: the region loses a strip of varying
    width and its centroid moves by ``-(g / A) M_P n`` (``M_P`` the perimeter's second
    moment about the centroid, ``n`` the outward unit vector), capped at
    :data:`EDGE_SHIFT_MAX_PX`. Measured on the RC-car scene
    (``benchmarks/bench_rect_lamps.py``): ``d`` -0.3 px at the centre, +0.5 px at
    240 px; the kept lamps' median centre error 0.11 -> 0.08 px (989 spots, 90
    frames; 0.07 with no fall-off and no correction)."""
    n = p.shape[0]
    x, y = p[..., 0], p[..., 1]
    dx, dy = np.roll(x, -1, axis=1) - x, np.roll(y, -1, axis=1) - y
    cr = x * dy - dx * y                                  # x_i y_(i+1) - x_(i+1) y_i
    out = np.zeros((n, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        a2 = cr.sum(axis=1)                               # twice the signed area
        cx = ((2 * x + dx) * cr).sum(axis=1) / (3 * a2)
        cy = ((2 * y + dy) * cr).sum(axis=1) / (3 * a2)
        area = 0.5 * np.abs(a2)
        length = np.sqrt(dx * dx + dy * dy)
        per = length.sum(axis=1)
        mx, my = x + 0.5 * dx - cx[:, None], y + 0.5 * dy - cy[:, None]
        rx, ry = cx - centre_px[0], cy - centre_px[1]
        rad = np.sqrt(rx * rx + ry * ry)
        d = (area - area_px) / per
        ok = use & np.isfinite(d) & np.isfinite(rad) & (rad > 0) & (np.abs(d) < 2.0)
        if int(ok.sum()) < EDGE_FIT_MIN:
            return out
        u = (rad[ok] / rad[ok].max()) ** 2               # d = a + b u, least squares
        du, dd = u - u.mean(), d[ok] - d[ok].mean()
        if float(du @ du) < 1e-6 * ok.sum():
            return out
        g = 2.0 * float(du @ dd / (du @ du)) * rad / rad[ok].max() ** 2
        along = length * (mx * (rx / rad)[:, None] + my * (ry / rad)[:, None])
        wx, wy = (along * mx).sum(axis=1), (along * my).sum(axis=1)      # M_P n
        shift = np.stack([-(g / area) * wx, -(g / area) * wy], axis=1)
        size = np.sqrt(shift[:, 0] ** 2 + shift[:, 1] ** 2)
        shift *= np.minimum(1.0, EDGE_SHIFT_MAX_PX / np.maximum(size, 1e-12))[:, None]
    good = np.all(np.isfinite(shift), axis=1)
    out[good] = shift[good]
    return out


def fitted_spot_params(params: SpotParams, rig: Rig, ceiling_height_m: float,
                       extent_m: float, valid_mask: np.ndarray,
                       factor: int = 1) -> SpotParams:
    """``params`` with the detector's Niblack window grown to the lights' image:
    :data:`WINDOW_LIGHTS` times a light's median image extent over the view
    (``extent_m``: its diameter, m), where that exceeds ``params``'. The estimator fits
    it to round lights only: grown to rectangular lamps (1.6 long sides), the window
    let a raw frame's halo into the lamps' regions and the held-out lamps0 drive (seed
    3, 1.28 x 0.47 m lamps saturated, a 166 deg fisheye) went from 5.6 to 10.4 mm
    median from its start pose.

    The image sizes come from the ceiling-to-pixel Jacobian over the view
    (``valid_mask``; nodes every 16 px), in pixels of the frame decimated by ``factor``
    (:mod:`~ceilkit.runtime.features.working`). Inside a light that fills most of the
    window the local mean is near the light's own level, and the threshold above it
    (at least 1.2 times the mean) hollowed an unsaturated light into a ring of
    fragments: a 0.21 m disc 2.7 m above a 585 px pinhole, 46 px across, under the
    default 41 px window gave two fragments of 35 and 51 px, both rejected (issue 36's
    held-out grids). A window 1.6 light extents wide is a third filled at the light's
    centre, and a 250-level light on a 150-level ceiling passes whole. The median, not
    the largest, image: on a tilted rig the nearest lights are twice the median, and a
    window grown to them changes every other light's threshold (the default window
    stays on every packaged rig). The area bound is left: a region above it is
    re-thresholded as glare (:mod:`~ceilkit.runtime.features.spots`), and raising it
    to the lamps' largest image moved the held-out lamps0 drive's median error from
    8.7 to 12.1 mm (every 4th of its 0/255 frames, 1.3 x 0.56 m lamps under a 174 deg
    fisheye, the prior the truth moved 1 cm)."""
    if extent_m <= 0:
        return params
    J = view_jacobians(rig, ceiling_height_m, valid_mask)
    if J.shape[0] == 0:
        return params
    scale = float(np.median(np.linalg.norm(J, ord=2, axis=(1, 2)))) / factor
    window = max(params.window_px, int(math.ceil(WINDOW_LIGHTS * extent_m * scale)) | 1)
    if window == params.window_px:
        return params
    return dataclasses.replace(params, window_px=window)


def fitted_lamp_window(params: SpotParams, rig: Rig, ceiling_height_m: float,
                       length_m: float, valid_mask: np.ndarray,
                       factor: int = 1) -> SpotParams:
    """``params`` with ``lamp_window_px``, the second Niblack window of rectangular lamps
    (:func:`~ceilkit.runtime.features.spots.lamp_mask`): :func:`fitted_spot_params`'s
    window for a light of the lamp's length ``length_m``, where that exceeds
    ``params.window_px``; ``params`` unchanged otherwise. Only the regions of that
    window that hold no saturated plateau are used: an unsaturated lamp wider than the
    window is taken whole (the held-out lamps1 of seed 3: 0.82 x 0.50 m lamps at 248
    grey levels, 96 x 59 px under a 407 px pinhole, were fragments of 20-35 px under the
    41 px window and gave ``no_lights`` on every frame), a saturated one keeps the
    default window's region, without its halo."""
    grown = fitted_spot_params(params, rig, ceiling_height_m, length_m, valid_mask, factor)
    if grown.window_px == params.window_px:
        return params
    return dataclasses.replace(params, lamp_window_px=grown.window_px)


def view_jacobians(rig: Rig, ceiling_height_m: float, valid_mask: np.ndarray,
                   step: int = 16) -> np.ndarray:
    """``(K, 2, 2)`` the ceiling-to-pixel Jacobians at the nodes (every ``step`` px)
    of the view (``valid_mask``) where a ray rises."""
    J = jacobian_grid(rig, ceiling_height_m, step)
    gh, gw = J.shape[:2]
    vv, uu = np.meshgrid(np.minimum(np.arange(gh) * step, valid_mask.shape[0] - 1),
                         np.minimum(np.arange(gw) * step, valid_mask.shape[1] - 1),
                         indexing="ij")
    return J[(valid_mask[vv, uu] > 0) & np.all(np.isfinite(J), axis=(2, 3))]


def fitted_light_bound(params: SpotParams, rig: Rig, ceiling_height_m: float,
                       area_m2: float, upper: float, valid_mask: np.ndarray,
                       factor: int = 1) -> SpotParams:
    """``params`` with ``max_light_px``, the largest core the glare split keeps
    (:func:`~ceilkit.runtime.features.spots._split_glare`), grown to the largest image
    a light of ``area_m2`` (m², on the ceiling) has anywhere in the view
    (``|det J|`` at the nodes of :func:`view_jacobians`) times ``upper``, the most the
    size check that follows accepts over its prediction (:data:`RECT_AREA`'s upper
    bound for rectangles, :func:`plausible_spot`'s 5 for discs), in pixels of the frame
    decimated by ``factor``; ``params`` unchanged where that is below ``max_area_px``.

    A region over ``max_area_px`` (6000 px) is a glare halo or a light that large:
    re-thresholded to its core, which was then dropped when over ``max_area_px``
    too, so a lamp whose own image is larger (a 0.93 x 0.46 m lamp 2.5 m above a
    334 px pinhole: about 7,500 px) gave ``no_lights`` on every frame (held-out
    ``lamps0-2`` of seed 7). The halo stays out: the region is still split, only its
    core is kept up to the light's own size (an unsaturated lamp wider than the window
    is another matter: :func:`fitted_lamp_window`)."""
    if area_m2 <= 0:
        return params
    J = view_jacobians(rig, ceiling_height_m, valid_mask)
    if J.shape[0] == 0:
        return params
    det = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
    bound = int(math.ceil(upper * area_m2 * float(det.max()) / (factor * factor)))
    if bound <= params.max_area_px:
        return params
    return dataclasses.replace(params, max_light_px=bound)


def spot_table(rig: Rig, ceiling_height_m: float, light_radius_m: float) -> np.ndarray:
    """``(GH, GW, 10)`` per-node table (nodes every :data:`JAC_STEP_PX` px): the pixel
    Jacobian ``J`` (4, row-major), ``C⁻¹`` of the predicted spot moments (00, 01, 11),
    the predicted area (see :func:`plausible_spot`) and the disc's centroid
    offset (u, v; :func:`disc_offsets`); NaN where no ray rises."""
    J = jacobian_grid(rig, ceiling_height_m, JAC_STEP_PX)
    gh, gw = J.shape[:2]
    J = J.reshape(-1, 2, 2)
    fin = np.all(np.isfinite(J), axis=(1, 2))
    Jf = np.where(fin[:, None, None], J, 1.0)
    r2 = light_radius_m ** 2
    C = 0.25 * r2 * np.einsum("nij,nkj->nik", Jf, Jf) + 0.8 * np.eye(2)
    Ci = np.linalg.inv(C)
    a_pred = math.pi * r2 * np.abs(np.linalg.det(Jf))
    off = disc_offsets(rig, ceiling_height_m, light_radius_m).reshape(-1, 2)
    out = np.concatenate([J.reshape(-1, 4), Ci[:, 0, 0:1], Ci[:, 0, 1:2], Ci[:, 1, 1:2],
                          a_pred[:, None], np.nan_to_num(off)], axis=1)
    out[~fin] = np.nan
    return out.reshape(gh, gw, 10)


def polygon_perimeters(p: np.ndarray) -> np.ndarray:
    """``(N,)`` perimeters of ``N`` closed polygons ``(N, K, 2)``."""
    return np.linalg.norm(np.roll(p, -1, axis=1) - p, axis=2).sum(axis=1)


def bloom_slope(u: np.ndarray, s: np.ndarray, good: np.ndarray) -> float:
    """The slope ``b`` of a frame's bloom dilations ``s (K,)`` (m) against ``u (K,)``
    (the spots' squared distance from the principal point over the half diagonal's),
    least squares over the ``good`` ones: 0 for fewer than :data:`BLOOM_MIN_SPOTS` or
    ``u`` spread too little to measure it."""
    if int(good.sum()) < BLOOM_MIN_SPOTS:
        return 0.0
    du = u[good] - u[good].mean()
    den = float(du @ du)
    if den < 1e-4 * good.sum():
        return 0.0
    return float(du @ (s[good] - s[good].mean()) / den)


def lamp_axes(J: np.ndarray, S: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(det, good, theta, shows)`` of ``K`` spots: the local ceiling-to-pixel
    Jacobians' determinants ``J (K, 2, 2)`` and where they are usable, the long axis in V
    (rad, mod pi) of each spot's second moments ``S (K, 2, 2)`` taken to the ceiling
    (``J⁻¹ (S - blur) J⁻ᵀ``, the optics' blur :data:`RECT_BLUR_PX2` off), and whether the
    spot is elongated enough to show it (:data:`AXIS_MIN_ELONGATION`)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    good = np.isfinite(det) & (np.abs(det) > 1e-9)
    Ji = np.linalg.inv(np.where(good[:, None, None], J, np.eye(2)))
    lo = np.linalg.eigvalsh(S)[:, 0]
    blur = np.minimum(RECT_BLUR_PX2, 0.5 * np.maximum(lo, 0.0))
    M = Ji @ (S - blur[:, None, None] * np.eye(2)) @ np.swapaxes(Ji, 1, 2)
    theta = 0.5 * np.arctan2(2 * M[:, 0, 1], M[:, 0, 0] - M[:, 1, 1])
    lam = np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, 1, 2)))
    with np.errstate(invalid="ignore", divide="ignore"):
        shows = lam[:, 1] >= AXIS_MIN_ELONGATION * np.maximum(lam[:, 0], 0.0)
    return det, good, theta, shows


def judged_blooms(u: np.ndarray, s: np.ndarray, bounded: np.ndarray, pool: BloomPool
                  ) -> tuple[np.ndarray, float, float]:
    """``(good (K,), b, median)``: which of a frame's blooms ``s (K,)`` (m, at ``u
    (K,)``) are a single lamp's, the dilation's slope ``b`` across the view
    (:func:`bloom_slope`) and the blooms' median, judged together with the run's recent
    blooms ``pool``
    (:class:`BloomPool`). A bloom is kept when ``bounded`` and within
    :data:`BLOOM_SPREAD` times the median of at least :data:`BLOOM_MIN_SPOTS`, the
    frame's ``bounded`` ones and the pool's; the slope is fitted over those alike."""
    pu = np.concatenate([pool.u, u[bounded]])
    ps = np.concatenate([pool.s, s[bounded]])
    if ps.size < BLOOM_MIN_SPOTS:
        return np.zeros(s.shape, bool), 0.0, 0.0
    median = float(np.median(ps))
    with np.errstate(invalid="ignore"):
        good = bounded & (s <= BLOOM_SPREAD * median)
    return good, bloom_slope(pu, ps, ps <= BLOOM_SPREAD * median), median


def centred(rig: Rig, ceiling_height_m: float, c_obs: np.ndarray, q_v: np.ndarray,
            theta: np.ndarray, outline: np.ndarray, good: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """``(q_v, good)``: the ceiling points (V) of ``K`` outlines' centres whose images'
    area centroids are the observed ``c_obs (K, 2)`` px (``outline``, ``(P, 2)`` or ``(K,
    P, 2)``, turned by ``theta`` about each; :func:`_project_rectangles`), by
    :data:`RECT_ITERATIONS` corrections from ``q_v``: an outline's centroid is the image
    of its centre only on the ceiling. ``good`` loses the ones no ray reaches."""
    # the centre projected with the outline, as its last point (one projection)
    with_centre = np.concatenate(
        [outline, np.zeros(outline.shape[:-2] + (1, 2))], axis=-2)
    for _ in range(RECT_ITERATIONS):
        img = _project_rectangles(rig, ceiling_height_m, q_v, theta, with_centre)
        off = polygon_centroids(img[:, :-1]) - img[:, -1]
        bad = ~np.all(np.isfinite(off), axis=1)
        qn, okn = ceiling_points(rig, ceiling_height_m,
                                 c_obs - np.where(bad[:, None], 0.0, off))
        good = good & okn & ~bad
        q_v = np.where(good[:, None], qn, q_v)
    return q_v, good


def moments_fit(cov_px: np.ndarray, S: np.ndarray, good: np.ndarray) -> np.ndarray:
    """``(K,)`` whether observed second moments ``S (K, 2, 2)`` fit predicted ones
    ``cov_px`` (plus the optics' blur, :data:`RECT_BLUR_PX2`): every eigenvalue of
    ``C⁻¹ S`` within :data:`RECT_MOMENTS` (False where ``good`` is not)."""
    C = np.where(good[:, None, None], cov_px + RECT_BLUR_PX2 * np.eye(2), np.eye(2))
    with np.errstate(invalid="ignore"):
        ev = np.linalg.eigvals(np.linalg.solve(C, S)).real
    return good & np.all((ev >= RECT_MOMENTS[0]) & (ev <= RECT_MOMENTS[1]), axis=1)


class SpotObserver:
    """Spots of a frame as ceiling points, with the checks a known light size allows.

    Args:
        rig: camera and mount.
        ceiling_height_m: ``H`` (W's z of the ceiling).
        light_radius_m: radius of a light's bright disc (0: no size and shape checks).
        spot_params: detector thresholds.
        valid_mask: ``(H, W)`` uint8, non-zero where spots are looked for.
        nadir_px: where regions are examined from (nearest first).
        max_spots: examine at most this many candidate regions.
        factor: spots are found on the frame decimated by this
            (:func:`~ceilkit.runtime.features.working.detect_spots_working`).
        stage: the spot stage at working resolution (``factor`` 1): ``windowed``
            (found on the frame decimated by 2, read at full resolution in windows:
            :func:`~ceilkit.runtime.features.windows.detect_spots_windowed`) or
            ``full`` (:func:`~ceilkit.runtime.features.spots.detect_spots`).
        light_size_m: rectangular lights' ``(length, width)`` (None: discs).
        bloom_max_m: how far beyond its rectangle a lamp's region may reach and still be
            measured as that lamp bloomed (:meth:`_bloomed`; 0: never).
    """

    def __init__(self, rig: Rig, ceiling_height_m: float, light_radius_m: float,
                 spot_params: SpotParams, valid_mask: np.ndarray,
                 nadir_px: tuple[float, float], max_spots: int, factor: int = 1,
                 stage: str = "full", light_size_m: tuple[float, float] | None = None,
                 bloom_max_m: float = 0.0):
        self.rig, self.ceiling_height_m = rig, ceiling_height_m
        self.bloom_max_m = float(bloom_max_m)    # most a lamp's bloom reaches (_bloomed)
        # rectangular lights (light_size): the disc checks are off, the rectangle's
        # (_rectangles) run in their place
        self.light_size_m = light_size_m
        if light_size_m is not None:
            light_radius_m = 0.0
        self.light_radius_m = light_radius_m
        self.spot_params, self.valid_mask = spot_params, valid_mask
        self.nadir_px, self.max_spots = nadir_px, max_spots
        self.t_vehicle_cam = mount_arrays(rig.mount)[1]
        self.table = spot_table(rig, ceiling_height_m, light_radius_m)
        self.grid = GridTable(self.table, JAC_STEP_PX)   # the table read at any pixel
        self.factor = factor
        self.valid_small = decimated_mask(valid_mask, factor)
        self.windowed = stage == "windowed" and factor == 1
        self.valid_half = decimated_mask(valid_mask, 2) if self.windowed else None
        # what the compiled examination reads (examine_core), made once
        self.grid_arrays = GridArrays(arr(self.grid.coef, np.float64),
                                      arr(self.grid.limits, np.float64))
        self.mount = kernel_rig(rig, ceiling_height_m)
        self.checks = SpotChecks(float(light_radius_m), rig.camera.width,
                                 rig.camera.height, RIM_REACH, RIM_MARGIN_PX)
        # rectangular lamps in raw frames: the lens's fall-off read off the ceiling
        # and divided out first (falloff_gain)
        self.falloff = None if light_size_m is None else falloff_rings(rig, valid_mask)
        self.principal = np.array([rig.camera.cx, rig.camera.cy])

    def observe(self, grey: np.ndarray, blooms: BloomPool | None = None) -> Observation:
        """The usable spots of a ``(H, W)`` uint8 frame, their ceiling points in V, a
        reliability order (nearest the camera first) and their pixel Jacobians.

        Up to :data:`MAX_BUDGET_FACTOR` x ``max_spots`` regions are examined, nearest
        the nadir first, and the first ``max_spots`` that fit a light there are kept:
        regions that are not lights (a grille, a pipe crossing, a window: wrong size or
        shape for a light at their place) do not hide the lights behind them. One
        detection: examining more regions costs little beside the threshold. A raw
        frame of rectangular lamps is first divided by the lens's fall-off read off its
        ceiling (:func:`falloff_gain`, :func:`deshaded`): under it a lamp's halo, in
        its intensity-weighted centroid, moves the centroid towards the image centre.
        ``blooms``: the run's recent blooms, which a bloomed lamp is judged with."""
        centre = self.principal.copy() if two_level(grey) else None
        if self.falloff is not None and centre is None:
            bc = falloff_gain(grey, self.falloff)
            grey = grey if bc is None else deshaded(grey, self.falloff.rho2, bc)
        spots, q, ok, table = self._examine(grey, MAX_BUDGET_FACTOR * self.max_spots)
        if len(spots) == 0:
            return Observation(spots, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 2, 2)))
        principal = self.principal.copy()
        weak = axis = excess = bloom = seen = None
        if self.light_size_m is not None:
            q, ok, weak, axis, excess, bloom, seen = self._rectangles(
                spots, q, ok, table, centre, blooms or BloomPool())
        if int(ok.sum()) > self.max_spots:             # the first max_spots examined
            ok &= np.cumsum(ok) <= self.max_spots
        J = table[:, :4].reshape(-1, 2, 2)
        candidates_px = spots.centroids_px
        out = ~ok & np.all(np.isfinite(q), axis=1)
        rejected_v = q[out, 0] + 1j * q[out, 1]
        if not ok.all():
            spots, q, J = spots.select(ok), q[ok], J[ok]
        if weak is not None:
            weak, axis, excess, bloom = weak[ok], axis[ok], excess[ok], bloom[ok]
        t_vc = self.t_vehicle_cam
        rng = np.hypot(q[:, 0] - t_vc[0], q[:, 1] - t_vc[1])
        return Observation(spots, q, rng.argsort(kind="stable"), J,
                           candidates_px, ok, weak, axis, centre, excess, principal,
                           rejected_v, bloom, seen)

    def _rectangles(self, spots: Spots, q: np.ndarray, ok: np.ndarray, table: np.ndarray,
                    centre_px: np.ndarray | None = None, blooms: BloomPool = BloomPool()
                    ) -> tuple[np.ndarray, ...]:
        """The checks of rectangular lights (``light_size``), for the spots ``ok`` so
        far: ``(q, ok, weak, axis, excess, bloom, seen)`` (:class:`Observation`'s
        ``weak``, ``axis_v``, ``excess_px``, ``bloom_m``, ``blooms_seen``).

        A rectangle's orientation in V is not known without the pose: the spot's own
        second moments give it (modulo 180°; the long axis of ``J⁻¹ (S - blur) J⁻ᵀ``,
        ``J`` the local ceiling-to-pixel Jacobian). The rectangle of the site's size at
        that orientation, centred on the spot's ceiling point, is projected through the
        camera model (its sides sampled, so a fisheye's bending is in it) and its area
        centroid's offset from the image of its centre taken off the observed centroid
        (:data:`RECT_ITERATIONS` times): a rectangle's centroid is its centre only on the
        ceiling. The spot is kept when its area and whitened second moments fit that
        projected rectangle (:data:`RECT_AREA`, :data:`RECT_MOMENTS`), it falls short of
        it by no more than :data:`RECT_SHORT_PX` (a fragment), and the rectangle,
        :data:`RECT_CUT_REACH` times larger, lies inside the frame (by
        :data:`RIM_MARGIN_PX`) and the view mask (the lens's edge): a lamp cut by
        either gives a fragment's centroid. A kept spot is ``weak`` when the rectangle
        :data:`RECT_WEAK_REACH` times larger does not. A spot larger than
        :data:`RECT_AREA` allows is tried as a bloomed lamp (:meth:`_bloomed`).
        """
        n = q.shape[0]
        weak = np.zeros(n, bool)
        axis, excess, bloom = np.zeros(n), np.zeros(n), np.zeros(n)
        seen = None
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return q, ok, weak, axis, excess, bloom, seen
        rig, h = self.rig, self.ceiling_height_m
        c_obs = spots.centroids_px[idx]
        S = spots.cov_px[idx]
        det, good, theta, shows = lamp_axes(table[idx, :4].reshape(-1, 2, 2), S)
        outline = rectangle_outline(*self.light_size_m)          # (P, 2), long side on x
        qk = q[idx].copy()
        if centre_px is not None:     # a two-level frame: the threshold's shift taken off
            img = _project_rectangles(rig, h, qk, theta, outline)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = spots.areas_px[idx] / polygon_moments(img)[0]
            use = good & (ratio >= RECT_AREA[0]) & (ratio <= RECT_AREA[1])
            c_obs = c_obs - edge_shift_px(img, spots.areas_px[idx], centre_px, use)
        qk, good = centred(rig, h, c_obs, qk, theta, outline, good)
        img = _project_rectangles(rig, h, qk, theta, outline)
        area_p, cov_p = polygon_moments(img)
        area_o = spots.areas_px[idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = area_o / area_p
            excess[idx] = np.nan_to_num((area_o - area_p) / polygon_perimeters(img))
        fits = good & (ratio >= RECT_AREA[0]) & (ratio <= RECT_AREA[1])
        fits &= excess[idx] >= -RECT_SHORT_PX          # not a fragment of its lamp
        uncut, strong = self._inside(qk, theta, outline)
        fits &= moments_fit(cov_p, S, good) & uncut
        weak_k = ~strong
        big = good & (ratio > RECT_AREA[1])
        if centre_px is not None:   # a two-level frame: a quiet bloom, too (BLOOM_MIN_PX)
            big |= fits & (excess[idx] > BLOOM_MIN_PX)
        big = np.flatnonzero(big) if self.bloom_max_m > 0 else ()
        if len(big):
            qb, fb, wb, grown, seen = self._bloomed(
                c_obs[big], qk[big], theta[big], S[big], area_o[big], np.abs(det[big]),
                blooms)
            # a quiet bloom is measured as its rectangle while the run has too few blooms
            # to judge one by (a run's first frames)
            judged = blooms.s.size + seen[1].size >= BLOOM_MIN_SPOTS
            use = (ratio[big] > RECT_AREA[1]) | judged
            qk[big[use]], fits[big[use]], weak_k[big[use]] = qb[use], fb[use], wb[use]
            bloom[idx[big]] = grown
        q = q.copy()
        q[idx] = qk
        ok = ok.copy()
        ok[idx] = fits
        weak[idx] = weak_k
        axis[idx] = np.where(good & shows, theta, np.nan)
        return q, ok, weak, axis, excess, bloom, seen

    def _bloomed(self, c_obs: np.ndarray, q_v: np.ndarray, theta: np.ndarray, S: np.ndarray,
                 area_px: np.ndarray, det_px: np.ndarray, blooms: BloomPool = BloomPool()
                 ) -> tuple[np.ndarray, ...]:
        """``(q, ok, weak, s, seen)`` of ``K`` spots too large for their lamp's rectangle
        (``seen``: the ``(u, s)`` of those within ``bloom_max_m``, for the pool), each
        tried as that rectangle dilated by ``s`` metres on the ceiling (its sides moved
        out, its corners rounded: :func:`bloom_outline`): a lamp whose halo, or the
        lens's glare, lies over the threshold round it. ``s`` is the one that covers the
        spot's area (Steiner's ``LW + 2 (L + W) s + pi s²`` through the local Jacobian's
        determinant ``det_px``, then :data:`BLOOM_STEPS` corrections on the projected
        outline); the spot is kept when ``0 < s <= bloom_max_m`` (a bloom wider than
        half the gap between two lamps would merge them), ``s`` is within
        :data:`BLOOM_SPREAD` times the median of the frame's and the run's recent blooms
        (``blooms``; at least :data:`BLOOM_MIN_SPOTS` of them: one region of two merged
        lamps reaches about twice as far as each would; :func:`judged_blooms`), its
        whitened second moments
        fit the dilated outline (:data:`RECT_MOMENTS`) and that outline, like a
        rectangle's, lies inside the frame and the view. A symmetric dilation leaves the
        centre where it was; the lens's fall-off does not: the threshold cuts the halo
        nearer the lamp on its side away from the image centre, and the dilation's slope
        across the view (:func:`bloom_slope`, measured linear in ``u = (r / r_half
        diagonal)²`` to 6 mm rms on the held-out drives) is spread along each outline
        before its centroid offset is taken off as a rectangle's is (:func:`centred`)."""
        rig, h = self.rig, self.ceiling_height_m
        length, width = self.light_size_m
        base, out = bloom_outline(length, width)
        half_per = length + width
        with np.errstate(invalid="ignore", divide="ignore"):
            grow = np.maximum(area_px / det_px - length * width, 0.0)
            s = (np.sqrt(half_per * half_per + math.pi * grow) - half_per) / math.pi
            for _ in range(BLOOM_STEPS):
                img = _project_rectangles(rig, h, q_v, theta, base + s[:, None, None] * out)
                s = s + (area_px - polygon_moments(img)[0]) / (
                    polygon_perimeters(img) * np.sqrt(det_px))
        bounded = np.isfinite(s) & (s > 0) & (s <= self.bloom_max_m)
        cam = rig.camera
        half_diag2 = 0.25 * (cam.width ** 2 + cam.height ** 2)
        u = np.sum((c_obs - self.principal) ** 2, axis=1) / half_diag2
        good, b, median = judged_blooms(u, s, bounded, blooms)
        # the dilation falls off across the view with the lens's fall-off: its slope over
        # the blooms spread along each outline (its centroid moves with it)
        s_k = np.where(good, s, 0.0)[:, None]
        if b != 0.0:
            img = _project_rectangles(rig, h, q_v, theta, base + s_k[..., None] * out)
            u_k = np.sum((img - self.principal) ** 2, axis=2) / half_diag2
            s_k = np.maximum(s_k + b * np.nan_to_num(u_k - u[:, None]), 0.0)
        outline = base + s_k[..., None] * out
        q_v, good = centred(rig, h, c_obs, q_v, theta, outline, good)
        cov_p = polygon_moments(_project_rectangles(rig, h, q_v, theta, outline))[1]
        uncut, strong = self._inside(q_v, theta, outline)
        good &= moments_fit(cov_p, S, good) & uncut
        # a bloom cut short by the fall-off (towards the view's edge) keeps the centre
        # error of the run's typical bloom (BLOOM_CENTRE_SHARE)
        return (q_v, good, ~strong,
                np.where(good, np.maximum(s, median), 0.0), (u[bounded], s[bounded]))

    def _inside(self, q_v: np.ndarray, theta: np.ndarray, outline: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """``(uncut, strong)``, each ``(K,)``: whether rectangles (``outline``, ``(P, 2)`` or
        ``(K, P, 2)``, about ``q_v`` turned by ``theta``) grown :data:`RECT_CUT_REACH`
        and :data:`RECT_WEAK_REACH` times project inside the frame by
        :data:`RIM_MARGIN_PX` and inside the view mask (both in one projection)."""
        both = np.concatenate(np.broadcast_arrays(outline * RECT_CUT_REACH,
                                                  outline * RECT_WEAK_REACH), axis=-2)
        img = _project_rectangles(self.rig, self.ceiling_height_m, q_v, theta, both)
        fin = np.isfinite(img).all(axis=2)
        flat = np.nan_to_num(img.reshape(-1, 2), nan=-1e9)
        cam = self.rig.camera
        inside = cam.in_image(flat, margin_px=RIM_MARGIN_PX).reshape(img.shape[:2])
        uv = np.clip(np.rint(flat), 0, [cam.width - 1, cam.height - 1]).astype(int)
        in_mask = (self.valid_mask[uv[:, 1], uv[:, 0]] > 0).reshape(img.shape[:2])
        ok = fin & inside & in_mask
        p = outline.shape[-2]
        return np.all(ok[:, :p], axis=1), np.all(ok[:, p:], axis=1)

    def _examine(self, grey: np.ndarray, budget: int
                 ) -> tuple[Spots, np.ndarray, np.ndarray, np.ndarray]:
        """Spots of at most ``budget`` regions, their ceiling points, which are
        plausible lights, and their table rows."""
        if self.windowed:
            spots = detect_spots_windowed(grey, self.spot_params, self.valid_half,
                                          self.nadir_px, budget)
        else:
            spots = detect_spots_working(grey, self.spot_params, self.valid_mask,
                                         self.nadir_px, budget, self.factor, self.valid_small)
        if len(spots) == 0:
            return spots, np.zeros((0, 2)), np.zeros(0, bool), np.zeros((0, 8))
        q, ok, table = examine_core(
            arr(spots.centroids_px, np.float64), arr(spots.areas_px, np.float64),
            arr(spots.cov_px, np.float64), self.grid_arrays, self.mount, self.checks)
        return spots, q, ok, table


@njit
def examine_core(centroids, areas, cov, grid, mount, checks):  # pragma: no cover - compiled
    """``(q (K, 2), ok (K,), table (K, C))`` of spots (centroids ``(K, 2)`` px, areas,
    second moments ``cov (K, 2, 2)``): the spot table's row at each centroid (``grid``,
    a :class:`GridArrays`), the ceiling point in V of the light's centre (the centroid
    minus its disc's centroid offset, the table's columns 8-9;
    :func:`~.rays.ceiling_points_core` through ``mount``, a
    :class:`~ceilkit.runtime.geometry.ceiling.KernelMount`) and whether it is usable:
    its ray rises, the table is finite there and, for a light of known radius
    (``checks``, a :class:`SpotChecks`; radius 0: no checks), its size and shape fit
    one (:func:`plausible_spot`) and it lies well inside the frame
    (:func:`uncut_spot`)."""
    coef, limits = grid.coef, grid.limits
    radius, width, height = checks.radius_m, checks.width, checks.height
    rim_reach, rim_margin = checks.rim_reach, checks.rim_margin_px
    dz = mount.ceiling_m - mount.t[2]                 # the ceiling above the camera
    k = centroids.shape[0]
    table = np.empty((k, coef.shape[2]))
    centres = np.empty((k, 2))
    for i in range(k):
        grid_row(coef, limits, centroids[i, 0], centroids[i, 1], table[i])
        for j in range(2):
            off = table[i, 8 + j]
            centres[i, j] = centroids[i, j] - (off if math.isfinite(off) else 0.0)
    q = np.empty((k, 2))
    ok = ceiling_points_core(centres, mount.code, mount.lens, mount.R, mount.t, dz, q)
    for i in range(k):
        ok[i] = ok[i] and math.isfinite(table[i, 0])
        if ok[i] and radius > 0:
            ok[i] = (plausible_spot(areas[i], cov[i, 0, 0], cov[i, 0, 1], cov[i, 1, 1],
                                    table[i])
                     and uncut_spot(centroids[i, 0], centroids[i, 1], table[i],
                                    rim_reach * radius, rim_margin, width, height))
    return q, ok, table


@njit
def plausible_spot(area, s00, s01, s11, t):  # pragma: no cover - compiled
    """Whether a spot of ``area`` (px) and second moments ``S = (s00, s01; s01, s11)``
    (px²) fits a light of the spot table's row ``t`` at its place.

    The predicted spot is the light's disc through the local Jacobian ``J`` of the
    ceiling-to-pixel map: area ``pi r² |det J|`` (``t[7]``), second moments
    ``C = r²/4 J Jᵀ + 0.8 I`` (+ blur; ``t[4:7]`` hold ``C⁻¹``'s 00, 01, 11). The
    observed moments, whitened by the predicted ones (the eigenvalues of ``C⁻¹ S``),
    must be round (ratio >= 0.2) and of a plausible size, and the area within
    ``[0.15 a_pred - 3, 5 a_pred + 40]``."""
    a_pred = t[7]
    if not (area >= 0.15 * a_pred - 3 and area <= DISC_AREA_MAX * a_pred + 40):
        return False
    c00, c01, c11 = t[4], t[5], t[6]
    m00 = c00 * s00 + c01 * s01
    m01 = c00 * s01 + c01 * s11
    m10 = c01 * s00 + c11 * s01
    m11 = c01 * s01 + c11 * s11
    tr = m00 + m11
    det = m00 * m11 - m01 * m10
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    root = math.sqrt(max(det, 0.0))
    return lo > 0 and lo >= 0.2 * hi and root > 0.05 and root < 6.0


@njit
def uncut_spot(u, v, t, r, margin, width, height):  # pragma: no cover - compiled
    """Whether the light of a spot at ``(u, v)`` lies well inside a ``width x height``
    frame: a disc of radius ``r`` (m; :data:`RIM_REACH` x the light's) through the
    local Jacobian ``J`` (the spot table's row ``t``: reaching ``r |J_u|`` and
    ``r |J_v|`` from the centre, ``J``'s rows' norms), inside by ``margin`` px
    (:data:`RIM_MARGIN_PX`). Nearer the frame's
    edge a light's centroid is pulled inwards: cut by the edge, or with its outer part
    below the local threshold (the frame's mirrored border raises it), which the
    detector's own check (its region reaching the edge) cannot see. On the tilted
    corridor rig a far light leaving the top of the frame moved the pose by 2 cm in x."""
    reach_u = r * math.hypot(t[0], t[1]) + margin
    reach_v = r * math.hypot(t[2], t[3]) + margin
    return (u - reach_u >= -0.5 and u + reach_u <= width - 0.5
            and v - reach_v >= -0.5 and v + reach_v <= height - 0.5)


class VisibilityTable:
    """Which map lights the detector should report from a vehicle pose.

    A table over the ceiling in V: the pixel distance from the nadir of a light there,
    ``inf`` where the detector cannot report it (outside the image by
    :data:`VIEW_MARGIN_PX`, a disc of :data:`RIM_REACH` x ``light_radius_m`` around it
    not inside by :data:`RIM_MARGIN_PX`: the observer drops such a light, its centroid
    biased, or outside the view mask). It covers the ceiling seen by the
    view mask (from its pixels every 8 px), in at most 200 x 200 cells; calling it is a
    lookup, not a projection.

    Attributes:
        origin_m: ``(2,)`` V coordinates of cell ``(0, 0)``; ``cell_m``: cell side.
        table: ``(NI, NJ)`` float32 distances from the nadir, px (``inf``: not seen).
        padded: the table with a border of ``inf`` cells, flat (``(NI + 2) (NJ + 2)``,
            row-major; read-only): what :meth:`locate`'s ``cell`` indexes.
        arrays: ``(lights (M, 2), padded, (origin x, origin y, cell_m), (NI, NJ,
            max_spots))``, read-only: what the compiled lookup reads (:func:`locate_core`).
    """

    def __init__(self, rig: Rig, ceiling_height_m: float, lights_w: np.ndarray,
                 valid_mask: np.ndarray, nadir_px: tuple[float, float], max_spots: int,
                 light_radius_m: float = 0.0, reach_m: float | None = None):
        cam = rig.camera
        self.max_spots = max_spots
        uu, vv = np.meshgrid(np.arange(0, cam.width, 8.0), np.arange(0, cam.height, 8.0))
        grid_px = np.stack([uu.ravel(), vv.ravel()], 1)
        inside = valid_mask[grid_px[:, 1].astype(int), grid_px[:, 0].astype(int)] > 0
        q, ok = ceiling_points(rig, ceiling_height_m, grid_px[inside])
        if not np.any(ok):
            q, ok = np.zeros((1, 2)), np.ones(1, bool)
        lo, hi = q[ok].min(0) - 0.5, q[ok].max(0) + 0.5
        cell = max(0.01, float((hi - lo).max()) / 200)
        n = np.ceil((hi - lo) / cell).astype(int) + 1
        self.origin_m, self.cell_m = lo, cell
        gi, gj = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
        g = lo[None, :] + cell * np.stack([gi.ravel(), gj.ravel()], 1)
        px = project_lights(rig, ceiling_height_m, g, 0.0, 0.0, 0.0)
        ok = np.isfinite(px[:, 0])
        ok[ok] = cam.in_image(px[ok], margin_px=VIEW_MARGIN_PX)
        reach = RIM_REACH * light_radius_m if reach_m is None else reach_m
        if reach > 0:      # the whole disc inside: the detector drops a cut light
            for a in np.linspace(0.0, 2 * math.pi, DISC_POINTS, endpoint=False):
                idx = np.nonzero(ok)[0]
                rim = project_lights(rig, ceiling_height_m, g[idx] + reach
                                     * np.array([math.cos(a), math.sin(a)]), 0.0, 0.0, 0.0)
                ok[idx] = np.isfinite(rim[:, 0]) & cam.in_image(
                    np.nan_to_num(rim, nan=-1e9), margin_px=RIM_MARGIN_PX)
        idx = np.nonzero(ok)[0]
        uv = np.round(px[idx]).astype(int)
        ok[idx[valid_mask[uv[:, 1], uv[:, 0]] == 0]] = False
        if reach_m is not None and reach > 0:
            # a rectangle's reach: inside the view mask too (the lens's edge cuts it)
            for a in np.linspace(0.0, 2 * math.pi, DISC_POINTS, endpoint=False):
                idx = np.nonzero(ok)[0]
                rim = project_lights(rig, ceiling_height_m, g[idx] + reach
                                     * np.array([math.cos(a), math.sin(a)]), 0.0, 0.0, 0.0)
                uv = np.clip(np.rint(np.nan_to_num(rim, nan=0.0)), 0,
                             [cam.width - 1, cam.height - 1]).astype(int)
                ok[idx[valid_mask[uv[:, 1], uv[:, 0]] == 0]] = False
        d = np.hypot(px[:, 0] - nadir_px[0], px[:, 1] - nadir_px[1])
        self.table = np.where(ok, d, np.inf).astype(np.float32).reshape(n[0], n[1])
        # each cell's patch of the image (VIEW_PATCHES across, rows alike; -1 where not
        # seen): what a light's detection rate goes by (twins.DetectionRates: its image's
        # size and the lens's fall-off there)
        pu, pv = VIEW_PATCHES
        uv = np.nan_to_num(px, nan=0.0)
        patch = (np.clip((uv[:, 0] * pu / cam.width).astype(int), 0, pu - 1) + pu
                 * np.clip((uv[:, 1] * pv / cam.height).astype(int), 0, pv - 1))
        self.view_patch = np.pad(np.where(ok, patch, -1).astype(np.int16).reshape(n[0], n[1]),
                                 1, constant_values=-1).ravel()
        self.view_patch.setflags(write=False)
        # the same, with a border of inf cells: a clipped index off the table lands there
        self.padded = np.pad(self.table, 1, constant_values=np.inf).ravel()
        self.padded.setflags(write=False)
        # what the compiled lookup reads (locate_core)
        self.arrays = (arr(lights_w, np.float64), self.padded,
                       arr([lo[0], lo[1], cell], np.float64),
                       arr([n[0], n[1], max_spots], np.int64))

    def __call__(self, x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
        """``(M,)`` map lights the detector should report from a pose: inside the image
        and the view mask, and among the ``max_spots`` nearest the nadir."""
        return self.locate(x_m, y_m, yaw_rad)[0]

    def locate(self, x_m: float, y_m: float, yaw_rad: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(visible (M,), cell (M,), z (M,))``: what :meth:`__call__` answers, each
        light's cell as a flat index into the table padded by one cell of ``inf``
        (``(NI + 2) x (NJ + 2)``, row-major), and the lights in V as ``x + iy``."""
        ok, cell, zr, zi = locate_core(float(x_m), float(y_m), float(yaw_rad),
                                       *self.arrays)
        return ok, cell, zr + 1j * zi

    def unseen(self, z: np.ndarray, rates: np.ndarray) -> float:
        """The sum of ``1 - rates[patch]`` over the ceiling points ``z`` (V, ``x + iy``;
        :meth:`patches`; none off the seen ceiling), in one compiled call: the share of
        their lights a detector of those ``rates`` would miss anyway."""
        return unseen_core(np.ascontiguousarray(z, np.complex128), self.view_patch,
                           self.arrays[2], self.arrays[3], rates)

    def patches(self, z: np.ndarray) -> np.ndarray:
        """``(K,)`` the image patch (:attr:`view_patch`) of the ceiling points ``z`` (V,
        ``x + iy``), -1 off the seen ceiling: :func:`locate_core`'s cells, looked up."""
        ni, nj = self.table.shape
        i = np.clip(np.rint((z.real - self.origin_m[0]) / self.cell_m), -1, ni) + 1
        j = np.clip(np.rint((z.imag - self.origin_m[1]) / self.cell_m), -1, nj) + 1
        return self.view_patch[(i * (nj + 2) + j).astype(np.int64)]

    def cell_centres(self) -> np.ndarray:
        """``((NI + 2) (NJ + 2), 2)`` the V coordinates (m) of the padded table's cell
        centres, in the order of :meth:`locate`'s ``cell``."""
        ni, nj = self.table.shape
        gi, gj = np.meshgrid(np.arange(-1, ni + 1), np.arange(-1, nj + 1), indexing="ij")
        return self.origin_m[None, :] + self.cell_m * np.stack([gi.ravel(), gj.ravel()], 1)

@njit
def locate_core(x, y, yaw, lights, padded, geo, ints):  # pragma: no cover - compiled
    """:meth:`VisibilityTable.locate` in a compiled loop: ``(visible (M,), cell (M,),
    x (M,), y (M,))`` of the map ``lights (M, 2)`` seen from ``(x, y, yaw)``, the
    lights in V as two arrays (``padded``, ``geo``, ``ints``: the table's
    :attr:`~VisibilityTable.arrays`; ``ints`` may go on past its three entries)."""
    ni, nj, max_spots = ints[0], ints[1], ints[2]
    ox, oy, cell_m = geo[0], geo[1], geo[2]
    n = lights.shape[0]
    c, s = math.cos(yaw), -math.sin(yaw)
    zr = np.empty(n)
    zi = np.empty(n)
    cell = np.empty(n, np.int64)
    d = np.empty(n, np.float32)
    ok = np.zeros(n, np.bool_)
    seen = 0
    for k in range(n):
        # the light in V, x + iy: (L - t) Rz(-yaw), as a complex product
        a, b = lights[k, 0] - x, lights[k, 1] - y
        zr[k] = a * c - b * s
        zi[k] = a * s + b * c
        # cells of the padded table (a border of inf): off the table is not visible
        i = min(max(np.int64(np.rint((zr[k] - ox) / cell_m)), -1), ni) + 1
        j = min(max(np.int64(np.rint((zi[k] - oy) / cell_m)), -1), nj) + 1
        cell[k] = i * (nj + 2) + j
        d[k] = padded[cell[k]]
        if math.isfinite(d[k]):
            ok[k] = True
            seen += 1
    if seen > max_spots:                 # the max_spots nearest the nadir (stable)
        order = np.argsort(d, kind="mergesort")
        for r in range(max_spots, n):
            ok[order[r]] = False
    return ok, cell, zr, zi


@njit
def unseen_core(z, patch, geo, ints, rates):  # pragma: no cover - compiled
    """:meth:`VisibilityTable.unseen`: ``sum(1 - rates[patch of z])`` over the points
    ``z`` (V, complex) that lie on the seen ceiling (``patch``: the padded table's
    :attr:`~VisibilityTable.view_patch`; ``geo``, ``ints``: its ``arrays[2:]``), their
    cells as :func:`locate_core` finds them."""
    ni, nj = ints[0], ints[1]
    ox, oy, cell_m = geo[0], geo[1], geo[2]
    s = 0.0
    for k in range(z.size):
        i = min(max(np.int64(np.rint((z[k].real - ox) / cell_m)), -1), ni) + 1
        j = min(max(np.int64(np.rint((z[k].imag - oy) / cell_m)), -1), nj) + 1
        b = patch[i * (nj + 2) + j]
        if b >= 0:
            s += 1.0 - rates[b]
    return s


@warmer
def _warm() -> None:
    from ceilkit.runtime.geometry.camera import CameraModel

    cam = CameraModel.pinhole(16, 16, 10.0)
    f = arr(np.zeros((1, 2)), np.float64)
    examine_core(f, arr(np.ones(1), np.float64), arr(np.zeros((1, 2, 2)), np.float64),
                 GridArrays(arr(np.zeros((1, 4, 10)), np.float64), arr(np.ones(6), np.float64)),
                 kernel_mount(PlanarGeometry(cam, np.eye(3), np.zeros(3), 1.0)),
                 SpotChecks(0.1, 16, 16, RIM_REACH, RIM_MARGIN_PX))
    locate_core(0.0, 0.0, 0.0, f, arr(np.zeros(9), np.float32), arr(np.ones(3), np.float64),
                arr(np.ones(3), np.int64))
    unseen_core(np.zeros(1, np.complex128), arr(np.zeros(9, np.int16), np.int16),
                arr(np.ones(3), np.float64), arr(np.ones(3), np.int64), np.ones(1))


__all__ = ["JAC_STEP_PX", "RIM_MARGIN_PX", "RIM_REACH", "VIEW_MARGIN_PX", "WEAK_WEIGHT",
           "GridArrays", "Observation", "SpotChecks", "kernel_rig", "polygon_moments",
           "rectangle_outline", "bloom_outline", "SpotObserver", "VisibilityTable", "examine_core",
           "locate_core", "unseen_core", "plausible_spot", "spot_table", "uncut_spot"]
