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

Prints a table and saves it to ``benchmarks/out/bench_startup.csv``.

    .venv/bin/python benchmarks/bench_startup.py            # both
    .venv/bin/python benchmarks/bench_startup.py rss
    .venv/bin/python benchmarks/bench_startup.py first-pose --before /tmp/old --runs 2
"""

from __future__ import annotations

import argparse
import csv
import os
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


def peak_mb(args: list[str]) -> tuple[float, str]:
    """Peak RSS (MB) of ``ceilcal ARGS`` in a child process, and its first output line."""
    text, peak = child(CLI.format(args=args))
    return peak, (text.splitlines() or [""])[0][:70]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", nargs="?", choices=["first-pose", "rss", "all"], default="all")
    ap.add_argument("--runs", type=int, default=1, help="fresh/warm pairs, alternated")
    ap.add_argument("--before", help="a folder holding the code before as a `ceilkit` "
                    "package (e.g. `git archive HEAD` unpacked into BEFORE/ceilkit): "
                    "each run is then made with it and with the installed code, in turn")
    ap.add_argument("--after", help="the same for the code after (default: the installed)")
    args = ap.parse_args()
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
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
    OUT.parent.mkdir(exist_ok=True)
    keys = ["case", "first_wall_s", "first_cpu_s", "first_own_cpu_s", "end_wall_s",
            "end_cpu_s", "peak_rss_mb"]
    with OUT.open("w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"saved {OUT}")


if __name__ == "__main__":
    main()
