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
from ceilkit.runtime.config.site import MarkerPose, Markers, Site, check_rig_site
from ceilkit.runtime.config.yaml import atomic_write_text
from ceilkit.runtime.errors import CalibrationError, ConfigError
from ceilkit.runtime.estimators.lights.estimator import LightsOptions
from ceilkit.runtime.estimators.lights.matching import map_symmetries
from ceilkit.runtime.estimators.texture.ceilmap import CeilingMap
from ceilkit.runtime.features.quads import DICTIONARY_NAMES
from ceilkit.runtime.io.outputs import claim_outputs, recording_inputs
from ceilkit.runtime.io.recording import POSES_HEADER, Recording, Truth

from .lightmap import LightMap, lightmap_header_lines, survey_lights
from .survey import (
    CLOSURE_KINDS,
    SurveyOptions,
    SurveyResult,
    result_frames,
    survey_drives,
    survey_map,
)
from .survey_anchor import anchor_by_lights
from .survey_geo import origin_from_start, parse_geodetic, start_pose_from_geodetic
from .survey_lamps import MIN_LAMP_ROUNDNESS, lamp_shapes
from .survey_markers import (
    SurveyedMarker,
    anchor_by_markers,
    parse_anchor_marker,
    survey_markers,
)
from .survey_report import report_lines, write_plot
from .workflow import provenance_header

MAP_FILE = "ceiling_map.npz"
OUTPUT_FILES = ("site.yaml", MAP_FILE, "poses.csv", "survey.md", "survey.png")
DEFAULT_DICTIONARY = "DICT_APRILTAG_36h11"
"""The markers' dictionary when neither ``--site`` nor ``--marker-dictionary`` names one
(SPEC §2's example)."""
LIGHT_SPREAD_M = 0.015
"""A cluster of lit spots is written as a light only when its single-frame detections
scatter less than this about its centre: spot lights do (the lights fixture: 0.4 mm
median, 2.9 mm at most); the office scatter's panels, detectors and sprinklers give
clusters of bright fragments (48 mm median on a 19 m office loop) that are no lights a
method could use."""


@dataclass(frozen=True, eq=False)
class SurveyRun:
    """What :func:`survey_site` did: the result, the map, the lights (None: none
    found, ``lights_note`` says why) and the files written."""

    result: SurveyResult
    cmap: CeilingMap
    lights: LightMap | None
    lights_note: str
    files: tuple[Path, ...]
    markers: tuple[SurveyedMarker, ...] = ()

    def lines(self) -> list[str]:
        r = self.result
        loops = sum(lk.kind in CLOSURE_KINDS for lk in r.links)
        out = [f"surveyed {len(r.poses)} frames of {len(r.drives)} drive(s): "
               f"{len(r.links)} place matches ({loops} loop or drive closures), "
               f"{r.unplaced} frames not placed (in {r.unplaced_pieces} pieces no closure "
               f"tied to the anchor's); graph solved in {r.solve_s:.2f} s",
               f"ceiling map: {self.cmap.feature_count} features, median 1-sigma "
               f"{_median_mm(self.cmap.sigma_m)} mm",
               f"lights: {len(self.lights.lights_m)}" if self.lights is not None
               else f"lights: none ({self.lights_note})"]
        out += [f"warning: {r.unchecked}"] if r.unchecked else []
        out += [_marker_line(m) for m in self.markers]
        return out + [f"wrote {p}" for p in self.files]


def _marker_line(m: SurveyedMarker) -> str:
    p = m.pose()
    where = (f"at {m.places} places: two prints of one id, not written" if m.places > 1
             else f"({p.x_m:.4f}, {p.y_m:.4f}) m, yaw {math.degrees(p.yaw_rad):.2f} deg, "
                  f"side {p.size_m:.3f} m")
    return (f"marker {m.id}: {where}; {m.views} views, corner 1-sigma "
            f"{1e3 * m.sigma_m:.2f} mm (spread {1e3 * m.spread_m:.2f} mm)")


def _median_mm(sigma_m: np.ndarray) -> str:
    return f"{1e3 * float(np.median(sigma_m)):.2f}" if len(sigma_m) else "-"


