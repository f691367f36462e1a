"""Start-up of the command line: the first pose on a fresh machine, and the peak memory
of each ``ceilcal`` command.

``first-pose``: the README's first command (``ceilrun --device sim:corridor --serial -
--frames 150 ... --option assume_heading_deg=0``) in a child process, with numba's
cache in a new empty folder (``NUMBA_CACHE_DIR``: a fresh machine), then again on that
cache (a later start). For each: wall seconds and the child's CPU seconds (all its
threads, from ``/proc/PID/stat``, with its compile helpers; and its own alone, which
bounds the wall time on an idle machine with a CPU per process) when its first pose
sentence reaches stdout, and when it ends. ``--runs N`` makes N such pairs; with
``--before`` each pair is made with the code before and after, in turn.

``rss``: the peak resident memory (VmHWM, read by the child when it ends: ``getrusage``
of an exec'd child starts at the parent's) of ``ceilcal board`` at 25 mm squares on A4,
and of ``ceilcal COMMAND --help`` for every other command (what its start-up imports).

``frame-zero`` (issue 37: frame 0's latency within 2x the median of the rest): the
packaged examples (``ceilcal simulate`` drives of 120 frames, seed 1; the office's
ceiling map built from a second drive, seed 2, every 8th frame at its true pose)
replayed by each method (and ``auto``) from the true start pose (the default σ, and
for the office also ``X,Y,YAW,0.05,5``) and without one, each in a fresh process
(``--runs`` of each, alternated), OpenCV on one thread. Per replay: frame 0's
``latency_ms`` against the median of the other frames', and the same in thread CPU
(``Pipeline.process`` timed by ``time.thread_time_ns``: on a shared machine the wall
time is mostly the scheduler's); then frame 0 again in that process with a new
localizer built as ``ceilrun`` builds it (the least of three): its search alone, with
every first-call cost (imports, compiled loops, tables, the first OpenCV calls) paid.
``first_call_cpu_ms`` is frame 0's CPU less that. Saved to
``benchmarks/out/bench_startup_frame0.csv``.

Prints a table and saves it to ``benchmarks/out/bench_startup.csv``.

    .venv/bin/python benchmarks/bench_startup.py            # first-pose and rss
    .venv/bin/python benchmarks/bench_startup.py rss
    .venv/bin/python benchmarks/bench_startup.py first-pose --before /tmp/old --runs 2
    .venv/bin/python benchmarks/bench_startup.py frame-zero --runs 3 [--after TREE]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_board import CLI, child

OUT = Path(__file__).parent / "out" / "bench_startup.csv"
FIRST = ["--device", "sim:corridor", "--serial", "-", "--frames", "150",
         "--option", "assume_heading_deg=0"]
TICK = os.sysconf("SC_CLK_TCK")
COMMANDS = ["simulate", "intrinsics", "mount", "lightmap", "calibrate", "board",
            "exposure", "autopilot", "check-site"]


def cpu_s(pid: int) -> tuple[float, float]:
    """User + system CPU seconds of process ``pid`` (all its threads) so far: its own,
    and with its children that ended (the compile helpers)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(f) for f in fields[11:13]) / TICK, sum(int(f) for f in fields[11:15]) / TICK


def first_pose(cache: Path, out: Path, tree: str | None) -> dict[str, float]:
    """One run of the README's first command on numba cache ``cache`` (with ``tree``, a
    folder holding a ``ceilkit`` package, first on the path): the wall and CPU seconds
    at its first pose sentence and at its end."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    if tree:
        env["PYTHONPATH"] = tree
    exe = Path(sys.executable).parent / "ceilrun"
    t0 = time.perf_counter()
    proc = subprocess.Popen([str(exe), *FIRST, "--out", str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first_wall = first_cpu = first_own = float("nan")
    for line in proc.stdout:
        if line.startswith("$") and first_wall != first_wall:
            first_wall = time.perf_counter() - t0
            first_own, first_cpu = cpu_s(proc.pid)
    # the CPU of the whole run: read before reaping, when the process has exited
    stderr = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"ceilrun failed ({proc.returncode}):\n{stderr}")
    return {"first_wall_s": first_wall, "first_cpu_s": first_cpu,
            "first_own_cpu_s": first_own,
            "end_wall_s": time.perf_counter() - t0,
            "end_cpu_s": usage.ru_utime + usage.ru_stime}


FRAME_ZERO = [("corridor", "corridor"), ("corridor", "auto"), ("lights", "lights"),
              ("lights", "auto"), ("block", "block"), ("block", "auto"),
              ("office", "texture"), ("office", "auto")]
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
OUT0 = OUT.parent / "bench_startup_frame0.csv"
CHILD = r"""
import json, sys, time
import cv2
cv2.setNumThreads(1)
from ceilkit.runtime import pipeline as P
from ceilkit.runtime.io.mcap_rec import open_recording
from ceilkit.runtime.multi import make_localizer
from ceilkit.runtime.replay import replay

