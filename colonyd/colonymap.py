"""Colony map for localisation: the aligned peers' replicas near this agent, in its own frame."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.layers import Layer, Layers
from voxel.localisation import frame_error
from voxel.localisation.colony_map import ColonyMap, colony_map
from voxel.localisation.drift import OffsetWalk, widest
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
    errors: dict[str, PeerError]


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


def alignment_error(frame: ColonyFrame, own: str, origin: str) -> np.ndarray:
    """The error (x, y, yaw covariance about our origin, in our frame) of the transform taking
    `origin`'s frame into ours."""
    back = np.linalg.inv(frame.transforms[own])
    return frame_error.moved(frame.covariance(own) + frame.covariance(origin), back)


def peer_map_error(pose: np.ndarray, to_own: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The error (x, y, yaw covariance about our origin, in our frame) that a peer's pose
    covariance `pose` (x, y, yaw, in its frame) gives its map near `centre` (x, y, our frame);
    `to_own` takes its frame into ours.

    A pose error (dx, dy, dyaw) at the place a map was made moves that place's surfaces by
    (dx, dy) and turns them by dyaw about it: a motion about `centre` (put into the peer's frame),
    then re-expressed about the peer's origin (`frame_error.about`) and moved into our frame
    (`frame_error.moved`). The peer's *current* covariance stands in for the error its map had
    where it was made, which it does not report: a proxy, right when the peer mapped our
    surroundings recently or has been as (un)sure of itself since, too small when it was lost
    there and has closed a loop elsewhere since, too large when it mapped here sure of itself
    and is lost now."""
    back = np.linalg.inv(to_own)
    c = back[:2, :2] @ np.asarray(centre, np.float64)[:2] + back[:2, 3]
    return frame_error.moved(frame_error.about(pose, c), to_own)


@dataclass(frozen=True)
class PeerError:
    """One aligned peer's share of a cut's error: its alignment's and its own pose's (both
    x, y, yaw covariances about our origin, in our frame) and the pose covariance it reported
    (x, y, yaw, its frame; None when it sent no Pose)."""

    alignment: np.ndarray
    pose: np.ndarray
    reported: np.ndarray | None

    @property
    def total(self) -> np.ndarray:
        out: np.ndarray = self.alignment + self.pose
        return out


def peer_errors(
    frame: ColonyFrame,
    own: str,
    peers: list[tuple[Layer, np.ndarray]],
    poses: Mapping[str, np.ndarray],
    centre: np.ndarray,
) -> dict[str, PeerError]:
    """Each aligned peer's error near `centre` (x, y, our frame): its alignment's plus what its
    reported pose covariance (`poses`, origin -> x, y, yaw in its frame) gives its map there."""
    out = {}
    for layer, to_own in peers:
        reported = poses.get(layer.origin)
        pose = np.zeros((3, 3)) if reported is None else peer_map_error(reported, to_own, centre)
        out[layer.origin] = PeerError(alignment_error(frame, own, layer.origin), pose, reported)
    return out


def cut_error(errors: Mapping[str, PeerError]) -> np.ndarray:
    """The error of a cut (x, y, yaw covariance about our origin, in our frame) from its peers':
    the largest (by position variance) of each peer's alignment plus pose error, floored.

    A cut merges every peer's surfaces, and one match against it is pulled by each peer's error
    in proportion to the surfaces it holds in view; the peers' errors are independent, so the
    match's is at most the worst peer's (a peer alone in view), never their sum. The largest is
    the honest bound without knowing which peer's surfaces a scan will see. Made positive
    semi-definite (`frame_error.positive`): the peers' covariances are checked only to a
    tolerance, and the estimator refuses one that is not a covariance."""
    totals = [e.total for e in errors.values()]
    worst: np.ndarray = max(totals, key=lambda c: float(np.trace(c[:2, :2])))
    return frame_error.floored(frame_error.positive(worst))


def key_of(peers: list[tuple[Layer, np.ndarray]]) -> Key:
    """What a cut depends on: each peer's (origin, epoch, seq) and alignment."""
    return tuple(
        (layer.origin, layer.epoch, layer.seq, np.round(m, 4).tobytes()) for layer, m in peers
    )


#: A peer map whose surfaces' heights span at most this many of its voxels is one slice of the
#: world (a 2D scanner's): in a 3D cut its rows are traces of walls (`vertical_traces`).
SLICE_VOXELS = 2.0

#: The share of a peer map's surfaces, at each end of their heights, left out of its span
#: (at least one each when it holds two or more): a 2D scanner's map stays a slice with a few
#: off-height hits (a tilt, a glass's reflection).
SLICE_TRIM = 0.01

#: Fewer surfaces than this and a peer map is not called a slice: a 3D sensor's map is one flat
#: band early on (its first hits), and a 3D map taken for a slice would raise its band into
#: walls across every height, while a 2D map taken for 3D only lacks that extrusion until it
#: has grown (a 2D scanner's first scan holds hundreds of surfaces).
SLICE_MIN_SURFACES = 50


def is_slice(heights: np.ndarray, resolution: float) -> bool:
    """Whether surfaces at `heights` (M,) of a peer map of `resolution` are one slice: at least
    `SLICE_MIN_SURFACES` of them, spanning at most `SLICE_VOXELS` voxels once the lowest and
    highest `SLICE_TRIM` (at least one each) are left out."""
    n = len(heights)
    if n < SLICE_MIN_SURFACES:
        return False
    trim = max(1, int(SLICE_TRIM * n))
    z = np.partition(heights, (trim, n - 1 - trim))
    return float(z[n - 1 - trim] - z[trim]) <= SLICE_VOXELS * resolution


def peer_surfaces(peers: list[tuple[Layer, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Surface points of the peers' occupied voxels (each voxel's mean hit position, as its
    origin sent it: `VoxelGrid.occupied_surface`), in our frame, and which of them come from a
    peer map that is one slice (`is_slice`: a 2D scanner's)."""
    parts, slices = [], []
    for layer, m in peers:
        with layer.lock:
            points = layer.grid.occupied_surface()
        flat = is_slice(points[:, 2], layer.resolution)
        parts.append(points @ m[:3, :3].T + m[:3, 3])
        slices.append(np.full(len(points), flat))
    if not parts:
        return np.zeros((0, 3)), np.zeros(0, bool)
    return np.concatenate(parts), np.concatenate(slices)


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

    def refresh(
        self,
        layers: Layers,
        frame: ColonyFrame,
        pose: np.ndarray,
        poses: Mapping[str, np.ndarray] | None = None,
        walks: Mapping[str, OffsetWalk] | None = None,
    ) -> ColonyMap | None:
        """The cut for a robot at sensor pose `pose` (4x4, own frame); None without aligned
        peers. Its covariance (`cut_error`) holds the alignments' errors and the peers' own pose
        covariances (`poses`, origin -> x, y, yaw in its frame, as their Pose messages last said),
        updated on every call even when the surfaces are kept, as is its walk (the fastest of
        its peers' drifts, `walks`: origin -> `PeerDrift.walk`; the localiser walks by it when
        `ScanParams.colony_peer_walk`)."""
        started = time.perf_counter()
        peers = aligned_peers(layers, frame, self.own)
        key = key_of(peers)
        if not key:
            self.last = None
            return None
        walk = widest([w for o, w in (walks or {}).items() if o in {k[0] for k in key}])
        xy = pose[:2, 3]
        last = self.last
        if last is not None and last.map.covers(xy, self.radius - MARGIN_M):
            same = [(o, e, m) for o, e, _, m in last.key] == [(o, e, m) for o, e, _, m in key]
            if last.key == key or (same and time.time() - last.time < self.grown_s):
                errors = peer_errors(frame, self.own, peers, poses or {}, last.map.centre)
                covariance = cut_error(errors)
                if not np.array_equal(covariance, last.map.covariance) or walk != last.map.walk:
                    kept = replace(last.map, covariance=covariance, walk=walk)  # same surfaces
                    last = self.last = replace(last, map=kept, errors=errors)
                return last.map
        errors = peer_errors(frame, self.own, peers, poses or {}, xy)
        surfaces, slices = peer_surfaces(peers)
        cut = colony_map(
            surfaces,
            cell=0.05 if self.planar else 0.1,  # a 3D cut: one point per voxel, at most 20,000
            max_points=50_000 if self.planar else 20_000,
            planar=self.planar,
            height=self.height,
            centre=xy,
            radius=self.radius,
            sources=tuple(k[0] for k in key),
            covariance=cut_error(errors),
            alignment=b"".join(k[0].encode() + k[3] for k in key),
            free=partial(free_in_peers, peers),
            step=max(layer.resolution for layer, _ in peers),
            walk=walk,
            slices=slices,
        )
        self.last = Build(cut, key, time.perf_counter() - started, time.time(), errors)
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
            "centre": np.round(last.map.centre, 4).tolist(),
            "covariance": _listed(last.map.covariance),
            "walk": None
            if last.map.walk is None
            else {"trans": last.map.walk.trans, "yaw": last.map.walk.yaw},
            "peers": {
                origin: {
                    "alignment_covariance": _listed(e.alignment),
                    "pose_covariance": _listed(e.pose),
                    "reported_pose_covariance": None if e.reported is None else _listed(e.reported),
                }
                for origin, e in last.errors.items()
            },
        }


def _listed(cov: np.ndarray) -> list[list[float]]:
    out: list[list[float]] = np.round(cov, 9).tolist()
    return out
