"""The contact bound: a path that is right until a jump is fully corrected by a contact before
the jump and not by one after it, in the robot's own (rotated) frame read from real TUM files;
files it cannot score are named."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from colonyd.bench import contact_bound
from colonyd.mapping import tum_line
from voxel.rotation import euler_pose

JUMP_S = 25.0


def _truth(times: np.ndarray) -> np.ndarray:
    """A loop of radius 3 m in the plane, 0.1 rad/s."""
    return np.column_stack([3 * np.cos(0.1 * times), 3 * np.sin(0.1 * times), 0 * times])


def _write(path: Path, times: np.ndarray, positions: np.ndarray, first: np.ndarray) -> None:
    lines = []
    for i, (t, p) in enumerate(zip(times, positions, strict=True)):
        pose = first.copy() if i == 0 else np.eye(4)
        pose[:3, 3] = p
        lines.append(tum_line(float(t), pose))
    path.write_text("\n".join(lines) + "\n")


def _run(tmp_path: Path, prefix: str = "", start: float = 1000.0) -> Path:
    """The robot's own frame is the world turned by 40 degrees and moved; its estimate is exact
    until JUMP_S, then 0.5 m off sideways for good."""
    times = np.arange(0.0, 60.0, 0.1) + start
    truth = _truth(times - times[0])
    own = euler_pose(1.0, -2.0, 0.0, math.radians(40))
    estimate = truth @ own[:3, :3].T + own[:3, 3]
    estimate[times - times[0] >= JUMP_S] += [0.0, 0.5, 0.0]
    _write(tmp_path / f"{prefix}estimate.tum", times, estimate, own)
    _write(tmp_path / f"{prefix}groundtruth.tum", times, truth, np.eye(4))
    return tmp_path


def test_a_contact_before_the_jump_corrects_all_and_one_after_it_does_not(tmp_path: Path) -> None:
    row = contact_bound.measure(_run(tmp_path), (10.0, 20.0, 30.0, 50.0))
    assert row["ate_alone_m"] > 0.1
    assert row["10"]["start"] == pytest.approx(0.0, abs=1e-3)
    assert row["20"]["start"] == pytest.approx(0.0, abs=1e-3)
    # after the jump the spliced path keeps 5 (then 25) s of the offset estimate
    assert 0.1 < row["30"]["start"] < row["50"]["start"]
    # the frame fitted to an exact estimate before the jump is the own frame itself
    assert row["20"]["fitted"] == pytest.approx(0.0, abs=1e-3)


def test_the_command_prints_and_appends_one_line_per_call(tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    run = _run(tmp_path / "run")
    out = tmp_path / "bound.json"
    result = contact_bound.main([str(run), "--contacts", "20,30", "--json", str(out)])
    assert result["contacts_s"] == [20.0, 30.0]
    assert out.read_text().count("\n") == 1


def test_files_it_cannot_score_are_named(tmp_path: Path) -> None:
    with pytest.raises(contact_bound.ContactBoundError, match="file pairs"):
        contact_bound.measure(tmp_path)
    run = _run(tmp_path)
    (run / "groundtruth.tum").write_text("1.0 2.0 3.0\n" * 5)
    with pytest.raises(contact_bound.ContactBoundError, match="8 columns"):
        contact_bound.measure(run)
    with pytest.raises(SystemExit):
        contact_bound.main([str(tmp_path), "--contacts", "ten"])


def test_an_experiment_folder_is_scored_at_each_runs_own_contact(tmp_path: Path) -> None:
    """Runs' tracks start 15 s into the run (the start delay): a contact at 30 s of the run is
    15 s of path, before the jump (bound 0); one at 50 s of the run is after it."""
    for run in ("lidar-alone", "lidar+depth", "lidar+depth+cctv"):
        (tmp_path / run).mkdir()
        _run(tmp_path / run, "lidar-1.", start=15.0)
    results = {
        "runs": {
            "lidar-alone": {"lidar-1": {"ate_rmse_m": 0.2, "first_contact_s": None}},
            "lidar+depth": {"lidar-1": {"ate_rmse_m": 0.1, "first_contact_s": 30.0}},
            "lidar+depth+cctv": {"lidar-1": {"ate_rmse_m": 0.3, "first_contact_s": 50.0}},
        }
    }
    (tmp_path / "results.json").write_text(json.dumps(results))
    out = contact_bound.main(["--experiment", str(tmp_path)])
    shared, cctv = out["runs"]["lidar+depth"], out["runs"]["lidar+depth+cctv"]
    assert shared["contact_path_s"] == pytest.approx(15.0)
    assert shared["bound_start"] == pytest.approx(0.0, abs=1e-3)
    assert shared["measured"] == pytest.approx(0.5)
    assert cctv["contact_path_s"] == pytest.approx(35.0)
    assert cctv["bound_start"] > 0.1
    assert cctv["measured"] == pytest.approx(1.5)
    (tmp_path / "results.json").write_text("{}")
    with pytest.raises(contact_bound.ContactBoundError, match="experiment paper"):
        contact_bound.experiment(tmp_path)
