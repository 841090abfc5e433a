"""Free-space summaries: coarse cells that stand in for free voxels left out of a delta."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.errors import OversizedError
from protocol.limits import DEFAULT_LIMITS
from voxel.delta import Delta
from voxel.keys import pack

#: Coarsest summary level accepted: a cell is at most 2**MAX_LEVEL voxels on a side.
MAX_LEVEL = 6


@dataclass
class FreeSummary:
    """Free space at a coarser level: cell `keys` (voxel key >> level) with one log-odds each.

    A cell says "the voxels of this cube that this delta changed to free now have about this
    log-odds" — an approximation for budget-limited links. Receivers may expand it (`expand`)
    into voxels, skip it, or keep it apart; it never marks a voxel occupied.
    """

    resolution: float
    level: int
    from_version: int
    to_version: int
    keys: np.ndarray  # (M, 3) int64 cell keys
    logodds: np.ndarray  # (M,) float32, all < 0
    time: float  # latest observation time of the summarised voxels, seconds

    def __post_init__(self) -> None:
        self.keys = np.asarray(self.keys, dtype=np.int64).reshape(-1, 3)
        self.logodds = np.asarray(self.logodds, dtype=np.float32).reshape(-1)
        if self.logodds.shape[0] != self.keys.shape[0]:
            msg = (
                f"summary needs one log-odds per cell: {self.keys.shape[0]} cells, found "
                f"{self.logodds.shape[0]}"
            )
            raise ValueError(msg)
        if not 1 <= self.level <= MAX_LEVEL:
            msg = f"summary level must be in [1, {MAX_LEVEL}], found {self.level}"
            raise ValueError(msg)

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    @property
    def expanded_count(self) -> int:
        """Number of voxels `expand` would produce before exclusions."""
        return len(self) << (3 * self.level)  # 8**level cells each

    def expand(self, exclude: np.ndarray | None = None, max_voxels: int | None = None) -> Delta:
        """The voxels of every cell as a Delta (minus keys in `exclude` (K, 3)), one value per cell.

        Refuses (OversizedError) to produce more than `max_voxels` voxels (default: the
        `max_expanded_voxels` of the default decoder limits).
        """
        limit = DEFAULT_LIMITS.max_expanded_voxels if max_voxels is None else max_voxels
        if self.expanded_count > limit:
            msg = (
                f"summary expands to at most {limit} voxels, "
                f"found {len(self)} cells of {8**self.level} voxels"
            )
            raise OversizedError(msg)
        edge = 1 << self.level
        g = np.arange(edge, dtype=np.int64)
        child = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        keys = ((self.keys << self.level)[:, None, :] + child[None, :, :]).reshape(-1, 3)
        values = np.repeat(self.logodds, child.shape[0])
        if exclude is not None and len(exclude):
            keep = ~np.isin(pack(keys), pack(np.asarray(exclude, dtype=np.int64).reshape(-1, 3)))
            keys, values = keys[keep], values[keep]
        return Delta(
            resolution=self.resolution,
            from_version=self.from_version,
            to_version=self.to_version,
            keys=keys,
            logodds=values,
            last_time=np.full(keys.shape[0], self.time),
            time=self.time,
        )
