"""Odometry over the link (issue 40 item 5): applied over its own interval, bounded,
recorded; the link's state said when the peer goes and comes back."""

from __future__ import annotations

import logging
import math
import os
import select
import threading

import numpy as np
import pytest

from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.fusion import Fusion
from ceilkit.runtime.io.link import MemoryLink, SerialLink
from ceilkit.runtime.io.odometry_in import OdometryReceiver, encode_pceio
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.pipeline import ListSink, build_pipeline
from ceilkit.runtime.session import LinkConfig, SessionConfig, hook_link_odometry, run_session
from ceilkit.runtime.sim.render import straight_drive
from ceilkit.runtime.tracking import Tracker

S = 1_000_000_000
SIGMA_M = 0.0002
# the sim: device's drive (runtime/devices.py), so a peer knows the true motion
DRIVE = dict(fps=30.0, speed_mps=0.8, y_m=0.1, weave_m=0.15, yaw_wobble_rad=np.radians(4.0))


def drive(n: int):
    return straight_drive(n, rng=np.random.default_rng(0), **DRIVE)


def increment(traj, t0_ns: int, t1_ns: int) -> tuple[float, float, float]:
    """The true motion over [t0, t1]: (dx m, dy m) in V at t0, dyaw degrees."""
    x0, y0, a0 = traj.pose_at(t0_ns)
    x1, y1, a1 = traj.pose_at(t1_ns)
    c, s = math.cos(a0), math.sin(a0)
    return (c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0),
            math.degrees(math.remainder(a1 - a0, 2 * math.pi)))


def answers(traj, line: bytes, last: list[int], every_ms: int | None) -> list[bytes]:
    """A controller's answer to one ``$PCEIL``: the true increment(s) since its last row
    (one row at the pose's stamp, or rows every ``every_ms`` up to it)."""
    t_ms = int(line.split(b",")[2])
    if not last:
        last.append(t_ms)
        return []
    ends = [t_ms] if every_ms is None else list(range(last[-1] + every_ms, t_ms + 1, every_ms))
    out = []
    for end in ends:
        out.append(encode_pceio(end, *increment(traj, last[-1] * 10**6, end * 10**6)))
        last.append(end)
    return out


class FakeLights:
    """A full-pose fix per frame: the truth plus seeded noise of 0.2 mm."""

    name = "lights"

    def __init__(self, traj, seed: int = 1):
        self.traj, self.rng = traj, np.random.default_rng(seed)

    def estimate(self, image, t_ns, prior=None):
        x, y, a = self.traj.pose_at(t_ns)
        n = self.rng.normal(0.0, SIGMA_M, 3)
        return PoseEstimate(int(t_ns), "lights", x + n[0], y + n[1], a + 0.1 * n[2], 0.9,
                            cov=np.diag([SIGMA_M ** 2, SIGMA_M ** 2, (0.1 * SIGMA_M) ** 2]))


class AnsweringPeer(MemoryLink):
    """A controller that answers each pose it reads (``reply(line) -> sentences``)."""

    def __init__(self, reply, **kw):
        super().__init__("nmea", service_interval_s=None, **kw)
        self.reply, self._line = reply, b""

    def _write_some(self, data: bytes) -> int:
        n = super()._write_some(data)
        *lines, self._line = (self._line + data[:n]).split(b"\r\n")
        for line in lines:
            if line.startswith(b"$PCEIL"):
                for sentence in self.reply(line):
                    self.feed(sentence)
        return n


def fused_errors(traj, reply) -> tuple[np.ndarray, Fusion, OdometryReceiver]:
    """The fused position error of every frame (nan: no pose), a peer answering."""
    fusion, out = Fusion(), ListSink()
    ticks = iter(range(S, 10**15, 10**6))
    link = AnsweringPeer(reply, clock_ns=lambda: next(ticks))
    receiver = OdometryReceiver(fusion.add_odometry)
    link.on_receive = receiver
    with link:
        pipeline = build_pipeline(FakeLights(traj), fusion, link=link, more=[out])
        for k, t in enumerate(traj.t_ns):
            pipeline.process(Frame(np.zeros((4, 4), np.uint8), int(t), k))
    err = [math.hypot(e.x_m - traj.x_m[k], e.y_m - traj.y_m[k])
           if isinstance(e, PoseEstimate) and e.x_m is not None else math.nan
           for k, (e, _) in enumerate(out.items)]
    return np.array(err), fusion, receiver


@pytest.mark.parametrize("every_ms", [None, 10], ids=["a-row-a-pose", "rows-at-100hz"])
def test_true_increments_over_the_link_are_no_worse_than_none(every_ms):
    """Each pose answered after it was published with the true increment(s): the rows
    are applied over the interval they cover. Before, the pose was held still from the
    last row to the frame, one frame of travel behind: every fix gated."""
    traj = drive(60)
    last: list[int] = []
    with_odo, fusion, rx = fused_errors(traj, lambda ln: answers(traj, ln, last, every_ms))
    without, _, _ = fused_errors(traj, lambda ln: [])
    # every row but the answer to the last pose (it comes after the last frame) fused
    assert rx.rows > 50 and fusion.odometry_rows >= rx.rows - 4 and not fusion.gated
    assert not np.isnan(with_odo).any() and not np.isnan(without).any()
    assert np.median(with_odo[5:]) <= 1.1 * np.median(without[5:])
    assert np.percentile(with_odo[5:], 95) <= 1.1 * np.percentile(without[5:], 95)


