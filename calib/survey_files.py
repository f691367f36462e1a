"""``ceilcal survey``'s files: the library function behind the command
(:func:`survey_site`) and what it writes into ``SITE_DIR``:

* ``site.yaml``: ``ceiling_height``, ``ceiling_map: ceiling_map.npz`` (ceilkit's
  extension of SPEC §2, read by the ``texture`` method), ``lights`` when lit spots were
  seen often enough and stay put (:data:`LIGHT_SPREAD_M`), the other sections of
  ``--site`` kept; a provenance header with each section's 1σ (SPEC has no key for it);
* ``ceiling_map.npz``: the ceiling map
  (:class:`~ceilkit.runtime.estimators.texture.ceilmap.CeilingMap`, docs/conventions.md)
  built from the keyframes at their solved poses;
* ``poses.csv``: the first drive's frames at their solved poses (SPEC §2 poses layout,
  method ``survey``; the 1σ on keyframes, empty elsewhere); ``poses_<k>.csv`` for the
  k-th further drive;
* ``survey.md``: the report (every closure, the residuals, each section's σ) and
  ``survey.png`` (the mosaic with the path and the closures) when matplotlib is there.

Nothing is written when an input is bad or an output exists (unless ``force``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site, check_rig_site
from ceilkit.runtime.config.yaml import atomic_write_text
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap
from ceilkit.runtime.io.outputs import claim_outputs, recording_inputs
from ceilkit.runtime.io.recording import POSES_HEADER, Recording, Truth

from .lightmap import LightMap, lightmap_header_lines, survey_lights
from .survey import SurveyOptions, SurveyResult, survey_drives, survey_map
from .survey_anchor import anchor_by_lights
from .survey_report import report_lines, write_plot
from .workflow import provenance_header

MAP_FILE = "ceiling_map.npz"
OUTPUT_FILES = ("site.yaml", MAP_FILE, "poses.csv", "survey.md", "survey.png")
LIGHT_SPREAD_M = 0.015
"""The lit spots are written as ``lights`` only when their single-frame detections
scatter less than this about their clusters' centres (median over the clusters): spot
lights do (the lights fixture: 0.4 mm median, 2.9 mm at most); the office scatter's
panels, detectors and sprinklers give clusters of bright fragments (48 mm median on a
19 m office loop) that are no lights a method could use."""


@dataclass(frozen=True, eq=False)
class SurveyRun:
    """What :func:`survey_site` did: the result, the map, the lights (None: none
    found, ``lights_note`` says why) and the files written."""

    result: SurveyResult
    cmap: CeilingMap
    lights: LightMap | None
    lights_note: str
    files: tuple[Path, ...]

    def lines(self) -> list[str]:
        r = self.result
        loops = sum(lk.kind != "link" for lk in r.links)
        out = [f"surveyed {len(r.poses)} frames of {len(r.drives)} drive(s): "
               f"{len(r.links)} place matches ({loops} loop or drive closures), "
               f"{r.unplaced} frames not placed; graph solved in {r.solve_s:.2f} s",
               f"ceiling map: {len(self.cmap.points_xy)} features, median 1-sigma "
               f"{_median_mm(self.cmap.sigma_m)} mm",
               f"lights: {len(self.lights.lights_m)}" if self.lights is not None
               else f"lights: none ({self.lights_note})"]
        return out + [f"wrote {p}" for p in self.files]


def _median_mm(sigma_m: np.ndarray) -> str:
    return f"{1e3 * float(np.median(sigma_m)):.2f}" if len(sigma_m) else "-"


def parse_start_pose(text: str | None) -> tuple[float, float, float]:
    """``"X,Y,YAW"`` (m, m, degrees) as ``(x, y, yaw rad)``; the origin when None.

    Raises:
        ConfigError: keyed ``--start-pose``, for anything but three finite numbers.
    """
    if text is None:
        return 0.0, 0.0, 0.0
    try:
        x, y, yaw = (float(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(None, "--start-pose", f"expected X,Y,YAW (m, m, degrees), found "
                          f"{text!r}") from None
    if not all(math.isfinite(v) and abs(v) <= 1e6 for v in (x, y, yaw)):
        raise ConfigError(None, "--start-pose", f"expected finite X,Y,YAW, found {text!r}")
    return x, y, math.radians(yaw)


def _height(ceiling_height_m: float | None, site: Site | None, recordings: Sequence[Path]
            ) -> float:
    """The ceiling height: the option, else the known site's, else the first
    recording's ``site.yaml``."""
    if ceiling_height_m is not None:
        if not (math.isfinite(ceiling_height_m) and ceiling_height_m > 0):
            raise ConfigError(None, "--ceiling-height", f"expected a height > 0 m, found "
                              f"{ceiling_height_m!r}")
        return float(ceiling_height_m)
    if site is not None:
        return site.ceiling_height_m
    own = Path(recordings[0]) / "site.yaml"
    if own.is_file():
        return Site.load(own).ceiling_height_m
    raise ConfigError(None, "--ceiling-height", f"no ceiling height: {own} does not exist; "
                      "give --ceiling-height or --site")


