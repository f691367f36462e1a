"""Intrinsics from the ceiling, no board: a drive under a tiled ceiling.

The tile seams are a planar target of known pitch (site ``corridor``: ``lines_along``
evenly spaced, ``lines_across.spacing``), seen in every frame at a pose that is only
known up to the grid's symmetry, which does not matter for the intrinsics.

Model. The vehicle drives on a flat floor with a fixed mount, so every frame sees the
ceiling at the same attitude: ``R_WC,k = Rz(psi_k) Exp([a, b, 0]) R_VC`` (``R_VC`` the
rig's nominal mount, ``(a, b)`` a shared lean) with the camera centre
``(X_k, Y_k, H - d)``, ``d = ceiling_height - mount.z`` its distance below the
ceiling. A seam pixel is undistorted with the current intrinsics (``f`` with square
pixels, ``cx, cy``, plumb_bob ``k1, k2``), its ray is cut with the ceiling, and the
residual is its distance to the nearest seam of its family (x or y lines), in pixels
(times ``f / depth``). Seams must come out straight after undistortion, on the known
pitch, at one attitude for the whole drive: straightness gives the distortion and its
centre (the principal point), the pitch at distance ``d`` gives ``f``.

Observability (why ``d`` is taken from the site and rig, not fitted): views of one
plane that all share the plane's attitude give the image of the absolute conic the
same two constraints (Sturm and Maybank), so on a flat floor ``f`` and ``d`` trade
off one for one; ``f`` is as good as ``d`` (1 cm at 2.4 m is 0.4 %). The principal
point of a lens without distortion looking straight up trades with the lean; only
the distortion's centre or perspective (a tilted camera) pins it. Each parameter's
1 sigma comes from the fit; one above :data:`MAX_SIGMA` is refused with what to add.

Start. Per frame and candidate ``f``, the seam pixels near the image centre are cut
with the ceiling at ``psi = 0`` and the circular mean of ``exp(2 pi i X / pitch)`` is
scanned over ``psi``: the coherent heading and pitch give ``psi_k, X_k, Y_k`` and ``f``
(the 2x and 3x pitch harmonics are subtracted so ``f/2`` and ``f/3`` do not win).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.geometry.camera import CameraModel
from ceilkit.runtime.geometry.ceiling import ceiling_rays

INTRINSICS = ("f", "cx", "cy", "k1", "k2")
N_SHARED = 7                      # f, cx, cy, k1, k2, lean a, lean b
# a parameter whose 1 sigma exceeds this is not determined by the drive: refused
MAX_SIGMA = {"f": 0.001, "cx": 0.7, "cy": 0.7, "k1": 0.01, "k2": 0.01}  # f relative
MIN_FRAMES = 4
MIN_POINTS = 150                  # seam pixels a frame needs to be used
POINTS_PER_FRAME = 600
GATES_PX = (5.0, 2.0, 1.0)        # association gates of the successive refits
_PSI = np.radians(np.arange(0.0, 90.0, 0.5))
MIN_RISE = 1e-6                   # a ray meets the ceiling when R (x, y, 1) rises this much

_WHAT_TO_ADD = {
    "f": "drive under more of the tiled ceiling (more frames, seams across the image)",
    "cx": "perspective variety (a tilted camera, a lens with distortion) or frames with "
          "less blur, or calibrate with a board (--board)",
    "cy": "perspective variety (a tilted camera, a lens with distortion) or frames with "
          "less blur, or calibrate with a board (--board)",
    "k1": "seams near the image corners (drive so the grid fills the image)",
    "k2": "seams near the image corners (drive so the grid fills the image)",
}


@dataclass(frozen=True)
class TileGrid:
    """The seam grid: x lines at ``x0 + i * pitch_x``, y lines at ``y0 + j * pitch_y``,
    the camera ``distance_m`` below it."""

    pitch_x: float
    pitch_y: float
    x0: float
    y0: float
    distance_m: float


@dataclass(frozen=True, eq=False)
class SelfCalResult:
    """The solved camera, each intrinsic's value and 1 sigma, the fit's figures."""

    camera: CameraModel
    values: dict
    sigmas: dict
    rms_px: float
    frames: int
    points: int
    grid: TileGrid

    def lines(self, compare: CameraModel | None = None) -> list[str]:
        """The report: one line per parameter, with the board calibration beside."""
        out = [f"intrinsics from the ceiling: {self.frames} frames, {self.points} seam "
               f"points, residual RMS {self.rms_px:.3f} px, camera {self.grid.distance_m:.3f}"
               f" m below the tiles (f scales with it)"]
        ref = _values(compare) if compare is not None else {}
        for name in INTRINSICS:
            line = f"  {name:3s} {self.values[name]:10.4f} +- {self.sigmas[name]:.4f}"
            if name in ref:
                d = self.values[name] - ref[name]
                line += (f"   board {ref[name]:10.4f} (diff {d:+.4f}, "
                         f"{_n_sigma(d, self.sigmas[name])})")
            out.append(line)
        return out


def _n_sigma(d: float, s: float) -> str:
    return f"{abs(d) / s:.1f} sigma" if s > 0 else "-"


def _values(cam: CameraModel) -> dict:
    K, dist = cam.K, cam.dist
    return {"f": 0.5 * (K[0, 0] + K[1, 1]), "cx": K[0, 2], "cy": K[1, 2],
            "k1": dist[0], "k2": dist[1] if dist.size > 1 else 0.0}


# -- the grid and the seams ------------------------------------------------------------
def tile_grid(site: Site, rig: Rig) -> TileGrid:
    """The site's seam grid (evenly spaced ``lines_along``, ``lines_across``) and the
    camera's distance below it.

    Raises ConfigError naming the site key when the site has no regular grid.
    """
    src = site.source
    cor = site.corridor
    if cor is None or cor.lines_across is None or len(cor.lines_along_m) < 2:
        raise ConfigError(src, "corridor", "intrinsics from the ceiling need a tile grid: "
                          "lines_along (evenly spaced) and lines_across {first, spacing}")
    ys = np.sort(np.asarray(cor.lines_along_m, float))
    steps = np.diff(ys)
    if np.ptp(steps) > 1e-6 * max(1.0, steps.mean()):
        raise ConfigError(src, "corridor.lines_along", "expected evenly spaced tile seams, "
                          f"found spacings {', '.join(f'{s:g}' for s in steps)}")
    d = site.ceiling_height_m - rig.mount.z_m
    if d <= 0:
        raise ConfigError(src, "ceiling_height", "the camera is not below the ceiling")
    return TileGrid(cor.lines_across.spacing_m, float(steps.mean()),
                    cor.lines_across.first_m, float(ys[0]), float(d))


def seam_points(image: np.ndarray, max_points: int = POINTS_PER_FRAME,
                seed: int = 0) -> np.ndarray:
    """``(N, 2)`` pixels on thin dark lines (black-hat response), at most
    ``max_points`` of them drawn evenly at random."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    grey = cv2.GaussianBlur(grey.astype(np.float32), (3, 3), 0.8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))
    bh = cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel)
    noise = 1.4826 * float(np.median(np.abs(bh - np.median(bh))))
    thr = max(6.0 * noise, 0.35 * float(np.percentile(bh, 99.5)), 3.0)
    return _sample(_ridge(bh, thr), max_points, seed)


