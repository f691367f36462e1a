"""The ceiling map: a rectified mosaic of the ceiling and an index of its natural
features, in W, and how a frame is put on the ceiling plane to be compared with it.

Convention (SPEC §1): the ceiling is the plane ``z = H`` of W. A *rectified* image of
the ceiling is sampled on a square grid of the plane, ``resolution_m`` metres a pixel,
seen from below: its column index grows with +x, its row index with +y (of V for a
frame's patch, of W for the map's mosaic). A patch of ``n x n`` pixels is centred on
the vehicle's origin: pixel ``(row r, col c)`` is the ceiling point
``((c - (n - 1) / 2) res, (r - (n - 1) / 2) res)`` of V. The mosaic's pixel ``(0, 0)``
is the point ``origin_xy`` of W: pixel ``(r, c)`` is ``origin_xy + (c res, r res)``.
Since both grids keep the handedness, a patch maps onto the mosaic by a rotation and a
translation (the vehicle pose), never a reflection.

File (``CeilingMap.save``): one ``.npz`` (numpy's zip of arrays, read without pickle)
holding ``header`` (a JSON string: ``format``, ``version``, the scalars) and the arrays
``mosaic``, ``coverage``, ``points_xy``, ``descriptors``, ``sigma_m`` and, optional,
``keyframe_poses`` and ``keyframe_sigma`` (docs/conventions.md, "Ceiling map").

Example::

    cmap = build_map(frames, poses, rig, 2.7, anchor="truth")
    cmap.save("site/ceiling_map.npz")
    patch, valid = rectify(grey, rig, 2.7, cmap.resolution_m, 1.5)
    q_v, desc = features(patch, valid, cmap.resolution_m)      # (N, 2) in V, (N, 32)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.geometry.ceiling import (
    ceiling_points,
    on_ceiling,
    project_px,
    vehicle_to_world,
)
from ceilkit.runtime.jit import arr, njit, warmer

MAP_FORMAT = "ceilkit-ceiling-map"
MAP_VERSION = 1
"""The file format's version: :meth:`CeilingMap.load` refuses any other."""
DEFAULT_RESOLUTION_M = 0.01
"""Metres per rectified pixel: about twice the office rig's ground pixel at the
image centre (2.2 m / 450 px), so a patch is sampled, not invented."""
ORB_FEATURES = 400       # keypoints per patch, at most
ORB_PATCH = 31           # ORB's descriptor patch, px (its edge threshold too)
ORB_LEVELS = 1           # pyramid levels: the plane is metric, the scale does not change
ORB_FAST = 8             # FAST threshold, grey levels
MERGE_RADIUS_PX = 2.0    # build_map: observations of one feature lie this close ...
MERGE_HAMMING = 64       # ... and their descriptors differ by at most this many bits
MIN_VIEWS = 2            # build_map: a feature seen in fewer frames is not indexed
MIN_SIGMA_PX = 0.25      # the least 1σ of a feature's position, in rectified pixels
VIEW_DESCRIPTORS = 4     # build_map: a feature's descriptors, at most (views unlike ...
VIEW_APART_BITS = 40     # ... each other by more than this many bits each add one)
_ARRAYS = ("mosaic", "coverage", "points_xy", "descriptors", "sigma_m")
_KEYFRAME_ARRAYS = ("keyframe_poses", "keyframe_sigma")   # optional (absent: none)


