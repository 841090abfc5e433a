"""Tests of the CCTV adapter: ArUco detection and pose on rendered images, depth mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plugins.cctv import (
    CORNER_PX,
    FALLBACK_CORNER_PX,
    CctvCamera,
    CctvFrame,
    aruco_dictionary,
    edge_corners,
    marker_corners,
    marker_covariance,
    refine_corners,
)
from plugins.checks import pose_matrix
from plugins.errors import SensorInputError
from plugins.observation import ObjectDetection
from plugins.sim import OPTICAL, Rig, make_rig, render
from plugins.world import CLASSES, Box, Marker, World


def camera_rig(camera: CctvCamera, w: int = 640, h: int = 480) -> Rig:
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack(
        [
            (u - camera.K[0, 2]) / camera.K[0, 0],
            (v - camera.K[1, 2]) / camera.K[1, 1],
            np.ones((h, w)),
        ],
        -1,
    )
    return Rig(d.reshape(-1, 3), OPTICAL, (h, w), camera.K)


def tagged_pillar(marker_id: int = 7) -> World:
    # a pillar whose -x face is the plane x = 2.0, marker (0.2 m) centred at (2.0, 0.1, 1.05)
    # facing -x
    pillar = Box((2.0, -0.3, 0.0), (2.4, 0.3, 1.6), CLASSES["landmark"], 42)
    marker = Marker(marker_id, (2.0, 0.1, 1.05), (-1.0, 0.0, 0.0), 0.2, 42)
    return World(name="pillar", boxes=[pillar], markers=[marker])


@pytest.mark.parametrize(("x", "y", "yaw"), [(0.0, 0.0, 0.0), (0.3, -0.8, math.radians(20))])
def test_marker_pose_on_a_rendered_image_within_2cm_at_2m(x: float, y: float, yaw: float) -> None:
    world = tagged_pillar()
    body = pose_matrix(x, y, 1.0, yaw)
    pose = body @ OPTICAL
    camera = CctvCamera(pose=pose, fov=math.radians(60), marker_classes={7: CLASSES["landmark"]})
    frame = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0)
    obs = camera.observe(frame)
    assert [d.object_id for d in obs.objects] == [7]
    found = obs.objects[0]
    truth = np.linalg.inv(pose) @ world.markers[0].frame()
    distance = np.linalg.norm(truth[:3, 3])
    assert 1.7 < distance < 2.3
    assert np.linalg.norm(found.position - truth[:3, 3]) <= 0.02
    # orientation: marker normal within 10 degrees (a fronto-parallel square is ambiguous)
    cos = float(found.pose[:3, 2] @ truth[:3, 2])
    assert cos > math.cos(math.radians(10))
    assert found.class_id == CLASSES["landmark"] and 0.5 < found.probability <= 0.99
    # in the site frame, via the camera's known pose
    site = obs.pose @ found.pose
    assert np.linalg.norm(site[:3, 3] - world.markers[0].centre) <= 0.02


def test_depth_channel_maps_the_view_and_labels_marker_pixels() -> None:
    world = tagged_pillar()
    pose = pose_matrix(0.0, 0.0, 1.0, 0.0) @ OPTICAL
    camera = CctvCamera(pose=pose, fov=math.radians(60), marker_classes={7: CLASSES["landmark"]})
    frame = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0)
    assert frame.depth is not None
    obs = camera.observe(frame)
    assert len(obs) > 10000 and obs.colours is not None
    labelled = obs.class_ids == CLASSES["landmark"]
    assert labelled.sum() > 100
    pts = obs.points_world()[labelled]
    assert np.abs(pts[:, 0] - 2.0).max() < 1e-3  # marker pixels lie on the pillar face
    np.testing.assert_allclose(pts.mean(axis=0)[1:], [0.1, 1.05], atol=0.02)


def test_image_without_markers_and_bad_images() -> None:
    camera = CctvCamera(fov=1.0)
    assert camera.observe(np.full((120, 160, 3), 128, np.uint8)).objects == ()
    with pytest.raises(
        SensorInputError,
        match=r"image: expected \(H, W\) or \(H, W, 3\) uint8, found shape \(4, 4\) dtype float64",
    ):
        camera.observe(np.zeros((4, 4)))
    with pytest.raises(
        SensorInputError, match=r"depth: expected the image's shape \(4, 4\), found \(3, 4\)"
    ):
        camera.observe(CctvFrame(image=np.zeros((4, 4), np.uint8), depth=np.ones((3, 4))))
    with pytest.raises(
        SensorInputError,
        match="dictionary: expected an ArUco dictionary name like 'DICT_4X4_50', found 'DICT_9X9'",
    ):
        aruco_dictionary("DICT_9X9")
    with pytest.raises(SensorInputError, match="marker_length: expected a positive length"):
        CctvCamera(fov=1.0, marker_length=0.0)


def test_a_markers_covariance_is_long_along_the_ray_by_its_side_in_pixels() -> None:
    # the calibration (docs/BENCHMARKS.md "The CCTV's claimed covariances": RMS 0.22 px of the
    # side over 199 boards and 10 landmarks): a revert to 0.5 (twice the error) fails here
    assert pytest.approx(0.25, abs=0.03) == CORNER_PX
    # 10 m straight ahead, 10 px across: range x CORNER_PX / 10 px along the ray, 1 cm
    # across it; turned with the ray
    cov = marker_covariance(np.array([0.0, 0.0, 10.0]), 10.0)
    along = 10.0 * CORNER_PX / 10.0
    np.testing.assert_allclose(cov, np.diag([1e-4, 1e-4, along**2]), atol=1e-12)
    ray = np.array([3.0, 0.0, 4.0]) / 5.0
    cov = marker_covariance(5.0 * ray, 25.0)  # 5 m, 25 px: 5 CORNER_PX / 25 m along
    np.testing.assert_allclose(ray @ cov @ ray, (5.0 * CORNER_PX / 25.0) ** 2, atol=1e-12)
    across = np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(across @ cov @ across, 1e-4, atol=1e-12)
    # near and large: never below the floor
    np.testing.assert_allclose(
        marker_covariance(np.array([0.0, 0.0, 0.5]), 200.0), np.eye(3) * 1e-4
    )


def test_a_far_markers_range_error_is_within_its_claimed_covariance() -> None:
    """At 7 m a 0.2 m marker is ~15 px across: its solved range is centimetres off (a fixed
    camera makes the same error in every frame), and its covariance says so along the ray."""
    world = tagged_pillar()
    pose = pose_matrix(-5.0, 0.1, 1.05, 0.0) @ OPTICAL
    camera = CctvCamera(pose=pose, fov=math.radians(60), marker_classes={7: CLASSES["landmark"]})
    frame = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0)
    (found,) = camera.observe(frame).objects
    truth = (np.linalg.inv(pose) @ world.markers[0].frame())[:3, 3]
    error = found.position - truth
    ray = truth / np.linalg.norm(truth)
    assert found.covariance is not None
    along = math.sqrt(ray @ found.covariance @ ray)
    assert 0.05 < along < 0.15  # 7 m x 0.25 px / ~15 px
    assert abs(error @ ray) < 3 * along
    assert np.linalg.norm(error - (error @ ray) * ray) < 0.03


def test_refined_corners_of_an_area_sampled_square_are_exact() -> None:
    """A 20 px black square band (one cell of 6 wide, white inside and out), turned 20 degrees
    and sampled by area (16 x 16 samples per pixel): its refined corners are within 0.03 px of
    the true ones (OpenCV's cornerSubPix alone puts them ~0.2 px inside)."""
    s, n = 16, 48
    a = math.radians(20.0)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    centre = np.array([23.3, 24.1])
    corners = (np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])) @ rot.T
    corners += centre
    fine = (np.mgrid[0 : n * s, 0 : n * s][::-1].transpose(1, 2, 0) + 0.5) / s - 0.5
    local = np.abs((fine - centre) @ rot)  # pixel-centre convention: pixel i spans i +- 0.5
    band = (local.max(axis=2) <= 10.0) & (local.max(axis=2) > 10.0 - 20.0 / 6)
    grey = (255 * (1 - band.reshape(n, s, n, s).mean(axis=(1, 3)))).astype(np.float32)
    start = corners + np.array([[0.4, 0.3], [-0.3, 0.4], [-0.4, -0.3], [0.3, -0.4]])  # inside
    refined, corner_px = refine_corners(np.round(grey).astype(np.uint8), start, 6)
    assert corner_px == CORNER_PX
    assert np.abs(refined - corners).max() < 0.03


