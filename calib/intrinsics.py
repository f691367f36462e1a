"""Camera intrinsics from views of a calibration board, with their uncertainty.

Pipeline: detect the board in every image (:func:`detect_images`, cached), or keep the
diverse frames of a live or recorded stream (:func:`capture_views`); solve
(:func:`calibrate_intrinsics`) with OpenCV (``calibrateCameraExtended`` for
``plumb_bob`` and ``rational_polynomial``, ``cv2.fisheye.calibrate`` for
``equidistant``), drop outlying views and corners and solve again; report.

Conventions:
    * pixels as SPEC §1 (origin at the centre of the top-left pixel);
    * **RMS** is the per-corner Euclidean RMS of the reprojection residuals, in pixels:
      ``sqrt(mean_i |p_i - proj_i|^2)`` over every kept corner of every kept view
      (the value ``cv2.calibrateCamera`` returns);
    * a **1 sigma** is the square root of the diagonal of ``s^2 (J^T J)^-1`` with
      ``s^2 = sum r^2 / (2 N - n_params)``: the spread the fit itself implies, which
      assumes independent corner noise and a model that fits;
    * the **odd/even cross-validation** solves the odd and the even views apart and
      compares their projections: for pixels on a grid inside the area reached by
      corners, the pixel of model A's ray through model B, in pixels.

Example::

    board = parse_board("chess:9x6", square_m=0.025)
    views = detect_images(sorted(Path("shots").glob("*.png")), board)
    result = calibrate_intrinsics(views, model="plumb_bob")
    print(result.report.text())
    save_camera(result.camera, "camera.yaml")
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, TextIO

import cv2
import numpy as np

from ceilkit.runtime.config.yaml import atomic_write_bytes
from ceilkit.runtime.errors import CalibrationError, CaptureError, ConfigError
from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry.camera import DISTORTION_MODELS, CameraModel
from ceilkit.runtime.io.capture import IMAGE_SUFFIXES, list_images
from ceilkit.runtime.io.images import read_image
from ceilkit.runtime.io.sources import FrameSource
from ceilkit.runtime.viz.plots import with_colour_scale

from .boards import Board, CharucoBoard, ChessBoard, Detection

RMS_CONVENTION = "per-corner Euclidean RMS of the reprojection residuals, px"
COVERAGE_GRID = (8, 6)          # cells across, down
MIN_CORNERS_PER_VIEW = 6
DROP_WARN_FRACTION = 0.03
EARLY_CHECK = 3                 # images missed in a row before a wrong board size is sought
_COEFF_NAMES = {
    "plumb_bob": ("k1", "k2", "p1", "p2", "k3"),
    "rational_polynomial": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "equidistant": ("k1", "k2", "k3", "k4"),
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


# -- results ----------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class IntrinsicsReport:
    """How good a calibration is.

    Attributes:
        model: the distortion model.
        image_size: ``(width, height)`` px.
        rms_px: reprojection RMS (:data:`RMS_CONVENTION`) over kept corners.
        n_views, n_corners: kept views and corners.
        view_names, view_rms_px: every kept view and its own RMS, px.
        param_names, params, sigmas: ``fx fy cx cy`` (px) then the distortion
            coefficients, their values and 1 sigma.
        dropped_views: names of views rejected as outliers.
        dropped_corners: corners rejected inside kept views.
        dropped_fraction: share of all detected corners rejected (views and corners).
        coverage: share of the :data:`COVERAGE_GRID` image cells holding a kept corner.
        empty_cells: ``(col, row)`` of the cells no corner reached.
        cross_max_px, cross_rms_px: odd/even cross-validation (None with too few views).
        warnings: sentences for the user.
    """

    model: str
    image_size: tuple[int, int]
    rms_px: float
    n_views: int
    n_corners: int
    view_names: tuple[str, ...]
    view_rms_px: tuple[float, ...]
    param_names: tuple[str, ...]
    params: tuple[float, ...]
    sigmas: tuple[float, ...]
    dropped_views: tuple[str, ...]
    dropped_corners: int
    dropped_fraction: float
    coverage: float
    empty_cells: tuple[tuple[int, int], ...]
    cross_max_px: float | None
    cross_rms_px: float | None
    warnings: tuple[str, ...] = ()

    def sigma(self, name: str) -> float:
        """1 sigma of parameter ``name`` (``fx``, ``cx``, ``k1``, ...)."""
        return self.sigmas[self.param_names.index(name)]

    def worst_views(self, n: int = 3) -> list[tuple[str, float]]:
        """The ``n`` kept views with the largest RMS, worst first."""
        order = np.argsort(self.view_rms_px)[::-1][:n]
        return [(self.view_names[i], self.view_rms_px[i]) for i in order]

    def summary_lines(self) -> list[str]:
        """A few lines for a file header: RMS, dropped, 1 sigma."""
        sig = ", ".join(f"{n}={v:.6g}+-{s:.2g}" for n, v, s in
                        zip(self.param_names, self.params, self.sigmas, strict=False))
        lines = [f"model {self.model}; {self.n_views} views, {self.n_corners} corners",
                 f"RMS {self.rms_px:.4f} px ({RMS_CONVENTION})",
                 f"dropped {len(self.dropped_views)} views, {self.dropped_corners} corners "
                 f"({100 * self.dropped_fraction:.1f}% of corners)",
                 f"1 sigma: {sig}",
                 f"coverage {100 * self.coverage:.0f}% of {COVERAGE_GRID[0]}x"
                 f"{COVERAGE_GRID[1]} image cells"]
        if self.cross_max_px is not None:
            lines.append(f"odd/even cross-validation: max {self.cross_max_px:.3f} px, "
                         f"RMS {self.cross_rms_px:.3f} px")
        return lines

    def text(self) -> str:
        """A human-readable report."""
        w, h = self.image_size
        out = [f"intrinsics: {self.model}, {w}x{h} px, {self.n_views} views, "
               f"{self.n_corners} corners",
               f"RMS reprojection error: {self.rms_px:.4f} px ({RMS_CONVENTION})",
               "parameters (value +- 1 sigma):"]
        for n, v, s in zip(self.param_names, self.params, self.sigmas, strict=False):
            out.append(f"  {n:>3} = {v:14.6f} +- {s:.6f}")
        out.append("worst views (RMS px): " + ", ".join(
            f"{n} {e:.3f}" for n, e in self.worst_views(3)))
        if self.dropped_views or self.dropped_corners:
            out.append(f"dropped as outliers: {len(self.dropped_views)} views "
                       f"({', '.join(self.dropped_views) or '-'}), {self.dropped_corners} "
                       f"corners: {100 * self.dropped_fraction:.1f}% of corners")
        else:
            out.append("dropped as outliers: none")
        out.append(f"coverage: {100 * self.coverage:.0f}% of {COVERAGE_GRID[0]}x"
                   f"{COVERAGE_GRID[1]} image cells hold a corner")
        if self.cross_max_px is None:
            out.append("odd/even cross-validation: not run (too few views)")
        else:
            out.append(f"odd/even cross-validation (odd vs even views, inside the area "
                       f"reached by corners): max {self.cross_max_px:.3f} px, RMS "
                       f"{self.cross_rms_px:.3f} px")
        out += [f"warning: {m}" for m in self.warnings]
        return "\n".join(out)


@dataclass(frozen=True, eq=False)
class IntrinsicsResult:
    """A calibrated camera with its report and the views it rests on.

    Attributes:
        camera: the calibrated model.
        report: see :class:`IntrinsicsReport`.
        views: kept detections (outlying corners removed).
        rvecs, tvecs: ``(V, 3)`` board poses ``X_cam = R(rvec) X_board + t`` (m).
        residuals_px: per kept view, ``(N_i, 2)`` detected minus projected pixels.
        dropped: the rejected detections, whole.
    """

    camera: CameraModel
    report: IntrinsicsReport
    views: tuple[Detection, ...]
    rvecs: np.ndarray
    tvecs: np.ndarray
    residuals_px: tuple[np.ndarray, ...]
    dropped: tuple[Detection, ...] = field(default=())


# -- solving ----------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Solution:
    camera: CameraModel
    rvecs: np.ndarray
    tvecs: np.ndarray
    residuals: list[np.ndarray]
    sigmas: np.ndarray           # fx fy cx cy + coefficients


def _project(camera: CameraModel, obj: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
             ) -> np.ndarray:
    if camera.model == "equidistant":
        px, _ = cv2.fisheye.projectPoints(obj.reshape(-1, 1, 3), rvec.reshape(3, 1),
                                          tvec.reshape(3, 1), camera.K, camera.dist)
    else:
        px, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
    return px.reshape(-1, 2)


def _fisheye_sigmas(camera: CameraModel, views: Sequence[Detection], rvecs: np.ndarray,
                    tvecs: np.ndarray, residuals: list[np.ndarray]) -> np.ndarray:
    """1 sigma of fx fy cx cy k1..k4 from the full Jacobian (intrinsics + every pose)."""
    n_int, V = 8, len(views)
    rows = sum(2 * len(v) for v in views)
    J = np.zeros((rows, n_int + 6 * V))
    r0 = 0
    for i, v in enumerate(views):
        _, jac = cv2.fisheye.projectPoints(v.points_board.reshape(-1, 1, 3),
                                           rvecs[i].reshape(3, 1), tvecs[i].reshape(3, 1),
                                           camera.K, camera.dist, alpha=0.0)
        jac = np.asarray(jac).reshape(2 * len(v), -1)
        J[r0:r0 + jac.shape[0], :n_int] = jac[:, :8]
        J[r0:r0 + jac.shape[0], n_int + 6 * i:n_int + 6 * i + 6] = jac[:, 8:14]
        r0 += jac.shape[0]
    dof = max(rows - J.shape[1], 1)
    s2 = float(sum(np.sum(r ** 2) for r in residuals)) / dof
    cov = np.linalg.pinv(J.T @ J) * s2
    return np.sqrt(np.clip(np.diag(cov)[:n_int], 0.0, None))


def _solve(views: Sequence[Detection], image_size: tuple[int, int], model: str,
           fix_aspect_ratio: bool, name: str) -> _Solution:
    w, h = image_size
    obj = [v.points_board.astype(np.float32) for v in views]
    img = [v.points_px.astype(np.float32) for v in views]
    try:
        if model == "equidistant":
            flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
            _, K, D, rv, tv = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3).astype(np.float64) for o in obj],
                [i.reshape(1, -1, 2).astype(np.float64) for i in img],
                (w, h), None, None, flags=flags, criteria=_CRITERIA)
            if fix_aspect_ratio:
                raise ConfigError(None, "fix_aspect_ratio",
                                  "not available with the equidistant model")
            std = None
        else:
            flags = cv2.CALIB_RATIONAL_MODEL if model == "rational_polynomial" else 0
            K0 = None
            if fix_aspect_ratio:
                flags |= cv2.CALIB_FIX_ASPECT_RATIO
                K0 = np.eye(3)
            _, K, D, rv, tv, std, _, _ = cv2.calibrateCameraExtended(
                obj, img, (w, h), K0, None, flags=flags, criteria=_CRITERIA)
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
        raise CalibrationError(f"the {model} solve failed on {len(views)} views: {msg}"
                               ) from None
    n_coef = len(_COEFF_NAMES[model])
    D = np.asarray(D, np.float64).ravel()[:n_coef]
    camera = CameraModel(w, h, np.asarray(K, np.float64), D, model, name)
    rvecs = np.array([np.asarray(r, np.float64).ravel() for r in rv]).reshape(-1, 3)
    tvecs = np.array([np.asarray(t, np.float64).ravel() for t in tv]).reshape(-1, 3)
    residuals = [v.points_px - _project(camera, v.points_board, rvecs[i], tvecs[i])
                 for i, v in enumerate(views)]
    if std is None:
        sig = _fisheye_sigmas(camera, views, rvecs, tvecs, residuals)
    else:
        std = np.asarray(std, np.float64).ravel()
        sig = np.concatenate([std[:4], std[4:4 + n_coef]])
        if fix_aspect_ratio:           # OpenCV solves fy and derives fx = fy * ratio
            sig[0] = sig[1] * camera.fx / camera.fy
    if not np.all(np.isfinite(camera.K)) or not np.all(np.isfinite(D)):
        raise CalibrationError(f"the {model} solve diverged on {len(views)} views")
    return _Solution(camera, rvecs, tvecs, residuals, sig)


def _rms(residuals: Iterable[np.ndarray]) -> float:
    r = np.concatenate([np.asarray(x).reshape(-1, 2) for x in residuals])
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if r.size else float("nan")


def _coverage(views: Sequence[Detection], image_size: tuple[int, int]
              ) -> tuple[np.ndarray, float]:
    """``(rows, cols)`` bool grid of cells reached by a corner, and its filled share."""
    gx, gy = COVERAGE_GRID
    w, h = image_size
    grid = np.zeros((gy, gx), dtype=bool)
    for v in views:
        c = np.clip(((v.points_px[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
        r = np.clip(((v.points_px[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
        grid[r, c] = True
    return grid, float(grid.mean())


def _cross_validate(views: Sequence[Detection], image_size: tuple[int, int], model: str,
                    fix_aspect_ratio: bool, grid: np.ndarray, min_half: int
                    ) -> tuple[float | None, float | None]:
    odd, even = list(views[1::2]), list(views[0::2])
    if min(len(odd), len(even)) < min_half:
        return None, None
    try:
        a = _solve(odd, image_size, model, fix_aspect_ratio, "odd").camera
        b = _solve(even, image_size, model, fix_aspect_ratio, "even").camera
    except CalibrationError:
        return None, None
    w, h = image_size
    gx, gy = COVERAGE_GRID
    u, v = np.meshgrid(np.linspace(0, w - 1, 4 * gx), np.linspace(0, h - 1, 4 * gy))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    c = np.clip(((px[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
    r = np.clip(((px[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
    px = px[grid[r, c]]
    if px.shape[0] == 0:
        return None, None
    d = np.linalg.norm(b.distort(a.unproject(px)) - px, axis=1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return None, None
    return float(d.max()), float(np.sqrt(np.mean(d ** 2)))


def check_model(model: str) -> None:
    """Raise ``ConfigError`` (key ``model``) unless ``model`` is a distortion model."""
    if model not in DISTORTION_MODELS:
        raise ConfigError(None, "model", f"expected one of {', '.join(DISTORTION_MODELS)}, "
                          f"found {model!r}")


NEAR_SAME_PX = 2.0
"""Two views whose common corners lie within this RMS (px) of each other are one view."""
MIN_TILT_DEG = 10.0
"""A view is tilted when its board normal is this far (deg) off the optical axis."""
MIN_TILT_AXES_DEG = 30.0
"""The tilted views' tilt axes must span at least this (deg, modulo 180): tilts about
one axis alone leave the focal length across that axis to the distortion."""


def check_view_variety(views: Sequence[Detection], min_views: int) -> None:
    """Refuse a view set the solve cannot separate: copies of one view (corners within
    :data:`NEAR_SAME_PX`), fewer than ``min_views`` distinct views, or too little tilt
    variety (fewer than two views tilted :data:`MIN_TILT_DEG` or more, or all tilted
    about one axis). The message says what views to add.

    Raises:
        CalibrationError: the view set is degenerate.
    """
    distinct: list[Detection] = []
    copies: list[tuple[str, str]] = []
    for v in views:
        for d in distinct:
            common, iv, idd = np.intersect1d(v.ids, d.ids, return_indices=True)
            if common.size < 0.5 * min(len(v), len(d)):
                continue
            diff = v.points_px[iv] - d.points_px[idd]
            if float(np.sqrt(np.mean(np.sum(diff * diff, axis=1)))) < NEAR_SAME_PX:
                copies.append((v.name, d.name))
                break
        else:
            distinct.append(v)
    add = ("add views with the board moved across the whole image, nearer and farther, "
           "and tilted 20-45 deg towards the left, right, top and bottom")
    if len(distinct) < min_views:
        eg = ", ".join(f"{a} = {b}" for a, b in copies[:3])
        raise CalibrationError(
            f"only {len(distinct)} distinct views among {len(views)} (need {min_views}): "
            f"{len(copies)} are copies of another view, their corners within "
            f"{NEAR_SAME_PX:g} px ({eg}); {add}")
    shapes = [view_shape(d) for d in distinct]
    tilted = [s for s in shapes if s.tilt_deg >= MIN_TILT_DEG]
    if len(tilted) < 2:
        raise CalibrationError(
            f"too little tilt variety: {len(tilted)} of {len(distinct)} distinct views "
            f"have the board tilted {MIN_TILT_DEG:g} deg or more (need 2, about different "
            f"axes); the focal length cannot be told from the distance; {add}")
    dirs = np.radians([s.tilt_dir_deg for s in tilted]) * 2.0   # axes: modulo 180 deg
    spread = max(float(np.degrees(abs(math.remainder(a - b, 2 * math.pi)))) / 2.0
                 for a in dirs for b in dirs)
    if spread < MIN_TILT_AXES_DEG:
        raise CalibrationError(
            f"too little tilt variety: every tilted view turns the board about one axis "
            f"(within {spread:.0f} deg; need {MIN_TILT_AXES_DEG:g}); the focal length across "
            f"it is not determined; add views tilted towards the top and bottom as well as "
            f"left and right")


def calibrate_intrinsics(views: Sequence[Detection], model: str = "plumb_bob", *,
                         fix_aspect_ratio: bool = False, min_views: int = 5,
                         corner_k: float = 5.0, view_k: float = 3.0,
                         reject_outliers: bool = True, name: str = "camera"
                         ) -> IntrinsicsResult:
    """Solve the intrinsics from board detections, rejecting outliers.

    Args:
        views: detections (one per image, all of one image size).
        model: ``plumb_bob``, ``rational_polynomial`` or ``equidistant``.
        fix_aspect_ratio: solve one focal length (fx = fy), as OpenCV's
            ``CALIB_FIX_ASPECT_RATIO``.
        min_views: fewer kept views than this is a CalibrationError.
        corner_k: a corner whose residual exceeds ``corner_k`` robust sigmas (from the
            median residual, and at least 0.5 px) is dropped.
        view_k: a view whose median corner residual exceeds ``view_k`` times the median
            over views (and 0.4 px, and that median plus 6 MADs) is dropped, the worst
            one per round.
        reject_outliers: False keeps every detection.
        name: ``camera_name`` of the result.

    Returns:
        :class:`IntrinsicsResult`; its report warns when over 3% of the corners were
        dropped, when image cells were never reached, and when the cross-validation
        disagrees by over 1 px.

    Raises:
        ConfigError: unknown model, or views of different image sizes.
        CalibrationError: too few views, a degenerate view set
            (:func:`check_view_variety`), or a solve that fails.
    """
    check_model(model)
    usable = _usable_views(views, min_views)
    image_size = usable[0].image_size
    original = {v.name: v for v in usable}
    kept, dropped_views, sol = _reject_outliers(
        usable, original, _Solve(image_size, model, fix_aspect_ratio, name, min_views),
        corner_k, view_k, 50 if reject_outliers else 0)
    grid, coverage = _coverage(kept, image_size)
    cross_max, cross_rms = _cross_validate(kept, image_size, model, fix_aspect_ratio, grid,
                                           max(3, min_views // 2))
    n_kept = sum(len(v) for v in kept)
    frac = 1.0 - n_kept / sum(len(v) for v in usable)
    empty = tuple((int(c), int(r)) for r, c in zip(*np.nonzero(~grid), strict=False))
    cam = sol.camera
    names = ("fx", "fy", "cx", "cy") + _COEFF_NAMES[model]
    params = (cam.fx, cam.fy, cam.cx, cam.cy) + tuple(float(d) for d in cam.dist)
    report = IntrinsicsReport(
        model=model, image_size=image_size, rms_px=_rms(sol.residuals), n_views=len(kept),
        n_corners=n_kept, view_names=tuple(v.name for v in kept),
        view_rms_px=tuple(_rms([r]) for r in sol.residuals), param_names=names,
        params=tuple(float(p) for p in params), sigmas=tuple(float(s) for s in sol.sigmas),
        dropped_views=tuple(v.name for v in dropped_views),
        dropped_corners=sum(len(original[v.name]) - len(v) for v in kept),
        dropped_fraction=float(frac), coverage=coverage, empty_cells=empty,
        cross_max_px=cross_max, cross_rms_px=cross_rms,
        warnings=_solve_warnings(frac, empty, grid.size, cross_max))
    return IntrinsicsResult(cam, report, tuple(kept), sol.rvecs, sol.tvecs,
                            tuple(sol.residuals), tuple(dropped_views))


class _Solve(NamedTuple):
    """What every solve of one calibration shares."""

    image_size: tuple[int, int]
    model: str
    fix_aspect_ratio: bool
    name: str
    min_views: int

    def __call__(self, kept: list[Detection]):
        return _solve(kept, self.image_size, self.model, self.fix_aspect_ratio, self.name)


def _usable_views(views: Sequence[Detection | None], min_views: int) -> list[Detection]:
    """The detections with enough corners, all of one image size, uniquely named and
    varied enough to solve (:func:`check_view_variety`)."""
    views = [v for v in views if v is not None]
    sizes = {v.image_size for v in views}
    if len(sizes) > 1:
        first = views[0]
        other = next(v for v in views if v.image_size != first.image_size)
        raise ConfigError(other.name, None, f"image is {other.image_size[0]}x"
                          f"{other.image_size[1]} but {first.name} is {first.image_size[0]}x"
                          f"{first.image_size[1]}: mixed image sizes (one camera, one "
                          f"resolution per calibration)")
    usable = [v for v in views if len(v) >= MIN_CORNERS_PER_VIEW]
    if len(usable) < min_views:
        raise CalibrationError(f"too few views: the board was found in {len(usable)} "
                               f"image(s) with at least {MIN_CORNERS_PER_VIEW} corners, need "
                               f"at least {min_views}")
    check_view_variety(usable, min_views)
    if len({v.name for v in usable}) != len(usable):
        raise ConfigError(None, None, "two views share a name: view names must be unique")
    return usable


def _reject_outliers(usable: list[Detection], original: dict[str, Detection],
                     solve: _Solve, corner_k: float, view_k: float, rounds: int):
    """Solve, then drop the worst view or the outlying corners and solve again, until
    nothing is dropped (at most ``rounds`` times). Returns the kept views, the dropped
    ones and the last solution."""
    kept = list(usable)
    dropped_views: list[Detection] = []
    sol = solve(kept)
    for _ in range(rounds):
        # a view's score is its median corner residual: one bad corner does not sink it
        score = np.array([float(np.median(np.linalg.norm(r, axis=1))) for r in sol.residuals])
        med = float(np.median(score))
        mad = float(np.median(np.abs(score - med)))
        worst = int(np.argmax(score))
        limit_view = max(view_k * med, med + 6 * 1.4826 * mad, 0.4)
        if score[worst] > limit_view and len(kept) > solve.min_views:
            dropped_views.append(original[kept.pop(worst).name])
            sol = solve(kept)
            continue
        norms = [np.linalg.norm(r, axis=1) for r in sol.residuals]
        sigma = float(np.median(np.concatenate(norms))) / 1.1774
        limit = max(corner_k * sigma, 0.5)
        if all(bool((n <= limit).all()) for n in norms):
            break
        trimmed = [v.subset(n <= limit) for v, n in zip(kept, norms, strict=False)]
        kept = [v for v in trimmed if len(v) >= MIN_CORNERS_PER_VIEW]
        dropped_views += [original[v.name] for v in trimmed if len(v) < MIN_CORNERS_PER_VIEW]
        if len(kept) < solve.min_views:
            raise CalibrationError(f"too few views left after outlier rejection: {len(kept)}, "
                                   f"need at least {solve.min_views}")
        sol = solve(kept)
    return kept, dropped_views, sol


def _solve_warnings(frac: float, empty: tuple, n_cells: int,
                    cross_max: float | None) -> tuple[str, ...]:
    """The report's warnings: many corners dropped, image cells never reached, the odd
    and even views disagreeing."""
    warnings = []
    if frac > DROP_WARN_FRACTION:
        warnings.append(f"{100 * frac:.1f}% of the corners were dropped as outliers (over "
                        f"{100 * DROP_WARN_FRACTION:.0f}%): check the board is flat and the "
                        f"images sharp")
    if empty:
        warnings.append(f"{len(empty)} of {n_cells} image cells were never reached by a "
                        f"corner: the lens there is extrapolated; add views with the board "
                        f"near the edges and corners")
    if cross_max is not None and cross_max > 1.0:
        warnings.append(f"the odd and even views disagree by up to {cross_max:.2f} px: "
                        f"more, and more varied, views are needed")
    return tuple(warnings)


# -- images and the detection cache -------------------------------------------------------

def image_files(folder: str | Path) -> list[Path]:
    """The images in ``folder`` (by suffix, sorted by name); ConfigError if none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(folder, None, "not a folder of images")
    files = list_images(folder)
    if not files:
        raise ConfigError(folder, None, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return files


def read_grey(path: str | Path) -> np.ndarray:
    """An image file as 8-bit grey; a ConfigError naming the file if it cannot be read."""
    img, damage = read_image(path)  # a truncated JPEG is refused, not half grey
    if img is None:
        raise ConfigError(None, None, damage)
    return to_grey(img)


def _board_key(board: Board) -> str:
    extra = (f":{board.marker_m:g}" if isinstance(board, CharucoBoard)
             else f":{getattr(board, 'detector', '')}:w{getattr(board, 'subpix_half', None)}")
    return f"{board.spec}:{board.square_m:g}{extra}:m{getattr(board, 'working_mpx', 0):g}"


def _file_key(path: Path, board: Board) -> str:
    st = path.stat()
    return f"{path.name}|{st.st_size}|{st.st_mtime_ns}|{_board_key(board)}"


class DetectionCache:
    """Detections kept in an ``.npz`` file, keyed by file name, size, mtime and board.

    A re-solve (another model, other thresholds) then does not detect again. A missing
    or unreadable cache is simply empty; saving is atomic.
    """

    def __init__(self, path: str | Path | None):
        self.path = None if path is None else Path(path)
        self.entries: dict[str, Detection | None] = {}
        self.hits = 0
        if self.path is not None and self.path.is_file():
            try:
                self._load()
            except (OSError, ValueError, KeyError):
                self.entries = {}

    def _load(self) -> None:
        with np.load(self.path, allow_pickle=False) as z:
            keys, sizes, off = z["keys"], z["sizes"], z["offsets"]
            found, ids, px, obj = z["found"], z["ids"], z["px"], z["obj"]
        for i, k in enumerate(keys):
            if not found[i]:
                self.entries[str(k)] = None
                continue
            a, b = off[i], off[i + 1]
            name = str(k).split("|", 1)[0]
            self.entries[str(k)] = Detection(name, tuple(sizes[i]), ids[a:b], px[a:b],
                                             obj[a:b])

    def get(self, key: str) -> tuple[bool, Detection | None]:
        if key in self.entries:
            self.hits += 1
            return True, self.entries[key]
        return False, None

    def put(self, key: str, det: Detection | None) -> None:
        self.entries[key] = det

    def save(self) -> None:
        if self.path is None:
            return
        keys = list(self.entries)
        dets = [self.entries[k] for k in keys]
        off = np.cumsum([0] + [0 if d is None else len(d) for d in dets])
        cat = [d for d in dets if d is not None]
        arrays = {
            "keys": np.array(keys, dtype=str),
            "found": np.array([d is not None for d in dets], dtype=bool),
            "sizes": np.array([d.image_size if d is not None else (0, 0) for d in dets],
                              dtype=np.int64).reshape(-1, 2),
            "offsets": off.astype(np.int64),
            "ids": np.concatenate([d.ids for d in cat]) if cat else np.zeros(0, np.int32),
            "px": np.concatenate([d.points_px for d in cat]) if cat else np.zeros((0, 2)),
            "obj": np.concatenate([d.points_board for d in cat]) if cat else np.zeros((0, 3)),
        }
        import io
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        try:
            atomic_write_bytes(self.path, buf.getvalue())
        except ConfigError:
            pass                 # a cache that cannot be written is no error


def _board_size_text(board: Board) -> str:
    if isinstance(board, ChessBoard):
        return f"{board.cols}x{board.rows}"
    return board.spec


def _classic(boards: Sequence[Board]) -> list[Board]:
    """The chessboards among ``boards`` with the classic detector (others unchanged)."""
    return [ChessBoard(b.cols, b.rows, b.square_m, b.margin_squares, "classic",
                       b.subpix_half, b.working_mpx) if isinstance(b, ChessBoard) else b
            for b in boards]


def _no_board_error(board: Board, samples: Sequence[tuple[str, np.ndarray]], n: int
                    ) -> CalibrationError | ConfigError:
    """The error for 'no board in any image': a ``ConfigError`` keyed ``board`` with a
    did-you-mean when a board of another size is found, else a ``CalibrationError``."""
    for name, img in samples:
        # the classic detector first: it fails several times faster than the sb one
        found = [(len(d), alt) for alt in _classic(board.alternatives())
                 if (d := alt.detect(img, name)) is not None]
        if not found and any(isinstance(a, ChessBoard) and a.detector != "classic"
                             for a in board.alternatives()) and name == samples[0][0]:
            found = [(len(d), alt) for alt in board.alternatives()
                     if (d := alt.detect(img, name)) is not None]
        if found:                      # the largest board seen: a sub-board also matches
            alt = max(found, key=lambda f: f[0])[1]
            return ConfigError(
                None, "board", f"no {board.spec} board found in any of {n} image(s); "
                f"found a {_board_size_text(alt)} board in {name}: did you mean "
                f"{alt.spec}?" + (" (chessboards count inner corners)"
                                  if isinstance(board, ChessBoard) else ""))
    if isinstance(board, CharucoBoard) and any(board.markers_found(img) >= 2
                                               for _, img in samples):
        return CalibrationError(
            f"no {board.spec} board found in any of {n} image(s), but DICT_"
            f"{board.dictionary} markers were: check the squares count, the marker size "
            f"and the legacy layout")
    return CalibrationError(f"no {board.spec} board found in any of {n} image(s)")


def _reworded(err: CalibrationError | ConfigError, old: str, new: str
              ) -> CalibrationError | ConfigError:
    """``err`` of the same kind (and key) with ``old`` replaced by ``new`` in its text."""
    if isinstance(err, ConfigError):
        return ConfigError(err.path, err.key, err.detail.replace(old, new))
    return CalibrationError(str(err).replace(old, new))


def _check_whole_board(board: ChessBoard, found: Sequence[Detection],
                       files: dict[str, Path], n_check: int = 3) -> None:
    """Raise when the detected grids have further corners beyond them (a size that
    matches part of the board): checked on up to ``n_check`` views spread over
    ``found``; the likely size is the one most views agree on."""
    idx = np.unique(np.linspace(0, len(found) - 1, min(n_check, len(found))).round()
                    ).astype(int)
    sizes = []
    for i in idx:
        det = found[i]
        path = files.get(det.name)
        if path is None or not path.exists():
            continue
        left, right, top, bottom = board.grid_extends(read_grey(path), det)
        sizes.append((board.cols + left + right, board.rows + top + bottom, det.name))
    bigger = [sz for sz in sizes if sz[:2] != (board.cols, board.rows)]
    if not sizes or 2 * len(bigger) <= len(sizes):
        return
    # views may cut the board: the sizes from the largest extension seen up to two
    # more each way are tried, largest first, on the views (the classic detector fails
    # fast); the largest one found wins, else the largest extension seen
    c0 = max(c for c, _, _ in bigger)
    r0 = max(r for _, r, _ in bigger)
    best = (c0, r0)
    cands = sorted(((c, r) for c in range(board.cols, c0 + 3) for r in range(board.rows, r0 + 3)
                    if (c, r) != (board.cols, board.rows)), key=lambda cr: -cr[0] * cr[1])
    # probed on the views that showed the extension (a failed probe costs 0.2-0.5 s)
    greys = [read_grey(files[n]) for *_, n in bigger if n in files]
    for c, r in cands:
        probe = ChessBoard(c, r, board.square_m, detector="classic")
        if any(probe.detect(g) is not None for g in greys):
            best = (c, r)
            break
    names = ", ".join(n for *_, n in bigger)
    raise ConfigError(None, "board", f"chess:{board.cols}x{board.rows} matches only "
                      f"part of the board: further corners lie beyond the detected grid in "
                      f"{names}; did you mean chess:{best[0]}x{best[1]}? "
                      f"(chessboards count inner corners)")


def detect_images(paths: Sequence[str | Path], board: Board,
                  cache: DetectionCache | str | Path | None = None,
                  progress: Callable[[int, int, str, bool], None] | None = None
                  ) -> list[Detection]:
    """Detect ``board`` in every image file.

    Args:
        paths: image files (all of one size).
        board: the board.
        cache: a :class:`DetectionCache`, or its ``.npz`` path, or None.
        progress: called as ``progress(i, n, name, found)`` after each image.

    Returns:
        The detections, in ``paths`` order, images without a board left out.

    Raises:
        ConfigError: an image that cannot be read (named), mixed image sizes, or a
            chessboard size that matches only part of the board, or a board of another
            size found instead (key ``board``, with a did-you-mean).
        CalibrationError: no board in any image.
    """
    if not isinstance(cache, DetectionCache):
        cache = DetectionCache(cache)
    out: list[Detection] = []
    size: tuple[int, int] | None = None
    first = ""
    dirty = False
    for i, p in enumerate(paths):
        p = Path(p)
        key = _file_key(p, board) if p.exists() else ""
        hit, det = cache.get(key) if key else (False, None)
        if hit:
            im_size = det.image_size if det is not None else None
        else:
            grey = read_grey(p)
            im_size = (grey.shape[1], grey.shape[0])
            det = board.detect(grey, p.name)
            cache.put(key, det)
            dirty = True
        if im_size is None and hit:          # cached miss: size still needed for checks
            grey = read_grey(p)
            im_size = (grey.shape[1], grey.shape[0])
        if size is None:
            size, first = im_size, p.name
        elif im_size != size:
            raise ConfigError(p, None, f"image is {im_size[0]}x{im_size[1]} but {first} is "
                              f"{size[0]}x{size[1]}: mixed image sizes (one camera, one "
                              f"resolution per calibration)")
        if det is not None:
            out.append(det)
        if progress is not None:
            progress(i, len(paths), p.name, det is not None)
        if i + 1 == EARLY_CHECK and not out and len(paths) > EARLY_CHECK:
            # the first images all missed: a wrong size says so now, not after all of them
            samples = [(Path(q).name, read_grey(q)) for q in paths[:EARLY_CHECK]]
            err = _no_board_error(board, samples, EARLY_CHECK)
            if isinstance(err, ConfigError):  # a did-you-mean
                if dirty:
                    cache.save()
                raise _reworded(err, f"any of {EARLY_CHECK} image(s)",
                                f"the first {EARLY_CHECK} of {len(paths)} images")
    if dirty:
        cache.save()
    if isinstance(board, ChessBoard) and out:
        _check_whole_board(board, out, {Path(p).name: Path(p) for p in paths})
    if len(out) < max(1, len(paths) // 2):
        # the board was missed in most images: a wrong size is the usual reason (a
        # sub-board of the real one can still be found in a few images)
        found = {d.name for d in out}
        samples = [(Path(p).name, read_grey(p)) for p in paths
                   if Path(p).name not in found][:3]
        err = _no_board_error(board, samples, len(paths))
        if not out or isinstance(err, ConfigError):
            if out:
                err = _reworded(err, "found in any of", "found in most of")
            raise err
    return out


# -- live and recorded streams ------------------------------------------------------------

@dataclass(frozen=True)
class StopRule:
    """When live capture has enough.

    Capture stops once there are ``min_views`` views, ``coverage`` of the image cells
    are reached, at least two board sizes and three tilts are seen, and a trial solve
    gives ``sigma(fx) / fx <= rel_focal_sigma`` and ``sigma(cx), sigma(cy) <=
    pp_sigma_px``; or at ``max_views``; or when the source ends.
    """

    min_views: int = 12
    max_views: int = 40
    coverage: float = 0.7
    rel_focal_sigma: float = 0.004
    pp_sigma_px: float = 2.0
    min_distance: float = 0.12


@dataclass(frozen=True)
class ViewShape:
    """Where a board sits in a view: centre ``(x, y)`` in [0, 1] of the image, size
    (square root of the hull area over the image area), tilt (deg) of the board normal
    from the optical axis and its direction ``tilt_dir_deg`` (from a rough pinhole)."""

    x: float
    y: float
    size: float
    tilt_deg: float
    tilt_dir_deg: float

    def vector(self) -> np.ndarray:
        a = np.radians(self.tilt_dir_deg)
        t = self.tilt_deg / 60.0
        return np.array([self.x, self.y, 1.5 * self.size, t * np.cos(a), t * np.sin(a)])


def view_shape(det: Detection) -> ViewShape:
    """The :class:`ViewShape` of a detection."""
    w, h = det.image_size
    c = det.points_px.mean(axis=0)
    hull = cv2.convexHull(det.points_px.astype(np.float32))
    size = float(np.sqrt(max(cv2.contourArea(hull), 0.0) / (w * h)))
    f = 0.9 * max(w, h)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    tilt, tdir = 0.0, 0.0
    ok, rvec, _ = cv2.solvePnP(det.points_board, det.points_px, K, None,
                               flags=cv2.SOLVEPNP_IPPE)
    if ok:
        R, _ = cv2.Rodrigues(rvec)
        n = R[:, 2]
        tilt = float(np.degrees(np.arccos(min(1.0, abs(n[2])))))
        tdir = float(np.degrees(np.arctan2(n[1], n[0]) * np.sign(n[2] or 1.0)))
    return ViewShape(float(c[0] / w), float(c[1] / h), size, tilt, tdir)


class CoverageMeter:
    """Progress of a capture: position (image cells), size and tilt bins; drawn as text."""

    SIZE_BINS = (0.0, 0.3, 0.5)
    TILT_BINS = 5   # flat (< 12 deg), then tilted >= 12 deg towards each quadrant

    def __init__(self, image_size: tuple[int, int]):
        self.image_size = image_size
        self.grid = np.zeros((COVERAGE_GRID[1], COVERAGE_GRID[0]), dtype=bool)
        self.sizes: set[int] = set()
        self.tilts: set[int] = set()

    def add(self, det: Detection, shape: ViewShape) -> None:
        g, _ = _coverage([det], self.image_size)
        self.grid |= g
        self.sizes.add(int(np.searchsorted(self.SIZE_BINS, shape.size, side="right")) - 1)
        if shape.tilt_deg < 12:
            self.tilts.add(0)
        else:
            self.tilts.add(1 + int(((shape.tilt_dir_deg + 45) % 360) // 90))

    @property
    def position(self) -> float:
        return float(self.grid.mean())

    def line(self, n_views: int, focal_rel_sigma: float | None) -> str:
        def bar(frac: float, width: int = 12) -> str:
            k = int(round(max(0.0, min(1.0, frac)) * width))
            return "[" + "#" * k + "." * (width - k) + "]"
        acc = "-" if focal_rel_sigma is None else f"{100 * focal_rel_sigma:.2f}%"
        return (f"position {bar(self.position)} {100 * self.position:3.0f}%  "
                f"size {bar(len(self.sizes) / 3, 3)}  "
                f"tilt {bar(len(self.tilts) / self.TILT_BINS, 5)}  "
                f"views {n_views:3d}  fx 1-sigma {acc}")


def capture_views(source: FrameSource, board: Board, model: str = "plumb_bob",
                  stop: StopRule | None = None, every: int = 1,
                  meter: TextIO | None = sys.stderr) -> list[Detection]:
    """Keep the frames of ``source`` that add diversity, until coverage and accuracy suffice.

    A frame is kept when its board is found and its :class:`ViewShape` differs from
    every kept one by at least ``stop.min_distance``. A coverage meter (position, size,
    tilt, views, fx 1 sigma) is redrawn on ``meter`` (stderr; None for quiet).

    Args:
        source: any frame source (camera, video file, ListSource).
        board: the board.
        model: the model for the trial solves that judge accuracy.
        stop: when to stop (:class:`StopRule`).
        every: look at one frame in ``every``.
        meter: a text stream for the meter, or None.

    Returns:
        The kept detections, named ``frame000123`` by frame index.

    Raises:
        CalibrationError: no board seen in any frame.
    """
    stop = stop or StopRule()
    kept: list[Detection] = []
    shapes: list[np.ndarray] = []
    meter_obj: CoverageMeter | None = None
    rel_sigma: float | None = None
    n_frames = 0
    last_trial = 0
    samples: list[tuple[str, np.ndarray]] = []
    size0: tuple[int, int] | None = None
    with source:
        while True:
            frame = source.read()
            if frame is None:
                break
            n_frames += 1
            if (n_frames - 1) % max(1, every):
                continue
            grey = to_grey(frame.image)
            name = f"frame{frame.index:06d}"
            if size0 is None:
                size0 = (grey.shape[1], grey.shape[0])
            elif size0 != (grey.shape[1], grey.shape[0]):
                raise CaptureError(f"{name}: frame size changed from {size0[0]}x{size0[1]} "
                                   f"to {grey.shape[1]}x{grey.shape[0]}")
            det = board.detect(grey, name)
            if det is None:
                if len(samples) < 3 and n_frames % 5 == 1:
                    samples.append((name, grey))
                continue
            if len(det) < MIN_CORNERS_PER_VIEW:
                continue
            vec = view_shape(det)
            if shapes and min(np.linalg.norm(vec.vector() - s) for s in shapes) \
                    < stop.min_distance:
                continue
            kept.append(det)
            shapes.append(vec.vector())
            if meter_obj is None:
                meter_obj = CoverageMeter(det.image_size)
            meter_obj.add(det, vec)
            enough = False
            if len(kept) >= stop.min_views and len(kept) - last_trial >= 3:
                last_trial = len(kept)
                enough, rel_sigma = _trial_enough(kept, model, stop, meter_obj)
            if meter is not None:
                meter.write("\r" + meter_obj.line(len(kept), rel_sigma))
                meter.flush()
            if enough or len(kept) >= stop.max_views:
                break
    if meter is not None and meter_obj is not None:
        meter.write("\n")
        meter.flush()
    if not kept:
        raise _no_board_error(board, samples, n_frames) if samples else CalibrationError(
            f"no {board.spec} board found in any of {n_frames} frame(s)")
    return kept

def _trial_enough(kept: list[Detection], model: str, stop: StopRule,
                  meter_obj: CoverageMeter) -> tuple[bool, float | None]:
    """A trial solve of the views kept so far: whether coverage and accuracy suffice
    (``stop``), and the focal length's relative 1 sigma (None when the solve fails)."""
    try:
        sol = _solve(kept, kept[-1].image_size, model, False, "trial")
    except CalibrationError:
        return False, None
    rel_sigma = float(sol.sigmas[0] / sol.camera.fx)
    pp_ok = max(sol.sigmas[2], sol.sigmas[3]) <= stop.pp_sigma_px
    enough = (meter_obj.position >= stop.coverage and len(meter_obj.sizes) >= 2
              and len(meter_obj.tilts) >= 3 and rel_sigma <= stop.rel_focal_sigma and pp_ok)
    return enough, rel_sigma


# -- plots ----------------------------------------------------------------------------------

def _png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:                                    # pragma: no cover - cv2 failure
        raise ConfigError(path, None, "cannot encode the plot as PNG")
    atomic_write_bytes(path, buf.tobytes())


def _text(img: np.ndarray, s: str, org: tuple[int, int], scale: float = 0.45,
          colour: tuple[int, int, int] = (30, 30, 30)) -> None:
    cv2.putText(img, s, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def plot_view_errors(result: IntrinsicsResult) -> np.ndarray:
    """A bar chart (BGR image) of every kept view's RMS, px; the median dashed."""
    rep = result.report
    n = max(rep.n_views, 1)
    W, H, left, bottom, top = max(480, 40 + 28 * n), 360, 50, 90, 30
    img = np.full((H, W, 3), 255, np.uint8)
    top_val = max(max(rep.view_rms_px, default=1.0) * 1.15, 1e-6)
    sy = (H - bottom - top) / top_val
    bw = (W - left - 10) / n
    for i, (name, e) in enumerate(zip(rep.view_names, rep.view_rms_px, strict=True)):
        x0 = int(left + i * bw + 2)
        x1 = int(left + (i + 1) * bw - 2)
        y = int(H - bottom - e * sy)
        colour = (60, 60, 220) if e > 2 * rep.rms_px else (190, 120, 40)
        cv2.rectangle(img, (x0, y), (x1, H - bottom), colour, -1)
        label = np.full((14, 80, 3), 255, np.uint8)
        _text(label, name[:12], (0, 11), 0.35)
        label = cv2.rotate(label, cv2.ROTATE_90_COUNTERCLOCKWISE)
        xa = max(0, min(W - 14, (x0 + x1) // 2 - 7))
        img[H - bottom + 4:H - bottom + 84, xa:xa + 14] = np.minimum(
            img[H - bottom + 4:H - bottom + 84, xa:xa + 14], label)
    med = float(np.median(rep.view_rms_px)) if rep.view_rms_px else 0.0
    ym = int(H - bottom - med * sy)
    for x in range(left, W - 10, 12):
        cv2.line(img, (x, ym), (x + 6, ym), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, H - bottom), (0, 0, 0), 1)
    cv2.line(img, (left, H - bottom), (W - 10, H - bottom), (0, 0, 0), 1)
    for k in range(5):
        v = top_val * k / 4
        yk = int(H - bottom - v * sy)
        _text(img, f"{v:.2f}", (4, yk + 4), 0.35)
    _text(img, f"per-view RMS reprojection error, px (overall {rep.rms_px:.3f}; dashed: "
               f"median)", (left, 18))
    return img


def plot_coverage(result: IntrinsicsResult) -> np.ndarray:
    """The image area (BGR): kept corners coloured by residual, empty cells shaded red."""
    w, h = result.report.image_size
    img = np.full((h, w, 3), 255, np.uint8)
    gx, gy = COVERAGE_GRID
    empty = set(result.report.empty_cells)
    for c in range(gx):
        for r in range(gy):
            p0 = (int(c * w / gx), int(r * h / gy))
            p1 = (int((c + 1) * w / gx) - 1, int((r + 1) * h / gy) - 1)
            if (c, r) in empty:
                cv2.rectangle(img, p0, p1, (200, 200, 255), -1)
            cv2.rectangle(img, p0, p1, (210, 210, 210), 1)
    scale = max(3 * result.report.rms_px, 1e-6)
    for v, res in zip(result.views, result.residuals_px, strict=True):
        e = np.linalg.norm(res, axis=1)
        for p, ei in zip(v.points_px, e, strict=True):
            t = float(min(ei / scale, 1.0))
            colour = (int(200 * (1 - t)), int(160 * (1 - t)), int(220 * t))
            cv2.circle(img, (int(round(p[0])), int(round(p[1]))), 2, colour, -1, cv2.LINE_AA)
    _text(img, f"coverage {100 * result.report.coverage:.0f}% (red: no corner); "
               f"dot colour: residual, red >= {scale:.2f} px", (6, 16))
    t = np.linspace(0.0, 1.0, 256)[:, None]
    lut = np.hstack([200 * (1 - t), 160 * (1 - t), 220 * t])  # the dots' colours, BGR
    return with_colour_scale(img, lut, 0.0, scale, "residual [px]")


def plot_distortion(result: IntrinsicsResult, step_px: int = 40) -> np.ndarray:
    """The distortion field (BGR): colour = displacement from the ideal pinhole, px;
    arrows (scaled, at most x4) point from the pinhole pixel towards the distorted one."""
    cam = result.camera
    w, h = cam.size
    small = 8
    u, v = np.meshgrid(np.arange(0, w, small) + small / 2, np.arange(0, h, small) + small / 2)
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    xy = cam.unproject(px)
    ideal = xy @ cam.K[:2, :2].T + cam.K[:2, 2]
    d = np.linalg.norm(px - ideal, axis=1).reshape(u.shape)
    d = np.nan_to_num(d, nan=0.0)
    dmax = float(d.max()) if d.size else 0.0
    norm = np.clip(d / max(dmax, 1e-9) * 255, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(cv2.resize(norm, (w, h), interpolation=cv2.INTER_LINEAR),
                            cv2.COLORMAP_VIRIDIS)
    U, V = np.meshgrid(np.arange(step_px // 2, w, step_px), np.arange(step_px // 2, h, step_px))
    q = np.stack([U.ravel(), V.ravel()], axis=1).astype(np.float64)
    ideal_q = cam.unproject(q) @ cam.K[:2, :2].T + cam.K[:2, 2]
    disp = np.linalg.norm(q - ideal_q, axis=1)
    dq = float(np.nanmax(disp)) if np.any(np.isfinite(disp)) else 0.0
    gain = min(4.0, 0.9 * step_px / max(dq, 1e-9))
    for a, b in zip(ideal_q, q, strict=True):
        if np.all(np.isfinite(a)):
            tip = b + gain * (b - a)
            cv2.arrowedLine(img, (int(b[0]), int(b[1])), (int(tip[0]), int(tip[1])),
                            (255, 255, 255), 1, cv2.LINE_AA, tipLength=0.25)
    _text(img, f"{cam.model}: distortion 0..{dmax:.1f} px (arrows x{gain:.2g})", (6, 16), 0.45,
          (255, 255, 255))
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)
    return with_colour_scale(img, lut[:, 0, :], 0.0, dmax, "distortion [px]")


PLOT_NAMES = ("views.png", "coverage.png", "distortion.png")
"""The files :func:`write_plots` writes (claimed before a calibration starts)."""


def write_plots(result: IntrinsicsResult, folder: str | Path) -> list[Path]:
    """Write :data:`PLOT_NAMES` (``views.png``, ``coverage.png``, ``distortion.png``)
    into ``folder`` (created if missing), each atomically; returns their paths."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(folder, None, f"cannot create the plot folder: "
                          f"{exc.strerror or exc}") from None
    out = []
    for name, fn in zip(PLOT_NAMES, (plot_view_errors, plot_coverage, plot_distortion),
                        strict=True):
        p = folder / name
        _png(p, fn(result))
        out.append(p)
    return out


__all__ = ["COVERAGE_GRID", "PLOT_NAMES", "RMS_CONVENTION", "CoverageMeter", "DetectionCache",
           "IntrinsicsReport", "IntrinsicsResult", "StopRule", "ViewShape",
           "calibrate_intrinsics", "capture_views", "check_model", "detect_images",
           "image_files", "plot_coverage", "plot_distortion", "plot_view_errors", "read_grey",
           "view_shape", "write_plots"]
