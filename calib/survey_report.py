"""The survey's report: ``survey.md`` (every place match, the residuals, each section's
σ) and ``survey.png`` (the mosaic, the solved path, the chain before the solve and the
closures; matplotlib's Agg backend, skipped when matplotlib is not installed)."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.yaml import atomic_write_bytes
from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap

from .lightmap import LightMap
from .survey import CLOSURE_KINDS, SurveyResult


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def report_lines(res: SurveyResult, cmap: CeilingMap, lights: LightMap | None, note: str,
                 png: bool) -> list[str]:
    """``survey.md``'s lines."""
    closures = [lk for lk in res.links if lk.kind != "link"]
    moved = np.hypot(*(res.poses[:, :2] - res.chain[:, :2]).T)
    refused = ", ".join(f"{k} {v}" for k, v in sorted(res.refused.items()))
    out = ["# Survey", "",
           f"Drives: {', '.join(res.drives)}; {len(res.poses)} frames placed, "
           f"{res.unplaced} not placed ({res.unplaced_pieces} pieces of the drive that no "
           f"closure tied to the anchor's: not in the map); ceiling height "
           f"{res.ceiling_height_m:g} m; anchor: {res.anchor}.",
           "", "## Graph", "",
           f"Edges: {', '.join(f'{k} {v}' for k, v in sorted(res.edge_kinds.items()))}; "
           f"solved in {res.solve_s:.3f} s ({res.iterations} iterations).",
           f"Consecutive-frame residuals (sigmas): median {_pct(res.odometry_whitened, 50):.2f}, "
           f"95th percentile {_pct(res.odometry_whitened, 95):.2f}, max "
           f"{np.max(res.odometry_whitened, initial=0):.2f}.",
           f"The solve moved the chained poses by {1e3 * _pct(moved, 50):.1f} mm median, "
           f"{1e3 * np.max(moved, initial=0):.1f} mm at most (the chain's drift that the "
           "closures corrected).",
           f"Refused place matches: {refused or 'none'}.",
           "", "## Closures", "", "Loop and drive closures, and the gaps of the chain matched "
           "across (kind `gap`: a break bridged by frames a few steps apart), and the "
           "pieces joined (kind `piece`: a keyframe matched against the whole other piece, "
           "agreeing with others).", "",
           "| a | b | kind | dx m | dy m | dyaw deg | inliers | runner-up | residual (sigmas) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for lk in closures:
        out.append(f"| {lk.a} | {lk.b} | {lk.kind} | {lk.z[0]:.4f} | {lk.z[1]:.4f} | "
                   f"{math.degrees(lk.z[2]):.3f} | {lk.inliers} | {lk.runner_up} | "
                   f"{lk.whitened:.2f} |")
    links = [lk.whitened for lk in res.links if lk.kind == "link"]
    out += ["", f"Keyframe links: {len(links)}, residual median {_pct(np.array(links), 50):.2f}"
            f" sigmas, max {max(links, default=0):.2f}.", "", "## Sections and their 1-sigma",
            "", f"- `ceiling_map`: {cmap.feature_count} features; per-axis 1-sigma median "
            f"{1e3 * _pct(cmap.sigma_m, 50):.2f} mm, 95th percentile "
            f"{1e3 * _pct(cmap.sigma_m, 95):.2f} mm, max "
            f"{1e3 * np.max(cmap.sigma_m, initial=0):.2f} mm (every feature's in "
            "`ceiling_map.npz`, `sigma_m`); keyframe poses' 1-sigma relative to the anchor "
            f"up to {1e3 * float(np.nanmax(res.sigma[res.keys, :2])):.2f} mm."]
    out += [f"- **Warning**: {res.unchecked}."] if res.unchecked else []
    if lights is None:
        out.append(f"- `lights`: none ({note}).")
    else:
        out.append(f"- `lights`: {len(lights.lights_m)}" + (f" ({note})" if note else "")
                   + ":")
        out += [f"  - ({p[0]:.4f}, {p[1]:.4f}) m: 1-sigma {1e3 * s:.2f} mm, {int(v)} views"
                for p, s, v in zip(lights.lights_m, lights.sigma_m, lights.views, strict=True)]
    if png:
        out += ["", "![the map, the path and the closures](survey.png)"]
    return out


def write_plot(path: Path, res: SurveyResult, cmap: CeilingMap) -> Path | None:
    """``survey.png``, or None when matplotlib is not installed."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    x0, y0, x1, y1 = cmap.extent_xy
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig, ax = plt.subplots(figsize=(12, max(3.0, 12 * aspect)), dpi=100)
    ax.imshow(cmap.mosaic, cmap="gray", origin="lower", extent=(x0, x1, y0, y1))
    ax.plot(res.chain[:, 0], res.chain[:, 1], color="tab:orange", lw=0.8,
            label="chain before the solve")
    ax.plot(res.poses[:, 0], res.poses[:, 1], color="tab:blue", lw=1.0, label="solved path")
    for lk in res.links:
        if lk.kind in CLOSURE_KINDS:
            a, b = res.poses[lk.a], res.poses[lk.b]
            ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:red", lw=0.6)
    ax.plot([], [], color="tab:red", lw=0.6, label="loop / drive closures")
    ax.set_xlabel("x (m, W)")
    ax.set_ylabel("y (m, W)")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path
