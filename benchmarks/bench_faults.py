"""Reliability under faults (issues 17, 40): SIGKILLs, a full disk, a late port, a battery.

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
* ``battery`` (issue 40): bad inputs and faults run as a user runs them (the console
  scripts, one folder per case): every numeric flag out of range and every text flag
  empty (from the CLI's own parameter table), every output over a file the user made,
  over an input, or while another run holds its lock, damaged frames, special and
  pathological files, bad contents, link odometry with no link, two runs into one
  output. Each case ends ``clean``, ``silent-wrong``, ``data-loss``, ``traceback``,
  ``hang`` or ``unnamed`` (:data:`OUTCOMES`); printed beside the issue's counts.

    .venv/bin/python benchmarks/bench_faults.py [--kills 50] [--out benchmarks/out/faults]
    .venv/bin/python benchmarks/bench_faults.py --only battery [--cases 'replay|--rig']
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
from collections.abc import Callable
from dataclasses import dataclass
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


# -- the battery (issue 40): bad inputs and faults run from outside ------------------------
OUTCOMES = ("clean", "silent-wrong", "data-loss", "traceback", "hang", "unnamed")
"""How a battery case ends: ``clean`` (refused in one line naming what it must, nothing
lost; or, for a case that must run, it ran right), ``silent-wrong`` (exit 0 where a
refusal was due, or a wrong result), ``data-loss`` (a file the user had changed),
``traceback``, ``hang`` (no exit within the case's time), ``unnamed`` (refused, but not
in one line naming the flag or the file and key the user gave)."""
BASELINE = {"cases": 553, "clean": 456, "silent-wrong": 21, "data-loss": 8, "traceback": 8,
            "hang": 2, "unnamed": 58}
"""The battery of issue 40 run against main before it (its counts, from the issue)."""
MARK = b"what the user made\n"
REC_FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "corridor_rec"


@dataclass
class Case:
    """One battery case: ``argv`` (the tool first; ``{t}`` the case's folder, ``{rec}`` a
    copy of the 8-frame corridor recording in it), run as a user runs it."""

    family: str
    name: str
    argv: list[str]
    names: tuple[str, ...] = ()   # words the one error line must hold (flag, file, key)
    guard: tuple[str, ...] = ()   # files made by the user (MARK) that must stay as they are
    refused: bool = True          # False: the case must run (exit 0) and pass ``check``
    setup: Callable[[Path], Callable[[], None] | None] | None = None  # returns a cleanup
    check: Callable[[Path, subprocess.CompletedProcess], str | None] | None = None
    timeout_s: float = 180.0  # at a load of 13 a first start compiles for ~60 s


def _tool(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def _run_case(case: Case) -> dict:
    with tempfile.TemporaryDirectory(prefix="battery-") as tmp:
        t = Path(tmp)
        rec = shutil.copytree(REC_FIXTURE, t / "rec")
        for g in case.guard:
            path = Path(g.format(t=t, rec=rec))
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(MARK)
        end = case.setup(t) if case.setup is not None else None
        argv = [_tool(case.argv[0])] + [a.format(t=t, rec=rec) for a in case.argv[1:]]
        try:
            proc = subprocess.run(argv, capture_output=True, text=True, cwd=t,
                                  timeout=case.timeout_s, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            return {"outcome": "hang", "line": ""}
        finally:
            if end is not None:
                end()
        outcome, line = _outcome(case, t, rec, proc)
        return {"outcome": outcome, "line": line, "exit": proc.returncode}


def _outcome(case: Case, t: Path, rec: Path, proc: subprocess.CompletedProcess):
    errors = [ln for ln in proc.stderr.splitlines() if ": error: " in ln]
    line = errors[-1] if errors else (proc.stderr.strip().splitlines() or [""])[-1]
    if "Traceback (most recent call last)" in proc.stderr:
        return "traceback", line
    if any(Path(g.format(t=t, rec=rec)).read_bytes() != MARK for g in case.guard):
        return "data-loss", line
    if case.check is not None and (verdict := case.check(t, proc)) is not None:
        return verdict, line
    if not case.refused:
        return ("clean" if proc.returncode == 0 else "silent-wrong"), line
    if proc.returncode == 0:
        return "silent-wrong", line
    words = [w.format(t=t, rec=rec) for w in case.names]
    one = len(errors) == 1 and errors[0].startswith(f"{case.argv[0]}: error: ")
    return ("clean" if one and all(w in line for w in words) else "unnamed"), line


def _commands():
    import typer.main

    from ceilkit.cli.ceilcal import app as ceilcal_app
    from ceilkit.cli.ceilrun import app as ceilrun_app
    for prog, app in (("ceilrun", ceilrun_app), ("ceilcal", ceilcal_app)):
        top = typer.main.get_command(app)
        yield prog, "", top
        for name, cmd in top.commands.items():
            yield prog, name, cmd


def _required(cmd, name: str) -> list[str]:
    from ceilkit.cli.values import flag_name, numeric_kind, range_of

    out: list[str] = []
    for p in cmd.params:
        if getattr(p, "required", False):
            kind, flag = numeric_kind(p), flag_name(p)
            span = range_of(name, flag) if kind else None
            value = (str(int(span.hi)) if kind is int else f"{span.hi:g}") if span else "x"
            out += [value] if p.param_type_name == "argument" else [flag, value]
    return out


OWN_HEADS = {"board": ["--board", "chess:9x6", "--square", "0.025", "--out", "{t}/b.pdf"],
             "autopilot": ["--rig", "{rec}/rig.yaml", "--firmware", "ardupilot-4.6"]}
"""Valid values for the commands that check their own arguments first (a bad value of
another flag is then the only fault of the case)."""


def _textual(param) -> bool:
    """A parameter that takes one text or path."""
    kind = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    if kind is None:
        kind = getattr(getattr(param, "type", None), "name", "")
    return not getattr(param, "multiple", False) and kind in (str, Path, "text", "path")


def value_cases() -> list[Case]:
    """Every numeric flag of every command (from the CLI's own parameter table) given
    NaN, infinities, a value below its range, -1 and a huge one; every text flag given
    an empty string: each refused in one line naming the flag."""
    from ceilkit.cli.values import EMPTY_OK, flag_name, numeric_kind, range_of

    cases = []
    for prog, name, cmd in _commands():
        head = [prog] + ([name] if name else []) + OWN_HEADS.get(name, _required(cmd, name))
        for p in cmd.params:
            if p.param_type_name == "argument" or getattr(p, "is_flag", False):
                continue
            flag, kind = flag_name(p), numeric_kind(p)
            if kind is None:
                if flag in EMPTY_OK or getattr(p, "required", False) or not _textual(p):
                    continue
                bad = [""]
            else:
                span = range_of(name, flag)
                below = span.lo if span is not None and span.lo_open else \
                    (span.lo - 1 if span is not None else -1)
                bad = (["nan", "inf", "-inf"] if kind is float else []) + [
                    str(int(below)) if kind is int else repr(float(below))]
                bad += ["-1"] if span is None or span.lo >= 0 else []
                bad.append("99999999999999999999" if kind is int else "1e308")
            for v in dict.fromkeys(bad):
                cases.append(Case("bad value", f"{prog} {name} {flag} {v!r}".replace("  ", " "),
                                  [*head, flag, v], names=(flag,)))
    return cases


REPLAY = ["ceilrun", "replay", "{rec}", "--out", "{t}/o", "--method", "corridor"]
LIVE = ["ceilrun", "--device", "sim:corridor", "--frames", "2", "--no-realtime"]
MOUNT = ["ceilcal", "mount", "{t}/p.yaml", "--site", "{rec}/site.yaml", "--camera",
         "{t}/c.yaml", "--out", "{t}/rig.yaml"]
BOARD = ["--board", "chess:9x6", "--square", "0.025"]
WRITES = [  # (file made by the user, the command that would write it)
    ("o/poses.csv", REPLAY), ("o/run.yaml", REPLAY), ("o/poses.tum", [*REPLAY, "--tum"]),
    ("o/truth.tum", [*REPLAY, "--tum"]), ("o/report.html", [*REPLAY, "--report"]),
    ("ov/000003.png", [*REPLAY, "--overlays", "{t}/ov"]),
    ("link.nmea", [*REPLAY, "--serial", "{t}/link.nmea"]),
    ("o/poses.csv", [*LIVE, "--out", "{t}/o"]), ("o/run.yaml", [*LIVE, "--out", "{t}/o"]),
    ("link.nmea", [*LIVE, "--serial", "{t}/link.nmea"]),
    ("cam.yaml", ["ceilcal", "intrinsics", "{t}", *BOARD, "--out", "{t}/cam.yaml"]),
    ("pl/views.png", ["ceilcal", "intrinsics", "{t}", *BOARD, "--out", "{t}/cam.yaml",
                      "--plots", "{t}/pl"]),
    ("cam.yaml", ["ceilcal", "intrinsics", "--ceiling", "{rec}", "--out", "{t}/cam.yaml"]),
    ("rig.yaml", MOUNT), ("rig.urdf.xml", MOUNT), ("rig.static_tf.sh", MOUNT),
    ("pl/mount_residuals.png", [*MOUNT, "--plots", "{t}/pl"]),
    ("site.yaml", ["ceilcal", "lightmap", "{rec}", "--out", "{t}/site.yaml"]),
    ("pl/lightmap.png", ["ceilcal", "lightmap", "{rec}", "--out", "{t}/site.yaml",
                         "--plots", "{t}/pl"]),
    ("capture.yaml", ["ceilcal", "exposure", "--device", "sim:lights", "--out",
                      "{t}/capture.yaml"]),
    ("chk/check-site.yaml", ["ceilcal", "check-site", "--rig", "{rec}/rig.yaml", "--site",
                             "{rec}/site.yaml", "--out", "{t}/chk"]),
    ("b.pdf", ["ceilcal", "board", *BOARD, "--out", "{t}/b.pdf"]),
    ("ap.param", ["ceilcal", "autopilot", "--rig", "{rec}/rig.yaml", "--firmware",
                  "ardupilot-4.6", "--out", "{t}/ap.param"]),
    ("rec.mcap", ["ceilrun", "convert", "{rec}", "{t}/rec.mcap"]),
]
OVERLAPS = [  # (extra replay arguments, the flag named, a recording file that must stay)
    (["--serial", "{rec}/frames/000000.png"], "--serial", "{rec}/frames/000000.png"),
    (["--overlays", "{rec}/frames"], "--overlays", "{rec}/frames/000000.png"),
    (["--serial", "{rec}/truth.csv"], "--serial", "{rec}/truth.csv"),
    (["--serial", "{t}/o/poses.csv"], "--serial", None),
    (["--tum", "--serial", "{t}/o/poses.tum"], "--serial", None),
    (["--odometry", "{t}/odo.csv", "--serial", "{t}/odo.csv"], "--serial", "{t}/odo.csv"),
]


def overwrite_cases() -> list[Case]:
    """Every output over a file the user made, without ``--force``; every output over an
    input of the run; the lone calibration files while another run writes them."""
    cases = []
    for made, argv in WRITES:
        names = ("{t}/" + made, "--force")
        cases.append(Case("data loss", f"{' '.join(argv[:2])} over {made}", argv, names,
                          guard=("{t}/" + made,)))
        if "/" not in made and argv[0] == "ceilcal":
            cases.append(Case("data loss", f"{' '.join(argv[:2])} --force while another "
                              f"run writes {made}", [*argv, "--force"],
                              ("another run", "is writing"), guard=("{t}/" + made,),
                              setup=_holding(made)))
    for extra, flag, kept in OVERLAPS:
        guard = () if kept is None or "{rec}" in kept else (kept,)
        case = Case("data loss", f"replay {' '.join(extra)}", [*REPLAY, *extra, "--force"],
                    (flag,), guard=guard)  # a guarded file is there (MARK) already
        if kept is not None and "{rec}" in kept:
            case.check = _unchanged(kept)
        cases.append(case)
    return cases


def _unchanged(rel: str):
    def check(t: Path, proc) -> str | None:
        now = Path(rel.format(t=t, rec=t / "rec")).read_bytes()
        was = (REC_FIXTURE / rel.replace("{rec}/", "")).read_bytes()
        return None if now == was else "data-loss"
    return check


def _holding(made: str):
    """A setup that starts another process holding ``made``'s lock (another run writing
    it); it returns what ends that process after the case."""
    def setup(t: Path) -> Callable[[], None]:
        holder = subprocess.Popen(
            [sys.executable, "-c", "import sys\nfrom ceilkit.runtime.io.outputs import "
             "file_lock\nwith file_lock(sys.argv[1]):\n    print('held', flush=True)\n"
             "    sys.stdin.read()\n", str(t / made)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        holder.stdout.readline()

        def end() -> None:
            holder.stdin.close()
            holder.wait()
        return end
    return setup


def _damage(rel: str, how: str):
    def setup(t: Path) -> None:
        path = t / "rec" / rel
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2] if how == "half" else data[:-12])
    return setup


def _jpeg_folder(t: Path) -> None:
    import cv2

    img = cv2.imread(str(REC_FIXTURE / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
    (t / "imgs").mkdir()
    for k in range(3):
        data = cv2.imencode(".jpg", img)[1].tobytes()
        (t / "imgs" / f"{k:06d}.jpg").write_bytes(data[:2000] if k == 1 else data)


def _no_pose_at(t_ns: int | None, poses: str):
    """The run's row at ``t_ns`` (None: the second row) is a failure, not a pose."""
    def check(t: Path, proc) -> str | None:
        import csv
        path = t / poses
        if not path.exists():
            return "silent-wrong"
        rows = list(csv.DictReader(path.open()))
        row = rows[1] if t_ns is None else next(
            (r for r in rows if int(r["t_ns"]) == t_ns), None)
        named = "bad_frame" in proc.stderr or "truncated" in proc.stderr
        return None if row is not None and row["yaw_deg"] == "" and named else "silent-wrong"
    return check


