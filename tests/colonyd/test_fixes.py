"""Pose fixes: the covariance a CCTV claims, the fix in the robot's frame, and an alignment's error
counted harmonically over many fixes (constructed cases)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from colonyd.alignment import ColonyFrame
from colonyd.fixes import (
    FIX_ACROSS_M,
    FIX_ALONG_M,
    FIX_ANGLE_K,
    FIX_MODEL,
    YAW_PER_M,
    YAW_SD,
    FixCounter,
    fix_covariance,
    fix_in_own_frame,
    fix_sd,
)
from voxel.localisation import frame_error, se2
from voxel.localisation.ekf import PlanarEkf


def _at(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    """A pose at (x, y, z) turned by `yaw` about z."""
    m = se2.to_matrix(np.array([x, y, yaw]))
    m[2, 3] = z
    return m


def test_fix_covariance_is_the_calibrated_model_along_and_across_the_ray() -> None:
    # the calibration's figures (docs/BENCHMARKS.md "The CCTV's claimed covariances": fixes'
    # RMS error 0.3-0.5 cm near, 4.6 cm along and 4 degrees in yaw at 8.5-12.5 m): a revert to
    # the old 1 cm + 1 cm per metre, 4 degrees fails here
    for range_m, along_m, across_m, yaw_deg in (
        (4.0, 0.0044, 0.0056, 0.30),
        (10.0, 0.053, 0.02, 4.1),
    ):
        cov = fix_covariance(range_m, ray=np.array([1.0, 0.0]), model="fitted")
        assert cov.shape == (6, 6)
        assert math.sqrt(cov[0, 0]) == pytest.approx(along_m, rel=0.1)
        assert math.sqrt(cov[1, 1]) == pytest.approx(across_m, rel=0.1)
        assert math.degrees(math.sqrt(cov[5, 5])) == pytest.approx(yaw_deg, rel=0.1)
    assert fix_sd(FIX_ALONG_M, 7.0) == pytest.approx(0.0031 + 4.97e-6 * 7.0**4)
    # turned with the ray: along (1, 1) the along variance is on the diagonal, the across off it
    cov = fix_covariance(8.0, ray=np.array([2.0, 2.0]), model="fitted")
    along, across = fix_sd(FIX_ALONG_M, 8.0), fix_sd(FIX_ACROSS_M, 8.0)
    u = np.array([1.0, 1.0]) / math.sqrt(2.0)
    v = np.array([-1.0, 1.0]) / math.sqrt(2.0)
    assert u @ cov[:2, :2] @ u == pytest.approx(along**2)
    assert v @ cov[:2, :2] @ v == pytest.approx(across**2)
    assert u @ cov[:2, :2] @ v == pytest.approx(0.0, abs=1e-15)
    # without a ray: the along sd in every direction (the larger)
    flat = fix_covariance(8.0, model="fitted")
    assert flat[0, 0] == pytest.approx(along**2) and flat[1, 1] == pytest.approx(along**2)
    assert flat[0, 1] == 0.0
    # the bench's alternative yaw: per metre of range
    ranged = fix_covariance(5.0, YAW_PER_M, model="fitted")
    assert math.sqrt(ranged[5, 5]) == pytest.approx(math.radians(5.0))


def test_the_daemons_fix_model_is_flat_until_the_fitted_one_passes_its_rule() -> None:
    # docs/BENCHMARKS.md "The CCTV's claimed covariances": the fitted model failed its rule;
    # the daemon keeps 1 cm + 1 cm per metre and 4 degrees, a ray ignored
    assert FIX_MODEL == "flat"
    cov = fix_covariance(5.0, ray=np.array([0.0, 3.0]))
    np.testing.assert_allclose(np.diag(cov)[[0, 1, 5]], [0.06**2, 0.06**2, YAW_SD**2])
    assert cov[0, 1] == 0.0


def test_the_angle_model_grows_the_fitted_one_with_the_boards_incidence() -> None:
    # docs/BENCHMARKS.md "The fix's claim by the board's angle": square on it is the fitted
    # model; at 75 degrees along x1.6 and across x1.9 (k tan^2), the yaw unchanged
    ray = np.array([1.0, 0.0])
    fitted = fix_covariance(6.0, ray=ray, model="fitted")
    np.testing.assert_allclose(fix_covariance(6.0, ray=ray, model="angle", incidence=0.0), fitted)
    edge_on = fix_covariance(6.0, ray=ray, model="angle", incidence=math.radians(75.0))
    grow = math.tan(math.radians(75.0)) ** 2
    for i, k in ((0, FIX_ANGLE_K[0]), (1, FIX_ANGLE_K[1]), (5, FIX_ANGLE_K[2])):
        assert math.sqrt(edge_on[i, i] / fitted[i, i]) == pytest.approx(1.0 + k * grow)
    assert 1.4 < math.sqrt(edge_on[0, 0] / fitted[0, 0]) < 1.8
    assert 1.7 < math.sqrt(edge_on[1, 1] / fitted[1, 1]) < 2.1
    # capped: a board seen exactly edge-on claims a finite covariance
    grazing = fix_covariance(6.0, ray=ray, model="angle", incidence=math.pi / 2)
    assert np.isfinite(grazing).all() and grazing[0, 0] > edge_on[0, 0]
    # the other models ignore the angle
    flat = fix_covariance(6.0, ray=ray, model="flat", incidence=1.3)
    np.testing.assert_allclose(flat, fix_covariance(6.0, ray=ray, model="flat"))
    for bad in (None, -0.1, 2.0, float("nan")):
        with pytest.raises(ValueError, match="incidence: expected the board's angle to the ray"):
            fix_covariance(6.0, ray=ray, model="angle", incidence=bad)


def test_fix_covariance_says_what_it_expected() -> None:
    with pytest.raises(ValueError, match="range_m: expected a finite range"):
        fix_covariance(float("nan"))
    with pytest.raises(ValueError, match="ray: expected a finite horizontal direction"):
        fix_covariance(5.0, ray=np.array([np.nan, 1.0]))
    # a robot right below the camera: no direction to split along
    below = fix_covariance(5.0, ray=np.zeros(2), model="fitted")
    assert below[0, 0] == pytest.approx(fix_sd(FIX_ALONG_M, 5.0) ** 2) and below[0, 1] == 0.0
    with pytest.raises(ValueError, match="model: expected one of"):
        fix_covariance(5.0, model="honest")


def _frame(alignment: np.ndarray) -> tuple[ColonyFrame, np.ndarray]:
    """A CCTV (the root, its frame the colony's) and robot r, whose frame is turned by 90
    degrees and shifted by (2, 1) in the CCTV's, with `alignment` as its error."""
    mine = se2.to_matrix(np.array([2.0, 1.0, math.pi / 2]))
    return ColonyFrame("cctv", {"cctv": np.eye(4), "r": mine}, {"r": alignment}), mine


def test_fix_in_own_frame_is_the_pose_through_the_alignment_and_its_error_counted() -> None:
    alignment = np.diag([0.02**2, 0.03**2, math.radians(1.0) ** 2])
    frame, mine = _frame(alignment)
    body = _at(4.0, 3.0, 0.0, 0.3)  # the robot seen at (4, 3), heading 0.3, CCTV frame
    cov6 = np.diag([0.05**2, 0.01**2, 1.0, 1.0, 1.0, 0.1**2])
    once = fix_in_own_frame(frame, "r", "cctv", body, cov6)
    assert once is not None
    pose, cov = once
    # in r's frame: (4, 3) - (2, 1) = (2, 2) turned by -90 degrees is (2, -2); heading 0.3 - pi/2
    assert pose == pytest.approx([2.0, -2.0, 0.3 - math.pi / 2])
    # the fix's x-y covariance turned by -90 degrees: x and y swap
    fix_part = np.diag([0.01**2, 0.05**2, 0.1**2])
    shared = frame_error.at(frame_error.moved(alignment, np.linalg.inv(mine)), pose[:2])
    assert cov == pytest.approx(fix_part + shared)
    third = fix_in_own_frame(frame, "r", "cctv", body, cov6, count=3)
    assert third is not None
    assert third[1] == pytest.approx(fix_part + 3 * shared)
    biased = fix_in_own_frame(frame, "r", "cctv", body, cov6, count=2, bias=0.02)
    assert biased is not None
    assert biased[1] == pytest.approx(fix_part + 2 * (shared + np.diag([4e-4, 4e-4, 0.0])))
    assert fix_in_own_frame(frame, "r", "other", body, cov6) is None


def test_fix_counter_counts_per_sender_and_alignment() -> None:
    frame, _ = _frame(np.eye(3) * 1e-4)
    counter = FixCounter()
    key = counter.key(frame, "r", "cctv")
    assert key is not None and counter.key(frame, "r", "other") is None
    assert counter.next("cctv", key) == 1
    counter.fused("cctv", key)
    counter.fused("cctv", key)
    assert counter.next("cctv", key) == 3
    moved, _ = _frame(np.eye(3) * 1e-4)
    moved.transforms["r"] = se2.to_matrix(np.array([2.1, 1.0, math.pi / 2]))
    other = counter.key(moved, "r", "cctv")
    assert other is not None and other != key and counter.next("cctv", other) == 1


def test_n_fixes_through_one_alignment_count_its_error_harmonically_not_n_times() -> None:
    """Fixes whose own error is nil and whose alignment's error is A: the filter, from a vague
    prior, ends with the variance A / H_n (H_n = 1 + 1/2 + ... + 1/n), where fusing each with A
    alone would claim A / n."""
    a = np.diag([0.04**2, 0.04**2, math.radians(1.0) ** 2])
    n = 17
    counted, plain = (
        PlanarEkf(np.zeros(3), np.eye(3) * 1e4),
        PlanarEkf(np.zeros(3), np.eye(3) * 1e4),
    )
    for k in range(1, n + 1):
        assert counted.update(np.zeros(3), k * a, gate=None)
        assert plain.update(np.zeros(3), a, gate=None)
    harmonic = sum(1.0 / k for k in range(1, n + 1))
    assert np.diag(counted.covariance) == pytest.approx(np.diag(a) / harmonic, rel=1e-3)
    assert np.diag(plain.covariance) == pytest.approx(np.diag(a) / n, rel=1e-3)


def test_an_alignment_from_sightings_counts_our_own_pose_error_when_seen() -> None:
    """Sightings that fit one transform to a millimetre still carry our drift: a robot 5 m out
    along x whose estimate was 1 degree unsure makes the alignment 1 degree unsure, and ~9 cm
    at our origin (the turn about where it was seen)."""
    from colonyd.fixes import sightings_covariance

    positions = np.array([[5.0, -0.5, 0.0], [5.0, 0.5, 0.0], [5.5, 0.0, 0.0]])
    residual = frame_error.planar(sightings_covariance(0.001, 1.0, positions))
    assert math.sqrt(residual[2, 2]) == pytest.approx(math.radians(0.1))  # the floor: no drift
    own = np.diag([0.02**2, 0.02**2, math.radians(1.0) ** 2])
    pose = np.array([5.0, 0.0, 0.0])
    honest = frame_error.planar(sightings_covariance(0.001, 1.0, positions, (pose, own)))
    assert math.sqrt(honest[2, 2]) == pytest.approx(math.radians(1.0), rel=0.05)
    # a turn of 1 degree about (5, 0) moves our origin by 5 m x 1 degree across it (y)
    assert math.sqrt(honest[1, 1]) == pytest.approx(
        math.hypot(0.02, 5.0 * math.radians(1.0)), rel=0.05
    )
    assert math.sqrt(honest[0, 0]) == pytest.approx(0.02, rel=0.3)
    assert honest[1, 2] < 0.0  # the origin moves against the turn's lever
