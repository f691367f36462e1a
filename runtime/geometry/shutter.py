"""Rolling shutter: when each image row was exposed, relative to the frame's stamp.

Convention (docs/conventions.md, "Frame stamps"): a frame's ``t_ns`` is the middle of
its centre row's exposure. A rolling-shutter camera reads its rows out one after
another, top to bottom, over the readout time ``readout_s`` (first row to last row);
row ``v`` (pixel coordinate, 0 at the top row's centre) is exposed

    tau(v) = (v / (H - 1) - 1/2) * readout_s

after the stamp (negative: before). ``readout_s = 0`` is a global shutter. The
simulator's ``rolling_shutter_ms`` knob and the estimators' ``readout_ms`` option both
mean this readout time.

With the vehicle's velocity, a feature seen at row ``v`` is seen from the pose at
``t + tau(v)``: :func:`pose_offsets` gives that pose's offset to first order.

Example::

    tau = row_times_s(np.array([0.0, 239.5, 479.0]), 480, 0.025)   # -12.5, 0, +12.5 ms
"""

from __future__ import annotations

import numpy as np


def row_times_s(v_px: np.ndarray, height_px: int, readout_s: float) -> np.ndarray:
    """Exposure time of image rows ``v_px`` (any shape, pixels, may be fractional)
    relative to the frame's stamp, s (same shape): ``(v / (H - 1) - 1/2) readout_s``."""
    v = np.asarray(v_px, dtype=np.float64)
    return (v / max(height_px - 1, 1) - 0.5) * float(readout_s)


def pose_offsets(tau_s: np.ndarray, velocity: tuple[float, float, float]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(dx_m, dy_m, dyaw_rad)`` (each shaped as ``tau_s``): the vehicle's motion in W
    from the stamp to ``t + tau_s`` at constant ``velocity`` ``(vx m/s, vy m/s,
    yaw rate rad/s)`` in W (first order)."""
    tau = np.asarray(tau_s, dtype=np.float64)
    vx, vy, w = (float(v) for v in velocity)
    return vx * tau, vy * tau, w * tau


__all__ = ["row_times_s", "pose_offsets"]