@dataclass(frozen=True, eq=False)
class CeilingMap:
    """A ceiling map in W (see the module docstring for the grids).

    Attributes:
        resolution_m: metres per mosaic pixel.
        origin_xy: ``(x, y)`` of W at mosaic pixel (0, 0)'s centre, m.
        mosaic: ``(H, W)`` uint8 grey: the ceiling seen from below, rectified.
        coverage: ``(H, W)`` bool: where the mosaic holds data.
        points_xy: ``(N, 2)`` float64: the indexed features in W, m (a feature with
            several descriptors: a row each, at the very same point).
        descriptors: ``(N, D)`` uint8: their descriptors (ORB: D = 32).
        sigma_m: ``(N,)`` float64: each feature's 1σ position, m (per axis).
        ceiling_height: the ceiling plane's height above the floor, m.
        feature: the descriptor type (``orb``).
        anchor: what fixed the map to W (``truth``, ``start pose``, ``marker 7``).
        version: the file format's version (:data:`MAP_VERSION`).
        keyframe_poses: ``(K, 3)`` float64: the poses ``(x m, y m, yaw rad)`` in W the
            frames were pasted at (none: a map of an older ceilkit).
        keyframe_sigma: ``(K, 3)`` float64: their 1σ relative to the anchor (m, m, rad;
            zeros: known poses, ``truth``). The error a pose carries is shared by every
            feature its frame placed: :meth:`placement_cov`.
    """

    resolution_m: float
    origin_xy: tuple[float, float]
    mosaic: np.ndarray
    coverage: np.ndarray
    points_xy: np.ndarray
    descriptors: np.ndarray
    sigma_m: np.ndarray
    ceiling_height: float
    feature: str = "orb"
    anchor: str = ""
    version: int = MAP_VERSION
    keyframe_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    keyframe_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def extent_xy(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)``: the mosaic's outer edges in W, m."""
        h, w = self.mosaic.shape
        r = self.resolution_m
        x0, y0 = self.origin_xy[0] - r / 2, self.origin_xy[1] - r / 2
        return x0, y0, x0 + w * r, y0 + h * r

    @property
    def feature_count(self) -> int:
        """The features the map holds (distinct points; a feature with several
        descriptors has a row each)."""
        return int(len(np.unique(self.points_xy, axis=0))) if len(self.points_xy) else 0

    def placement_cov(self, points_xy: np.ndarray, pose: tuple[float, float, float]
                      ) -> np.ndarray:
        """``(3, 3)``: the covariance the map's own error gives a pose fitted on the
        map's features ``points_xy`` ``(N, 2)`` in W (its inliers) at ``pose``. Each
        feature was placed by the keyframe nearest it (the one that saw it most
        centrally) and moves with that keyframe's pose error ``(dx, dy, dyaw)``: a
        keyframe's features together, so the error is not divided by their count. A
        keyframe ``c`` whose share of the inliers is ``w`` moves the pose by
        ``w J δk`` (``J``: a rotation ``dyaw`` about ``c`` carries the pose's position by
        ``dyaw x (pose - c)``); neighbouring keyframes' errors taken as one (a survey's
        drift: taken independent, the held-out NEES stayed 5.6 and 25 against a band
        up to 5.3). Zeros for a map without keyframe 1σ (known poses, or an older
        ceilkit)."""
        out = np.zeros((3, 3))
        sig = self.keyframe_sigma
        if len(sig) == 0 or len(points_xy) == 0 or not np.any(sig > 0):
            return out
        kf = self.keyframe_poses
        _, near = _keyframe_tree(self).query(np.asarray(points_xy, float).reshape(-1, 2))
        keys, counts = np.unique(near, return_counts=True)
        w = counts / float(len(near))
        A = np.zeros((3, 3))
        for k, wk in zip(keys, w, strict=True):
            J = np.eye(3)
            J[0, 2] = -(pose[1] - kf[k, 1])
            J[1, 2] = pose[0] - kf[k, 0]
            A += wk * J * sig[k]
        return A @ A.T

    def pixel_of(self, points_xy: np.ndarray) -> np.ndarray:
        """``(N, 2)`` mosaic pixel ``(col, row)`` (float) of points of W ``(N, 2)``."""
        return (np.asarray(points_xy, float).reshape(-1, 2) - self.origin_xy) / self.resolution_m

    def save(self, path: str | Path) -> Path:
        """Write the map to ``path`` (``.npz``, see the module docstring)."""
        path = Path(path)
        header = {"format": MAP_FORMAT, "version": self.version,
                  "resolution_m": self.resolution_m, "origin_xy": list(self.origin_xy),
                  "ceiling_height": self.ceiling_height, "feature": self.feature,
                  "anchor": self.anchor, "features": int(len(self.points_xy))}
        with path.open("wb") as f:
            np.savez_compressed(f, header=np.array(json.dumps(header)),
                                **{k: getattr(self, k) for k in _ARRAYS + _KEYFRAME_ARRAYS})
        return path

    @classmethod
    def load(cls, path: str | Path) -> CeilingMap:
        """Read a map written by :meth:`save`.

        Raises:
            ConfigError: naming the file and the key, for a file that is missing, not a
                ceiling map, of another version, or whose arrays disagree.
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise ConfigError(path, None, "no such ceiling map") from None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
            raise ConfigError(path, None, f"not a ceiling map (.npz): {e}") from None
        return cls._from_arrays(path, data)

    @classmethod
    def _from_arrays(cls, path: str | Path, data: dict[str, np.ndarray]) -> CeilingMap:
        if "header" not in data:
            raise ConfigError(path, "header", "not a ceiling map: no header")
        try:
            head = json.loads(str(data["header"]))
        except (TypeError, ValueError):
            raise ConfigError(path, "header", "not JSON") from None
        if not isinstance(head, dict) or head.get("format") != MAP_FORMAT:
            raise ConfigError(path, "header.format", f"expected {MAP_FORMAT!r}, found "
                              f"{head.get('format') if isinstance(head, dict) else head!r}")
        if head.get("version") != MAP_VERSION:
            raise ConfigError(path, "header.version", f"this ceilkit reads version "
                              f"{MAP_VERSION}, found {head.get('version')!r}")
        for key in _ARRAYS:
            if key not in data:
                raise ConfigError(path, key, "missing array")
        try:
            res, h = float(head["resolution_m"]), float(head["ceiling_height"])
            ox, oy = (float(v) for v in head["origin_xy"])
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(path, "header", f"bad or missing scalar: {e}") from None
        if not (math.isfinite(res) and res > 0 and math.isfinite(h)):
            raise ConfigError(path, "header.resolution_m", f"expected a resolution > 0, "
                              f"found {res!r}")
        kf = {k: data[k] for k in _KEYFRAME_ARRAYS if k in data}
        cmap = cls(res, (ox, oy), data["mosaic"], data["coverage"], data["points_xy"],
                   data["descriptors"], data["sigma_m"], h, str(head.get("feature", "orb")),
                   str(head.get("anchor", "")), MAP_VERSION, **kf)
        bad = cmap.shape_problem()
        if bad is not None:
            raise ConfigError(path, *bad)
        return cmap

    def shape_problem(self) -> tuple[str, str] | None:
        """``(key, message)`` of the first array whose type or shape disagrees, or None."""
        m, c = self.mosaic, self.coverage
        if m.ndim != 2 or m.dtype != np.uint8:
            return "mosaic", f"expected (H, W) uint8, found {m.shape} {m.dtype}"
        if c.shape != m.shape or c.dtype != bool:
            return "coverage", f"expected {m.shape} bool, found {c.shape} {c.dtype}"
        p = self.points_xy
        if p.ndim != 2 or p.shape[1] != 2 or p.dtype != np.float64:
            return "points_xy", f"expected (N, 2) float64, found {p.shape} {p.dtype}"
        d = self.descriptors
        if d.ndim != 2 or d.shape[0] != p.shape[0] or d.dtype != np.uint8:
            return "descriptors", f"expected ({p.shape[0]}, D) uint8, found {d.shape} {d.dtype}"
        s = self.sigma_m
        if s.shape != (p.shape[0],) or not np.all(np.isfinite(s)):
            return "sigma_m", f"expected ({p.shape[0]},) finite, found {s.shape}"
        kp, ks = self.keyframe_poses, self.keyframe_sigma
        if kp.ndim != 2 or kp.shape[1:] != (3,) or not np.all(np.isfinite(kp)):
            return "keyframe_poses", f"expected (K, 3) finite, found {kp.shape}"
        if ks.shape != kp.shape or not np.all(np.isfinite(ks)) or np.any(ks < 0):
            return "keyframe_sigma", f"expected {kp.shape} finite, >= 0, found {ks.shape}"
        return None


@functools.lru_cache(maxsize=8)
def _keyframe_tree(cmap: CeilingMap) -> cKDTree:
    """The k-d tree of a map's keyframe positions (a map is hashed by identity)."""
    return cKDTree(cmap.keyframe_poses[:, :2])


