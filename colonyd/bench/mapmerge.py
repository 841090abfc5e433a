"""The peer's method for comparison: multirobot_map_merge's ORB features + RANSAC on occupancy
images.

As m-explore's `combine_grids` does it (read, not copied): ORB features of each occupancy image
(OpenCV stitching's ORB finder: 1500 features, scale 1.3, 5 levels), best-of-2-nearest matching
with match_conf 0.3 (ratio 0.7), a RANSAC partial-affine (rotation, translation, scale) estimate,
and the stitching confidence inliers / (8 + 0.3 * matches); map_merge accepts a pair at
confidence >= 1.0 (its default `estimation_confidence`). Images use the ROS OccupancyGrid values
as bytes: free 0, occupied 100, unknown 255.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from voxel.registration import MapCloud

FREE, OCCUPIED, UNKNOWN = 0, 100, 255
ACCEPT_CONFIDENCE = 1.0


@dataclass(frozen=True)
class BaselineResult:
    """The baseline's estimate (B into A, 4x4, metres) and whether map_merge would merge."""

    merged: bool
    transform: np.ndarray
    confidence: float
    matches: int
    inliers: int
    seconds: float


def occupancy_image(cloud: MapCloud, margin: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """OccupancyGrid-style image of a planar map (row 0 at the top, +y up) and the world xy of
    its lower-left cell's corner."""
    res = cloud.resolution
    layer = math.floor(float(np.median(cloud.occupied[:, 2])) / res)
    occ = np.floor(cloud.occupied[:, :2] / res).astype(np.int64)
    free = np.empty((0, 2), np.int64)
    if cloud.known is not None and cloud.known_occupied is not None:
        from voxel import keys as vk

        keys = vk.unpack(cloud.known[~cloud.known_occupied])
        free = keys[keys[:, 2] == layer, :2]
    lo, hi = occ.min(axis=0) - margin, occ.max(axis=0) + margin
    free = free[np.all((free >= lo) & (free <= hi), axis=1)]
    w, h = (hi - lo + 1).tolist()
    image = np.full((h, w), UNKNOWN, np.uint8)
    image[h - 1 - (free[:, 1] - lo[1]), free[:, 0] - lo[0]] = FREE
    image[h - 1 - (occ[:, 1] - lo[1]), occ[:, 0] - lo[0]] = OCCUPIED
    return image, lo * res


def _pixel_to_world(lo: np.ndarray, height: int, res: float) -> np.ndarray:
    """3x3 matrix taking pixel (u, v, 1) to world (x, y, 1) at the pixel centre."""
    return np.array(
        [[res, 0.0, lo[0] + 0.5 * res], [0.0, -res, lo[1] + (height - 0.5) * res], [0.0, 0.0, 1.0]]
    )


def estimate(a: MapCloud, b: MapCloud, seed: int = 0) -> BaselineResult:
    """map_merge's estimate of the transform taking B's points into A's frame."""
    began = time.perf_counter()
    cv2.setRNGSeed(seed)
    img_a, lo_a = occupancy_image(a)
    img_b, lo_b = occupancy_image(b)
    orb = cv2.ORB_create(nfeatures=1500, scaleFactor=1.3, nlevels=5)  # type: ignore[attr-defined]
    kp_a, des_a = orb.detectAndCompute(img_a, None)
    kp_b, des_b = orb.detectAndCompute(img_b, None)
    none = BaselineResult(False, np.eye(4), 0.0, 0, 0, 0.0)
    if des_a is None or des_b is None or len(kp_a) < 3 or len(kp_b) < 3:
        return _timed(none, began)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs: dict[tuple[int, int], None] = {}
    for q_des, t_des, flip in ((des_b, des_a, False), (des_a, des_b, True)):
        for m in matcher.knnMatch(q_des, t_des, k=2):
            if len(m) == 2 and m[0].distance < 0.7 * m[1].distance:
                key = (m[0].trainIdx, m[0].queryIdx) if flip else (m[0].queryIdx, m[0].trainIdx)
                pairs[key] = None
    if len(pairs) < 6:
        return _timed(BaselineResult(False, np.eye(4), 0.0, len(pairs), 0, 0.0), began)
    src = np.array([kp_b[i].pt for i, _ in pairs], np.float32)
    dst = np.array([kp_a[j].pt for _, j in pairs], np.float32)
    affine, mask = cv2.estimateAffinePartial2D(
        src, dst, method=cv2.RANSAC, ransacReprojThreshold=3.0
    )
    if affine is None:
        return _timed(BaselineResult(False, np.eye(4), 0.0, len(pairs), 0, 0.0), began)
    inliers = int(mask.sum())
    confidence = inliers / (8.0 + 0.3 * len(pairs))
    pix = np.vstack([affine, [0.0, 0.0, 1.0]])
    world = (
        _pixel_to_world(lo_a, img_a.shape[0], a.resolution)
        @ pix
        @ np.linalg.inv(_pixel_to_world(lo_b, img_b.shape[0], b.resolution))
    )
    t = np.eye(4)
    t[:2, :2] = world[:2, :2]
    t[:2, 3] = world[:2, 2]
    t[2, 3] = float(np.median(a.occupied[:, 2]) - np.median(b.occupied[:, 2]))
    return _timed(
        BaselineResult(confidence >= ACCEPT_CONFIDENCE, t, confidence, len(pairs), inliers, 0.0),
        began,
    )


def _timed(r: BaselineResult, began: float) -> BaselineResult:
    return BaselineResult(
        r.merged, r.transform, r.confidence, r.matches, r.inliers, time.perf_counter() - began
    )
