"""The paper_align bench's measures: the registration worker's CPU from /proc, an estimate's
error against the true transform between two sim agents' start frames."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from colonyd.aligner import Aligner
from colonyd.bench.paper_align import error_of, summary, true_transform, worker_cpu


def _spin(seconds: float) -> int:
    import time

    end, n = time.process_time() + seconds, 0
    while time.process_time() < end:
        n += 1
    return n


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc")
def test_worker_cpu_counts_the_spawned_registration_worker():
    assert worker_cpu(os.getpid()) == 0.0  # no worker yet
    aligner = Aligner()
    try:
        aligner.run(_spin, 0.1)
        assert worker_cpu(os.getpid()) >= 0.1
    finally:
        aligner.close()


def test_error_of_an_estimate_against_the_true_start_frames():
    truth = true_transform("office", "lidar-1", "depth-1")
    # lidar-1 starts at (-5, 0) heading east, depth-1 at (-5, -2.6) heading north-east
    assert np.allclose(truth[:2, 2], [0.0, -2.6], atol=1e-9)
    off = np.eye(4)
    c, s = math.cos(math.radians(1.0)), math.sin(math.radians(1.0))
    planar = truth @ np.array([[c, -s, 0.03], [s, c, 0.04], [0, 0, 1.0]])
    off[:2, :2], off[:2, 3] = planar[:2, :2], planar[:2, 2]
    pos, yaw = error_of({"transform": off.tolist()}, truth)
    assert pos == pytest.approx(0.05) and yaw == pytest.approx(1.0)


def test_summary_shows_each_attempts_frames_mapped():
    attempt = {
        "sim_s": 104.1,
        "frames_mapped": 294,
        "seconds": 5.1,
        "worker_cpu_s": 2.4,
        "aligned": True,
        "ambiguity": 0.0,
        "geometric_ambiguity": 0.79,
        "overlap": 0.43,
        "error_m": 0.206,
        "error_deg": 3.72,
    }
    result = {
        "seed": 2,
        "session_nice": None,
        "load": [8.2, 12.5],
        "seconds": 369.2,
        "first_contact_sim_s": {"depth-1": 117.7},
        "first_identified_object_sim_s": {"depth-1": 0.7},
        "worker_cpu_s": {"depth-1": 11.7},
        "attempts": {"depth-1": [attempt, {**attempt, "aligned": False, "reason": "ambiguous"}]},
    }
    lines = summary(result).splitlines()
    assert "f=294" in lines[1] and lines[1].endswith(": ok")
    assert lines[2].endswith(": ambiguous")
