"""Alignment evidence from objects: class-consistent RANSAC over object centroids, and object
centroids checked against the other map's voxels.

Object centroids are biased (the mean of the *observed* surface voxels leans towards the
observer by 0.1-0.6 m), so a fit from objects alone is a coarse pose: it seeds the geometric
search and votes among its hypotheses; ICP on the maps refines. Plain numpy, vectorised over
hypotheses and objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from voxel.errors import AlignmentError
from voxel.registration.icp import fit_rigid
from voxel.registration.mapcloud import FREE, OCCUPIED, MapCloud
from voxel.registration.transform import apply


@dataclass(frozen=True)
class Landmarks:
    """Object centroids (N, 3) of one map in its frame and their class ids (N,)."""

    positions: np.ndarray
    classes: np.ndarray

    @classmethod
    def of(cls, items: list[tuple[int, np.ndarray | tuple[float, ...]]]) -> Landmarks:
        """From (class id, position) pairs."""
        if not items:
            return cls(np.empty((0, 3)), np.empty(0, np.int64))
        classes = np.array([int(c) for c, _ in items], np.int64)
        positions = np.array([np.asarray(p, float).reshape(3) for _, p in items])
        if not np.all(np.isfinite(positions)):
            msg = "object positions: expected finite coordinates, found NaN or inf"
            raise AlignmentError(msg)
        return cls(positions, classes)

    def __len__(self) -> int:
        return len(self.classes)


@dataclass(frozen=True)
class LandmarkFit:
    """The best pose of B's objects on A's: inlier pairs (B index, A index), RMS residual, and
    the ambiguity (inliers of the best distinct other pose over the best's)."""

    found: bool
    transform: np.ndarray
    pairs: np.ndarray  # (K, 2): B object index, A object index
    rmse: float
    ambiguity: float
    hypotheses: int
    reason: str | None

    @property
    def inliers(self) -> int:
        return len(self.pairs)


def match_landmarks(
    a: Landmarks,
    b: Landmarks,
    dof: int = 4,
    *,
    gate_m: float = 0.8,
    min_separation_m: float = 1.0,
    distinct_m: float = 1.0,
    max_hypotheses: int = 20000,
    seed: int = 0,
) -> LandmarkFit:
    """RANSAC over pairs of class-consistent correspondences (all of them when few).

    dof 3 and 4 (gravity known): yaw from the horizontal offset of two objects, translation from
    their midpoints; at least 2 inlier objects. dof 6: Kabsch on three correspondences (tilts
    over 30 degrees dropped: gravity is roughly known); at least 3. The best hypothesis (most B
    objects with an object of their class within `gate_m`, lower residual on a tie) is refined
    by Kabsch/Umeyama (no scale) on its inliers.
    """
    if dof not in (3, 4, 6):
        msg = f"dof: expected 3, 4 or 6, found {dof!r}"
        raise AlignmentError(msg)
    need = 3 if dof == 6 else 2
    if len(a) < need or len(b) < need:
        return _none(
            f"too few objects: expected at least {need} in each map, found {len(a)} and {len(b)}"
        )
    ib, ia = np.nonzero(b.classes[:, None] == a.classes[None, :])  # class-consistent pairs
    if len(ib) < need:
        return _none(
            f"too few objects of a shared class: expected at least {need} pairs, found {len(ib)}"
        )
    rng = np.random.default_rng(seed)
    hyps = _hypotheses(a, b, ia, ib, dof, min_separation_m, max_hypotheses, rng)
    if len(hyps) == 0:
        return _none("no two objects of a shared class are far enough apart to fix the yaw")
    counts, resid = _score(hyps, a, b, gate_m)
    order = np.lexsort((resid, -counts))
    best = hyps[order[0]]
    fit, pairs, rmse = _refine(best, a, b, gate_m, dof)
    if len(pairs) < need:
        return LandmarkFit(
            False,
            fit,
            pairs,
            rmse,
            1.0,
            len(hyps),
            f"too few objects agree on one pose: expected at least {need}, found {len(pairs)}",
        )
    # ambiguity: the best other hypothesis that associates some object differently
    mapping = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))
    used = {j: i for i, j in mapping.items()}
    second = 0
    for h in order[:200]:
        if counts[h] <= second:
            break
        other = _pairs(hyps[h], a, b, gate_m)
        conflicts = sum(mapping.get(i, j) != j or used.get(j, i) != i for i, j in other.tolist())
        if (
            conflicts >= 2
            and len(other) > second
            and _moved(hyps[h], fit, b.positions) > distinct_m
        ):
            second = len(other)
    ambiguity = second / max(len(pairs), 1)
    return LandmarkFit(True, fit, pairs, rmse, ambiguity, len(hyps), None)