def damage_cases() -> list[Case]:
    """A damaged frame is a failure naming the file, never a pose."""
    out = []
    for how in ("half", "no end"):
        out.append(Case("damaged frame", f"replay, frame 2 PNG cut ({how})", REPLAY,
                        refused=False, setup=_damage("frames/000002.png", how),
                        check=_no_pose_at(200_000_000, "o/poses.csv")))
    out.append(Case("damaged frame", "image folder, a JPEG cut in half",
                    ["ceilrun", "--device", "{t}/imgs", "--rig", "{rec}/rig.yaml", "--site",
                     "{rec}/site.yaml", "--method", "corridor", "--out", "{t}/o"],
                    refused=False, setup=_jpeg_folder, check=_no_pose_at(None, "o/poses.csv")))
    return out


def _special(kind: str):
    """A setup making ``{t}/in`` a file of ``kind`` (its path is the case's input)."""
    def setup(t: Path) -> None:
        path = t / "in"
        if kind == "fifo":
            os.mkfifo(path)
        elif kind == "folder":
            path.mkdir()
        elif kind == "device":
            path.symlink_to("/dev/zero")
        elif kind != "missing":
            path.write_bytes(SPECIAL_BYTES[kind]())
    return setup


SPECIAL_BYTES = {
    "empty": lambda: b"",
    "binary": lambda: np.random.default_rng(0).bytes(4096),
    "a list": lambda: b"- 1\n- 2\n",
    "9 MiB": lambda: b"a: 1\n" * (9 << 18),
    "7 MB key": lambda: b"k" * 7_000_000 + b": 1\n",
    "base-60 number": lambda: b"a: " + b"1:" * 1_000_000 + b"1\n",
    "deep nesting": lambda: b"a: " + b"[" * 100_000 + b"\n",
}


