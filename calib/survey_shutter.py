"""The survey's frames put back to a global shutter at their stamps (docs/survey.md,
"Rolling shutter").

A rolling-shutter camera exposes row ``v`` at ``tau(v)`` after the frame's stamp
(:func:`~ceilkit.runtime.geometry.shutter.row_times_s`: the readout time from the top
row to the bottom). A ceiling point at ``q'`` in the stamp's V is seen by its row from
the pose at ``t + tau``: at a constant velocity ``(u, w)`` (``u`` m/s in V, ``w`` rad/s)
the vehicle has moved by ``u tau`` and turned by ``w tau``, so the row sees the point at

    q = R(-w tau) (q' - u tau)          (first order in tau)

of the moved vehicle's frame. Driving at speed ``s`` along the image's columns, this
shrinks every frame along the travel by ``s readout / L`` (``L`` the view's length on
the ceiling along the columns): on the office rig (V's x along the image's rows'
order, L 2.36 m) 0.53 % at 0.5 m/s and a 25 ms readout. The ceiling-plane odometry's
steps and the place matches between keyframes shrink with it, and so would the whole
survey: a loop's closures do not see a scale, and each feature is off by up to
``s readout / 2`` besides.

:class:`GlobalShutter` resamples a frame into the image a global shutter at the stamp
would have taken of the ceiling plane: output pixel ``p0`` sees the ceiling point
``q'(p0)``; it is read from the frame where its row saw that point,
``p0 + J (q - q')`` (``J`` the pixel's derivative by the ceiling point: the move is a
few pixels), ``tau`` taken at that row (two fixed-point steps). Whatever is not on the
ceiling plane (a person, a pendant) is resampled as if it were. The velocity is the
survey's own: :func:`chain_velocities`, from the chained poses of the frames around.

Example::

    gs = GlobalShutter.of(rig, 2.7, 25.0)                   # None for readout 0
    v = chain_velocities(segment.chain, rec.t_ns[segment.frames])
    grey_at_stamp = gs(grey, v[i])                          # (u_x, u_y, w) in V
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ceilkit.runtime.features.grey import to_grey
from ceilkit.runtime.geometry.ceiling import ceiling_points, pixel_jacobian
from ceilkit.runtime.geometry.shutter import row_times_s


@dataclass(frozen=True, eq=False)
class GlobalShutter:
    """One rig's resampling to a global shutter (module docstring).

    Attributes:
        readout_s: the readout time, top row to bottom row, s (> 0).
        shape: ``(height, width)`` of the frames, px.
        index: ``(M,)`` flat indices of the output pixels that see the ceiling.
        px0: ``(M, 2)`` those pixels ``(u, v)``.
        q: ``(M, 2)`` the ceiling points they see in V, m.
        jac: ``(M, 2, 2)`` d(pixel)/d(ceiling point) there, px/m.
    """

    readout_s: float
    shape: tuple[int, int]
    index: np.ndarray
    px0: np.ndarray
    q: np.ndarray
    jac: np.ndarray

    @classmethod
    def of(cls, rig: Any, ceiling_m: float, readout_ms: float) -> GlobalShutter | None:
        """The resampling for ``rig`` under a ceiling ``ceiling_m`` above the floor, or
        None for a global shutter (``readout_ms`` 0)."""
        if readout_ms <= 0:
            return None
        cam, mount = rig.camera, rig.mount
        R = np.asarray(mount.R_vehicle_cam, float)
        t = np.asarray(mount.t_vehicle_cam, float)
        h, w = int(cam.height), int(cam.width)
        vv, uu = np.mgrid[0:h, 0:w]
        px = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
        q, ok = ceiling_points(cam.unproject(px), R, t, float(ceiling_m) - float(t[2]))
        jac = pixel_jacobian(cam, R, t, float(ceiling_m), q[ok])
        good = np.all(np.isfinite(jac.reshape(len(jac), -1)), axis=1)
        index = np.flatnonzero(ok)[good]
        return cls(readout_ms / 1e3, (h, w), index, px[index], q[ok][good], jac[good])

    def source_px(self, velocity: tuple[float, float, float]) -> np.ndarray:
        """``(M, 2)`` where the frame holds each output pixel's ceiling point under
        ``velocity`` ``(u_x m/s, u_y m/s, w rad/s)`` in V (module docstring)."""
        ux, uy, w = (float(v) for v in velocity)
        h = self.shape[0]
        tau = row_times_s(self.px0[:, 1], h, self.readout_s)
        p = self.px0
        for _ in range(2):
            c, s = np.cos(w * tau), np.sin(w * tau)
            dx, dy = self.q[:, 0] - ux * tau, self.q[:, 1] - uy * tau
            move = np.column_stack([c * dx + s * dy - self.q[:, 0],
                                    -s * dx + c * dy - self.q[:, 1]])
            p = self.px0 + np.einsum("nij,nj->ni", self.jac, move)
            tau = row_times_s(p[:, 1], h, self.readout_s)
        return p

    def __call__(self, grey: np.ndarray, velocity: tuple[float, float, float]
                 ) -> np.ndarray:
        """``grey`` (``shape``, uint8) as a global shutter at its stamp would have seen
        the ceiling, the vehicle moving at ``velocity`` (V; a zero velocity returns
        ``grey``)."""
        if not any(float(v) for v in velocity):
            return grey
        h, w = self.shape
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
        p = self.source_px(velocity).astype(np.float32)
        uu.ravel()[self.index] = p[:, 0]
        vv.ravel()[self.index] = p[:, 1]
        return cv2.remap(grey, uu, vv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@dataclass(frozen=True, eq=False)
class SurveyFrames:
    """The recordings' frames as the survey reads them: grey, and with ``shutter`` each
    put back to its stamp at its ``velocity`` (by ``(drive, frame)``; a frame without
    one is read as recorded).

    Attributes:
        recordings: the drives, in the survey's order.
        shutter: the resampling, or None (a global shutter).
        velocity: ``(u_x m/s, u_y m/s, w rad/s)`` in V by ``(drive, frame)``.
    """

    recordings: Sequence[Any]
    shutter: GlobalShutter | None = None
    velocity: Mapping[tuple[int, int], tuple[float, float, float]] = field(
        default_factory=dict)

    def prepare(self, drive: int, k: int, grey: np.ndarray) -> np.ndarray:
        """Frame ``k`` of drive ``drive``, already grey, as the survey reads it."""
        v = self.velocity.get((drive, k)) if self.shutter is not None else None
        return grey if v is None else self.shutter(grey, v)

    def grey(self, drive: int, k: int) -> np.ndarray:
        """Frame ``k`` of drive ``drive`` as the survey reads it."""
        return self.prepare(drive, k, to_grey(self.recordings[drive].frame(k).image))


def chain_velocities(chain: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """``(n, 3)`` each pose's velocity ``(u_x m/s, u_y m/s, w rad/s)`` in its own V from
    a chain of poses ``(n, 3)`` (any frame; m, m, rad) at stamps ``t_ns`` ``(n,)``: the
    motion from the pose before to the pose after (central differences; one-sided at
    the ends; zero for a chain of one pose)."""
    chain = np.asarray(chain, float)
    n = len(chain)
    out = np.zeros((n, 3))
    if n < 2:
        return out
    k = np.arange(n)
    a, b = np.maximum(k - 1, 0), np.minimum(k + 1, n - 1)
    dt = (np.asarray(t_ns, np.int64)[b] - np.asarray(t_ns, np.int64)[a]) / 1e9
    dt = np.where(dt > 0, dt, np.nan)
    d = chain[b, :2] - chain[a, :2]
    c, s = np.cos(chain[:, 2]), np.sin(chain[:, 2])
    out[:, 0] = (c * d[:, 0] + s * d[:, 1]) / dt
    out[:, 1] = (-s * d[:, 0] + c * d[:, 1]) / dt
    out[:, 2] = np.remainder(chain[b, 2] - chain[a, 2] + math.pi, 2 * math.pi) - math.pi
    out[:, 2] /= dt
    return np.nan_to_num(out)


__all__ = ["GlobalShutter", "SurveyFrames", "chain_velocities"]
