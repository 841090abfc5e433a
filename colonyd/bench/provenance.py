"""Harness prototype: which of a robot's poses (steps) hit each voxel of its map, so a match
against that map can name the past poses that built the part it matched (`JointGraph`)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from plugins.observation import Observation
from voxel.scan import Scan, sort_beams
from voxel.sensor import SensorModel


class Provenance:
    """Per plan cell (x-y cell of the grid's `resolution`, within a height band): the steps whose
    hits fell in it, each step counted once per cell. Hits are the grid's: its own sorting of
    a scan's beams (`voxel.scan.sort_beams`, as `integrate_observation` integrates them)."""

    def __init__(self, resolution: float) -> None:
        if not resolution > 0:
            msg = f"Provenance: expected a positive resolution, found {resolution!r}"
            raise ValueError(msg)
        self.resolution = resolution
        self._parts: list[tuple[np.ndarray, np.ndarray]] = []  # (keys (K, 3), step)
        self.steps = 0
        self._plans: dict[tuple[float, float], tuple[np.ndarray, sp.csr_matrix, object]] = {}

    def add_observation(
        self, obs: Observation, pose: np.ndarray, sensor: SensorModel, step: int
    ) -> int:
        """Record step `step`'s hits of `obs` at `pose` (the pose the grid saw); how many voxels."""
        self.steps = max(self.steps, step + 1)
        self._plans.clear()
        if obs.delta is not None or len(obs) == 0:
            return 0
        # the grid's own sorting of the beams (a reliability is what a Scan needs, not the sort)
        scan = Scan.of(
            obs.points_world(pose),
            pose[:3, 3],
            time=obs.time,
            reliability=1.0,
            no_return=obs.no_return,
        )
        beams = sort_beams(scan, sensor, self.resolution, distinct=True)
        keys = np.unique(beams.hit_keys.T.astype(np.int64), axis=0)
        self._parts.append((keys, np.full(len(keys), step, np.int64)))
        return len(keys)

    def steps_near(
        self,
        points: np.ndarray,
        height: float,
        band: float = 0.2,
        reach: float | None = None,
    ) -> np.ndarray:
        """Weight per step (S,) of the plan cells nearest `points` (N, 3, this map's frame),
        within `reach` (default one cell) of a cell hit within `band` of `height`: each point
        found gives its cell's steps 1 / their number. Zeros when none is found."""
        cells, steps, tree = self._plan(height, band)
        out = np.zeros(self.steps)
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if len(cells) == 0 or len(pts) == 0:
            return out
        limit = self.resolution if reach is None else reach
        d, i = tree.query(pts[:, :2], distance_upper_bound=limit)  # type: ignore[attr-defined]
        found = np.isfinite(d)
        counts = np.bincount(i[found], minlength=len(cells)).astype(np.float64)
        out[: steps.shape[1]] = np.asarray(steps.T @ counts).reshape(-1)
        return out

    def _plan(self, height: float, band: float) -> tuple[np.ndarray, sp.csr_matrix, object]:
        """Plan cells (C, 2) hit within `band` of `height`, their steps (C, S) as a sparse
        matrix of 1 / (steps in the cell), and a tree of their centres (kept per band)."""
        from scipy.spatial import cKDTree  # loads on first use, not at start-up

        if (height, band) in self._plans:
            return self._plans[(height, band)]
        if not self._parts:
            return np.zeros((0, 2), np.int64), sp.csr_matrix((0, self.steps)), None
        keys = np.concatenate([p[0] for p in self._parts])
        step = np.concatenate([p[1] for p in self._parts])
        z = (keys[:, 2] + 0.5) * self.resolution
        keep = np.abs(z - height) <= band + 0.5 * self.resolution
        plan = keys[keep, :2]
        step = step[keep]
        cells, cell = np.unique(plan, axis=0, return_inverse=True)
        pairs = np.unique(np.column_stack([cell.reshape(-1), step]), axis=0)
        per = np.bincount(pairs[:, 0], minlength=len(cells)).astype(np.float64)
        matrix = sp.csr_matrix(
            (1.0 / per[pairs[:, 0]], (pairs[:, 0], pairs[:, 1])), shape=(len(cells), self.steps)
        )
        self._plans[(height, band)] = (cells, matrix, cKDTree((cells + 0.5) * self.resolution))
        return self._plans[(height, band)]


def quantile_steps(weights: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` steps standing for a weight per step (S,): the steps at the (k + 0.5) / count
    quantiles of the weight along the step index, each with weight 1 / count (a step may
    repeat). Empty when every weight is zero."""
    w = np.asarray(weights, np.float64).reshape(-1)
    total = float(w.sum())
    if not total > 0 or count < 1:
        return np.zeros(0, np.int64), np.zeros(0)
    cumulative = np.cumsum(w) / total
    at = (np.arange(count) + 0.5) / count
    steps = np.minimum(np.searchsorted(cumulative, at), len(w) - 1)
    return steps.astype(np.int64), np.full(count, 1.0 / count)
