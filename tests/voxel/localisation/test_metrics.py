"""ATE with Umeyama alignment: known answers, errors, and agreement with evo_ape -a."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from colonyd.mapping import tum_line
from voxel.errors import LocalisationError
from voxel.localisation.metrics import absolute_trajectory_error, umeyama
from voxel.registration.transform import rigid


def _random_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    for i in range(n):
        poses[i] = rigid(*rng.normal(size=3), *rng.uniform(-math.pi, math.pi, size=3))
    return poses


def test_umeyama_recovers_a_rigid_transform_and_a_scale() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(50, 3))
    t = rigid(1.0, -2.0, 0.5, 0.3, -0.2, 2.0)
    y = 2.5 * x @ t[:3, :3].T + t[:3, 3]
    fit = umeyama(x, y, with_scale=True)
    assert fit.scale == pytest.approx(2.5)
    np.testing.assert_allclose(fit.rotation, t[:3, :3], atol=1e-9)
    np.testing.assert_allclose(fit.apply(x), y, atol=1e-9)
    rigid_fit = umeyama(x, y @ np.diag([1.0, 1.0, 1.0]) / 2.5)
    assert rigid_fit.scale == 1.0


def test_ate_is_zero_for_a_moved_copy_and_known_for_an_offset() -> None:
    rng = np.random.default_rng(2)
    ref = _random_poses(30, rng)
    moved = np.array([rigid(3.0, 1.0, 0.0, yaw=1.2) @ p for p in ref])
    assert absolute_trajectory_error(ref, moved).rmse < 1e-9
    assert absolute_trajectory_error(ref, moved, align=False).rmse > 1.0
    # alternating +-0.1 m along x cannot be aligned away: every error is 0.1 m
    est = ref[:, :3, 3] + np.outer((-1.0) ** np.arange(30), [0.1, 0.0, 0.0])
    assert absolute_trajectory_error(ref, est).rmse == pytest.approx(0.1, abs=1e-3)


def test_ate_errors_say_what_was_expected() -> None:
    with pytest.raises(
        LocalisationError, match=r"expected the same number of poses, found 3 and 4"
    ):
        absolute_trajectory_error(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(LocalisationError, match=r"expected positions \(N, 3\) or poses"):
        absolute_trajectory_error(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(LocalisationError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(LocalisationError, match="finite"):
        absolute_trajectory_error(np.full((3, 3), np.nan), np.zeros((3, 3)))


def test_ate_equals_evo_ape_with_alignment(tmp_path: Path) -> None:
    evo_sync = pytest.importorskip("evo.core.sync", reason="evo (test extra) is not installed")
    from evo.core import metrics
    from evo.tools import file_interface

    rng = np.random.default_rng(3)
    ref = _random_poses(200, rng)
    est = np.array([rigid(0.4, -1.0, 0.2, 0.1, 0.0, 0.7) @ p for p in ref])
    est[:, :3, 3] += rng.normal(scale=0.05, size=(200, 3)) + np.linspace(0, 0.3, 200)[:, None]
    times = np.arange(200) * 0.1
    for name, poses in (("gt", ref), ("est", est)):
        (tmp_path / f"{name}.tum").write_text(
            "".join(tum_line(t, p) + "\n" for t, p in zip(times, poses, strict=True))
        )
    traj_ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    traj_est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    traj_ref, traj_est = evo_sync.associate_trajectories(traj_ref, traj_est)
    traj_est.align(traj_ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    theirs = ape.get_statistic(metrics.StatisticsType.rmse)
    ours = absolute_trajectory_error(ref, est).rmse
    assert ours == pytest.approx(theirs, abs=1e-3)
    assert ours == pytest.approx(theirs, abs=1e-5)  # the same up to the files' 6 decimals
