"""Colony map: aligned peers' occupied voxels near an agent, in its own frame, as a scan-matching
target with normals (how another agent's map corrects this one's pose)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation.drift import OffsetWalk
from voxel.localisation.scan_match import surface_normals, thin_index

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: The alignment error a colony map assumes when it is given none (x, y, yaw variances about
#: the agent's origin): live alignment is within ~3 cm and 0.2 degrees in the sim office
#: (docs/BENCHMARKS.md), so 3 cm and 0.3 degrees standard deviation. The daemon gives each cut
#: its alignments' own error (`frame_error`).
ALIGNMENT_VARIANCE = np.diag([0.03**2, 0.03**2, np.radians(0.3) ** 2])


@dataclass(frozen=True)
class ColonyMap:
    """Peers' occupied voxels' surface points (thinned) around `centre`, with normals and a k-d
    tree.

    `points` are in the agent's own (odometry) frame; for a 2D scanner they are the peers'
    surfaces in a band around the scan height, put onto that height. `covariance` (x, y, yaw) is
    the alignment's error, a small motion of the whole map about the agent's origin
    (`frame_error`): one error shared by every pose measured against this map.
    """

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree | None
    centre: np.ndarray  # (2,) x, y where the map was cut
    radius: float
    sources: tuple[str, ...] = ()
    covariance: np.ndarray = field(default_factory=ALIGNMENT_VARIANCE.copy)
    #: Identifies the alignments the cut was made with: a localiser that stopped trusting a
    #: colony map trusts it again only once this changes.
    alignment: bytes = b""
    #: True when every normal faces the free side of its surface (`orient_by_free_space`);
    #: voxels' surface points alone carry no side they were seen from, and then normals are
    #: unsigned.
    oriented: bool = False
    #: How fast the map's error may change along a path, from its peers' own drift
    #: (`PeerDrift`; the widest of its peers'); None: not known.
    walk: OffsetWalk | None = None

    def __len__(self) -> int:
        return len(self.points)

    def covers(self, xy: np.ndarray, margin: float) -> bool:
        """Whether a scan of range `radius - margin` taken at `xy` stays inside the cut."""
        return float(np.linalg.norm(np.asarray(xy)[:2] - self.centre)) <= self.radius - margin


def colony_map(
    surfaces: np.ndarray,
    *,
    planar: bool,
    height: float,
    centre: np.ndarray,
    radius: float,
    cell: float = 0.05,
    band: float = 0.2,
    k: int = 8,
    max_points: int = 50_000,
    sources: tuple[str, ...] = (),
    covariance: np.ndarray | None = None,
    alignment: bytes = b"",
    free: Callable[[np.ndarray], np.ndarray] | None = None,
    step: float = 0.1,
    walk: OffsetWalk | None = None,
    slices: np.ndarray | None = None,
) -> ColonyMap:
    """The scan-matching target of the peers' occupied voxels' surface points (N, 3: each
    voxel's mean hit position, `VoxelGrid.occupied_surface`; its centre where a grid keeps no
    surface, up to half a voxel off the real surface) already in the agent's frame.

    Keeps the points within `radius` (x-y) of `centre`; planar (a 2D scanner at `height`): those
    within `band` of the scan height, moved onto it. Thinned to `cell`, at most `max_points`
    (evenly subsampled), normals from `k` neighbours; corners and clutter (flatness <= 0.7) are
    dropped, as in the agent's own local map. With `free` (points (M, 3) in the agent's frame ->
    bool mask, "a peer knows this is free space"), normals are oriented to the free side of their
    surface, probed `step` metres along each normal (`orient_by_free_space`). `walk`: the
    peers' drift (`ColonyMap.walk`).
    """
    pts = np.asarray(surfaces, np.float64).reshape(-1, 3)
    c = np.asarray(centre, np.float64).reshape(-1)[:2]
    if radius <= 0 or cell <= 0 or band <= 0 or k < 3 or c.shape != (2,):
        msg = (
            "colony map: expected radius, cell, band > 0, k >= 3 and an (x, y) centre, found "
            f"{radius}, {cell}, {band}, {k}, {c}"
        )
        raise LocalisationError(msg)
    keep = np.sum((pts[:, :2] - c) ** 2, axis=1) <= radius * radius
    if planar:
        keep &= np.abs(pts[:, 2] - height) <= band
    sliced = np.ones(len(pts), bool) if slices is None else np.asarray(slices, bool).reshape(-1)
    if len(sliced) != len(pts):
        msg = (
            f"colony map: expected a slice flag per surface point ({len(pts)}), found {len(sliced)}"
        )
        raise LocalisationError(msg)
    pts, sliced = pts[keep], sliced[keep]
    if planar:
        pts = pts.copy()
        pts[:, 2] = height
    first = thin_index(pts, cell)
    pts, sliced = pts[first], sliced[first]
    if len(pts) > max_points:
        every = np.linspace(0, len(pts) - 1, max_points).astype(np.int64)
        pts, sliced = pts[every], sliced[every]
    cov = ALIGNMENT_VARIANCE.copy() if covariance is None else np.asarray(covariance, np.float64)
    if len(pts) < k:
        return ColonyMap(
            np.zeros((0, 3)), np.zeros((0, 3)), None, c, radius, sources, cov, alignment, walk=walk
        )
    from scipy.spatial import cKDTree  # loads on first use, not at start-up

    tree = cKDTree(pts)
    normals, flat = surface_normals(pts, pts, tree, k, planar)
    if not planar:
        normals, flat = vertical_traces(pts, tree, k, normals, flat, sliced)
    good = flat > 0.7
    pts, normals = pts[good], normals[good]
    oriented = False
    if free is not None and len(pts):
        sided = orient_by_free_space(pts, normals, free, step)
        if sided is not None:
            pts, normals = sided
            oriented = True
    tree_kept = cKDTree(pts) if len(pts) >= k else None
    return ColonyMap(pts, normals, tree_kept, c, radius, sources, cov, alignment, oriented, walk)


def vertical_traces(
    points: np.ndarray,
    tree: cKDTree,
    k: int,
    normals: np.ndarray,
    flat: np.ndarray,
    sliced: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a 3D cut where a neighbourhood has no height: a 2D scanner's map holds one
    slice of each wall, a row of voxels whose plane fit is degenerate (its smallest spread is
    height, zero: the normal points up and the flatness test passes on rounding). Such a row is
    taken as the trace of a vertical surface, as a 2D scanner's own map is: its normal and
    flatness are those of the line fitted in x-y (corners of the slice are dropped, as in 2D).

    Only points of a slice (`sliced`, (N,) bool; None: every point) are taken so. Elsewhere a
    neighbourhood without height is a patch of a horizontal surface (a 3D sensor's floor, seen
    at a grazing angle in strips a few voxels wide, passes the line's flatness test as well):
    it gets flatness 0 (dropped from the cut), not a line's normal, which would put a wall where
    there is floor."""
    _, idx = tree.query(points, k=min(k, len(points)))
    nb = points[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / nb.shape[1]
    layer = cov[:, 2, 2] < 0.01 * (np.trace(cov, axis1=1, axis2=2) + 1e-12)
    if not np.any(layer):
        return normals, flat
    out_n, out_f = normals.copy(), flat.copy()
    if sliced is not None:
        out_f[layer & ~np.asarray(sliced, bool)] = 0.0
        layer &= np.asarray(sliced, bool)
    values, vectors = np.linalg.eigh(cov[layer][:, :2, :2])
    out_n[layer] = 0.0
    out_n[layer, :2] = vectors[:, :, 0]
    out_f[layer] = np.clip(1.0 - values[:, 0] / (values[:, 1] + 1e-12), 0.0, 1.0)
    return out_n, out_f


#: Below this share of surface points with a free side, a cut keeps its normals unsigned.
MIN_SIDED = 0.5


def orient_by_free_space(
    points: np.ndarray,
    normals: np.ndarray,
    free: Callable[[np.ndarray], np.ndarray],
    step: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Points and normals facing the free side of their surface, or None when fewer than
    `MIN_SIDED` of them have one.

    Probes `step` along each normal both ways. Free on one side: the normal faces it. Free on
    both (a wall one voxel thick, seen from both sides): two faces, a quarter step either way,
    each facing its side. Free on neither (inside a thick wall, or seen by no one): dropped. A
    scan of a wall's far face then no longer matches its near face in a peer's map.
    """
    ahead = np.asarray(free(points + normals * step), bool)
    behind = np.asarray(free(points - normals * step), bool)
    if np.count_nonzero(ahead | behind) < MIN_SIDED * len(points):
        return None
    one = ahead ^ behind
    sign = np.where(ahead[one], 1.0, -1.0)[:, None]
    both = ahead & behind
    n_both = normals[both]
    q = 0.25 * step
    pts = np.concatenate([points[one], points[both] + n_both * q, points[both] - n_both * q])
    nrm = np.concatenate([normals[one] * sign, n_both, -n_both])
    return pts, nrm
