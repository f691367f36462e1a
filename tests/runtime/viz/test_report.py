"""Replay overlays and the HTML report; truth.tum beside poses.tum."""

from __future__ import annotations

import base64
import html
import math
import re
import shutil
import time

import cv2
import numpy as np
import pytest
from chromium_cdp import CHROMIUM, Browser

from ceilkit.calib.simulate import simulate_recording
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.io.recording import Recording, tum_line, write_truth_tum
from ceilkit.runtime.replay import replay
from ceilkit.runtime.sim.render import SimOptions, Trajectory
from helpers import CONFIGS, FIXTURES

MAX_REPORT_BYTES = 5 * 1024 * 1024


def _images(html: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)",
                                                    html)]


def test_report_and_overlays_of_the_lights_fixture(tmp_path):
    res = replay(FIXTURES / "lights_rec", tmp_path / "out", overlays=tmp_path / "ov",
                 report=True, tum=True)
    assert res.overlays == 6 and sorted(p.name for p in (tmp_path / "ov").iterdir())[0] \
        == "000000.png"
    assert res.report == tmp_path / "out" / "report.html"
    html = res.report.read_text()
    assert "http://" not in html and "https://" not in html and "<script" not in html
    pngs = _images(html)
    assert len(pngs) >= 6 and all(p[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    for heading in ("trajectory", "errors", "quality against error", "outcomes", "latency"):
        assert f"alt='{heading}'" in html
    assert "worst frames" in html
    assert any("report: " in line for line in res.lines())
    assert (tmp_path / "out" / "truth.tum").exists()


def test_overlays_only_failures(tmp_path):
    """Two frames of the lights fixture made flat grey (no lights): their overlays, and
    only theirs, are written."""
    rec = tmp_path / "rec"
    shutil.copytree(FIXTURES / "lights_rec", rec)
    shape = cv2.imread(str(rec / "frames" / "000002.png"), cv2.IMREAD_UNCHANGED).shape
    for k in (2, 5):
        cv2.imwrite(str(rec / "frames" / f"{k:06d}.png"), np.full(shape, 90, np.uint8))
    res = replay(rec, tmp_path / "out", overlays=tmp_path / "ov",
                 overlays_only_failures=True)
    assert res.telemetry.failures == {"no_lights": 2}
    assert res.report is None
    assert sorted(p.name for p in (tmp_path / "ov").glob("*.png")) == ["000002.png",
                                                                     "000005.png"]
    assert res.overlays == 2


def test_no_views_no_change(tmp_path):
    res = replay(FIXTURES / "corridor_rec", tmp_path / "a")
    assert res.overlays == 0 and res.report is None
    assert not (tmp_path / "a" / "report.html").exists()


def test_truth_tum_round_trip(tmp_path):
    rec = Recording(FIXTURES / "corridor_rec")
    path = write_truth_tum(rec.truth, tmp_path / "truth.tum")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# t_s x y z qx qy qz qw; written by ceilkit ")
    rows = [line.split() for line in lines[1:]]
    assert len(rows) == rec.truth.t_ns.size
    for row, t, x, y, a in zip(rows, rec.truth.t_ns, rec.truth.x_m, rec.truth.y_m,
                               rec.truth.yaw_rad, strict=True):
        assert int(row[0].replace(".", "")) == int(t)
        assert float(row[1]) == pytest.approx(x, abs=1e-6)
        assert float(row[2]) == pytest.approx(y, abs=1e-6)
        qz, qw = float(row[6]), float(row[7])
        assert 2 * math.atan2(qz, qw) == pytest.approx(math.remainder(a, 2 * math.pi), abs=1e-8)
    assert tum_line(1_500_000_000, 1.0, 2.0, 0.0) == b"1.500000000 1.000000 2.000000 0 0 0 " \
        b"0.000000000 1.000000000\n"


def test_report_of_a_300_frame_recording_is_under_5_mb(tmp_path):
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    n = 300
    t = np.arange(n, dtype=np.int64) * 33_333_333
    x = 0.5 + 0.02 * np.arange(n)
    y = 0.15 * np.sin(np.arange(n) / 25)
    yaw = np.radians(4 * np.sin(np.arange(n) / 40))
    simulate_recording(rig, site, Trajectory(t, x, y, yaw), tmp_path / "rec",
                       SimOptions(supersample=1), seed=1)
    res = replay(tmp_path / "rec", tmp_path / "out", report=True)
    size = res.report.stat().st_size
    print(f"\nreport of {n} frames: {size / 1e6:.2f} MB at {res.report}")
    assert res.telemetry.frames == n
    assert size < MAX_REPORT_BYTES
    assert len(_images(res.report.read_text())) >= 6


def test_the_report_says_which_frames_were_ambiguous(tmp_path):
    """The symmetric fixture corridor with no start pose: every frame ambiguous, the
    report's ambiguity section lists them as one stretch with the half-turn twin; from
    a start pose, the prior chose every pose among twins."""
    from ceilkit.runtime.replay import replay

    res = replay(FIXTURES / "corridor_rec", tmp_path / "a", method="corridor", report=True)
    text = res.report.read_text()
    assert "<h2>ambiguity</h2>" in text and "8 frames not singled out" in text
    assert "half_turn" in text and "<td>0-7</td>" in text
    res = replay(FIXTURES / "corridor_rec", tmp_path / "b", method="corridor", report=True,
                 start_pose=(0.0, 0.244558, math.radians(8.262851)))
    text = res.report.read_text()
    assert "0 frames not singled out" in text and "8 poses chosen among twins" in text


def test_the_report_explains_itself_in_mm_with_rmse_and_real_captions(tmp_path):
    """Positions in mm everywhere; mean, RMSE, median, p95 and max per quantity, equal
    to the errors of poses.csv against truth.csv; each worst frame captioned with its
    own errors; a legend for every overlay colour; latency with its unit."""
    from ceilkit.runtime.io.recording import load_poses
    from ceilkit.runtime.viz.overlay import legend_rows

    res = replay(FIXTURES / "lights_rec", tmp_path / "out", report=True)
    text = res.report.read_text()
    assert " cm" not in text and "[cm]" not in text
    truth, got = Recording(FIXTURES / "lights_rec").truth, load_poses(res.poses_path)
    err = []
    for t, x, y in zip(got.t_ns, got.x_m, got.y_m, strict=True):
        tx, ty, _ = truth.lookup(int(t))
        err.append(1e3 * math.hypot(x - tx, y - ty))
    e = np.array(err)
    row = re.search(r"<tr><td>position \[mm\]</td><td>(\d+)</td>((?:<td>[\d.]+</td>){5})",
                    text)
    values = [float(v) for v in re.findall(r"<td>([\d.]+)</td>", row.group(2))]
    assert int(row.group(1)) == e.size
    np.testing.assert_allclose(values, [e.mean(), np.sqrt(np.mean(e * e)), np.median(e),
                                        np.percentile(e, 95), e.max()], atol=0.006)
    captions = re.findall(r"<h3>frame (\d+): position error ([\d.]+) mm \(x ([-+\d.]+) mm, "
                          r"y ([-+\d.]+) mm\), yaw ([-+\d.]+) deg</h3>", text)
    assert captions and float(captions[0][1]) == pytest.approx(e.max(), abs=0.006)
    for k, pos, dx, dy, _ in captions:
        assert float(pos) == pytest.approx(err[int(k)], abs=0.006)
        assert float(pos) == pytest.approx(math.hypot(float(dx), float(dy)), abs=0.01)
    assert "<h2>overlay colours</h2>" in text
    for _, colour, meaning in legend_rows():
        assert f"color:{colour};" in text and html.escape(meaning) in text


def test_a_corridor_replay_says_why_poses_tum_is_empty(tmp_path, caplog):
    res = replay(FIXTURES / "corridor_rec", tmp_path / "out", method="corridor", tum=True,
                 report=True, start_pose=(0.0, 0.244558, math.radians(8.262851)))
    tum = [ln for ln in (tmp_path / "out" / "poses.tum").read_text().splitlines()
           if not ln.startswith("#")]
    assert tum == [] and res.telemetry.frames == 8
    said = [r.getMessage() for r in caplog.records if "poses.tum" in r.getMessage()]
    assert len(said) == 1 and "8 poses without x" in said[0] and "\n" not in said[0]
    text = res.report.read_text()
    assert "note: 8 poses have no x" in text and "lateral error" in text
    assert "<tr><td>lateral (y) [mm]</td><td>8</td>" in text
    assert "<tr><td>x [mm]</td>" not in text


@pytest.mark.skipif(shutil.which(CHROMIUM) is None,
                    reason="Debian's chromium is not installed (.ci/run installs it)")
def test_the_summary_fits_the_page_in_chromium(tmp_path):
    """The summary's long lines (the timing line is about 120 characters) wrap inside
    the report's 900 px column: no sideways scrolling (they ran 78 px past it)."""
    res = replay(FIXTURES / "lights_rec", tmp_path / "out", report=True)
    with Browser(tmp_path / "chromium", size=(1000, 800)) as browser:
        browser.open(res.report.as_uri())
        deadline = time.monotonic() + 30
        while browser.evaluate("document.readyState") != "complete":
            assert time.monotonic() < deadline
            time.sleep(0.1)
        pre = browser.evaluate("[...document.querySelectorAll('pre')]"
                               ".map(p => [p.scrollWidth, p.clientWidth])")
        page = browser.evaluate("[document.documentElement.scrollWidth, "
                                "document.documentElement.clientWidth]")
    assert pre and all(scroll <= client for scroll, client in pre), pre
    assert page[0] <= page[1], page
