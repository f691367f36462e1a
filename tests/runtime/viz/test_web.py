"""The live web view: address parsing, the server's answers, and a real browser on a
simulated run (headless Chromium over the DevTools protocol)."""

from __future__ import annotations

import json
import math
import shutil
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from chromium_cdp import CHROMIUM, Browser

from ceilkit.runtime.devices import packaged_config
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.session import SessionConfig, run_session
from ceilkit.runtime.viz.web import LiveView, parse_view_address, pose_json


def _get(url: str, method: str = "GET", headers: dict | None = None) -> tuple[int, bytes]:
    req = urllib.request.Request(url, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_parse_view_address():
    assert parse_view_address("8080") == ("127.0.0.1", 8080)
    assert parse_view_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_view_address("[::1]:7000") == ("::1", 7000)
    for bad in ("", "host:", "x:70000", "abc"):
        with pytest.raises(ConfigError, match="view"):
            parse_view_address(bad)


def test_pose_json_pose_failure_and_unobserved_x():
    cov = np.diag([0.01, 0.04, 0.001])
    p = pose_json(PoseEstimate(5, "lights", 1.0, 2.0, math.pi / 2, 0.8, cov=cov))
    assert p["ok"] and p["x"] == 1.0 and p["yaw_deg"] == pytest.approx(90.0)
    assert p["cov_xy"] == [[0.01, 0.0], [0.0, 0.04]] and p["sigma_y"] == pytest.approx(0.2)
    c = pose_json(PoseEstimate(5, "corridor", None, 0.3, 0.0, 0.9,
                               cov=np.diag([np.inf, 0.0004, 1e-6])))
    assert c["x"] is None and c["cov_xy"] is None and c["sigma_y"] == pytest.approx(0.02)
    assert pose_json(Failure(7, "lights", "no_lights")) == {
        "ok": False, "t_ns": 7, "method": "lights", "reason": "no_lights"}
    json.dumps([p, c])  # what the page receives is JSON


def _lights():
    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site
    return Rig.load(packaged_config("lights") / "rig.yaml"), \
        Site.load(packaged_config("lights") / "site.yaml")


def test_server_token_read_only_and_frame():
    rig, site = _lights()
    with LiveView(rig, site, port=0, token="s3cret", period_s=0.05) as view:
        base = f"http://127.0.0.1:{view.port}"
        assert view.host == "127.0.0.1"
        assert _get(base + "/")[0] == 403
        assert _get(base + "/?token=wrong")[0] == 403
        assert _get(base + "/state.json")[0] == 403
        code, page = _get(base + "/?token=s3cret")
        assert code == 200 and b"EventSource" in page
        assert _get(base + "/site.json", headers={"X-Ceilkit-Token": "s3cret"})[0] == 200
        assert _get(base + "/frame.jpg?token=s3cret")[0] == 404  # nothing published yet
        assert _get(base + "/?token=s3cret", method="POST")[0] in (403, 405)
        assert _get(base + "/?token=s3cret", method="PUT")[0] in (403, 405)
        grey = np.full((rig.camera.height, rig.camera.width), 90, np.uint8)
        est = PoseEstimate(1_000, "lights", 1.0, 2.0, 0.1, 0.7, cov=np.eye(3) * 1e-4)
        view.publish(grey, est, est)
        code, jpeg = _get(base + "/frame.jpg?token=s3cret")
        assert code == 200 and jpeg[:2] == b"\xff\xd8"
        state = json.loads(_get(base + "/state.json?token=s3cret")[1])
        assert state["seq"] == 1 and state["pose"]["x"] == 1.0 and state["trail"] == [[1.0, 2.0]]
        site_map = json.loads(_get(base + "/site.json?token=s3cret")[1])
        assert len(site_map["lights"]) == len(site.lights_m)


def test_server_without_token_is_open_and_refuses_writes():
    rig, site = _lights()
    with LiveView(rig, site, port=0) as view:
        base = f"http://127.0.0.1:{view.port}"
        assert _get(base + "/")[0] == 200
        assert _get(base + "/", method="POST")[0] == 405
        assert _get(base + "/nothing")[0] == 404


def test_a_port_in_use_is_an_output_error():
    from ceilkit.runtime.errors import OutputError
    rig, site = _lights()
    with LiveView(rig, site, port=0) as view, pytest.raises(OutputError):
        with LiveView(rig, site, port=view.port):
            pass


def _page_state(browser: Browser) -> dict:
    return browser.evaluate(
        "JSON.stringify({frames: +document.getElementById('frames-loaded').textContent,"
        " poses: +document.getElementById('poses-seen').textContent,"
        " pose: document.getElementById('pose').textContent,"
        " width: document.getElementById('frame').naturalWidth})")


@pytest.mark.skipif(shutil.which(CHROMIUM) is None,
                    reason="Debian's chromium is not installed (.ci/run installs it)")
def test_live_view_of_a_sim_run_in_chromium(tmp_path):
    """A simulated run served with a token: the page itself shows frames and poses that
    change; a request without the token is refused; a screenshot is kept."""
    port = _free_port()
    stop = threading.Event()
    # (the simulated corridor is symmetric about its centre line: its heading is stated)
    config = SessionConfig(device="sim:corridor", frames=100_000, view=f"127.0.0.1:{port}",
                           view_token="tok3n", options={"assume_heading_deg": 0.0})
    result = {}
    run = threading.Thread(target=lambda: result.setdefault("r", run_session(config, stop)),
                           daemon=True)
    run.start()
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        seq = 0
        while seq == 0 and time.monotonic() < deadline:
            time.sleep(0.2)
            try:
                code, body = _get(base + "/state.json?token=tok3n")
            except OSError:
                continue
            seq = json.loads(body).get("seq", 0) if code == 200 else 0
        assert seq > 0, "the view never published a frame"
        assert _get(base + "/")[0] == 403
        assert _get(base + "/events")[0] == 403
        with Browser(tmp_path / "chromium") as browser:
            browser.open(base + "/?token=tok3n")
            seen = []
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                time.sleep(0.5)
                seen.append(json.loads(_page_state(browser) or "{}"))
                if seen[-1].get("frames", 0) >= 4 and seen[-1].get("poses", 0) >= 4:
                    break
            last = seen[-1]
            assert last["frames"] >= 4, seen  # the frame image was reloaded, decoded
            assert last["poses"] >= 4, seen  # new poses (new stamps) reached the page
            # naturalWidth reads 0 while the image is being reloaded, so any sample may
            # catch a reload: every decoded frame has one width, and some sample has it
            widths = {s["width"] for s in seen if s.get("width", 0) > 0}
            assert len(widths) == 1, seen
            assert len({s["pose"] for s in seen if s.get("pose", "-") != "-"}) >= 2
            assert last["pose"].startswith("corridor")
            shot = browser.screenshot(tmp_path / "live_view.png")
            print(f"\nlive view screenshot: {shot}")
            assert shot.stat().st_size > 10_000
    finally:
        stop.set()
        run.join(timeout=30)
    assert result["r"].telemetry.frames > 0


def _wait_for(browser: Browser, expression: str, timeout_s: float = 20.0) -> dict:
    """The page's state (as :func:`_page_state` and more) once ``expression`` holds."""
    probe = ("JSON.stringify({ok: !!(" + expression + "),"
             " display: getComputedStyle(document.getElementById('frame')).display,"
             " waiting: getComputedStyle(document.getElementById('waiting')).display,"
             " pose: document.getElementById('pose').textContent,"
             " time: document.getElementById('time').textContent,"
             " quality: document.getElementById('quality').textContent,"
             " legend: document.querySelectorAll('table.legend tr').length})")
    deadline = time.monotonic() + timeout_s
    state = {}
    while time.monotonic() < deadline:
        state = json.loads(browser.evaluate(probe) or "{}")
        if state.get("ok"):
            return state
        time.sleep(0.1)
    raise AssertionError(f"the page never showed {expression}: {state}")


@pytest.mark.skipif(shutil.which(CHROMIUM) is None,
                    reason="Debian's chromium is not installed (.ci/run installs it)")
def test_the_page_before_the_first_frame_and_after_a_failure(tmp_path):
    """Nothing broken before the first frame (no image shown, a waiting line); a pose's
    time in seconds, not nanoseconds; a failure with no quality beside it; the
    overlays' legend on the page."""
    from ceilkit.runtime.viz.overlay import legend_rows

    rig, site = _lights()
    image = np.full((480, 640), 60, np.uint8)
    t0 = 1_780_000_000_123_456_789                      # a wall-clock stamp (2026)
    with LiveView(rig, site, port=0, period_s=60.0) as view, \
            Browser(tmp_path / "chromium") as browser:
        browser.open(f"http://127.0.0.1:{view.port}/")
        state = _wait_for(browser, "document.readyState === 'complete'")
        assert state["display"] == "none" and state["waiting"] != "none"
        assert state["legend"] == len(legend_rows())
        pose = PoseEstimate(t0, "lights", 1.0, 2.0, 0.0, 0.82)
        view.publish(image, pose, pose)
        state = _wait_for(browser, "document.getElementById('quality').textContent === '0.82'")
        state = _wait_for(browser, "getComputedStyle(document.getElementById('frame'))"
                                   ".display === 'block'")
        assert state["waiting"] == "none"
        assert state["time"].startswith("0.000 s") and "2026-05-28" in state["time"]
        assert str(t0) not in state["time"] + state["pose"]
        failed = Failure(t0 + 500_000_000, "lights", "no_lights")
        view.publish(image, failed, failed)
        state = _wait_for(browser, "document.getElementById('pose').textContent"
                                   ".includes('FAILED')")
        assert state["quality"] == "-" and "no_lights" in state["pose"]
        assert state["time"].startswith("0.500 s")