def special_cases() -> list[Case]:
    """Inputs that are not what they claim: a FIFO, a device, a folder, a missing, empty,
    binary or huge file, a pathological YAML, as --rig, --site, --camera, --odometry,
    and a recording's own truth.csv; each one line naming the file, within the time."""
    kinds = ["fifo", "device", "folder", "missing", *SPECIAL_BYTES]
    uses = [("--rig", REPLAY), ("--site", REPLAY), ("--camera", MOUNT[:-4] + MOUNT[-2:]),
            ("--odometry", REPLAY)]
    out = []
    for flag, argv in uses:
        for kind in kinds:
            if flag == "--odometry" and kind in ("9 MiB", "7 MB key", "deep nesting"):
                continue  # CSV: its cap is 256 MiB
            out.append(Case("special file", f"{argv[1]} {flag} {kind}",
                            [*argv, flag, "{t}/in"], ("{t}/in",), setup=_special(kind)))
    for kind in ("fifo", "device", "folder", "binary"):
        out.append(Case("special file", f"replay, the recording's truth.csv {kind}", REPLAY,
                        ("truth.csv",), setup=_inside_rec("truth.csv", kind)))
    return out


def _inside_rec(name: str, kind: str):
    def setup(t: Path) -> None:
        (t / "rec" / name).unlink()
        _special(kind)(t)
        os.replace(t / "in", t / "rec" / name)
    return setup


