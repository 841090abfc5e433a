"""How well one pose explains both maps: inliers, RMS residual, overlap and contradictions."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from voxel import keys as vk
from voxel.registration.transform import apply

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

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
        from scipy.spatial import cKDTree  # scipy.spatial loads on first use, not at start-up

        return cls(tree, cKDTree(walls), np.sort(_columns(observed_xy, cell)), cell)

    def sees(self, points: np.ndarray) -> np.ndarray:
        """Mask of the points (N, 3) in columns this map has observed."""
        if self.observed.size == 0:
            return np.zeros(len(points), bool)
        packed = _columns(points[:, :2], self.cell)
        idx = np.minimum(np.searchsorted(self.observed, packed), self.observed.size - 1)
        seen: np.ndarray = self.observed[idx] == packed
        return seen


def _columns(xy: np.ndarray, cell: float) -> np.ndarray:
    cols = np.floor(xy / cell).astype(np.int64)
    return vk.pack(np.column_stack([cols, np.zeros(len(cols), np.int64)]))


@dataclass(frozen=True)
class Evidence:
    """Agreement of the two maps under one pose, counted both ways: B's sampled wall points moved
    into A's frame against A, and A's moved into B's frame against B.

    Walls decide the planar pose (floors match floors anywhere); `support`, the inliers among all
    sampled B points (floors and ceilings included), decides between poses that differ only in z.
    Both directions are pooled: a small map dropped into a big one agrees one way (its few
    points all land near walls) and is contradicted the other (the big map's walls cross its
    open rooms).
    """

    samples: int  # B wall points evaluated
    inliers: int  # of them, with an A point within the inlier distance
    rmse: float  # RMS distance of those inliers, metres
    overlapping: int  # of them, in columns A has observed (or inliers)
    conflicts: int  # of them, where A has observed and has no wall within CLEAR_M
    back_inliers: int  # the same for A's wall points in B
    back_overlapping: int
    back_conflicts: int
    support: int  # inliers among all sampled B points
    support_overlapping: int  # all sampled B points where A has observed (or inliers)
    conflict_extent: float = 0.0  # largest connected patch of contradicted walls (either way), m

    @property
    def overlap(self) -> float:
        """Share of B's wall points that fall where A has observed."""
        return self.overlapping / self.samples if self.samples else 0.0

    @property
    def inlier_ratio(self) -> float:
        """Share of the overlapping wall points, both ways, that the other map confirms."""
        over = self.overlapping + self.back_overlapping
        return (self.inliers + self.back_inliers) / over if over else 0.0

    @property
    def conflict_ratio(self) -> float:
        """Share of the overlapping wall points, both ways, that the other map contradicts."""
        over = self.overlapping + self.back_overlapping
        return (self.conflicts + self.back_conflicts) / over if over else 0.0

    @property
    def support_ratio(self) -> float:
        """Share of all overlapping B points (floors and ceilings included) that A confirms: low
        when the walls agree but the floors do not (a height error the pose does not model)."""
        return self.support / self.support_overlapping if self.support_overlapping else 0.0

    @property
    def worst_inlier_ratio(self) -> float:
        """The lower of the two directions' confirmed shares."""
        return min(
            self.inliers / max(self.overlapping, 1),
            self.back_inliers / max(self.back_overlapping, 1),
        )

    @property
    def worst_conflict_ratio(self) -> float:
        """The higher of the two directions' contradicted shares."""
        return max(
            self.conflicts / max(self.overlapping, 1),
            self.back_conflicts / max(self.back_overlapping, 1),
        )

    @property
    def worst_near_miss_ratio(self) -> float:
        """The higher of the two directions' shares of near misses: overlapping wall points that
        the other map neither confirms nor contradicts (a wall of it within CLEAR_M, not within
        the inlier distance). A right pose puts walls on walls or where the other map saw none;
        a pose slid along repeated structure puts many next to them."""

        def share(inl: int, over: int, conf: int) -> float:
            return (over - inl - conf) / over if over else 0.0

        return max(
            share(self.inliers, self.overlapping, self.conflicts),
            share(self.back_inliers, self.back_overlapping, self.back_conflicts),
        )

    @property
    def agreement(self) -> float:
        """Confirmed minus contradicted share, in [0, 1]."""
        return max(0.0, self.inlier_ratio - self.conflict_ratio)

    @property
    def score(self) -> float:
        """What hypotheses are ranked by: confirmed points (both ways) times agreement to the
        fourth power.

        A pose that piles more of B onto A does not win by overlap alone: twice the confirmed
        points cannot make up for agreement falling from 100 % to 84 %, so a repeated corridor
        slid by one office, or a building turned round, loses to the pose where everything
        that can be checked agrees.
        """
        return float((self.inliers + self.back_inliers) * self.agreement**4)