def test_an_increment_out_of_reach_is_refused_counted_and_the_run_goes_on():
    traj = drive(20)
    last: list[int] = []

    def reply(line):
        rows = answers(traj, line, last, None)
        return rows if len(last) != 5 else [encode_pceio(last[-1], 1e308, -1e308, 1e308)]

    err, fusion, rx = fused_errors(traj, reply)
    assert rx.refused == 1 and fusion.odometry_refused == 1 and rx.bad == 0
    assert not np.isnan(err).any() and np.max(err) < 0.002


# ----------------------------------------------------------- requested, not read or used


@pytest.mark.parametrize("link", [None, LinkConfig("-"), LinkConfig("poses.nmea")],
                         ids=["no-serial", "stdout", "a-file"])
def test_link_odometry_with_no_port_to_read_is_an_error(link, tmp_path):
    with pytest.raises(ConfigError) as exc:
        run_session(SessionConfig(device="sim:lights", frames=1, link=link,
                                  link_odometry=True, out=tmp_path))
    assert exc.value.key == "link_odometry" and "--serial PORT" in str(exc.value)
    assert not (tmp_path / "poses.csv").exists()


def test_link_odometry_on_a_method_without_the_fusion_is_a_warning(caplog):
    link = MemoryLink("nmea")
    cfg = SessionConfig(device="sim:corridor", method="corridor", link_odometry=True)
    with caplog.at_level(logging.WARNING, logger="ceilkit"):
        assert hook_link_odometry(cfg, link, Tracker(), "corridor") is None
    assert link.on_receive is None
    assert [r.getMessage() for r in caplog.records] == [
        "odometry from the link (--link-odometry) is not used: method corridor runs "
        "without the fusion (--method auto fuses it); it is not read"]
    assert isinstance(hook_link_odometry(cfg, link, Fusion(), "auto"), OdometryReceiver)


# ------------------------------------------------------------------ the peer goes, comes back


class Clock:
    def __init__(self) -> None:
        self.t = 0

    def __call__(self) -> int:
        return self.t


def _pose(k: int) -> PoseEstimate:
    return PoseEstimate(k * 33_000_000, "lights", 1.0, 2.0, 0.1, 0.9)


def test_the_peer_gone_and_back_is_said_and_poses_resume_at_once(tmp_path, caplog):
    """A socat pair or a USB adapter: the port's path goes, then comes back. The link
    says both, and reopens as soon as the path is there (not at the back-off's next
    attempt, seconds later: a short run then ended with no pose after the return)."""
    path = tmp_path / "ttyUSB0"
    master, slave = os.openpty()
    os.symlink(os.ttyname(slave), path)
    clock = Clock()
    with caplog.at_level(logging.WARNING, logger="ceilkit.link"), \
            SerialLink(path, 115200, "nmea", clock_ns=clock, service_interval_s=None,
                       backoff_s=(0.5, 8.0)) as link:
        link.send(_pose(0))
        os.close(master)
        os.close(slave)
        path.unlink()                      # socat gone: its link removed
        for k in range(1, 60):             # 5.9 s away: back-off attempts at 0.5, 1.5, 3.5 s
            clock.t += S // 10
            link.send(_pose(k))
        assert link.state == "disconnected" and link.counters.lost == 1
        master, slave = os.openpty()       # socat back
        os.symlink(os.ttyname(slave), path)
        clock.t += S // 10                 # the next attempt is due at 7.5 s; now is 6.0 s
        link.send(_pose(60))               # (a service thread polls every 50 ms)
        assert link.state == "connected" and link.counters.reconnects == 1
        link.send(_pose(61))
        r, _, _ = select.select([master], [], [], 1.0)
        got = os.read(master, 4096) if r else b""
    os.close(master)
    os.close(slave)
    assert b",2013,A," in got             # the next pose goes out at once
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "lost (" in lines[0] and "back after 5.9 s" in lines[1]


# ------------------------------------------------------------------ recorded, replayed


def test_link_odometry_is_recorded_and_the_replay_gives_the_same_poses(tmp_path):
    """A live run (sim device) with a controller answering each pose over a pty, recorded;
    ``replay`` of the recording feeds its odometry.csv and publishes the same poses."""
    from ceilkit.runtime.io.recording import Recording, load_poses
    from ceilkit.runtime.replay import replay

    n = 8
    traj, last = drive(n), []
    master, slave = os.openpty()
    path = tmp_path / "ttyACM0"
    os.symlink(os.ttyname(slave), path)
    stop = threading.Event()

    def peer():
        buf = b""
        while not stop.is_set():
            if select.select([master], [], [], 0.02)[0]:
                *lines, buf = (buf + os.read(master, 4096)).split(b"\r\n")
                for line in (ln for ln in lines if ln.startswith(b"$PCEIL")):
                    for sentence in answers(traj, line, last, None):
                        os.write(master, sentence)

    th = threading.Thread(target=peer, daemon=True)
    th.start()
    try:
        res = run_session(SessionConfig(device="sim:lights", method="auto", frames=n,
                                        link=LinkConfig(str(path)), link_odometry=True,
                                        record=tmp_path / "rec", out=tmp_path / "live"))
    finally:
        stop.set()
        th.join()
        os.close(master)
        os.close(slave)
    rec = Recording(tmp_path / "rec")
    assert rec.odometry is not None and len(rec.odometry) == n - 1
    assert any("link odometry: 7 rows received, 0 refused" in line for line in res.link)
    replay(tmp_path / "rec", tmp_path / "replayed", method="auto")
    live, again = load_poses(tmp_path / "live" / "poses.csv"), load_poses(
        tmp_path / "replayed" / "poses.csv")
    assert np.array_equal(live.t_ns, again.t_ns)
    np.testing.assert_allclose(again.x_m, live.x_m, atol=2e-4)
    np.testing.assert_allclose(again.y_m, live.y_m, atol=2e-4)