def _ridge(bh: np.ndarray, thr: float) -> np.ndarray:
    """Sub-pixel centre points of the black-hat ridges: each pixel above ``thr`` that
    peaks across its line (x for steep lines, y for flat ones), moved to the vertex of
    the parabola through it and its two neighbours."""
    c = bh[1:-1, 1:-1]
    lx, rx, uy, dy = bh[1:-1, :-2], bh[1:-1, 2:], bh[:-2, 1:-1], bh[2:, 1:-1]
    cxx, cyy = lx - 2 * c + rx, uy - 2 * c + dy
    steep = cxx < cyy
    px_ok = steep & (c > thr) & (c >= lx) & (c > rx) & (cxx < 0)
    py_ok = ~steep & (c > thr) & (c >= uy) & (c > dy) & (cyy < 0)
    out = []
    for ok, a, b, curv, axis in ((px_ok, lx, rx, cxx, 0), (py_ok, uy, dy, cyy, 1)):
        ys, xs = np.nonzero(ok)
        off = 0.5 * (a[ys, xs] - b[ys, xs]) / curv[ys, xs]
        p = np.column_stack([xs + 1.0, ys + 1.0])
        p[:, axis] += off
        out.append(p)
    return np.concatenate(out)


def _sample(pts: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    if len(pts) > max_points:
        pick = np.random.default_rng(seed).choice(len(pts), max_points, replace=False)
        pts = pts[np.sort(pick)]
    return pts


# -- geometry --------------------------------------------------------------------------
def _exp(w: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))
    return R


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _normalized(px: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Normalized points ``(N, 2)`` (z = 1) of distorted pixels, intrinsics
    ``(f, cx, cy, k1, k2)``."""
    f, cx, cy, k1, k2 = intr
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    dist = np.array([k1, k2, 0.0, 0.0, 0.0])
    n = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist,
                            criteria=
                            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10))
    return n.reshape(-1, 2)


def _on_ceiling(px: np.ndarray, intr: np.ndarray, R_wc: np.ndarray, d: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal offsets ``(N, 2)`` from the camera of the pixels' ceiling points, and
    their depths along the optical axis (NaN for rays that miss the ceiling):
    :func:`~ceilkit.runtime.geometry.ceiling.ceiling_rays`."""
    q, s, _ = ceiling_rays(_normalized(px, intr), R_wc, d, min_rz=MIN_RISE)
    return q, s


def _wrap(v: np.ndarray, p: float) -> np.ndarray:
    return v - p * np.round(v / p)


# -- the start -------------------------------------------------------------------------
def _coherence(q: np.ndarray, grid: TileGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per heading in :data:`_PSI`: the grid score and the complex x and y means."""
    c, s = np.cos(_PSI)[:, None], np.sin(_PSI)[:, None]
    X = c * q[None, :, 0] - s * q[None, :, 1]
    Y = s * q[None, :, 0] + c * q[None, :, 1]
    score = np.zeros(len(_PSI))
    means = []
    for V, p in ((X, grid.pitch_x), (Y, grid.pitch_y)):
        m1 = np.exp(2j * np.pi * V / p).mean(axis=1)
        m2 = np.exp(1j * np.pi * V / p).mean(axis=1)
        m3 = np.exp(2j * np.pi * V / (3 * p)).mean(axis=1)
        score += np.abs(m1) - np.abs(m2) - np.abs(m3)
        means.append(m1)
    return score, means[0], means[1]


def _central(px: np.ndarray, size: tuple[int, int], frac: float = 0.5) -> np.ndarray:
    w, h = size
    r = np.hypot(px[:, 0] - 0.5 * w, px[:, 1] - 0.5 * h)
    return px[r < frac * 0.5 * math.hypot(w, h)]


def _start_frame(px: np.ndarray, f: float, size: tuple[int, int], R0: np.ndarray,
                 grid: TileGrid) -> tuple[float, np.ndarray]:
    """Best score and ``(psi, X, Y)`` of one frame for focal length ``f``."""
    intr = np.array([f, 0.5 * (size[0] - 1), 0.5 * (size[1] - 1), 0.0, 0.0])
    q, s = _on_ceiling(px, intr, R0, grid.distance_m)
    q = q[np.isfinite(s)]
    if len(q) < 20:
        return -np.inf, np.zeros(3)
    score, mx, my = _coherence(q, grid)
    i = int(np.argmax(score))
    X = grid.x0 - np.angle(mx[i]) * grid.pitch_x / (2 * np.pi)
    Y = grid.y0 - np.angle(my[i]) * grid.pitch_y / (2 * np.pi)
    return float(score[i]), np.array([_PSI[i], X, Y])


def start(frames: Sequence[np.ndarray], size: tuple[int, int], R0: np.ndarray,
          grid: TileGrid) -> tuple[float, np.ndarray]:
    """The start: ``f`` (scanned over 0.3..3 image widths) and each frame's
    ``(psi, X, Y)`` ``(n, 3)``."""
    central = [_central(px, size) for px in frames]
    probe = central[:: max(1, len(central) // 4)][:4]
    fs = size[0] * np.geomspace(0.3, 3.0, 40)
    totals = [sum(_start_frame(px, f, size, R0, grid)[0] for px in probe) for f in fs]
    k = int(np.argmax(totals))
    fine = fs[k] * np.geomspace(0.97, 1.03, 13)
    totals = [sum(_start_frame(px, f, size, R0, grid)[0] for px in probe) for f in fine]
    f0 = float(fine[int(np.argmax(totals))])
    poses = np.array([_start_frame(px, f0, size, R0, grid)[1] for px in central])
    return f0, poses


# -- the bundle ------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _Problem:
    """Seam pixels of every frame, their family (0: x lines, 1: y lines) and the
    nominal mount rotation."""

    frames: tuple[np.ndarray, ...]
    families: tuple[np.ndarray, ...]
    R0: np.ndarray
    grid: TileGrid


def _frame_residuals(x: np.ndarray, k: int, prob: _Problem) -> np.ndarray:
    g = prob.grid
    psi, X, Y = x[N_SHARED + 3 * k: N_SHARED + 3 * k + 3]
    R = _rz(psi) @ _exp([x[5], x[6], 0.0]) @ prob.R0
    q, s = _on_ceiling(prob.frames[k], x[:5], R, g.distance_m)
    fam = prob.families[k]
    v = np.where(fam == 0, _wrap(X + q[:, 0] - g.x0, g.pitch_x),
                 _wrap(Y + q[:, 1] - g.y0, g.pitch_y))
    r = v * x[0] / s
    return np.where(np.isfinite(r), r, 1e3)


def _residuals(x: np.ndarray, prob: _Problem) -> np.ndarray:
    return np.concatenate([_frame_residuals(x, k, prob) for k in range(len(prob.frames))])


def _sparsity(prob: _Problem) -> lil_matrix:
    n = [len(p) for p in prob.frames]
    J = lil_matrix((sum(n), N_SHARED + 3 * len(n)), dtype=int)
    row = 0
    for k, m in enumerate(n):
        J[row:row + m, :N_SHARED] = 1
        J[row:row + m, N_SHARED + 3 * k:N_SHARED + 3 * k + 3] = 1
        row += m
    return J


def _associate(x: np.ndarray, frames: Sequence[np.ndarray], R0: np.ndarray, grid: TileGrid,
               gate_px: float) -> _Problem:
    """Each pixel's nearest seam family at ``x``; pixels farther than ``gate_px`` from
    both (markers, blocks, stains) are dropped."""
    kept, fams = [], []
    for k, px in enumerate(frames):
        psi, X, Y = x[N_SHARED + 3 * k: N_SHARED + 3 * k + 3]
        R = _rz(psi) @ _exp([x[5], x[6], 0.0]) @ R0
        q, s = _on_ceiling(px, x[:5], R, grid.distance_m)
        dx = np.abs(_wrap(X + q[:, 0] - grid.x0, grid.pitch_x)) * x[0] / s
        dy = np.abs(_wrap(Y + q[:, 1] - grid.y0, grid.pitch_y)) * x[0] / s
        ok = np.isfinite(s) & (np.minimum(dx, dy) < gate_px)
        kept.append(px[ok])
        fams.append((dy[ok] < dx[ok]).astype(np.int8))
    return _Problem(tuple(kept), tuple(fams), R0, grid)


def _solve(x0: np.ndarray, frames: Sequence[np.ndarray], R0: np.ndarray, grid: TileGrid
           ) -> tuple[np.ndarray, _Problem, object]:
    x = x0.copy()
    for gate in GATES_PX:
        prob = _associate(x, frames, R0, grid, gate)
        scale = np.r_[10.0, 1.0, 1.0, 0.01, 0.01, 1e-3, 1e-3,
                      np.tile([1e-3, 1e-3, 1e-3], len(frames))]
        fit = least_squares(_residuals, x, args=(prob,), jac_sparsity=_sparsity(prob),
                            x_scale=scale, loss="soft_l1", f_scale=0.3, method="trf",
                            max_nfev=60)
        x = fit.x
    return x, prob, fit


def _sigmas(fit, n_params: int) -> np.ndarray:
    """1 sigma of the shared parameters: ``s^2 (J^T J)^-1`` with the residual variance
    per degree of freedom (robust-loss inliers only)."""
    J = fit.jac.toarray() if hasattr(fit.jac, "toarray") else np.asarray(fit.jac)
    r = fit.fun
    inl = np.abs(r) < 3.0
    dof = max(int(inl.sum()) - n_params, 1)
    s2 = float(np.sum(r[inl] ** 2)) / dof
    JtJ = J[inl].T @ J[inl]
    try:
        cov = np.linalg.inv(JtJ) * s2
    except np.linalg.LinAlgError:
        return np.full(N_SHARED, np.inf)
    return np.sqrt(np.maximum(np.diag(cov)[:N_SHARED], 0.0))


def _refuse_undetermined(values: dict, sigmas: dict) -> None:
    bad = []
    for name in INTRINSICS:
        s = sigmas[name] / values["f"] if name == "f" else sigmas[name]
        if not np.isfinite(s) or s > MAX_SIGMA[name]:
            shown = f"{100 * s:.2f} %" if name == "f" else f"{s:.3g}"
            bad.append(f"{name} (1 sigma {shown}, limit "
                       f"{100 * MAX_SIGMA[name] if name == 'f' else MAX_SIGMA[name]:g}"
                       f"{' %' if name == 'f' else ''}): add {_WHAT_TO_ADD[name]}")
    if bad:
        raise CalibrationError("the drive does not determine " + "; ".join(bad))


def calibrate_from_ceiling(frames: Sequence[np.ndarray], size: tuple[int, int], rig: Rig,
                           grid: TileGrid, name: str = "camera") -> SelfCalResult:
    """Solve ``f, cx, cy, k1, k2`` from the seam pixels of each frame (``seam_points``).

    Raises CalibrationError when too few frames show the grid, or when a parameter's
    1 sigma exceeds :data:`MAX_SIGMA` (the message says what views to add).
    """
    frames = [p for p in frames if len(p) >= MIN_POINTS]
    if len(frames) < MIN_FRAMES:
        raise CalibrationError(f"only {len(frames)} frames show the tile grid (at least "
                               f"{MIN_POINTS} seam pixels each; {MIN_FRAMES} needed): drive "
                               "under the tiled ceiling with the seams in view")
    R0 = rig.mount.R_vehicle_cam
    f0, poses = start(frames, size, R0, grid)
    x0 = np.r_[f0, 0.5 * (size[0] - 1), 0.5 * (size[1] - 1), 0.0, 0.0, 0.0, 0.0,
               poses.ravel()]
    x, prob, fit = _solve(x0, frames, R0, grid)
    sig = _sigmas(fit, len(x))
    values = dict(zip(INTRINSICS, map(float, x[:5]), strict=True))
    sigmas = dict(zip(INTRINSICS, map(float, sig[:5]), strict=True))
    _refuse_undetermined(values, sigmas)
    cam = CameraModel.pinhole(size[0], size[1], x[0], x[0], x[1], x[2],
                              dist=[x[3], x[4], 0.0, 0.0, 0.0], name=name)
    inl = np.abs(fit.fun) < 3.0
    return SelfCalResult(cam, values, sigmas, float(np.sqrt(np.mean(fit.fun[inl] ** 2))),
                         len(frames), int(sum(len(p) for p in prob.frames)), grid)


# -- the whole, from a recording ------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CeilingRun:
    """What :func:`intrinsics_from_ceiling` solved and wrote."""

    result: SelfCalResult
    out: Path
    report: tuple[str, ...]

    def lines(self) -> list[str]:
        return [*self.report, f"wrote {self.out}"]


def load_seam_frames(recording: Path, max_frames: int = 40
                     ) -> tuple[list[np.ndarray], tuple[int, int], Rig, Site]:
    """Seam pixels of at most ``max_frames`` frames spread evenly over a recording
    (SPEC layout), its image size, rig and site."""
    from ceilkit.runtime.io.recording import Recording

    if not (Path(recording) / "frames.csv").exists():
        raise ConfigError(Path(recording) / "frames.csv", None, "file not found: "
                          "--ceiling reads a recording (frames.csv, frames/, rig.yaml, "
                          "site.yaml)")
    rec = Recording(recording)
    ks = np.unique(np.linspace(0, len(rec) - 1, min(max_frames, len(rec))).round()
                   .astype(int))
    frames = []
    for k in ks:
        frame = rec.frame(int(k))
        if frame.damage:  # a file cut short or not an image: no seams from it, said
            logging.getLogger("ceilkit.selfcal").warning("%s: skipped (bad_frame)",
                                                         frame.damage)
            continue
        frames.append(seam_points(frame.image, seed=int(k)))
    cam = rec.rig.camera
    return frames, (cam.width, cam.height), rec.rig, rec.site


def intrinsics_from_ceiling(recording: Path, out: Path, *, compare: Path | None = None,
                            name: str = "camera", max_frames: int = 40,
                            force: bool = False) -> CeilingRun:
    """Solve the intrinsics from a drive under a tiled ceiling and write ``out``
    (camera.yaml, atomically, with a provenance header); nothing is written when the
    drive does not determine them. ``compare``: a board camera.yaml put beside each
    value in the report. ``force``: replace an existing ``out`` (refused otherwise).

    Raises ConfigError (a bad recording, site or ``compare`` file; ``out`` exists without
    ``force``, or lies in the recording), CalibrationError (the drive does not determine
    a parameter), OutputError (``out`` not writable).
    """
    from ceilkit.runtime.config.camera import load_camera, save_camera
    from ceilkit.runtime.io.outputs import recording_inputs

    from .workflow import _check_writable, _claim, provenance_header

    out = Path(out)
    _check_writable(out)
    with _claim(out, force, [*recording_inputs(recording), compare]):  # locked till written
        ref = load_camera(compare) if compare is not None else None
        frames, size, rig, site = load_seam_frames(Path(recording), max_frames)
        if ref is not None and (ref.width, ref.height) != size:
            raise ConfigError(compare, "image_width", f"expected {size[0]}x{size[1]} like the "
                              f"recording, found {ref.width}x{ref.height}")
        res = calibrate_from_ceiling(frames, size, rig, tile_grid(site, rig), name)
        report = tuple(res.lines(ref))
        save_camera(res.camera, out, provenance_header(
            "camera intrinsics from the ceiling by ceilcal intrinsics --ceiling",
            [f"recording: {recording}", *report]))
        return CeilingRun(res, out, report)


__all__ = ["CeilingRun", "SelfCalResult", "TileGrid", "calibrate_from_ceiling",
           "intrinsics_from_ceiling", "load_seam_frames", "seam_points", "start",
           "tile_grid"]
