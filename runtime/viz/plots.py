"""Plots of a replay (and the site map under them), drawn with matplotlib's Agg backend.

matplotlib is an optional dependency (``pip install ceilkit[plots]``; ``.[test]``
installs it) imported only when a plot is drawn (:func:`pyplot`). Every function
returns a finished figure's PNG bytes; axes carry units, colours carry a colour bar or
a legend.

Example::

    png = trajectory_png(site, truth_xy_m, est_xy_m)
    Path("trajectory.png").write_bytes(png)
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError

DPI = 80
"""Dots per inch of every figure (a 7.5 x 4.5 in figure is 600 x 360 px)."""
SIZE_IN = (7.5, 4.5)
TRAJECTORY_MARGIN_M = 1.0
"""The trajectory plot shows the site this far around the drive."""


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend, imported on first use.

    Raises:
        ConfigError: matplotlib is not installed (``plots``: install ``ceilkit[plots]``).
    """
    try:
        import matplotlib
    except ImportError:
        raise ConfigError(None, "plots", "matplotlib is not installed: pip install "
                          "'ceilkit[plots]'") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def figure_png(fig: Any) -> bytes:
    """The figure's PNG bytes; the figure is closed."""
    plt = pyplot()
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


def draw_site(ax: Any, site: Site) -> None:
    """The site map on ``ax`` (W, metres): corridor lines, lamps, lights, blocks, markers."""
    if site.corridor is not None:
        for k, y in enumerate(site.corridor.lines_along_m):
            ax.axhline(y, color="0.6", lw=0.8, label="site lines" if k == 0 else None)
    for k, rect in enumerate(site.lamp_rectangles()):
        r = np.r_[rect, rect[:1]]
        ax.plot(r[:, 0], r[:, 1], color="goldenrod", lw=0.8, label="lamps" if k == 0 else None)
    if len(site.lights_m):
        L = np.asarray(site.lights_m, float)
        ax.scatter(L[:, 0], L[:, 1], marker="+", color="goldenrod", s=30,
                   label="site map's lights")
    quads = [b.corners_m for b in site.blocks]
    if site.markers is not None:
        quads += [m.corners_m() for m in site.markers.poses]
    for k, q in enumerate(quads):
        q = np.r_[np.asarray(q, float), np.asarray(q, float)[:1]]
        ax.plot(q[:, 0], q[:, 1], color="purple", lw=1, label="blocks" if k == 0 else None)


