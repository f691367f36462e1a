"""Reliability under faults (issue 17): SIGKILLs, a full disk, a port that appears late.

Prints the figures and saves them as JSON in ``--out``:

* ``kill``: ``--kills`` (50) recording runs of the simulator (``ceilrun --device
  sim:corridor --record R --serial PTY``, the serial side a pty opened by its path),
  each SIGKILLed at a random moment (seeded: a fifth 0-3 s after the process started,
  i.e. during start-up, the rest 0-4 s after the first ``$PCEIL`` reached the pty).
  For each: does the recording open and replay, and is every frame whose ``$PCEIL``
  reached the pty (its stamp) in the recording's frames.csv?
* ``disk``: a session recording onto a disk that fills mid-run and is freed later: a
  real 64 MB tmpfs (``mount -t tmpfs -o size=64m``, as root) filled by a ballast
  file to 1 MB free, the ballast deleted at frame 60
  or else the ``FullDisk`` fake. The pose stream's sentences, its longest gap between
  frames (wall time) against the same run without a fault, the lines logged, frames not
  recorded.
* ``wait``: ``ceilrun --wait`` started 10 s before its serial port (a pty) appears:
  whether anything was on disk before, the time from the port appearing to the first
  pose; and without ``--wait``: the lines printed, whether anything is on disk.

    .venv/bin/python benchmarks/bench_faults.py [--kills 50] [--out benchmarks/out/faults]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tty
from pathlib import Path

import numpy as np
from stated import stated  # noqa: E402  (the symmetric corridor's heading)

from ceilkit.runtime.io.recording import FullDisk, Recording, repair_recording
from ceilkit.runtime.replay import replay
from ceilkit.runtime.session import LinkConfig, SessionConfig, run_session

TMPFS_MB = 64          # holds a 300-frame sim recording (about 145 kB a frame)
ROOM_BYTES = 1_000_000  # what the ballast leaves free: the disk fills after a few frames
RUN = ("from ceilkit.cli.ceilrun import main; import sys; "
       "sys.argv = ['ceilrun', *sys.argv[1:]]; main()")


def _sent_ms(wire: Path) -> list[int]:
    if not wire.exists():
        return []
    return _stamps_ms(wire.read_bytes())


def _stamps_ms(data: bytes) -> list[int]:
    """The capture times (ms) of the whole ``$PCEIL`` sentences in ``data``."""
    return [int(line.split(b",")[2]) for line in data.split(b"\r\n")[:-1]
            if line.startswith(b"$PCEIL,")]


class _Pty:
    """A pseudo-terminal pair: ceilrun opens the slave by its path (``/dev/pts/N``) as a
    serial port; a thread reads everything that reaches the master (the controller)."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.data = bytearray()
        self.first_pose: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            if select.select([self.master], [], [], 0.02)[0]:
                try:
                    chunk = os.read(self.master, 65536)
                except OSError:
                    return
                self.data += chunk
                if self.first_pose is None and b"$PCEIL" in self.data:
                    self.first_pose = time.monotonic()

    def close(self) -> bytes:
        if self._stop.is_set():
            return bytes(self.data)
        time.sleep(0.1)  # what the kernel still holds for the master
        self._stop.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)
        return bytes(self.data)


