"""In-process A/B of one change: the same estimator twice, one with functions patched
back to an older file's, frames interleaved, every call timed.

A change to one stage (a compiled loop, a rewrite) is measured against the code before
it in one process, on the same frames and priors, the two copies called alternately
frame by frame (the order swapped every frame), so the machine's drift and its shared
caches fall on both alike. The older code is a file (``git show REV:path > old.py``);
each ``--patch MODULE:NAME=FILE:NAME`` sets ``MODULE.NAME`` to ``FILE``'s ``NAME`` for the
"before" copy's calls only (patch the name where it is looked up: the module that
imports it).

    git show 9a3f277:runtime/features/quads.py > /tmp/quads_old.py
    .venv/bin/python benchmarks/bench_ab.py block --track \\
        --patch ceilkit.runtime.estimators.block.detect:edge_points=/tmp/quads_old.py:edge_points

Prints the median and p95 thread CPU time per call of each copy, their ratio, and the
largest difference between the two copies' poses (decisions at thresholds may differ
from float rounding). The recordings are bench_all's (``benchmarks/out/recordings``;
run ``bench_all.py`` once to make them).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import importlib.util
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_all import load, make_estimator  # noqa: E402
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.tracking import Tracker  # noqa: E402

RECORDINGS = {"block": "block_60", "lights": "lights_60", "corridor": "corridor_60"}


def older(spec: str) -> tuple[object, str, object, object]:
    """``(module, name, before, after)`` of one ``MODULE:NAME=FILE:NAME``; the file is
    loaded as a sibling of ``MODULE``'s package (its relative imports resolve there)."""
    target, source = spec.split("=", 1)
    mod_name, name = target.split(":")
    path, src_name = source.rsplit(":", 1)
    mod = importlib.import_module(mod_name)
    pkg = mod_name.rsplit(".", 1)[0]
    # a name fixed by the path: numba's cache of the file's loops records it
    tag = hashlib.sha1(str(Path(path).resolve()).encode()).hexdigest()[:10]
    sp = importlib.util.spec_from_file_location(f"{pkg}._before_{tag}", path)
    old = importlib.util.module_from_spec(sp)
    sys.modules[sp.name] = old
    sp.loader.exec_module(old)
    return mod, name, getattr(old, src_name), getattr(mod, name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("method", choices=sorted(RECORDINGS))
    ap.add_argument("--track", action="store_true", help="the tracked path (a prior)")
    ap.add_argument("--patch", action="append", default=[], metavar="MOD:NAME=FILE:NAME")
    ap.add_argument("--reps", type=int, default=6, help="passes over the frames (1 warm-up)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    data = load(ROOT / "benchmarks" / "out" / "recordings" / RECORDINGS[args.method])
    patches = [older(s) for s in args.patch]

    def use(before: bool) -> None:
        for mod, name, old, new in patches:
            setattr(mod, name, old if before else new)

    opts = {"window_search": True} if args.track else None
    ests = [make_estimator(args.method, data.rig, data.site, stated(args.method, opts))
            for _ in range(2)]
    trackers = [Tracker(), Tracker()]
    times: list[list[float]] = [[], []]
    poses: list[list[object]] = [[], []]
    for rep in range(args.reps):
        for k in range(len(data.grey)):
            for w in ((0, 1) if (k + rep) % 2 == 0 else (1, 0)):
                use(before=w == 0)
                prior = trackers[w].predict(data.t_ns[k]) if args.track else None
                t0 = time.thread_time_ns()
                out = ests[w].estimate(data.grey[k], data.t_ns[k], prior)
                dt = time.thread_time_ns() - t0
                if args.track:
                    trackers[w].update(out)
                if rep > 0:
                    times[w].append(dt / 1e6)
                if rep == 1:
                    poses[w].append(out)
    use(before=False)
    for w, label in enumerate(("before", "after")):
        print(f"{label}: median {np.median(times[w]):.3f} ms, p95 "
              f"{np.percentile(times[w], 95):.3f} ms ({len(times[w])} calls)")
    print(f"after/before medians {np.median(times[1]) / np.median(times[0]):.3f}")
    both = [(a, b) for a, b in zip(*poses, strict=True)
            if getattr(a, "y_m", None) is not None and getattr(b, "y_m", None) is not None]
    if both:          # (the corridor gives no x)
        dpos = max(math.hypot((a.x_m or 0.0) - (b.x_m or 0.0), a.y_m - b.y_m) for a, b in both)
        dyaw = max(abs(math.remainder(a.yaw_rad - b.yaw_rad, 2 * math.pi)) for a, b in both)
        print(f"poses of both: {len(both)}, largest difference {1e3 * dpos:.4f} mm, "
              f"{math.degrees(dyaw):.2e} deg")


if __name__ == "__main__":
    main()
