import math

import numpy as np
import pytest

from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.fusion import Fusion
from ceilkit.runtime.multi import AutoEstimator, make_localizer, parse_start_pose
from ceilkit.runtime.tracking import Tracker


def test_start_pose_parses_degrees():
    assert parse_start_pose("1,2,90") == pytest.approx((1.0, 2.0, math.pi / 2))
    assert parse_start_pose("1,2,90,0.3,10") == pytest.approx(
        (1.0, 2.0, math.pi / 2, 0.3, math.radians(10.0)))
    for bad in ("1,2", "a,b,c", "1,2,inf", "1,2,3,4", "1,2,3,0,5", "1,2,3,0.1,-5",
                "1,2,3,0.1,181"):
        with pytest.raises(ConfigError, match="start_pose"):
            parse_start_pose(bad)


def test_a_start_pose_s_sigma_is_its_prior_s_region(lights_rig, lights_site):
    """The start pose's 1σ (two more numbers) is the first prior's covariance, for the
    tracker and the fusion alike; without it, the default region."""
    from ceilkit.runtime.estimators.prior import DEFAULT_PRIOR_SIGMA

    for method in ("lights", "auto"):
        _, tracker = make_localizer(method, lights_rig, lights_site,
                                    start_pose=(1.0, 2.0, 0.5, 0.3, math.radians(10.0)))
        sd = np.sqrt(np.diag(tracker.predict(0).cov))
        assert sd == pytest.approx([0.3, 0.3, math.radians(10.0)], rel=1e-6), method
        _, tracker = make_localizer(method, lights_rig, lights_site, start_pose=(1.0, 2.0, 0.5))
        sd = np.sqrt(np.diag(tracker.predict(0).cov))
        assert sd[0] == pytest.approx(DEFAULT_PRIOR_SIGMA[0], rel=1e-6), method


def test_auto_on_a_one_method_site_is_that_method(lights_rig, lights_site):
    est, tracker = make_localizer("auto", lights_rig, lights_site)
    assert est.name == "lights" and isinstance(tracker, Tracker)
    est, tracker = make_localizer("auto", lights_rig, lights_site, start_pose=(0, 0, 0))
    assert isinstance(est, AutoEstimator) and isinstance(tracker, Fusion)
    # every method takes a start pose: its tracker's first prior
    est, tracker = make_localizer("lights", lights_rig, lights_site, start_pose=(1, 2, 0.5))
    assert est.name == "lights" and isinstance(tracker, Tracker)
    prior = tracker.predict(0)
    assert (prior.x_m, prior.y_m, prior.yaw_rad) == (1, 2, 0.5) and tracker.start_poses == 1
    with pytest.raises(ConfigError, match="options.nope"):
        AutoEstimator(lights_rig, lights_site, {"nope": 1})


def test_block_with_plane_odometry_runs_behind_the_fusion():
    from ceilkit.runtime.config.rig import Rig
    from ceilkit.runtime.config.site import Site
    from helpers import CONFIGS

    rig = Rig.load(CONFIGS / "block" / "rig.yaml")
    site = Site.load(CONFIGS / "block" / "site.yaml")
    assert isinstance(make_localizer("block", rig, site)[1], Fusion)
    off = make_localizer("block", rig, site, {"plane_odometry": False})[1]
    assert isinstance(off, Tracker) and not isinstance(off, Fusion)


# -- the "Done when" scenarios of issue 12, small, through SPEC recordings and replay --
def _record(tmp_path, name, rig, site, traj, covered=None, odometry=None):
    """The drive rendered and written as a SPEC recording (frames, rig, site, truth)."""
    from ceilkit.runtime.io.recording import RecordingWriter
    from ceilkit.runtime.io.sources import Frame
    from ceilkit.runtime.sim.render import SimOptions, render_frame

    folder = tmp_path / name
    with RecordingWriter(folder, rig, site, truth=True) as w:
        for k in range(len(traj)):
            if covered is not None and covered[k]:
                img = np.full((rig.camera.height, rig.camera.width), 3, np.uint8)
            else:
                img = render_frame(rig, site, *traj.pose(k), SimOptions(supersample=1),
                                   np.random.default_rng([5, k]))
            w.write(Frame(img, int(traj.t_ns[k]), k))
            w.write_truth(int(traj.t_ns[k]), *traj.pose(k))
    return folder


