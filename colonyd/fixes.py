"""Pose fixes: the error a fixed camera claims for a robot it saw, and the fix in its frame."""

from __future__ import annotations

import math

import numpy as np

from colonyd.alignment import ColonyFrame
from voxel.localisation import frame_error, se2

#: Standard deviation of a fix's yaw (rad) the daemon claims at any range.
YAW_SD = math.radians(4.0)
#: An alternative measured offline (`cctv_offline --fix-model new`, not the daemon's): a yaw
#: standard deviation per metre of range, as a board's solved normal gets worse the smaller it
#: looks (sim office, cctv-1, 0.24 m boards: RMS 2 degrees at 4.7-5.6 m, 5-7 at 6.5-8 m, up to
#: 11; docs/BENCHMARKS.md "The CCTV's fixes offline").
YAW_PER_M = math.radians(1.0)


def fix_covariance(range_m: float, yaw_per_m: float | None = None) -> np.ndarray:
    """The covariance (6x6, x y z roll pitch yaw) a CCTV sends with a robot's body pose seen
    `range_m` m away: 1 cm per metre of range in x and y (the board's known height fixes the
    range) plus 1 cm; in yaw `YAW_SD`, or `yaw_per_m` per metre of range when given."""
    sd = 0.01 * range_m + 0.01
    yaw = YAW_SD if yaw_per_m is None else yaw_per_m * range_m
    return np.diag([sd**2, sd**2, 0.05**2, 0.05**2, 0.05**2, yaw**2])


def sightings_covariance(rmse: float, spread: float, positions: np.ndarray) -> np.ndarray:
    """Error of a frame fitted to sightings (6x6, x y z roll pitch yaw, about our origin): the
    fit's residual in x and y, about the sightings' centroid, and a yaw of that residual over
    their spread (a lever of `spread` metres)."""
    planar = np.diag([rmse**2, rmse**2, (rmse / max(spread, 0.1)) ** 2])
    cov = np.zeros((6, 6))
    cov[np.ix_(frame_error.PLANAR, frame_error.PLANAR)] = frame_error.floored(
        frame_error.about(planar, positions[:, :2].mean(axis=0))
    )
    return cov


def fix_in_own_frame(
    frame: ColonyFrame,
    own: str,
    origin: str,
    body: np.ndarray,
    covariance: np.ndarray,
    count: int = 1,
    bias: float = 0.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A fix from `origin` (the robot's body pose `body`, 4x4 in origin's frame, with its 6x6
    `covariance`) in `own`'s frame through the colony frame: the body pose (x, y, yaw) and its
    covariance (3x3: the fix's, rotated, plus `count` times the alignments' error at the robot's
    position, `frame_error.at`). None when either frame is not aligned.

    Every fix through one alignment shares its error, and the daemon counts it in each (count 1).
    Measured alternatives (`cctv_offline --fix-model new|shared`, `FixCounter`): the k-th fix
    through one alignment carrying `count` = k times that error (n fixes tell the filter about
    it H_n = 1 + 1/2 + ... + 1/n times what one does, 3.4 for 17, not n times), or k(k+1)
    times (at most once in all); `bias` (m): a systematic error of the camera's positions,
    shared by its fixes like the alignment's error and counted with it."""
    mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
    if mine is None or theirs is None:
        return None
    to_own = np.linalg.inv(mine) @ theirs
    seen = to_own @ np.asarray(body, np.float64)
    # a peer's covariance is checked to a tolerance of its largest variance: made positive
    cov = frame_error.positive(frame_error.planar(np.asarray(covariance, np.float64)))
    rot = np.eye(3)
    rot[:2, :2] = to_own[:2, :2]
    alignment = frame_error.moved(
        frame.covariance(own) + frame.covariance(origin), np.linalg.inv(mine)
    )
    shared = frame_error.at(alignment, seen[:2, 3]) + np.diag([bias**2, bias**2, 0.0])
    out = rot @ cov @ rot.T + max(1, count) * shared
    return se2.from_matrix(seen), out


class FixCounter:
    """Fixes fused so far through each sender's current alignment (its transform into ours,
    rounded): the next one's `count` for `fix_in_own_frame` (`cctv_offline --fix-model new`).
    A changed alignment starts again."""

    def __init__(self) -> None:
        self._counts: dict[str, tuple[bytes, int]] = {}

    def key(self, frame: ColonyFrame, own: str, origin: str) -> bytes | None:
        """What the fixes from `origin` go through: the transform of its frame into ours."""
        mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
        if mine is None or theirs is None:
            return None
        return bytes(np.round(np.linalg.inv(mine) @ theirs, 4).tobytes())

    def next(self, origin: str, key: bytes) -> int:
        """The count of the next fix from `origin` through the alignment `key`."""
        kept = self._counts.get(origin)
        return 1 if kept is None or kept[0] != key else kept[1] + 1

    def fused(self, origin: str, key: bytes) -> None:
        """A fix from `origin` through `key` was fused."""
        self._counts[origin] = (key, self.next(origin, key))
