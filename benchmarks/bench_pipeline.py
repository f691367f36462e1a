"""Benchmark of the live pipeline: grab-to-bytes latency, and a memory soak of replay.

**latency**: simulated 640x480 frames of configs/corridor, pre-rendered, served by a
fake camera device (``capture.FakeCamera``) at 30 and 60 fps through the real
``CameraSource`` (grabber thread, stamped with ``time.monotonic_ns`` at grab,
latest-frame policy), the ``corridor`` estimator, the tracker, and a ``SerialLink``
writing NMEA into a real pseudo-terminal (a thread drains the other end), run by
``run_live`` exactly as ``ceilrun`` runs it. Latency is from the grab stamp to the
pipeline's last sink returning (the link's bytes handed to the pty). Prints median /
p95 / max latency, per-stage medians, the pipeline's overhead (latency minus
estimator time), frames dropped by the latest-frame policy, and the median latency
of the first and last quarter of the run (no growth = the rate is sustained).
``--record`` adds a SPEC recording of every frame (written on its own thread).

**soak**: ``replay()`` of a 10 000-frame recording made by cycling the frames of
tests/fixtures/corridor_rec (symlinks; stamps continue at 10 Hz), poses into
``poses.csv`` and NMEA into a file; resident memory (``VmRSS``) after a warm-up of
500 frames and at the end; growth must stay below 10 MB.

OpenCV runs on one thread (``cv2.setNumThreads(1)``): figures are for one core.
The machine is shared, so compare figures measured in one run.

    .venv/bin/python benchmarks/bench_pipeline.py latency [--seconds 10] [--fps 30 60] [--record]
    .venv/bin/python benchmarks/bench_pipeline.py soak [--frames 10000] [--method corridor]
"""

from __future__ import annotations

import argparse
import os
import select
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.capture import CameraSource, FakeCamera
from ceilkit.runtime.io.link import SerialLink
from ceilkit.runtime.io.recording import PoseWriter, RecordingWriter
from ceilkit.runtime.live import run_live
from ceilkit.runtime.pipeline import Pipeline, PoseFileSink
from ceilkit.runtime.replay import replay
from ceilkit.runtime.sim.render import SimSource, straight_drive
from ceilkit.runtime.tracking import Tracker

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
FIXTURES = ROOT / "tests" / "fixtures"


def rss_mb() -> float:
    """Resident set size of this process, MB (``VmRSS`` of /proc/self/status)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class PtyPeer:
    """The controller's end of a pseudo-terminal, drained by a thread."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self.bytes = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.05)
            if r:
                try:
                    self.bytes += len(os.read(self.master, 65536))
                except OSError:
                    return

    def close(self) -> None:
        self._stop.set()
        self._t.join(2)
        os.close(self.master)
        os.close(self.slave)


def _pct(a, q: float) -> float:
    return float(np.percentile(np.asarray(a, dtype=float), q)) if len(a) else float("nan")