def _one_way(
    moved: np.ndarray, wall: np.ndarray, target: Side, inlier_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distances, inlier, overlap and conflict masks of points moved into `target`'s frame
    (`wall`: which of them are wall points; only those can contradict). Distances beyond the
    inlier distance are inf (only the inliers' are used): the look-up stops there."""
    reach = min(CLEAR_M, inlier_m * (1.0 + 1e-9) + 1e-9)  # every d <= inlier_m found
    d, _ = target.tree.query(moved, distance_upper_bound=reach)
    inlier = d <= inlier_m
    seen = target.sees(moved)
    conflict = np.zeros(len(moved), bool)
    check = wall & seen
    if check.any():
        dw, _ = target.walls.query(moved[check], distance_upper_bound=CLEAR_M)
        conflict[check] = ~np.isfinite(dw)
    return d, inlier, seen | inlier, conflict


def evaluate(
    t: np.ndarray,
    a: Side,
    b_sample: np.ndarray,
    b_wall: np.ndarray,
    b: Side,
    a_sample: np.ndarray,
    a_wall: np.ndarray,
    inlier_m: float,
) -> Evidence:
    """Evidence for the transform `t` (B into A) on samples of both maps (with wall masks)."""
    d, inlier, overlapping, conflict = _one_way(apply(t, b_sample), b_wall, a, inlier_m)
    _, inlier_back, ov_back, conflict_back = _one_way(
        apply(np.linalg.inv(t), a_sample), a_wall, b, inlier_m
    )
    wall_in = inlier & b_wall
    rmse = float(np.sqrt(np.mean(d[wall_in] ** 2))) if wall_in.any() else float("inf")
    return Evidence(
        samples=int(b_wall.sum()),
        inliers=int(wall_in.sum()),
        rmse=rmse,
        overlapping=int((overlapping & b_wall).sum()),
        conflicts=int(conflict.sum()),
        back_inliers=int((inlier_back & a_wall).sum()),
        back_overlapping=int((ov_back & a_wall).sum()),
        back_conflicts=int(conflict_back.sum()),
        support=int(inlier.sum()),
        support_overlapping=int(overlapping.sum()),
        conflict_extent=max(_extent(b_sample[conflict]), _extent(a_sample[conflict_back])),
    )


def _extent(points: np.ndarray, cell: float = 0.2) -> float:
    """Longest horizontal side (m) of the largest 8-connected patch of `points` on a `cell` grid
    (one empty cell bridged): a whole wall in the other map's open space, not scattered specks
    (rays through glass or doors)."""
    if len(points) < 2:
        return 0.0
    import cv2  # loads on first use (the yaw search has loaded it), not at start-up

    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    if int(ij.max()) > 4096:
        return float("inf")
    img = np.zeros(tuple(ij.max(axis=0) + 1), np.uint8)
    img[ij[:, 0], ij[:, 1]] = 1
    grown = cv2.dilate(img, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)))
    _, labels = cv2.connectedComponents(grown, connectivity=8, ltype=cv2.CV_32S)
    # number the patches in raster order of their first cell, so that of equally big patches
    # the first is chosen whatever order the labelling gave them
    found, first = np.unique(labels.ravel(), return_index=True)
    patch = found > 0
    rank = np.zeros(int(found[-1]) + 1, np.int64)
    rank[found[patch][np.argsort(first[patch])]] = np.arange(1, int(patch.sum()) + 1)
    lab = rank[labels[ij[:, 0], ij[:, 1]]]
    sizes = np.bincount(lab)
    biggest = ij[lab == int(np.argmax(sizes[1:]) + 1)]
    return float((np.ptp(biggest, axis=0).max() + 1) * cell)
