"""TF tree: timed transforms between named frames (ROS /tf, /tf_static, Odometry), looked up at a
time."""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from plugins.errors import SensorInputError
from voxel.rotation import matrix_to_quaternion, quaternion_to_matrix


class TfGapError(SensorInputError):
    """A transform needed at some time is not known (yet): missing frame, or time outside the
    history."""


def transform_matrix(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """4x4 parent-from-child transform of a translation (3,) and a quaternion (x, y, z, w)."""
    q = np.asarray(quaternion, np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-9 or not np.all(np.isfinite(translation)):
        msg = f"transform: expected a finite translation and a non-zero quaternion, found {q}"
        raise SensorInputError(msg)
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(q / n)
    pose[:3, 3] = translation
    return pose


def _interpolate(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """Pose between a (w = 0) and b (w = 1): linear in position, normalised lerp in rotation."""
    qa, qb = matrix_to_quaternion(a[:3, :3]), matrix_to_quaternion(b[:3, :3])
    if float(qa @ qb) < 0:
        qb = -qb
    return transform_matrix(a[:3, 3] * (1 - w) + b[:3, 3] * w, qa * (1 - w) + qb * w)


@dataclass
class _Edge:
    """The transforms parent-from-child over time (one, timeless, for a static edge)."""

    parent: str
    static: bool
    times: deque[float] = field(default_factory=deque)
    poses: deque[np.ndarray] = field(default_factory=deque)


class TfTree:
    """Transforms between frames, each child with one parent (as tf2 keeps them).

    A dynamic edge keeps the last `history` transforms (bounded); a lookup between two of them
    interpolates, one within a lookup's `tolerance` seconds outside them takes the nearest, anything
    else is a `TfGapError` naming the edge.
    """

    def __init__(self, history: int = 400, max_frames: int = 256) -> None:
        self.history, self.max_frames = history, max_frames
        self._edges: dict[str, _Edge] = {}

    def set(self, parent: str, child: str, time: float, pose: np.ndarray, static: bool) -> None:
        """Record parent-from-child at `time`; a static edge keeps only its latest transform."""
        parent, child = parent.strip("/"), child.strip("/")
        if not parent or not child or parent == child:
            msg = f"transform: expected two different frame ids, found {parent!r} -> {child!r}"
            raise SensorInputError(msg)
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent or edge.static != static:
            if edge is None and len(self._edges) >= self.max_frames:
                msg = f"transform: expected at most {self.max_frames} frames, found more"
                raise SensorInputError(msg)
            if self._loops(parent, child):
                msg = f"transform: {parent!r} -> {child!r} would close a loop in the TF tree"
                raise SensorInputError(msg)
            edge = self._edges[child] = _Edge(parent, static)
        if static:
            edge.times, edge.poses = deque([0.0]), deque([pose])
            return
        if edge.times and time < edge.times[-1]:
            i = bisect.bisect_left(list(edge.times), time)
            if i < len(edge.times) and edge.times[i] == time:
                edge.poses[i] = pose
                return
            edge.times.insert(i, time)
            edge.poses.insert(i, pose)
        elif edge.times and time == edge.times[-1]:
            edge.poses[-1] = pose
            return
        else:
            edge.times.append(time)
            edge.poses.append(pose)
        while len(edge.times) > self.history:
            edge.times.popleft()
            edge.poses.popleft()

    def _loops(self, parent: str, child: str) -> bool:
        frame: str | None = parent
        for _ in range(len(self._edges) + 1):
            if frame == child:
                return True
            edge = self._edges.get(frame) if frame is not None else None
            if edge is None:
                return False
            frame = edge.parent
        return True

    def newest(self, child: str) -> float | None:
        """Time of the newest transform into `child` (None if unknown or static)."""
        edge = self._edges.get(child.strip("/"))
        if edge is None or edge.static or not edge.times:
            return None
        return edge.times[-1]

    def _edge_at(self, child: str, edge: _Edge, time: float, tolerance: float) -> np.ndarray:
        if edge.static:
            return edge.poses[0]
        times = edge.times
        i = bisect.bisect_left(list(times), time)
        if i < len(times) and times[i] == time:
            return edge.poses[i]
        if 0 < i < len(times):
            w = (time - times[i - 1]) / (times[i] - times[i - 1])
            return _interpolate(edge.poses[i - 1], edge.poses[i], w)
        if i == len(times) and time - times[-1] <= tolerance:
            return edge.poses[-1]
        if i == 0 and times[0] - time <= tolerance:
            return edge.poses[0]
        span = f"{times[0]:.3f}..{times[-1]:.3f}"
        msg = f"TF gap: {edge.parent} -> {child} known for {span} s, wanted at {time:.3f}"
        raise TfGapError(msg)

    def _ancestors(self, frame: str) -> list[str]:
        """`frame` and its parents up to the root (no transform evaluated)."""
        chain = [frame]
        for _ in range(self.max_frames):
            edge = self._edges.get(chain[-1])
            if edge is None:
                break
            chain.append(edge.parent)
        return chain

    def _up_to(self, chain: list[str], top: str, time: float, tolerance: float) -> np.ndarray:
        """top-from-chain[0]: the edges of `chain` below `top` only, each at `time`."""
        pose = np.eye(4)
        for frame in chain[: chain.index(top)]:
            pose = self._edge_at(frame, self._edges[frame], time, tolerance) @ pose
        return pose

    def lookup(self, target: str, source: str, time: float, tolerance: float = 0.0) -> np.ndarray:
        """target-from-source at `time` (maps points in `source` into `target`), through their
        lowest common ancestor; transforms up to `tolerance` seconds outside an edge's history
        stand for it."""
        target, source = target.strip("/"), source.strip("/")
        if target == source:
            return np.eye(4)
        up_s, up_t = self._ancestors(source), self._ancestors(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            msg = (
                f"TF gap: no transform chain from {source!r} to {target!r} "
                f"({source} reaches {up_s[-1]!r}, {target} reaches {up_t[-1]!r})"
            )
            raise TfGapError(msg)
        common_from_source = self._up_to(up_s, common, time, tolerance)
        common_from_target = self._up_to(up_t, common, time, tolerance)
        result: np.ndarray = np.linalg.inv(common_from_target) @ common_from_source
        return result
