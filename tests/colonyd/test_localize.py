"""`colonyd localize`: sim, real laser log and real RGB-D frames (subsets), results.json, evo
agreement, bad specs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from colonyd.cli import EXIT_CONFIG, EXIT_DATA, launch, main
from tests.shared import SHARED_DATA

DATA = SHARED_DATA
LOG = DATA / "carmen" / "freiburg-079-corrected.log.gz"
KITCHEN = DATA / "redkitchen-seq01-a"


def _results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def _evo_ate(gt: Path, est: Path) -> float:
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref, traj = sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(str(gt)),
        file_interface.read_tum_trajectory_file(str(est)),
    )
    traj.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def test_sim_lidar_agent_estimate_beats_its_odometry(tmp_path: Path) -> None:
    assert (
        main(
            [
                "localize",
                "--source",
                "sim:world=room,agent=lidar-1,frames=200",
                "--odometry-noise",
                "high",
                "--seed",
                "3",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    r = _results(tmp_path)
    assert r["frames"] == 200 and r["estimator"] == "ekf+scan-to-map"
    assert r["ate_rmse_m"]["estimate"] < 0.5 * r["ate_rmse_m"]["odometry"]
    for name in (
        "estimate.tum",
        "smoothed.tum",
        "odometry.tum",
        "groundtruth.tum",
        "map.bt",
        "map.ply",
        "grid.npz",
    ):
        assert (tmp_path / name).is_file(), name


@pytest.mark.skipif(not LOG.is_file(), reason=f"real CARMEN log not found at {LOG}")
def test_real_laser_log_with_synthesised_odometry(tmp_path: Path) -> None:
    assert (
        main(
            [
                "localize",
                "--source",
                f"replay:{LOG},stop=300",
                "--odometry-noise",
                "realistic",
                "--seed",
                "1",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    r = _results(tmp_path)
    assert r["frames"] == 300
    assert r["ate_rmse_m"]["estimate"] < 0.3 * r["ate_rmse_m"]["odometry"]
    assert r["faster_than_real_time"] > 0  # speed is a benchmark (docs/BENCHMARKS.md), not a test
    gt = np.loadtxt(tmp_path / "groundtruth.tum")
    odo = np.loadtxt(tmp_path / "odometry.tum")
    assert not np.allclose(gt[:, 1:3], odo[:, 1:3], atol=0.05)  # the noisy odometry, not the log's
    pytest.importorskip("evo", reason="evo (test extra) is not installed")
    theirs = _evo_ate(tmp_path / "groundtruth.tum", tmp_path / "estimate.tum")
    assert r["ate_rmse_m"]["estimate"] == pytest.approx(theirs, abs=1e-3)
    # the smoothed trajectory (every pose re-solved with what the filter fused): as good as the
    # online one (measured 0.0284 against 0.0286 m), the same stamps, its poses moved
    smoothed = _evo_ate(tmp_path / "groundtruth.tum", tmp_path / "smoothed.tum")
    assert r["ate_rmse_m"]["smoothed"] == pytest.approx(smoothed, abs=1e-3)
    assert r["ate_rmse_m"]["smoothed"] <= r["ate_rmse_m"]["estimate"] + 0.002
    online, moved = np.loadtxt(tmp_path / "estimate.tum"), np.loadtxt(tmp_path / "smoothed.tum")
    assert online.shape == moved.shape == (300, 8)
    np.testing.assert_array_equal(online[:, 0], moved[:, 0])
    assert 1e-4 < np.linalg.norm(online[:, 1:3] - moved[:, 1:3], axis=1).max() < 0.2


@pytest.mark.skipif(not KITCHEN.is_dir(), reason=f"real 7-Scenes sequence not found at {KITCHEN}")
def test_real_rgbd_frames_visual_odometry(tmp_path: Path) -> None:
    assert (
        main(
            [
                "localize",
                "--source",
                f"replay:{KITCHEN},stop=40,stride=4",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    r = _results(tmp_path)
    assert r["frames"] == 40 and r["estimator"] == "rgbd-visual-odometry"
    assert r["ate_rmse_m"]["odometry"] is None and not (tmp_path / "odometry.tum").exists()
    assert r["ate_rmse_m"]["smoothed"] is None and not (tmp_path / "smoothed.tum").exists()
    assert r["ate_rmse_m"]["estimate"] < 0.03
    pytest.importorskip("evo", reason="evo (test extra) is not installed")
    theirs = _evo_ate(tmp_path / "groundtruth.tum", tmp_path / "estimate.tum")
    assert r["ate_rmse_m"]["estimate"] == pytest.approx(theirs, abs=1e-3)


def test_bad_odometry_noise_is_a_config_error(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        launch(
            [
                "localize",
                "--source",
                "sim:frames=2",
                "--odometry-noise",
                "loud",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
    assert exit_info.value.code == EXIT_CONFIG
    assert (
        "odometry_noise: odometry noise: expected one of ['high', 'low', 'none', 'realistic']"
        in capfd.readouterr().err
    )


def test_a_source_no_estimator_can_follow_says_what_would_do(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """`synthetic:` delivers points without odometry or a depth image: the error says which
    sources `colonyd localize` can follow (was: 'expected a depth image for visual odometry')."""
    with pytest.raises(SystemExit) as exit_info:
        launch(["localize", "--source", "synthetic:scans=2", "--out", str(tmp_path)])
    assert exit_info.value.code == 4  # input data
    assert (
        "expected a source an estimator can follow (a 2D or 3D LiDAR, a sensor with odometry, "
        "or a depth camera for visual odometry), found points with neither odometry nor a "
        "depth image" in capfd.readouterr().err
    )


@pytest.mark.parametrize(
    ("spec", "code", "message"),
    [
        (
            "sim:frames=0",
            EXIT_CONFIG,
            "option 'frames': expected a number greater than or equal to 1, found '0'",
        ),
        (f"replay:{LOG},start=5,stop=5", EXIT_CONFIG, "expected stop > start, found start 5"),
        (
            f"replay:{LOG},start=999999",
            EXIT_DATA,
            "start=999999: expected at least one readable frame, found none",
        ),
        (
            f"replay:{DATA / 'redkitchen-50'},start=50",
            EXIT_CONFIG,
            "expected a selection of at least one of the 50 frames, found none (start 50,",
        ),
    ],
)
def test_a_source_of_no_frames_is_an_error_and_nothing_is_written(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], spec: str, code: int, message: str
) -> None:
    """No frames gave an empty map, trajectory and results.json, and exit code 0."""
    if spec.startswith("replay:") and not DATA.is_dir():
        pytest.skip(f"real data not found: {DATA} is missing")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        launch(["localize", "--source", spec, "--out", str(out), "--no-progress"])
    assert exit_info.value.code == code
    assert message in capfd.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("command", ["localize", "map"])
def test_a_run_of_no_frames_leaves_no_folder_it_made(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], command: str
) -> None:
    """Exit 4, nothing written, and the --out folder made for the run (with the parents it
    lacked) gone again; a folder that existed stays (the empty folder made was left behind)."""
    log = tmp_path / "bad.log"
    log.write_text("FLASER 3 1.0 2.0\nFLASER x y z\n")
    given = tmp_path / "given"
    given.mkdir()
    for out in (tmp_path / "new" / "out", given):
        with pytest.raises(SystemExit) as exit_info:
            launch([command, "--source", f"replay:{log},format=carmen", "--out", str(out)])
        assert exit_info.value.code == EXIT_DATA
        assert "expected at least one readable frame, found none" in capfd.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.log", "given"]
    assert not any(given.iterdir())


def test_too_few_poses_for_an_ate_say_so_and_keep_the_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two sim frames: the reference is there (groundtruth.tum, as the docs promise), the ATE
    needs three poses; it said 'no reference' and wrote no groundtruth.tum."""
    out = tmp_path / "out"
    assert main(["localize", "--source", "sim:frames=2", "--out", str(out), "--no-progress"]) == 0
    said = capsys.readouterr().out
    assert "ATE not measured: expected at least 3 poses, found 2" in said, said
    assert len((out / "groundtruth.tum").read_text().splitlines()) == 2
    assert _results(out)["ate_rmse_m"]["estimate"] is None
