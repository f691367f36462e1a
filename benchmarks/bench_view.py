"""Benchmark: what the live web view adds to the per-frame path, with a client connected.

One process, one run: simulated corridor frames (configs/corridor, 640x480) go
through two pipelines of the same estimator, each with its own tracker: *without*
(the estimator, no sink) and *with* the view (the estimator behind the view's tap, the
view as a sink), with a client connected to the view the whole time: headless
Chromium showing the page (``--client chromium``, the default when it is installed)
or a Python client that reads the server-sent events and fetches every frame JPEG.
The two alternate in blocks of ``--block`` frames (the first ``--settle`` frames of
each block are not counted, so the encoder's work started in the other block has
settled), ``--blocks`` times each, at the camera's rate (``--fps``: the frames are
paced as a camera would deliver them, so the encoder thread runs between frames as it
does on the vehicle). The time of ``pipeline.process`` is measured per frame.

Prints the median and p95 per frame of each, their difference (the target is
<= 0.2 ms median), and the updates the client received; saves a histogram figure and
the numbers (JSON) in ``--out``.

    .venv/bin/python benchmarks/bench_view.py [--frames 40] [--blocks 6] [--block 50]
        [--fps 30] [--client chromium|python] [--out benchmarks/out/view]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.pipeline import Pipeline
from ceilkit.runtime.sim.render import SimOptions, render_frame
from ceilkit.runtime.tracking import Tracker
from ceilkit.runtime.viz import plots
from ceilkit.runtime.viz.web import LiveView

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "corridor"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run"]


def sim_frames(rig: Rig, site: Site, n: int) -> list[tuple[float, float, float, np.ndarray]]:
    """``n`` frames along the corridor, 0.05 m apart, with a gentle weave."""
    rng = np.random.default_rng(0)
    opts = SimOptions(noise_sigma=2.0, blur_px=0.8)
    out = []
    for k in range(n):
        x, y, yaw = 0.05 * k, 0.1 * math.sin(k / 7), math.radians(5 * math.sin(k / 11))
        out.append((x, y, yaw, render_frame(rig, site, x, y, yaw, options=opts, rng=rng)))
    return out


class PythonClient:
    """Reads the event stream and fetches the JPEG after each event, as the page does."""

    def __init__(self, url: str) -> None:
        self.url, self.events, self.frames = url, 0, 0
        self.stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        with urllib.request.urlopen(self.url + "events", timeout=30) as stream:
            for line in stream:
                if self.stop:
                    return
                if line.startswith(b"data: "):
                    self.events += 1
                    with urllib.request.urlopen(self.url + "frame.jpg", timeout=30) as r:
                        r.read()
                        self.frames += 1

    def close(self) -> None:
        self.stop = True


class ChromiumClient:
    """Headless Chromium with the page open (it runs until closed)."""

    def __init__(self, url: str) -> None:
        self.tmp = tempfile.TemporaryDirectory()
        self.proc = subprocess.Popen(
            [shutil.which("chromium") or "/usr/bin/chromium", *CHROMIUM_FLAGS,
             f"--user-data-dir={self.tmp.name}", "--remote-debugging-port=0", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=10)
        self.tmp.cleanup()


def run(args: argparse.Namespace) -> dict:
    cv2.setNumThreads(1)
    rig, site = Rig.load(CONFIGS / "rig.yaml"), Site.load(CONFIGS / "site.yaml")
    frames = sim_frames(rig, site, args.frames)
    plain = Pipeline(make_estimator("corridor", rig, site, stated("corridor")), [], Tracker())
    with LiveView(rig, site, port=0) as view:
        sinks: list = []
        est = make_estimator("corridor", rig, site, stated("corridor"))
        viewed = Pipeline(view.watch(est, sinks), sinks, Tracker())
        view.attach(viewed.telemetry)
        client = (ChromiumClient(view.url) if args.client == "chromium"
                  else PythonClient(view.url))
        time.sleep(args.warmup_s)  # the client connects, the page loads
        times: dict[str, list[float]] = {"without": [], "with": []}
        period_s = 1.0 / args.fps
        k = 0
        try:
            for _ in range(args.blocks):
                for name, pipeline in (("without", plain), ("with", viewed)):
                    for i in range(args.block):
                        _, _, _, image = frames[k % len(frames)]
                        due = time.perf_counter() + period_s
                        frame = Frame(image, 1_000_000_000 + k * 33_000_000, k)
                        t = time.perf_counter()
                        pipeline.process(frame)
                        dt = time.perf_counter() - t
                        if i >= args.settle:
                            times[name].append(dt * 1e3)
                        k += 1
                        while time.perf_counter() < due:
                            time.sleep(max(0.0, due - time.perf_counter()) * 0.9)
        finally:
            client.close()
        updates = view.seq
    w, wo = np.array(times["with"]), np.array(times["without"])
    return {"frames_each": int(w.size), "client": args.client, "fps": args.fps,
            "with_median_ms": float(np.median(w)), "with_p95_ms": float(np.percentile(w, 95)),
            "without_median_ms": float(np.median(wo)),
            "without_p95_ms": float(np.percentile(wo, 95)),
            "added_median_ms": float(np.median(w) - np.median(wo)),
            "view_updates": int(updates), "with_ms": w.tolist(), "without_ms": wo.tolist()}


def figure(res: dict, path: Path) -> None:
    plt = plots.pyplot()
    fig, ax = plt.subplots(figsize=plots.SIZE_IN)
    hi = float(np.percentile(res["with_ms"] + res["without_ms"], 99))
    bins = np.linspace(0, hi, 50)
    for name, colour in (("without", "tab:blue"), ("with", "tab:orange")):
        v = np.array(res[f"{name}_ms"])
        ax.hist(v, bins=bins, alpha=0.55, color=colour,
                label=f"{name} the view: median {np.median(v):.3f} ms")
    ax.set_xlabel("pipeline.process per frame [ms]")
    ax.set_ylabel("frames")
    ax.set_title(f"live view, {res['client']} client connected: added median "
                 f"{res['added_median_ms']:+.3f} ms")
    ax.legend(fontsize=8)
    path.write_bytes(plots.figure_png(fig))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=40, help="distinct frames (cycled)")
    ap.add_argument("--blocks", type=int, default=6)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--settle", type=int, default=5)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--warmup-s", type=float, default=3.0)
    ap.add_argument("--client", choices=("chromium", "python"),
                    default="chromium" if shutil.which("chromium") else "python")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/view"))
    args = ap.parse_args()
    res = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    figure(res, args.out / "view_cost.png")
    (args.out / "view_cost.json").write_text(json.dumps(res, indent=1))
    print(f"live view cost, {res['client']} client, {res['frames_each']} frames each at "
          f"{res['fps']:g} fps, interleaved in blocks:")
    print(f"  without the view: median {res['without_median_ms']:.3f} ms, "
          f"p95 {res['without_p95_ms']:.3f} ms")
    print(f"  with the view:    median {res['with_median_ms']:.3f} ms, "
          f"p95 {res['with_p95_ms']:.3f} ms")
    print(f"  added: {res['added_median_ms']:+.3f} ms median per frame (target <= 0.2 ms); "
          f"{res['view_updates']} view updates")
    print(f"  saved {args.out / 'view_cost.png'} and {args.out / 'view_cost.json'}")


if __name__ == "__main__":
    main()