def parse_start_pose(text: str | None) -> tuple[float, float, float] | None:
    """``"X,Y,YAW"`` (m, m, degrees) as ``(x, y, yaw rad)``; None when not given.

    Raises:
        ConfigError: keyed ``--start-pose``, for anything but three finite numbers.
    """
    if text is None:
        return None
    try:
        x, y, yaw = (float(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(None, "--start-pose", f"expected X,Y,YAW (m, m, degrees), found "
                          f"{text!r}") from None
    if not all(math.isfinite(v) and abs(v) <= 1e6 for v in (x, y, yaw)):
        raise ConfigError(None, "--start-pose", f"expected finite X,Y,YAW, found {text!r}")
    return x, y, math.radians(yaw)


def parse_anchors(start_pose: str | None, markers: Sequence[str], dictionary: str | None,
                  geodetic: str | None, site: Path | None) -> Anchors:
    """The command's anchor options parsed (:class:`Anchors`); a marker given with no side
    takes ``--site``'s side for that id (else unchecked).

    Raises:
        ConfigError: a malformed option (keyed by its flag), an unknown dictionary, or a
            bad ``--site``.
    """
    sizes, default = {}, math.nan
    if markers and site is not None:
        known = Site.load(site)
        if known.markers is not None:
            sizes = {p.id: p.size_m for p in known.markers.poses}
            default = known.markers.size_m
    if dictionary is not None and dictionary not in DICTIONARY_NAMES:
        raise ConfigError(None, "--marker-dictionary", f"unknown aruco dictionary "
                          f"{dictionary!r} (e.g. DICT_APRILTAG_36h11, DICT_4X4_50)")
    return Anchors(parse_start_pose(start_pose),
                   tuple(parse_anchor_marker(m, sizes, default) for m in markers),
                   parse_geodetic(geodetic), dictionary)


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


def _repeated_beyond(lights_m: np.ndarray, unplaced: int) -> str:
    """Why lights found on a drive the survey did not all place are not written ('' when
    they are): they repeat (a motion of the map puts at least half of them on others,
    :func:`~ceilkit.runtime.estimators.lights.matching.map_symmetries` at the lights
    method's gate), so a pose matched to them has twins a period on, and the frames
    left unplaced (refused as twins, most often) say the ceiling goes on beyond the
    lights placed, where those twins lie and no light of the map can rule them out.
    (``bench_heldout_texture.py --seed 10``'s repeated control, a detector and a
    sprinkler on every tile, 318 of 334 frames unplaced: 28 lights of a lattice over
    six keyframes, and ``auto`` published 15-26 poses 3.1 m off from them.)"""
    n, o = len(lights_m), LightsOptions()
    if unplaced == 0 or n < 2 * o.min_inliers:
        return ""
    # every light searched, past SYMMETRY_MAX_LIGHTS (offline: 0.14 s for 400 lights;
    # bench_heldout_texture --seed 4's repeated control holds 364)
    sym = map_symmetries(lights_m, o.gate_m, max(o.min_inliers, math.ceil(n / 2)),
                         max_lights=n)
    if not len(sym):
        return ""
    return (f"{n} lights left out: a motion of the map puts half of them or more on others "
            f"(they repeat) and {unplaced} frames of the drive were not placed, so a pose "
            "matched to them has twins beyond the part surveyed that no light rules out")


def _lights(recs: Sequence[Recording], res: SurveyResult) -> tuple[LightMap | None, str]:
    """The lit spots of the first drive placed with its solved poses (those whose
    detections stay within :data:`LIGHT_SPREAD_M` of their cluster's centre and whose
    spots are round, :mod:`.survey_lamps`; each one's 1σ the cluster's, with the
    keyframes' median radial pose 1σ added in quadrature), or why none; the note says how
    many clusters were left out."""
    d0 = res.drive == 0
    truth = Truth(res.t_ns[d0], res.poses[d0, 0], res.poses[d0, 1], res.poses[d0, 2])
    try:
        lm = survey_lights(recs[0], truth, ceiling_height_m=res.ceiling_height_m)
    except (CalibrationError, ConfigError) as exc:
        return None, str(exc).splitlines()[0]
    stay = lm.spread_m <= LIGHT_SPREAD_M
    left = int(np.count_nonzero(~stay))
    if not stay.any():
        return None, (f"{len(lm.lights_m)} clusters of lit spots, but none stays put "
                      f"from frame to frame (median spread "
                      f"{1e3 * float(np.median(lm.spread_m)):.0f} mm > "
                      f"{1e3 * LIGHT_SPREAD_M:.0f} mm): bright patches, not spot lights")
    keys = res.keys[res.drive[res.keys] == 0]
    # radial, as the centre's standard error it is added to (LightMap.sigma_m); until
    # 2026-12-07 per axis (/ sqrt 2), so the header's 1-sigma was 0.71 of its own
    pose_sigma = float(np.nanmedian(np.hypot(*res.sigma[keys, :2].T))) if len(keys) else 0.0
    roundness = lamp_shapes(recs[0], res.frame[keys], res.poses[keys], lm.lights_m[stay],
                            res.ceiling_height_m)[0]
    lamp = np.zeros(len(stay), bool)
    lamp[np.flatnonzero(stay)] = roundness >= MIN_LAMP_ROUNDNESS
    if not lamp.any():
        return None, (f"{int(stay.sum())} clusters of lit spots stay put, but none is "
                      f"round (median minor / major extent under {MIN_LAMP_ROUNDNESS}): "
                      "not spot lights")
    lm = dataclasses.replace(lm, lights_m=lm.lights_m[lamp], spread_m=lm.spread_m[lamp],
                             sigma_m=np.hypot(lm.sigma_m[lamp], pose_sigma),
                             views=lm.views[lamp], unassigned=lm.unassigned)
    repeated = _repeated_beyond(lm.lights_m, res.unplaced)
    if repeated:
        return None, repeated
    notes = [f"{left} of {len(stay)} clusters of lit spots left out: they do not stay put "
             f"from frame to frame (spread > {1e3 * LIGHT_SPREAD_M:.0f} mm: bright "
             "patches, not spot lights)"] if left else []
    if int(stay.sum() - lamp.sum()):
        notes.append(f"{int(stay.sum() - lamp.sum())} that stay put left out: not round "
                     f"(their spots' median minor / major extent under "
                     f"{MIN_LAMP_ROUNDNESS}: not spot lights)")
    return lm, "; ".join(notes)


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
                 lights: LightMap | None, marks: Sequence[SurveyedMarker]) -> list[str]:
    keys = res.sigma[res.keys]
    lines = [f"anchor: {res.anchor}" + (f" (frame 0 of {res.drives[0]})"
                                         if res.anchor == "start pose" else ""),
             f"ceiling_map: {cmap.feature_count} features; 1-sigma per axis median "
             f"{_median_mm(cmap.sigma_m)} mm, 95th percentile "
             f"{1e3 * float(np.percentile(cmap.sigma_m, 95)) if len(cmap.sigma_m) else 0:.2f}"
             " mm (from the views' scatter); keyframe poses' 1-sigma (relative to the "
             f"anchor) up to {1e3 * float(np.nanmax(keys[:, :2])):.2f} mm, "
             f"{math.degrees(float(np.nanmax(keys[:, 2]))):.3f} deg"]
    lines += [f"warning: {res.unchecked}"] if res.unchecked else []
    if lights is not None:
        lines += lightmap_header_lines(lights)
    return run_lines + lines + [_marker_line(m) for m in marks]


@dataclass(frozen=True)
class Anchors:
    """What the user knows to anchor a survey (docs/survey.md, "Anchors").

    Attributes:
        start_pose: the first drive's first frame in W (m, m, rad); None: not given.
        markers: markers of known pose (``--anchor-marker``), beside ``--site``'s.
        geodetic: the first frame on the Earth ``(lat, lon, heading)``, degrees.
        dictionary: the markers' aruco dictionary (None: ``--site``'s, else
            :data:`DEFAULT_DICTIONARY`).
    """

    start_pose: tuple[float, float, float] | None = None
    markers: tuple[MarkerPose, ...] = ()
    geodetic: tuple[float, float, float] | None = None
    dictionary: str | None = None


def survey_site(rig: Path, recordings: Sequence[Path], out: Path, *,
                site: Path | None = None, anchors: Anchors = Anchors(),
                ceiling_height_m: float | None = None, force: bool = False,
                options: SurveyOptions = SurveyOptions()) -> SurveyRun:
    """Survey ``recordings`` with ``rig`` and write ``out`` (module docstring), anchored
    (first found): by markers of known pose (``anchors.markers``, else ``--site``'s),
    by ``--site``'s lights, by the geodetic point on ``--site``'s ``origin``, by the
    start pose (default the origin).

    Raises:
        ConfigError: a bad rig, site, recording or option (naming the file and key); an
            output that exists without ``force``.
        CalibrationError: nothing could be chained; an anchor not seen or ambiguous.
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
        start = _start_pose(anchors, known, site)
        res = survey_drives(recs, the_rig, height, start or (0.0, 0.0, 0.0), options)
        if start is not None and anchors.start_pose is None:
            res = dataclasses.replace(res, anchor="geodetic point on --site's origin")
        first = res.poses[0].copy()
        lights, note = _lights(recs, res)
        marks, base = _markers(res, recs, the_rig, anchors, known, base)
        known_marks = anchors.markers or (known.markers.poses if known is not None and
                                          known.markers is not None else ())
        if known_marks:
            res, lights, marks = _anchor_markers(res, lights, marks, known_marks)
        elif known is not None and known.has_lights:
            res, lights, marks = _anchor_lights(res, lights, note, known, site, marks)
        base = _with_markers(base, marks, anchors)
        if start is not None and anchors.start_pose is None and \
                not res.anchor.startswith("geodetic"):
            res = dataclasses.replace(res, anchor=res.anchor + "; --anchor-geodetic on "
                                      f"--site's origin is {_pose_gap(first, res.poses[0])}"
                                      " from it")
        if anchors.geodetic is not None and base.origin is None:
            base = dataclasses.replace(base, origin=origin_from_start(
                anchors.geodetic, tuple(res.poses[0])))
            res = dataclasses.replace(res, anchor=res.anchor + "; origin from "
                                      f"--anchor-geodetic at frame {int(res.frame[0])} of "
                                      "the first drive")
        cmap = survey_map(res, recs, the_rig)
        return _write(out, res, cmap, lights, note, base, height, marks)


def _pose_gap(a: np.ndarray, b: np.ndarray) -> str:
    """How far pose ``a`` is from ``b``: ``"12.3 mm, 0.45 deg"``."""
    dyaw = (a[2] - b[2] + math.pi) % (2 * math.pi) - math.pi
    return f"{1e3 * math.hypot(a[0] - b[0], a[1] - b[1]):.1f} mm, {math.degrees(dyaw):.2f} deg"


def _start_pose(anchors: Anchors, known: Site | None, site: Path | None
                ) -> tuple[float, float, float] | None:
    """The start pose: given, or the geodetic point on ``--site``'s origin (not both)."""
    if anchors.geodetic is None or known is None or known.origin is None:
        return anchors.start_pose
    if anchors.start_pose is not None:
        raise ConfigError(None, "--anchor-geodetic", f"{site} has an origin, so the "
                          "geodetic point is the start pose: give it or --start-pose, "
                          "not both")
    return start_pose_from_geodetic(known.origin, anchors.geodetic)


def _markers(res: SurveyResult, recs: Sequence[Recording], rig: Rig, anchors: Anchors,
             known: Site | None, base: Site) -> tuple[list[SurveyedMarker], Site]:
    """The markers the keyframes read (when a dictionary is known: ``--site``'s
    markers, ``--anchor-marker`` or ``--marker-dictionary``), in the survey's frame."""
    has = known is not None and known.markers is not None
    if not (has or anchors.markers or anchors.dictionary):
        return [], base
    dictionary = (known.markers.dictionary if has else
                  anchors.dictionary or DEFAULT_DICTIONARY)
    read = result_frames(res, recs, rig)
    frames = ((read.grey(int(res.drive[n]), int(res.frame[n])), res.poses[n])
              for n in res.keys)
    pose_sigma = float(np.nanmedian(np.hypot(*res.sigma[res.keys, :2].T))) / math.sqrt(2)
    found = survey_markers(frames, rig, res.ceiling_height_m, dictionary,
                           pose_sigma if math.isfinite(pose_sigma) else 0.0)
    if not has:
        base = dataclasses.replace(base, markers=Markers(dictionary, math.nan, ()))
    return found, base


def _anchor_markers(res: SurveyResult, lights: LightMap | None,
                    marks: list[SurveyedMarker], known: Sequence[MarkerPose]
                    ) -> tuple[SurveyResult, LightMap | None, list[SurveyedMarker]]:
    """The survey moved onto the known markers
    (:func:`~ceilkit.calib.survey_markers.anchor_by_markers`).

    Raises:
        CalibrationError: a known marker not seen, ambiguous, of another size, or the
            markers disagree.
    """
    a = anchor_by_markers(marks, known)
    if not a:
        raise CalibrationError(f"the markers do not anchor the survey: {a.reason} (markers "
                               "of known pose are the anchor when given: to anchor by the "
                               "start pose, give a --site without markers)")
    each = ", ".join(f"{i}: {1e3 * r:.1f} mm (side {s:.3f} m)"
                     for i, r, s in zip(a.ids, a.residual_m, a.size_m, strict=True))
    anchor = (f"markers: {len(a.ids)} of known pose; each one's RMS corner distance "
              f"after the fit: {each}; the anchor's yaw 1-sigma "
              f"{math.degrees(a.sigma_yaw_rad):.3f} deg ({1e3 * a.sigma_yaw_rad:.1f} mm "
              "at 1 m from the markers)")
    res = dataclasses.replace(res, poses=a.apply(res.poses), chain=a.apply(res.chain),
                              anchor=anchor)
    if lights is not None:
        lights = dataclasses.replace(lights, lights_m=a.apply_xy(lights.lights_m))
    marks = [m.moved(a.yaw_rad, a.t_m) for m in marks]
    return res, lights, marks


def _with_markers(base: Site, marks: list[SurveyedMarker], anchors: Anchors) -> Site:
    """``base``'s markers with the surveyed ones it does not list (one place each) added,
    and the ``--anchor-marker`` ones as given."""
    if base.markers is None:
        return base
    listed = {p.id: p for p in base.markers.poses}
    listed.update({p.id: p for p in anchors.markers if math.isfinite(p.size_m)})
    for m in marks:
        if m.id not in listed and m.places == 1:
            p = m.pose()
            listed[m.id] = MarkerPose(p.id, round(p.x_m, 4), round(p.y_m, 4), p.yaw_rad,
                                      round(p.size_m, 3))
    if not listed:
        return dataclasses.replace(base, markers=None)
    size = base.markers.size_m
    if not math.isfinite(size):
        size = float(np.median([p.size_m for p in listed.values()]))
    return dataclasses.replace(base, markers=Markers(base.markers.dictionary, size,
                                                     tuple(listed[i] for i in sorted(listed))))


def _anchor_lights(res: SurveyResult, lights: LightMap | None, note: str, known: Site,
                   site: Path | None, marks: list[SurveyedMarker]
                   ) -> tuple[SurveyResult, LightMap, list[SurveyedMarker]]:
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
    marks = [m.moved(a.yaw_rad, a.t_m) for m in marks]
    return res, dataclasses.replace(lights, lights_m=a.apply_xy(lights.lights_m)), marks


def _write(out: Path, res: SurveyResult, cmap: CeilingMap, lights: LightMap | None,
           note: str, base: Site, height: float, marks: Sequence[SurveyedMarker]
           ) -> SurveyRun:
    written = [cmap.save(out / MAP_FILE)]
    site = dataclasses.replace(base, ceiling_height_m=height, ceiling_map=MAP_FILE,
                               source=None)
    if lights is not None:      # each light's 1σ per axis (light_sigma: the map's error)
        site = dataclasses.replace(site, lights_m=np.round(lights.lights_m, 4),
                                   light_sigma_m=np.round(lights.sigma_m / math.sqrt(2.0), 6))
    header = provenance_header("site surveyed by ceilcal survey (no external poses)",
                               _site_header([], res, cmap, lights, marks))
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
    return SurveyRun(res, cmap, lights, note, tuple(written), tuple(marks))
