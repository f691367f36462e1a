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
