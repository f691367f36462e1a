"""Benchmark of the block method on a drop-tile ceiling with small markers (issue 36).

The case measured from outside on main: 0.6 m tiles (``corridor`` seams ``lines_along``
/ ``lines_across`` every 0.6 m), a dark 0.6 m hatch (a square block) and five 16 cm
AprilTag 36h11 markers; an upward 640x480 pinhole camera, f = 310 px, 1.9 m below the
ceiling (about 26 px per tag, 3.2 px per cell); noise 2 grey levels, blur 0.8 px; a loop
of ``--frames`` poses round the site. Every frame is estimated with no prior (as
``ceilrun replay --no-track``), with the full-resolution marker fallback (the default)
and without it (``marker_fallback=false``: the method as it was), and read by
``cv2.aruco``'s default ``ArucoDetector``.

    python benchmarks/bench_tiles_markers.py [--frames 120] [--out FILE.json]

Prints and saves (JSON, beside this script by default):

* frames with a marker fully in view; frames on which the block method localized from a
  marker, and on which ``cv2.aruco`` read one of the site's markers;
* position and yaw error (median, p95, max) of the marker fixes;
* valid full poses more than 10 cm or 2 degrees off (must be 0); heading-only estimates
  (the tiles' parallels: modulo 90 degrees, never a full pose) and ``ambiguous`` frames
  (the hatch alone: its 4 hypotheses, the truth among them);
* time per frame (wall clock, median and p95) with and without the fallback, and
  ``cv2.aruco``'s own.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import AcrossLines, Block, Corridor, MarkerPose, Markers, Site
from ceilkit.runtime.estimators.block.estimator import BlockEstimator
from ceilkit.runtime.features.quads import QUIET_CELLS
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.sim.render import SimOptions, render_frame

HERE = Path(__file__).resolve().parent
DICT = "DICT_APRILTAG_36h11"
CEILING_M = 2.8
CAMERA_Z_M = 0.9
TAG_M = 0.16
OPTIONS = SimOptions(noise_sigma=2.0, blur_px=0.8)
HATCH = np.array([[1.2, 0.0], [1.8, 0.0], [1.8, 0.6], [1.2, 0.6]])
MARKERS = ((3, 0.3, 0.3, 0.0), (11, 0.9, -0.9, 90.0), (17, 2.7, 0.3, 180.0),
           (23, 3.3, -0.9, -90.0), (42, 4.5, 0.9, 30.0))
WRONG_M, WRONG_DEG = 0.10, 2.0


def rig() -> Rig:
    cam = CameraModel.pinhole(640, 480, 310.0)
    return Rig(cam, Mount(0.0, math.radians(90.0), 0.0, 0.1, 0.0, CAMERA_Z_M))


def site() -> Site:
    along = tuple(round(-3.0 + 0.6 * k, 6) for k in range(11))
    poses = tuple(MarkerPose(i, x, y, math.radians(a), TAG_M) for i, x, y, a in MARKERS)
    return Site(CEILING_M, corridor=Corridor(along, AcrossLines(0.0, 0.6)),
                blocks=(Block("H", HATCH, "dark"),), markers=Markers(DICT, TAG_M, poses))


def loop(n: int) -> list[tuple[float, float, float]]:
    """``n`` poses round an ellipse (centre (2.4, 0), radii 3.0 x 1.6 m), facing along it."""
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        x, y = 2.4 + 3.0 * math.cos(a), 1.6 * math.sin(a)
        out.append((x, y, math.atan2(1.6 * math.cos(a), -3.0 * math.sin(a))))
    return out


def fully_in_view(r: Rig, s: Site, pose) -> list[int]:
    """Ids of the markers whose printed area (quiet ring included) is in the frame."""
    R = r.mount.R_world_cam(pose[2])
    c = r.mount.camera_position(*pose)
    out = []
    for p in s.markers.poses:
        ring = [p.x_m, p.y_m] + (p.corners_m() - [p.x_m, p.y_m]) * (8 + 2 * QUIET_CELLS) / 8
        px = r.camera.project((np.hstack([ring, np.full((4, 1), CEILING_M)]) - c) @ R)
        if np.all(np.isfinite(px)) and px[:, 0].min() > 2 and px[:, 1].min() > 2 \
                and px[:, 0].max() < r.camera.width - 3 and px[:, 1].max() < r.camera.height - 3:
            out.append(p.id)
    return out


def _stats(v: list[float]) -> dict[str, float | None]:
    if not v:
        return {"median": None, "p95": None, "max": None}
    a = np.asarray(v, float)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max())}


def run(frames: list[np.ndarray], poses, est: BlockEstimator) -> dict:
    ms, ours, pos, yaw, wrong, heading, ambiguous, amb_ok = [], [], [], [], 0, 0, 0, 0
    for k, (img, p) in enumerate(zip(frames, poses, strict=True)):
        t = time.perf_counter()
        e = est.estimate(img, k)
        ms.append(1e3 * (time.perf_counter() - t))
        marker = bool(e) and str(e.diagnostics.get("source", "")).startswith("marker:")
        ours.append(marker)
        if e and e.x_m is not None:
            d = math.hypot(e.x_m - p[0], e.y_m - p[1])
            dy = abs(math.degrees(math.remainder(e.yaw_rad - p[2], 2 * math.pi)))
            wrong += d > WRONG_M or dy > WRONG_DEG
            if marker:
                pos.append(1e3 * d)
                yaw.append(dy)
        elif e:
            heading += 1
        elif e.reason == "ambiguous":
            ambiguous += 1
            amb_ok += any(math.hypot(h.x_m - p[0], h.y_m - p[1]) < 0.02 and abs(
                math.remainder(h.yaw_rad - p[2], 2 * math.pi)) < math.radians(1.0)
                for h in e.hypotheses if h.x_m is not None)
    return {"marker_frames": ours, "position_mm": _stats(pos), "yaw_deg": _stats(yaw),
            "wrong_valid": int(wrong), "heading_only": heading, "ambiguous": ambiguous,
            "ambiguous_truth_among_hypotheses": amb_ok,
            "ms": {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95))}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--out", type=Path, default=HERE / "bench_tiles_markers.json")
    a = ap.parse_args()
    r, s = rig(), site()
    poses = loop(a.frames)
    rng = np.random.default_rng(36)
    frames = [render_frame(r, s, *p, OPTIONS, rng) for p in poses]
    in_view = [bool(fully_in_view(r, s, p)) for p in poses]
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
                                  cv2.aruco.DetectorParameters())
    known = {p.id for p in s.markers.poses}
    theirs, aruco_ms = [], []
    for img in frames:
        t = time.perf_counter()
        _, ids, _ = det.detectMarkers(img)
        aruco_ms.append(1e3 * (time.perf_counter() - t))
        theirs.append(ids is not None and bool(known & {int(i) for i in ids.ravel()}))
    results = {}
    for name, opts in (("before", {"marker_fallback": False}), ("after", {})):
        est = BlockEstimator(r, s, opts)
        est.estimate(frames[0], 0)                     # compile / warm
        est = BlockEstimator(r, s, opts)
        got = run(frames, poses, est)
        mf = got.pop("marker_frames")
        got["frames_marker_localized"] = int(sum(mf))
        got["frames_in_view_not_localized"] = int(sum(v and not m for v, m in
                                                      zip(in_view, mf, strict=True)))
        got["frames_aruco_read_not_localized"] = int(sum(t and not m for t, m in
                                                         zip(theirs, mf, strict=True)))
        results[name] = got
    out = {"case": {"frames": a.frames, "f_px": 310.0, "below_ceiling_m": CEILING_M - CAMERA_Z_M,
                    "tag_m": TAG_M, "tile_m": 0.6, "noise": OPTIONS.noise_sigma,
                    "blur_px": OPTIONS.blur_px},
           "frames_marker_fully_in_view": int(sum(in_view)),
           "frames_aruco_reads_a_marker": int(sum(theirs)),
           "aruco_ms": {"median": float(np.median(aruco_ms)),
                        "p95": float(np.percentile(aruco_ms, 95))},
           **results}
    print(f"{a.frames} frames: a marker fully in view on {out['frames_marker_fully_in_view']}, "
          f"cv2.aruco (default) reads one on {out['frames_aruco_reads_a_marker']} "
          f"({out['aruco_ms']['median']:.1f} ms median)")
    for name in ("before", "after"):
        g = results[name]
        p, y = g["position_mm"], g["yaw_deg"]
        pm = "-" if p["median"] is None else f"{p['median']:.2f}/{p['p95']:.2f}/{p['max']:.2f}"
        ym = "-" if y["median"] is None else f"{y['median']:.3f}/{y['p95']:.3f}"
        print(f"{name:6s}: marker fixes on {g['frames_marker_localized']} frames "
              f"(in view but not localized {g['frames_in_view_not_localized']}, "
              f"read by aruco but not localized {g['frames_aruco_read_not_localized']}); "
              f"position median/p95/max {pm} mm, yaw median/p95 {ym} deg; "
              f"wrong valid poses {g['wrong_valid']}; heading-only {g['heading_only']}, "
              f"ambiguous {g['ambiguous']} (truth among hypotheses "
              f"{g['ambiguous_truth_among_hypotheses']}); "
              f"{g['ms']['median']:.1f} ms median, {g['ms']['p95']:.1f} p95 per frame")
    a.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"saved {a.out}")


if __name__ == "__main__":
    main()
