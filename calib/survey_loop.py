"""A survey drive's path: a closed loop that comes back over its start.

A survey needs loop closures (docs/survey.md): a drive that passes again under ceiling
it has seen. :func:`loop_trajectory` is the path the tests, the benchmark and the
simulator use for it: a rectangle with rounded corners, driven counter-clockwise,
``laps`` times (a fraction beyond 1 drives on over the start: those frames close
the loop), the heading along the path.

Example::

    traj = loop_trajectory(length_m=8.0, width_m=2.4, laps=1.25, fps=10, speed_mps=0.5)
    simulate_recording(rig, site, traj, "runs/loop", SimOptions(scatter=scene))
"""

from __future__ import annotations

import math

import numpy as np

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.sim.render import Trajectory


def _loop_point(s: np.ndarray, length_m: float, width_m: float, radius_m: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points ``s`` m along the loop (x, y, heading in rad), from the middle of its
    bottom side (y = -width/2) heading +x; counter-clockwise."""
    a, b, r = length_m - 2 * radius_m, width_m - 2 * radius_m, radius_m
    arc = 0.5 * math.pi * r
    legs = [("line", a / 2, (0.0, -width_m / 2), 0.0)]
    corners = [(length_m / 2 - r, -width_m / 2 + r), (length_m / 2 - r, width_m / 2 - r),
               (-length_m / 2 + r, width_m / 2 - r), (-length_m / 2 + r, -width_m / 2 + r)]
    starts = [(length_m / 2, -width_m / 2 + r), (length_m / 2 - r, width_m / 2),
              (-length_m / 2, width_m / 2 - r), (-length_m / 2 + r, -width_m / 2)]
    for k in range(4):
        legs.append(("arc", arc, corners[k], k * 0.5 * math.pi))
        legs.append(("line", b if k % 2 == 0 else a, starts[k], (k + 1) * 0.5 * math.pi))
    legs[-1] = ("line", a / 2, starts[3], 0.0)
    total = sum(leg[1] for leg in legs)
    s = np.mod(s, total)
    x, y, h = np.zeros_like(s), np.zeros_like(s), np.zeros_like(s)
    s0 = 0.0
    for kind, ln, p, yaw in legs:
        m = (s >= s0) & (s < s0 + ln)
        u = s[m] - s0
        if kind == "line":
            x[m], y[m], h[m] = p[0] + u * math.cos(yaw), p[1] + u * math.sin(yaw), yaw
        else:
            ang = yaw - 0.5 * math.pi + u / r
            x[m], y[m], h[m] = p[0] + r * np.cos(ang), p[1] + r * np.sin(ang), ang + 0.5 * math.pi
        s0 += ln
    return x, y, h


def loop_perimeter_m(length_m: float, width_m: float, radius_m: float) -> float:
    """The length of one lap, m."""
    return 2 * (length_m + width_m) - (8 - 2 * math.pi) * radius_m


def loop_trajectory(length_m: float, width_m: float, *, laps: float = 1.2,
                    fps: float = 10.0, speed_mps: float = 0.5, radius_m: float = 0.6,
                    centre_m: tuple[float, float] = (0.0, 0.0)) -> Trajectory:
    """A rounded-rectangle loop ``length_m`` along x by ``width_m`` along y (the path's
    extent, m) centred on ``centre_m``, driven ``laps`` times at ``speed_mps``, one
    frame every ``1 / fps`` s (frame k at ``k / fps`` s), the heading along the path
    (yaw 0 at the start, the middle of the side at the smallest y).

    Raises:
        ConfigError: a size, speed or rate that is not positive and finite, or corners
            (``radius_m``) that do not fit.
    """
    for name, v in (("length_m", length_m), ("width_m", width_m), ("laps", laps),
                    ("fps", fps), ("speed_mps", speed_mps), ("radius_m", radius_m)):
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(None, name, f"expected a positive number, found {v!r}")
    if 2 * radius_m > min(length_m, width_m):
        raise ConfigError(None, "radius_m", f"corners of {radius_m:g} m do not fit a "
                          f"{length_m:g} x {width_m:g} m loop")
    total = laps * loop_perimeter_m(length_m, width_m, radius_m)
    n = int(math.floor(total / speed_mps * fps)) + 1
    t_s = np.arange(n) / fps
    x, y, h = _loop_point(speed_mps * t_s, length_m, width_m, radius_m)
    t_ns = np.rint(t_s * 1e9).astype(np.int64)
    return Trajectory(t_ns, x + centre_m[0], y + centre_m[1], np.unwrap(h))