def _none(reason: str) -> LandmarkFit:
    return LandmarkFit(False, np.eye(4), np.empty((0, 2), np.int64), math.inf, 1.0, 0, reason)


def _hypotheses(
    a: Landmarks,
    b: Landmarks,
    ia: np.ndarray,
    ib: np.ndarray,
    dof: int,
    min_sep: float,
    limit: int,
    rng: np.random.Generator,
    max_tilt_deg: float = 30.0,
) -> np.ndarray:
    """(H, 4, 4) transforms from pairs (dof 3/4) or triples (dof 6) of correspondences."""
    k = len(ia)
    if dof == 6:
        combos = rng.integers(0, k, size=(min(limit, k**3), 3))
        combos = combos[
            (combos[:, 0] != combos[:, 1])
            & (combos[:, 1] != combos[:, 2])
            & (combos[:, 0] != combos[:, 2])
        ]
        out: list[np.ndarray] = []
        for c in combos:  # Kabsch per triple (few: objects are tens at most)
            p, q = b.positions[ib[c]], a.positions[ia[c]]
            if len(set(ib[c].tolist())) < 3 or len(set(ia[c].tolist())) < 3:
                continue
            if np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0])) < min_sep**2 * 0.5:
                continue  # nearly collinear: no roll or pitch
            t = fit_rigid(p, q, 6)
            if t[2, 2] >= math.cos(math.radians(max_tilt_deg)):  # gravity is roughly known
                out.append(t)
        return np.array(out).reshape(-1, 4, 4)
    i, j = np.triu_indices(k, 1)
    if len(i) > limit:
        pick = rng.choice(len(i), limit, replace=False)
        i, j = i[pick], j[pick]
    ok = (ib[i] != ib[j]) & (ia[i] != ia[j])
    i, j = i[ok], j[ok]
    db = b.positions[ib[j], :2] - b.positions[ib[i], :2]
    da = a.positions[ia[j], :2] - a.positions[ia[i], :2]
    lb, la = np.linalg.norm(db, axis=1), np.linalg.norm(da, axis=1)
    ok = (lb >= min_sep) & (la >= min_sep) & (np.abs(lb - la) <= 0.5 * min_sep)
    i, j, db, da = i[ok], j[ok], db[ok], da[ok]
    yaw = np.arctan2(da[:, 1], da[:, 0]) - np.arctan2(db[:, 1], db[:, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.zeros((len(yaw), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    mb = (b.positions[ib[i]] + b.positions[ib[j]]) / 2
    ma = (a.positions[ia[i]] + a.positions[ia[j]]) / 2
    t = ma - np.einsum("hij,hj->hi", rot, mb)
    if dof == 3:
        t[:, 2] = 0.0
    hyp = np.tile(np.eye(4), (len(yaw), 1, 1))
    hyp[:, :3, :3], hyp[:, :3, 3] = rot, t
    return hyp


def _score(
    hyps: np.ndarray, a: Landmarks, b: Landmarks, gate: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per hypothesis: B objects with an A object of their class within `gate` (each A object
    counted once at most: min of both ways), and their mean squared distance."""
    moved = np.einsum("hij,nj->hni", hyps[:, :3, :3], b.positions) + hyps[:, None, :3, 3]
    d = np.linalg.norm(moved[:, :, None, :] - a.positions[None, None, :, :], axis=3)
    d = np.where(b.classes[:, None] == a.classes[None, :], d, np.inf)
    near = d <= gate
    count = np.minimum(near.any(axis=2).sum(axis=1), near.any(axis=1).sum(axis=1))
    dmin = np.where(near.any(axis=2), d.min(axis=2), 0.0)
    resid = (dmin**2).sum(axis=1) / np.maximum(count, 1)
    return count, resid


def _pairs(t: np.ndarray, a: Landmarks, b: Landmarks, gate: float) -> np.ndarray:
    """Mutual nearest same-class pairs within `gate` under `t`."""
    d = np.linalg.norm(apply(t, b.positions)[:, None, :] - a.positions[None, :, :], axis=2)
    d = np.where(b.classes[:, None] == a.classes[None, :], d, np.inf)
    bi = np.arange(len(b))
    ai = d.argmin(axis=1)
    mutual = (d.argmin(axis=0)[ai] == bi) & (d[bi, ai] <= gate)
    return np.column_stack([bi[mutual], ai[mutual]])


def _refine(
    t: np.ndarray, a: Landmarks, b: Landmarks, gate: float, dof: int
) -> tuple[np.ndarray, np.ndarray, float]:
    need = 3 if dof == 6 else 2
    pairs = _pairs(t, a, b, gate)
    for _ in range(3):
        if len(pairs) < need:
            break
        t = fit_rigid(b.positions[pairs[:, 0]], a.positions[pairs[:, 1]], dof if dof != 3 else 4)
        if dof == 3:
            t[2, 3] = 0.0
        new = _pairs(t, a, b, gate)
        if len(new) < len(pairs):
            break
        pairs = new
    if len(pairs) == 0:
        return t, pairs, math.inf
    r = apply(t, b.positions[pairs[:, 0]]) - a.positions[pairs[:, 1]]
    return t, pairs, float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def _moved(t1: np.ndarray, t2: np.ndarray, points: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(apply(t1, points) - apply(t2, points), axis=1)))


@dataclass(frozen=True)
class ObjectEvidence:
    """Objects of one map placed in the other by a pose: how many land on its occupied voxels
    (`supported`), in space it saw open (`contradicted`), or where it has not looked."""

    supported: int = 0
    contradicted: int = 0
    unknown: int = 0
    matched: int = 0  # objects with an object of their class in the other map within the gate

    def __add__(self, other: ObjectEvidence) -> ObjectEvidence:
        return ObjectEvidence(
            self.supported + other.supported,
            self.contradicted + other.contradicted,
            self.unknown + other.unknown,
            self.matched + other.matched,
        )

    @property
    def observed(self) -> int:
        return self.supported + self.contradicted


def objects_in_map(
    t: np.ndarray,
    objects: Landmarks,
    m: MapCloud,
    *,
    radius_m: float = 0.3,
    min_known: float = 0.3,
) -> ObjectEvidence:
    """Place `objects` (in their map's frame) into map `m` by `t` and ask `m` about the cube of
    half-size `radius_m` around each: a cube `m` knows (at least `min_known` of its voxels) with
    occupied voxels supports the object, one it knows entirely free contradicts it. A planar map
    (a 2D scanner's slice) is asked at its own height (objects stand on the floor)."""
    if len(objects) == 0 or m.known is None:
        return ObjectEvidence(unknown=len(objects))
    res = m.resolution
    n = max(1, round(radius_m / res))
    g = np.arange(-n, n + 1) * res
    if m.planar:
        off = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), axis=-1).reshape(-1, 3)
    else:
        off = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = apply(t, objects.positions)
    if m.planar:
        centres[:, 2] = float(m.occupied[0, 2])
    state = m.state_at((centres[:, None, :] + off[None, :, :]).reshape(-1, 3)).reshape(
        len(centres), -1
    )
    known = (state != -1).sum(axis=1)
    occ = (state == OCCUPIED).sum(axis=1)
    free = (state == FREE).sum(axis=1)
    seen = known >= min_known * off.shape[0]
    supported = seen & (occ >= 2)
    contradicted = seen & (occ == 0) & (free > 0)
    return ObjectEvidence(
        int(supported.sum()), int(contradicted.sum()), int((~supported & ~contradicted).sum())
    )


def landmark_matches(t: np.ndarray, a: Landmarks, b: Landmarks, gate_m: float = 0.8) -> int:
    """B objects with an A object of their class within `gate_m` under `t` (mutual nearest)."""
    if len(a) == 0 or len(b) == 0:
        return 0
    return len(_pairs(t, a, b, gate_m))