def test_a_marker_600_px_wide_is_refined_too() -> None:
    """A marker filling the image (a robot's board right in front of a camera): its corners are
    sampled in rows under cv2.remap's 32767-column limit (one row of ~48000 samples raised)."""
    n = 800
    yx = np.mgrid[0:n, 0:n]
    outer = (np.abs(yx - 400.0).max(axis=0)) <= 300.0
    inner = (np.abs(yx - 400.0).max(axis=0)) <= 200.0
    grey = np.where(outer & ~inner, 0, 255).astype(np.uint8)
    corners = np.array([[99.5, 99.5], [700.5, 99.5], [700.5, 700.5], [99.5, 700.5]])
    refined, _ = refine_corners(
        grey, corners + np.array([[1.0, 1.0], [-1, 1], [-1, -1], [1, -1]]), 6
    )
    assert np.abs(refined - corners).max() < 0.1


@pytest.mark.parametrize(("distance", "yaw"), [(5.0, -0.25), (7.0, -0.2), (8.5, 0.0), (10.0, -0.3)])
def test_a_rendered_markers_range_is_within_1_5_percent_at_5_to_10m(
    distance: float, yaw: float
) -> None:
    """The sim CCTV (640 x 480, 75 degrees) sees a 0.3 m landmark marker 5-10 m away (10-25 px
    sides): its corners are not pulled inside the square (mean < 0.2 px) and its range is within
    1.5 % (the render's edges are nearly point-sampled: -1.1 to -0.1 % here, within 0.6 % on an
    area-sampled image; OpenCV's subpixel corners alone: +1.8, +0.4, +2.7, +1.8 % long)."""
    pillar = Box((2.0, -0.5, 0.0), (2.4, 0.5, 2.0), CLASSES["landmark"], 42)
    world = World("pillar", boxes=[pillar], markers=[Marker(7, (2.0, 0.0, 1.0), (-1, 0, 0), 0.3)])
    rig, _ = make_rig("cctv")
    assert rig.K is not None
    pose = pose_matrix(2.0 - distance, 0.3, 1.2, yaw) @ OPTICAL
    camera = CctvCamera(pose=pose, K=rig.K, marker_length=0.3)
    (found,) = camera.detect(render(world, "cctv", rig, pose, np.random.default_rng(0), 0.0).image)
    truth = np.linalg.inv(pose) @ world.markers[0].frame()
    cam = marker_corners(0.3) @ truth[:3, :3].T + truth[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * np.diag(rig.K)[:2] + rig.K[:2, 2]
    assert found.corners is not None
    outward = (uv - uv.mean(axis=0)) / np.linalg.norm(uv - uv.mean(axis=0), axis=1)[:, None]
    inward = -np.einsum("ij,ij->i", found.corners - uv, outward)
    assert abs(inward.mean()) < 0.2
    r = float(np.linalg.norm(truth[:3, 3]))
    assert abs(np.linalg.norm(found.position) - r) < 0.015 * r


def with_bands(image: np.ndarray, quad: np.ndarray, out: float, to: float) -> np.ndarray:
    """`image` with black bands `out` to `to` px outside the sides of `quad` from corner 0 to 1
    and from corner 3 to 0 (clutter in the marker's white margin)."""
    import cv2

    image = image.copy()
    for i in (0, 3):
        a, b = quad[i], quad[(i + 1) % 4]
        inward = quad.mean(axis=0) - (a + b) / 2
        inward /= np.linalg.norm(inward)
        band = np.array([a - out * inward, b - out * inward, b - to * inward, a - to * inward])
        cv2.fillPoly(image, [np.round(band).astype(np.int32)], (0, 0, 0))
    return image


@pytest.mark.parametrize(("out", "to"), [(2.5, 5.5), (1.5, 3.5), (3.0, 5.0)])
def test_clutter_beside_a_marker_is_not_fitted_as_its_edge(out: float, to: float) -> None:
    """Dark bands a few pixels outside two sides of a 0.2 m marker 2 m away (55 px): the
    detector's corners move ~1 px out, the edges' sample windows then hold the band's outer edge
    as well as the square's, and lines fitted to both pulled the marker 7-10 cm along its ray
    while it claimed 1 cm (the fit moved its corners less than its 1 px + a quarter cell limit).
    Such a sample's fall is two edges wide (`EDGE_SPREAD_PX`): the corners fall back to the
    detector's and the claim widens (`FALLBACK_CORNER_PX`), within 3 claimed sd."""
    import cv2

    world = tagged_pillar()
    pose = pose_matrix(0.0, 0.0, 1.0, 0.0) @ OPTICAL
    camera = CctvCamera(pose=pose, fov=math.radians(60), marker_classes={7: CLASSES["landmark"]})
    image = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0).image
    (clean,) = camera.detect(image)
    assert clean.corners is not None
    banded = with_bands(image, clean.corners, out, to)
    (found,) = camera.detect(banded)
    truth = (np.linalg.inv(pose) @ world.markers[0].frame())[:3, 3]
    ray = truth / np.linalg.norm(truth)
    assert found.covariance is not None
    error = float((found.position - truth) @ ray)
    claimed = math.sqrt(ray @ found.covariance @ ray)
    assert abs(error) < 3.0 * claimed, (error, claimed)
    grey = cv2.cvtColor(banded, cv2.COLOR_BGR2GRAY)
    detected = camera.detector.detectMarkers(grey)[0][0].reshape(4, 2)
    assert edge_corners(grey, detected, camera.cells) is None
    assert refine_corners(grey, detected, camera.cells)[1] == FALLBACK_CORNER_PX