def trajectory_png(site: Site, truth_xy_m: np.ndarray | None, est_xy_m: np.ndarray,
                   quality: np.ndarray, title: str = "trajectory") -> bytes:
    """The estimated positions (coloured by quality) over the site map and the truth.

    Args:
        truth_xy_m: ``(N, 2)`` truth in W, or None. est_xy_m: ``(M, 2)``; a NaN x (the
            corridor method) is drawn at the truth's x of the same frame by the caller.
        quality: ``(M,)`` in [0, 1].
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=SIZE_IN)
    draw_site(ax, site)
    if truth_xy_m is not None and len(truth_xy_m):
        ax.plot(truth_xy_m[:, 0], truth_xy_m[:, 1], color="k", lw=1.2, label="truth")
    if len(est_xy_m):
        sc = ax.scatter(est_xy_m[:, 0], est_xy_m[:, 1], c=quality, cmap="viridis", vmin=0,
                        vmax=1, s=10, label="estimates", zorder=3)
        fig.colorbar(sc, ax=ax, label="quality [0, 1]")
    pts = [a for a in (truth_xy_m, est_xy_m) if a is not None and len(a)]
    if pts:  # the drive, not the whole site, sets the view
        allp = np.concatenate(pts)
        lo, hi = np.nanmin(allp, axis=0) - TRAJECTORY_MARGIN_M, \
            np.nanmax(allp, axis=0) + TRAJECTORY_MARGIN_M
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_xlabel("x in W [m]")
    ax.set_ylabel("y in W [m]")
    ax.set_aspect("equal", adjustable="box" if pts else "datalim")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=7)
    return figure_png(fig)


def errors_png(t_s: np.ndarray, errors: Mapping[str, np.ndarray]) -> bytes:
    """Errors against truth over time: each of ``errors`` (name with its unit -> ``(N,)``);
    one never observed (all NaN: the corridor method's x) is left out."""
    plt = pyplot()
    errors = {k: v for k, v in errors.items() if np.isfinite(v).any()} or errors
    fig, axes = plt.subplots(len(errors), 1, figsize=SIZE_IN, sharex=True, squeeze=False)
    for ax, (name, e) in zip(axes[:, 0], errors.items(), strict=True):
        ax.plot(t_s, e, ".", ms=3)
        ax.axhline(0, color="0.6", lw=0.6)
        ax.set_ylabel(name, fontsize=8)
    axes[-1, 0].set_xlabel("time since the first frame [s]")
    axes[0, 0].set_title("errors against truth.csv")
    return figure_png(fig)


def quality_error_png(quality: np.ndarray, error: np.ndarray, error_name: str) -> bytes:
    """Quality against error (does a low quality flag a bad pose?)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=SIZE_IN)
    ax.plot(error, quality, ".", ms=4)
    ax.set_xlabel(error_name)
    ax.set_ylabel("quality [0, 1]")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("quality against error")
    return figure_png(fig)


def failures_png(t_s: np.ndarray, reasons: Sequence[str]) -> bytes:
    """A timeline: one row per outcome (``ok`` and each failure reason), a tick per frame."""
    plt = pyplot()
    names = sorted(set(reasons), key=lambda r: (r != "ok", r))
    fig, ax = plt.subplots(figsize=(SIZE_IN[0], 0.6 + 0.35 * max(len(names), 1)))
    cmap = plt.get_cmap("tab10")
    ticks = []
    for k, name in enumerate(names):
        t = np.asarray([ts for ts, r in zip(t_s, reasons, strict=True) if r == name])
        ax.scatter(t, np.full(t.size, k), marker="|", s=120, color=cmap(k % 10))
        ticks.append(f"{name} ({t.size})")
    ax.set_yticks(range(len(names)), ticks, fontsize=8)
    ax.set_xlabel("time since the first frame [s]")
    ax.set_title("outcome per frame")
    ax.set_ylim(-0.7, len(names) - 0.3)
    return figure_png(fig)


def histogram_png(values: np.ndarray, xlabel: str, title: str, unit: str = "") -> bytes:
    """A histogram with the median and the 95th percentile marked (their values in the
    legend, with ``unit``)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=SIZE_IN)
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size:
        ax.hist(v, bins=40, color="steelblue")
        for q, name, style in ((50, "median", "-"), (95, "p95", "--")):
            p = float(np.percentile(v, q))
            ax.axvline(p, color="k", ls=style, lw=1, label=f"{name} {p:.3g} {unit}".rstrip())
        ax.legend(fontsize=8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("frames")
    ax.set_title(title)
    return figure_png(fig)


def ellipse_xy(cov_xy: np.ndarray, n_sigma: float = 1.0, n: int = 48) -> np.ndarray:
    """``(n, 2)`` points of the ``n_sigma`` ellipse of a 2x2 covariance (about 0)."""
    w, V = np.linalg.eigh(np.asarray(cov_xy, float))
    a = np.linspace(0, 2 * np.pi, n)
    return (V @ (np.sqrt(np.maximum(w, 0))[:, None] * n_sigma
                 * np.stack([np.cos(a), np.sin(a)]))).T


def lightmap_png(lights_m: np.ndarray, sigma_m: np.ndarray, views: np.ndarray,
                 drive_xy_m: np.ndarray | None, site: Site | None = None) -> bytes:
    """A surveyed light map: each light's 1σ circle (drawn ``gain`` times larger, the
    gain printed), coloured by its σ in mm; the drive the survey came from."""
    plt = pyplot()
    from matplotlib.collections import EllipseCollection
    fig, ax = plt.subplots(figsize=SIZE_IN)
    if site is not None:
        draw_site(ax, site)
    L = np.asarray(lights_m, float).reshape(-1, 2)
    s_mm = 1e3 * np.asarray(sigma_m, float)
    if drive_xy_m is not None and len(drive_xy_m):
        ax.plot(drive_xy_m[:, 0], drive_xy_m[:, 1], color="0.3", lw=1, label="drive")
    span = float(np.ptp(L, axis=0).max()) if len(L) > 1 else 1.0
    gain = 10 ** math.floor(math.log10(max(0.04 * span / max(float(np.max(s_mm, initial=1e-3))
                                                              / 1e3, 1e-6), 1.0)))
    d = 2 * gain * s_mm / 1e3
    ec = EllipseCollection(d, d, np.zeros_like(d), units="xy", offsets=L,
                           offset_transform=ax.transData, array=s_mm, cmap="plasma",
                           facecolors="none", linewidths=1.2)
    ax.add_collection(ec)
    sc = ax.scatter(L[:, 0], L[:, 1], c=s_mm, cmap="plasma", s=8, zorder=3)
    ec.set_clim(*sc.get_clim())
    fig.colorbar(sc, ax=ax, label="light position 1σ [mm]")
    for (x, y), n in zip(L, np.asarray(views, int), strict=True):
        ax.annotate(str(n), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("x in W [m]")
    ax.set_ylabel("y in W [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"surveyed lights: 1σ circles x{gain:g}, labels = views")
    ax.legend(loc="best", fontsize=7)
    return figure_png(fig)


def mount_png(per_placement_rms_px: dict[str, float], rms_px: float,
              outliers: Sequence[str] = ()) -> bytes:
    """The mount fit's residual RMS per placement (px); outliers in red."""
    plt = pyplot()
    names = list(per_placement_rms_px)
    fig, ax = plt.subplots(figsize=(max(SIZE_IN[0], 0.35 * len(names)), SIZE_IN[1]))
    v = [per_placement_rms_px[n] for n in names]
    colours = ["tab:red" if n in set(outliers) else "tab:blue" for n in names]
    ax.bar(range(len(names)), v, color=colours)
    ax.axhline(rms_px, color="k", ls="--", lw=1, label=f"overall RMS {rms_px:.3f} px")
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=7)
    ax.set_ylabel("residual RMS [px]")
    ax.set_xlabel("placement (red: outlier, not used)")
    ax.set_title("mount fit: residual per placement")
    ax.legend(fontsize=8)
    return figure_png(fig)


def with_colour_scale(img: np.ndarray, lut_bgr: np.ndarray, vmin: float, vmax: float,
                      label: str) -> np.ndarray:
    """``img`` (BGR) with a vertical colour bar on its right: ``lut_bgr`` ``(256, 3)``
    from ``vmin`` (bottom) to ``vmax`` (top), five ticks and ``label`` (with its unit).
    Pure OpenCV (for the images the calibration draws itself)."""
    import cv2
    h = img.shape[0]
    bar_w, pad, width = 18, 10, 110
    out = np.full((h, img.shape[1] + width, 3), 255, np.uint8)
    out[:, :img.shape[1]] = img
    top, bottom = 30, h - 20
    idx = np.linspace(255, 0, bottom - top).astype(int)
    x0 = img.shape[1] + pad
    out[top:bottom, x0:x0 + bar_w] = np.asarray(lut_bgr, np.uint8)[idx][:, None, :]
    cv2.rectangle(out, (x0, top), (x0 + bar_w, bottom - 1), (0, 0, 0), 1)
    for k in range(5):
        v = vmin + (vmax - vmin) * k / 4
        y = int(bottom - 1 - (bottom - top - 1) * k / 4)
        cv2.line(out, (x0 + bar_w, y), (x0 + bar_w + 4, y), (0, 0, 0), 1)
        cv2.putText(out, f"{v:.3g}", (x0 + bar_w + 6, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (30, 30, 30), 1, cv2.LINE_AA)
    cv2.putText(out, label, (img.shape[1] + 4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                (30, 30, 30), 1, cv2.LINE_AA)
    return out
