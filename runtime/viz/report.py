"""What a replay shows: overlay PNGs per frame and one self-contained HTML report.

:class:`ReplayViews` is handed each replayed frame (the frame, the estimator's own
estimate, the published one, the latency); it writes overlays
(``OUT/overlays/000123.png``; all frames or only failures and low-quality ones) and
keeps what the report needs: per-frame outcomes and a few frames (by reference) for
the worst frames' overlays. :meth:`ReplayViews.write_report` writes ``report.html``:
plots as embedded PNG (``data:`` URIs), no script, nothing fetched: it opens offline.

Example::

    views = ReplayViews(rig, site, overlays_dir=Path("out/overlays"))
    ...  views.frame(k, image, raw, published, latency_ms) per frame ...
    views.write_report(Path("out/report.html"), truth, "replay of rec")
"""

from __future__ import annotations

import base64
import heapq
import html
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import OutputError
from ceilkit.runtime.estimators.base import (
    AMBIGUOUS,
    Estimate,
    Hypothesis,
    PoseEstimate,
    Provenance,
)
from ceilkit.runtime.geometry.rotations import wrap_pi
from ceilkit.runtime.io.provenance import version_line
from ceilkit.runtime.io.recording import Truth
from ceilkit.runtime.viz import plots
from ceilkit.runtime.viz.overlay import draw_overlay, encode_png, legend_html

LOW_QUALITY = 0.5
"""``--overlays-only-failures`` also writes frames whose published quality is below this."""
WORST_FRAMES = 4
"""The report shows this many worst frames (largest position error) ..."""
FAILED_FRAMES = 3
"""... and the first frame of up to this many failure reasons."""
REPORT_MAX_WIDTH_PX = 640
"""Overlays in the report are scaled down to this width."""


@dataclass(frozen=True)
class FrameOutcome:
    """One replayed frame: stamp, published pose (NaN where none), quality, reason
    (``ok`` for a pose), latency (ms)."""

    t_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    quality: float
    reason: str
    latency_ms: float


def _outcome(est: Estimate, latency_ms: float) -> FrameOutcome:
    if isinstance(est, PoseEstimate):
        nan = float("nan")
        return FrameOutcome(est.t_ns, nan if est.x_m is None else float(est.x_m),
                            nan if est.y_m is None else float(est.y_m), float(est.yaw_rad),
                            float(est.quality), "ok", latency_ms)
    return FrameOutcome(est.t_ns, math.nan, math.nan, math.nan, 0.0, est.reason, latency_ms)