rec_path, out, method, start = sys.argv[1:5]
start = None if start == "none" else tuple(float(v) for v in start.split(","))
cpu, process, first = [], P.Pipeline.process, []

def timed(self, frame, capture_ns=None):   # the frame's thread CPU, as latency_ms spans it
    c0 = time.thread_time_ns()
    got = process(self, frame, capture_ns)
    cpu.append((time.thread_time_ns() - c0) / 1e6)
    first[:] = first or [got]              # the replay's own frame 0
    return got

P.Pipeline.process = timed
res = replay(rec_path, out, method=method, start_pose=start, force=True)
run = {"latency": list(res.telemetry.latency_ms), "cpu": list(cpu), "again": []}
rec = open_recording(rec_path)
for _ in range(3):    # frame 0 again: a new localizer, every first-call cost paid
    est, tracker = make_localizer(method, rec.rig, rec.site, None, start, False)
    cpu.clear()
    got = P.Pipeline(est, [], tracker).process(rec.frame(0), capture_ns=time.monotonic_ns())
    run["again"].append(cpu[0])
got = first[0]
run["frame0"] = str(getattr(got, "reason", None) or got.provenance.name)
print(json.dumps(run))
"""


def examples(folder: Path) -> dict[str, Path]:
    """The packaged examples as ``ceilcal simulate`` drives (120 frames, seed 1), by
    config; the office's site given a ceiling map built from a second drive (seed 2)."""
    cli = Path(sys.executable).parent / "ceilcal"
    recs = {}
    for config in sorted({c for c, _ in FRAME_ZERO}):
        drives = [(1, config)] + ([(2, "office_map")] if config == "office" else [])
        for seed, name in drives:
            subprocess.run([str(cli), "simulate", "--out", str(folder / name), "--rig",
                            str(CONFIGS / config / "rig.yaml"), "--site",
                            str(CONFIGS / config / "site.yaml"), "--frames", "120",
                            "--seed", str(seed)], check=True, capture_output=True)
        recs[config] = folder / config
    office_map(folder / "office_map", folder / "office.npz")
    with (folder / "office" / "site.yaml").open("a") as f:
        f.write(f"ceiling_map: {folder / 'office.npz'}\n")
    return recs


def office_map(rec: Path, out: Path) -> None:
    """The ceiling map of drive ``rec``: every 8th frame at its true pose."""
    import cv2

    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site
    from ceilkit.runtime.estimators.texture import build_map

    rows = start_rows(rec)[::8]
    frames = [cv2.imread(str(rec / "frames" / f"{int(k):06d}.png"), cv2.IMREAD_GRAYSCALE)
              for k, _ in rows]
    build_map(frames, [p for _, p in rows], Rig.load(rec / "rig.yaml"),
              Site.load(rec / "site.yaml").ceiling_height_m).save(out)


def start_rows(rec: Path) -> list[tuple[int, tuple[float, float, float]]]:
    """``(frame, (x, y, yaw rad))`` of each row of the drive's ``truth.csv``."""
    with (rec / "truth.csv").open() as f:
        return [(k, (float(r["x"]), float(r["y"]), math.radians(float(r["yaw_deg"]))))
                for k, r in enumerate(csv.DictReader(f))]


