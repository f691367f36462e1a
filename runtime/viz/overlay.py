"""Debug overlays: what an estimator detected, what it matched it to, and the site at its pose.

:func:`draw_overlay` is a pure function: a frame, its estimate (a
:class:`~ceilkit.runtime.estimators.base.PoseEstimate` or a falsy ``Failure``, with the
diagnostics the estimators carry for overlays) and the rig and site give a new BGR
image; nothing is kept between calls.

Drawn, by method:

* corridor: every segment (grey), the forward family coloured by the site line each
  segment was matched to (:data:`LINE_COLOURS`, index in ``lines_along``; white: not
  matched), the across family magenta; the site's ``lines_along`` reprojected at the
  estimated pose, in the same colour as their segments (a wrong match is a misfit).
* lights: examined spots (dim grey rings: rejected by the size/shape checks), used
  spots (yellow), matched spots (green, with the light's index in ``site.lights``);
  every light of the site reprojected at the estimated pose (cyan crosses).
* block: the block's or marker's corners (reprojected at the pose) with their index,
  and every block and marker of the site reprojected at the pose.
* always: a text box with the method, the pose, the quality, or the failure reason.

Convention: pixels ``(u, v)`` (SPEC §1), a site point ``X_W`` seen at vehicle pose
``(x, y, yaw)`` is ``X_C = R_vehicle_camᵀ (Rz(-yaw) (X_W - (x, y, 0)) - t_vehicle_cam)``
(:func:`~ceilkit.runtime.geometry.ceiling.project_px`, as the estimators project).

Example::

    img = draw_overlay(frame.image, est, rig, site)
    cv2.imwrite("frame.png", img)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.geometry.ceiling import project_px

LINE_COLOURS = ((40, 40, 255), (40, 200, 40), (255, 120, 30), (0, 200, 255),
                (200, 60, 200), (255, 255, 60), (60, 140, 255), (160, 255, 160))
"""BGR colour of ``lines_along[k]`` (k modulo the length) and of its matched segments."""

ACROSS_BGR = (255, 0, 255)
UNMATCHED_BGR = (255, 255, 255)
OTHER_BGR = (110, 110, 110)
REJECTED_BGR = (90, 90, 90)
SPOT_BGR = (0, 220, 255)
MATCHED_BGR = (0, 255, 0)
SITE_BGR = (255, 255, 0)
TEXT_BGR = (255, 255, 255)
FAIL_BGR = (60, 60, 255)

LEGEND: tuple[tuple[str, tuple[int, int, int], str], ...] = (
    ("line", OTHER_BGR, "corridor: a detected segment of neither family"),
    ("line", UNMATCHED_BGR, "corridor: a forward segment matched to no site line"),
    ("line", ACROSS_BGR, "corridor: an across segment"),
    ("ring", REJECTED_BGR, "lights: a spot rejected by the size/shape checks"),
    ("ring", SPOT_BGR, "lights: a spot used"),
    ("ring", MATCHED_BGR, "lights: a spot matched to a site light (its index beside it); "
     "block: its detected corners"),
    ("cross", SITE_BGR, "the site's lights, lamps, blocks and markers reprojected at the "
     "estimated pose"),
    ("text", FAIL_BGR, "a failure's reason"),
)
"""What each colour of an overlay means, as ``(shape, BGR, meaning)``; the corridor's
site lines add :data:`LINE_COLOURS` (``lines_along[k]`` and the segments matched to it,
in its colour). The report and the live view draw their legends from these."""


def legend_rows() -> list[tuple[str, str, str]]:
    """:data:`LEGEND` and the site lines' colours as ``(shape, '#rrggbb', meaning)``
    rows, for a legend in HTML."""
    def css(bgr: tuple[int, int, int]) -> str:
        return f"#{bgr[2]:02x}{bgr[1]:02x}{bgr[0]:02x}"

    rows = [(shape, css(bgr), text) for shape, bgr, text in LEGEND]
    rows += [("line", css(bgr), f"corridor: site line lines_along[{k}] reprojected, and the "
              "segments matched to it" + (f" (and [{k + len(LINE_COLOURS)}], ...)" if k == 0
                                          else ""))
             for k, bgr in enumerate(LINE_COLOURS)]
    return rows


def legend_html() -> str:
    """The overlays' colours (:func:`legend_rows`) as an HTML section: the replay report
    and the live view show it beside the overlays."""
    import html

    marks = {"line": "&#9472;&#9472;", "ring": "&#9675;", "cross": "+", "text": "Aa"}
    rows = "".join(
        f"<tr><td style='background:#222;color:{colour};font-weight:bold;"
        f"text-align:center;padding:0 6px'>{marks.get(shape, '&#9632;')}</td>"
        f"<td>{html.escape(text)}</td></tr>" for shape, colour, text in legend_rows())
    return ("<h2>overlay colours</h2><table class='legend'>" + rows + "</table>"
            "<p>The text box: the method and the frame's time (s), the pose (m, deg) and its "
            "quality, or the failure's reason.</p>")


SITE_LINE_HALF_LENGTH_M = 30.0
"""Reprojected corridor lines run this far either side of the camera, along x."""
SITE_LINE_SAMPLES = 241
"""Points per reprojected line (a polyline follows the lens distortion)."""


def as_bgr(image: np.ndarray) -> np.ndarray:
    """A new ``(H, W, 3)`` uint8 BGR copy of a grey or BGR frame."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img[:, :, :3].copy()


