"""Vehicle poses at their own stamps (motion capture, a total station, a truth table):
interpolated at the frames' stamps, with a time offset (pose time = frame stamp +
offset).

Example::

    table = load_pose_csv("mocap.csv")            # t_ns,x,y,yaw_deg at 120 Hz
    poses = table.at(recording.t_ns, offset_ns=7e6)  # (N, 3), NaN outside the table
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.inputs import CSV_MAX_BYTES, read_input
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.recording import Truth
from ceilkit.runtime.io.tables import TRUTH_LIMITS


@dataclass(frozen=True, eq=False)
class StampedPoses:
    """Vehicle poses at their own stamps (``t_ns`` int64 increasing, x, y, yaw rad).

    :meth:`at` interpolates (SE(2): position linear, heading along the shorter arc)
    at ``t + offset_ns``; outside the table it returns NaN (no extrapolation).
    """

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray

    def at(self, t_ns: np.ndarray, offset_ns: float = 0.0,
           max_gap_ns: float | None = None) -> np.ndarray:
        """``(N, 3)`` poses at ``t_ns + offset_ns``; NaN rows outside the table (and,
        with ``max_gap_ns``, between two rows further apart than that: a pose is not
        invented across a dropout of the motion capture)."""
        t = np.asarray(t_ns, float) + float(offset_ns)
        tt = self.t_ns.astype(float)
        if tt.size == 1:
            out = np.full((t.size, 3), np.nan)
            hit = t == tt[0]
            out[hit] = [self.x_m[0], self.y_m[0], self.yaw_rad[0]]
            return out
        k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, tt.size - 2)
        a = (t - tt[k]) / (tt[k + 1] - tt[k])
        dyaw = np.angle(np.exp(1j * (self.yaw_rad[k + 1] - self.yaw_rad[k])))
        out = np.stack([self.x_m[k] + a * (self.x_m[k + 1] - self.x_m[k]),
                        self.y_m[k] + a * (self.y_m[k + 1] - self.y_m[k]),
                        self.yaw_rad[k] + a * dyaw], axis=1)
        out[(t < tt[0]) | (t > tt[-1])] = np.nan
        if max_gap_ns is not None:
            gap = (tt[k + 1] - tt[k]) > max_gap_ns
            out[gap & (t != tt[k]) & (t != tt[k + 1])] = np.nan
        return out

    def exact(self, t_ns: np.ndarray) -> bool:
        """True when every stamp of ``t_ns`` is a row of the table."""
        t = np.asarray(t_ns, np.int64)
        return bool(np.isin(t, self.t_ns).all())

    @classmethod
    def from_truth(cls, truth: Truth) -> StampedPoses:
        """The table of a recording's ``truth.csv`` (or any :class:`Truth`)."""
        return cls(np.asarray(truth.t_ns, np.int64), np.asarray(truth.x_m, float),
                   np.asarray(truth.y_m, float), np.asarray(truth.yaw_rad, float))


def load_pose_csv(path) -> StampedPoses:
    """A pose table from a ``t_ns,x,y,yaw_deg`` CSV (motion capture, a total station) at
    its own stamps; rows sorted by time.

    Raises:
        ConfigError: the file, naming the row and column that is wrong.
    """
    path = Path(path)
    try:
        text = read_input(path, CSV_MAX_BYTES).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(path, None, "not UTF-8 text (save the file as UTF-8)") from None
    rows = [r for r in text.splitlines() if r.strip() and not r.startswith("#")]
    if not rows or rows[0].replace(" ", "") != "t_ns,x,y,yaw_deg":
        raise ConfigError(path, "header", "expected the header t_ns,x,y,yaw_deg")
    vals = []
    for i, r in enumerate(rows[1:], start=2):
        parts = r.split(",")
        if len(parts) != 4:
            raise ConfigError(path, f"row {i}", f"expected 4 values, found {len(parts)}")
        try:
            v = (int(parts[0]), float(parts[1]), float(parts[2]), float(parts[3]))
        except ValueError:
            raise ConfigError(path, f"row {i}", f"not a number: {r[:80]!r}") from None
        if not (-(2**63) <= v[0] < 2**63 and all(abs(x) <= lim for x, lim
                                                  in zip(v[1:], TRUTH_LIMITS, strict=True))):
            raise ConfigError(path, f"row {i}", f"expected a 64-bit stamp in ns and |x|, |y| "
                              f"(m), |yaw_deg| of at most {TRUTH_LIMITS[0]:g}, found {r[:80]!r}")
        vals.append(v)
    if len(vals) < 2:
        raise ConfigError(path, None, "expected at least two poses")
    a = sorted(vals)
    t = np.array([v[0] for v in a], np.int64)
    if np.any(np.diff(t) <= 0):
        raise ConfigError(path, "t_ns", "two rows have the same stamp")
    return StampedPoses(t, np.array([v[1] for v in a]), np.array([v[2] for v in a]),
                     np.unwrap(np.radians([v[3] for v in a])))


# ------------------------------------------------------------------------------ fit


__all__ = ["StampedPoses", "load_pose_csv"]