def _write(rel: str, text: str):
    def setup(t: Path) -> None:
        (t / rel).write_text(text)
    return setup


def _edit(rel: str, old: str, new: str):
    def setup(t: Path) -> None:
        path = t / rel
        path.write_text(path.read_text().replace(old, new, 1))
    return setup


def content_cases() -> list[Case]:
    """Files that read but hold wrong values; link odometry asked for but not readable."""
    odo = "t_ns,dx,dy,dyaw_deg\n0,0,0,0\n100000000,1e308,0,0\n"
    return [
        Case("bad content", "rig.yaml k1: 1e308", [*REPLAY, "--rig", "{t}/rig.yaml"],
             ("{t}/rig.yaml", "distortion_coefficients"), setup=_copy_edit_rig()),
        Case("bad content", "truth.csv out of time order", REPLAY, ("truth.csv", "t_ns"),
             setup=_swap_truth_rows),
        Case("bad content", "odometry.csv dx 1e308",
             [*REPLAY[:-2], "--method", "auto", "--odometry", "{t}/odo.csv"],
             ("odo.csv", "dx"), setup=_write("odo.csv", odo)),
        Case("bad content", "--start-pose 1,2", [*REPLAY, "--start-pose", "1,2"],
             ("--start-pose",)),
        Case("bad content", "--method magic", [*REPLAY[:-1], "magic"], ("--method",)),
        Case("link", "--link-odometry without --serial", [*LIVE, "--link-odometry"],
             ("--link-odometry",)),
        Case("link", "--link-odometry --serial -", [*LIVE, "--link-odometry", "--serial", "-"],
             ("--link-odometry",)),
        Case("link", "--link-odometry to a file",
             [*LIVE, "--link-odometry", "--serial", "{t}/x.nmea"], ("--link-odometry",)),
        Case("link", "--view-token ''", [*LIVE, "--view", "127.0.0.1:0", "--view-token", ""],
             ("--view-token",)),
    ]