class ReplayViews:
    """Overlays and report data of a replay (see the module doc).

    Args:
        rig, site: what the replay ran with.
        overlays_dir: write overlay PNGs here (None: none).
        only_failures: only failures and frames of quality below :data:`LOW_QUALITY`.
        truth: ``truth.csv`` (ranks the worst frames by position error), or None.
    """

    def __init__(self, rig: Rig, site: Site, overlays_dir: Path | None = None,
                 only_failures: bool = False, truth: Truth | None = None) -> None:
        self.rig, self.site, self.truth = rig, site, truth
        self.overlays_dir = overlays_dir
        self.only_failures = only_failures
        self.outcomes: list[FrameOutcome] = []
        self.written = 0
        self._worst: list[tuple[float, int, str, np.ndarray, Estimate]] = []
        self._failed: dict[str, tuple[int, np.ndarray, Estimate]] = {}
        self.ambiguity = AmbiguityLog()
        if overlays_dir is not None:
            try:
                overlays_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise OutputError(overlays_dir, f"cannot create: {exc.strerror}") from None

    def frame(self, k: int, image: np.ndarray | None, raw: Estimate, published: Estimate,
              latency_ms: float) -> None:
        """Record frame ``k``: its overlay when asked, its outcome, and the frame itself
        if it is among the worst so far; ``image`` ``None`` (a damaged frame, no image):
        its outcome only."""
        self.outcomes.append(_outcome(published, latency_ms))
        self.ambiguity.add(k, raw, published)
        if image is None:
            return
        if self.overlays_dir is not None and (
                not self.only_failures or not published or published.quality < LOW_QUALITY):
            path = self.overlays_dir / f"{k:06d}.png"
            try:
                path.write_bytes(encode_png(draw_overlay(image, raw, self.rig, self.site)))
            except OSError as exc:
                raise OutputError(path, f"cannot write: {exc.strerror}") from None
            self.written += 1
        if not published:
            if published.reason not in self._failed and len(self._failed) < FAILED_FRAMES:
                self._failed[published.reason] = (k, image, raw)
            return
        scored = self._position_error(published)
        if scored is not None:
            err, words = scored
            item = (err, k, words, image, raw)
            if len(self._worst) < WORST_FRAMES:
                heapq.heappush(self._worst, item)
            elif err > self._worst[0][0]:
                heapq.heapreplace(self._worst, item)

    def _position_error(self, est: PoseEstimate) -> tuple[float, str] | None:
        """The position error (m; the lateral one when x is not estimated) against the
        truth, and its caption in mm and degrees; None without a truth row."""
        row = self.truth.lookup(est.t_ns) if self.truth is not None else None
        if row is None or est.y_m is None:
            return None
        dy = est.y_m - row[1]
        dyaw = math.degrees(wrap_pi(est.yaw_rad - row[2]))
        if est.x_m is None:
            return abs(dy), (f"lateral error {1e3 * abs(dy):.2f} mm (y {1e3 * dy:+.2f} mm; "
                             f"x not estimated), yaw {dyaw:+.3f} deg")
        dx = est.x_m - row[0]
        err = math.hypot(dx, dy)
        return err, (f"position error {1e3 * err:.2f} mm (x {1e3 * dx:+.2f} mm, "
                     f"y {1e3 * dy:+.2f} mm), yaw {dyaw:+.3f} deg")

    def write_report(self, path: Path, title: str, summary: list[str]) -> Path:
        """Write the self-contained HTML report; returns its path.

        Raises:
            OutputError: it cannot be written.
        """
        sections = [f"<h1>{html.escape(title)}</h1>",
                    "<pre>" + html.escape("\n".join(summary)) + "</pre>"]
        sections += self._error_table() + self._tum_note()
        sections += [_img(png, alt) for alt, png in self._plots()]
        sections.append(legend_html())
        sections.append("<h2>worst frames (largest position error)</h2>")
        for _, k, words, image, raw in sorted(self._worst, key=lambda w: (-w[0], w[1])):
            sections.append(f"<h3>frame {k}: {html.escape(words)}</h3>")
            sections.append(_img(self._overlay_png(image, raw), f"overlay of frame {k}"))
        sections += self.ambiguity.html()
        if self._failed:
            sections.append("<h2>failed frames (first of each reason)</h2>")
        for reason, (k, image, raw) in self._failed.items():
            sections.append(f"<h3>frame {k}: {html.escape(reason)}</h3>")
            sections.append(_img(self._overlay_png(image, raw), f"overlay of frame {k}"))
        doc = ("<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
               f"<meta name='generator' content='{version_line()}'>"
               f"<title>{html.escape(title)}</title><style>body{{font-family:sans-serif;"
               "max-width:900px;margin:auto}img{max-width:100%}"
               "pre{white-space:pre-wrap;overflow-wrap:anywhere}"   # the summary's long lines
               "table.errors td,table.errors th{padding:1px 8px;text-align:right}"
               "</style></head><body>\n"
               + "\n".join(sections) + "\n</body></html>\n")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(doc, encoding="utf-8")
        except OSError as exc:
            raise OutputError(path, f"cannot write: {exc.strerror}") from None
        return path

    def _error_table(self) -> list[str]:
        """The errors against the truth: mean, RMSE, median, p95 and max, per quantity."""
        if self.truth is None or not self.outcomes:
            return []
        rows = error_rows(_errors(self.outcomes, [self.truth.lookup(r.t_ns)
                                                  for r in self.outcomes]))
        if not rows:
            return []
        head = "".join(f"<th>{h}</th>" for h in ("error", "frames", "mean |e|", "RMSE",
                                                   "median |e|", "p95 |e|", "max |e|"))
        body = "".join(
            f"<tr><td>{name} [{unit}]</td><td>{n}</td>"
            + "".join(f"<td>{v:.{3 if unit == 'deg' else 2}f}</td>" for v in values)
            + "</tr>" for name, unit, n, values in rows)
        return ["<h2>errors against truth.csv</h2>",
                f"<table class='errors'><tr>{head}</tr>{body}</table>"]

    def _tum_note(self) -> list[str]:
        """A note when poses have no x: a TUM file (``--tum``) cannot hold them."""
        n = sum(1 for r in self.outcomes
                if r.reason == "ok" and math.isnan(r.x_m) and math.isfinite(r.y_m))
        if not n:
            return []
        return [f"<p class='note'>note: {n} poses have no x (the method observes y and "
                "the heading only). TUM has no empty field, so <code>poses.tum</code> "
                "(<code>--tum</code>) leaves them out and evo cannot compare them; their "
                "lateral errors are in the table above.</p>"]

    def _overlay_png(self, image: np.ndarray, raw: Estimate) -> bytes:
        img = draw_overlay(image, raw, self.rig, self.site)
        if img.shape[1] > REPORT_MAX_WIDTH_PX:
            s = REPORT_MAX_WIDTH_PX / img.shape[1]
            img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        return encode_png(img)

    def _plots(self) -> list[tuple[str, bytes]]:
        """``(alt text, PNG)`` of every plot."""
        o = self.outcomes
        if not o:
            return []
        t0 = o[0].t_ns
        t_s = np.array([r.t_ns - t0 for r in o]) / 1e9
        xy = np.array([[r.x_m, r.y_m] for r in o])
        q = np.array([r.quality for r in o])
        truth_rows = [self.truth.lookup(r.t_ns) if self.truth is not None else None for r in o]
        truth_xy = (np.array([[self.truth.x_m[i], self.truth.y_m[i]]
                              for i in range(self.truth.t_ns.size)])
                    if self.truth is not None else None)
        shown = xy.copy()
        for i, row in enumerate(truth_rows):  # an unobserved x drawn at the truth's x
            if row is not None and np.isnan(shown[i, 0]) and np.isfinite(shown[i, 1]):
                shown[i, 0] = row[0]
        ok = np.isfinite(shown).all(axis=1)
        out = [("trajectory", plots.trajectory_png(self.site, truth_xy, shown[ok], q[ok],
                                                   "trajectory over the site map"))]
        if any(row is not None for row in truth_rows):
            err = _errors(o, truth_rows)
            out.append(("errors", plots.errors_png(t_s, err)))
            pos = np.hypot(np.nan_to_num(err[X_ERROR]), np.nan_to_num(err[Y_ERROR]))
            pos[~np.isfinite(err[Y_ERROR])] = np.nan
            out.append(("quality against error",
                        plots.quality_error_png(q, pos, "position error [mm] (lateral "
                                                "where x is not estimated)")))
        out.append(("outcomes", plots.failures_png(t_s, [r.reason for r in o])))
        out.append(("latency", plots.histogram_png(np.array([r.latency_ms for r in o]),
                                                   "latency, capture to pose out [ms]",
                                                   "latency per frame", "ms")))
        return out


