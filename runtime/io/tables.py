"""The CSV tables of SPEC §2 and the TUM trajectory: ``truth.csv`` (:class:`Truth`),
``odometry.csv`` (:class:`Odometry`), ``poses.csv`` (:class:`PoseWriter` writes it
row by row, :func:`load_poses` reads it back as a :class:`PoseTable`), and the
strict readers they share (the exact header, typed fields, errors naming the file,
the line and the column).
"""

from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.inputs import CSV_MAX_BYTES, read_input
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.io.files import OS_DISK, AppendFile, CsvFile, Disk, output_error
from ceilkit.runtime.io.provenance import RUN_METADATA, run_metadata, version_line

log = logging.getLogger(__name__)

FRAMES_HEADER = ["index", "t_ns"]
TRUTH_HEADER = ["t_ns", "x", "y", "yaw_deg"]
ODOMETRY_HEADER = ["t_ns", "dx", "dy", "dyaw_deg"]
POSES_HEADER = ["t_ns", "x", "y", "yaw_deg", "lateral", "method", "quality", "latency_ms",
                "sigma_x", "sigma_y", "sigma_yaw_deg"]
POSES_SIGMA_COLUMNS = POSES_HEADER[8:]
"""The columns SPEC §2 added after the first eight; a file without them still reads."""


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


def read_rows(path: Path, header: list[str]) -> list[list[str]]:
    """The rows of the CSV file ``path`` after its ``header`` (exact), each of
    ``len(header)`` stripped fields; blank lines skipped. The file is a regular file
    of at most :data:`~ceilkit.runtime.config.inputs.CSV_MAX_BYTES`.

    Raises:
        ConfigError: naming the file (and the line): not readable, not UTF-8, another
            header, a row of another length, a line CSV cannot parse.
    """
    data = read_input(path, CSV_MAX_BYTES)
    try:
        # utf-8-sig: a byte-order mark (spreadsheets write one) is not part of the header
        reader = csv.reader(io.StringIO(data.decode("utf-8-sig"), newline=""))
        rows = list(reader)
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(path, f"line {line}", f"not UTF-8 text: byte "
                          f"0x{data[exc.start]:02x} (save the file as UTF-8)") from None
    except csv.Error as exc:
        raise ConfigError(path, f"line {reader.line_num}", f"not CSV: {exc}") from None
    if not rows or [c.strip() for c in rows[0]] != header:
        found = ",".join(rows[0]) if rows else "an empty file"
        found = found if len(found) <= 80 else f"{found[:60]}... ({len(found)} characters)"
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


FIELD_LIMIT = 1e9
"""The largest magnitude of a number a table may hold unless its reader says less:
numbers are bounded before any arithmetic (no overflow to infinity downstream)."""

TRUTH_LIMITS = (1e6, 1e6, 1e6)
"""``truth.csv``: |x|, |y| in m, |yaw_deg| (a yaw may be unwrapped)."""

ODOMETRY_LIMITS = (1e3, 1e3, 3600.0)
"""``odometry.csv``: the largest increment of a row, |dx|, |dy| in m and |dyaw_deg|."""


def _shown(text: str) -> str:
    return repr(text) if len(text) <= 40 else f"{text[:20]!r}... ({len(text)} characters)"


def int_field(path: Path, line: int, col: str, text: str) -> int:
    if len(text) > 40:   # Python refuses to convert more than 4300 digits; 20 is int64
        raise ConfigError(path, f"line {line}: {col}",
                          f"expected an integer, found {_shown(text)}")
    try:
        return int(text)
    except ValueError:
        raise ConfigError(path, f"line {line}: {col}",
                          f"expected an integer, found {_shown(text)}") from None


def float_field(path: Path, line: int, col: str, text: str,
                limit: float = FIELD_LIMIT) -> float:
    """``text`` as a number of magnitude at most ``limit``."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise ConfigError(path, f"line {line}: {col}", f"expected a number, found "
                                                       f"{_shown(text)}")
    if abs(v) > limit:
        raise ConfigError(path, f"line {line}: {col}", f"expected a number in "
                          f"[-{limit:g}, {limit:g}], found {_shown(text)}")
    return v


def stamp_column(path: Path, rows: list[list[str]]) -> np.ndarray:
    """Column 0 of ``rows`` as int64 ``t_ns`` (line numbers from 2 in errors)."""
    t = [int_field(path, i + 2, "t_ns", r[0]) for i, r in enumerate(rows)]
    for i, v in enumerate(t):
        if not -(2**63) <= v < 2**63:
            raise ConfigError(path, f"line {i + 2}: t_ns", f"expected a 64-bit stamp in ns, "
                              f"found {v}")
    return np.array(t, dtype=np.int64)


def stamped_rows(path: Path, header: list[str],
                 limits: tuple[float, float, float] = (FIELD_LIMIT,) * 3,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A ``t_ns`` + three numbers table: ``(t_ns (N,) int64, values (N, 3))``, each
    number of magnitude at most its column's ``limits``; stamps strictly increasing
    (rows in time order).

    Raises:
        ConfigError: naming the file, the line and the column.
    """
    rows = read_rows(path, header)
    t_ns = stamp_column(path, rows)
    vals = np.array([[float_field(path, i + 2, c, r[k], limits[k - 1])
                      for k, c in enumerate(header[1:], 1)]
                     for i, r in enumerate(rows)], dtype=float).reshape(-1, 3)
    if t_ns.size > 1 and np.any(np.diff(t_ns) <= 0):
        bad = int(np.argmax(np.diff(t_ns) <= 0)) + 3
        raise ConfigError(path, f"line {bad}: t_ns", f"stamps must increase (rows in time "
                          f"order), found {t_ns[bad - 2]} after {t_ns[bad - 3]}")
    return t_ns, vals


