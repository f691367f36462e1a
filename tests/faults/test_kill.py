"""SIGKILL at random moments of a recording run: every recording replays, and every
frame whose pose reached the link is in it (the write-ahead frame log).

Eight kills here (seeded); ``benchmarks/bench_faults.py`` does fifty."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ceilkit.runtime.io.recording import Recording, repair_recording
from ceilkit.runtime.replay import replay

KILLS = 8
RUN = ("from ceilkit.cli.ceilrun import main; import sys; "
       "sys.argv = ['ceilrun', *sys.argv[1:]]; main()")


def kill_run(folder: Path, after_s: float) -> tuple[Path, Path]:
    """Start a recording run of the simulator, SIGKILL it ``after_s`` seconds after its
    first pose reached the link; the recording and the link's file."""
    rec, wire = folder / "rec", folder / "wire.nmea"
    proc = subprocess.Popen([sys.executable, "-c", RUN, "--device", "sim:corridor",
                             "--record", str(rec), "--serial", str(wire),
                             "--fsync-every", "0"],
                            stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    # a generous wait: a machine's first run compiles the per-frame loops (runtime/jit.py)
    deadline = time.monotonic() + 240
    sent = False
    while time.monotonic() < deadline and proc.poll() is None:
        sent = wire.exists() and b"$PCEIL" in wire.read_bytes()
        if sent:
            break
        time.sleep(0.01)
    if not sent:
        proc.kill()
        proc.wait()
        raise AssertionError(f"no pose reached the link in 240 s (exit {proc.returncode})")
    time.sleep(after_s)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return rec, wire


def sent_stamps_ms(wire: Path) -> set[int]:
    """The capture times (ms) of the whole $PCEIL sentences on the wire."""
    out = set()
    for line in wire.read_bytes().split(b"\r\n")[:-1]:
        if line.startswith(b"$PCEIL,"):
            out.add(int(line.split(b",")[2]))
    return out


def check_killed(rec: Path, wire: Path, tmp: Path) -> tuple[int, int]:
    """Assert the invariants on a killed run; (frames sent, frames only in the log)."""
    sent = sent_stamps_ms(wire) if wire.exists() else set()
    recording = Recording(rec)  # always opens: the folder appears whole
    stamps_ms = {int(t) // 1_000_000 for t in recording.t_ns}
    assert sent <= stamps_ms, f"{len(sent - stamps_ms)} sent frames not recorded"
    res = replay(rec, tmp / "replay")
    assert res.telemetry.frames == len(recording)
    logged = recording.logged
    assert repair_recording(rec) == logged
    again = Recording(rec)
    assert again.logged == 0 and np.array_equal(again.t_ns, recording.t_ns)
    return len(sent), logged


def test_sigkill_at_random_moments_loses_no_sent_frame(tmp_path):
    rng = np.random.default_rng(17)
    for k, after in enumerate(rng.uniform(0.0, 1.0, KILLS)):
        folder = tmp_path / f"run{k}"
        folder.mkdir()
        rec, wire = kill_run(folder, float(after))
        check_killed(rec, wire, folder)
        assert not list(folder.glob(".rec.partial*"))  # no half-made folder left
