"""Recordings, truth and pose files in the layouts of SPEC §2.

A recording is a folder::

    frames/000000.png ...          # 8-bit grey or BGR, as captured
    frames.csv                     # header `index,t_ns`, one row per frame
    rig.yaml, site.yaml            # as used when recording
    truth.csv                      # optional: `t_ns,x,y,yaw_deg`
    odometry.csv                   # optional: `t_ns,dx,dy,dyaw_deg`, increments in V

:class:`RecordingWriter` writes each frame's PNG (atomically, by rename) before
its row, and flushes the row, so a run killed at any moment leaves a readable
recording holding every frame it completed. :class:`Recording` checks the whole
folder when it is opened. A file that cannot be written is an
:class:`~ceilkit.runtime.errors.OutputError` naming it.
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.io.sources import Frame, SourceBase

FRAMES_HEADER = ["index", "t_ns"]
TRUTH_HEADER = ["t_ns", "x", "y", "yaw_deg"]
ODOMETRY_HEADER = ["t_ns", "dx", "dy", "dyaw_deg"]
POSES_HEADER = ["t_ns", "x", "y", "yaw_deg", "lateral", "method", "quality", "latency_ms",
                "sigma_x", "sigma_y", "sigma_yaw_deg"]
POSES_SIGMA_COLUMNS = POSES_HEADER[8:]
"""The columns SPEC §2 added after the first eight; a file without them still reads."""


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


# --------------------------------------------------------------------------- writing
class RecordingWriter:
    """Writes a SPEC recording, frame by frame.

    Example::

        with RecordingWriter(out_dir, rig, site, truth=True) as rec:
            rec.write(frame)                       # PNG, then its frames.csv row
            rec.write_truth(frame.t_ns, x, y, yaw_rad)

    With ``truth_of`` (the ground truth a source carries: the simulator's trajectory,
    a replayed recording's ``truth.csv``), :meth:`write` adds the truth row of each
    frame it stores (by the frame's exact stamp), so the recording replays with its
    errors against truth. ``truth.csv`` is created at once with ``truth`` or
    ``truth_of``, else by the first :meth:`write_truth`.

    Raises:
        ConfigError: the folder already holds a recording (nothing is overwritten).
        OutputError: a folder or file that cannot be written.
    """

    def __init__(self, folder: str | Path, rig: Rig, site: Site, truth: bool = False,
                 header: str = "", truth_of: Truth | None = None):
        self.folder = Path(folder)
        frames_dir = self.folder / "frames"
        if (self.folder / "frames.csv").exists():
            raise ConfigError(self.folder, None, "a recording is already there; "
                              "choose another folder (nothing was overwritten)")
        try:
            frames_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(self.folder, f"cannot create: {exc.strerror}") from None
        rig.save(self.folder / "rig.yaml", header)
        site.save(self.folder / "site.yaml", header)
        self._frames = _open_csv(self.folder / "frames.csv", FRAMES_HEADER)
        self._truth_of = truth_of
        self._truth = (_open_csv(self.folder / "truth.csv", TRUTH_HEADER)
                       if truth or truth_of is not None else None)
        self.count = 0

    def write(self, frame: Frame) -> None:
        """Store one frame: its PNG first, then its row (flushed)."""
        name = frame_name(self.count)
        path = self.folder / "frames" / name
        tmp = path.with_name("." + name)
        try:
            ok = cv2.imwrite(str(tmp), frame.image)
        except cv2.error:  # an empty or non-image array
            ok = False
        if not ok:
            shape = getattr(frame.image, "shape", None)
            raise OutputError(tmp, f"cannot write the frame image (shape {shape})")
        try:
            os.replace(tmp, path)
            self._frames[1].writerow([self.count, int(frame.t_ns)])
            self._frames[0].flush()
        except OSError as exc:
            raise OutputError(path, f"cannot write: {exc.strerror or exc}") from None
        self.count += 1
        pose = self._truth_of.lookup(frame.t_ns) if self._truth_of is not None else None
        if pose is not None:
            self.write_truth(frame.t_ns, *pose)

    def write_truth(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        """One ``truth.csv`` row (the vehicle pose in W at ``t_ns``), flushed."""
        if self._truth is None:
            self._truth = _open_csv(self.folder / "truth.csv", TRUTH_HEADER)
        path = self.folder / "truth.csv"
        try:
            self._truth[1].writerow([int(t_ns), f"{x_m:.6f}", f"{y_m:.6f}",
                                     f"{math.degrees(yaw_rad):.6f}"])
            self._truth[0].flush()
        except OSError as exc:
            raise OutputError(path, f"cannot write: {exc.strerror or exc}") from None

    def close(self) -> None:
        for fh in (self._frames, self._truth):
            if fh is not None and not fh[0].closed:
                fh[0].close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_csv(path: Path, header: list[str]):
    try:
        fh = open(path, "w", newline="", encoding="utf-8")
    except OSError as exc:
        raise OutputError(path, f"cannot write: {exc.strerror}") from None
    w = csv.writer(fh, lineterminator="\n")
    try:
        w.writerow(header)
        fh.flush()
    except OSError as exc:
        with contextlib.suppress(OSError):
            fh.close()
        raise OutputError(path, f"cannot write: {exc.strerror or exc}") from None
    return fh, w


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth rows: ``t_ns`` (N,), ``x_m``, ``y_m``, ``yaw_rad`` (N,)."""

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray

    def lookup(self, t_ns: int) -> tuple[float, float, float] | None:
        """The truth row with exactly this stamp, or ``None``."""
        i = int(np.searchsorted(self.t_ns, t_ns))
        if i < self.t_ns.size and self.t_ns[i] == t_ns:
            return float(self.x_m[i]), float(self.y_m[i]), float(self.yaw_rad[i])
        return None


@dataclass(frozen=True, eq=False)
class Odometry:
    """Wheel odometry rows of ``odometry.csv`` (SPEC §2), in time order.

    Attributes:
        t_ns: ``(N,)`` int64 stamps, strictly increasing.
        dx_m, dy_m: ``(N,)`` the vehicle's displacement in V since the previous row, m.
        dyaw_rad: ``(N,)`` its turn since the previous row, rad (counter-clockwise).
    """

    t_ns: np.ndarray
    dx_m: np.ndarray
    dy_m: np.ndarray
    dyaw_rad: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.size)


def _read_csv(path: Path, header: list[str]) -> list[list[str]]:
    try:
        # utf-8-sig: a byte-order mark (spreadsheets write one) is not part of the header
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(path, None, f"cannot read: {exc}") from None
    if not rows or [c.strip() for c in rows[0]] != header:
        found = ",".join(rows[0]) if rows else "an empty file"
        raise ConfigError(path, "header", f"expected `{','.join(header)}`, found `{found}`")
    out = []
    for n, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ConfigError(path, f"line {n}",
                              f"expected {len(header)} fields, found {len(row)}")
        out.append([c.strip() for c in row])
    return out


def _int(path: Path, line: int, col: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ConfigError(path, f"line {line}: {col}",
                          f"expected an integer, found {text!r}") from None


def _float(path: Path, line: int, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise ConfigError(path, f"line {line}: {col}", f"expected a number, found {text!r}")
    return v


def _stamps(path: Path, rows: list[list[str]]) -> np.ndarray:
    """Column 0 of ``rows`` as int64 ``t_ns`` (line numbers from 2 in errors)."""
    t = [_int(path, i + 2, "t_ns", r[0]) for i, r in enumerate(rows)]
    for i, v in enumerate(t):
        if not -(2**63) <= v < 2**63:
            raise ConfigError(path, f"line {i + 2}: t_ns", f"expected a 64-bit stamp in ns, "
                              f"found {v}")
    return np.array(t, dtype=np.int64)


def _stamped_rows(path: Path, header: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A ``t_ns`` + three numbers table: ``(t_ns (N,) int64, values (N, 3))``."""
    rows = _read_csv(path, header)
    t_ns = _stamps(path, rows)
    vals = np.array([[_float(path, i + 2, c, r[k]) for k, c in enumerate(header[1:], 1)]
                     for i, r in enumerate(rows)], dtype=float).reshape(-1, 3)
    return t_ns, vals


def load_odometry(path: str | Path) -> Odometry:
    """Read ``odometry.csv`` (``t_ns,dx,dy,dyaw_deg``) strictly: the exact header, one
    integer stamp and three finite numbers a row, stamps strictly increasing.

    Raises:
        ConfigError: naming the file, the line and the column.
    """
    path = Path(path)
    t, vals = _stamped_rows(path, ODOMETRY_HEADER)
    if t.size > 1 and np.any(np.diff(t) <= 0):
        bad = int(np.argmax(np.diff(t) <= 0)) + 3
        raise ConfigError(path, f"line {bad}: t_ns", "stamps must increase")
    return Odometry(t, vals[:, 0], vals[:, 1], np.radians(vals[:, 2]))


def load_truth(path: str | Path) -> Truth:
    """Read ``truth.csv`` (``t_ns,x,y,yaw_deg``), sorted by time."""
    path = Path(path)
    t, vals = _stamped_rows(path, TRUTH_HEADER)
    order = np.argsort(t, kind="stable")
    return Truth(t[order], vals[order, 0], vals[order, 1], np.radians(vals[order, 2]))


def check_frame_image(image: np.ndarray, path: str | Path, rig: Rig) -> None:
    """Raise a ConfigError naming ``path`` unless ``image`` is what SPEC §2 allows and
    the rig's camera expects: 8-bit grey ``(H, W)`` or BGR ``(H, W, 3)``, ``W x H`` the
    camera's ``image_width x image_height``."""
    if image.dtype != np.uint8:
        raise ConfigError(path, None, f"expected an 8-bit image, found {image.dtype} "
                          "(convert to 8-bit grey or BGR)")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        what = f"{image.shape[2]} channels" if image.ndim == 3 else f"{image.ndim} dimensions"
        raise ConfigError(path, None, f"expected grey or BGR, found {what}")
    h, w = image.shape[:2]
    cam = rig.camera
    if (w, h) != (cam.width, cam.height):
        raise ConfigError(path, None, f"the image is {w}x{h} but the camera "
                          f"({rig.camera_file or rig.source or 'the rig'}) is "
                          f"{cam.width}x{cam.height}: a frame must come from the calibrated "
                          "camera at its calibrated size")


class Recording(SourceBase):
    """A SPEC recording opened for reading; also a frame source.

    The whole folder is checked when opened: ``frames.csv`` header and rows, every
    frame file present, stamps increasing, ``rig.yaml`` and ``site.yaml`` valid
    (unless ``rig``/``site`` override them), ``truth.csv`` and ``odometry.csv`` when
    present (``truth``, ``odometry``: ``None`` when absent).
    """

    live = False  # stored stamps: the live loop stamps frames with its own clock
    dropped = 0

    def __init__(self, folder: str | Path, rig: Rig | str | Path | None = None,
                 site: Site | str | Path | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ConfigError(self.folder, None, "not a recording folder (not found)")
        fpath = self.folder / "frames.csv"
        rows = _read_csv(fpath, FRAMES_HEADER)
        index, t_ns = [], []
        for n, r in enumerate(rows, start=2):
            index.append(_int(fpath, n, "index", r[0]))
            t_ns.append(_int(fpath, n, "t_ns", r[1]))
        seen: dict[int, int] = {}
        for n, i in enumerate(index, start=2):
            if i < 0:
                raise ConfigError(fpath, f"line {n}: index", f"expected an integer >= 0, "
                                  f"found {i}")
            if i in seen:
                raise ConfigError(fpath, f"line {n}: index",
                                  f"index {i} already listed on line {seen[i]}")
            seen[i] = n
        self.index = np.array(index, dtype=np.int64)
        self.t_ns = np.array(t_ns, dtype=np.int64)
        if self.t_ns.size > 1 and np.any(np.diff(self.t_ns) <= 0):
            bad = int(np.argmax(np.diff(self.t_ns) <= 0)) + 3
            raise ConfigError(fpath, f"line {bad}: t_ns", "stamps must increase")
        for n, i in enumerate(self.index, start=2):
            if not (self.folder / "frames" / frame_name(int(i))).exists():
                raise ConfigError(fpath, f"line {n}",
                                  f"frame file frames/{frame_name(int(i))} is missing")
        self.rig = rig if isinstance(rig, Rig) else Rig.load(
            rig if rig is not None else self.folder / "rig.yaml")
        self.site = site if isinstance(site, Site) else Site.load(
            site if site is not None else self.folder / "site.yaml")
        tpath = self.folder / "truth.csv"
        self.truth = load_truth(tpath) if tpath.exists() else None
        opath = self.folder / "odometry.csv"
        self.odometry = load_odometry(opath) if opath.exists() else None
        self._i = 0

    def __len__(self) -> int:
        return int(self.index.size)

    def frame(self, k: int) -> Frame:
        """The k-th frame listed in ``frames.csv``."""
        i = int(self.index[k])
        path = self.folder / "frames" / frame_name(i)
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ConfigError(path, None, "cannot decode the image (corrupt or not a PNG)")
        check_frame_image(image, path, self.rig)
        return Frame(image, int(self.t_ns[k]), i)

    def read(self) -> Frame | None:
        if self._i >= len(self):
            return None
        f = self.frame(self._i)
        self._i += 1
        return f


# --------------------------------------------------------------------------- poses
def _fmt(v: float | None, digits: int) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def pose_sigmas(est: PoseEstimate) -> tuple[float | None, float | None, float | None]:
    """``(sigma_x_m, sigma_y_m, sigma_yaw_deg)``: the 1-sigma of the pose in W from the
    diagonal of ``est.cov``; ``None`` for a term that is unobserved (infinite), not a
    number, or without a covariance."""
    cov = est.cov
    if cov is None:
        return None, None, None
    diag = np.diagonal(np.asarray(cov, dtype=float))
    out = [math.sqrt(v) if math.isfinite(v) and v >= 0 else None for v in diag[:3]]
    yaw = None if out[2] is None else math.degrees(out[2])
    return out[0], out[1], yaw


def pose_row(est: Estimate, latency_ms: float | None) -> list[str]:
    """One ``poses.csv`` row; a failure keeps its time and method, pose fields empty."""
    lat = _fmt(latency_ms, 3)
    if isinstance(est, PoseEstimate):
        sx, sy, syaw = pose_sigmas(est)
        return [str(int(est.t_ns)), _fmt(est.x_m, 6), _fmt(est.y_m, 6),
                _fmt(math.degrees(est.yaw_rad), 6), _fmt(est.lateral_m, 6), est.method,
                f"{est.quality:.3f}", lat, _fmt(sx, 6), _fmt(sy, 6), _fmt(syaw, 6)]
    return [str(int(est.t_ns)), "", "", "", "", est.method, "0.000", lat, "", "", ""]


def tum_seconds(t_ns: int) -> str:
    """``t_ns`` as decimal seconds with all nine digits, exactly (no float rounding:
    an epoch stamp in float seconds keeps only microseconds)."""
    t = int(t_ns)
    sign, t = ("-", -t) if t < 0 else ("", t)
    return f"{sign}{t // 1_000_000_000}.{t % 1_000_000_000:09d}"


def tum_line(t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> bytes:
    """One TUM row ``t_s x y z qx qy qz qw`` of a planar pose (z = 0, yaw about z)."""
    h = yaw_rad / 2
    return (f"{tum_seconds(t_ns)} {x_m:.6f} {y_m:.6f} 0 0 0 "
            f"{math.sin(h):.9f} {math.cos(h):.9f}\n").encode()


def write_truth_tum(truth: Truth, path: str | Path) -> Path:
    """``truth.csv``'s rows as a TUM trajectory (beside ``poses.tum``, for ``evo_ape``).

    Raises:
        OutputError: the file cannot be written.
    """
    path = Path(path)
    rows = [tum_line(int(t), float(x), float(y), float(a))
            for t, x, y, a in zip(truth.t_ns, truth.x_m, truth.y_m, truth.yaw_rad, strict=True)]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"".join(rows))
    except OSError as exc:
        raise OutputError(path, f"cannot write: {exc.strerror}") from None
    return path


class PoseWriter:
    """Writes ``poses.csv`` (SPEC §2), a row per frame, flushed as it goes;
    optionally a TUM trajectory (``t_s x y z qx qy qz qw``, z = 0, the yaw as a
    quaternion about z) beside it. TUM has no empty field, so it holds only the poses
    with both x and y: failures, and poses that leave a coordinate unobserved (the
    corridor method's, without x), are left out of it rather than given a made-up 0."""

    def __init__(self, path: str | Path, tum_path: str | Path | None = None):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(self.path.parent, f"cannot create: {exc.strerror}") from None
        self._fh, self._w = _open_csv(self.path, POSES_HEADER)
        self.tum_path = None if tum_path is None else Path(tum_path)
        self._tum = None
        if self.tum_path is not None:
            try:
                self._tum = open(self.tum_path, "w", encoding="utf-8")
            except OSError as exc:
                self._fh.close()
                raise OutputError(self.tum_path, f"cannot write: {exc.strerror}") from None

    def write(self, est: Estimate, latency_ms: float | None = None) -> None:
        """One row (flushed), and a TUM line for a pose with x and y.

        Raises:
            OutputError: the file cannot be written (a full disk), naming it.
        """
        try:
            self._w.writerow(pose_row(est, latency_ms))
            self._fh.flush()
        except OSError as exc:
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None
        if self._tum is not None and isinstance(est, PoseEstimate) \
                and est.x_m is not None and est.y_m is not None:
            h = est.yaw_rad / 2
            try:
                self._tum.write(f"{tum_seconds(est.t_ns)} {est.x_m:.6f} {est.y_m:.6f} 0 0 0 "
                                f"{math.sin(h):.9f} {math.cos(h):.9f}\n")
                self._tum.flush()
            except OSError as exc:
                raise OutputError(self.tum_path, f"cannot write: {exc.strerror or exc}") \
                    from None

    def close(self) -> None:
        self._fh.close()
        if self._tum is not None:
            self._tum.close()

    def __enter__(self) -> PoseWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class PoseTable:
    """``poses.csv`` read back; missing fields are NaN (the sigmas too, in a file
    written before SPEC added them)."""

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    lateral_m: np.ndarray
    method: list[str]
    quality: np.ndarray
    latency_ms: np.ndarray
    sigma_x_m: np.ndarray
    sigma_y_m: np.ndarray
    sigma_yaw_rad: np.ndarray


def load_poses(path: str | Path) -> PoseTable:
    """Read ``poses.csv`` by column name (SPEC §2): the SPEC header, or its first eight
    columns alone (a file from before the sigma columns).

    Raises:
        ConfigError: another header, a row of the wrong length, a field that is not a
            number (naming file, line and column).
    """
    path = Path(path)
    try:
        rows = _read_csv(path, POSES_HEADER)
    except ConfigError as exc:
        if exc.key != "header":
            raise
        try:
            rows = [r + [""] * len(POSES_SIGMA_COLUMNS)
                    for r in _read_csv(path, POSES_HEADER[:8])]
        except ConfigError as short:
            if short.key != "header":
                raise
            raise exc from None

    def col(k: int) -> np.ndarray:
        name = POSES_HEADER[k]
        return np.array([_float(path, n, name, r[k]) if r[k] else math.nan
                         for n, r in enumerate(rows, start=2)], dtype=float)

    return PoseTable(_stamps(path, rows), col(1), col(2), np.radians(col(3)), col(4),
                     [r[5] for r in rows], col(6), col(7), col(8), col(9),
                     np.radians(col(10)))