def _copy_edit_rig():
    def setup(t: Path) -> None:
        text = (t / "rec" / "rig.yaml").read_text()
        head, sep, rest = text.partition("distortion_coefficients:")
        body = rest.split("data: [", 1)
        (t / "rig.yaml").write_text(head + sep + body[0] + "data: [1e308, " + body[1])
    return setup


def _swap_truth_rows(t: Path) -> None:
    path = t / "rec" / "truth.csv"
    lines = path.read_text().splitlines(keepends=True)
    lines[2], lines[3] = lines[3], lines[2]
    path.write_text("".join(lines))


def _twice(argv: list[str], verify: Callable[[Path], bool]):
    """Two runs of ``argv`` at once into one output: one writes it whole, the other is
    refused; a setup starting the first, and the check."""
    first: dict = {}

    def setup(t: Path) -> Callable[[], None]:
        full = [_tool(argv[0])] + [a.format(t=t, rec=t / "rec") for a in argv[1:]]
        first["proc"] = subprocess.Popen(full, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.PIPE, text=True, cwd=t)
        return lambda: first.update(rc=first["proc"].wait(240))

    def check(t: Path, proc) -> str:
        ok = sorted([first["rc"], proc.returncode]) == [0, 1]
        return "clean" if ok and verify(t) else "silent-wrong"
    return setup, check


