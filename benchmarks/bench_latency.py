"""Grab-to-bytes latency with and without the tracked fast path, through the real loop.

Simulated 640x480 frames (``configs/corridor`` and ``configs/lights``, a weaving drive,
pre-rendered) are served by a fake camera device (``capture.FakeCamera``) through the
real ``CameraSource`` (grabber thread, stamped with ``time.monotonic_ns`` at grab,
latest-frame policy), the estimator (``window_search`` on or off), the
:class:`~ceilkit.runtime.tracking.Tracker` and a ``SerialLink`` writing NMEA into a
real pseudo-terminal, run by ``run_live`` as ``ceilrun`` runs it. The other end of the
terminal is drained by another process, as a controller is (``--peer-thread``: by a thread
of this process, as before: a thread woken by every write competes for the GIL at the
moment the loop takes it back, which is the benchmark's, not the vehicle's).
Latency is the pipeline's ``latency_ms``: from the grab stamp to the link's
bytes written (the link is the only sink). Besides it, per frame: the estimator's time
and the rest (``latency - estimate``: queueing, copy and grey conversion, tracking,
encoding, writing), and its share of the latency; the rest split into ``wait`` (grab
stamp to the loop taking the frame), ``track`` (prior and gate) and ``output`` (encode
and write).

The configurations run in short runs (``--run-s`` seconds each) alternating round by
round (``--rounds``), so a load change on the shared machine hits them alike; the
figures pool every frame of every round. OpenCV runs on one thread.

Output: a table on stdout and ``benchmarks/out/bench_latency.csv`` (``--out``) with the
same ``#`` provenance header as ``bench_all.py``.

    .venv/bin/python benchmarks/bench_latency.py [--fps 30] [--rounds 4] [--run-s 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from bench_all import provenance
from bench_pipeline import PtyPeer
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.estimators.registry import make_estimator
from ceilkit.runtime.io.capture import CameraSource, FakeCamera
from ceilkit.runtime.io.link import SerialLink
from ceilkit.runtime.live import run_live
from ceilkit.runtime.pipeline import Pipeline
from ceilkit.runtime.sim.render import SimSource, straight_drive
from ceilkit.runtime.tracking import Tracker

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
CONFIGS = ROOT / "configs"
COLUMNS = ["config", "method", "track", "frames", "dropped", "estimated",
           "latency_med_ms", "latency_p95_ms", "estimate_med_ms", "rest_med_ms",
           "rest_p95_ms", "rest_share_med", "wait_med_ms", "track_med_ms", "output_med_ms"]
DRAIN = "import os, sys\nwhile os.read(int(sys.argv[1]), 65536):\n    pass\n"


class ProcessPeer:
    """The controller's end of a pseudo-terminal, drained by a child process."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self._proc = subprocess.Popen([sys.executable, "-c", DRAIN, str(self.master)],
                                      pass_fds=(self.master,))

    def close(self) -> None:
        self._proc.terminate()
        self._proc.wait(5)
        os.close(self.master)
        os.close(self.slave)


def frames_of(config: str, n: int) -> tuple[Rig, Site, list[np.ndarray]]:
    """The config's rig and site and ``n`` rendered frames of a weaving drive."""
    rig = Rig.load(CONFIGS / config / "rig.yaml")
    site = Site.load(CONFIGS / config / "site.yaml")
    traj = straight_drive(n, fps=30.0, speed_mps=0.8, y_m=0.1, weave_m=0.15,
                          yaw_wobble_rad=np.radians(4.0), rng=np.random.default_rng(0))
    sim = SimSource(rig, site, traj, seed=0)
    return rig, site, [sim.render(k).image for k in range(n)]


