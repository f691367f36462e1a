"""Light-map survey: the ``lights`` section of a site, with each light's uncertainty.

Two ways, both from a recording (SPEC §2):

* **Known poses** (:func:`survey_lights`): every frame's spots
  (:func:`ceilkit.runtime.features.spots.detect_spots`) become ceiling points in the vehicle
  frame, each the centroid of the spot's lit face on the ceiling plane
  (:func:`ceilkit.runtime.estimators.lights.ceiling_centroids`), then in W with the frame's
  known pose (``X_W = Rz(yaw) X_V + (x, y)``, SPEC §1). Points of all frames are
  clustered (leader clustering within ``cluster_m``, then every point re-assigned to
  its nearest centre); a cluster seen in at least ``min_views`` frames is a light,
  placed at the median of its points. Its uncertainty is the scatter of the points
  (``spread_m``, RMS distance from the centre) and the standard error of the centre
  (``sigma_m = spread / sqrt(n)``).
* **Chaining** (:func:`survey_chain`, :func:`chain_points`): no pose is known. The
  vehicle starts under a light whose place was measured (:class:`KnownLights`); each
  frame is placed by the lights it shares with the map built so far and adds the new
  ones; a joint least-squares adjustment of all frame poses and light positions (in
  pixels, the gauge held by the known lights) gives the map in W and every light's
  covariance (``sigma_m`` = radial 1-sigma).

``site.yaml`` has no key for the uncertainty (SPEC: ``lights: - [x, y]``; unknown keys
are errors): it goes into the file's header comments, one line per light, via
:func:`lightmap_header_lines` or :func:`chain_header_lines`.

Example::

    rec = Recording("run1")
    lm = survey_lights(rec)                    # uses rec.truth
    write_site(lm, "site.yaml", base=rec.site, header=provenance_header(...))
    res = survey_chain(rec, KnownLights((0.0, 0.0), second_m=(7.2, 0.0)))
    write_site(res.lightmap, "site.yaml", rec.site, header, res.ceiling_height_m)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.estimators.lights import (
    PatternMatcher,
    ceiling_centroids,
    ceiling_points,
    interp_grid,
    jacobian_grid,
    view_mask,
)
from ceilkit.runtime.features.spots import SpotParams, detect_spots
from ceilkit.runtime.geometry.fits import fit_rigid_2d
from ceilkit.runtime.io.recording import Recording, Truth, load_poses, load_truth

from .poses import StampedPoses


@dataclass(frozen=True, eq=False)
class LightMap:
    """A surveyed light map.

    Attributes:
        lights_m: ``(N, 2)`` light centres in W, metres.
        sigma_m: ``(N,)`` standard error of each centre, metres.
        spread_m: ``(N,)`` RMS scatter of the single-frame detections, metres.
        views: ``(N,)`` number of frames that saw each light.
        frames_used: frames with a pose that were read.
        detections: ceiling points used (all frames).
        unassigned: detections in no retained cluster (spurious spots, too few views).
        offset_s: the poses' time offset to the frames used (pose time = frame stamp +
            offset), seconds; None when the poses were at the frames' stamps.
        offset_sigma_s: its 1 sigma when it was estimated (None: given or exact).
    """

    lights_m: np.ndarray
    sigma_m: np.ndarray
    spread_m: np.ndarray
    views: np.ndarray
    frames_used: int
    detections: int
    unassigned: int
    offset_s: float | None = None
    offset_sigma_s: float | None = None



_SAID_DAMAGED: set[str] = set()
"""The damaged frames already named (each is one line, however often it is read)."""


def _image(recording: Recording, k: int) -> np.ndarray:
    """Frame ``k``'s image; a damaged file (cut short, not an image) is named in one
    line and is an empty image (no spots from it)."""
    frame = recording.frame(k)
    if frame.damage and frame.damage not in _SAID_DAMAGED:
        _SAID_DAMAGED.add(frame.damage)
        logging.getLogger("ceilkit.lightmap").warning("%s: skipped (bad_frame)",
                                                      frame.damage)
    return frame.image

def load_pose_table(path: str | Path) -> Truth:
    """Known vehicle poses from ``truth.csv`` (``t_ns,x,y,yaw_deg``) or a ``poses.csv``
    (SPEC §2; rows without a full pose are skipped)."""
    path = Path(path)
    try:
        return load_truth(path)
    except ConfigError as exc:
        if exc.key != "header":
            raise
    table = load_poses(path)
    ok = np.isfinite(table.x_m) & np.isfinite(table.y_m) & np.isfinite(table.yaw_rad)
    if not np.any(ok):
        raise ConfigError(path, None, "no row holds a full pose (x, y, yaw)")
    order = np.argsort(table.t_ns[ok], kind="stable")
    return Truth(table.t_ns[ok][order], table.x_m[ok][order], table.y_m[ok][order],
                 table.yaw_rad[ok][order])


def cluster_points(points_w: np.ndarray, frame_ids: np.ndarray, cluster_m: float,
                   min_views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                            int]:
    """Cluster ceiling points ``(K, 2)`` of frames ``(K,)`` into lights.

    Returns ``(centres (N, 2), sigma (N,), spread (N,), views (N,), unassigned)``.
    """
    P = np.asarray(points_w, float).reshape(-1, 2)
    if P.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, int), 0
    centres: list[np.ndarray] = []
    sums: list[np.ndarray] = []
    counts: list[int] = []
    for p in P:                                     # leader clustering, running means
        if centres:
            C = np.array(centres)
            d = np.hypot(C[:, 0] - p[0], C[:, 1] - p[1])
            k = int(np.argmin(d))
            if d[k] < cluster_m:
                sums[k] = sums[k] + p
                counts[k] += 1
                centres[k] = sums[k] / counts[k]
                continue
        centres.append(p.copy())
        sums.append(p.copy())
        counts.append(1)
    C = np.array(centres)
    for _ in range(3):                              # re-assign, robust centres
        d = np.linalg.norm(P[:, None] - C[None], axis=2)
        lab = np.argmin(d, axis=1)
        lab[d[np.arange(P.shape[0]), lab] >= cluster_m] = -1
        newC = []
        for k in range(C.shape[0]):
            m = lab == k
            newC.append(np.median(P[m], axis=0) if np.any(m) else C[k])
        C = np.array(newC)
    out_c, out_s, out_sp, out_v = [], [], [], []
    assigned = 0
    for k in range(C.shape[0]):
        m = lab == k
        views = len(set(frame_ids[m].tolist()))
        if views < min_views:
            continue
        r = np.linalg.norm(P[m] - C[k], axis=1)
        spread = float(np.sqrt(np.mean(r ** 2)))
        out_c.append(C[k])
        out_sp.append(spread)
        out_s.append(spread / math.sqrt(m.sum()))
        out_v.append(views)
        assigned += int(m.sum())
    kept = np.array(out_c).reshape(-1, 2)
    # clusters closer than the gate are one light split in two: keep the better seen
    if kept.shape[0] > 1:
        order = np.argsort(-np.array(out_v), kind="stable")
        keep: list[int] = []
        for i in order:
            if all(np.linalg.norm(kept[i] - kept[j]) >= cluster_m for j in keep):
                keep.append(int(i))
        keep.sort(key=lambda i: (kept[i, 0], kept[i, 1]))
    else:
        keep = list(range(kept.shape[0]))
    return (kept[keep], np.array(out_s)[keep], np.array(out_sp)[keep],
            np.array(out_v, int)[keep], int(P.shape[0] - assigned))


MIN_SPOT_ROUNDNESS = 0.6
"""A spot light is round on the ceiling: its detections' minor / major axis (median)
at least this. Rendered spot lights measure 0.95-1.0 (tests/fixtures/lights_rec); the
corridor's 1.2 x 0.3 m lamps 0.35 (their visible parts 0.8 x 0.33 m)."""
MAX_SPOT_M = 0.6
"""...and smaller than this across (m): a lamp larger than this is a luminaire whose
centre is not a point the lights method can match."""