class AmbiguityLog:
    """What the report says of ambiguity: the frames the evidence did not single out
    (published ``ambiguous``, with their hypotheses), the frames whose pose the prior
    chose among twins (``Provenance.PRIOR``), the kinds of twin met, and the stretches
    of consecutive ambiguous frames (docs/methods/honesty.md)."""

    def __init__(self) -> None:
        self.ambiguous: list[tuple[int, tuple[Hypothesis, ...]]] = []
        self.prior_chosen = 0
        self.kinds: Counter = Counter()

    def add(self, k: int, raw: Estimate, published: Estimate) -> None:
        hyps = published.hypotheses or raw.hypotheses
        if not published and published.reason == AMBIGUOUS:
            self.ambiguous.append((k, hyps))
        elif published and raw and raw.provenance is Provenance.PRIOR and raw.hypotheses:
            self.prior_chosen += 1
        else:
            return
        self.kinds.update({h.label.split(" ")[0] for h in hyps[1:] if h.label} or {"?"})

    def stretches(self) -> list[tuple[int, int]]:
        """``(first, last)`` frame of each run of consecutive ambiguous frames."""
        out: list[tuple[int, int]] = []
        for k, _ in self.ambiguous:
            if out and out[-1][1] == k - 1:
                out[-1] = (out[-1][0], k)
            else:
                out.append((k, k))
        return out

    def html(self) -> list[str]:
        if not self.ambiguous and not self.prior_chosen:
            return []
        out = ["<h2>ambiguity</h2>",
               f"<p>{len(self.ambiguous)} frames not singled out (published "
               f"<code>ambiguous</code>: several poses explain them alike); "
               f"{self.prior_chosen} poses chosen among twins by the prior (start pose, "
               "track or stated heading). Twins met: "
               + html.escape(", ".join(f"{n} {c}" for n, c in self.kinds.most_common()))
               + ". Where on the site one frame alone is ambiguous, and which marker "
               "would single it out: <code>ceilcal check-site</code>.</p>"]
        first = dict(self.ambiguous)
        rows = []
        for a, b in self.stretches()[:MAX_STRETCHES]:
            poses = "; ".join(
                f"({'-' if h.x_m is None else f'{h.x_m:.2f}'}, "
                f"{'-' if h.y_m is None else f'{h.y_m:.2f}'}, {h.yaw_deg:.0f} deg)"
                for h in first[a][:4])
            rows.append(f"<tr><td>{a}-{b}</td><td>{len(first[a])}</td>"
                        f"<td>{html.escape(poses)}</td></tr>")
        if rows:
            out.append("<table><tr><th>frames</th><th>poses</th><th>the first frame's "
                       "(x m, y m, yaw)</th></tr>" + "".join(rows) + "</table>")
        return out


