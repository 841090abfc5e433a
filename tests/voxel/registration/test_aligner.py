"""Registration recovers known transforms of constructed maps and refuses ambiguous or foreign
ones."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.voxel.registration.worlds import RES, crop_and_move, error, floor_plan, plan_map
from voxel.errors import AlignmentError
from voxel.registration import AlignParams, MapCloud, align_clouds
from voxel.registration.transform import rigid


@pytest.fixture(scope="module")
def plan() -> tuple[np.ndarray, np.ndarray]:
    return floor_plan(seed=3)


@pytest.mark.parametrize(("dof", "yaw_deg"), [(3, 137.0), (4, -62.0)])
def test_planar_map_moved_by_known_transform_is_recovered(plan, dof: int, yaw_deg: float) -> None:
    keys, mask = plan_map(*plan)
    move = rigid(7.3, -4.1, 0.0, yaw=math.radians(yaw_deg))
    a = crop_and_move(keys, mask, 0.0, 15.0)
    b = crop_and_move(keys, mask, 9.0, 24.0, move)
    result = align_clouds(a, b, AlignParams(dof=dof))
    assert result.aligned, result.reason
    rms, yaw = error(result.transform, np.linalg.inv(move), b.occupied)
    assert rms < 1.5 * RES and yaw < 1.0
    assert result.confidence > 0.1 and result.inliers > 100 and result.rmse_m < RES
    assert result.covariance.shape == (3, 3) and np.all(np.diag(result.covariance) < 1e-3)
    record = result.to_json()
    assert {
        "aligned",
        "transform",
        "x",
        "y",
        "z",
        "roll_deg",
        "pitch_deg",
        "yaw_deg",
        "confidence",
        "inliers",
        "rmse_m",
        "overlap",
        "method",
        "seconds",
    } <= set(record)
    assert "reason" not in record
    assert np.allclose(np.array(record["transform"]), result.transform, atol=1e-8)


@pytest.mark.parametrize("dof", [4, 6])
def test_3d_map_moved_in_x_y_z_yaw_is_recovered(plan, dof: int) -> None:
    keys, mask = plan_map(*plan, height=20)
    move = rigid(-3.2, 11.0, 1.7, yaw=math.radians(-151.0))
    a = crop_and_move(keys, mask, 0.0, 15.0)
    b = crop_and_move(keys, mask, 8.0, 24.0, move)
    result = align_clouds(a, b, AlignParams(dof=dof))
    assert result.aligned, result.reason
    assert len(result.covariance_params) == dof
    rms, yaw = error(result.transform, np.linalg.inv(move), b.occupied)
    assert rms < 1.5 * RES and yaw < 1.0
    assert abs(result.transform[2, 3] - np.linalg.inv(move)[2, 3]) < RES


def test_maps_of_different_buildings_are_not_aligned() -> None:
    a_keys, a_mask = plan_map(*floor_plan(seed=1))
    b_keys, b_mask = plan_map(*floor_plan(seed=2, size=(14.0, 9.0)))
    a = crop_and_move(a_keys, a_mask, 0.0, 24.0)
    b = crop_and_move(b_keys, b_mask, 0.0, 14.0, rigid(2.0, 1.0, yaw=0.4))
    result = align_clouds(a, b)
    assert not result.aligned
    assert result.reason and result.confidence == 0.0
    assert result.to_json()["reason"] == result.reason


def test_halves_that_do_not_overlap_are_not_aligned(plan) -> None:
    keys, mask = plan_map(*plan)
    a = crop_and_move(keys, mask, 0.0, 11.0)
    b = crop_and_move(keys, mask, 13.0, 24.0, rigid(-5.0, 2.0, yaw=1.0))
    assert not align_clouds(a, b).aligned


def test_symmetric_corridor_is_not_aligned() -> None:
    """Two straight walls: sliding along the corridor or turning round fits as well, so no pose."""
    x = np.arange(0, 300)
    walls = np.concatenate(
        [np.column_stack([x, np.zeros_like(x)]), np.column_stack([x, np.full_like(x, 20)])]
    )
    free = np.array([[i, j] for i in x for j in range(1, 20)])
    keys, mask = plan_map(walls, free)
    a = crop_and_move(keys, mask, 0.0, 20.0)
    b = crop_and_move(keys, mask, 10.0, 30.0, rigid(3.0, 4.0, yaw=0.7))
    result = align_clouds(a, b)
    assert not result.aligned
    assert "ambiguous" in result.reason or "constrain" in result.reason


def test_bad_dof_and_tiny_maps_raise() -> None:
    pts = np.random.default_rng(0).uniform(0, 5, (100, 3))
    cloud = MapCloud(0.1, pts)
    with pytest.raises(AlignmentError, match=r"dof: expected 3 \(x, y, yaw\), 4 .* or 6, found 5"):
        align_clouds(cloud, cloud, AlignParams(dof=5))
    with pytest.raises(
        AlignmentError, match=r"map B .*expected at least 10 occupied voxels .*found shape \(3, 3\)"
    ):
        align_clouds(cloud, MapCloud(0.1, pts[:3]))
    bad = pts.copy()
    bad[0, 0] = np.nan
    with pytest.raises(AlignmentError, match=r"map A .*expected finite coordinates, found NaN"):
        align_clouds(MapCloud(0.1, bad), cloud)


@pytest.mark.parametrize(("side", "shape"), [(21, (64, 48)), (105, (300, 270)), (57, (125, 160))])
def test_the_padded_forward_transform_is_rfft2_bit_for_bit(
    side: int, shape: tuple[int, int]
) -> None:
    from scipy import fft

    from voxel.registration.global_search import _rfft2_padded

    rng = np.random.default_rng(side)
    image = np.zeros((side, side), np.float32)
    image[rng.integers(0, side, 4 * side), rng.integers(0, side, 4 * side)] = 1.0
    assert np.array_equal(_rfft2_padded(image, shape), fft.rfft2(image, s=shape))