def spot_extents_m(rig: Rig, ceiling_height_m: float, spots) -> np.ndarray:
    """``(N, 2)`` (major, minor) extent of each spot on the ceiling, metres: the ends of
    each principal axis of its second moments (``centroid +- 2 sqrt(eigenvalue)``, a
    uniform disc's diameter) meeting the ceiling. NaN where a ray does not rise."""
    out = np.full((len(spots), 2), np.nan)
    for i, (c, cov) in enumerate(zip(spots.centroids_px, spots.cov_px, strict=True)):
        w, v = np.linalg.eigh(np.asarray(cov, float))
        ext = []
        for k in (1, 0):
            d = 2.0 * math.sqrt(max(float(w[k]), 0.0)) * v[:, k]
            q, ok = ceiling_points(rig, ceiling_height_m, np.array([c - d, c + d]))
            ext.append(float(np.hypot(*(q[1] - q[0]))) if ok.all() else math.nan)
        out[i] = (max(ext), min(ext))
    return out


def check_spot_lights(recording: Recording, ceiling_height_m: float,
                      spot_params: SpotParams | None = None,
                      max_view_angle_deg: float = 60.0, samples: int = 20) -> None:
    """Refuse a recording whose lamps are not spot lights (rectangular luminaires, light
    strips): up to ``samples`` frames spread over it, every detection's extent on the
    ceiling (:func:`spot_extents_m`); the median must be round
    (:data:`MIN_SPOT_ROUNDNESS`) and small (:data:`MAX_SPOT_M`).

    Raises:
        CalibrationError: the lamps are not spot lights (the message says what they
            measure and what to use instead).
    """
    rig = recording.rig
    valid = view_mask(rig, math.radians(max_view_angle_deg))
    n = len(recording)
    ext = []
    for k in sorted({int(i) for i in np.linspace(0, n - 1, min(samples, n)).round()}):
        spots = detect_spots(_image(recording, k), spot_params, valid)
        if len(spots):
            ext.append(spot_extents_m(rig, ceiling_height_m, spots))
    if not ext:
        return
    e = np.concatenate(ext)
    e = e[np.isfinite(e).all(axis=1) & (e[:, 0] > 0)]
    if e.shape[0] == 0:
        return
    major, minor = float(np.median(e[:, 0])), float(np.median(e[:, 1]))
    roundness = float(np.median(e[:, 1] / e[:, 0]))
    if roundness < MIN_SPOT_ROUNDNESS or major > MAX_SPOT_M:
        raise CalibrationError(
            f"{recording.folder}: the lamps are not spot lights: their {e.shape[0]} "
            f"detections measure a median {major:.2f} x {minor:.2f} m on the ceiling "
            f"(minor/major {roundness:.2f}; a spot light is round, >= "
            f"{MIN_SPOT_ROUNDNESS:g}, and under {MAX_SPOT_M:g} m); the lights method "
            "cannot use their centres. For rectangular lamps give site.yaml `lamps` and "
            "`corridor` lines and use the corridor method. Nothing written")


# the time offset search between a pose table and the frames (pose time = frame stamp
# + offset): +-MAX_OFFSET_S on a grid of OFFSET_STEPS, then refined
MAX_OFFSET_S = 0.1
OFFSET_STEPS = 41
# no pose is interpolated across a gap of the pose table longer than this
MAX_GAP_S = 0.25