MAX_STRETCHES = 12
"""The report lists at most this many stretches of ambiguous frames."""


X_ERROR, Y_ERROR, YAW_ERROR = "x error [mm]", "y error [mm]", "yaw error [deg]"
"""The error series' names, with their units: mm for positions (the summary's unit)."""


def _errors(o: list[FrameOutcome], truth_rows: list) -> dict[str, np.ndarray]:
    """Per-frame errors (mm, mm, degrees) against the truth rows (NaN where none)."""
    e = np.full((len(o), 3), np.nan)
    for i, (r, row) in enumerate(zip(o, truth_rows, strict=True)):
        if row is not None and r.reason == "ok":
            e[i] = ((r.x_m - row[0]) * 1e3, (r.y_m - row[1]) * 1e3,
                    math.degrees(wrap_pi(r.yaw_rad - row[2])))
    return {X_ERROR: e[:, 0], Y_ERROR: e[:, 1], YAW_ERROR: e[:, 2]}


def error_rows(errors: dict[str, np.ndarray]) -> list[tuple[str, str, int, list[float]]]:
    """``(quantity, unit, n, [mean |e|, RMSE, median |e|, p95 |e|, max |e|])`` of the
    heading, lateral, x and position errors (each where it was estimated): evo's
    headline number is the RMSE, the summary's the median and p95."""
    x, y, yaw = errors[X_ERROR], errors[Y_ERROR], errors[YAW_ERROR]
    pos = np.hypot(x, y)
    out = []
    for name, unit, e in (("heading", "deg", yaw), ("lateral (y)", "mm", y), ("x", "mm", x),
                          ("position", "mm", pos)):
        a = np.abs(e[np.isfinite(e)])
        if a.size:
            out.append((name, unit, int(a.size), [float(a.mean()),
                                                  float(np.sqrt(np.mean(a * a))),
                                                  float(np.median(a)),
                                                  float(np.percentile(a, 95)),
                                                  float(a.max())]))
    return out


def _img(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f"<p><img alt='{html.escape(alt)}' src='data:image/png;base64,{data}'></p>"