def load_odometry(path: str | Path) -> Odometry:
    """Read ``odometry.csv`` (``t_ns,dx,dy,dyaw_deg``) strictly: the exact header, one
    integer stamp and three finite numbers a row (within :data:`ODOMETRY_LIMITS`),
    stamps strictly increasing.

    Raises:
        ConfigError: naming the file, the line and the column.
    """
    path = Path(path)
    t, vals = stamped_rows(path, ODOMETRY_HEADER, ODOMETRY_LIMITS)
    return Odometry(t, vals[:, 0], vals[:, 1], np.radians(vals[:, 2]))


def load_truth(path: str | Path) -> Truth:
    """Read ``truth.csv`` (``t_ns,x,y,yaw_deg``) strictly: rows in time order (a row out
    of order is an error, never sorted silently), numbers within :data:`TRUTH_LIMITS`.

    Raises:
        ConfigError: naming the file, the line and the column.
    """
    path = Path(path)
    t, vals = stamped_rows(path, TRUTH_HEADER, TRUTH_LIMITS)
    return Truth(t, vals[:, 0], vals[:, 1], np.radians(vals[:, 2]))


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
        path.write_bytes(TUM_HEADER + b"".join(rows))
    except OSError as exc:
        raise OutputError(path, f"cannot write: {exc.strerror}") from None
    return path


TUM_HEADER = f"# t_s x y z qx qy qz qw; written by {version_line()}\n".encode()
"""The first line of a TUM file ceilkit writes (a ``#`` comment: evo and the TUM tools
skip it)."""


class PoseWriter:
    """Writes ``poses.csv`` (SPEC §2), a row per frame, each row one whole write (never
    cut by a full disk); optionally a TUM trajectory (``t_s x y z qx qy qz qw``, z = 0,
    the yaw as a quaternion about z; its first line the comment :data:`TUM_HEADER`)
    beside it. TUM has no empty field, so it holds only
    the poses with both x and y: failures, and poses that leave a coordinate unobserved
    (the corridor method's, without x), are left out of it rather than given a made-up 0.
    ``poses.csv``'s first line is its SPEC header, with no room for a comment: a
    ``run.yaml`` beside it (:func:`~ceilkit.runtime.io.provenance.run_metadata`) names the
    version that wrote the folder, the time and the command line.

    Args:
        path, tum_path: the files (created or truncated).
        disk: how they are written (a fake in tests).
    """

    def __init__(self, path: str | Path, tum_path: str | Path | None = None,
                 disk: Disk = OS_DISK):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(self.path.parent, f"cannot create: {exc.strerror}") from None
        self._csv = CsvFile(self.path, POSES_HEADER, disk)
        self.rows = 0
        self.tum_left_out = 0   # poses TUM cannot hold (no x): said in one line at close
        self.tum_path = None if tum_path is None else Path(tum_path)
        self._tum = None
        self.metadata_path = self.path.parent / RUN_METADATA
        try:
            if self.tum_path is not None:
                self._tum = AppendFile(self.tum_path, disk, header=TUM_HEADER)
            disk.replace_file(self.metadata_path, run_metadata(
                f"{self.path.name}, written row by row").encode())
        except OSError as exc:
            self.close()
            raise output_error(self.metadata_path, exc) from None
        except OutputError:
            self.close()
            raise

    def write(self, est: Estimate, latency_ms: float | None = None) -> None:
        """One row, and a TUM line for a pose with x and y.

        Raises:
            OutputError: the file cannot be written (a full disk: ``errno`` ENOSPC),
                naming it; nothing of the row was written.
        """
        self._csv.row(pose_row(est, latency_ms))
        self.rows += 1
        if self._tum is not None and isinstance(est, PoseEstimate) \
                and est.x_m is not None and est.y_m is not None:
            self._tum.append([tum_line(est.t_ns, est.x_m, est.y_m, est.yaw_rad)])
        elif self._tum is not None and isinstance(est, PoseEstimate):
            self.tum_left_out += 1

    def close(self) -> None:
        self._csv.close()
        if getattr(self, "tum_left_out", 0):
            log.warning("%s: %d poses without x (the method observes y and the heading "
                        "only) are not in it, TUM having no empty field; their lateral "
                        "errors are in %s and the report", self.tum_path,
                        self.tum_left_out, self.path.name)
            self.tum_left_out = 0
        if getattr(self, "_tum", None) is not None:
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
        rows = read_rows(path, POSES_HEADER)
    except ConfigError as exc:
        if exc.key != "header":
            raise
        try:
            rows = [r + [""] * len(POSES_SIGMA_COLUMNS)
                    for r in read_rows(path, POSES_HEADER[:8])]
        except ConfigError as short:
            if short.key != "header":
                raise
            raise exc from None

    def col(k: int) -> np.ndarray:
        name = POSES_HEADER[k]
        return np.array([float_field(path, n, name, r[k]) if r[k] else math.nan
                         for n, r in enumerate(rows, start=2)], dtype=float)

    return PoseTable(stamp_column(path, rows), col(1), col(2), np.radians(col(3)), col(4),
                     [r[5] for r in rows], col(6), col(7), col(8), col(9),
                     np.radians(col(10)))
