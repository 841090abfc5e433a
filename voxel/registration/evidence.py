"""How well one pose explains both maps: inliers, RMS residual, overlap and contradictions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from voxel import keys as vk
from voxel.registration.transform import apply

#: A wall point of one map contradicts the other map where that map has observed the column
#: (free space or floor seen) and has no wall within this distance. Real maps of one place
#: disagree next to walls (rays grazing thin walls, glass, doors that moved); that is not a
#: contradiction.
CLEAR_M = 0.5


@dataclass(frozen=True, eq=False)
class Side:
    """One map as evidence sees it: KD-trees over all its occupied points and over its walls, and
    the xy columns (sorted packed keys of `cell`-sized cells) it has observed."""

    tree: cKDTree
    walls: cKDTree
    observed: np.ndarray
    cell: float

    @classmethod
    def build(cls, tree: cKDTree, walls: np.ndarray, observed_xy: np.ndarray, cell: float) -> Side:
        """A side from a tree over all occupied points, wall points (N, 3) and the centres (M, 2)
        of its observed columns."""
        return cls(tree, cKDTree(walls), np.sort(_columns(observed_xy, cell)), cell)

    def sees(self, points: np.ndarray) -> np.ndarray:
        """Mask of the points (N, 3) in columns this map has observed."""
        if self.observed.size == 0:
            return np.zeros(len(points), bool)
        packed = _columns(points[:, :2], self.cell)
        idx = np.minimum(np.searchsorted(self.observed, packed), self.observed.size - 1)
        return self.observed[idx] == packed


def _columns(xy: np.ndarray, cell: float) -> np.ndarray:
    cols = np.floor(xy / cell).astype(np.int64)
    return vk.pack(np.column_stack([cols, np.zeros(len(cols), np.int64)]))


@dataclass(frozen=True)
class Evidence:
    """Agreement of B's sampled wall points, moved into A's frame, with A (and of A's with B).

    Walls decide the planar pose (floors match floors anywhere); `support`, the inliers among all
    sampled points (floors and ceilings included), decides between poses that differ only in z.
    """

    samples: int  # B wall points evaluated
    inliers: int  # of them, with an A point within the inlier distance
    rmse: float  # RMS distance of the inliers, metres
    overlapping: int  # of them, in columns A has observed (or inliers)
    conflicts: int  # of them, where A has observed and has no wall within CLEAR_M
    conflict_ratio: float  # the larger share of conflicts of B in A and of A in B
    support: int  # inliers among all sampled B points

    @property
    def overlap(self) -> float:
        """Share of B's points that fall where A has observed."""
        return self.overlapping / self.samples if self.samples else 0.0

    @property
    def inlier_ratio(self) -> float:
        """Share of the overlapping points that match A's geometry."""
        return self.inliers / self.overlapping if self.overlapping else 0.0

    @property
    def score(self) -> float:
        """Confirmed minus unconfirmed points where A has observed, contradictions counted twice:
        what hypotheses are ranked by.

        A pose that piles more of B onto A does not win by overlap alone: every overlapping
        point that A does not confirm costs as much as a confirmed one earns, and one A
        contradicts (its wall in A's open space) costs double.
        """
        return float(self.inliers - (self.overlapping - self.inliers) - self.conflicts)


def _one_way(moved: np.ndarray, wall: np.ndarray, target: Side,
             inlier_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distances, inlier, overlap and conflict masks of points moved into `target`'s frame
    (`wall`: which of them are wall points; only those can contradict)."""
    d, _ = target.tree.query(moved, distance_upper_bound=CLEAR_M)
    inlier = d <= inlier_m
    seen = target.sees(moved)
    conflict = np.zeros(len(moved), bool)
    check = wall & seen
    if check.any():
        dw, _ = target.walls.query(moved[check], distance_upper_bound=CLEAR_M)
        conflict[check] = ~np.isfinite(dw)
    return d, inlier, seen | inlier, conflict


def evaluate(t: np.ndarray, a: Side, b_sample: np.ndarray, b_wall: np.ndarray, b: Side,
             a_sample: np.ndarray, a_wall: np.ndarray, inlier_m: float) -> Evidence:
    """Evidence for the transform `t` (B into A) on samples of both maps (with wall masks)."""
    d, inlier, overlapping, conflict = _one_way(apply(t, b_sample), b_wall, a, inlier_m)
    _, _, ov_back, conflict_back = _one_way(apply(np.linalg.inv(t), a_sample), a_wall, b, inlier_m)
    n_over = int((overlapping & b_wall).sum())
    ratio = max(int(conflict.sum()) / max(n_over, 1),
                int(conflict_back.sum()) / max(int((ov_back & a_wall).sum()), 1))
    wall_in = inlier & b_wall
    rmse = float(np.sqrt(np.mean(d[wall_in] ** 2))) if wall_in.any() else float("inf")
    return Evidence(samples=int(b_wall.sum()), inliers=int(wall_in.sum()), rmse=rmse, overlapping=n_over,
                    conflicts=int(conflict.sum()), conflict_ratio=float(ratio), support=int(inlier.sum()))