def latency(seconds: float, rates: list[float], record: bool) -> None:
    rig = Rig.load(CONFIGS / "corridor" / "rig.yaml")
    site = Site.load(CONFIGS / "corridor" / "site.yaml")
    n_img = 90
    traj = straight_drive(n_img, fps=30.0, speed_mps=0.8, y_m=0.1, weave_m=0.15,
                          yaw_wobble_rad=np.radians(4.0), rng=np.random.default_rng(0))
    sim = SimSource(rig, site, traj, seed=0)
    t = time.perf_counter()
    images = [sim.render(k).image for k in range(n_img)]
    print(f"rendered {n_img} frames {images[0].shape[1]}x{images[0].shape[0]} in "
          f"{time.perf_counter() - t:.1f} s (cycled)")
    print("fps   frames drop | latency ms: median   p95    max | first/last quarter "
          "median | stages ms (median): wait  estimate track output | overhead median p95")
    for fps in rates:
        tmp = Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
        cam = FakeCamera(images, fps)
        peer = PtyPeer()
        estimator = make_estimator("corridor", rig, site, stated("corridor"))
        n = int(round(seconds * fps))
        try:
            with CameraSource("fake", open_capture=cam.open) as source, \
                    SerialLink(peer.path, 115200, "nmea") as link, \
                    PoseWriter(tmp / "poses.csv") as writer:
                pipeline = Pipeline(estimator, [link, PoseFileSink(writer)], Tracker())
                rec = RecordingWriter(tmp / "rec", rig, site) if record else None
                res = run_live(source, pipeline, rec, max_frames=n)
                served = cam.served
        finally:
            peer.close()
            shutil.rmtree(tmp, ignore_errors=True)
        tel = res.telemetry
        lat = list(tel.latency_ms)
        est = list(tel.estimate_ms)
        over = [a - b for a, b in zip(lat, est, strict=True)]
        q = max(1, len(lat) // 4)
        print(f"{fps:4.0f} {tel.frames:7d} {tel.dropped:4d} | {_pct(lat, 50):17.2f} "
              f"{_pct(lat, 95):6.2f} {max(lat):6.2f} | {_pct(lat[:q], 50):8.2f} / "
              f"{_pct(lat[-q:], 50):5.2f}       | {_pct(tel.wait_ms, 50):27.2f} "
              f"{_pct(est, 50):9.2f} {_pct(tel.track_ms, 50):5.2f} "
              f"{_pct(tel.output_ms, 50):6.2f} | {_pct(over, 50):15.2f} {_pct(over, 95):5.2f}")
        print(f"      served by the camera {served}, processed {tel.frames}, "
              f"recorded {res.recorded}, link sent {link.counters.sent} "
              f"({peer.bytes} bytes), link dropped {link.counters.dropped}")


def make_soak_recording(folder: Path, n: int, source: Path) -> None:
    """A recording of ``n`` frames cycling ``source``'s frames (symlinks), stamps going on."""
    import csv

    (folder / "frames").mkdir(parents=True)
    for name in ("rig.yaml", "site.yaml", "camera.yaml"):
        if (source / name).exists():
            shutil.copy(source / name, folder / name)
    with open(source / "frames.csv", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))[1:]
    idx = [int(r[0]) for r in rows]
    stamps = [int(r[1]) for r in rows]
    period = (stamps[-1] - stamps[0]) // max(1, len(stamps) - 1) or 100_000_000
    with open(folder / "frames.csv", "w", encoding="utf-8") as fh:
        fh.write("index,t_ns\n")
        for k in range(n):
            src = source / "frames" / f"{idx[k % len(idx)]:06d}.png"
            os.symlink(src.resolve(), folder / "frames" / f"{k:06d}.png")
            fh.write(f"{k},{k * period}\n")


def soak(frames: int, method: str | None, recording: Path) -> None:
    tmp = Path(tempfile.mkdtemp(prefix="bench_soak_"))
    try:
        rec = tmp / "rec"
        make_soak_recording(rec, frames, recording)
        marks: dict[str, float] = {}

        def progress(done: int, total: int) -> None:
            if done == 500:
                marks["warm"] = rss_mb()
            if done % 2000 == 0 or done == total:
                sys.stdout.write(f"\r  {done}/{total} frames, RSS {rss_mb():.1f} MB")
                sys.stdout.flush()

        from ceilkit.runtime.io.link import FileLink

        t = time.perf_counter()
        with FileLink(tmp / "out.nmea", "nmea", append=False) as link:
            res = replay(rec, tmp / "out", method=method, sinks=[link], progress=progress,
                         options=stated(method))
        end = rss_mb()
        print()
        tel = res.telemetry
        print(f"soak {res.method}: {tel.frames} frames in {time.perf_counter() - t:.0f} s, "
              f"estimated {tel.estimated}, link sent {link.counters.sent}")
        growth = end - marks.get("warm", float("nan"))
        print(f"  RSS after 500 frames {marks.get('warm', float('nan')):.1f} MB, at the end "
              f"{end:.1f} MB: growth {growth:+.1f} MB "
              f"({'< 10 MB: ok' if growth < 10 else '>= 10 MB: LEAK'})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    a = sub.add_parser("latency")
    a.add_argument("--seconds", type=float, default=10.0)
    a.add_argument("--fps", type=float, nargs="+", default=[30.0, 60.0])
    a.add_argument("--record", action="store_true")
    b = sub.add_parser("soak")
    b.add_argument("--frames", type=int, default=10_000)
    b.add_argument("--method", default=None)
    b.add_argument("--recording", type=Path, default=FIXTURES / "corridor_rec")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"cv2.setNumThreads(1); {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    if args.what == "latency":
        latency(args.seconds, args.fps, args.record)
    else:
        soak(args.frames, args.method, args.recording)


if __name__ == "__main__":
    main()
