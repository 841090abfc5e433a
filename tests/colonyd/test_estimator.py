"""The daemon maps from its own pose estimate: with odometry drift, the estimate stays closer."""

from __future__ import annotations

import numpy as np

from colonyd.estimator import PoseError

SPEC = "sim:world=office,agent=lidar-1,frames=80,drift=0.03,seed=3"


def test_pose_error_measures_drift_since_the_first_frame():
    err = PoseError()
    start = np.eye(4)
    start[:3, 3] = [5.0, 1.0, 0.0]  # the agent's own frame differs from the truth's: no matter
    assert err.update(np.eye(4), start) == 0.0
    moved, truth = np.eye(4), start.copy()
    moved[0, 3], truth[0, 3] = 1.1, 6.0
    assert abs(err.update(moved, truth) - 0.1) < 1e-12
    assert err.update(moved, None) == err.last


def test_a_daemon_that_estimates_drifts_less_than_one_that_does_not(make_colony):
    colony = make_colony("estimate")
    estimating = colony.add("est", [SPEC])
    raw = colony.add("raw", [SPEC], start=False)
    raw.env = {"COLONYD_LOCALISE": "false"}
    raw.start()
    colony.wait_converged(60)
    reports = colony.reports(["est", "raw"])
    est, dead = reports["est"]["pose_error_m"], reports["raw"]["pose_error_m"]
    assert dead is not None and est is not None
    assert dead > 0.05 and est < 0.5 * dead, (est, dead)
    assert estimating.alive()
    # the estimate travels as Pose messages with its covariance: raw knows est's uncertainty
    seen = {m["agent"]: m for m in reports["raw"]["members"]}
    assert seen["est"]["pose_std_m"] is not None and 0 < seen["est"]["pose_std_m"] < 0.5, seen
    # nothing rejected but frames that came before the sender's first heartbeat (its key unknown)
    assert set(reports["raw"]["metrics"]["rejected"]) <= {"unknown_identity"}
