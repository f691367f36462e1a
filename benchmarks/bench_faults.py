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
import contextlib
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
    if any(not _still_marked(Path(g.format(t=t, rec=rec))) for g in case.guard):
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


def _still_marked(path: Path) -> bool:
    """Whether ``path`` is still the user's file (MARK): not replaced, not removed."""
    return path.is_file() and path.read_bytes() == MARK


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
                bad += ["", _other_unit(span)]
            for v in dict.fromkeys(bad):
                cases.append(Case("bad value", f"{prog} {name} {flag} {v!r}".replace("  ", " "),
                                  [*head, flag, v], names=(flag,)))
    return cases


OTHER_UNITS = {"m": "mm", "m/s": "km/h", "s": "ms", "ms": "s", "degrees": "rad",
               "Hz": "kHz", "px": "mm", "bit/s": "kbit/s", "frames": "s",
               "grey levels": "%"}
"""A unit a user may type after a number by mistake, for each unit of a flag's range."""


def _other_unit(span) -> str:
    """A value in range written with a unit (``25mm`` for a flag in m): not a number."""
    unit = "" if span is None else span.unit.split(" (")[0]
    value = 1 if span is None else max(min(1.0, span.hi), span.lo + 1e-3)
    return f"{value:g}{OTHER_UNITS.get(unit, 'x')}"


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
        return _hold_in_another_process("file_lock(sys.argv[1])", t / made)
    return setup


def _hold_in_another_process(lock: str, path: Path) -> Callable[[], None]:
    """Start a process that enters ``with <lock>:`` (Python, ``sys.argv[1]`` is
    ``path``) and stays in it; returns what ends it."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys\nfrom ceilkit.runtime.io.outputs import "
         f"FolderLock, file_lock\nwith {lock}:\n    print('held', flush=True)\n"
         "    sys.stdin.read()\n", str(path)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    holder.stdout.readline()

    def end() -> None:
        holder.stdin.close()
        holder.wait()
    return end


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


CHARUCO = ["ceilcal", "board", "--board", "charuco:5x7", "--square", "0.04", "--out",
           "{t}/b.pdf"]


def board_cases() -> list[Case]:
    """``ceilcal board`` with a ChArUco board: bad ``--marker`` values (and one not
    smaller than the square), bad ``--paper`` names, board sizes and squares that do not
    exist or do not fit the paper; each one line naming its flag, no PDF written."""
    def no_pdf(t: Path, proc) -> str | None:
        return "data-loss" if (t / "b.pdf").exists() else None

    out = [Case("bad value", f"ceilcal board charuco --marker {v!r}",
                [*CHARUCO, "--marker", v], ("--marker",), check=no_pdf)
           for v in ("nan", "inf", "-inf", "-1", "0", "1e308", "", "0.04", "0.05", "30mm",
                     "99999999999999999999")]
    out += [Case("bad value", f"ceilcal board charuco --paper {v!r}",
                 [*CHARUCO, "--marker", "0.03", "--paper", v], ("--paper",), check=no_pdf)
            for v in ("", "a99", "a4x", "letter landscape", "210x297", "nan")]
    sizes = [("--board", "charuco:0x7"), ("--board", "charuco:1x1"),
             ("--board", "charuco:5x7:NO_SUCH_DICT"), ("--board", "charuco:99999x99999"),
             ("--board", "charuco:5x"), ("--square", "0.5"), ("--square", "1e-9")]
    for flag, v in sizes:
        argv = [*CHARUCO, "--marker", "0.03"] if flag == "--board" else \
            [*CHARUCO[:-4], flag, v, "--out", "{t}/b.pdf"]
        if flag == "--board":
            argv[3] = v
        out.append(Case("bad value", f"ceilcal board {flag} {v!r} (charuco)", argv,
                        (flag,), check=no_pdf))
    return out


_MCAP: dict[str, bytes] = {}
"""The 8-frame corridor recording as MCAP bytes, made once by ``ceilrun convert``."""


def _mcap_bytes() -> bytes:
    if "data" not in _MCAP:
        with tempfile.TemporaryDirectory(prefix="battery-mcap-") as tmp:
            subprocess.run([_tool("ceilrun"), "convert", str(REC_FIXTURE),
                            f"{tmp}/rec.mcap"], check=True, capture_output=True)
            _MCAP["data"] = Path(tmp, "rec.mcap").read_bytes()
    return _MCAP["data"]


def _with_mcap(then: Callable[[Path], Callable[[], None] | None] | None = None):
    """A setup writing ``{t}/in.mcap`` (the corridor recording), then ``then``."""
    def setup(t: Path):
        (t / "in.mcap").write_bytes(_mcap_bytes())
        return then(t) if then is not None else None
    return setup


def _holding_lock(folder: str, name: str | None = None):
    """A setup that starts another process holding the lock of ``{t}/folder`` (its
    ``.ceilkit.lock``; ``name``: another lock file in it): another run writing there."""
    def setup(t: Path) -> Callable[[], None]:
        args = "sys.argv[1]" + (f", {name!r}" if name else "")
        return _hold_in_another_process(f"FolderLock({args})", t / folder)
    return setup


def _symlink(name: str, target: str, then=None):
    def setup(t: Path):
        (t / name).symlink_to(t / target)
        return then(t) if then is not None else None
    return setup


def _listing(rel: str):
    """A check: the folder ``rel`` ({rec}/frames) holds what the fixture's does."""
    def check(t: Path, proc) -> str | None:
        now = sorted(p.name for p in Path(rel.format(t=t, rec=t / "rec")).iterdir())
        was = sorted(p.name for p in (REC_FIXTURE / rel.replace("{rec}", ".")).iterdir())
        return None if now == was else "data-loss"
    return check