def bench_kills(n: int, seed: int, startup_share: float = 0.2) -> dict:
    """``n`` SIGKILLs of ``ceilrun --device sim:corridor --record R --serial PTY``: a
    share ``startup_share`` at 0-3 s after the process started (start-up: port, camera,
    folder), the rest at 0-4 s after the first ``$PCEIL`` reached the pty."""
    rng = np.random.default_rng(seed)
    out = {"kills": n, "replayed": 0, "no_folder": 0, "sent": 0, "sent_missing": 0,
           "frames": 0, "only_in_log": 0, "repaired": 0, "partial_left": 0,
           "serial": "pty (slave opened by its /dev/pts path)", "failures": [],
           "runs": []}
    for k in range(n):
        at_start = bool(rng.uniform() < startup_share)
        after = float(rng.uniform(0.0, 3.0 if at_start else 4.0))
        tmp = Path(tempfile.mkdtemp(prefix="bench_kill_"))
        rec, pty = tmp / "rec", _Pty()
        data = b""
        try:
            proc = subprocess.Popen([sys.executable, "-c", RUN, "--device", "sim:corridor",
                                     "--record", str(rec), "--serial", pty.path],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            if not at_start:
                deadline = time.monotonic() + 120
                while pty.first_pose is None and time.monotonic() < deadline \
                        and proc.poll() is None:
                    time.sleep(0.01)
            time.sleep(after)
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            data = pty.close()
            sent = set(_stamps_ms(data))
            out["sent"] += len(sent)
            out["partial_left"] += len(list(tmp.glob(".rec.partial*")))
            moment = f"{after:4.2f} s after {'start' if at_start else 'first pose'}"
            if not rec.exists():
                out["no_folder"] += 1
                out["sent_missing"] += len(sent)
                out["runs"].append({"at": moment, "sent": len(sent), "recorded": None})
                print(f"  kill {k:2d} {moment}: {len(sent):3d} sent, no recording yet")
                continue
            try:
                recording = Recording(rec)
                res = replay(rec, tmp / "replay", options=stated("corridor"))
                out["replayed"] += 1
            except Exception as exc:  # noqa: BLE001 - counted and shown
                out["failures"].append(f"kill {k} {moment}: {exc}")
                continue
            stamps = {int(t) // 1_000_000 for t in recording.t_ns}
            missing = len(sent - stamps)
            out["sent_missing"] += missing
            out["frames"] += len(recording)
            out["only_in_log"] += recording.logged
            out["repaired"] += repair_recording(rec)
            out["runs"].append({"at": moment, "sent": len(sent), "recorded": len(recording),
                                "replayed": res.telemetry.frames, "missing": missing,
                                "only_in_log": recording.logged})
            print(f"  kill {k:2d} {moment}: {len(sent):3d} sent, {len(recording):3d} "
                  f"recorded ({recording.logged} only in the log), {missing} sent but "
                  f"missing, {res.telemetry.frames} replayed")
        finally:
            pty.close()
            shutil.rmtree(tmp, ignore_errors=True)
    return out


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def _mount_tmpfs(path: Path) -> bool:
    if os.geteuid() != 0:
        return False
    path.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_MB}m", "tmpfs",
                           str(path)],
                          capture_output=True).returncode == 0


def _session(tmp: Path, record: Path, disk, on_frame, frames: int):
    handler = _Lines()
    logging.getLogger("ceilkit").addHandler(handler)
    logging.getLogger("ceilkit").setLevel(logging.WARNING)
    stamps: list[float] = []

    def frame(tel):
        stamps.append(time.monotonic())
        on_frame(tel)

    wire = tmp / f"wire-{record.name}.nmea"
    cfg = SessionConfig(device="sim:corridor", frames=frames, record=record,
                        link=LinkConfig(str(wire)), force=True, options=stated("corridor"))
    try:
        res = run_session(cfg, on_frame=frame, **({"disk": disk} if disk else {}))
    finally:
        logging.getLogger("ceilkit").removeHandler(handler)
    gaps = np.diff(stamps) * 1e3
    sent = _sent_ms(wire)
    return {"frames": res.telemetry.frames, "sentences": len(sent),
            "in_order": sent == sorted(sent), "max_gap_ms": float(gaps.max()),
            "median_gap_ms": float(np.median(gaps)), "recorded": res.run.recorded,
            "not_recorded": res.run.not_recorded, "lines": handler.lines,
            "report": res.lines()}


def bench_disk(frames: int) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench_disk_"))
    mnt = tmp / "small"
    real = _mount_tmpfs(mnt)
    try:
        base = _session(tmp, tmp / "baseline", None, lambda tel: None, frames)
        if real:
            ballast = mnt / "ballast"  # leaves room for a few frames only
            st = os.statvfs(mnt)
            ballast.write_bytes(b"\0" * (st.f_bavail * st.f_frsize - ROOM_BYTES))

            def free(tel):
                if tel.frames == 60 and ballast.exists():
                    ballast.unlink()

            fault = _session(tmp, mnt / "rec", None, free, frames)
            how = (f"tmpfs size={TMPFS_MB}m filled by a ballast file to "
                   f"{ROOM_BYTES // 1000} kB free, the ballast deleted at frame 60")
        else:
            disk = FullDisk(fail_after_bytes=4_000_000)

            def free(tel):
                if tel.frames == 60:
                    disk.full = False

            fault = _session(tmp, tmp / "rec", disk, free, frames)
            how = "FullDisk fake (fills after 4 MB, freed at frame 60)"
    finally:
        if real:
            subprocess.run(["umount", str(mnt)], capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)
    return {"disk": how, "baseline": base, "fault": fault}


