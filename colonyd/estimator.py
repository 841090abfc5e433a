"""Estimator: an agent's sensor pose from its observations (EKF + scan matching, or VO)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from colonyd.resume import EstimatorState
from plugins.adapter import SensorAdapter
from plugins.depth import marker_sd
from plugins.observation import Observation
from voxel.localisation import se2
from voxel.localisation.colony_map import ColonyMap
from voxel.localisation.ekf import PlanarEkf
from voxel.localisation.localiser import ScanLocaliser, ScanParams, Through
from voxel.localisation.visual import VisualOdometry


class Estimator(Protocol):
    """Turns each observation into the estimated sensor pose (4x4) in the agent's own frame."""

    name: str

    def __call__(self, obs: Observation) -> np.ndarray: ...

    def covariance(self) -> np.ndarray | None:
        """The latest estimate's 6x6 covariance (x y z roll pitch yaw), if the estimator has one."""
        ...


class ScanEstimator:
    """Adapter of `ScanLocaliser` to observations: body-frame points in, sensor pose out."""

    name = "ekf+scan-to-map"

    def __init__(self, planar: bool, mount: np.ndarray, sensor_range: float = 30.0) -> None:
        # A 3D scan (depth image, 3D LiDAR) is thinned to 10 cm: a tenth of the cost of 5 cm,
        # as accurate on room-sized geometry (docs/LOCALISATION.md).
        self.localiser = ScanLocaliser(
            planar=planar,
            params=None if planar else ScanParams(scan_cell=0.1, map_cell=0.1, max_points=1500),
            sensor=mount[:3, 3],
        )
        self.mount = mount
        self.planar = planar
        self.height = float(mount[2, 3])  # a 2D scan's height in the body frame
        self.sensor_range = float(sensor_range)
        #: The aligned peers' map near the agent (set by the daemon's colony-map thread).
        self.colony: ColonyMap | None = None

    def __call__(self, obs: Observation) -> np.ndarray:
        points = obs.points if obs.no_return is None else obs.points[~obs.no_return]
        body = points @ self.mount[:3, :3].T + self.mount[:3, 3]
        odometry = None if obs.odometry is None else se2.from_matrix(obs.odometry)
        step = self.localiser.step(body, odometry, colony=self.colony, time=obs.time)
        pose: np.ndarray = se2.to_matrix(step.pose) @ self.mount
        return pose

    @property
    def framed(self) -> bool:
        """Whether the filter estimates the error of the alignments fixes and landmarks come
        through (`ScanParams.alignment_frames`): the callers then leave it out of their
        covariances and give the alignment (`Through`)."""
        return self.localiser.params.alignment_frames

    def fix(
        self,
        pose: np.ndarray,
        covariance: np.ndarray,
        stamp: float,
        through: Through | None = None,
    ) -> bool | None:
        """Fuse an absolute body pose (x, y, yaw) in our frame seen at `stamp`, with `through`
        the alignment it came through (see `ScanLocaliser.fix`)."""
        return self.localiser.fix(pose, covariance, stamp, through)

    def landmarks(self, obs: Observation, known: Mapping[int, tuple[Any, ...]]) -> None:
        """Fuse every object of `obs` whose identity the colony knows (`known`: object id ->
        its (x, y) in our frame, 2x2 covariance and optionally the alignment it came through,
        `colony_landmarks`): its position seen from the body now, with a camera's error of
        2 cm + 2 % of the range; the id keys its error in the filter
        (`ScanParams.landmark_errors`)."""
        for det in obs.objects:
            entry = known.get(det.object_id)
            if entry is None:
                continue
            body = self.mount[:3, :3] @ det.position + self.mount[:3, 3]
            sd = marker_sd(float(np.linalg.norm(det.position)))
            via = entry[2] if len(entry) > 2 else None
            self.localiser.landmark(
                body[:2], np.eye(2) * sd**2, entry[0], entry[1], key=det.object_id, through=via
            )

    def counts(self) -> dict[str, int]:
        """Updates fused and refused so far, by kind."""
        loc = self.localiser
        ekf = loc.ekf
        return {
            "updates_accepted": 0 if ekf is None else ekf.accepted,
            "updates_rejected": 0 if ekf is None else ekf.rejected,
            "colony_accepted": loc.colony_accepted,
            "colony_rejected": loc.colony_rejected,
            "colony_failed": loc.colony_failed,
            "colony_suspended": loc.colony_suspended,
            "fix_accepted": loc.fix_accepted,
            "fix_rejected": loc.fix_rejected,
            "fix_stale": loc.fix_stale,
            "landmark_accepted": loc.landmark_accepted,
            "landmark_rejected": loc.landmark_rejected,
        }

    def state(self) -> EstimatorState | None:
        """What `restore` needs to continue in the same frame: the filter's pose, its
        covariance and the last odometry reading (None before the first step)."""
        loc = self.localiser
        if loc.ekf is None:
            return None
        return EstimatorState(loc.ekf.pose, loc.ekf.covariance, loc.last_odometry)

    def restore(self, state: EstimatorState) -> None:
        """Continue from a stored `state` (before the first step): the next odometry reading
        predicts from the stored pose, so the estimate stays in the frame the layer was built
        in. Only the pose part: the keyframe map and its states in the filter, the estimated
        errors of alignments and landmarks and the recent poses (`pose_at`) start empty, so the
        first scans after it match against keyframes rebuilt from the stored pose."""
        loc = self.localiser
        loc.ekf = PlanarEkf(state.pose, state.covariance, motion=loc.motion)
        loc.last_odometry = None if state.odometry is None else state.odometry.copy()

    def covariance(self) -> np.ndarray | None:
        ekf = self.localiser.ekf
        if ekf is None:
            return None
        planar = ekf.covariance  # x, y, yaw
        cov = np.zeros((6, 6))
        cov[np.ix_([0, 1, 5], [0, 1, 5])] = planar
        return cov