CONVERT = ["ceilrun", "convert"]
HELD = [  # (folder held by another run, a file the user made in it, the command, --force)
    ("o", "o/poses.csv", [*REPLAY, "--force"]),
    ("ov", "ov/000003.png", [*REPLAY, "--overlays", "{t}/ov", "--force"]),
    ("o", "o/poses.csv", [*LIVE, "--out", "{t}/o", "--force"]),
    ("r", "r/notes.txt", [*LIVE, "--record", "{t}/r"]),
    ("chk", "chk/check-site.yaml", ["ceilcal", "check-site", "--rig", "{rec}/rig.yaml",
                                    "--site", "{rec}/site.yaml", "--out", "{t}/chk",
                                    "--force"]),
    ("pl", "pl/lightmap.png", ["ceilcal", "lightmap", "{rec}", "--out", "{t}/site.yaml",
                               "--plots", "{t}/pl", "--force"]),
    ("pl", "pl/views.png", ["ceilcal", "intrinsics", "{t}", *BOARD, "--out",
                            "{t}/cam.yaml", "--plots", "{t}/pl", "--force"]),
    ("pl", "pl/mount_residuals.png", [*MOUNT, "--plots", "{t}/pl", "--force"]),
    ("conv", "conv/notes.txt", [*CONVERT, "{t}/in.mcap", "{t}/conv", "--force"]),
    ("sim", "sim/notes.txt", ["ceilcal", "simulate", "--out", "{t}/sim", "--frames", "2"]),
]


def held_cases() -> list[Case]:
    """Every output folder while another run holds its lock (even with ``--force``):
    refused naming the other run, the user's file in it kept."""
    out = []
    for folder, made, argv in HELD:
        setup = _holding_lock(folder)
        if "{t}/in.mcap" in argv:
            setup = _with_mcap(setup)
        out.append(Case("data loss", f"{' '.join(argv[:2])} into {folder}/ held by another "
                        "run", argv, ("another run", "is writing"), guard=("{t}/" + made,),
                        setup=setup))
    return out