@dataclass(frozen=True, eq=False)
class _Detections:
    """Every frame's spots as ceiling points in V, with their frame's stamp."""

    t_ns: np.ndarray                 # (K,) the stamp of each point's frame
    q_v: np.ndarray                  # (K, 2) ceiling points in V, metres
    frame: np.ndarray                # (K,) frame index
    frames_used: int

    def world(self, table: StampedPoses, offset_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(K', 2)`` points in W at ``offset_s`` and the mask of points with a pose."""
        pose = table.at(self.t_ns, offset_s * 1e9, MAX_GAP_S * 1e9)
        ok = np.all(np.isfinite(pose), axis=1)
        x, y, yaw = pose[ok].T
        c, s = np.cos(yaw), np.sin(yaw)
        q = self.q_v[ok]
        return np.stack([c * q[:, 0] - s * q[:, 1] + x, s * q[:, 0] + c * q[:, 1] + y],
                        1), ok


def _detections(recording: Recording, table: StampedPoses, height: float,
                spot_params: SpotParams | None, valid: np.ndarray,
                margin_s: float | None) -> _Detections:
    """Spots of every frame whose pose the table holds ``margin_s`` either side (None:
    only frames whose stamp is a row of the table)."""
    rig = recording.rig
    ts, qs, fs = [], [], []
    used = 0
    for k in range(len(recording)):
        t = np.full(1, int(recording.t_ns[k]))
        if margin_s is None:
            if not table.exact(t):
                continue
        elif not all(np.isfinite(table.at(t, o * 1e9, MAX_GAP_S * 1e9)).all()
                     for o in (-margin_s, 0.0, margin_s)):
            continue
        used += 1
        spots = detect_spots(_image(recording, k), spot_params, valid)
        if len(spots) == 0:
            continue
        q, ok = ceiling_centroids(rig, height, spots.centroids_px, spots.cov_px)
        qs.append(q[ok][:, :2])
        ts.append(np.full(int(ok.sum()), t[0], np.int64))
        fs.append(np.full(int(ok.sum()), k))
    if used == 0:
        raise ConfigError(recording.folder, "truth.csv",
                          "no pose matches a frame stamp (frames.csv t_ns): the poses "
                          "cover none of the frames")
    return _Detections(_cat(ts, 0).astype(np.int64), _cat(qs, (0, 2)),
                       _cat(fs, 0).astype(int), used)


def _cat(parts: list[np.ndarray], empty_shape) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty_shape)


def _labels(det: _Detections, table: StampedPoses, offset_s: float, cluster_m: float,
            min_views: int) -> np.ndarray:
    """``(K,)`` each point's light (nearest centre within ``cluster_m``), -1: none."""
    P, ok = det.world(table, offset_s)
    C = cluster_points(P, det.frame[ok], cluster_m, min_views)[0]
    lab = np.full(det.t_ns.size, -1)
    if C.shape[0]:
        d = np.linalg.norm(P[:, None] - C[None], axis=2)
        k = np.argmin(d, axis=1)
        lab[np.flatnonzero(ok)] = np.where(d[np.arange(P.shape[0]), k] < cluster_m, k, -1)
    return lab


def _scatter(det: _Detections, table: StampedPoses, offset_s: float,
             labels: np.ndarray) -> float:
    """Sum of squared distances of the points at ``offset_s`` from their light's mean,
    over the points ``labels`` assigns (the same points at every offset)."""
    P, ok = det.world(table, offset_s)
    lab = labels[ok]
    J = 0.0
    for k in np.unique(lab[lab >= 0]):
        pk = P[lab == k]
        J += float(((pk - pk.mean(axis=0)) ** 2).sum())
    return J


def estimate_offset(det: _Detections, table: StampedPoses, cluster_m: float,
                    min_views: int) -> tuple[float, float]:
    """The pose table's time offset to the frames (s) and its 1 sigma: the offset at
    which every light's detections from all frames fall closest together (a wrong
    offset smears each light along the drive). A drive that stands still does not
    determine it, and then it does not matter: the sigma says so."""
    from scipy.optimize import minimize_scalar

    grid = np.linspace(-MAX_OFFSET_S, MAX_OFFSET_S, OFFSET_STEPS)
    lab = _labels(det, table, 0.0, cluster_m, min_views)
    best = float(grid[int(np.argmin([_scatter(det, table, o, lab) for o in grid]))])
    lab = _labels(det, table, best, cluster_m, min_views)
    step = float(grid[1] - grid[0])
    lo, hi = max(best - step, -MAX_OFFSET_S), min(best + step, MAX_OFFSET_S)
    res = minimize_scalar(lambda o: _scatter(det, table, o, lab), bounds=(lo, hi),
                          method="bounded", options={"xatol": 1e-5})
    tau, h = float(res.x), 1e-3
    J0 = _scatter(det, table, tau, lab)
    curv = (_scatter(det, table, tau + h, lab) - 2 * J0
            + _scatter(det, table, tau - h, lab)) / h ** 2
    n_lights = np.unique(lab[lab >= 0]).size
    dof = max(2 * int((lab >= 0).sum()) - 2 * n_lights - 1, 1)
    sigma = math.sqrt(2 * (J0 / dof) / curv) if curv > 0 else math.inf
    return tau, sigma


def survey_lights(recording: Recording, poses: Truth | StampedPoses | None = None, *,
                  ceiling_height_m: float | None = None, cluster_m: float = 0.15,
                  min_views: int = 3, spot_params: SpotParams | None = None,
                  max_view_angle_deg: float = 60.0,
                  offset_s: float | None = None) -> LightMap:
    """Build a light map from a recording with known poses.

    Args:
        recording: frames, rig and site (its ``ceiling_height`` unless overridden).
        poses: known vehicle poses (default: the recording's ``truth.csv``). Poses at
            the frames' own stamps are used as they are; poses at their own stamps
            (motion capture, a total station) are interpolated at each frame's stamp
            (not across a gap longer than ``MAX_GAP_S``) and their time offset to the
            frames is estimated (:func:`estimate_offset`) unless ``offset_s`` is given.
        cluster_m: detections of one light lie within this of each other (and distinct
            lights further apart).
        min_views: fewest frames that must see a light.
        max_view_angle_deg: spots further from the vertical are not used (the
            steepest views are the least precise).
        offset_s: the known time offset (pose time = frame stamp + offset), seconds:
            the poses are interpolated with it and it is not estimated.

    Raises:
        ConfigError: no poses, or none covering a frame; a ceiling below the camera.
        CalibrationError: no light was seen often enough; lamps that are not spot
            lights (:func:`check_spot_lights`).
    """
    truth = poses if poses is not None else recording.truth
    if truth is None:
        raise ConfigError(recording.folder, "truth.csv",
                          "the survey needs known poses: truth.csv or --poses FILE")
    if cluster_m <= 0 or min_views < 1:
        raise ConfigError(None, "cluster_m", "expected cluster_m > 0 and min_views >= 1")
    table = truth if isinstance(truth, StampedPoses) else StampedPoses.from_truth(truth)
    rig = recording.rig
    height = recording.site.ceiling_height_m if ceiling_height_m is None else ceiling_height_m
    check_rig_site(rig, replace(Site(height), source=recording.site.source))
    check_spot_lights(recording, height, spot_params, max_view_angle_deg)
    valid = view_mask(rig, math.radians(max_view_angle_deg))
    # poses at (some of) the frames' own stamps are used as they are
    stamped = offset_s is None and bool(np.isin(table.t_ns, recording.t_ns).all())
    estimate = offset_s is None and not stamped
    det = _detections(recording, table, height, spot_params, valid,
                      None if stamped else MAX_OFFSET_S if estimate else abs(offset_s))
    sigma_off = None
    if estimate:
        offset_s, sigma_off = estimate_offset(det, table, cluster_m, min_views)
    P, ok = det.world(table, offset_s or 0.0)
    C, sig, spread, views, unassigned = cluster_points(P, det.frame[ok], cluster_m,
                                                       min_views)
    if C.shape[0] == 0:
        raise CalibrationError(f"{recording.folder}: no light seen in {min_views} or more "
                               f"frames ({P.shape[0]} detections in {det.frames_used} "
                               "frames)")
    return LightMap(C, sig, spread, views, det.frames_used, int(P.shape[0]), unassigned,
                    offset_s, sigma_off)


# ------------------------------------------------------------------ chaining survey
@dataclass(frozen=True)
class KnownLights:
    """What the integrator measures to tie a chained survey to the site frame W.

    The vehicle starts parked under light A (the light nearest the image nadir in frame
    ``anchor_frame``), whose position in W was measured (a plumb line from the light to
    the floor, a tape to two walls or to the origin mark). The direction of W's x axis
    comes from either

    * ``second_m``: a second light B measured the same way (best: a long baseline, e.g.
      the site frame *defined* by A at the origin and B on the +x axis at a taped
      distance). Only B's direction from A fixes the map; its distance identifies B
      among the surveyed lights (within ``match_m``) and is checked, or
    * ``yaw_deg``: the vehicle's heading in the anchor frame (parked parallel to a wall
      or a floor line that is the x axis: about +-1 deg, so worse than B far away).

    With both, the heading finds B and B fixes the map.

    Attributes:
        first_m: ``(x, y)`` of light A in W, metres.
        second_m: ``(x, y)`` of light B in W, metres, or None.
        yaw_deg: vehicle yaw in the anchor frame, degrees (SPEC §1), or None.
        anchor_frame: index of the frame taken under light A.
        match_m: tolerance on the taped distance A-B when looking for B.
        fit_height: with B, trust the taped distance A-B over the site's ceiling height:
            B is held at ``second_m`` and the scale of the map (the camera-to-ceiling
            height) is estimated. A tape over 5 m is good to a few mm (0.1 %); a ceiling
            height rarely to better than 1 cm in 2.5 m (0.4 %). Without it, only B's
            bearing is used and the height sets the scale.
    """

    first_m: tuple[float, float]
    second_m: tuple[float, float] | None = None
    yaw_deg: float | None = None
    anchor_frame: int = 0
    match_m: float = 0.15
    fit_height: bool = True

    def __post_init__(self) -> None:
        if self.second_m is None and self.yaw_deg is None:
            raise ConfigError(None, "second_m", "the survey needs the direction of the "
                              "site x axis: a second known light or the first frame's yaw")
        for key in ("first_m", "second_m"):
            v = getattr(self, key)
            if v is not None and (len(v) != 2 or not all(math.isfinite(float(a)) for a in v)):
                raise ConfigError(None, key, f"expected (x, y) in metres, found {v!r}")
        if self.second_m is not None and math.dist(self.first_m, self.second_m) < 0.3:
            raise ConfigError(None, "second_m", "the second known light must be at least "
                              "0.3 m from the first")
        if self.yaw_deg is not None and not math.isfinite(self.yaw_deg):
            raise ConfigError(None, "yaw_deg", f"expected degrees, found {self.yaw_deg!r}")
        if self.anchor_frame < 0 or self.match_m <= 0:
            raise ConfigError(None, "anchor_frame", "expected anchor_frame >= 0, match_m > 0")


@dataclass(frozen=True, eq=False)
class ChainSurvey:
    """The result of :func:`survey_chain`.

    Attributes:
        lightmap: the lights, ``sigma_m`` the radial 1-sigma ``sqrt(trace C)`` of each
            light's 2x2 covariance ``C`` from the adjustment (``cov_m2``), ``spread_m``
            the RMS ceiling distance of its single-frame detections from it.
        cov_m2: ``(N, 2, 2)`` light covariances in W, m².
        frames: ``(F,)`` indices of the frames placed in the chain.
        poses: ``(F, 3)`` adjusted vehicle poses ``(x, y, yaw_rad)`` of those frames in W.
        rms_px: RMS pixel residual of the adjustment.
        unplaced: frames that saw lights but shared fewer than two with the map.
        anchor: index (in ``lightmap.lights_m``) of light A; ``second`` that of B or -1.
        ceiling_height_m, height_sigma_m: the ceiling height that makes the map's scale
            agree with the taped distance A-B, and its 1-sigma (when ``height_fitted``;
            else the height used, sigma 0).
        height_fitted: whether the height was estimated (B given, ``fit_height``).
    """

    lightmap: LightMap
    cov_m2: np.ndarray
    frames: np.ndarray
    poses: np.ndarray
    rms_px: float
    unplaced: int
    anchor: int
    second: int
    ceiling_height_m: float
    height_sigma_m: float
    height_fitted: bool


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _place(q: np.ndarray, lights: np.ndarray, prior: np.ndarray, gate_wide: float,
           gate: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose ``(x, y, yaw)`` of a frame with ceiling points ``q`` (V) against the map
    built so far, and its ``(K, 2)`` (observation, light) pairs; None below 2 pairs.

    Tried from the previous frame's pose (a wide gate, refit, the tight gate), then, if
    that fails, by global pattern matching on the map (a jump in the recording).
    """
    pm = PatternMatcher(lights, gate)

    def from_seed(yaw: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        # associate with a shrinking gate, refitting the rigid transform each time
        for g in (gate_wide, 0.5 * (gate_wide + gate), gate):
            pairs = pm.associate(q, yaw, t, g)
            if pairs.shape[0] < 2:
                return None
            yaw, t = fit_rigid_2d(q[pairs[:, 0]], lights[pairs[:, 1]])
        return np.array([t[0], t[1], yaw]), pairs

    out = from_seed(float(prior[2]), prior[:2])
    if out is None and q.shape[0] >= 3 and lights.shape[0] >= 3:
        cands = [c for c in pm.match(q) if c.inliers >= 3]
        if cands and (len(cands) == 1 or cands[0].score > cands[1].score + 1):
            out = from_seed(cands[0].yaw_rad, np.array([cands[0].x_m, cands[0].y_m]))
    return out


def _adjust(obs_q: np.ndarray, obs_J: np.ndarray, obs_f: np.ndarray, obs_l: np.ndarray,
            poses: np.ndarray, lights: np.ndarray, fixed_light: int, axis_light: int,
            axis_dir: np.ndarray | None, fixed_yaw_frame: int,
            centre_v: np.ndarray | None = None, scale: float = 1.0, iterations: int = 20,
            sigma_floor_px: float = 0.05
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, float, float]:
    """Joint least squares of frame poses and light positions (Levenberg-Marquardt).

    Residual of observation k (frame f, light l): ``J_k (q̂ - q_k)`` pixels, with
    ``q̂ = Rz(-yaw_f) (L_l - t_f)`` the light seen from the frame (as
    :func:`ceilkit.runtime.estimators.lights.refine_pose_ceiling`). Gauge: light ``fixed_light``
    held; then either light ``axis_light`` moves only along ``axis_dir`` (its bearing
    from the fixed light is held) or frame ``fixed_yaw_frame``'s yaw is held. With
    ``centre_v`` (the camera's place in V), light ``axis_light`` is held entirely and a
    scale ``s`` of the ceiling points about ``centre_v`` is estimated instead: a wrong
    ceiling height (or a radial centroid bias) scales them so; ``q -> c + s (q - c)``.

    Returns ``(poses (F, 3), lights (N, 2), light covariances (N, 2, 2), rms_px,
    residual norms (K,) px, scale, scale 1-sigma)``; covariances are ``s² (JᵀJ)⁻¹`` of
    the reduced problem.
    """
    F, N = poses.shape[0], lights.shape[0]
    fit_scale = centre_v is not None
    P = 3 * F + 2 * N + 1
    T = _gauge_basis(F, N, fixed_light, axis_light, axis_dir, fixed_yaw_frame, fit_scale)
    K = obs_q.shape[0]
    idx = np.concatenate([3 * obs_f[:, None] + np.arange(3)[None],
                          3 * F + 2 * obs_l[:, None] + np.arange(2)[None],
                          np.full((K, 1), P - 1)], axis=1)                 # (K, 6)
    c_v = np.zeros(2) if centre_v is None else np.asarray(centre_v, float)[:2]
    dq = obs_q - c_v

    def residuals(po: np.ndarray, li: np.ndarray, sc: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        yaw = po[obs_f, 2]
        c, s = np.cos(yaw), np.sin(yaw)
        v = li[obs_l] - po[obs_f, :2]
        qh = np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], 1)
        r = np.einsum("kij,kj->ki", obs_J, qh - (c_v + sc * dq))
        M = np.zeros((K, 2, 6))
        M[:, 0, 0], M[:, 0, 1], M[:, 0, 2] = -c, -s, qh[:, 1]
        M[:, 1, 0], M[:, 1, 1], M[:, 1, 2] = s, -c, -qh[:, 0]
        M[:, 0, 3], M[:, 0, 4] = c, s
        M[:, 1, 3], M[:, 1, 4] = -s, c
        M[:, :, 5] = -dq
        return r, obs_J @ M                                   # (K, 2), (K, 2, 6)

    def normal(r: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        H = np.zeros((P, P))
        g = np.zeros(P)
        blocks = np.einsum("kai,kaj->kij", A, A)
        np.add.at(H, (idx[:, :, None], idx[:, None, :]), blocks)
        np.add.at(g, idx, np.einsum("kai,ka->ki", A, r))
        return T.T @ H @ T, T.T @ g

    po, li, sc, r, A, cost = _iterate(residuals, normal, T, poses.copy(), lights.copy(),
                                      float(scale), iterations)
    Hr, _ = normal(r, A)
    dof = 2 * K - T.shape[1]
    s2 = max(cost / dof if dof > 0 else 0.0, sigma_floor_px ** 2)
    try:
        Cr = np.linalg.inv(Hr)
    except np.linalg.LinAlgError:
        raise CalibrationError("the light-map adjustment is singular: too little "
                               "overlap between frames") from None
    TL = T[3 * F:P - 1]
    C = s2 * (TL @ Cr @ TL.T)
    cov = np.stack([C[2 * n:2 * n + 2, 2 * n:2 * n + 2] for n in range(N)]) if N else \
        np.zeros((0, 2, 2))
    sc_sigma = float(math.sqrt(s2 * (T[P - 1] @ Cr @ T[P - 1]))) if fit_scale else 0.0
    po[:, 2] = (po[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return (po, li, cov, math.sqrt(cost / max(K, 1)), np.linalg.norm(r, axis=1), sc,
            sc_sigma)


def _gauge_basis(F: int, N: int, fixed_light: int, axis_light: int,
                 axis_dir: np.ndarray | None, fixed_yaw_frame: int, fit_scale: bool
                 ) -> np.ndarray:
    """``T`` ``(3F + 2N + 1, reduced)``: the full increment of :func:`_adjust`'s
    parameters (poses, lights, scale) is ``T @`` the reduced one (the gauge removed)."""
    P = 3 * F + 2 * N + 1
    cols: list[np.ndarray] = []
    for f in range(F):
        for a in range(3):
            if a == 2 and f == fixed_yaw_frame and axis_light < 0:
                continue
            e = np.zeros(P)
            e[3 * f + a] = 1.0
            cols.append(e)
    for n in range(N):
        if n == fixed_light:
            continue
        if n == axis_light and fit_scale:
            continue
        if n == axis_light and axis_dir is not None:
            e = np.zeros(P)
            e[3 * F + 2 * n:3 * F + 2 * n + 2] = axis_dir
            cols.append(e)
            continue
        for a in range(2):
            e = np.zeros(P)
            e[3 * F + 2 * n + a] = 1.0
            cols.append(e)
    if fit_scale:
        e = np.zeros(P)
        e[P - 1] = 1.0
        cols.append(e)
    return np.array(cols).T


def _iterate(residuals, normal, T: np.ndarray, po: np.ndarray, li: np.ndarray, sc: float,
             iterations: int) -> tuple:
    """:func:`_adjust`'s iterations from ``(po, li, sc)``, in the reduced parameters
    ``T`` spans: ``(po, li, sc, residuals, their Jacobian, cost)`` at the end."""
    F, N = po.shape[0], li.shape[0]
    P = 3 * F + 2 * N + 1
    r, A = residuals(po, li, sc)
    cost = float((r * r).sum())
    lam = 1e-6
    for _ in range(iterations):
        Hr, gr = normal(r, A)
        try:
            step = -np.linalg.solve(Hr + lam * np.diag(np.diag(Hr) + 1e-12), gr)
        except np.linalg.LinAlgError:
            raise CalibrationError("the light-map adjustment is singular: too little "
                                   "overlap between frames") from None
        full = T @ step
        po_n = po + full[:3 * F].reshape(F, 3)
        li_n = li + full[3 * F:P - 1].reshape(N, 2)
        sc_n = sc + full[P - 1]
        r_n, A_n = residuals(po_n, li_n, sc_n)
        cost_n = float((r_n * r_n).sum())
        if cost_n <= cost:
            po, li, sc, r, A = po_n, li_n, sc_n, r_n, A_n
            done = cost - cost_n < 1e-10 * max(cost, 1e-12)
            cost = cost_n
            lam = max(lam / 10, 1e-9)
            if done or np.abs(full).max() < 1e-7:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    return po, li, sc, r, A, cost


def frame_points(recording: Recording, ceiling_height_m: float | None = None,
                 spot_params: SpotParams | None = None, max_view_angle_deg: float = 60.0
                 ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per frame with lights: ``(frame index, ceiling points in V (n, 2), pixel
    Jacobians d(px)/d(q) (n, 2, 2))``, each point the centroid of the spot's lit face on
    the ceiling (:func:`~ceilkit.runtime.estimators.lights.ceiling_centroids`), each
    Jacobian at its image centroid; spots beyond ``max_view_angle_deg`` from the
    vertical are left out."""
    rig = recording.rig
    height = recording.site.ceiling_height_m if ceiling_height_m is None else ceiling_height_m
    check_rig_site(rig, replace(Site(height), source=recording.site.source))
    valid = view_mask(rig, math.radians(max_view_angle_deg))
    jgrid = jacobian_grid(rig, height, 8)
    obs: list[tuple[int, np.ndarray, np.ndarray]] = []
    for k in range(len(recording)):
        spots = detect_spots(_image(recording, k), spot_params, valid)
        if len(spots) == 0:
            continue
        q, ok = ceiling_centroids(rig, height, spots.centroids_px, spots.cov_px)
        J = interp_grid(jgrid, 8, spots.centroids_px)
        ok &= np.all(np.isfinite(J), axis=(1, 2))
        if np.any(ok):
            obs.append((k, q[ok], J[ok]))
    return obs


def survey_chain(recording: Recording, known: KnownLights, *,
                 ceiling_height_m: float | None = None, min_views: int = 3,
                 gate_m: float = 0.1, step_gate_m: float = 0.6,
                 spot_params: SpotParams | None = None, max_view_angle_deg: float = 60.0,
                 max_residual_px: float = 3.0) -> ChainSurvey:
    """Build a light map without known poses, by chaining overlapping frames.

    Every frame's spots become ceiling points in V (:func:`frame_points`, as for
    :func:`survey_lights`); :func:`chain_points` does the rest.

    Args:
        recording: frames, rig and site (its ``ceiling_height`` unless overridden).
        known: light A (under the vehicle in ``known.anchor_frame``) and the x axis.
        spot_params, max_view_angle_deg: as :func:`survey_lights`.
        min_views, gate_m, step_gate_m, max_residual_px: see :func:`chain_points`.

    Raises:
        ConfigError: bad options; the anchor frame is not in the recording.
        CalibrationError: as :func:`chain_points`.
    """
    n_frames = len(recording)
    if known.anchor_frame >= n_frames:
        raise ConfigError(None, "anchor_frame",
                          f"frame {known.anchor_frame} is not in the recording "
                          f"{recording.folder} ({n_frames} frames: 0..{n_frames - 1})")
    height = recording.site.ceiling_height_m if ceiling_height_m is None else ceiling_height_m
    check_spot_lights(recording, height, spot_params, max_view_angle_deg)
    obs = frame_points(recording, height, spot_params, max_view_angle_deg)
    return chain_points(obs, recording.rig, height, known, min_views=min_views,
                        gate_m=gate_m, step_gate_m=step_gate_m,
                        max_residual_px=max_residual_px, source=str(recording.folder))


def chain_points(obs: list[tuple[int, np.ndarray, np.ndarray]], rig: Rig,
                 ceiling_height_m: float, known: KnownLights, *, min_views: int = 3,
                 gate_m: float = 0.1, step_gate_m: float = 0.6,
                 max_residual_px: float = 3.0, systematic_px: float = 0.05,
                 source: str = "survey") -> ChainSurvey:
    """The chaining survey from per-frame ceiling points (:func:`frame_points`).

    The first frame that sees lights starts the map in its own vehicle frame; each next
    frame is placed by the lights it shares with the map so far (at least two, found
    from the previous frame's pose within ``step_gate_m``, or else by pattern
    matching), and adds the lights it sees first. The map is moved into W by the known
    lights; then a joint least-squares adjustment (Levenberg-Marquardt, in pixels) of
    all placed frames' poses and all lights seen in ``min_views`` frames or more, with
    the gauge held by the known lights (:class:`KnownLights`), gives the map and each
    light's covariance.

    Args:
        obs: ``(frame index, q_V (n, 2), J (n, 2, 2))`` per frame, in frame order.
        rig, ceiling_height_m: the rig and height the points were computed with.
        known: light A (under the vehicle in ``known.anchor_frame``) and the x axis.
        min_views: fewest frames that must see a light for it to be kept.
        gate_m: an observation farther than this from its light (ceiling metres) is
            another light.
        step_gate_m: largest move of a light between the predictions of consecutive
            frames (vehicle motion between frames, at the light).
        max_residual_px: observations with larger residuals after a first adjustment
            are dropped (reflections, merged spots) and the adjustment is repeated.
        systematic_px: centroid error that more views do not average out (the lens and
            perspective shift a disc's centroid from its centre's image; vignetting and
            glow pull it inwards: a few hundredths of a pixel). Each light's covariance
            gets ``(systematic_px / g)² I`` added, ``g`` the median pixels per metre of
            its sightings (``sqrt |det J|``); 0 reports the adjustment's alone.
        source: names the data in error messages.

    Raises:
        ConfigError: bad options.
        CalibrationError: the known light is never seen (no light in the anchor frame,
            or the anchor frame cannot be placed), the second known light is not
            found, or consecutive frames do not overlap (more than half the frames
            share fewer than two lights with the map).
    """
    if min_views < 2:
        raise ConfigError(None, "min_views", f"a chaining survey needs at least 2 views of "
                          f"a light, found {min_views}")
    if gate_m <= 0 or step_gate_m < gate_m:
        raise ConfigError(None, "gate_m", "expected 0 < gate_m <= step_gate_m")
    if not any(o[0] == known.anchor_frame for o in obs):
        raise CalibrationError(f"{source}: the known light is never seen: frame "
                               f"{known.anchor_frame} (under the known light) shows no light")
    chain = _chain(obs, gate_m, step_gate_m)                       # 2. chain
    _check_chain(chain, obs, known, source)
    anchor = _anchor(chain, rig, ceiling_height_m, known, min_views, source)   # 3. into W
    adjusted = _adjust_robustly(chain, anchor, rig, min_views, max_residual_px,  # 4.
                                source)
    return _survey(chain, anchor, adjusted, rig, ceiling_height_m, min_views,    # 5.
                   systematic_px)


@dataclass(frozen=True, eq=False)
class _Chain:
    """The chained map in the first placed frame's vehicle frame (:func:`_chain`).

    Attributes:
        lights: ``(L, 2)`` the lights' places (running means). counts: ``(L,)`` their
            sightings. frames: the placed frames' indices. poses: ``(F, 3)`` their
            poses. unplaced: the frames that could not be placed.
        obs_q, obs_J: ``(N, 2)``, ``(N, 2, 2)`` the kept observations and Jacobians;
            obs_f, obs_l: ``(N,)`` the placed frame (0-based) and light of each.
    """

    lights: np.ndarray
    counts: np.ndarray
    frames: list[int]
    poses: np.ndarray
    unplaced: list[int]
    obs_q: np.ndarray
    obs_J: np.ndarray
    obs_f: np.ndarray
    obs_l: np.ndarray


def _chain(obs: list[tuple[int, np.ndarray, np.ndarray]], gate_m: float,
           step_gate_m: float) -> _Chain:
    """Step 2: each frame placed by the lights it shares with the map so far (the first
    frame at the origin), adding the lights it sees first."""
    lights: list[np.ndarray] = []
    counts: list[int] = []
    frames: list[int] = []
    poses: list[np.ndarray] = []
    o_q, o_J, o_f, o_l = [], [], [], []
    unplaced: list[int] = []
    for k, q, J in obs:
        if not frames:
            pose, pairs = np.zeros(3), np.zeros((0, 2), int)
        else:
            got = _place(q, np.array(lights), poses[-1], step_gate_m, gate_m)
            if got is None:
                unplaced.append(k)
                continue
            pose, pairs = got
        f = len(frames)
        frames.append(k)
        poses.append(pose)
        pw = q @ _rot(pose[2]).T + pose[:2]
        seen = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))
        for i in range(q.shape[0]):
            li = seen.get(i)
            if li is None:                      # a new light, unless one is near
                if lights:
                    d = np.linalg.norm(np.array(lights) - pw[i], axis=1)
                    if d.min() < 2 * gate_m:
                        continue
                lights.append(pw[i].copy())
                counts.append(0)
                li = len(lights) - 1
            else:                               # running mean of the light's place
                lights[li] = lights[li] + (pw[i] - lights[li]) / (counts[li] + 1)
            counts[li] += 1
            o_q.append(q[i])
            o_J.append(J[i])
            o_f.append(f)
            o_l.append(li)
    return _Chain(np.array(lights), np.asarray(counts), frames, np.array(poses), unplaced,
                  np.array(o_q), np.array(o_J), np.array(o_f), np.array(o_l))


def _check_chain(chain: _Chain, obs: list, known: KnownLights, source: str) -> None:
    """Raise the CalibrationError of a chain that misses the anchor frame or most frames."""
    if known.anchor_frame not in chain.frames:
        raise CalibrationError(f"{source}: the known light is never placed: frame "
                               f"{known.anchor_frame} shares fewer than two lights with "
                               f"the frames before it")
    n_obs_frames = len(obs)
    unplaced = chain.unplaced
    if len(unplaced) > 0.5 * n_obs_frames or len(chain.frames) < 2:
        first = unplaced[0] if unplaced else obs[0][0]
        raise CalibrationError(
            f"{source}: the frames do not overlap: {len(unplaced)} of "
            f"{n_obs_frames} frames share fewer than two lights with the map (first: frame "
            f"{first}); drive slower, or so that two lights stay in view from frame to frame")


@dataclass(frozen=True, eq=False)
class _Anchor:
    """The chained map moved into W by the known lights (:func:`_anchor`).

    Attributes:
        L0, P0: the lights ``(L, 2)`` and frame poses ``(F, 3)`` in W.
        la, lb: light A's and light B's index in the chain (``lb`` -1: no B).
        fa: the anchor frame's place among the placed frames.
        axis_dir: the unit vector from A to B in W, or ``None``.
        fit_height: the ceiling points' scale is estimated (B held where it was taped).
    """

    L0: np.ndarray
    P0: np.ndarray
    la: int
    lb: int
    fa: int
    axis_dir: np.ndarray | None
    fit_height: bool


def _anchor(chain: _Chain, rig: Rig, height: float, known: KnownLights, min_views: int,
            source: str) -> _Anchor:
    """Step 3: light A is the light nearest the nadir in the anchor frame; the rotation
    into W from the first frame's yaw or from light B, found by its distance from A."""
    fa = chain.frames.index(known.anchor_frame)
    la = _light_a(chain, rig, height, fa)
    L0, P0 = chain.lights, chain.poses
    A_w = np.asarray(known.first_m, float)
    lb, axis_dir = -1, None
    if known.yaw_deg is not None:
        rot = math.radians(known.yaw_deg) - P0[fa, 2]
    else:
        rot = 0.0
    if known.second_m is not None:
        B_w = np.asarray(known.second_m, float)
        lb = _light_b(chain, known, la, rot, min_views, source)
        v = L0[lb] - L0[la]
        rot = math.atan2(B_w[1] - A_w[1], B_w[0] - A_w[0]) - math.atan2(v[1], v[0])
        axis_dir = (B_w - A_w) / float(np.linalg.norm(B_w - A_w))
    Rw = _rot(rot)
    L0 = (L0 - L0[la]) @ Rw.T + A_w
    P0 = np.column_stack([(P0[:, :2] - chain.lights[la]) @ Rw.T + A_w, P0[:, 2] + rot])
    fit_height = lb >= 0 and known.fit_height
    if fit_height:   # B held where it was taped; the ceiling points' scale is estimated
        L0[lb] = B_w
    elif lb >= 0:    # B onto its bearing from A (its distance stays surveyed)
        L0[lb] = A_w + axis_dir * float(np.dot(L0[lb] - A_w, axis_dir))
    return _Anchor(L0, P0, la, lb, fa, axis_dir, fit_height)


def _light_a(chain: _Chain, rig: Rig, height: float, fa: int) -> int:
    """The light of the anchor frame nearest the camera's nadir (straight up)."""
    R_vc, t_vc = rig.mount.R_vehicle_cam, rig.mount.t_vehicle_cam
    up = R_vc.T @ np.array([0.0, 0.0, 1.0])
    nadir = rig.camera.project(up[None])[0] if up[2] > 1e-6 else \
        np.array([rig.camera.cx, rig.camera.cy])
    in_a = np.nonzero(chain.obs_f == fa)[0]
    q_nadir = ceiling_points(rig, height, nadir[None])[0][0]
    if not np.all(np.isfinite(q_nadir)):
        q_nadir = t_vc[:2]
    ia = in_a[np.argmin(np.linalg.norm(chain.obs_q[in_a] - q_nadir, axis=1))]
    return int(chain.obs_l[ia])


def _light_b(chain: _Chain, known: KnownLights, la: int, rot: float, min_views: int,
             source: str) -> int:
    """The one chained light at the taped distance from light A (near its taped place
    when the first frame's yaw is given too)."""
    A_w = np.asarray(known.first_m, float)
    B_w = np.asarray(known.second_m, float)
    d_ab = float(np.linalg.norm(B_w - A_w))
    rel = chain.lights - chain.lights[la]
    dist = np.linalg.norm(rel, axis=1)
    cand = np.nonzero((np.abs(dist - d_ab) < known.match_m)
                      & (chain.counts >= min_views))[0]
    if known.yaw_deg is not None and cand.size:
        pred = (rel[cand] @ _rot(rot).T) + A_w
        near = np.linalg.norm(pred - B_w, axis=1)
        cand = cand[near < max(1.0, 0.1 * d_ab)]
    if cand.size == 0:
        raise CalibrationError(
            f"{source}: the second known light is never seen: no surveyed "
            f"light lies {d_ab:.2f} +- {known.match_m:.2f} m from the first")
    if cand.size > 1:
        raise CalibrationError(
            f"{source}: the second known light is ambiguous: {cand.size} "
            f"surveyed lights lie {d_ab:.2f} m from the first; give the first frame's "
            f"yaw as well")
    return int(cand[0])


@dataclass(frozen=True, eq=False)
class _Adjusted:
    """The joint adjustment's outcome (:func:`_adjust_robustly`): the poses ``po``, the
    kept lights ``li`` and their covariances ``cov``, the residual RMS, the scale and
    its sigma; ``keep_l`` the lights kept, ``use`` the observations used, ``Lidx`` a
    chain light's row in ``li``."""

    po: np.ndarray
    li: np.ndarray
    cov: np.ndarray
    rms: float
    scale: float
    scale_sigma: float
    keep_l: np.ndarray
    use: np.ndarray
    Lidx: np.ndarray


def _adjust_robustly(chain: _Chain, anchor: _Anchor, rig: Rig, min_views: int,
                     max_residual_px: float, source: str) -> _Adjusted:
    """Step 4: the adjustment over the lights seen in ``min_views`` frames or more (and
    the known ones); observations with outlying residuals dropped, then again."""
    obs_q, obs_J, obs_f, obs_l = chain.obs_q, chain.obs_J, chain.obs_f, chain.obs_l
    la, lb = anchor.la, anchor.lb
    P0, L0 = anchor.P0, anchor.L0
    t_vc = rig.mount.t_vehicle_cam
    scale = 1.0
    keep_l = chain.counts >= min_views
    keep_l[la] = True
    if lb >= 0:
        keep_l[lb] = True
    use = keep_l[obs_l]
    for _ in range(2):
        Lidx = np.cumsum(keep_l) - 1
        po, li, cov, rms, res, scale, scale_sigma = _adjust(
            obs_q[use], obs_J[use], obs_f[use], Lidx[obs_l[use]], P0, L0[keep_l],
            int(Lidx[la]), int(Lidx[lb]) if lb >= 0 else -1, anchor.axis_dir, anchor.fa,
            t_vc[:2] if anchor.fit_height else None, scale)
        bad = res > max(max_residual_px, 5.0 * float(np.median(res)))
        if not np.any(bad):
            break
        u = np.nonzero(use)[0]
        use[u[bad]] = False
        P0, L0[keep_l] = po, li
        # a light left without observations leaves the adjustment
        seen_l = np.bincount(obs_l[use], minlength=keep_l.size) > 0
        keep_l &= seen_l
        use &= keep_l[obs_l]
        if not (keep_l[la] and (lb < 0 or keep_l[lb])):
            raise CalibrationError(f"{source}: every sighting of a known light "
                                   f"was rejected as an outlier")
    return _Adjusted(po, li, cov, rms, scale, scale_sigma, keep_l, use, Lidx)


def _survey(chain: _Chain, anchor: _Anchor, adj: _Adjusted, rig: Rig, height: float,
            min_views: int, systematic_px: float) -> ChainSurvey:
    """Step 5: the result, the lights with their views, scatter and covariance (with the
    centroids' systematic error), in x then y order."""
    t_vc = rig.mount.t_vehicle_cam
    obs_q, obs_J, obs_f, obs_l = chain.obs_q, chain.obs_J, chain.obs_f, chain.obs_l
    la, lb, use, Lidx = anchor.la, anchor.lb, adj.use, adj.Lidx
    po, li, cov, scale = adj.po, adj.li, adj.cov, adj.scale
    lk = np.nonzero(adj.keep_l)[0]
    c_v = t_vc[:2] if anchor.fit_height else np.zeros(2)
    used_l = Lidx[obs_l[use]]
    of = obs_f[use]
    yaw = po[of, 2]
    pw = np.einsum("kij,kj->ki", np.stack([np.stack([np.cos(yaw), -np.sin(yaw)], 1),
                                           np.stack([np.sin(yaw), np.cos(yaw)], 1)], 1),
                   c_v + scale * (obs_q[use] - c_v)) + po[of, :2]
    views = np.array([len(set(of[used_l == n].tolist())) for n in range(lk.size)])
    spread = np.array([float(np.sqrt(np.mean(np.sum((pw[used_l == n] - li[n]) ** 2, 1))))
                       if np.any(used_l == n) else np.nan for n in range(lk.size)])
    ok = views >= min(min_views, 2)
    ok[Lidx[la]] = True
    if systematic_px > 0:
        gain = np.sqrt(np.abs(np.linalg.det(obs_J[use])))
        for n in range(lk.size):
            if np.any(used_l == n) and n != Lidx[la]:
                g = float(np.median(gain[used_l == n]))
                cov[n] = cov[n] + (systematic_px / g) ** 2 * np.eye(2)
    sigma = np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0))
    order = np.nonzero(ok)[0]
    order = order[np.lexsort((li[order, 1], li[order, 0]))]
    lm = LightMap(li[order], sigma[order], spread[order], views[order], len(chain.frames),
                  int(obs_q.shape[0]), int(obs_q.shape[0] - use.sum()))
    pos = {int(n): i for i, n in enumerate(order)}
    dz = height - float(t_vc[2])
    return ChainSurvey(lm, cov[order], np.array(chain.frames), po, adj.rms,
                       len(chain.unplaced), pos[int(Lidx[la])],
                       pos.get(int(Lidx[lb]), -1) if lb >= 0 else -1,
                       float(t_vc[2]) + scale * dz, adj.scale_sigma * dz, anchor.fit_height)