def concurrent_cases() -> list[Case]:
    def poses_whole(t: Path) -> bool:
        return len((t / "o" / "poses.csv").read_text().splitlines()) == 9

    def recording_whole(t: Path) -> bool:
        from ceilkit.runtime.io.recording import Recording
        return len(Recording(t / "r")) == 2

    out = []
    for name, argv, verify in (("two replays into one --out", REPLAY, poses_whole),
                               ("two --record into one folder", [*LIVE, "--record", "{t}/r"],
                                recording_whole)):
        setup, check = _twice(argv, verify)
        out.append(Case("concurrent", name, argv, refused=False, setup=setup, check=check,
                        timeout_s=240))
    return out


def battery_cases() -> list[Case]:
    return (value_cases() + overwrite_cases() + damage_cases() + special_cases()
            + content_cases() + concurrent_cases())


def bench_battery(workers: int = 2, only: str = "") -> dict:
    """Run every battery case (``only``: those whose name holds one of its
    ``|``-separated parts), ``workers`` at a
    time; the counts of each outcome, overall and by family, and each case that did
    not end clean with its last error line."""
    from concurrent.futures import ThreadPoolExecutor

    cases = [c for c in battery_cases() if any(o in c.name for o in only.split("|"))]
    with ThreadPoolExecutor(workers) as pool:
        results = list(pool.map(_run_case, cases))
    counts = {k: 0 for k in OUTCOMES}
    families: dict[str, dict[str, int]] = {}
    bad = []
    for case, res in zip(cases, results, strict=True):
        counts[res["outcome"]] += 1
        fam = families.setdefault(case.family, {k: 0 for k in OUTCOMES})
        fam[res["outcome"]] += 1
        if res["outcome"] != "clean":
            bad.append({"case": case.name, **res})
    return {"cases": len(cases), "counts": counts, "families": families, "not_clean": bad}


def print_battery(res: dict) -> None:
    c = res["counts"]
    print(f"  {res['cases']} cases: " + ", ".join(f"{c[k]} {k}" for k in OUTCOMES))
    print(f"  before (issue 40, {BASELINE['cases']} cases): "
          + ", ".join(f"{BASELINE[k]} {k}" for k in OUTCOMES))
    for fam, n in res["families"].items():
        print(f"    {fam:14s} {sum(n.values()):4d}: "
              + ", ".join(f"{v} {k}" for k, v in n.items() if v))
    for b in res["not_clean"]:
        print(f"  {b['outcome'].upper()}: {b['case']} (exit {b.get('exit')}): {b['line']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kills", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--wait-s", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/faults"))
    ap.add_argument("--only", choices=("battery",), help="run the battery only")
    ap.add_argument("--cases", default="",
                    help="battery: the cases whose name holds one of these (A|B)")
    ap.add_argument("--workers", type=int, default=2, help="battery: cases at a time")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.only == "battery":
        print("battery: bad inputs and faults, each run as a user runs it")
        res = bench_battery(args.workers, args.cases)
        print_battery(res)
        (args.out / "battery.json").write_text(json.dumps(res, indent=1))
        print(f"  saved {args.out / 'battery.json'}")
        return
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
    print("battery: bad inputs and faults, each run as a user runs it")
    battery = bench_battery(args.workers, args.cases)
    print_battery(battery)
    res = {"kill": kills, "disk": disk, "wait": wait, "battery": battery}
    (args.out / "faults.json").write_text(json.dumps(res, indent=1))
    print(f"  saved {args.out / 'faults.json'}")


if __name__ == "__main__":
    main()
