"""Colony map for localisation: the aligned peers' replicas near this agent, in its own frame."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.layers import Layer, Layers
from voxel import keys as vk
from voxel.localisation import frame_error
from voxel.localisation.colony_map import ColonyMap, colony_map
from voxel.occupancy import FREE_STATE, OCCUPIED

#: Metres beyond the sensor's range that a cut of the colony map reaches: the robot may move this
#: far from where the cut was made before it is made again.
MARGIN_M = 2.0

#: What a cut depends on: each aligned peer's (origin, epoch, seq) and alignment (rounded).
Key = tuple[tuple[str, int, int, bytes], ...]


@dataclass(frozen=True)
class Build:
    """One cut of the colony map: what it holds, how long it took."""

    map: ColonyMap
    key: Key
    seconds: float
    time: float


def aligned_peers(layers: Layers, frame: ColonyFrame, own: str) -> list[tuple[Layer, np.ndarray]]:
    """Every peer layer aligned (through the colony frame) with ours, and the transform taking
    its frame into ours."""
    mine = frame.transforms.get(own)
    if mine is None:
        return []
    to_own = np.linalg.inv(mine)
    out = []
    for layer in layers.all():
        t = frame.transforms.get(layer.origin)
        if layer.origin != own and t is not None and layer.seq > 0:
            out.append((layer, to_own @ t))
    return out


def alignment_error(
    frame: ColonyFrame, own: str, peers: list[tuple[Layer, np.ndarray]]
) -> np.ndarray:
    """The error (x, y, yaw covariance about our origin, in our frame) of the transforms taking
    the peers' frames into ours: the largest of them (a cut merges every peer's surfaces)."""
    back = np.linalg.inv(frame.transforms[own])
    errors = [
        frame_error.moved(frame.covariance(own) + frame.covariance(layer.origin), back)
        for layer, _ in peers
    ]
    worst: np.ndarray = max(errors, key=lambda c: float(np.trace(c[:2, :2])))
    return frame_error.floored(worst)


def key_of(peers: list[tuple[Layer, np.ndarray]]) -> Key:
    """What a cut depends on: each peer's (origin, epoch, seq) and alignment."""
    return tuple(
        (layer.origin, layer.epoch, layer.seq, np.round(m, 4).tobytes()) for layer, m in peers
    )


def peer_centres(peers: list[tuple[Layer, np.ndarray]]) -> np.ndarray:
    """Occupied voxel centres of the peers' layers, in our frame."""
    parts = []
    for layer, m in peers:
        with layer.lock:
            occupied = layer.grid.occupied_keys()
        centres = vk.keys_to_centers(occupied, layer.resolution)
        parts.append(centres @ m[:3, :3].T + m[:3, 3])
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def free_in_peers(peers: list[tuple[Layer, np.ndarray]], points: np.ndarray) -> np.ndarray:
    """Whether any peer knows each point (N, 3, our frame) as free and none as occupied."""
    free = np.zeros(len(points), bool)
    occupied = np.zeros(len(points), bool)
    for layer, m in peers:
        back = np.linalg.inv(m)
        there = points @ back[:3, :3].T + back[:3, 3]
        with layer.lock:
            state = layer.grid.state(there)
        free |= state == FREE_STATE
        occupied |= state == OCCUPIED
    out: np.ndarray = free & ~occupied
    return out


class ColonyMaps:
    """Keeps one agent's cut of the colony map: made again when an alignment or the set of
    aligned peers changed, when a replica grew (at most every `grown_s` seconds), or when the
    robot moved `MARGIN_M` from where it was made (its scans would reach past the cut)."""

    def __init__(
        self,
        own: str,
        *,
        planar: bool,
        height: float,
        sensor_range: float,
        grown_s: float = 5.0,
    ) -> None:
        self.own = own
        self.grown_s = grown_s  # a cut is made again for grown replicas at most this often
        self.planar, self.height = planar, height
        self.radius = min(sensor_range, 30.0) + MARGIN_M
        self.last: Build | None = None

    def refresh(self, layers: Layers, frame: ColonyFrame, pose: np.ndarray) -> ColonyMap | None:
        """The cut for a robot at sensor pose `pose` (4x4, own frame); None without aligned
        peers."""
        started = time.perf_counter()
        peers = aligned_peers(layers, frame, self.own)
        key = key_of(peers)
        if not key:
            self.last = None
            return None
        xy = pose[:2, 3]
        last = self.last
        if last is not None and last.map.covers(xy, self.radius - MARGIN_M):
            same = [(o, e, m) for o, e, _, m in last.key] == [(o, e, m) for o, e, _, m in key]
            if last.key == key or (same and time.time() - last.time < self.grown_s):
                return last.map
        cut = colony_map(
            peer_centres(peers),
            cell=0.05 if self.planar else 0.1,  # a 3D cut: voxel centres, at most 20,000
            max_points=50_000 if self.planar else 20_000,
            planar=self.planar,
            height=self.height,
            centre=xy,
            radius=self.radius,
            sources=tuple(k[0] for k in key),
            covariance=alignment_error(frame, self.own, peers),
            alignment=b"".join(k[0].encode() + k[3] for k in key),
            free=partial(free_in_peers, peers),
            step=max(layer.resolution for layer, _ in peers),
        )
        self.last = Build(cut, key, time.perf_counter() - started, time.time())
        return cut

    def report(self) -> dict[str, object] | None:
        last = self.last
        if last is None:
            return None
        return {
            "sources": list(last.map.sources),
            "points": len(last.map),
            "build_ms": round(last.seconds * 1000, 2),
            "built": last.time,
        }