def predicted_patch(cmap: CeilingMap, pose: tuple[float, float, float], n: int,
                    stride: int = 1, cover: bool = True
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """What a patch of side ``n`` (at the map's resolution) shows of the map from the
    vehicle pose ``(x, y, yaw)``: ``(patch, covered bool)``, the mosaic resampled
    (bilinear) and where it has data (None with ``cover=False``: not computed); with
    ``stride`` s, only every s-th row and column of the patch (``patch[::s, ::s]``'s
    pixels: ``ceil(n / s)`` a side)."""
    res = cmap.resolution_m
    col, row = cmap.pixel_of(np.array([pose[:2]]))[0]
    A = _patch_to_mosaic(n, res, col, row, pose[2])
    A[:, :2] *= stride
    m = -(-n // stride)
    flags = cv2.WARP_INVERSE_MAP
    patch = cv2.warpAffine(cmap.mosaic, A, (m, m), flags=flags | cv2.INTER_LINEAR)
    if not cover:
        return patch, None
    covered = cv2.warpAffine(cmap.coverage.view(np.uint8), A, (m, m),
                             flags=flags | cv2.INTER_NEAREST)
    return patch, covered.astype(bool)


def coarser(cmap: CeilingMap, levels: int = 1) -> CeilingMap:
    """The map with its mosaic ``levels`` times ``cv2.pyrDown``-ed (each halves the
    resolution; mosaic pixel ``(0, 0)`` stays at ``origin_xy``) and its coverage
    subsampled alike; the features unchanged. For comparing with a frame rectified
    at the coarser resolution."""
    mosaic, cover = cmap.mosaic, cmap.coverage
    for _ in range(levels):
        mosaic = cv2.pyrDown(mosaic)
        cover = cover[::2, ::2]
    return dataclasses.replace(cmap, resolution_m=cmap.resolution_m * 2 ** levels,
                               mosaic=mosaic, coverage=np.ascontiguousarray(cover))


MIN_NCC_SHARE = 0.3      # appearance_ncc: the share of the patch both must cover


def appearance_ncc(cmap: CeilingMap, patch: np.ndarray, valid: np.ndarray,
                   pose: tuple[float, float, float], stride: int = 1) -> float:
    """How well the map's mosaic at ``pose`` explains a rectified patch: the normalized
    cross-correlation of the two where both hold data, in [-1, 1]; NaN where they
    share less than :data:`MIN_NCC_SHARE` of the patch's valid pixels (off the map).
    With ``stride`` s, over every s-th row and column only (s² times cheaper; the
    patch and the mosaic are compared at the same ceiling points, no smoothing). The
    mosaic is read as :func:`predicted_patch` reads it (bilinear; covered where its
    nearest pixel is), at those points only (:func:`_ncc_at`)."""
    (ox, oy), res = cmap.origin_xy, cmap.resolution_m
    col, row = (float(pose[0]) - ox) / res, (float(pose[1]) - oy) / res
    A = _patch_to_mosaic(patch.shape[0], res, col, row, float(pose[2]))
    return float(_ncc_at(arr(cmap.mosaic, np.uint8), arr(cmap.coverage, np.bool_),
                         arr(patch, np.uint8), arr(valid, np.bool_), arr(A, np.float64),
                         int(stride), MIN_NCC_SHARE))


@njit
def _mosaic_at(mosaic, coverage, A, r, c):  # pragma: no cover - compiled
    """The mosaic's bilinear value at patch pixel ``(r, c)`` mapped by ``A @ (c, r, 1)``;
    NaN off the mosaic (its outermost pixels, which no bilinear sample spans, count as
    off) or where its nearest pixel is not covered."""
    h, w = mosaic.shape
    x = A[0, 0] * c + A[0, 1] * r + A[0, 2]
    y = A[1, 0] * c + A[1, 1] * r + A[1, 2]
    if not (0.0 <= x < w - 1 and 0.0 <= y < h - 1):
        return math.nan
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    if not coverage[y0 + (fy >= 0.5), x0 + (fx >= 0.5)]:
        return math.nan
    v00, v01 = np.float64(mosaic[y0, x0]), np.float64(mosaic[y0, x0 + 1])
    v10, v11 = np.float64(mosaic[y0 + 1, x0]), np.float64(mosaic[y0 + 1, x0 + 1])
    return (1 - fy) * (v00 + fx * (v01 - v00)) + fy * (v10 + fx * (v11 - v10))


@njit
def _ncc_at(mosaic, coverage, patch, valid, A, stride, min_share):  # pragma: no cover
    """:func:`appearance_ncc` over the patch pixels ``(r, c)`` of every ``stride``-th row
    and column, the mosaic at ``A @ (c, r, 1)`` (a point on the mosaic's outermost
    pixels, which no bilinear sample spans, counts as not covered: :func:`_mosaic_at`)."""
    n = patch.shape[0]
    W = np.zeros(7)
    for r in range(0, n, stride):
        for c in range(0, n, stride):
            if valid[r, c]:
                _add_whole(W, np.float64(patch[r, c]), _mosaic_at(mosaic, coverage, A, r, c))
    return _ncc_of(W, min_share)


@njit
def _add_whole(W, a, b):  # pragma: no cover - compiled
    """One valid patch sample ``a`` and the mosaic's ``b`` (NaN: not held) added to the
    whole patch's sums ``W``: the valid samples, those both hold, Σa, Σb, Σa², Σb²,
    Σab (:func:`_ncc_of`)."""
    W[0] += 1.0
    if math.isnan(b):
        return
    W[1] += 1.0
    W[2] += a
    W[3] += b
    W[4] += a * a
    W[5] += b * b
    W[6] += a * b


@njit
def _ncc_of(W, min_share):  # pragma: no cover - compiled
    """The correlation of :func:`_add_whole`'s sums ``W``; NaN where both hold fewer
    than ``min_share`` of the valid samples, or either is flat."""
    m, sa, sb = W[1], W[2], W[3]
    if m == 0 or m < min_share * max(W[0], 1.0):
        return math.nan
    va, vb = W[4] - sa * sa / m, W[5] - sb * sb / m
    if va <= 0.0 or vb <= 0.0:
        return math.nan
    return (W[6] - sa * sb / m) / math.sqrt(va * vb)


@warmer
def _warm() -> None:
    g = np.zeros((8, 8), np.uint8)
    g[2:5, 2:5] = 100
    A = arr(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.float64)
    _ncc_at(arr(g, np.uint8), arr(np.ones((8, 8), bool), np.bool_), arr(g, np.uint8),
            arr(np.ones((8, 8), bool), np.bool_), A, 2, MIN_NCC_SHARE)
    S, W = _part_sums(arr(g, np.uint8), arr(np.ones((8, 8), bool), np.bool_),
                      arr(g, np.uint8), arr(np.ones((8, 8), bool), np.bool_), A, 2,
                      PART_BLOCKS)
    _part_median(S, PART_MIN_STD, MIN_PARTS)
    _part_pooled(S, W, MIN_NCC_SHARE)


PART_BLOCKS = 3          # part_ncc: the patch cut in 3 x 3 blocks ...
PART_MIN_STD = 4.0       # ... judged where the frame and the mosaic vary by this (grey
#                          levels, std; a plain tile's noise is 2) on 30 % of the block
MIN_PARTS = 3            # ... fewer such blocks: no verdict (NaN)


def part_ncc(cmap: CeilingMap, patch: np.ndarray, valid: np.ndarray,
             pose: tuple[float, float, float], stride: int = 1) -> float:
    """How well the mosaic at ``pose`` explains each part of a rectified patch: the
    median over the patch's :data:`PART_BLOCKS` x :data:`PART_BLOCKS` blocks (sampled
    row ``i`` of ``m`` in block row ``floor(i B / m)``, columns alike) of their
    normalized cross-correlation with the mosaic, every ``stride``-th pixel, where both
    hold data (the mosaic read as :func:`appearance_ncc` reads it), each less its
    least-squares plane over the block (a lens's falloff or a lamp's glow, which any two
    parts of a ceiling share, is no evidence of the place); a block is judged where both
    hold data on 30 % of it and both then vary by :data:`PART_MIN_STD`. The whole
    patch's correlation can be high when one part matches (a bright panel, the tile
    grid) and the rest does not: a pose off the mapped place (issue 39's held-out
    kidnap: 0.66 over the whole frame, 0.22 over its parts). NaN with fewer than
    :data:`MIN_PARTS` blocks judged. One compiled pass (:func:`_part_sums`)."""
    return explains(cmap, patch, valid, pose, stride)[1]


def flat_ncc(cmap: CeilingMap, patch: np.ndarray, valid: np.ndarray,
             pose: tuple[float, float, float], stride: int = 1) -> float:
    """How well the mosaic at ``pose`` explains a rectified patch with its shading left
    out: the normalized cross-correlation of the two pooled over :func:`part_ncc`'s
    :data:`PART_BLOCKS` x :data:`PART_BLOCKS` blocks, each block of each less its own
    least-squares plane (every block held on 30 % of it, however flat; a lens's
    vignetting or a lamp's glow varies over a frame at the blocks' scale and dominates
    :func:`appearance_ncc` where the texture is faint: issue 39's seeds 2 and 3 read
    down to 0.18 there at the true pose, 0.72 and more read so). NaN where the two
    share less than :data:`MIN_NCC_SHARE` of the patch's valid samples (off the map),
    as :func:`appearance_ncc`. :func:`explains`' first."""
    return explains(cmap, patch, valid, pose, stride)[0]


def explains(cmap: CeilingMap, patch: np.ndarray, valid: np.ndarray,
             pose: tuple[float, float, float], stride: int = 1) -> tuple[float, float]:
    """``(flat_ncc, part_ncc)`` of the mosaic at ``pose``, from one pass over the patch
    (:func:`_part_sums`): a pose's whole-frame and parts checks read each sample once."""
    (ox, oy), res = cmap.origin_xy, cmap.resolution_m
    col, row = (float(pose[0]) - ox) / res, (float(pose[1]) - oy) / res
    A = _patch_to_mosaic(patch.shape[0], res, col, row, float(pose[2]))
    S, W = _part_sums(arr(cmap.mosaic, np.uint8), arr(cmap.coverage, np.bool_),
                      arr(patch, np.uint8), arr(valid, np.bool_), arr(A, np.float64),
                      int(stride), PART_BLOCKS)
    return (float(_part_pooled(S, W, MIN_NCC_SHARE)),
            float(_part_median(S, PART_MIN_STD, MIN_PARTS)))


@njit
def _less_planes(S, i):  # pragma: no cover - compiled
    """Block ``i`` of :func:`_part_sums`' ``S`` less the planes of the frame and the
    mosaic over it (the normal equations of ``1, r, c`` solved by their inverse):
    ``(Σa'², Σb'², Σa'b')`` of the residuals; NaN where the block is held on fewer than
    3 pixels or 30 % of it, or its pixels span no plane."""
    n = S[i, 0]
    if n < max(3.0, 0.3 * S[i, 15]):
        return math.nan, math.nan, math.nan
    M = np.array([[S[i, 0], S[i, 1], S[i, 2]], [S[i, 1], S[i, 3], S[i, 5]],
                  [S[i, 2], S[i, 5], S[i, 4]]])
    if abs(np.linalg.det(M)) < 1e-9:
        return math.nan, math.nan, math.nan
    Mi = np.linalg.inv(M)
    xa = np.array([S[i, 6], S[i, 7], S[i, 8]])
    xb = np.array([S[i, 10], S[i, 11], S[i, 12]])
    return S[i, 9] - xa @ Mi @ xa, S[i, 13] - xb @ Mi @ xb, S[i, 14] - xa @ Mi @ xb


@njit
def _part_median(S, min_std, min_parts):  # pragma: no cover - compiled
    """:func:`part_ncc` from :func:`_part_sums`' ``S``: each block's correlation less
    the planes (:func:`_less_planes`), the median over the judged blocks; NaN with
    fewer than ``min_parts``."""
    out = np.empty(S.shape[0])
    k = 0
    for i in range(S.shape[0]):
        saa, sbb, sab = _less_planes(S, i)
        n = S[i, 0]
        if not (saa >= min_std ** 2 * n and sbb >= min_std ** 2 * n):
            continue
        out[k] = sab / math.sqrt(saa * sbb)
        k += 1
    if k < min_parts:
        return math.nan
    return np.median(out[:k])


@njit
def _part_pooled(S, W, min_share):  # pragma: no cover - compiled
    """:func:`flat_ncc` from :func:`_part_sums`' ``S`` and ``W``: the residuals of every
    held block less its planes (:func:`_less_planes`) pooled into one correlation; NaN
    where frame and mosaic share less than ``min_share`` of the valid samples (``W``,
    as :func:`_ncc_of`) or either is flat once less its planes."""
    if W[1] == 0 or W[1] < min_share * max(W[0], 1.0):
        return math.nan
    taa = tbb = tab = 0.0
    for i in range(S.shape[0]):
        saa, sbb, sab = _less_planes(S, i)
        if math.isfinite(saa):
            taa += saa
            tbb += sbb
            tab += sab
    if not (taa > 0.0 and tbb > 0.0):
        return math.nan
    return tab / math.sqrt(taa * tbb)


@njit
def _part_sums(mosaic, coverage, patch, valid, A, stride, blocks):  # pragma: no cover
    """:func:`part_ncc`'s sums per block ``(blocks², 16)``: over the pixels both hold
    (``r``, ``c`` the sampled row and column in the block, ``a`` the patch, ``b`` the
    mosaic): n, Σr, Σc, Σr², Σc², Σrc, Σa, Σar, Σac, Σa², Σb, Σbr, Σbc, Σb², Σab; and
    the block's sampled pixels (column 15); and the whole patch's sums ``(7,)`` in
    :func:`_ncc_at`'s order (:func:`_add_whole`: the same correlation, to the bit)."""
    n = patch.shape[0]
    m = (n + stride - 1) // stride
    S = np.zeros((blocks * blocks, 16))
    W = np.zeros(7)
    for i in range(m):
        bi = i * blocks // m
        r0 = (bi * m + blocks - 1) // blocks
        for j in range(m):
            bj = j * blocks // m
            k = bi * blocks + bj
            S[k, 15] += 1.0
            r, c = i * stride, j * stride
            if not valid[r, c]:
                continue
            b = _mosaic_at(mosaic, coverage, A, r, c)
            a = np.float64(patch[r, c])
            _add_whole(W, a, b)
            if math.isnan(b):
                continue
            u = np.float64(i - r0)
            v = np.float64(j - (bj * m + blocks - 1) // blocks)
            S[k, 0] += 1.0
            S[k, 1] += u
            S[k, 2] += v
            S[k, 3] += u * u
            S[k, 4] += v * v
            S[k, 5] += u * v
            S[k, 6] += a
            S[k, 7] += a * u
            S[k, 8] += a * v
            S[k, 9] += a * a
            S[k, 10] += b
            S[k, 11] += b * u
            S[k, 12] += b * v
            S[k, 13] += b * b
            S[k, 14] += a * b
    return S, W


# -- a frame on the ceiling plane --------------------------------------------------------
def patch_size(resolution_m: float, half_extent_m: float) -> int:
    """The side ``n`` of a patch, pixels: ``2 round(half / res) + 1`` (odd: the vehicle's
    origin is the centre pixel)."""
    return 2 * int(round(half_extent_m / resolution_m)) + 1


def patch_points_v(resolution_m: float, n: int) -> np.ndarray:
    """``(n * n, 2)`` ceiling points of V at a patch's pixel centres, row-major."""
    c = (np.arange(n) - (n - 1) / 2) * resolution_m
    xx, yy = np.meshgrid(c, c)
    return np.column_stack([xx.ravel(), yy.ravel()])


MAX_LEVEL = 3            # rectify: the coarsest pyramid level it samples from


@functools.lru_cache(maxsize=8)
def _remap_tables(key: tuple, camera: Any, R: bytes, t: bytes, ceiling_m: float,
                  resolution_m: float, n: int, level: int | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``(map1, map2, valid, level)``: the fixed-point remap tables from the frame's
    pyramid level ``level`` (None: :func:`pyramid_level`) to a patch, and where the
    patch's ceiling points fall inside the frame."""
    R_vc = np.frombuffer(R).reshape(3, 3)
    t_vc = np.frombuffer(t).reshape(3)
    q = patch_points_v(resolution_m, n)
    px = project_px(camera, R_vc, t_vc, on_ceiling(q, ceiling_m), np.zeros((1, 3)))[0]
    ok = np.all(np.isfinite(px), axis=1)
    ok &= (px[:, 0] >= 0) & (px[:, 0] <= camera.width - 1)
    ok &= (px[:, 1] >= 0) & (px[:, 1] <= camera.height - 1)
    if level is None:
        level = pyramid_level(px.reshape(n, n, 2), ok.reshape(n, n))
    # pyrDown: pixel u of level 0 is u / 2 there; a 2x2 mean (:func:`_pyramid`'s first
    # halving from level 2 up): (u - 0.5) / 2
    shift = 0.5 if _area_first(level, camera.width, camera.height) else 0.0
    px = (px - shift) / 2 ** level
    px[~ok] = -10.0
    m1, m2 = cv2.convertMaps(px[:, 0].reshape(n, n).astype(np.float32),
                             px[:, 1].reshape(n, n).astype(np.float32), cv2.CV_16SC2)
    valid = ok.reshape(n, n)
    valid.setflags(write=False)
    return m1, m2, valid, level


def pyramid_level(px: np.ndarray, ok: np.ndarray) -> int:
    """The frame's pyramid level (``cv2.pyrDown`` ``L`` times) whose pixel is nearest
    (in log scale) a patch pixel: ``round(log2 s)`` of the median frame pixels ``s`` a
    patch pixel spans, from ``(n, n, 2)`` frame pixels of the patch's points and
    ``(n, n)`` where they are in the frame; between 0 and :data:`MAX_LEVEL`. Sampling
    a level whose pixel is about the patch's is the anti-aliasing the patch needs
    (bilinear sampling of a finer level aliases a seam into a staircase of false
    corners) and costs a quarter of the next finer level's."""
    dx = np.linalg.norm(np.diff(px, axis=1)[:-1], axis=2)
    dy = np.linalg.norm(np.diff(px, axis=0)[:, :-1], axis=2)
    both = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:]
    s = np.sqrt(dx * dy)[both]
    if len(s) == 0:
        return 0
    return int(min(MAX_LEVEL, max(0, round(math.log2(max(float(np.median(s)), 1e-9))))))


def rectify(grey: np.ndarray, rig: Any, ceiling_height: float, resolution_m: float,
            half_extent_m: float, *, level: int | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """The frame resampled onto the ceiling plane, in V: ``(patch, valid)``.

    Each patch pixel (module docstring: column +x, row +y of V, the vehicle's origin at
    the centre) is the ceiling point it stands for, projected through the rig's mount
    and lens (:func:`~ceilkit.runtime.geometry.ceiling.project_px`: every distortion
    model) and sampled bilinearly from the frame's pyramid level ``level``
    (``cv2.pyrDown``; default :func:`pyramid_level`, the level whose pixel is about
    the patch's: 1 for the office rig's 4.9 mm ground pixel and a 1 cm patch). The
    lookup table is made once per rig, height, resolution, extent and level.

    Args:
        grey: ``(h, w)`` uint8 frame of ``rig.camera``.
        rig: the rig (``camera``, ``mount``).
        ceiling_height: the ceiling's height above the floor, m.
        resolution_m: metres per patch pixel.
        half_extent_m: half the patch's side, m.
        level: the pyramid level sampled (0: the frame itself), or None (automatic).

    Returns:
        ``(patch (n, n) uint8, valid (n, n) bool)``: ``valid`` where the ceiling point is
        in the frame (0 grey elsewhere); ``n`` is :func:`patch_size`.
    """
    return Rectifier.of(rig, ceiling_height, resolution_m, half_extent_m, level)(grey)


@dataclass(frozen=True, eq=False)
class Rectifier:
    """:func:`rectify` for one rig, ceiling height, resolution and extent, its tables
    looked up once: calling it on a frame is :func:`rectify` less the lookup (the
    mount's rotation and the tables' key: a tenth of a tracked frame's time).

    Attributes:
        map1, map2: the fixed-point ``cv2.remap`` tables from the pyramid level.
        valid: ``(n, n)`` where the patch's ceiling points fall inside the frame.
        level: the frame's pyramid level sampled (:func:`_pyramid`).
    """

    map1: np.ndarray
    map2: np.ndarray
    valid: np.ndarray
    level: int

    @classmethod
    def of(cls, rig: Any, ceiling_height: float, resolution_m: float, half_extent_m: float,
           level: int | None = None) -> Rectifier:
        """The tables of :func:`rectify` with these arguments."""
        cam = rig.camera
        R = np.ascontiguousarray(rig.mount.R_vehicle_cam, float)
        t = np.ascontiguousarray(rig.mount.t_vehicle_cam, float)
        n = patch_size(resolution_m, half_extent_m)
        return cls(*_remap_tables(cam._key, cam, R.tobytes(), t.tobytes(),
                                  float(ceiling_height), float(resolution_m), n, level))

    def __call__(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(patch (n, n) uint8, valid (n, n) bool)`` of the frame, as :func:`rectify`."""
        patch = cv2.remap(_pyramid(grey, self.level), self.map1, self.map2,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return patch, self.valid


def _pyramid(grey: np.ndarray, level: int) -> np.ndarray:
    """The frame's pyramid level ``level``: ``cv2.pyrDown`` ``level`` times, except
    that from level 2 up the first halving is the mean of each 2x2 block
    (``cv2.INTER_AREA``, a quarter of ``pyrDown``'s time on a full frame): its blur
    (σ 0.5 level-0 px) under the next ``pyrDown``'s (σ 2 level-0 px) gives σ 2.06 where
    two ``pyrDown`` give 2.24; its half-pixel shift is in :func:`_remap_tables`. A side
    of odd length keeps ``pyrDown`` (:func:`_area_first`)."""
    h, w = grey.shape[:2]
    if _area_first(level, w, h):
        grey = cv2.resize(grey, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        level -= 1
    for _ in range(level):
        grey = cv2.pyrDown(grey)
    return grey


def _area_first(level: int, width: int, height: int) -> bool:
    """Whether :func:`_pyramid` halves a ``width x height`` frame first by 2x2 means:
    from level 2 up, the sides even (a 2x2 block for every pixel)."""
    return level >= 2 and width % 2 == 0 and height % 2 == 0


@functools.lru_cache(maxsize=4)
def _orb(n_features: int, levels: int, fast: int) -> Any:
    return cv2.ORB_create(n_features, 1.2, levels, ORB_PATCH, 0, 2, cv2.ORB_HARRIS_SCORE,
                          ORB_PATCH, fast)


@functools.lru_cache(maxsize=4)
def _eroded(valid_bytes: bytes, shape: tuple[int, int], margin: int) -> np.ndarray:
    v = np.frombuffer(valid_bytes, np.uint8).reshape(shape)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * margin + 1, 2 * margin + 1))
    return cv2.erode(v, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)


def features(patch: np.ndarray, valid: np.ndarray, resolution_m: float, *,
             n_features: int = ORB_FEATURES, levels: int = ORB_LEVELS,
             fast_threshold: int = ORB_FAST) -> tuple[np.ndarray, np.ndarray]:
    """Detect and describe (ORB) on a rectified patch, away from where it has no data.

    Args:
        patch, valid: ``(n, n)`` from :func:`rectify`.
        resolution_m: its metres per pixel.
        n_features, levels, fast_threshold: ORB's keypoint budget, pyramid levels and
            FAST threshold (grey levels).

    Returns:
        ``(points_v_xy (N, 2) float64 in V, m; descriptors (N, 32) uint8)``.
    """
    n = patch.shape[0]
    margin = ORB_PATCH // 2 + 2 ** (levels - 1) * 2
    mask = _eroded(np.ascontiguousarray(valid, np.uint8).tobytes(), valid.shape, margin)
    kps, desc = _orb(n_features, levels, fast_threshold).detectAndCompute(patch, mask)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
    uv = np.array([kp.pt for kp in kps], float)
    return (uv - (n - 1) / 2) * resolution_m, desc


def warm_features(valid: np.ndarray, resolution_m: float, n_features: int = ORB_FEATURES
                  ) -> None:
    """:func:`features`' first calls made before a first frame (issue 37): the ORB
    detector, the eroded mask of ``valid``, and the describing's, on a textured patch
    (blurred noise, a fixed seed: it finds ``n_features`` keypoints). A blank patch
    finds none and left the describing's first call to frame 0: its ORB took 1.0 ms
    against 0.55 ms after this (the office example's frame 0, fresh processes
    alternated, 2026-12-07)."""
    noise = np.random.default_rng(0).integers(0, 256, valid.shape, np.uint8)
    features(cv2.GaussianBlur(noise, (0, 0), 2.0), valid, resolution_m, n_features=n_features)


# -- building a map from frames with known poses --------------------------------------
def build_map(frames: Iterable[np.ndarray], poses: Iterable[tuple[float, float, float]],
              rig: Any, ceiling_height: float, resolution_m: float = DEFAULT_RESOLUTION_M,
              anchor: str = "truth", half_extent_m: float | None = None,
              min_views: int = MIN_VIEWS, pose_sigma: np.ndarray | None = None
              ) -> CeilingMap:
    """A ceiling map from grey frames with known vehicle poses ``(x, y, yaw rad)`` in W.

    Every frame is rectified (:func:`rectify`) and pasted into the mosaic at its pose
    (the mean of the frames covering a pixel); its features (:func:`features`) are put
    in W. Observations of one feature in several frames (within
    :data:`MERGE_RADIUS_PX` pixels, descriptors within :data:`MERGE_HAMMING` bits) are
    merged: the feature is their mean, its ``sigma_m`` their scatter's standard error
    (a per-observation scatter pooled over all merged features where a feature has too
    few views to give its own, never below :data:`MIN_SIGMA_PX` pixels), its
    descriptors their medoid and, up to :data:`VIEW_DESCRIPTORS`, those of the views
    farthest from the ones kept while more than :data:`VIEW_APART_BITS` bits from each
    (:func:`_view_descriptors`: one row each, at the feature's point). A drive's views
    of a spot differ: the middle between two rows 2.4 m apart is seen only near the
    frames' edges, darker and oblique, and a frame at the spot itself describes it
    78 bits (median) from that medoid against 63 on a map whose views were near it
    (bench_texture's office, supersample 2); one descriptor a view kind lets the frame
    match the view nearest its own. Features seen in fewer than ``min_views`` frames
    are left out (noise, or at the edge of the drive).

    Args:
        half_extent_m: the patch's half side (default: the frame's ceiling footprint,
            :func:`footprint_half_extent`).
        pose_sigma: ``(N, 3)`` the poses' 1σ (m, m, rad) relative to the anchor (a
            survey's), kept as ``keyframe_sigma``; None: known poses (zeros).

    Raises:
        ConfigError: ``frames`` for no frames, or frames and poses of different counts.
    """
    half = footprint_half_extent(rig, ceiling_height) if half_extent_m is None else half_extent_m
    poses = [tuple(float(v) for v in p) for p in poses]
    pts, descs, views = [], [], []
    acc = _Mosaic(resolution_m)
    k = -1
    for k, grey in enumerate(frames):
        if k >= len(poses):
            raise ConfigError(None, "frames", f"more frames than the {len(poses)} poses")
        patch, valid = rectify(grey, rig, ceiling_height, resolution_m, half)
        acc.add(patch, valid, poses[k])
        q, d = features(patch, valid, resolution_m)
        pts.append(vehicle_to_world(q, *poses[k]))
        descs.append(d)
        views.append(np.full(len(q), k))
    if k < 0 or k + 1 != len(poses):
        raise ConfigError(None, "frames", f"expected {len(poses)} frames (one per pose), "
                          f"found {k + 1}")
    mosaic, coverage, origin = acc.result()
    p, d, s = merge_features(np.concatenate(pts), np.concatenate(descs),
                             np.concatenate(views), resolution_m, min_views)
    kp = np.array(poses, float).reshape(-1, 3)
    ks = np.zeros_like(kp) if pose_sigma is None else \
        np.abs(np.asarray(pose_sigma, float)).reshape(kp.shape)
    return CeilingMap(float(resolution_m), origin, mosaic, coverage, p, d, s,
                      float(ceiling_height), "orb", anchor, keyframe_poses=kp,
                      keyframe_sigma=np.nan_to_num(ks))


def footprint_half_extent(rig: Any, ceiling_height: float, cap_m: float = 4.0) -> float:
    """The half side (m) of the square about V's origin holding every ceiling point the
    frame's border sees (at most ``cap_m``: a wide lens near the horizon)."""
    cam = rig.camera
    w, h = cam.width - 1, cam.height - 1
    s = np.linspace(0.0, 1.0, 33)
    px = np.concatenate([np.c_[s * w, 0 * s], np.c_[s * w, h + 0 * s],
                         np.c_[0 * s, s * h], np.c_[w + 0 * s, s * h]])
    t = rig.mount.t_vehicle_cam
    q, ok = ceiling_points(cam.unproject(px), rig.mount.R_vehicle_cam, t,
                           float(ceiling_height) - float(t[2]))
    if not np.any(ok):
        return cap_m
    return float(min(cap_m, np.max(np.abs(q[ok]))))


class _Mosaic:
    """Running sums of patches pasted into W's grid (grown as frames come)."""

    def __init__(self, resolution_m: float) -> None:
        self.res = float(resolution_m)
        self.items: list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]] = []

    def add(self, patch: np.ndarray, valid: np.ndarray,
            pose: tuple[float, float, float]) -> None:
        self.items.append((patch, valid, pose))

    def result(self) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
        """``(mosaic uint8, coverage bool, origin_xy)``."""
        res = self.res
        corners = []
        for patch, _, (x, y, yaw) in self.items:
            half = (patch.shape[0] - 1) / 2 * res
            sq = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
            corners.append(vehicle_to_world(sq, x, y, yaw))
        allc = np.concatenate(corners)
        lo = np.floor(allc.min(0) / res) * res
        hi = np.ceil(allc.max(0) / res) * res
        w, h = (int(round(v)) + 1 for v in (hi - lo) / res)
        total = np.zeros((h, w), np.float32)
        count = np.zeros((h, w), np.float32)
        for (patch, valid, (x, y, yaw)), cw in zip(self.items, corners, strict=True):
            # the frame's own window of the mosaic: (col, row) from c0, r0
            # (at least 0: a corner on a pixel's edge may floor one below ``lo``)
            c0, r0 = (max(int(v), 0) for v in np.floor((cw.min(0) - lo) / res))
            c1, r1 = (int(v) + 2 for v in np.ceil((cw.max(0) - lo) / res))
            c1, r1 = min(c1, w), min(r1, h)
            A = _patch_to_mosaic(patch.shape[0], res, (x - lo[0]) / res - c0,
                                 (y - lo[1]) / res - r0, yaw)
            size = (c1 - c0, r1 - r0)
            vw = cv2.warpAffine(valid.astype(np.float32), A, size, flags=cv2.INTER_NEAREST)
            pw = cv2.warpAffine(patch.astype(np.float32), A, size, flags=cv2.INTER_LINEAR)
            total[r0:r1, c0:c1] += pw * vw
            count[r0:r1, c0:c1] += vw
        cover = count > 0
        mosaic = np.zeros((h, w), np.uint8)
        mosaic[cover] = np.clip(np.rint(total[cover] / count[cover]), 0, 255)
        return mosaic, cover, (float(lo[0]), float(lo[1]))


def _patch_to_mosaic(n: int, res: float, col: float, row: float, yaw: float) -> np.ndarray:
    """``(2, 3)`` affine from a patch's ``(col, row)`` to a window's of the mosaic, the
    vehicle's origin at the window's ``(col, row)`` (both grids ``res`` m a pixel)."""
    c, s = math.cos(yaw), math.sin(yaw)
    h = (n - 1) / 2
    return np.array([[c, -s, col - (c * h - s * h)], [s, c, row - (s * h + c * h)]])


_POPCOUNT = np.array([bin(b).count("1") for b in range(256)], np.uint8)
_PAIR_CHUNK = 200_000


def merge_features(points_xy: np.ndarray, descriptors: np.ndarray, views: np.ndarray,
                   resolution_m: float, min_views: int = MIN_VIEWS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge observations ``(N, 2)`` in W (with their descriptors and frame indices)
    of the same feature: ``(points (M, 2), descriptors (M, D), sigma_m (M,))``, a row
    per descriptor kept (see :func:`build_map`)."""
    n = len(points_xy)
    if n == 0:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0)
    parent = np.arange(n)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    pairs = cKDTree(points_xy).query_pairs(MERGE_RADIUS_PX * resolution_m, output_type="ndarray")
    for c in range(0, len(pairs), _PAIR_CHUNK):     # bounded memory: a long drive's pairs
        p = pairs[c:c + _PAIR_CHUNK]                # run to millions
        ham = _POPCOUNT[descriptors[p[:, 0]] ^ descriptors[p[:, 1]]].sum(1, dtype=np.int32)
        for a, b in p[(ham <= MERGE_HAMMING) & (views[p[:, 0]] != views[p[:, 1]])]:
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[rb] = ra
    roots = np.array([root(i) for i in range(n)])
    _, label = np.unique(roots, return_inverse=True)
    return _clusters(points_xy, descriptors, views, label, resolution_m, min_views)


def _clusters(points_xy: np.ndarray, descriptors: np.ndarray, views: np.ndarray,
              label: np.ndarray, resolution_m: float, min_views: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    order = np.argsort(label, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(label[order]) != 0])
    groups = np.split(order, starts[1:])
    keep = [g for g in groups if len(np.unique(views[g])) >= min_views]
    if not keep:
        return np.zeros((0, 2)), np.zeros((0, descriptors.shape[1]), np.uint8), np.zeros(0)
    means = np.array([points_xy[g].mean(0) for g in keep])
    sq = np.array([((points_xy[g] - m) ** 2).sum() for g, m in zip(keep, means, strict=True)])
    counts = np.array([len(g) for g in keep], float)
    multi = counts >= 3
    # the per-observation 1σ (per axis), pooled over the features seen 3 times or more
    pooled = math.sqrt(sq[multi].sum() / max(2.0 * (counts[multi] - 1).sum(), 1.0)) \
        if np.any(multi) else resolution_m
    own = np.sqrt(sq / np.maximum(2.0 * (counts - 1), 1.0))
    per_obs = np.where(multi, own, pooled)
    sigma = np.maximum(per_obs / np.sqrt(counts), MIN_SIGMA_PX * resolution_m)
    rows = [g[_view_descriptors(descriptors[g])] for g in keep]
    owner = np.repeat(np.arange(len(keep)), [len(r) for r in rows])
    return means[owner], descriptors[np.concatenate(rows)], sigma[owner]


def _view_descriptors(desc: np.ndarray, most: int = VIEW_DESCRIPTORS,
                      apart_bits: int = VIEW_APART_BITS) -> np.ndarray:
    """Indices of the descriptors a feature keeps among its observations' ``(n, D)``:
    the medoid (least summed Hamming distance to the others), then greedily the one
    farthest from all kept while that is more than ``apart_bits`` bits, ``most`` in all."""
    if len(desc) == 1:
        return np.zeros(1, int)
    bits = np.unpackbits(desc, axis=1).astype(np.int16)
    ham = (bits[:, None, :] != bits[None, :, :]).sum(2)
    chosen = [int(np.argmin(ham.sum(1)))]
    while len(chosen) < most:
        far = ham[:, chosen].min(1)
        j = int(np.argmax(far))
        if not far[j] > apart_bits:
            break
        chosen.append(j)
    return np.array(chosen)


__all__ = ["DEFAULT_RESOLUTION_M", "MAP_FORMAT", "MAP_VERSION", "CeilingMap", "Rectifier",
           "appearance_ncc", "build_map", "coarser", "explains", "features", "flat_ncc",
           "footprint_half_extent", "merge_features", "part_ncc", "patch_points_v",
           "patch_size", "predicted_patch", "pyramid_level", "rectify", "warm_features"]