def frame_zero_run(rec: Path, method: str, start: str, out: Path,
                   tree: str | None) -> dict[str, float | str]:
    """One replay in a fresh process (:data:`CHILD`): frame 0 against the rest."""
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    if tree:
        env["PYTHONPATH"] = tree
    proc = subprocess.run([sys.executable, "-c", CHILD, str(rec), str(out), method, start],
                          capture_output=True, text=True, env=env)
    if proc.returncode:
        raise SystemExit(f"replay failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    d = json.loads(proc.stdout.strip().splitlines()[-1])
    lat, cpu, again = d["latency"], d["cpu"], min(d["again"])
    return {"frame0_ms": lat[0], "rest_med_ms": statistics.median(lat[1:]),
            "ratio": lat[0] / statistics.median(lat[1:]), "frame0_cpu_ms": cpu[0],
            "rest_cpu_med_ms": statistics.median(cpu[1:]),
            "cpu_ratio": cpu[0] / statistics.median(cpu[1:]), "again_cpu_ms": again,
            "first_call_cpu_ms": cpu[0] - again, "frame0": d["frame0"]}


def frame_zero(folder: Path, runs: int, tree: str | None) -> list[dict[str, object]]:
    """Every case of :data:`FRAME_ZERO`, from the start pose and without, ``runs`` times
    (round by round, alternated)."""
    recs = examples(folder)
    rows: list[dict[str, object]] = []
    for r in range(runs):
        order = FRAME_ZERO if r % 2 == 0 else FRAME_ZERO[::-1]
        for config, method in order:
            x, y, yaw = start_rows(recs[config])[0][1]
            starts = [("start", f"{x},{y},{yaw}"), ("none", "none")]
            if config == "office":
                starts.insert(1, ("start 0.05", f"{x},{y},{yaw},0.05,{math.radians(5)}"))
            for kind, start in starts:
                got = frame_zero_run(recs[config], method, start, folder / "out", tree)
                rows.append({"config": config, "method": method, "start": kind,
                             "run": r, **got})
                print(f"{config:8s} {method:8s} {kind:10s} frame 0 {got['frame0_ms']:7.2f} "
                      f"ms, rest {got['rest_med_ms']:6.2f} ({got['ratio']:5.2f}x); CPU "
                      f"{got['frame0_cpu_ms']:6.2f}, {got['rest_cpu_med_ms']:5.2f} "
                      f"({got['cpu_ratio']:4.2f}x), again {got['again_cpu_ms']:5.2f}; "
                      f"{got['frame0']}", flush=True)
    return rows


def peak_mb(args: list[str]) -> tuple[float, str]:
    """Peak RSS (MB) of ``ceilcal ARGS`` in a child process, and its first output line."""
    text, peak = child(CLI.format(args=args))
    return peak, (text.splitlines() or [""])[0][:70]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", nargs="?", choices=["first-pose", "rss", "all", "frame-zero"],
                    default="all")
    ap.add_argument("--runs", type=int, default=1,
                    help="fresh/warm pairs (first-pose) or rounds of replays (frame-zero), "
                    "alternated")
    ap.add_argument("--before", help="a folder holding the code before as a `ceilkit` "
                    "package (e.g. `git archive HEAD` unpacked into BEFORE/ceilkit): "
                    "each run is then made with it and with the installed code, in turn")
    ap.add_argument("--after", help="the same for the code after (default: the installed)")
    args = ap.parse_args()
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        if args.what == "frame-zero":
            write_rows(OUT0, frame_zero(tmp_path, args.runs, args.after))
            return
        if args.what in ("first-pose", "all"):
            trees = [("before", args.before), ("after", args.after)] if args.before else [
                ("", args.after)]
            for i in range(args.runs):
                for label, tree in trees:
                    cache = tmp_path / f"cache{i}{label}"
                    cache.mkdir()
                    for kind in ("fresh", "warm"):
                        r = first_pose(cache, tmp_path / f"run{i}{label}{kind}", tree)
                        case = f"first pose, {kind} cache{', ' + label if label else ''}"
                        rows.append({"case": case, **r})
                        print(f"{case:32s}: first pose at {r['first_wall_s']:6.1f} s wall, "
                              f"{r['first_cpu_s']:6.1f} s CPU ({r['first_own_cpu_s']:.1f} "
                              f"s its own); end {r['end_wall_s']:6.1f} s "
                              f"wall, {r['end_cpu_s']:6.1f} s CPU", flush=True)
        if args.what in ("rss", "all"):
            board = ["board", "--board", "chess:9x6", "--square", "0.025",
                     "--out", str(tmp_path / "board.pdf")]
            cases = [("ceilcal board chess:9x6 0.025 a4", board)]
            cases += [(f"ceilcal {c} --help", [c, "--help"]) for c in COMMANDS]
            for name, cli in cases:
                peak, first = peak_mb(cli)
                rows.append({"case": name, "peak_rss_mb": peak})
                print(f"{name:36s} {peak:7.1f} MB   {first}", flush=True)
    write_rows(OUT, rows)


def write_rows(path: Path, rows: list[dict[str, object]]) -> None:
    """``rows`` as a CSV (the keys of all, in order of appearance)."""
    path.parent.mkdir(exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