class VisualEstimator:
    """Adapter of `VisualOdometry` to depth observations (colour image when there is one)."""

    name = "rgbd-visual-odometry"

    def __init__(self) -> None:
        self.odometry: VisualOdometry | None = None

    def __call__(self, obs: Observation) -> np.ndarray:
        import cv2

        view = obs.depth
        if view is None:
            from voxel.errors import LocalisationError

            msg = (
                f"{obs.frame}: expected a source an estimator can follow (a 2D or 3D LiDAR, a "
                "sensor with odometry, or a depth camera for visual odometry), found points "
                "with neither odometry nor a depth image"
            )
            raise LocalisationError(msg)
        if self.odometry is None:
            self.odometry = VisualOdometry(view.K)
        gray = None if view.image is None else cv2.cvtColor(view.image, cv2.COLOR_RGB2GRAY)
        return self.odometry.step(gray, view.depth).pose

    def covariance(self) -> np.ndarray | None:
        return None  # visual odometry alone keeps no covariance


def get_estimator(adapter: SensorAdapter, first: Observation) -> Estimator:
    """The estimator for a source: scan matching for range sensors and for any agent with
    odometry (depth points serve as a scan), visual odometry for a camera without it."""
    if adapter.kind in ("lidar2d", "lidar3d") or first.odometry is not None:
        return scan_estimator(adapter)
    return VisualEstimator()


def scan_estimator(adapter: SensorAdapter) -> ScanEstimator:
    """The scan-matching estimator for a source read by `adapter` (its mount, its range)."""
    model = getattr(adapter, "sensor_model", None)
    sensor_range = 30.0 if model is None else min(float(model.max_range), 30.0)
    return ScanEstimator(
        adapter.kind == "lidar2d", getattr(adapter, "mount", np.eye(4)), sensor_range
    )


class PoseError:
    """Evaluation only (a simulator's truth): how far the estimate has drifted from the truth
    since the first frame, where the agent's frame and the truth are put together."""

    def __init__(self) -> None:
        self._first: tuple[np.ndarray, np.ndarray] | None = None
        self.last: float | None = None

    def update(self, estimate: np.ndarray, truth: np.ndarray | None) -> float | None:
        """Translation error (m) of the estimate's motion since the first frame, or None."""
        if truth is None:
            return self.last
        if self._first is None:
            self._first = (np.linalg.inv(estimate), np.linalg.inv(truth))
        est = self._first[0] @ estimate
        ref = self._first[1] @ truth
        self.last = float(np.linalg.norm(est[:3, 3] - ref[:3, 3]))
        return self.last