def bench_wait(delay_s: float) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench_wait_"))
    port = tmp / "ttyUSB0"
    try:
        proc = subprocess.Popen([sys.executable, "-c", RUN, "--device", "sim:corridor",
                                 "--frames", "30", "--record", str(tmp / "rec"), "--out",
                                 str(tmp / "run"), "--serial", str(port), "--wait"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(delay_s)
        before = sorted(p.name for p in tmp.iterdir())
        master, slave = os.openpty()
        os.symlink(os.ttyname(slave), port)
        t_plug = time.monotonic()
        data, first = b"", None
        while proc.poll() is None or select.select([master], [], [], 0)[0]:
            if select.select([master], [], [], 0.05)[0]:
                data += os.read(master, 65536)
                if first is None and b"$PCEIL" in data:
                    first = time.monotonic() - t_plug
        err = proc.stderr.read().decode()
        os.close(master)
        os.close(slave)
        waited = {"delay_s": delay_s, "on_disk_before_port": before,
                  "first_pose_after_port_s": first, "poses": data.count(b"$PCEIL"),
                  "exit": proc.returncode, "recorded": len(Recording(tmp / "rec")),
                  "stderr_first_line": err.splitlines()[0] if err else ""}
        shutil.rmtree(tmp / "rec")
        shutil.rmtree(tmp / "run")
        port.unlink()
        res = subprocess.run([sys.executable, "-c", RUN, "--device", "sim:corridor",
                              "--frames", "30", "--record", str(tmp / "rec"), "--out",
                              str(tmp / "run"), "--serial", str(port)],
                             capture_output=True, text=True)
        no_wait = {"exit": res.returncode, "stderr": res.stderr.strip().splitlines(),
                   "on_disk": sorted(p.name for p in tmp.iterdir())}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"wait": waited, "no_wait": no_wait}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kills", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--wait-s", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/faults"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"kill: {args.kills} SIGKILLs at random moments (seed {args.seed})")
    kills = bench_kills(args.kills, args.seed)
    print(f"  {kills['replayed']} of {kills['kills'] - kills['no_folder']} recordings "
          f"replayed ({kills['no_folder']} killed before the recording existed); "
          f"{kills['sent']} poses sent, {kills['sent_missing']} of their frames missing "
          f"from the recording; {kills['frames']} frames recorded, "
          f"{kills['only_in_log']} of them only in the write-ahead log (repaired "
          f"{kills['repaired']}); half-made folders left: {kills['partial_left']}")
    for f in kills["failures"]:
        print("  FAILED", f)
    print("disk: the disk fills mid-run")
    disk = bench_disk(args.frames)
    for name in ("baseline", "fault"):
        d = disk[name]
        print(f"  {name:8s}: {d['frames']} frames, {d['sentences']} sentences "
              f"(in order: {d['in_order']}), frame gap median {d['median_gap_ms']:.1f} "
              f"ms, max {d['max_gap_ms']:.1f} ms; recorded {d['recorded']}, not recorded "
              f"{d['not_recorded']}")
    print(f"  ({disk['disk']})")
    for line in disk["fault"]["lines"]:
        print("  log:", line)
    print(f"wait: the serial port appears {args.wait_s:g} s after the start")
    wait = bench_wait(args.wait_s)
    w, nw = wait["wait"], wait["no_wait"]
    print(f"  --wait: on disk before the port: {w['on_disk_before_port']}; first pose "
          f"{w['first_pose_after_port_s']:.2f} s after the port appeared; {w['poses']} "
          f"poses, {w['recorded']} frames recorded, exit {w['exit']}")
    print(f"  without --wait: exit {nw['exit']}, stderr {nw['stderr']}, on disk "
          f"{nw['on_disk']}")
    res = {"kill": kills, "disk": disk, "wait": wait}
    (args.out / "faults.json").write_text(json.dumps(res, indent=1))
    print(f"  saved {args.out / 'faults.json'}")


if __name__ == "__main__":
    main()
