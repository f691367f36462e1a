"""Light-map survey: the ``lights`` section of a site from a recording with known poses.

Every frame's spots (:func:`ceilkit.runtime.spots.detect_spots`) become ceiling points
in the vehicle frame (:func:`ceilkit.runtime.lights.ceiling_points`), then in W with the
frame's known pose (``X_W = Rz(yaw) X_V + (x, y)``, SPEC §1). Points of all frames are
clustered (leader clustering within ``cluster_m``, then every point re-assigned to its
nearest centre); a cluster seen in at least ``min_views`` frames is a light, placed at
the median of its points. Its uncertainty is reported as the scatter of the points
(``spread_m``, RMS distance from the centre) and the standard error of the centre
(``sigma_m = spread / sqrt(n)``).

``site.yaml`` has no key for the uncertainty (unknown keys are errors): it goes into
the file's header comments, one line per light, via :func:`lightmap_header_lines`.

Example::

    rec = Recording("run1")
    lm = survey_lights(rec)                    # uses rec.truth
    write_site(lm, "site.yaml", base=rec.site, header=provenance_header(...))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.lights import ceiling_points, view_mask
from ceilkit.runtime.recording import Recording, Truth, load_poses, load_truth
from ceilkit.runtime.site import Site, check_rig_site
from ceilkit.runtime.spots import SpotParams, detect_spots


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
    """

    lights_m: np.ndarray
    sigma_m: np.ndarray
    spread_m: np.ndarray
    views: np.ndarray
    frames_used: int
    detections: int
    unassigned: int


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


def survey_lights(recording: Recording, poses: Truth | None = None, *,
                  ceiling_height_m: float | None = None, cluster_m: float = 0.15,
                  min_views: int = 3, spot_params: SpotParams | None = None,
                  max_view_angle_deg: float = 60.0) -> LightMap:
    """Build a light map from a recording with known poses.

    Args:
        recording: frames, rig and site (its ``ceiling_height`` unless overridden).
        poses: known vehicle poses, matched to frames by exact stamp (default: the
            recording's ``truth.csv``).
        cluster_m: detections of one light lie within this of each other (and distinct
            lights further apart).
        min_views: fewest frames that must see a light.
        max_view_angle_deg: spots further from the vertical are not used (the
            steepest views are the least precise).

    Raises:
        ConfigError: no poses, or none matching a frame; a ceiling below the camera.
        CalibrationError: no light was seen often enough.
    """
    truth = poses if poses is not None else recording.truth
    if truth is None:
        raise ConfigError(recording.folder, "truth.csv",
                          "the survey needs known poses: truth.csv or --poses FILE")
    if cluster_m <= 0 or min_views < 1:
        raise ConfigError(None, "cluster_m", "expected cluster_m > 0 and min_views >= 1")
    rig = recording.rig
    height = recording.site.ceiling_height_m if ceiling_height_m is None else ceiling_height_m
    site = Site(height)
    check_rig_site(rig, replace(site, source=recording.site.source))
    valid = view_mask(rig, math.radians(max_view_angle_deg))
    pts, ids = [], []
    used = 0
    for k in range(len(recording)):
        pose = truth.lookup(int(recording.t_ns[k]))
        if pose is None:
            continue
        used += 1
        frame = recording.frame(k)
        spots = detect_spots(frame.image, spot_params, valid)
        if len(spots) == 0:
            continue
        q, ok = ceiling_points(rig, height, spots.centroids_px)
        q = q[ok]
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        pw = np.stack([c * q[:, 0] - s * q[:, 1] + x, s * q[:, 0] + c * q[:, 1] + y], 1)
        pts.append(pw)
        ids.append(np.full(pw.shape[0], k))
    if used == 0:
        raise ConfigError(recording.folder, "truth.csv",
                          "no pose matches a frame stamp (frames.csv t_ns)")
    P = np.concatenate(pts) if pts else np.zeros((0, 2))
    F = np.concatenate(ids) if ids else np.zeros(0, int)
    C, sig, spread, views, unassigned = cluster_points(P, F, cluster_m, min_views)
    if C.shape[0] == 0:
        raise CalibrationError(f"{recording.folder}: no light seen in {min_views} or more "
                               f"frames ({P.shape[0]} detections in {used} frames)")
    return LightMap(C, sig, spread, views, used, int(P.shape[0]), unassigned)


def lightmap_header_lines(lm: LightMap) -> list[str]:
    """Report lines for the site file's header: the survey and each light's uncertainty."""
    lines = [f"light survey: {lm.lights_m.shape[0]} lights from {lm.detections} detections "
             f"in {lm.frames_used} frames ({lm.unassigned} unassigned)",
             "per light (same order as `lights`): sigma_mm = standard error of the centre, "
             "spread_mm = scatter of single-frame detections, views"]
    for i, (p, s, sp, v) in enumerate(zip(lm.lights_m, lm.sigma_m, lm.spread_m, lm.views,
                                          strict=True)):
        lines.append(f"  lights[{i}] ({p[0]:.3f}, {p[1]:.3f}): sigma_mm {1e3 * s:.2f}  "
                     f"spread_mm {1e3 * sp:.2f}  views {int(v)}")
    return lines


def write_site(lm: LightMap, out: str | Path, base: Site | None, header: str = "",
               ceiling_height_m: float | None = None) -> Site:
    """Write ``out`` (site.yaml) with ``lights`` from ``lm``, the other sections kept
    from ``base`` (an existing site file, or the recording's); returns the site."""
    if base is None:
        if ceiling_height_m is None:
            raise ConfigError(out, "ceiling_height", "no base site and no ceiling height")
        base = Site(ceiling_height_m)
    site = replace(base, lights_m=np.round(lm.lights_m, 4), source=str(out))
    if ceiling_height_m is not None:
        site = replace(site, ceiling_height_m=ceiling_height_m)
    site.save(out, header)
    return Site.load(out)   # read back: the file is valid by the same rules as any other


__all__ = ["LightMap", "cluster_points", "lightmap_header_lines", "load_pose_table",
           "survey_lights", "write_site"]
