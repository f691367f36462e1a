import math

from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.tracking import Tracker

DT = 33_000_000


def _pose(k, y, yaw=0.0, x=None):
    return PoseEstimate(k * DT, "corridor", x, y, yaw, 0.9)


def test_first_fix_is_a_relocalization_then_tracks():
    tr = Tracker()
    assert tr.predict(0) is None
    assert tr.update(_pose(0, 0.0)).relocalized
    for k in range(1, 10):
        res = tr.update(_pose(k, 0.01 * k))
        assert res.estimate and not res.relocalized
    pred = tr.predict(10 * DT)
    assert pred.x_m is None and math.isclose(pred.y_m, 0.10, abs_tol=0.01)


def test_outlier_is_gated_as_a_failure_with_a_reason():
    tr = Tracker()
    for k in range(5):
        tr.update(_pose(k, 0.0))
    res = tr.update(_pose(5, 0.9))
    assert isinstance(res.estimate, Failure) and res.estimate.reason == "gated"
    assert "y +0.90 m" in res.estimate.detail
    assert tr.update(_pose(6, 0.0)).estimate  # back on track


def test_consistent_jump_relocalizes_loudly():
    tr = Tracker()
    for k in range(5):
        tr.update(_pose(k, 0.0))
    results = [tr.update(_pose(k, 0.9, yaw=math.radians(30))) for k in range(5, 8)]
    assert [bool(r.estimate) for r in results] == [False, False, True]
    assert results[-1].relocalized and tr.relocalizations == 2


def test_lost_track_restarts():
    tr = Tracker()
    tr.update(_pose(0, 0.0))
    assert tr.update(_pose(100, 1.0)).relocalized  # 3.3 s later: a new track


def test_failures_pass_through():
    tr = Tracker()
    f = Failure(0, "corridor", "blank_frame")
    assert tr.update(f).estimate is f


def test_a_start_pose_is_a_reset_and_the_frame_says_where():
    """A start pose taken is published as a reset (the link bumps its counter); a rough
    one (0.4 m off, the heading right) is not a gate the first pose it chose must pass:
    the frame's position is taken."""
    from ceilkit.runtime.estimators.base import PoseEstimate, Provenance
    from ceilkit.runtime.tracking import Tracker

    tr = Tracker(start_pose=(1.0, 0.4, 0.0))
    tr.predict(0)
    est = PoseEstimate(0, "corridor", None, 0.0, 0.01, 1.0, provenance=Provenance.PRIOR)
    res = tr.update(est)
    assert res.relocalized and res.estimate is est
    nxt = PoseEstimate(33_000_000, "corridor", None, 0.001, 0.01, 1.0,
                       provenance=Provenance.PRIOR)
    tr.predict(nxt.t_ns)
    res = tr.update(nxt)
    assert not res.relocalized and res.estimate is nxt
    # a start pose turned half way round is no such prior: the frame's pose is gated
    tr = Tracker(start_pose=(1.0, 0.0, 3.1))
    tr.predict(0)
    res = tr.update(est)
    assert res.relocalized and not res.estimate and res.estimate.reason == "gated"


def test_a_prior_s_choice_after_a_contradicting_frame_does_not_confirm_the_track():
    """Issue 36 (tiles2's corridor kidnap): an ambiguous frame with no pose in the
    track's region contradicts it; the poses its widened prior then chooses among
    twins do not confirm it, and with the contradiction they drop the track."""
    import numpy as np

    from ceilkit.runtime.estimators.base import Hypothesis, Provenance

    tr = Tracker()
    for k in range(5):
        tr.update(_pose(k, 0.0))
    cov = np.diag([np.inf, 1e-6, 1e-6])
    far = tuple(Hypothesis(None, 0.3 + 0.6 * j, math.radians(40.0), cov, 0.5, "")
                for j in range(2))
    assert not tr.update(Failure(5 * DT, "corridor", "ambiguous", hypotheses=far)).estimate
    chosen = [tr.update(PoseEstimate(k * DT, "corridor", None, 0.02, 0.0, 0.9,
                                     provenance=Provenance.PRIOR)) for k in (6, 7)]
    assert not any(r.estimate for r in chosen) and not tr.tracking


