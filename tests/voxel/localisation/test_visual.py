"""RGB-D visual odometry: depth-only alignment on a constructed room with a known motion;
ORB + depth on real frames."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.shared import SHARED_DATA
from voxel.errors import LocalisationError
from voxel.localisation.metrics import absolute_trajectory_error
from voxel.localisation.visual import VisualOdometry
from voxel.registration.transform import rigid

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
KITCHEN = SHARED_DATA / "redkitchen-seq01-a"

#: A room (inside of a box) with a block in it: planes n . x = c.
PLANES = [
    ((1, 0, 0), 2.0),
    ((-1, 0, 0), 2.5),
    ((0, 1, 0), 0.6),
    ((0, -1, 0), 0.8),
    ((0, 0, 1), 3.0),
    ((0, 0, -1), 1.0),
]


def _render(pose: np.ndarray, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    """Depth image (metres) of the room and an axis-aligned block, seen by a camera at `pose`
    (camera-to-world)."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack(
        [(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], axis=-1
    ).reshape(-1, 3)
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    best = np.full(len(d), np.inf)
    for normal, c in PLANES:
        n = np.asarray(normal, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - n @ o) / (d @ n)
        best = np.where((t > 0) & (t < best), t, best)
    lo, hi = np.array([0.3, -0.3, 1.6]), np.array([0.9, 0.3, 2.2])  # a block
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (near <= far) & (near > 0)
    best = np.where(hit & (near < best), near, best)
    return best.reshape(h, w).astype(np.float32)  # z = t for rays with z = 1


def test_depth_only_alignment_recovers_a_known_motion() -> None:
    vo = VisualOdometry(K)
    first = rigid(0.0, 0.0, 0.0)
    second = rigid(0.04, -0.02, 0.03, roll=0.01, pitch=math.radians(2.0), yaw=-0.015)
    assert vo.step(None, _render(first)).method == "first"
    step = vo.step(None, _render(second))
    assert step.method == "icp"
    np.testing.assert_allclose(step.pose[:3, 3], second[:3, 3], atol=3e-3)
    angle = math.acos(min(1.0, (np.trace(step.pose[:3, :3].T @ second[:3, :3]) - 1) / 2))
    assert angle < math.radians(0.2)


def test_bad_inputs_say_what_was_expected() -> None:
    with pytest.raises(
        LocalisationError, match=r"K: expected 3x3 intrinsics, found shape \(2, 2\)"
    ):
        VisualOdometry(np.eye(2))
    with pytest.raises(
        LocalisationError, match=r"depth: expected a \(H, W\) image in metres, found shape \(4,\)"
    ):
        VisualOdometry(K).step(None, np.zeros(4))


@pytest.mark.skipif(not KITCHEN.is_dir(), reason=f"real 7-Scenes sequence not found at {KITCHEN}")
def test_orb_and_depth_track_real_kinect_frames() -> None:
    frames = sorted((KITCHEN / "frames").glob("frame-*.depth.png"))[:25]
    kitchen_k = np.loadtxt(KITCHEN / "camera-intrinsics.txt")
    vo = VisualOdometry(kitchen_k)
    est, ref, methods = [], [], []
    for path in frames:
        stem = path.name[: -len(".depth.png")]
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        depth = np.where((raw == 0) | (raw == 65535), np.nan, raw / 1000.0).astype(np.float32)
        gray = cv2.imread(str(path.with_name(f"{stem}.color.jpg")), cv2.IMREAD_GRAYSCALE)
        step = vo.step(gray, depth)
        est.append(step.pose)
        methods.append(step.method)
        ref.append(np.loadtxt(path.with_name(f"{stem}.pose.txt")))
    assert methods.count("orb+icp") == len(frames) - 1
    assert absolute_trajectory_error(np.array(ref), np.array(est)).rmse < 0.03