def one_run(rig: Rig, site: Site, method: str, track: bool, images: list[np.ndarray],
            fps: float, seconds: float, peer_thread: bool = False
            ) -> dict[str, list[float] | int]:
    """One live run: the telemetry's per-frame lists and counters."""
    cam = FakeCamera(images, fps)
    peer = PtyPeer() if peer_thread else ProcessPeer()
    est = make_estimator(method, rig, site, stated(method, {"window_search": track}))
    try:
        with CameraSource("fake", open_capture=cam.open) as source, \
                SerialLink(peer.path, 115200, "nmea") as link:
            pipeline = Pipeline(est, [link], Tracker())
            res = run_live(source, pipeline, None, max_frames=int(round(seconds * fps)))
    finally:
        peer.close()
    tel = res.telemetry
    return {"latency": list(tel.latency_ms), "estimate": list(tel.estimate_ms),
            "wait": list(tel.wait_ms), "track": list(tel.track_ms), "output": list(tel.output_ms),
            "frames": tel.frames, "dropped": tel.dropped, "estimated": tel.estimated}


def _q(a: list[float], p: float) -> float:
    return float(np.percentile(np.asarray(a, float), p)) if a else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--run-s", type=float, default=3.0, help="seconds per run")
    ap.add_argument("--out", type=Path, default=OUT / "bench_latency.csv")
    ap.add_argument("--peer-thread", action="store_true",
                    help="drain the terminal in a thread of this process, not a child")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    load0 = os.getloadavg()
    cases = [("corridor", "corridor"), ("lights", "lights")]
    data = {c: frames_of(c, 90) for c, _ in cases}
    pooled: dict[tuple[str, bool], dict[str, list]] = {}
    for r in range(args.rounds):
        order = [(c, m, t) for c, m in cases for t in (False, True)]
        if r % 2:
            order.reverse()
        for config, method, track in order:
            rig, site, images = data[config]
            got = one_run(rig, site, method, track, images, args.fps, args.run_s,
                          args.peer_thread)
            acc = pooled.setdefault((config, track), {"method": method})
            for k, v in got.items():
                acc[k] = acc.get(k, [] if isinstance(v, list) else 0) + v
    load1 = os.getloadavg()
    rows = []
    for (config, track), a in pooled.items():
        rest = [x - y for x, y in zip(a["latency"], a["estimate"], strict=True)]
        share = [x / y for x, y in zip(rest, a["latency"], strict=True) if y > 0]
        rows.append({"config": config, "method": a["method"], "track": track,
                     "frames": a["frames"], "dropped": a["dropped"],
                     "estimated": a["estimated"],
                     "latency_med_ms": _q(a["latency"], 50),
                     "latency_p95_ms": _q(a["latency"], 95),
                     "estimate_med_ms": _q(a["estimate"], 50),
                     "rest_med_ms": _q(rest, 50), "rest_p95_ms": _q(rest, 95),
                     "rest_share_med": _q(share, 50), "wait_med_ms": _q(a["wait"], 50),
                     "track_med_ms": _q(a["track"], 50),
                     "output_med_ms": _q(a["output"], 50)})
    print(f"{'config':9s} {'track':5s} {'frames':>6s} {'drop':>4s} {'lat med':>8s} "
          f"{'p95':>6s} {'est med':>8s} {'rest med':>8s} {'p95':>6s} {'share':>6s} "
          f"{'wait':>6s} {'track':>6s} {'output':>6s}")
    for w in rows:
        print(f"{w['config']:9s} {str(w['track']):5s} {w['frames']:6d} {w['dropped']:4d} "
              f"{w['latency_med_ms']:8.3f} {w['latency_p95_ms']:6.3f} "
              f"{w['estimate_med_ms']:8.3f} {w['rest_med_ms']:8.3f} {w['rest_p95_ms']:6.3f} "
              f"{w['rest_share_med']:6.2f} {w['wait_med_ms']:6.3f} {w['track_med_ms']:6.3f} "
              f"{w['output_med_ms']:6.3f}")
    prov = provenance("bench_latency.py", load0, load1, [
        f"# fps {args.fps}  rounds {args.rounds}  run {args.run_s} s  peer "
        f"{'thread' if args.peer_thread else 'process'}; times in ms, medians and p95 "
        "over every frame of every round"])
    print("\n".join(prov))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        fh.write("\n".join(prov) + "\n" + ",".join(COLUMNS) + "\n")
        for w in rows:
            fh.write(",".join(f"{w[c]:.4f}" if isinstance(w[c], float) else str(w[c])
                              for c in COLUMNS) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
