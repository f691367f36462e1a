"""Does a ROS 2 replay lose anything? ``ceilrun replay REC --ros2`` through the CLI (a
subprocess, as a user runs it) to a real rclpy subscriber in another process started
first, ``--runs`` times (five by default), on a 100-frame recording (the lights fixture
forth and back, ``tests/ros2_listen.py``).

Per run: poses in ``poses.csv``, poses received, camera_info and overlay images
received, the CLI's wall time; ``--baseline`` adds the same runs without waiting for
subscribers or for acknowledgements (``--ros2-wait 0``, ``flush_s=0``, volatile), the
behaviour before issue 37.

Output: a table on stdout and ``benchmarks/out/bench_ros2_replay.csv`` (``--out``) with
the ``#`` provenance header of ``bench_all.py``. ROS_LOCALHOST_ONLY=1, a domain of its
own.

    .venv/bin/python benchmarks/bench_ros2_replay.py [--runs 5] [--baseline]
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
from pathlib import Path

from bench_all import provenance

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from ros2_listen import pingpong_recording, replay_to_listener, ros_env  # noqa: E402

BASELINE = ("--ros2-wait", "0", "--ros2-param", "flush_s=0",
            "--ros2-param", "transient_local=false")


def one_run(rec: Path, out: Path, domain: int, args: tuple[str, ...]) -> dict:
    got, cli, elapsed = replay_to_listener(rec, out, ros_env(domain), *args)
    if cli.returncode != 0:
        raise SystemExit(f"ceilrun replay failed: {cli.stderr.strip()[-400:]}")
    with open(out / "poses.csv", newline="") as fh:
        published = sum(1 for r in csv.DictReader(fh) if r["y"] != "")
    return {"published": published, "received": len(got["poses"]),
            "camera_info": len(got["camera_info"]), "images": len(got["images"]),
            "cli_s": round(elapsed, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--baseline", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" /
                    "bench_ros2_replay.csv")
    a = ap.parse_args()
    load0 = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-ros2-") as tmp:
        rec = pingpong_recording(Path(tmp) / "rec", a.frames)
        configs = [("wait+flush", ())] + ([("baseline", BASELINE)] if a.baseline else [])
        for k in range(a.runs):
            for name, args in configs:   # alternating: a load change hits both alike
                r = one_run(rec, Path(tmp) / f"{name}{k}", 120 + os.getpid() % 80, args)
                rows.append({"config": name, "run": k + 1, **r})
                print(f"{name:11s} run {k + 1}: received {r['received']}/{r['published']} "
                      f"poses, {r['camera_info']} camera_info, {r['images']} images, "
                      f"CLI {r['cli_s']:.1f} s", flush=True)
    for name, _ in configs:
        mine = [r for r in rows if r["config"] == name]
        whole = sum(r["received"] == r["published"] for r in mine)
        print(f"{name}: every pose received in {whole} of {len(mine)} runs")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    head = provenance("bench_ros2_replay.py", load0, os.getloadavg(),
                      [f"# {a.frames}-frame CLI replays to an rclpy subscriber process"])
    with open(a.out, "w", newline="") as fh:
        fh.write("\n".join(head) + "\n")
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"-> {a.out}")


if __name__ == "__main__":
    main()
