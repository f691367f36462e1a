"""Paths and small utilities shared by the tests (importable as ``helpers``)."""

from __future__ import annotations

import contextlib
import math
import threading
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
FIXTURES = Path(__file__).resolve().parent / "fixtures"


def replay_errors(rec: Path, poses: Path) -> tuple[np.ndarray, np.ndarray]:
    """Absolute heading (deg) and lateral (m) errors of a poses.csv against truth.csv."""
    from ceilkit.runtime.io.recording import Recording, load_poses

    truth = Recording(rec).truth
    got = load_poses(poses)
    dh, dy = [], []
    for t, y, yaw in zip(got.t_ns, got.y_m, got.yaw_rad, strict=True):
        _, ty, tyaw = truth.lookup(int(t))
        dh.append(abs(math.degrees(math.remainder(yaw - tyaw, 2 * math.pi))))
        dy.append(abs(y - ty))
    a, b = np.array(dh), np.array(dy)
    return a[np.isfinite(a)], b[np.isfinite(b)]


def write_text(tmp_path: Path, text: str, name: str = "site.yaml") -> Path:
    """``text`` written to ``tmp_path / name``; its path."""
    path = tmp_path / name
    path.write_text(text)
    return path


def assert_broken_field(load, path: Path, key: str, words: str) -> None:
    """``load(path)`` raises one ConfigError line naming the file and the dotted key,
    with ``words`` in it (a fixture broken one field at a time)."""
    import pytest

    from ceilkit.runtime.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        load(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: {key}: "), msg
    assert words in msg, msg


@contextlib.contextmanager
def held_elsewhere(lock):
    """``lock`` (a context manager: a ``FolderLock``, a file lock) held by another
    thread, as by another run, for the ``with`` block (a lock the same thread holds is
    taken again: a run's own nested step)."""
    taken, release = threading.Event(), threading.Event()

    def hold():
        with lock:
            taken.set()
            release.wait(30)

    thread = threading.Thread(target=hold, daemon=True)
    thread.start()
    assert taken.wait(10)
    try:
        yield lock
    finally:
        release.set()
        thread.join(10)


def tile_grid(folder: Path):
    """``(rig, site)``: bench_ambiguity's plain 0.6 m drop-tile grid given as corridor
    lines along and across (3 m up), seen by configs/block's upward wide-angle camera;
    the site file written in ``folder``."""
    import yaml

    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site

    d = {"ceiling_height": 3.0,
         "corridor": {"lines_along": [round(-3.0 + 0.6 * i, 2) for i in range(11)],
                      "lines_across": {"first": 0.0, "spacing": 0.6}}}
    p = Path(folder) / "tiles.yaml"
    p.write_text(yaml.safe_dump(d))
    return Rig.load(CONFIGS / "block" / "rig.yaml"), Site.load(p)
