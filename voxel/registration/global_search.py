"""Global search without a prior: yaw x translation correlation of 2D occupancy images, then z
votes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from voxel import keys as vk
from voxel.registration.transform import planar


@dataclass(frozen=True)
class Hypothesis:
    """A candidate transform (B into A) from the global search, with its correlation score."""

    transform: np.ndarray
    yaw: float
    score: float


def structure(points: np.ndarray, resolution: float, min_height_m: float = 1.0) -> np.ndarray:
    """Mask of the points that carry horizontal information: walls, not floors, ceilings or clutter.

    In a 3D map these are the voxels of columns (one voxel wide) holding at least `min_height_m`
    of occupied voxels: tall vertical surfaces. A planar map, or one with too little vertical
    structure, keeps every voxel. Floors match floors anywhere and clutter matches clutter, so
    neither may vote for a planar pose nor count as evidence for one.
    """
    keys = vk.points_to_keys(points, resolution)
    if int(np.ptp(keys[:, 2])) < 2:
        return np.ones(len(points), bool)
    cols = vk.pack(np.column_stack([keys[:, :2], np.zeros(len(keys), np.int64)]))
    _, inv, counts = np.unique(cols, return_inverse=True, return_counts=True)
    tall = counts[inv] * resolution >= min_height_m
    if np.count_nonzero(tall) < 0.05 * len(points):
        return np.ones(len(points), bool)
    return tall


def _member(sorted_packed: np.ndarray, packed: np.ndarray) -> np.ndarray:
    idx = np.minimum(np.searchsorted(sorted_packed, packed), sorted_packed.size - 1)
    found: np.ndarray = sorted_packed[idx] == packed
    return found


def observed_columns(known: np.ndarray, resolution: float, cell: float) -> np.ndarray:
    """xy centres (M, 2) of the search cells in which a map knows any voxel (free or occupied).

    Where a map has observed the floor or free space but has no wall, another map's wall would be
    a contradiction: `score_field` and the evidence penalise B's walls landing there. Cells are
    marked in a dense bitmap over the known extent (no sort of the millions of known voxels).
    """
    if known.size == 0:
        return np.empty((0, 2))
    scale = resolution / cell
    cx = np.floor(
        (((known >> (2 * vk.AXIS_BITS)) & vk.AXIS_MASK) - vk.AXIS_OFFSET + 0.5) * scale
    ).astype(np.int64)
    cy = np.floor((((known >> vk.AXIS_BITS) & vk.AXIS_MASK) - vk.AXIS_OFFSET + 0.5) * scale).astype(
        np.int64
    )
    x0, y0 = int(cx.min()), int(cy.min())
    shape = (int(cx.max()) - x0 + 1, int(cy.max()) - y0 + 1)
    if shape[0] * shape[1] > 50_000_000:  # absurd extent: sort instead
        uniq = np.unique(vk.pack(np.column_stack([cx, cy, np.zeros(len(cx), np.int64)])))
        return (vk.unpack(uniq)[:, :2] + 0.5) * cell
    seen = np.zeros(shape, bool)
    seen[cx - x0, cy - y0] = True
    ix, iy = np.nonzero(seen)
    return (np.column_stack([ix + x0, iy + y0]) + 0.5) * cell


def score_field(
    xy: np.ndarray,
    cell: float,
    pad: int,
    sigma: float = 1.0,
    free_xy: np.ndarray | None = None,
    free_penalty: float = 1.0,
    near: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Score image indexed [ix, iy] and the world xy of cell (0, 0)'s lower corner.

    exp(-d^2 / 2 sigma^2) within `near` cells of the points (d: cells to the nearest occupied
    cell); where the map has observed (`free_xy`) but has no wall that near, -free_penalty: a
    pose is paid for B's walls that A confirms and charged for those A contradicts, so a pose
    that piles B onto more of A does not win by overlap alone.
    """
    lo = xy.min(axis=0) - pad * cell
    cells = np.floor((xy - lo) / cell).astype(np.int64)
    shape = tuple(int(v) for v in cells.max(axis=0) + pad + 1)
    empty = np.full(shape, 255, np.uint8)
    empty[cells[:, 0], cells[:, 1]] = 0
    import cv2  # loads on first use, not at start-up

    d = cv2.distanceTransform(empty, cv2.DIST_L2, 5)
    field = np.exp(-(d * d) / (2.0 * sigma * sigma)).astype(np.float32)
    field[d > near] = 0.0
    if free_xy is not None and len(free_xy):
        fc = np.floor((free_xy - lo) / cell).astype(np.int64)
        inside = np.all((fc >= 0) & (fc < np.array(shape)), axis=1)
        fc = fc[inside]
        sel = d[fc[:, 0], fc[:, 1]] > near
        field[fc[sel, 0], fc[sel, 1]] = -free_penalty
    return field, lo


