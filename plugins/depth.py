"""Depth camera adapter: depth image plus intrinsics (or field of view) to points, colour and
labels."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from plugins.checks import as_array, as_pose, camera_intrinsics
from plugins.errors import SensorInputError
from plugins.observation import DepthView, ObjectDetection, Observation
from voxel.depth import camera_points
from voxel.sensor import SensorModel


@dataclass(frozen=True)
class DepthFrame:
    """One depth camera reading: depth (H, W) in metres (float) or raw units (integer)."""

    depth: np.ndarray
    colour: np.ndarray | None = None  # (H, W, 3) uint8, registered to depth
    labels: np.ndarray | None = None  # (H, W) int class ids, negative = unlabelled
    label_probs: np.ndarray | None = None  # (H, W) float in [0, 1]
    normals: np.ndarray | None = None  # (H, W, 3) float, camera frame


class DepthCamera:
    """Pinhole depth camera (OpenCV frame: x right, y down, z forward)."""

    name = "depth"
    kind = "depth"

    def __init__(
        self,
        *,
        K: np.ndarray | None = None,
        fov: float | None = None,
        width: int = 640,
        height: int = 480,
        depth_scale: float = 0.001,
        invalid: tuple[int, ...] = (0, 65535),
        min_range: float = 0.0,
        max_range: float = 10.0,
        stride: int = 1,
        mount: np.ndarray | None = None,
        reliability: float = 1.0,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        noise: float = 0.0,
        markers: str | None = None,
        marker_length: float = 0.2,
        marker_classes: dict[int, int] | None = None,
    ) -> None:
        self.K = camera_intrinsics(K, fov, width, height, "depth camera")
        #: With `markers` (an ArUco dictionary name), ArUco markers in the colour image are
        #: reported as identified objects (landmarks), placed by the depth at their centre.
        self.markers: Any = None
        if markers is not None:
            from plugins.cctv import CctvCamera  # OpenCV's ArUco detector, as the CCTV's

            self.markers = CctvCamera(
                K=self.K,
                dictionary=markers,
                marker_length=marker_length,
                marker_classes=marker_classes,
            )
        self.width, self.height = int(width), int(height)
        if stride < 1:
            msg = f"stride: expected an integer >= 1, found {stride!r}"
            raise SensorInputError(msg)
        self.depth_scale, self.invalid, self.stride = (
            float(depth_scale),
            tuple(invalid),
            int(stride),
        )
        self.min_range, self.max_range = float(min_range), float(max_range)
        self.mount = np.eye(4) if mount is None else as_pose(mount, "mount")
        self.reliability = float(reliability)
        self.noise = float(noise)
        self.sensor_model = SensorModel(
            prob_hit=prob_hit, prob_miss=prob_miss, max_range=max_range, kind="depth"
        )

    def metres(self, depth: np.ndarray, field: str = "depth") -> np.ndarray:
        """Depth in metres (float32), NaN where there is no reading or it is out of range."""
        raw = np.asarray(depth)
        if raw.ndim != 2:
            msg = f"{field}: expected a (H, W) depth image, found shape {raw.shape}"
            raise SensorInputError(msg)
        if raw.dtype.kind in "iu":
            out = raw.astype(np.float32) * np.float32(self.depth_scale)
            out[np.isin(raw, self.invalid)] = np.nan
        elif raw.dtype.kind == "f":
            out = raw.astype(np.float32, copy=True)
        else:
            msg = f"{field}: expected an integer or float depth image, found dtype {raw.dtype}"
            raise SensorInputError(msg)
        with np.errstate(invalid="ignore"):
            out[(out <= self.min_range) | (out > self.max_range) | (out <= 0)] = np.nan
        return out

    def observe(
        self,
        reading: DepthFrame | np.ndarray,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Observation of one depth frame; `pose` is the body pose (camera pose = pose @ mount)."""
        if not isinstance(reading, DepthFrame):
            reading = DepthFrame(depth=reading)
        depth = self.metres(reading.depth)
        h, w = depth.shape
        points, index = camera_points(depth, self.K, self.stride)
        extras: dict[str, Any] = {}  # Observation fields: arrays, and a dict of scalar channels
        colour = None
        if reading.colour is not None:
            colour = as_array(reading.colour, "colour", shape=(h, w, 3), dtype=np.uint8)
            extras["colours"] = colour.reshape(-1, 3)[index]
        if reading.labels is not None:
            labels = as_array(reading.labels, "labels", shape=(h, w), dtype=np.int32)
            extras["class_ids"] = np.where(
                labels.reshape(-1)[index] < 0, -1, labels.reshape(-1)[index]
            )
            probs = (
                np.ones(h * w, np.float32)
                if reading.label_probs is None
                else as_array(
                    reading.label_probs, "label_probs", shape=(h, w), dtype=np.float32
                ).reshape(-1)
            )
            extras["class_probs"] = probs[index]
        if reading.normals is not None:
            normals = as_array(
                reading.normals, "normals", shape=(h, w, 3), dtype=np.float32, finite=False
            )
            extras["normals"] = np.nan_to_num(normals.reshape(-1, 3)[index])
        if self.markers is not None and colour is not None:
            extras["objects"] = self._markers(colour, depth)
        body = np.eye(4) if pose is None else as_pose(pose, "pose")
        return Observation(
            sensor=self.name,
            time=time,
            points=points,
            pose=body @ self.mount,
            odometry=odometry,
            depth=DepthView(depth=depth, K=self.K, image=colour),
            frame=frame,
            **extras,
        )

    def _markers(self, colour: np.ndarray, depth: np.ndarray) -> tuple[ObjectDetection, ...]:
        """ArUco markers in the colour image (RGB), each at the median depth of its quad's
        middle, along the ray through its centre (a small marker's solved range is its worst
        coordinate; the depth image measures it); markers without depth there are dropped."""
        import cv2

        found = []
        for det in self.markers.detect(cv2.cvtColor(colour, cv2.COLOR_RGB2BGR)):
            centre = det.corners.mean(axis=0)
            half = max(1, int(0.2 * np.ptp(det.corners[:, 0])))
            u, v = round(float(centre[0])), round(float(centre[1]))
            patch = depth[max(v - half, 0) : v + half + 1, max(u - half, 0) : u + half + 1]
            if not np.any(np.isfinite(patch)):
                continue
            z = float(np.nanmedian(patch))
            ray = np.linalg.solve(self.K, np.array([centre[0], centre[1], 1.0]))
            pose = det.pose.copy()
            pose[:3, 3] = ray / ray[2] * z
            sd = marker_sd(float(np.linalg.norm(pose[:3, 3])))
            found.append(replace(det, pose=pose, covariance=np.eye(3) * sd**2))
        return tuple(found)


def marker_sd(range_m: float) -> float:
    """Standard deviation (m) of a marker's centre placed by the depth image `range_m` m away:
    2 cm + 2 % of the range, in any direction."""
    return 0.02 + 0.02 * range_m


def fov_of(K: np.ndarray, width: int) -> float:
    """Horizontal field of view (radians) of intrinsics K for an image `width` pixels wide."""
    return 2.0 * math.atan(0.5 * width / K[0, 0])
