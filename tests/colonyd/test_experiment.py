"""The paper's experiment as real daemons (a short run): every output is there and sane. The order
of the runs' errors is a benchmark's business (docs/BENCHMARKS.md), not asserted here."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest

from colonyd.experiment import RUNS, agent_metrics, update_counts
from colonyd.tracks import Track

FIELDS = {"ate_rmse_m", "final_error_m", "max_error_after_contact_m", "first_contact_s"}


def test_experiment_paper_writes_every_output(tmp_path):
    out = tmp_path / "paper"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "colonyd",
            "experiment",
            "paper",
            "--out",
            str(out),
            "--duration",
            "5",
            "--parallel",
            "4",
            "--start-delay",  # (15 s by default: late frames are mapped late, none is skipped)
            "4",
            "--world",  # the sparse hall: the option reaches every daemon's source (the default,
            "hall",  # the office, is the same code with another world's name)
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["world"] == "hall" and results["start_delay_s"] == 4
    assert set(results["runs"]) == set(RUNS)
    for name, agents in RUNS.items():
        assert set(results["runs"][name]) == set(agents), name
        for agent in agents:
            m = results["runs"][name][agent]
            assert set(m) == FIELDS, (name, agent)
            if agent != "cctv-1":  # a fixed camera has no path to evaluate
                assert m["ate_rmse_m"] is not None and 0 <= m["ate_rmse_m"] < 1.0, (name, m)
                assert m["final_error_m"] is not None and m["final_error_m"] >= 0
            for trajectory in ("estimate", "groundtruth"):
                lines = (out / name / f"{agent}.{trajectory}.tum").read_text().splitlines()
                assert all(len(line.split()) == 8 for line in lines), (name, agent)
                assert len(lines) >= (1 if agent == "cctv-1" else 3), (name, agent)
        assert set(results["updates"][name]) == set(agents), name
        if "lidar-1" in agents:  # its estimator matched scans against its own map
            assert results["updates"][name]["lidar-1"]["updates_accepted"] > 0, name
        if "lidar-1" in agents:  # in the hall it starts east from (-7.5, 0), beyond the office
            rows = (out / name / "lidar-1.groundtruth.tum").read_text().splitlines()
            xy = np.array([[float(v) for v in row.split()[1:3]] for row in rows])
            assert xy[:, 0].min() < -6.0 and np.abs(xy[:, 1]).max() < 0.3, xy
        if len(agents) == 1:  # alone: nobody to meet
            assert results["runs"][name][agents[0]]["first_contact_s"] is None
    for picture in ["pose-error.png", *(f"{name}/topdown.png" for name in RUNS)]:
        image = cv2.imread(str(out / picture))
        assert image is not None and image.std() > 10, picture  # not blank
    assert "lidar+depth+cctv" in run.stdout and "ATE" in run.stdout  # the printed table
    for name in RUNS:  # not a terminal: a line per run started and ended (no live table there)
        assert f"{name}: started\n" in run.stdout, run.stdout
        assert re.search(rf"{re.escape(name)}: (done|timed out)\n", run.stdout), run.stdout


def test_metrics_of_a_constructed_track():
    """Errors after the Umeyama fit: a path shifted as a whole has none; one bad last pose shows
    in the final and the after-contact error, not before contact."""
    track = Track("2D LiDAR", 0.0)
    for i in range(10):
        truth = np.eye(4)
        truth[:3, 3] = [i * 0.5, (i % 3) * 0.2, 0.0]
        estimate = truth.copy()
        estimate[:3, 3] += [10.0, -3.0, 0.0]  # another frame: no error after alignment
        track.times.append(float(i))
        track.truth.append(truth)
        track.estimate.append(estimate)
    m = agent_metrics(track)
    assert m["ate_rmse_m"] < 1e-6 and m["final_error_m"] < 1e-6
    assert m["first_contact_s"] is None and m["max_error_after_contact_m"] is None
    track.estimate[-1] = track.estimate[-1].copy()
    track.estimate[-1][:3, 3] += [0.0, 1.0, 0.0]
    track.aligned_at = 8.5
    m = agent_metrics(track)
    assert m["final_error_m"] > 0.5
    assert m["max_error_after_contact_m"] == m["final_error_m"]
    assert m["first_contact_s"] == 8.5


def test_update_counts_gathers_the_estimators_and_the_fixes_counts():
    report = {
        "localisation": {
            "estimate_ms": 3.2,
            "sim:agent=lidar-1": {"estimator": "ekf", "colony_accepted": 4, "colony_rejected": 1},
        },
        "metrics": {"counts": {"frames": 600, "fix_fused": 2, "fix_refused": 1}},
    }
    assert update_counts(report) == {
        "colony_accepted": 4,
        "colony_rejected": 1,
        "fix_fused": 2,
        "fix_refused": 1,
    }
    assert update_counts({}) == {}


def test_a_run_interrupted_while_starting_stops_the_daemons_it_started(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM between two daemons' starts: the first one is stopped, not left."""
    from colonyd import experiment

    started: list = []
    real_options = experiment.agent_options

    def options(agents, agent, epoch, lidar_range):
        if started:  # the second agent of the run: interrupted before it starts
            raise KeyboardInterrupt
        return real_options(agents, agent, epoch, lidar_range)

    real_add = experiment.SimRun.add

    def add(self, agent, *args):
        real_add(self, agent, *args)
        started.append(self.colony.daemons[agent])

    monkeypatch.setattr(experiment, "agent_options", options)
    monkeypatch.setattr(experiment.SimRun, "add", add)
    with pytest.raises(KeyboardInterrupt):
        experiment._start(tmp_path, "lidar+depth", 1, 5.0, 4.0, "office")
    assert len(started) == 1
    assert not started[0].alive()


def test_a_runs_shared_clock_starts_its_start_delay_after_its_daemons(tmp_path, monkeypatch):
    """`--start-delay`: every agent of a run gets the same epoch, that many seconds from now."""
    import time

    from colonyd import experiment

    options: list[str] = []
    monkeypatch.setattr(
        experiment.SimRun,
        "add",
        lambda self, agent, duration, seed, extra="": options.append(extra),
    )
    now = time.time()
    experiment._start(tmp_path, "lidar+depth+cctv", 1, 5.0, 4.0, "office", 4.0).close()
    epochs = {float(re.search(r"epoch=([0-9.]+)", o).group(1)) for o in options}
    assert len(options) == 3 and len(epochs) == 1, options
    assert abs(epochs.pop() - (now + 4.0)) < 1.0