def test_a_marker_whose_edge_fit_fails_keeps_the_detectors_corners_and_a_wider_covariance() -> None:
    """Dark bands in the white margin along two sides of a marker (2-6.8 px out, clutter the
    detector ignores) pull their edges' lines off the square: the corners fall back to OpenCV's
    (biased inward), and the covariance along the ray says so (FALLBACK_CORNER_PX, not
    CORNER_PX); the detection without the bands keeps the edges' corners and CORNER_PX."""
    import cv2

    world = tagged_pillar()
    pose = pose_matrix(0.0, 0.0, 1.0, 0.0) @ OPTICAL
    camera = CctvCamera(pose=pose, fov=math.radians(60), marker_classes={7: CLASSES["landmark"]})
    image = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0).image
    (clean,) = camera.detect(image)
    q = clean.corners
    assert q is not None
    for i in (0, 3):  # the sides from corner 0 to 1 and from 3 to 0
        a, b = q[i], q[(i + 1) % 4]
        inward = q.mean(axis=0) - (a + b) / 2
        inward /= np.linalg.norm(inward)
        band = np.array([a - 2.0 * inward, b - 2.0 * inward, b - 6.8 * inward, a - 6.8 * inward])
        cv2.fillPoly(image, [np.round(band).astype(np.int32)], (0, 0, 0))
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    detected = camera.detector.detectMarkers(grey)[0][0].reshape(4, 2)
    assert edge_corners(grey, detected, camera.cells) is None  # forced to fail
    (fallen,) = camera.detect(image)
    assert fallen.corners is not None and np.array_equal(fallen.corners, detected)
    assert fallen.covariance is not None and clean.covariance is not None

    def along(found: ObjectDetection) -> float:
        p, cov = found.position, found.covariance
        assert cov is not None
        return float(np.sqrt(p @ cov @ p) / np.linalg.norm(p))

    sides = np.linalg.norm(np.roll(detected, 1, axis=0) - detected, axis=1).mean()
    np.testing.assert_allclose(
        fallen.covariance, marker_covariance(fallen.position, sides, FALLBACK_CORNER_PX)
    )
    assert along(fallen) > 1.8 * along(clean)  # ~ FALLBACK_CORNER_PX / CORNER_PX
    clean_sides = np.linalg.norm(np.roll(q, 1, axis=0) - q, axis=1).mean()
    np.testing.assert_allclose(
        clean.covariance, marker_covariance(clean.position, clean_sides, CORNER_PX)
    )