def _lights(recs: Sequence[Recording], res: SurveyResult) -> tuple[LightMap | None, str]:
    """The lit spots of the first drive placed with its solved poses, or why none."""
    d0 = res.drive == 0
    truth = Truth(res.t_ns[d0], res.poses[d0, 0], res.poses[d0, 1], res.poses[d0, 2])
    try:
        lm = survey_lights(recs[0], truth, ceiling_height_m=res.ceiling_height_m)
    except (CalibrationError, ConfigError) as exc:
        return None, str(exc).splitlines()[0]
    spread = float(np.median(lm.spread_m))
    if spread > LIGHT_SPREAD_M:
        return None, (f"{len(lm.lights_m)} clusters of lit spots, but they do not stay put "
                      f"from frame to frame (median spread {1e3 * spread:.0f} mm > "
                      f"{1e3 * LIGHT_SPREAD_M:.0f} mm): bright patches, not spot lights")
    return lm, ""


def _poses_text(res: SurveyResult, drive: int) -> str:
    rows = [",".join(POSES_HEADER)]
    for n in np.flatnonzero(res.drive == drive):
        x, y, yaw = res.poses[n]
        s = res.sigma[n]
        sig = ["" if not np.isfinite(v) else f"{v:.6f}"
               for v in (s[0], s[1], math.degrees(s[2]))]
        rows.append(",".join([str(int(res.t_ns[n])), f"{x:.6f}", f"{y:.6f}",
                              f"{math.degrees(yaw):.6f}", "", "survey", "1.000", ""] + sig))
    return "\n".join(rows) + "\n"


def _site_header(run_lines: list[str], res: SurveyResult, cmap: CeilingMap,
                 lights: LightMap | None) -> list[str]:
    keys = res.sigma[res.keys]
    lines = [f"anchor: {res.anchor}" + (f" (frame 0 of {res.drives[0]})"
                                         if res.anchor == "start pose" else ""),
             f"ceiling_map: {len(cmap.points_xy)} features; 1-sigma per axis median "
             f"{_median_mm(cmap.sigma_m)} mm, 95th percentile "
             f"{1e3 * float(np.percentile(cmap.sigma_m, 95)) if len(cmap.sigma_m) else 0:.2f}"
             " mm (from the views' scatter); keyframe poses' 1-sigma (relative to the "
             f"anchor) up to {1e3 * float(np.nanmax(keys[:, :2])):.2f} mm, "
             f"{math.degrees(float(np.nanmax(keys[:, 2]))):.3f} deg"]
    if lights is not None:
        lines += lightmap_header_lines(lights)
    return run_lines + lines


