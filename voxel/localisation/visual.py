"""RGB-D visual odometry: ORB features with depth and PnP RANSAC between frames, refined (or
replaced where images lack texture) by depth point-to-plane ICP against the camera's recent
keyframes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation.scan_match import LocalMap, Match, match


@dataclass(frozen=True)
class VisualParams:
    """Parameters of `VisualOdometry` (plain values)."""

    features: int = 1000
    min_inliers: int = 20  # fewer PnP inliers: the frame lacks texture, depth alone aligns it
    reprojection_px: float = 3.0
    ransac_iterations: int = 200
    max_depth: float = 4.0  # metres; farther depth is too noisy to align on
    stride: int = 4  # depth pixels taken for ICP, every stride-th on each axis
    icp_points: int = 4000
    keyframes: int = 20
    map_cell: float = 0.03
    key_distance: float = 0.1
    key_angle: float = 0.1
    max_distance: float = 0.1
    final_distance: float = 0.04
    iterations: int = 15


@dataclass(frozen=True)
class VisualStep:
    """One tracked frame: camera pose in the first camera's frame, how it was found, ORB inliers."""

    pose: np.ndarray  # (4, 4) camera-to-world
    # "first", "orb+icp", "icp" (depth only), "orb" (ICP failed), "lost" (kept the prediction)
    method: str
    inliers: int
    match: Match | None


def _back_project(depth: np.ndarray, K: np.ndarray, stride: int, max_depth: float) -> np.ndarray:
    z = depth[::stride, ::stride]
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    ok = np.isfinite(z) & (z > 0) & (z < max_depth)
    z = z[ok].astype(np.float64)
    return np.column_stack([(u[ok] - K[0, 2]) * z / K[0, 0], (v[ok] - K[1, 2]) * z / K[1, 1], z])


class VisualOdometry:
    """Camera pose of a handheld or mounted RGB-D camera from its images alone (no wheel
    odometry)."""

    def __init__(self, K: np.ndarray, params: VisualParams | None = None) -> None:
        self.K = np.asarray(K, np.float64)
        if self.K.shape != (3, 3):
            msg = f"K: expected 3x3 intrinsics, found shape {self.K.shape}"
            raise LocalisationError(msg)
        import cv2  # loads with a depth camera's odometry, not at start-up

        self.params = p = params or VisualParams()
        self.orb = cv2.ORB_create(nfeatures=p.features)  # type: ignore[attr-defined]  # not in cv2's stubs
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.local = LocalMap(
            planar=False,
            keyframes=p.keyframes,
            cell=p.map_cell,
            k=10,
            key_distance=p.key_distance,
            key_angle=p.key_angle,
        )
        self.pose: np.ndarray | None = None
        self.velocity = np.eye(4)
        self.previous: tuple[np.ndarray, np.ndarray] | None = (
            None  # 3D points (camera frame), descriptors
        )
        self.rng = np.random.default_rng(0)

    def features(
        self, gray: np.ndarray | None, depth: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ORB keypoints (pixels), their camera-frame 3D points and descriptors, keeping those with
        valid depth."""
        empty = (np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 32), np.uint8))
        if gray is None:
            return empty
        kps, desc = self.orb.detectAndCompute(gray, None)
        if desc is None or not kps:
            return empty
        px = np.array([k.pt for k in kps])
        u = np.clip(np.round(px[:, 0]).astype(int), 0, depth.shape[1] - 1)
        v = np.clip(np.round(px[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[v, u].astype(np.float64)
        ok = np.isfinite(z) & (z > 0) & (z < self.params.max_depth)
        z = z[ok]
        xyz = np.column_stack(
            [
                (px[ok, 0] - self.K[0, 2]) * z / self.K[0, 0],
                (px[ok, 1] - self.K[1, 2]) * z / self.K[1, 1],
                z,
            ]
        )
        return px[ok], xyz, desc[ok]

    def _pnp(self, px: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray | None, int]:
        """Motion (previous camera to current camera, 4x4) from ORB matches, or None; and the inlier
        count."""
        if self.previous is None or len(desc) < 6 or len(self.previous[1]) < 6:
            return None, 0
        pairs = self.matcher.match(self.previous[1], desc)
        if len(pairs) < self.params.min_inliers:
            return None, len(pairs)
        a = np.array([m.queryIdx for m in pairs])
        b = np.array([m.trainIdx for m in pairs])
        import cv2

        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            self.previous[0][a],
            px[b],
            self.K,
            None,
            iterationsCount=self.params.ransac_iterations,
            reprojectionError=self.params.reprojection_px,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        count = 0 if inliers is None else len(inliers)
        if not ok or count < self.params.min_inliers:
            return None, count
        idx = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(
            self.previous[0][a[idx]], px[b[idx]], self.K, None, rvec, tvec
        )
        cur_from_prev = np.eye(4)
        cur_from_prev[:3, :3] = cv2.Rodrigues(rvec)[0]
        cur_from_prev[:3, 3] = tvec.ravel()
        return np.linalg.inv(cur_from_prev), count

    def step(self, gray: np.ndarray | None, depth: np.ndarray) -> VisualStep:
        """Track one frame: `gray` (H, W) uint8 image or None (depth only), `depth` (H, W) metres,
        NaN = none."""
        p = self.params
        depth = np.asarray(depth)
        if depth.ndim != 2:
            msg = f"depth: expected a (H, W) image in metres, found shape {depth.shape}"
            raise LocalisationError(msg)
        px, xyz, desc = self.features(gray, depth)
        cloud = _back_project(depth, self.K, p.stride, p.max_depth)
        if self.pose is None:
            self.pose = np.eye(4)
            self._keep(px, xyz, desc, cloud, first=True)
            return VisualStep(self.pose.copy(), "first", 0, None)
        motion, inliers = self._pnp(px, desc)
        predicted = self.pose @ (self.velocity if motion is None else motion)
        source = (
            cloud
            if len(cloud) <= p.icp_points
            else cloud[self.rng.choice(len(cloud), p.icp_points, replace=False)]
        )
        result = match(
            source,
            self.local,
            predicted,
            dof=6,
            max_distance=p.max_distance,
            final_distance=p.final_distance,
            iterations=p.iterations,
            robust_scale=0.02,
            min_matched=100,
        )
        if result.ok:
            pose, method = result.pose, "icp" if motion is None else "orb+icp"
        else:
            pose, method = predicted, "lost" if motion is None else "orb"
        self.velocity = np.linalg.inv(self.pose) @ pose
        self.pose = pose
        self._keep(px, xyz, desc, cloud)
        return VisualStep(pose.copy(), method, inliers, result)

    def _keep(
        self,
        px: np.ndarray,
        xyz: np.ndarray,
        desc: np.ndarray,
        cloud: np.ndarray,
        first: bool = False,
    ) -> None:
        self.previous = (xyz, desc)
        pose = self.pose
        assert pose is not None  # step() sets the pose before it keeps a frame
        if first or self.local.wants(pose):
            self.local.add(cloud @ pose[:3, :3].T + pose[:3, 3], pose)