def _replayed(folder, **kw):
    from ceilkit.runtime.pipeline import ListSink
    from ceilkit.runtime.replay import replay

    sink = ListSink()
    replay(folder, folder / "out", sinks=[sink], **kw)
    return sink.items


def _pos_error(est, pose):
    if not isinstance(est, PoseEstimate) or est.x_m is None:
        return math.inf
    return math.hypot(est.x_m - pose[0], est.y_m - pose[1])


def test_regular_grid_is_tracked_from_a_known_start_through_replay(tmp_path, lights_rig):
    from ceilkit.runtime.sim.render import Trajectory

    g = np.arange(-3.0, 4.51, 1.5)
    path = tmp_path / "grid.yaml"
    path.write_text("ceiling_height: 3.0\nlights:\n" + "".join(
        f"  - [{a:.3f}, {b:.3f}]\n" for a in g for b in g))
    site = Site.load(path)
    n = 15
    t = np.arange(n) * 100_000_000
    traj = Trajectory(t, 0.3 + 0.1 * np.arange(n), np.full(n, 0.2), np.zeros(n))
    folder = _record(tmp_path, "grid", lights_rig, site, traj)
    items = _replayed(folder, method="auto", start_pose=traj.pose(0))
    errs = [_pos_error(e, traj.pose(k)) for k, (e, _) in enumerate(items)]
    assert len(errs) == n and max(errs) < 0.75          # every frame tracked, no cell slip
    assert float(np.median(errs)) <= 0.005


def test_teleport_through_replay_bumps_the_reset_once_and_is_never_confidently_wrong(
        tmp_path, lights_rig, lights_site):
    from ceilkit.runtime.sim.render import Trajectory

    n1, nc, n2 = 6, 6, 8
    n = n1 + nc + n2
    t = np.arange(n) * 100_000_000
    x = np.where(np.arange(n) < n1 + nc // 2, 3.0 + 0.05 * np.arange(n), 6.0)
    y = np.where(np.arange(n) < n1 + nc // 2, -1.0, 2.0 + 0.05 * (np.arange(n) - n1))
    yaw = np.where(np.arange(n) < n1 + nc // 2, 0.0, math.pi / 2)
    traj = Trajectory(t, x, y, yaw)
    covered = np.zeros(n, bool)
    covered[n1:n1 + nc] = True
    folder = _record(tmp_path, "teleport", lights_rig, lights_site, traj, covered)
    items = _replayed(folder, method="auto", start_pose=traj.pose(0))
    bumps = [k for k, (_, reloc) in enumerate(items) if reloc and k >= n1]
    assert len(bumps) == 1 and bumps[0] <= n1 + nc + 3   # within 3 frames of the view
    wrong = [k for k, (e, _) in enumerate(items) if isinstance(e, PoseEstimate)
             and e.quality >= 0.8 and _pos_error(e, traj.pose(k)) > 0.05]
    assert wrong == []
    assert _pos_error(items[-1][0], traj.pose(n - 1)) < 0.005


def test_no_track_replay_of_random_poses_publishes_one_estimate_per_frame(
        tmp_path, lights_rig, lights_site):
    from ceilkit.runtime.sim.render import random_poses

    traj = random_poses(8, (2.0, 16.0), (-3.5, 3.5), (-math.pi, math.pi),
                        np.random.default_rng(21), fps=10.0)
    folder = _record(tmp_path, "random", lights_rig, lights_site, traj)
    raw = _replayed(folder, track=False)
    assert [_pos_error(e, traj.pose(k)) < 0.01 for k, (e, _) in enumerate(raw)] == [True] * 8
