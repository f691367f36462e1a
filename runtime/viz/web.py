"""The live web view (``ceilrun --view [HOST:]PORT``): the latest frame with its overlay,
the pose on the site map with its 1σ ellipse and trail, quality and link statistics.

The per-frame path only hands references over: :class:`~.tap.EstimateTap` keeps the
latest ``(frame, raw estimate)``, :meth:`LiveView.send` (a pose sink) the latest
published estimate. An encoder thread wakes every ``period_s`` (default 0.2 s: 5 frames
per second), draws the overlay, encodes a JPEG and publishes a state; a stdlib
``http.server`` in its own threads serves the page, the state as server-sent events
(``/events``), the JPEG (``/frame.jpg``) and the site map (``/site.json``). The page
draws the map on a canvas; it loads nothing from the network but this server.

Read-only: GET and HEAD only (anything else: 405). Bound to 127.0.0.1 unless a host
is given. With a token, every request needs ``?token=TOKEN`` (the page passes its own
on) or the header ``X-Ceilkit-Token: TOKEN``; without it: 403.

Example::

    with LiveView(rig, site, port=8080) as view:
        pipeline = Pipeline(view.watch(estimator), [*sinks, view], Tracker())
        view.attach(pipeline.telemetry)
        ...                              # run; open http://127.0.0.1:8080/
"""

from __future__ import annotations

import contextlib
import hmac
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import cv2
import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Estimate, Estimator, PoseEstimate
from ceilkit.runtime.viz.overlay import draw_overlay, encode_jpeg, legend_html
from ceilkit.runtime.viz.tap import EstimateTap

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
VIEW_PERIOD_S = 0.2
"""Seconds between frames sent to the page (the pose stream is never waited on)."""
VIEW_MAX_WIDTH_PX = 640
"""Frames are scaled down to this width before encoding."""
TRAIL_POSES = 300
"""Published positions kept for the trail."""
KEEPALIVE_S = 5.0