def yaw_search(
    a_xy: np.ndarray,
    b_xy: np.ndarray,
    cell: float,
    *,
    a_free_xy: np.ndarray | None = None,
    yaw_step_deg: float = 1.0,
    peaks_per_yaw: int = 3,
    keep: int = 8,
    separation_m: float = 1.0,
) -> list[Hypothesis]:
    """Best distinct planar transforms (B into A) by correlating B's rotated occupancy image with
    A's score field over every yaw step (FFT over translations); best first.

    Yaws are searched coarse to fine: every second step, then the steps next to the 2 * keep
    best coarse yaws (so a step of 1 degree costs ~210 correlations, not 360).

    Each yaw contributes its `peaks_per_yaw` best translations (at least `separation_m` apart);
    the `keep` best candidates that move B's extent by more than `separation_m` from each other
    are returned, so a second-best distinct pose is always available to judge ambiguity.
    """
    pad = 3
    field, lo = score_field(a_xy, cell, pad, free_xy=a_free_xy)
    centre = b_xy.mean(axis=0)
    q = b_xy - centre
    radius = float(np.max(np.linalg.norm(q, axis=1))) if len(q) else 0.0
    half = math.ceil(radius / cell) + 2
    side = 2 * half + 1
    from scipy import fft  # loads on first use, not at start-up

    shape = (
        fft.next_fast_len(field.shape[0] + side, real=True),
        fft.next_fast_len(field.shape[1] + side, real=True),
    )
    fa = fft.rfft2(field, s=shape)
    suppress = max(1, round(separation_m / cell))
    cand_yaw: list[float] = []
    cand_score: list[float] = []
    cand_shift: list[tuple[int, int]] = []
    image = np.zeros((side, side), np.float32)

    def correlate(yaw: float) -> None:
        c, s = math.cos(yaw), math.sin(yaw)
        rot = q @ np.array([[c, s], [-s, c]])
        cells = np.floor(rot / cell).astype(np.int64) + half
        image[:] = 0.0
        image[cells[:, 0], cells[:, 1]] = 1.0
        corr = fft.irfft2(fa * np.conj(_rfft2_padded(image, shape)), s=shape)
        for _ in range(peaks_per_yaw):
            u, v = divmod(int(np.argmax(corr)), shape[1])
            cand_yaw.append(yaw)
            cand_score.append(float(corr[u, v]))
            cand_shift.append(
                (
                    u if u < shape[0] - side else u - shape[0],
                    v if v < shape[1] - side else v - shape[1],
                )
            )
            corr[
                max(0, u - suppress) : u + suppress + 1, max(0, v - suppress) : v + suppress + 1
            ] = -np.inf

    # Coarse to fine: every other yaw step first, then the steps next to the best coarse yaws.
    step = math.radians(yaw_step_deg)
    for yaw in np.arange(0.0, 2 * math.pi - 1e-9, 2 * step):
        correlate(float(yaw))
    best_yaws = []
    for i in np.argsort(cand_score)[::-1]:
        if cand_yaw[i] not in best_yaws:
            best_yaws.append(cand_yaw[i])
            if len(best_yaws) >= 2 * keep:
                break
    for yaw in best_yaws:
        for neighbour in (yaw - step, yaw + step):
            correlate(float(neighbour % (2 * math.pi)))
    order = np.argsort(cand_score)[::-1]
    corners = _extent_corners(b_xy)
    chosen: list[Hypothesis] = []
    for i in order:
        yaw = float(cand_yaw[i])
        # cell k of B's image lands on cell k + shift of A's field:
        # p_A = R (b - centre) + lo + (half + shift) cell
        t_xy = lo + (half + np.asarray(cand_shift[i], float)) * cell
        c, s = math.cos(yaw), math.sin(yaw)
        t_xy = t_xy - np.array([[c, -s], [s, c]]) @ centre
        t = planar(yaw, float(t_xy[0]), float(t_xy[1]))
        if all(_moved(t, h.transform, corners) > separation_m for h in chosen):
            chosen.append(Hypothesis(t, yaw, float(cand_score[i])))
            if len(chosen) >= keep:
                break
    return chosen


