"""What a new user met on the first day (issue 37, second walk): Ctrl-C during a first
start's compiling, a protocol the site cannot serve said before the loops load, a run
stopped before its first frame, ``ceilrun --version`` and ``-h`` without the library,
the survey's and blockmap's help, intrinsics' warnings said once on a terminal."""

from __future__ import annotations

import os
import pty
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ceilkit.cli import ceilrun
from ceilkit.cli.ceilcal import app as ceilcal_app
from ceilkit.cli.ceilrun import app as ceilrun_app
from ceilkit.runtime import session
from ceilkit.runtime.estimators import registry
from ceilkit.runtime.live import LiveResult
from ceilkit.runtime.metrics import AccuracyMeter
from ceilkit.runtime.pipeline import Telemetry
from helpers import CONFIGS, ROOT


def _helpers_alive(cache: Path) -> list[int]:
    """Processes (ours) whose environment names this numba cache."""
    mark = f"NUMBA_CACHE_DIR={cache}".encode()
    out = []
    for d in Path("/proc").iterdir():
        try:
            if d.name.isdigit() and mark in (d / "environ").read_bytes().split(b"\0"):
                out.append(int(d.name))
        except OSError:
            pass
    return out


def test_ctrl_c_while_compiling_stops_the_helpers_and_the_run_at_once(tmp_path):
    """An empty numba cache: the first start compiles (minutes). SIGINT once the
    progress line says it compiles: the run ends without the warm-up's last line, its
    helper gone, exit 0 and the summary (a stop before the first frame)."""
    cache = tmp_path / "numba"
    cache.mkdir()
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), CEILKIT_COMPILE_HELPERS="1",
               PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-c", "from ceilkit.cli.ceilrun import main; main()", "--device",
         "sim:corridor", "--frames", "5", "--no-realtime", "--out", str(tmp_path / "run")],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    compiling = threading.Event()

    def read() -> None:
        for line in proc.stderr:
            lines.append(line.rstrip("\n"))
            if "compiling the per-frame loops" in line:
                compiling.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert compiling.wait(600), lines
        assert _helpers_alive(cache)          # the helper compiles beside it
        proc.send_signal(signal.SIGINT)
        proc.wait(600)
        reader.join(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = "\n".join(lines)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert "(stopped by a signal)" in err
    assert "no frame estimated: stopped before the first frame" in err
    # the warm-up did not finish: no final progress line (done == total)
    progress = [ln.split(": ")[-1].split(",")[0] for ln in lines if "per-frame loops" in ln]
    assert progress and all(a != b for a, b in (p.split("/") for p in progress)), err
    assert _helpers_alive(cache) == []
    assert not (tmp_path / "run").exists()    # nothing written


def test_nmea_gps_without_the_site_origin_is_said_before_the_loops_load(tmp_path,
                                                                         monkeypatch):
    def never(*_a, **_k):
        raise AssertionError("the method's loops were loaded first")

    monkeypatch.setattr(session, "make_localizer", never)
    site = CONFIGS / "lights" / "site.yaml"
    res = CliRunner().invoke(ceilrun_app, ["--device", "sim:lights", "--site", str(site),
                                           "--serial", str(tmp_path / "gps.nmea"),
                                           "--protocol", "nmea-gps", "--frames", "1"])
    assert res.exit_code == 1, res.output
    assert res.stderr.startswith(f"ceilrun: error: {site}: origin: missing: the nmea-gps")
    assert len(res.stderr.splitlines()) == 1
    assert not (tmp_path / "gps.nmea").exists()


def test_a_run_stopped_before_its_first_frame_says_so():
    config = session.SessionConfig(device="sim:lights")
    nothing = AccuracyMeter(None).result()         # 0 frames against truth
    res = session.SessionResult(config, "lights", LiveResult(Telemetry(), 0, 1.0, True),
                                (), 0, nothing)
    text = "\n".join(res.lines())
    assert "no frame estimated: stopped before the first frame" in text
    assert "nan" not in text and "0/0" not in text
    ended = session.SessionResult(config, "lights", LiveResult(Telemetry(), 0, 1.0, False),
                                  (), 0, None)
    assert "no frame estimated: the source gave none" in "\n".join(ended.lines())


@pytest.mark.parametrize("args", [["ceilrun", "--version"], ["ceilrun", "-h"],
                                  ["ceilrun", "replay", "-h"],
                                  ["ceilkit-ros2", "--version"]])
def test_version_and_help_load_neither_numba_nor_opencv(args):
    code = (f"import sys\nfrom ceilkit.cli import ceilrun\nsys.argv = {args!r}\n"
            "try:\n    (ceilrun.ros2_main if sys.argv[0] == 'ceilkit-ros2' else "
            "ceilrun.main)()\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('numba', 'cv2', 'scipy') if m in sys.modules), "
            "file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env=dict(os.environ, COLUMNS="100"))
    assert out.stderr.strip().splitlines()[-1] == "[]", out.stderr
    assert "ceilkit" in out.stdout or "Usage" in out.stdout


def test_the_help_names_every_method_of_the_registry():
    assert ceilrun.METHOD_NAMES == registry.METHOD_NAMES
    assert ceilrun.AUTO == registry.AUTO


def test_survey_and_blockmap_help():
    res = CliRunner().invoke(ceilcal_app, ["survey", "-h"], terminal_width=100)
    assert "<list[" not in res.stdout and "{RIG} {RECORDING}..." in res.stdout
    assert "<path>..." in res.stdout
    res = CliRunner().invoke(ceilcal_app, ["-h"], terminal_width=100)
    row = next(ln for ln in res.stdout.splitlines() if " blockmap " in ln)
    assert row.rstrip(" │").endswith("from a drive of known poses.")   # one whole sentence


@pytest.mark.parametrize("on_terminal", [True, False])
def test_same_terminal(on_terminal):
    """The intrinsics' warnings go to stderr as well only when stdout is not the
    terminal stderr shows."""
    code = ("from ceilkit.cli.ceilcal_intrinsics import same_terminal\n"
            "import sys\nsys.stderr.write(f'same={same_terminal()}\\n')")
    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stderr=slave,
                                stdout=slave if on_terminal else subprocess.DEVNULL)
        os.close(slave)
        data = b""
        while True:
            try:
                chunk = os.read(master, 1024)
            except OSError:
                break
            if not chunk:
                break
            data += chunk
        proc.wait(60)
    finally:
        os.close(master)
    assert f"same={on_terminal}" in data.decode()