def parse_view_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` as ``(host, port)``; the host defaults to 127.0.0.1.

    Raises:
        ConfigError: ``view`` when it is not ``[HOST:]PORT`` with a port in 0..65535.
    """
    host, _, port = text.rpartition(":")
    host = host.strip("[]") or DEFAULT_HOST
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535:
        raise ConfigError(None, "view", f"expected [HOST:]PORT, found {text!r}")
    return host, number


def open_view(address: str | None, token: str | None, rig: Rig, site: Site,
              stack: contextlib.ExitStack,
              stats: Callable[[], Sequence[str]] | None = None) -> LiveView | None:
    """The live view at ``address`` (``[HOST:]PORT``), entered on ``stack``; None
    without an address (a session's ``view``, ``view_token``).

    Raises:
        ConfigError: ``view`` is not ``[HOST:]PORT``; ``view_token`` is empty (an unset
            variable would otherwise serve the view to anyone).
        OutputError: the address cannot be served (in use, not an address of this host).
    """
    if token is not None and not token.strip():
        raise ConfigError(None, "view_token", "expected a token, found an empty one (give "
                          "none to serve without a token)")
    if address is None:
        return None
    host, port = parse_view_address(address)
    return stack.enter_context(LiveView(rig, site, host, port, token, stats=stats))


def site_json(site: Site) -> dict[str, Any]:
    """The site map the page draws (W, metres)."""
    quads = [np.asarray(b.corners_m, float).tolist() for b in site.blocks]
    if site.markers is not None:
        quads += [m.corners_m().tolist() for m in site.markers.poses]
    return {
        "lines_along": list(site.corridor.lines_along_m) if site.corridor else [],
        "lamps": [r.tolist() for r in site.lamp_rectangles()],
        "lights": np.asarray(site.lights_m, float).reshape(-1, 2).tolist(),
        "quads": quads,
    }


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def pose_json(est: Estimate | None) -> dict[str, Any] | None:
    """The published estimate as the page shows it: pose, 1σ, quality, or the failure."""
    if est is None:
        return None
    if not isinstance(est, PoseEstimate):
        return {"ok": False, "t_ns": est.t_ns, "method": est.method, "reason": est.reason}
    cov = est.cov
    cov_xy = None
    if cov is not None and np.all(np.isfinite(cov[:2, :2])):
        cov_xy = [[float(cov[0, 0]), float(cov[0, 1])], [float(cov[1, 0]), float(cov[1, 1])]]
    sigma_y = (_finite(math.sqrt(cov[1, 1])) if cov is not None and cov[1, 1] >= 0 else None)
    return {"ok": True, "t_ns": est.t_ns, "method": est.method, "x": _finite(est.x_m),
            "y": _finite(est.y_m), "yaw_deg": math.degrees(est.yaw_rad),
            "quality": est.quality, "cov_xy": cov_xy, "sigma_y": sigma_y}


class LiveView:
    """The live view server; a pose sink; a context manager (see the module doc).

    Args:
        rig, site: what the run uses (overlays, the map).
        host, port: where to listen (port 0: any free port, see :attr:`port`).
        token: required of every request when set.
        period_s: seconds between frames sent to the page.
        stats: extra status lines (the link's counters), called by the encoder thread.
    """

    def __init__(self, rig: Rig, site: Site, host: str = DEFAULT_HOST, port: int = 0,
                 token: str | None = None, period_s: float = VIEW_PERIOD_S,
                 stats: Callable[[], Sequence[str]] | None = None) -> None:
        self.rig, self.site = rig, site
        self.host, self.port = host, port
        self.token = token or None
        self.period_s = period_s
        self.stats = stats
        self.telemetry: Any = None
        self._tap: EstimateTap | None = None
        self.published: Estimate | None = None  # the per-frame path writes only this
        self.site_bytes = json.dumps(site_json(site)).encode()
        self.cond = threading.Condition()
        self.seq = 0
        self.jpeg = b""
        self.state = b"{}"
        self.closing = False
        self._trail: list[tuple[float | None, float]] = []
        self._server: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    # -- the per-frame path: references only ----------------------------------------
    def watch(self, estimator: Estimator, sinks: list | None = None) -> EstimateTap:
        """``estimator`` wrapped so that each frame and its raw estimate reach the view;
        the view is appended to ``sinks`` (it then sees the published estimates)."""
        self._tap = EstimateTap(estimator)
        if sinks is not None:
            sinks.append(self)
        return self._tap

    def attach(self, telemetry: Any) -> None:
        """The run's telemetry (its counters are shown)."""
        self.telemetry = telemetry

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        self.published = est

    # -- lifecycle -------------------------------------------------------------------
    def __enter__(self) -> LiveView:
        handler = type("Handler", (_Handler,), {"view": self})
        try:
            self._server = ThreadingHTTPServer((self.host, self.port), handler)
        except OSError as exc:
            raise OutputError(f"{self.host}:{self.port}",
                              f"cannot serve the live view: {exc.strerror}") from None
        self._server.daemon_threads = True
        self.port = self._server.server_address[1]
        self._threads = [threading.Thread(target=self._server.serve_forever,
                                          name="view-http", daemon=True),
                         threading.Thread(target=self._encode_loop, name="view-encode",
                                          daemon=True)]
        for t in self._threads:
            t.start()
        log.warning("live view on %s", self.url)
        return self

    def __exit__(self, *exc: object) -> None:
        with self.cond:
            self.closing = True
            self.cond.notify_all()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        for t in self._threads:
            t.join(timeout=2.0)

    @property
    def url(self) -> str:
        q = f"?token={self.token}" if self.token else ""
        return f"http://{self.host}:{self.port}/{q}"

    # -- the encoder thread ----------------------------------------------------------
    def _encode_loop(self) -> None:
        seen = -1
        while not self.closing:
            time.sleep(self.period_s)
            tap = self._tap
            if tap is None or tap.latest is None or tap.count == seen:
                continue
            seen = tap.count
            self.publish(*tap.latest, self.published)

    def publish(self, image: np.ndarray, raw: Estimate, published: Estimate | None) -> None:
        """Draw, encode and publish one update (the encoder thread; tests call it)."""
        img = draw_overlay(image, raw, self.rig, self.site)
        if img.shape[1] > VIEW_MAX_WIDTH_PX:
            s = VIEW_MAX_WIDTH_PX / img.shape[1]
            img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        jpeg = encode_jpeg(img)
        pose = pose_json(published)
        if pose is not None and pose["ok"] and pose["y"] is not None:
            self._trail = (self._trail + [(pose["x"], pose["y"])])[-TRAIL_POSES:]
        state = {"seq": self.seq + 1, "pose": pose, "trail": self._trail,
                 "stats": self._stat_lines()}
        body = json.dumps(state).encode()
        with self.cond:
            self.jpeg, self.state = jpeg, body
            self.seq += 1
            self.cond.notify_all()

    def _stat_lines(self) -> list[str]:
        lines = []
        tel = self.telemetry
        if tel is not None:
            lines += list(tel.summary())
        if self.stats is not None:
            lines += list(self.stats())
        return lines

    def authorized(self, query: str, header: str | None) -> bool:
        if self.token is None:
            return True
        given = parse_qs(query).get("token", [header or ""])[0]
        return hmac.compare_digest(given.encode(), self.token.encode())


class _Handler(BaseHTTPRequestHandler):
    view: LiveView
    server_version = "ceilkit-view"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib's name
        log.debug("view: " + format, *args)

    def _refuse(self, code: int, text: str) -> None:
        body = (text + "\n").encode()
        self.send_response(code)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _send(self, ctype: str, body: bytes) -> None:
        self.send_response(200)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - stdlib's name
        url = urlsplit(self.path)
        view = self.view
        if not view.authorized(url.query, self.headers.get("X-Ceilkit-Token")):
            return self._refuse(403, "forbidden: a token is required (?token=...)")
        if url.path == "/":
            return self._send("text/html; charset=utf-8", PAGE.encode())
        if url.path == "/frame.jpg":
            with view.cond:
                jpeg = view.jpeg
            return self._send("image/jpeg", jpeg) if jpeg else self._refuse(404, "no frame yet")
        if url.path == "/state.json":
            with view.cond:
                state = view.state
            return self._send("application/json", state)
        if url.path == "/site.json":
            return self._send("application/json", view.site_bytes)
        if url.path == "/events":
            return self._events()
        return self._refuse(404, "not found")

    do_HEAD = do_GET  # noqa: N815

    def _events(self) -> None:
        """Server-sent events: the state after each update, until the view closes."""
        view = self.view
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        seq = -1
        try:
            while True:
                with view.cond:
                    view.cond.wait_for(lambda s=seq: view.closing or view.seq != s,
                                       KEEPALIVE_S)
                    if view.closing:
                        return
                    fresh = view.seq != seq
                    seq, state = view.seq, view.state
                self.wfile.write(b"data: " + state + b"\n\n" if fresh else b": keepalive\n\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            return

    def _read_only(self) -> None:
        self._refuse(405, "read-only: GET and HEAD only")

    do_POST = do_PUT = do_DELETE = do_PATCH = _read_only  # noqa: N815


PAGE = (Path(__file__).with_name("view.html")).read_text(encoding="utf-8").replace(
    "<!--LEGEND-->", legend_html())
"""The page: the frame (hidden until the first one arrives) with the overlays' legend,
a canvas with the map at one scale (8 m across, a grid in metres and a scale bar), the
pose and trail, the time, the quality (none beside a failure), the status lines; it
counts the frames and poses it has shown (``#frames-loaded``, ``#poses-seen``)."""