def _rfft2_padded(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`scipy.fft.rfft2(image, s=shape)`, bit for bit, for an image smaller than `shape`: the
    transform of its own rows, then of the columns (the padding rows' transforms are zeros)."""
    from scipy import fft

    spectrum: np.ndarray = fft.fft(fft.rfft(image, n=shape[1], axis=1), n=shape[0], axis=0)
    return spectrum


def _extent_corners(xy: np.ndarray) -> np.ndarray:
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]]])


def _moved(t1: np.ndarray, t2: np.ndarray, xy: np.ndarray) -> float:
    p1 = xy @ t1[:2, :2].T + t1[:2, 3]
    p2 = xy @ t2[:2, :2].T + t2[:2, 3]
    return float(np.max(np.linalg.norm(p1 - p2, axis=1)))


def z_offsets(
    a_points: np.ndarray,
    b_points: np.ndarray,
    cell: float,
    resolution: float,
    *,
    count: int = 2,
    separation_m: float = 1.0,
    max_votes: int = 2_000_000,
) -> list[tuple[float, float]]:
    """Best vertical offsets (dz, votes) moving B (already placed in xy) onto A, best first.

    Every B point votes for z_A - z_B with each A point in the same xy cell; the histogram (bins
    of one voxel, lightly smoothed) gives the offsets. Planar maps give their layers' offset.
    """
    if np.ptp(a_points[:, 2]) < 0.5 * resolution and np.ptp(b_points[:, 2]) < 0.5 * resolution:
        return [(float(a_points[0, 2] - b_points[0, 2]), float(len(b_points)))]
    ka = np.floor(a_points[:, :2] / cell).astype(np.int64)
    kb = np.floor(b_points[:, :2] / cell).astype(np.int64)
    col_a = vk.pack(np.column_stack([ka, np.zeros(len(ka), np.int64)]))
    order = np.argsort(col_a, kind="stable")
    col_a, za = col_a[order], a_points[order, 2]
    col_b = vk.pack(np.column_stack([kb, np.zeros(len(kb), np.int64)]))
    start = np.searchsorted(col_a, col_b, side="left")
    stop = np.searchsorted(col_a, col_b, side="right")
    n = stop - start
    if n.sum() > max_votes:  # thin B evenly to bound the votes
        keep = np.arange(len(n))[:: math.ceil(n.sum() / max_votes)]
        start, n, b_z = start[keep], n[keep], b_points[keep, 2]
    else:
        b_z = b_points[:, 2]
    total = int(n.sum())
    if total == 0:
        return []
    owner = np.repeat(np.arange(len(n)), n)
    within = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
    dz = za[start[owner] + within] - b_z[owner]
    lo = float(dz.min())
    bins = np.rint((dz - lo) / resolution).astype(np.int64)
    hist = np.bincount(bins).astype(np.float64)
    hist = np.convolve(hist, [0.25, 0.5, 0.25], mode="same")
    out: list[tuple[float, float]] = []
    width = max(1, round(separation_m / resolution))
    for _ in range(count):
        i = int(np.argmax(hist))
        if hist[i] <= 0:
            break
        out.append((lo + i * resolution, float(hist[i])))
        hist[max(0, i - width) : i + width + 1] = 0.0
    return out