@pytest.mark.parametrize("angle", [0.0, 35.0, 60.0])
def test_a_boards_incidence_is_its_solved_normal_against_the_camera_ray(angle: float) -> None:
    """A robot's 0.2 m board 2.5 m away seen at 0, 35 and 60 degrees off its normal: its
    incidence (`board_incidence`, the fix model "angle"'s) is the true angle within 5 degrees;
    a landmark's detection has none."""
    world = tagged_pillar()
    centre = np.array(world.markers[0].centre)
    a = math.radians(angle)
    eye = centre + 2.5 * np.array([-math.cos(a), math.sin(a), 0.0])
    eye[2] = 1.0
    pose = pose_matrix(eye[0], eye[1], eye[2], -a) @ OPTICAL
    mount = np.eye(4)
    mount[2, 3] = centre[2]  # the board 1.05 m above the body (z = 0, the floor)
    camera = CctvCamera(pose=pose, fov=math.radians(60), agent_markers={7: ("robot-1", mount, 0.2)})
    frame = render(world, "cctv", camera_rig(camera), pose, np.random.default_rng(0), 0.0)
    (found,) = camera.detect(frame.image)
    assert found.label == "agent:robot-1"
    assert abs(math.degrees(camera.board_incidence(found)) - angle) < 5.0
    landmark = CctvCamera(pose=pose, fov=math.radians(60)).detect(frame.image)[0]
    with pytest.raises(SensorInputError, match="detection: expected an agent's board"):
        camera.board_incidence(landmark)