def convert_cases() -> list[Case]:
    """``ceilrun convert`` over what exists, into or onto its source, into an ``.mcap``
    being written."""
    src = [*CONVERT, "{t}/in.mcap"]
    return [
        Case("data loss", "convert .mcap into a folder holding a recording",
             [*src, "{t}/conv"], ("{t}/conv", "--force"), guard=("{t}/conv/frames.csv",),
             setup=_with_mcap()),
        Case("data loss", "convert .mcap into a folder holding a rig.yaml",
             [*src, "{t}/conv"], ("{t}/conv", "--force"), guard=("{t}/conv/rig.yaml",),
             setup=_with_mcap()),
        Case("data loss", "convert a folder onto its own frames/",
             [*CONVERT, "{rec}", "{rec}/frames/x.mcap"], ("DST", "inside an input"),
             check=_listing("{rec}/frames")),
        Case("data loss", "convert a folder into itself", [*CONVERT, "{rec}", "{rec}/x.mcap"],
             ("DST", "inside an input"), check=_listing("{rec}")),
        Case("data loss", "convert .mcap onto a link to itself", [*src, "{t}/lnk", "--force"],
             ("DST", "is an input"), setup=_with_mcap(_symlink("lnk", "in.mcap")),
             check=lambda t, proc: None if (t / "in.mcap").read_bytes() == _mcap_bytes()
             else "data-loss"),
        Case("data loss", "convert into an .mcap another run is recording",
             [*CONVERT, "{rec}", "{t}/x.mcap", "--force"], ("another run", "is writing"),
             guard=("{t}/x.mcap",), setup=_holding_lock(".", ".x.mcap.lock")),
        Case("data loss", "convert over a user's .mcap", [*CONVERT, "{rec}", "{t}/x.mcap"],
             ("{t}/x.mcap", "--force"), guard=("{t}/x.mcap",)),
    ]


INTO_INPUTS = [  # (command, the flag named, a check that the input stayed)
    (["ceilcal", "intrinsics", "--ceiling", "{rec}", "--out", "{rec}/rig.yaml", "--force"],
     "--out", "{rec}/rig.yaml"),
    (["ceilcal", "lightmap", "{rec}", "--out", "{rec}/frames/site.yaml"], "--out",
     "{rec}/frames"),
    (["ceilcal", "lightmap", "{rec}", "--out", "{rec}/truth.csv", "--force"], "--out",
     "{rec}/truth.csv"),
    (["ceilcal", "lightmap", "{rec}", "--out", "{t}/site.yaml", "--plots", "{rec}/frames"],
     "--plots", "{rec}/frames"),
    (["ceilcal", "autopilot", "--rig", "{rec}/rig.yaml", "--firmware", "ardupilot-4.6",
      "--out", "{rec}/rig.yaml", "--force"], "--out", "{rec}/rig.yaml"),
    (["ceilcal", "check-site", "--rig", "{rec}/rig.yaml", "--site", "{rec}/site.yaml",
      "--out", "{rec}/site.yaml", "--force"], "{rec}/site.yaml", "{rec}/site.yaml"),
    (["ceilcal", "simulate", "--out", "{rec}", "--frames", "2"], "{rec}", "{rec}/frames"),
    (["ceilcal", "simulate", "--out", "{rec}/site.yaml", "--frames", "2", "--site",
      "{rec}/site.yaml"], "--out", "{rec}/site.yaml"),
    ([*REPLAY[:4], "{rec}/frames", *REPLAY[5:]], "--out", "{rec}/frames"),
    ([*REPLAY, "--tum", "--overlays", "{rec}/frames/sub"], "--overlays", "{rec}/frames"),
]


def into_input_cases() -> list[Case]:
    """Outputs of the calibration commands (and a replay's) into or over one of their
    inputs: refused naming the flag, the input as it was."""
    out = []
    for argv, flag, kept in INTO_INPUTS:
        check = _listing(kept) if kept.endswith(("frames", "}")) else _unchanged(kept)
        out.append(Case("data loss", f"{' '.join(argv[:2])} {flag} into its input "
                        f"{kept.replace('{rec}/', 'REC/')}", argv, (flag,), check=check))
    return out