def _drive_pose(t, x=None):
    """A corridor pose (x unknown) of a vehicle at 0.3 m/s across, turning 47 deg/s."""
    import numpy as np
    y, yaw = 0.5 + 0.3 * t, math.radians(47.0) * t
    return PoseEstimate(round(t * 1e9), "corridor", x, y, yaw, 0.9,
                        cov=np.diag([math.inf, 1e-8, 1e-8]))


def test_a_kidnap_onto_a_tile_twin_contradicts_the_track():
    """Issue 36 (held-out tiles0, seed 41): 0.1 s after a fix the track's region is the
    vehicle's motion model's (a few cm); a kidnap's ambiguous frame whose nearest twin
    lies 0.16 m off contradicts it, and the twin its prior then chooses 0.2 s after the
    fix (7.5 cm and 3.2 deg off the prediction) does not confirm it (before: the region
    was a 0.3 m/s velocity held over dt, 4 cm at 0.1 s, and the twin was published
    valid, and every pose after it 0.5 m off)."""
    import numpy as np

    from ceilkit.runtime.estimators.base import Hypothesis, Provenance

    tr = Tracker()
    for k in range(10):
        assert tr.update(_drive_pose(0.1 * k)).estimate
    pred = tr.predict(round(1.0e9))
    cov = np.diag([np.inf, 0.027 ** 2, math.radians(1.0) ** 2])
    yaw = pred.yaw_rad + math.radians(3.2)
    twins = tuple(Hypothesis(None, pred.y_m + 0.156 + 0.5 * j, yaw, cov, 0.5, "")
                  for j in range(-2, 3))
    assert not tr.update(Failure(round(1.0e9), "corridor", "ambiguous",
                                 hypotheses=twins)).estimate
    nxt = tr.predict(round(1.1e9))
    twin = PoseEstimate(round(1.1e9), "corridor", None, nxt.y_m + 0.075,
                        nxt.yaw_rad + math.radians(3.2), 0.9,
                        cov=np.diag([math.inf, 1e-8, 1e-8]), provenance=Provenance.PRIOR)
    res = tr.update(twin)
    assert isinstance(res.estimate, Failure) and res.estimate.reason == "gated"


def test_a_maneuver_within_the_limits_stays_inside_the_region():
    """From rest to the stated maximum speed (2.5 m/s) in 1 s and a turn rate swinging
    between the stated limit's -90 and +90 deg/s at 0.5 Hz (283 deg/s^2 at its peak),
    at 10 Hz: every frame's true pose lies inside the prediction's region, and every
    pose is accepted."""
    import numpy as np

    from ceilkit.runtime.estimators.prior import MAX_SPEED_MPS, MAX_TURN_RPS, allows

    tr = Tracker()
    for k in range(40):
        t = 0.1 * k
        y = MAX_SPEED_MPS * (0.5 * t * t if t < 1.0 else t - 0.5)
        yaw = -MAX_TURN_RPS / math.pi * math.cos(math.pi * t)
        est = PoseEstimate(round(t * 1e9), "lights", 0.2 * t, y, yaw, 0.9,
                           cov=np.diag([1e-8, 1e-8, 1e-8]))
        pred = tr.predict(est.t_ns)
        if k >= 2:
            assert allows(pred, (est.x_m, est.y_m, est.yaw_rad, None)), k
        res = tr.update(est)
        assert res.estimate is est, (k, getattr(res.estimate, "detail", ""))


def test_a_new_track_reaches_the_limits_on_its_fewest_coordinates():
    """0.1 s after a track's first fix (its velocity unknown), a heading-only check of
    the prior (1 dof: a corridor frame's turn) allows the vehicle's stated turn rate,
    and a position one its stated speed, each read alone; a 0.5 m tile's twin, no."""
    import numpy as np

    from ceilkit.runtime.estimators.prior import MAX_SPEED_MPS, MAX_TURN_RPS, allows

    tr = Tracker()
    tr.update(PoseEstimate(0, "lights", 1.0, 2.0, 0.3, 0.9, cov=np.diag([1e-8] * 3)))
    pred = tr.predict(round(0.1e9))
    assert allows(pred, (None, None, 0.3 + 0.1 * MAX_TURN_RPS, None))
    assert allows(pred, (None, None, 0.3 - 0.1 * MAX_TURN_RPS, None))
    assert allows(pred, (1.0 + 0.1 * MAX_SPEED_MPS, None, 0.3, None))
    assert not allows(pred, (1.5, None, 0.3, None))
