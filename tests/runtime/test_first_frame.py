"""The first frame of a run is like the others: every import, table and compiled loop it
needs is made before it (issue 37: frame 0 was 0.5-2.3 s late while ``scipy.stats``
was imported on it).

A replay in a fresh process (imports and loops are per process): between the start of
the frame loop and the end of frame 0 no module is imported and no compiled loop is
loaded or compiled (the work itself, exactly). How late frame 0 is in wall time is a
benchmark's figure (``benchmarks/bench_startup.py``), not a test's: on a shared
machine a timed assertion fails by load alone.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import pytest

from helpers import FIXTURES

SCRIPT = r"""
import json, sys, time
import numba

def loaded():
    return sum(len(v.signatures) for m in list(sys.modules.values())
               if getattr(m, "__name__", "").startswith("ceilkit")
               for v in list(vars(m).values())
               if isinstance(v, numba.core.dispatcher.Dispatcher))

marks = []

def clock(_ns=time.monotonic_ns):
    if not marks:    # the first call: the replay's start, after the warm-up
        marks.append((sorted(sys.modules), loaded()))
    return _ns()

class Sink:   # after the poses file: its row (and latency) is written by then
    def send(self, est, relocalized, capture_ns):
        if len(marks) == 1:
            marks.append((sorted(sys.modules), loaded()))

from ceilkit.runtime.replay import replay

replay(sys.argv[1], sys.argv[2], method=sys.argv[3], sinks=[Sink()], clock=clock,
       start_pose=tuple(float(v) for v in sys.argv[4].split(",")))
(before, n0), (after, n1) = marks
print(json.dumps({"imported": sorted(set(after) - set(before)), "loops": n1 - n0}))
"""


@pytest.mark.parametrize("rec,method,start", [
    ("lights_rec", "auto", "3.0,0.0,0.0"),
    ("corridor_rec", "corridor", "0.0,0.244558,0.144213"),   # the README's method
])
def test_frame_zero_imports_and_compiles_nothing_and_is_not_late(tmp_path, rec, method,
                                                                 start):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(FIXTURES / rec), str(out), method, start],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    done = json.loads(proc.stdout.strip().splitlines()[-1])
    assert done == {"imported": [], "loops": 0}, done
    with (out / "poses.csv").open() as f:
        assert len(list(csv.DictReader(f))) >= 5