def drawn_estimate(est: Estimate) -> tuple[Estimate, bool]:
    """The estimate whose diagnostics are drawn, and whether the tracker gated it: a
    ``gated`` Failure carries the rejected estimate as ``diagnostics['rejected']``."""
    rejected = est.diagnostics.get("rejected") if not est else None
    if isinstance(rejected, PoseEstimate):
        return rejected, True
    return est, False


def world_to_px(rig: Rig, x_m: float, y_m: float, yaw_rad: float,
                points_w: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of points ``(N, 3)`` in W seen from the vehicle pose; NaN
    behind the camera."""
    m = rig.mount
    return project_px(rig.camera, m.R_vehicle_cam, m.t_vehicle_cam, points_w,
                      np.array([[x_m, y_m, yaw_rad]]))[0]


def norm_to_px(rig: Rig, xy_norm: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of undistorted normalized points ``(N, 2)``."""
    return rig.camera.distort(np.asarray(xy_norm, float).reshape(-1, 2))


def _polyline(img: np.ndarray, pts_px: np.ndarray, colour: tuple[int, int, int],
              thickness: int = 1) -> None:
    """Draw the finite runs of ``pts_px`` (N, 2) as polylines."""
    ok = np.all(np.isfinite(pts_px), axis=1)
    h, w = img.shape[:2]
    ok &= (np.abs(pts_px[:, 0]) < 4 * w) & (np.abs(pts_px[:, 1]) < 4 * h)
    runs = np.split(np.arange(ok.size), np.flatnonzero(np.diff(ok.astype(int))) + 1)
    for run in runs:
        if run.size >= 2 and ok[run[0]]:
            cv2.polylines(img, [np.round(pts_px[run]).astype(np.int32)], False, colour,
                          thickness, cv2.LINE_AA)


def _pose_of(est: Estimate) -> tuple[float, float, float] | None:
    """``(x, y, yaw)`` to reproject the site at; x 0 when unobserved (corridor)."""
    if not isinstance(est, PoseEstimate) or est.y_m is None:
        return None
    return (0.0 if est.x_m is None else float(est.x_m)), float(est.y_m), float(est.yaw_rad)


def _draw_corridor(img: np.ndarray, d: Mapping[str, Any], rig: Rig, site: Site,
                   pose: tuple[float, float, float] | None, x_known: bool) -> None:
    segs = d.get("segments_n")
    if pose is not None and site.corridor is not None:
        c_w = rig.mount.camera_position(*pose)
        xs = c_w[0] + np.linspace(-SITE_LINE_HALF_LENGTH_M, SITE_LINE_HALF_LENGTH_M,
                                  SITE_LINE_SAMPLES)
        for k, y_line in enumerate(site.corridor.lines_along_m):
            pts = np.stack([xs, np.full_like(xs, y_line),
                            np.full_like(xs, site.ceiling_height_m)], axis=1)
            _polyline(img, world_to_px(rig, *pose, pts), LINE_COLOURS[k % len(LINE_COLOURS)])
        if x_known:
            for rect in site.lamp_rectangles():
                pts = np.c_[np.r_[rect, rect[:1]], np.full(5, site.ceiling_height_m)]
                _polyline(img, world_to_px(rig, *pose, pts), SITE_BGR)
    if segs is None or len(segs) == 0:
        return
    segs = np.asarray(segs, float)
    ends = norm_to_px(rig, segs.reshape(-1, 2)).reshape(-1, 4)
    along = d.get("along")
    across = d.get("across")
    assign = d.get("assign")
    for i, (u0, v0, u1, v1) in enumerate(ends):
        if not np.all(np.isfinite((u0, v0, u1, v1))):
            continue
        colour, width = OTHER_BGR, 1
        if along is not None and along[i]:
            k = int(assign[i]) if assign is not None else -1
            colour = LINE_COLOURS[k % len(LINE_COLOURS)] if k >= 0 else UNMATCHED_BGR
            width = 3
        elif across is not None and across[i]:
            colour, width = ACROSS_BGR, 3
        cv2.line(img, (int(round(u0)), int(round(v0))), (int(round(u1)), int(round(v1))),
                 colour, width, cv2.LINE_AA)


def _draw_lights(img: np.ndarray, d: Mapping[str, Any], rig: Rig, site: Site,
                 pose: tuple[float, float, float] | None) -> None:
    if pose is not None and len(site.lights_m):
        lights = np.asarray(site.lights_m, float)
        pts = np.c_[lights, np.full(len(lights), site.ceiling_height_m)]
        for u, v in world_to_px(rig, *pose, pts):
            if np.isfinite(u) and np.isfinite(v):
                cv2.drawMarker(img, (int(round(u)), int(round(v))), SITE_BGR,
                               cv2.MARKER_CROSS, 14, 1, cv2.LINE_AA)
    cands, kept = d.get("candidates_px"), d.get("kept")
    if cands is not None:
        for i, (u, v) in enumerate(np.asarray(cands, float)):
            if kept is None or not kept[i]:
                cv2.circle(img, (int(round(u)), int(round(v))), 9, REJECTED_BGR, 1, cv2.LINE_AA)
    spots = d.get("spots_px")
    if spots is None:
        return
    spots = np.asarray(spots, float)
    for u, v in spots:
        cv2.circle(img, (int(round(u)), int(round(v))), 8, SPOT_BGR, 1, cv2.LINE_AA)
    pairs = d.get("pairs")
    for i_spot, light in (() if pairs is None else np.asarray(pairs, int)):
        u, v = spots[i_spot]
        p = (int(round(u)), int(round(v)))
        cv2.circle(img, p, 10, MATCHED_BGR, 2, cv2.LINE_AA)
        cv2.putText(img, str(int(light)), (p[0] + 12, p[1] - 8), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45, MATCHED_BGR, 1, cv2.LINE_AA)


def _draw_blocks(img: np.ndarray, d: Mapping[str, Any], rig: Rig, site: Site,
                 pose: tuple[float, float, float] | None) -> None:
    h = site.ceiling_height_m
    if pose is not None:
        quads = [b.corners_m for b in site.blocks]
        if site.markers is not None:
            quads += [m.corners_m() for m in site.markers.poses]
        for quad in quads:
            q = np.asarray(quad, float)
            pts = np.c_[np.r_[q, q[:1]], np.full(len(q) + 1, h)]
            _polyline(img, world_to_px(rig, *pose, pts), SITE_BGR)
    corners = d.get("corners_norm")
    if corners is None:
        return
    px = norm_to_px(rig, corners)
    cv2.polylines(img, [np.round(px).astype(np.int32)], True, MATCHED_BGR, 2, cv2.LINE_AA)
    for k, (u, v) in enumerate(px):
        cv2.circle(img, (int(round(u)), int(round(v))), 4, MATCHED_BGR, -1, cv2.LINE_AA)
        cv2.putText(img, str(k), (int(round(u)) + 6, int(round(v)) - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, MATCHED_BGR, 1, cv2.LINE_AA)
    src = d.get("source")
    if src is not None:
        u, v = np.nanmean(px, axis=0)
        cv2.putText(img, str(src), (int(u), int(v)), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    MATCHED_BGR, 1, cv2.LINE_AA)


def caption(est: Estimate, gated: bool = False) -> list[str]:
    """The text box's lines: method and time, then the pose and quality or the failure."""
    lines = [f"{est.method}  t={est.t_ns / 1e9:.3f} s"]
    if isinstance(est, PoseEstimate):
        x = "-" if est.x_m is None else f"{est.x_m:.3f}"
        y = "-" if est.y_m is None else f"{est.y_m:.3f}"
        lines.append(f"x={x} m  y={y} m  yaw={math.degrees(est.yaw_rad):.2f} deg")
        lines.append(f"quality {est.quality:.2f}" + ("  GATED by the tracker" if gated else ""))
    else:
        lines.append(f"FAILED: {est.reason}")
        if est.detail:
            lines.append(est.detail[:90])
    return lines


def _draw_text(img: np.ndarray, lines: list[str], failed: bool) -> None:
    scale, step = 0.5, 18
    width = max(cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] for t in lines)
    cv2.rectangle(img, (0, 0), (width + 12, step * len(lines) + 8), (0, 0, 0), -1)
    for k, t in enumerate(lines):
        colour = FAIL_BGR if failed and k > 0 else TEXT_BGR
        cv2.putText(img, t, (6, step * (k + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1,
                    cv2.LINE_AA)


def draw_overlay(image: np.ndarray, est: Estimate, rig: Rig, site: Site) -> np.ndarray:
    """A new BGR image: ``image`` with what ``est`` detected and matched, the site
    reprojected at its pose, and the pose, quality or failure reason as text.

    Args:
        image: ``(H, W)`` grey or ``(H, W, 3)`` BGR frame, uint8.
        est: the frame's estimate (a tracker's ``gated`` Failure shows the rejected one).
        rig, site: what the estimate was made with.

    Returns:
        ``(H, W, 3)`` uint8 BGR; ``image`` is not modified.
    """
    img = as_bgr(image)
    shown, gated = drawn_estimate(est)
    d = shown.diagnostics
    pose = _pose_of(shown)
    x_known = isinstance(shown, PoseEstimate) and shown.x_m is not None
    if "segments_n" in d or (site.corridor is not None and shown.method.endswith("corridor")):
        _draw_corridor(img, d, rig, site, pose, x_known)
    if "spots_px" in d or shown.method.endswith("lights"):
        _draw_lights(img, d, rig, site, pose)
    if "corners_norm" in d or shown.method == "block":
        _draw_blocks(img, d, rig, site, pose)
    _draw_text(img, caption(est if not gated else shown, gated), not est)
    return img


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of a BGR or grey image."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - only for images OpenCV cannot hold
        raise ValueError("the image cannot be encoded as PNG")
    return buf.tobytes()


def encode_jpeg(image: np.ndarray, quality: int = 80) -> bytes:
    """JPEG bytes of a BGR or grey image (the live view's frames)."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover
        raise ValueError("the image cannot be encoded as JPEG")
    return buf.tobytes()