def lightmap_header_lines(lm: LightMap) -> list[str]:
    """Report lines for the site file's header: the survey and each light's uncertainty."""
    lines = [f"light survey: {lm.lights_m.shape[0]} lights from {lm.detections} detections "
             f"in {lm.frames_used} frames ({lm.unassigned} unassigned)",
             "per light (same order as `lights`): sigma_mm = standard error of the centre, "
             "spread_mm = scatter of single-frame detections, views"]
    if lm.offset_s is not None:
        how = ("as given" if lm.offset_sigma_s is None
               else f"+- {1e3 * lm.offset_sigma_s:.3f} ms (1 sigma), estimated")
        lines.insert(1, f"pose time offset {1e3 * lm.offset_s:+.3f} ms {how} (pose time = "
                        "frame stamp + offset; poses interpolated at the frame stamps)")
    for i, (p, s, sp, v) in enumerate(zip(lm.lights_m, lm.sigma_m, lm.spread_m, lm.views,
                                          strict=True)):
        lines.append(f"  lights[{i}] ({p[0]:.3f}, {p[1]:.3f}): sigma_mm {1e3 * s:.2f}  "
                     f"spread_mm {1e3 * sp:.2f}  views {int(v)}")
    return lines


def chain_header_lines(res: ChainSurvey) -> list[str]:
    """Report lines for a chained survey: how it was tied to W, the adjustment, and
    every light's uncertainty (``sigma_mm`` = radial 1-sigma, ``sx_mm``/``sy_mm`` per
    axis, from the adjustment's covariance and the systematic floor)."""
    lm = res.lightmap
    tie = (f"gauge: light A = lights[{res.anchor}] held"
           + (f", light B = lights[{res.second}]" if res.second >= 0 else "")
           + (f"; ceiling height {res.ceiling_height_m:.4f} +- {res.height_sigma_m:.4f} m "
              f"fitted to the taped A-B distance" if res.height_fitted else ""))
    lines = [f"chained survey: {lm.lights_m.shape[0]} lights from {lm.detections} "
             f"detections in {lm.frames_used} placed frames ({res.unplaced} not placed, "
             f"{lm.unassigned} detections unused); adjustment residual "
             f"{res.rms_px:.3f} px RMS", tie,
             "per light (same order as `lights`): sigma_mm = radial 1-sigma "
             "sqrt(sx^2 + sy^2), sx_mm, sy_mm, spread_mm = scatter of single-frame "
             "detections, views"]
    for i, (p, s, sp, v) in enumerate(zip(lm.lights_m, lm.sigma_m, lm.spread_m, lm.views,
                                          strict=True)):
        sx, sy = np.sqrt(np.maximum(np.diag(res.cov_m2[i]), 0.0))
        lines.append(f"  lights[{i}] ({p[0]:.4f}, {p[1]:.4f}): sigma_mm {1e3 * s:.2f}  "
                     f"sx_mm {1e3 * sx:.2f}  sy_mm {1e3 * sy:.2f}  spread_mm {1e3 * sp:.2f}"
                     f"  views {int(v)}")
    return lines


def write_site(lm: LightMap, out: str | Path, base: Site | None, header: str = "",
               ceiling_height_m: float | None = None) -> Site:
    """Write ``out`` (site.yaml) with ``lights`` from ``lm``, the other sections kept
    from ``base`` (an existing site file, or the recording's); returns the site."""
    if base is None:
        if ceiling_height_m is None:
            raise ConfigError(None, "ceiling_height_m", f"no site to keep the ceiling height "
                              f"of ({out} is new): give the ceiling height")
        base = Site(ceiling_height_m)
    site = replace(base, lights_m=np.round(lm.lights_m, 4), light_sigma_m=None,
                   source=str(out))
    if ceiling_height_m is not None:
        site = replace(site, ceiling_height_m=ceiling_height_m)
    site.save(out, header)
    return Site.load(out)   # read back: the file is valid by the same rules as any other


__all__ = ["ChainSurvey", "KnownLights", "LightMap", "chain_header_lines", "chain_points",
           "cluster_points",
           "frame_points",
           "lightmap_header_lines", "load_pose_table", "survey_chain", "survey_lights",
           "write_site"]