def _frame_png(shape: tuple[int, ...] | None = None, colour: bool = False) -> bytes:
    import cv2

    img = cv2.imread(str(REC_FIXTURE / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
    if shape is not None:
        img = cv2.resize(img, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    if colour and img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return cv2.imencode(".png", img)[1].tobytes()


FRAME_DAMAGE: dict[str, Callable[[bytes], bytes | None]] = {
    "zero bytes": lambda data: b"",
    "garbage": lambda data: np.random.default_rng(2).bytes(len(data)),
    "a JPEG header, then garbage": lambda data: b"\xff\xd8\xff\xe0" + bytes(4000),
    "half the resolution": lambda data: _frame_png((120, 160)),
    "1x1 px": lambda data: _frame_png((1, 1)),
    "missing": lambda data: None,
}
"""How frame 2 of a recording (or of an image folder) is damaged: its new bytes (None:
the file is removed)."""


LIGHTS_FIXTURE = REC_FIXTURE.parent / "lights_rec"


def _damage_frame(folder: str, name: str, how: str):
    def setup(t: Path) -> None:
        if folder.startswith("lrec"):  # the 6-frame lights recording (a lightmap's input)
            shutil.copytree(LIGHTS_FIXTURE, t / "lrec")
        path = t / folder / name
        data = FRAME_DAMAGE[how](path.read_bytes())
        if data is None:
            path.unlink()
        else:
            path.write_bytes(data)
    return setup


def _named_or_refused(name: str, then=None):
    """A check: the run is refused in one error line naming ``name`` (the damaged file),
    or it runs (exit 0), names it on stderr and passes ``then`` (no pose from it)."""
    def check(t: Path, proc) -> str:
        if proc.returncode != 0:  # one error line; the file named by it or before it
            errors = [ln for ln in proc.stderr.splitlines() if ": error: " in ln]
            return "clean" if len(errors) == 1 and name in proc.stderr else "unnamed"
        if name not in proc.stderr:
            return "silent-wrong"
        return (then(t, proc) if then is not None else None) or "clean"
    return check


def _pose_after(t_ns: int, poses: str):
    """A check: the row at ``t_ns`` has no pose and the next row has one (a frame after
    a damaged one is estimated)."""
    def check(t: Path, proc) -> str | None:
        import csv
        path = t / poses
        rows = list(csv.DictReader(path.open())) if path.exists() else []
        k = next((i for i, r in enumerate(rows) if int(r["t_ns"]) == t_ns), None)
        ok = k is not None and k + 1 < len(rows) and rows[k]["yaw_deg"] == "" \
            and rows[k + 1]["yaw_deg"] != ""
        return None if ok else "silent-wrong"
    return check


def more_damage_cases() -> list[Case]:
    """Frame 2 of a recording (and of an image folder) zero bytes, garbage, a JPEG cut
    short, another resolution, 1x1 px or missing: a replay publishes no pose from it
    and names it; a conversion and the calibrations that read a recording name it."""
    out = []
    for how in FRAME_DAMAGE:
        setup = _damage_frame("rec/frames", "000002.png", how)
        out.append(Case("damaged frame", f"replay, frame 2 {how}",
                        [*REPLAY, "--option", "assume_heading_deg=0"], refused=False,
                        setup=setup, check=_named_or_refused(
                            "000002.png", _pose_after(200_000_000, "o/poses.csv"))))
        out.append(Case("damaged frame", f"convert, frame 2 {how}",
                        [*CONVERT, "{rec}", "{t}/x.mcap"], refused=False, setup=setup,
                        check=_named_or_refused("000002.png")))
        for argv, rec in ((["ceilcal", "lightmap", "{t}/lrec", "--out", "{t}/site.yaml"],
                           "lrec"),
                          (["ceilcal", "intrinsics", "--ceiling", "{rec}", "--out",
                            "{t}/cam.yaml"], "rec")):
            out.append(Case("damaged frame", f"{argv[1]}, frame 2 {how}", argv,
                            refused=False, setup=_damage_frame(f"{rec}/frames",
                                                               "000002.png", how),
                            check=_named_or_refused("000002")))
    for how in ("zero bytes", "garbage", "half the resolution"):
        for ext in ("jpg", "png"):
            out.append(Case("damaged frame", f"image folder, a {ext} {how}",
                            ["ceilrun", "--device", "{t}/imgs", "--rig", "{rec}/rig.yaml",
                             "--site", "{rec}/site.yaml", "--method", "corridor", "--out",
                             "{t}/o"], refused=False,
                            setup=_image_folder(ext, how), check=_named_or_refused(
                                "frame 1 is 320x240" if how == "half the resolution"
                                else f"000001.{ext}", _no_pose_at(None, "o/poses.csv"))))
    return out


def _image_folder(ext: str, how: str):
    def setup(t: Path) -> None:
        import cv2

        img = cv2.imread(str(REC_FIXTURE / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
        (t / "imgs").mkdir()
        for k in range(3):
            data = cv2.imencode(f".{ext}", img)[1].tobytes()
            if k == 1:
                data = FRAME_DAMAGE[how](data) if how != "half the resolution" else \
                    cv2.imencode(f".{ext}", img[::2, ::2])[1].tobytes()
            (t / "imgs" / f"{k:06d}.{ext}").write_bytes(data)
    return setup


def _unreadable(path: Path) -> None:
    """``path`` made a file whose reads fail: mode 000 for a user; as root (who reads
    anything), a link to ``/proc/self/mem``, which opens but fails every read (EIO)."""
    if os.geteuid() == 0:
        path.symlink_to("/proc/self/mem")
    else:
        path.write_text("a: 1\n")
        path.chmod(0)


MORE_SPECIAL = {
    "fifo": lambda p: os.mkfifo(p),
    "/dev/null": lambda p: p.symlink_to("/dev/null"),
    "a folder": lambda p: p.mkdir(),
    "a file": lambda p: p.write_text("a: 1\n"),
    "a symlink loop": lambda p: p.symlink_to(p),
    "unreadable": _unreadable,
}
"""Special files given where a file (or a folder) is read."""
FILE_USES = [  # (what, the command with {t}/in where the file goes)
    ("ceilrun --rig", [*LIVE, "--rig", "{t}/in"]),
    ("ceilrun --site", [*LIVE, "--site", "{t}/in"]),
    ("ceilrun --capture", [*LIVE, "--capture", "{t}/in"]),
    ("mount PLACEMENTS", ["ceilcal", "mount", "{t}/in", "--site", "{rec}/site.yaml",
                          "--rig", "{rec}/rig.yaml", "--out", "{t}/rig.yaml"]),
    ("lightmap --poses", ["ceilcal", "lightmap", "{rec}", "--poses", "{t}/in", "--out",
                          "{t}/site.yaml"]),
    ("autopilot --rig", ["ceilcal", "autopilot", "--rig", "{t}/in", "--firmware",
                         "ardupilot-4.6", "--out", "{t}/ap.param"]),
    ("check-site --rig", ["ceilcal", "check-site", "--rig", "{t}/in", "--site",
                          "{rec}/site.yaml", "--out", "{t}/chk"]),
    ("check-site --site", ["ceilcal", "check-site", "--rig", "{rec}/rig.yaml", "--site",
                           "{t}/in", "--out", "{t}/chk"]),
    ("exposure --rig", ["ceilcal", "exposure", "--device", "sim:lights", "--rig", "{t}/in",
                        "--out", "{t}/capture.yaml"]),
    ("survey RIG", ["ceilcal", "survey", "{t}/in", "{rec}", "--out", "{t}/sv"]),
    ("convert SRC .mcap", [*CONVERT, "{t}/in", "{t}/conv"]),
]
FOLDER_USES = [
    ("replay RECORDING", ["ceilrun", "replay", "{t}/in", "--out", "{t}/o"]),
    ("repair RECORDING", ["ceilrun", "repair", "{t}/in"]),
    ("convert SRC folder", [*CONVERT, "{t}/in", "{t}/x.mcap"]),
    ("lightmap RECORDING", ["ceilcal", "lightmap", "{t}/in", "--out", "{t}/site.yaml"]),
    ("intrinsics FOLDER", ["ceilcal", "intrinsics", "{t}/in", *BOARD, "--out",
                           "{t}/cam.yaml"]),
    ("intrinsics --ceiling", ["ceilcal", "intrinsics", "--ceiling", "{t}/in", "--out",
                              "{t}/cam.yaml"]),
    ("ceilrun --device FOLDER", [*LIVE[:2], "{t}/in", "--rig", "{rec}/rig.yaml", "--site",
                                 "{rec}/site.yaml", "--method", "corridor"]),
]


def more_special_cases() -> list[Case]:
    """Every other file and folder input given a FIFO, /dev/null, a folder (a file where
    a folder is read), a symlink loop or an unreadable file; and /dev/null, a loop and
    an unreadable file as the inputs the first table covers. Each one line naming it."""
    out = []
    uses = [(w, a, False) for w, a in FILE_USES] + [(w, a, True) for w, a in FOLDER_USES]
    uses += [(f"{a[1]} {flag}", [*a, flag, "{t}/in"], False)
             for flag, a in (("--rig", REPLAY), ("--site", REPLAY),
                             ("--camera", MOUNT[:-4] + MOUNT[-2:]), ("--odometry", REPLAY))]
    for what, argv, folder in uses:
        kinds = [k for k in MORE_SPECIAL if k != ("a folder" if folder else "a file")]
        if what.startswith(("replay --", "mount --camera")):
            kinds = ["/dev/null", "a symlink loop", "unreadable"]  # the rest: special_cases
        for kind in kinds:
            out.append(Case("special file", f"{what} {kind}", argv, ("{t}/in",),
                            setup=_make_in(kind)))
    return out


def _make_in(kind: str):
    def setup(t: Path) -> None:
        MORE_SPECIAL[kind](t / "in")
    return setup


def _nmea(body: str) -> bytes:
    x = 0
    for c in body.encode():
        x ^= c
    return f"${body}*{x:02X}\r\n".encode()


class _Peer:
    """The controller at the other end of a pty, ``{t}/tty`` a link to its slave (the
    path ceilrun opens): ``away`` s after the first ``$PCEIL`` it closes its end and
    the link goes; ``back`` s later (None: never) a new pty takes the path. ``answer``:
    a ``$PCEIO`` body (``{t}``: the pose's stamp in ms) sent after each ``$PCEIL``."""

    def __init__(self, t: Path, away: float | None = None, back: float | None = None,
                 answer: str = ""):
        self.link, self.away, self.back, self.answer = t / "tty", away, back, answer
        self.before, self.after = bytearray(), bytearray()
        self._stop = threading.Event()
        self._open()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _open(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()
        self.link.symlink_to(os.ttyname(self.slave))

    def _close(self) -> None:
        """Close this end once (a number closed twice may be another case's pty by then)."""
        for fd in (self.master, self.slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = -1

    def _read(self, into: bytearray, until: float) -> None:
        while not self._stop.is_set() and time.monotonic() < until and self.master >= 0:
            if select.select([self.master], [], [], 0.02)[0]:
                try:
                    chunk = os.read(self.master, 65536)
                except OSError:
                    return
                into += chunk
                for line in chunk.split(b"\r\n"):  # a pose or a status: its stamp
                    if self.answer and line.startswith((b"$PCEIL,", b"$PCEIS,")):
                        stamp = line.split(b",")[2]
                        os.write(self.master, _nmea(self.answer.format(t=stamp.decode())))

    def _run(self) -> None:
        forever = float("inf")
        while not self.before and not self._stop.is_set():  # the first bytes sent
            self._read(self.before, time.monotonic() + 0.05)
        if self.away is None:
            return self._read(self.before, forever)
        self._read(self.before, time.monotonic() + self.away)
        self._close()
        self.link.unlink()
        if self.back is None:
            return None
        self._stop.wait(self.back)
        self._open()
        self._read(self.after, forever)
        return None

    def end(self) -> None:
        self._stop.set()
        self._thread.join()
        self._close()


def _peer_case(**kw):
    """A setup starting a :class:`_Peer`, and a check of what it saw."""
    peer: dict = {}

    def setup(t: Path) -> Callable[[], None]:
        peer["p"] = _Peer(t, **kw)
        return peer["p"].end

    def check(t: Path, proc) -> str | None:
        p, err = peer["p"], proc.stderr
        if proc.returncode != 0 or not p.before:
            return "silent-wrong"
        if kw.get("away") is not None and " lost " not in err:
            return "unnamed"  # no line said the link went
        pose = b"\xfd" if "mavlink" in proc.args else b"$PCEIL"  # MAVLink 2: frames
        if kw.get("back") is not None and (" back after " not in err or pose not in p.after):
            return "silent-wrong"  # no line said it is back, or no pose after it
        if kw.get("answer") and not ("PCEIO" in err or ("link odometry:" in err
                                                         and " refused" in err)):
            return "unnamed"  # the sentences refused, and nothing said so
        return None
    return setup, check


LINK_LIVE = ["ceilrun", "--device", "sim:corridor", "--frames", "240", "--serial",
             "{t}/tty", "--option", "assume_heading_deg=0"]  # poses, not only status
PCEIO_BAD = {"dx 1e308": "PCEIO,{t},1e308,0,0", "dy -1e308": "PCEIO,{t},0,-1e308,0",
             "dyaw 1e308": "PCEIO,{t},0,0,1e308", "all 1e308": "PCEIO,{t},1e308,-1e308,1e308",
             "t 1e30": "PCEIO,1000000000000000000000000000000,0.01,0,0",
             "t -5": "PCEIO,-5,0.01,0,0", "dx 900 m": "PCEIO,{t},900,0,0"}
"""``$PCEIO`` sentences (correct checksums) out of bounds, answering every pose."""


def link_cases() -> list[Case]:
    """The serial peer going away and coming back (a pty whose path is taken by a new
    one), going away for good; ``$PCEIO`` odometry out of bounds over the link. Each
    run ends with exit 0 and lines saying what happened; poses resume once it is back."""
    out = []
    for name, kw, argv in (
            ("peer away 1 s and back (nmea)", {"away": 0.3, "back": 1.0}, LINK_LIVE),
            ("peer away 3 s and back (nmea)", {"away": 0.3, "back": 3.0}, LINK_LIVE),
            ("peer away 1 s and back (mavlink)", {"away": 0.3, "back": 1.0},
             [*LINK_LIVE, "--protocol", "mavlink"]),
            ("peer away for good", {"away": 0.3, "back": None}, LINK_LIVE)):
        setup, check = _peer_case(**kw)
        out.append(Case("link", name, argv, refused=False, setup=setup, check=check,
                        timeout_s=300))
    for name, body in PCEIO_BAD.items():
        setup, check = _peer_case(answer=body)
        out.append(Case("link", f"$PCEIO {name} over the link",
                        [*LINK_LIVE[:4], "120", *LINK_LIVE[5:], "--method", "auto",
                         "--link-odometry"],
                        refused=False, setup=setup, check=check, timeout_s=300))
    return out


def battery_cases() -> list[Case]:
    return (value_cases() + overwrite_cases() + damage_cases() + special_cases()
            + content_cases() + concurrent_cases() + board_cases() + held_cases()
            + convert_cases() + into_input_cases() + more_damage_cases()
            + more_special_cases() + link_cases())


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