def survey_site(rig: Path, recordings: Sequence[Path], out: Path, *,
                site: Path | None = None, start_pose: tuple[float, float, float] = (0, 0, 0),
                ceiling_height_m: float | None = None, force: bool = False,
                options: SurveyOptions = SurveyOptions()) -> SurveyRun:
    """Survey ``recordings`` with ``rig`` and write ``out`` (module docstring).

    Raises:
        ConfigError: a bad rig, site, recording or option (naming the file and key); an
            output that exists without ``force``.
        CalibrationError: nothing could be chained.
    """
    the_rig = Rig.load(rig)
    known = Site.load(site) if site is not None else None
    height = _height(ceiling_height_m, known, recordings)
    base = known if known is not None else Site(height)
    check_rig_site(the_rig, dataclasses.replace(base, ceiling_height_m=height))
    recs = [Recording(r, rig=the_rig, site=dataclasses.replace(base, ceiling_height_m=height))
            for r in recordings]
    out = Path(out)
    files = [out / n for n in OUTPUT_FILES]
    inputs = [rig] + ([site] if site is not None else []) + \
        [p for r in recordings for p in recording_inputs(r)]
    files += [out / f"poses_{k}.csv" for k in range(1, len(recs))]
    with contextlib.ExitStack() as stack:
        claim_outputs({"out": files}, folders={"out": [out]}, inputs=inputs, force=force,
                      stack=stack)
        res = survey_drives(recs, the_rig, height, start_pose, options)
        lights, note = _lights(recs, res)
        if known is not None and known.has_lights:
            res, lights = _anchor_lights(res, lights, note, known, site)
        cmap = survey_map(res, recs, the_rig)
        return _write(out, res, cmap, lights, note, base, height)


def _anchor_lights(res: SurveyResult, lights: LightMap | None, note: str, known: Site,
                   site: Path | None) -> tuple[SurveyResult, LightMap]:
    """The survey moved into the known site's W by its lights
    (:func:`~ceilkit.calib.survey_anchor.anchor_by_lights`).

    Raises:
        CalibrationError: the drive saw no lights, or they do not single out a motion.
    """
    if lights is None:
        raise CalibrationError(f"{site}: its {len(known.lights_m)} lights anchor the "
                               f"survey, but the drive surveyed none ({note}); give a "
                               "site without lights and a --start-pose")
    a = anchor_by_lights(lights.lights_m, known.lights_m)
    if not a:
        raise CalibrationError(f"{site}: the surveyed lights do not anchor the survey: "
                               f"{a.reason}")
    res_mm = ", ".join(f"{1e3 * r:.1f}" for r in a.residual_m)
    anchor = (f"lights: {len(a.pairs)} surveyed lights on --site's (runner-up motion "
              f"{a.runner_up}); their distances after the fit, mm: {res_mm}")
    res = dataclasses.replace(res, poses=a.apply(res.poses), chain=a.apply(res.chain),
                              anchor=anchor)
    return res, dataclasses.replace(lights, lights_m=a.apply_xy(lights.lights_m))


def _write(out: Path, res: SurveyResult, cmap: CeilingMap, lights: LightMap | None,
           note: str, base: Site, height: float) -> SurveyRun:
    written = [cmap.save(out / MAP_FILE)]
    site = dataclasses.replace(base, ceiling_height_m=height, ceiling_map=MAP_FILE,
                               source=None)
    if lights is not None:
        site = dataclasses.replace(site, lights_m=np.round(lights.lights_m, 4))
    header = provenance_header("site surveyed by ceilcal survey (no external poses)",
                               _site_header([], res, cmap, lights))
    site.save(out / "site.yaml", header)
    Site.load(out / "site.yaml")      # read back: valid by the same rules as any other
    written.append(out / "site.yaml")
    for d in range(len(res.drives)):
        p = out / ("poses.csv" if d == 0 else f"poses_{d}.csv")
        atomic_write_text(p, _poses_text(res, d))
        written.append(p)
    png = write_plot(out / "survey.png", res, cmap)
    atomic_write_text(out / "survey.md", "\n".join(report_lines(res, cmap, lights, note,
                                                                png is not None)) + "\n")
    written.append(out / "survey.md")
    if png is not None:
        written.append(png)
    return SurveyRun(res, cmap, lights, note, tuple(written))
