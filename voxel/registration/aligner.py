"""Align two maps by their geometry (global yaw search, ICP on the best distinct hypotheses) and
their objects, with a verdict."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from os import PathLike
from typing import TYPE_CHECKING, Any

import numpy as np

from voxel import keys as vk
from voxel.errors import AlignmentError
from voxel.registration.evidence import Evidence, Side, evaluate
from voxel.registration.global_search import (
    Hypothesis,
    observed_columns,
    structure,
    yaw_search,
    z_offsets,
)
from voxel.registration.icp import covariance, icp, normals
from voxel.registration.landmarks import (
    LandmarkFit,
    Landmarks,
    ObjectEvidence,
    landmark_matches,
    match_landmarks,
    objects_in_map,
)
from voxel.registration.mapcloud import MapCloud, load_map
from voxel.registration.transform import apply, euler
from voxel.registration.verdict import Thresholds, judge

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

METHOD = "yaw-correlation+icp"
#: Objects placed by a pose must not land in the other map's open space more than this share of
#: the objects the other map observed (more rules the pose out).
MAX_OBJECT_CONFLICT = 0.25
#: A rival pose the objects give no ground (`AlignParams.prefer_backed`) has at most this share
#: of the best pose's objects on the other map's surfaces.
UNBACKED_SHARE = 1.0 / 3.0


@dataclass(frozen=True)
class AlignParams:
    """Knobs of `align_clouds`; the defaults are what the benchmark measured."""

    dof: int = 4  # 3: x, y, yaw; 4: + z; 6: full
    search_cell_m: float | None = None  # cell of the yaw search images; None: max(2 voxels, 0.2 m)
    yaw_step_deg: float = 1.0
    hypotheses: int = 8  # distinct poses from the global search refined by ICP
    coarse_samples: int = 4000  # B points per hypothesis ICP / evidence
    fine_samples: int = 20000  # B points of the final ICP
    eval_samples: int = 50000  # B points the final evidence counts
    inlier_voxels: float = 1.5  # inlier distance, voxels (at least inlier_min_m)
    inlier_min_m: float = 0.1
    distinct_m: float = 0.5  # poses moving B's extent less than this apart are the same pose
    seed: int = 0
    limits: Thresholds = field(default_factory=Thresholds)
    #: Objects that must land on the other map's surfaces at the best pose (more than fall where
    #: it has not looked, few in its open space) for rivals whose objects fall unobserved (at
    #: most UNBACKED_SHARE as many on surfaces, most unobserved) to leave the ambiguity; None:
    #: off (only objects in the open space rule a rival out).
    prefer_backed: int | None = 4


@dataclass(frozen=True)
class Alignment:
    """Result of aligning map B to map A: `transform` maps B's points into A's frame."""

    aligned: bool
    transform: np.ndarray
    confidence: float
    inliers: int
    rmse_m: float
    overlap: float
    inlier_ratio: float
    conflict: float
    agreement: float
    ambiguity: float
    z_ambiguity: float
    covariance: np.ndarray
    covariance_params: list[str]
    hypotheses: int
    dof: int
    seconds: float
    reason: str | None
    failed_checks: tuple[str, ...] = ()
    method: str = METHOD
    geometric_ambiguity: float = 0.0  # before objects ruled rival poses out
    conflict_extent_m: float = 0.0  # largest connected patch of walls in the other's open space
    #: object evidence: supported, contradicted, matched, the objects' own fit, poses ruled out
    objects: dict[str, object] | None = None
    #: The point in A's frame (the matched points' centroid) that `covariance`'s rotations are
    #: about; None when there was no fit.
    covariance_centre: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON record `colonyd align` writes (angles in degrees, transform 4x4 row-major)."""
        roll, pitch, yaw = (math.degrees(v) for v in euler(self.transform))
        out = {
            "aligned": self.aligned,
            "transform": np.round(self.transform, 9).tolist(),
            "x": float(self.transform[0, 3]),
            "y": float(self.transform[1, 3]),
            "z": float(self.transform[2, 3]),
            "roll_deg": roll,
            "pitch_deg": pitch,
            "yaw_deg": yaw,
            "confidence": round(self.confidence, 4),
            "inliers": self.inliers,
            "rmse_m": None if not math.isfinite(self.rmse_m) else round(self.rmse_m, 5),
            "overlap": round(self.overlap, 4),
            "inlier_ratio": round(self.inlier_ratio, 4),
            "conflict": round(self.conflict, 4),
            "agreement": round(self.agreement, 4),
            "ambiguity": round(self.ambiguity, 4),
            "z_ambiguity": round(self.z_ambiguity, 4),
            "covariance": np.round(self.covariance, 12).tolist(),
            "covariance_params": self.covariance_params,
            "hypotheses": self.hypotheses,
            "dof": self.dof,
            "method": self.method,
            "geometric_ambiguity": round(self.geometric_ambiguity, 4),
            "conflict_extent_m": round(self.conflict_extent_m, 2),
            "objects": self.objects,
            "seconds": round(self.seconds, 3),
        }
        if not self.aligned:
            out["reason"] = self.reason
            out["failed_checks"] = list(self.failed_checks)
        return out


@dataclass(frozen=True)
class _Candidate:
    transform: np.ndarray
    evidence: Evidence


def align_maps(
    path_a: str | PathLike[str], path_b: str | PathLike[str], params: AlignParams | None = None
) -> Alignment:
    """Align the map file B to the map file A (.bt, grid .npz, .ply); time includes reading."""
    began = time.perf_counter()
    a, b = load_map(path_a), load_map(path_b)
    result = align_clouds(a, b, params)
    return _with_seconds(result, time.perf_counter() - began)


def align_clouds(
    a: MapCloud,
    b: MapCloud,
    params: AlignParams | None = None,
    *,
    objects_a: Landmarks | None = None,
    objects_b: Landmarks | None = None,
) -> Alignment:
    """Align map B to map A: the transform of B's points into A's frame, with its verdict.

    `objects_a` / `objects_b` are the maps' object centroids (class ids and positions, each in
    its map's frame), when known: a class-consistent fit of B's objects to A's seeds the search,
    and objects placed by each candidate pose in the other map vote among the poses (a pose that
    puts objects in the other map's open space is ruled out). A planar map (a 2D scanner's)
    against a 3D one is aligned to the 3D map's slice at the planar map's height, in x, y and
    yaw (z 0: both frames on the same floor).
    """
    began = time.perf_counter()
    p = params or AlignParams()
    _check(a, b, p)
    full_a, full_b = a, b
    sliced = a.planar != b.planar
    if sliced:  # a 2D scan against a 3D map: the 3D map's slice at the scan's height
        a, b = (
            (a, _slice(b, float(a.occupied[0, 2])))
            if a.planar
            else (_slice(a, float(b.occupied[0, 2])), b)
        )
        if len(a.occupied) < 10 or len(b.occupied) < 10:
            return _not_aligned(
                p.dof,
                0,
                time.perf_counter() - began,
                "the 3D map has too little at the planar map's height: expected at least 10 "
                "occupied voxels in the slice",
            )
    res = max(a.resolution, b.resolution)
    cell = p.search_cell_m or max(2.0 * res, 0.2)
    both_planar = a.planar and b.planar
    icp_dof = 3 if both_planar else p.dof
    inlier_m = max(p.inlier_voxels * res, p.inlier_min_m)
    rng = np.random.default_rng(p.seed)
    oa = objects_a if objects_a is not None else Landmarks.of([])
    ob = objects_b if objects_b is not None else Landmarks.of([])
    fit = match_landmarks(oa, ob, 4 if p.dof == 4 or both_planar else p.dof)
    if fit.found and both_planar:
        fit = replace(fit, transform=_z_zero(fit.transform))

    from scipy.spatial import cKDTree  # scipy.spatial loads on first use, not at start-up

    a_tree = cKDTree(a.occupied)
    a_coarse = _thin(a.occupied, 2.0 * res)
    a_coarse_tree = cKDTree(a_coarse)
    a_wall, b_wall = structure(a.occupied, a.resolution), structure(b.occupied, b.resolution)
    a_walls, b_walls = a.occupied[a_wall], b.occupied[b_wall]
    a_side, b_side = _side(a, a_tree, a_walls, cell), _side(b, cKDTree(b.occupied), b_walls, cell)
    b_coarse = _sample(b.occupied, p.coarse_samples, rng)
    b_check = _sample_masked(b.occupied, b_wall, p.coarse_samples, rng)
    a_check = _sample_masked(a.occupied, a_wall, p.coarse_samples, rng)

    hypotheses = _global_hypotheses(a, b, a_walls, b_walls, a_side, cell, res, p, both_planar)
    if fit.found:  # objects seed the search too (their centroids are biased: ICP refines)
        hypotheses.append(Hypothesis(fit.transform, float(euler(fit.transform)[2]), 0.0))
    candidates = [
        _refine_coarse(
            h,
            a_coarse,
            a_coarse_tree,
            a_side,
            b_side,
            b_coarse,
            b_check,
            a_check,
            icp_dof,
            cell,
            res,
            inlier_m,
        )
        for h in hypotheses
    ]
    ranked, z_ambiguity = _distinct(candidates, b.occupied, p.distinct_m)
    if not ranked:
        return _not_aligned(
            p.dof,
            len(hypotheses),
            time.perf_counter() - began,
            "the global search found no pose that puts any of B on A",
        )
    geometric_ambiguity = _ambiguity(ranked)
    votes = [_object_votes(c.transform, full_a, full_b, oa, ob) for c in ranked]
    ranked, votes, ambiguity, ruled_out, unbacked = _resolve(
        ranked, votes, geometric_ambiguity, p.prefer_backed
    )
    best = ranked[0]

    b_fine = _sample(b.occupied, p.fine_samples, rng)
    fine = icp(
        b_fine,
        a_tree,
        a.occupied,
        best.transform,
        icp_dof,
        start_m=3.0 * res,
        end_m=1.5 * res,
        iterations=30,
    )
    transform = _z_zero(fine.transform) if sliced else fine.transform
    b_eval = _sample_masked(b.occupied, b_wall, p.eval_samples, rng)
    a_eval = _sample_masked(a.occupied, a_wall, p.eval_samples, rng)
    evidence = evaluate(fine.transform, a_side, *b_eval, b_side, *a_eval, inlier_m)
    cov, names, centre = _covariance(
        fine.transform, b_fine, a, a_tree, inlier_m, icp_dof, both_planar
    )
    verdict = judge(evidence, ambiguity, z_ambiguity, cov, names, p.limits)
    vote = _object_votes(transform, full_a, full_b, oa, ob)
    objection = _objection(vote, fit, transform, b.occupied, p)
    aligned, reason, failed, confidence = (
        verdict.aligned,
        verdict.reason,
        verdict.failed,
        verdict.confidence,
    )
    if objection is not None:
        aligned, confidence = False, 0.0
        reason = reason or objection
        failed = (*failed, "objects")
    used = len(oa) + len(ob) > 0
    method = ("slice+" if sliced else "") + METHOD + ("+objects" if used else "")
    return Alignment(
        aligned=aligned,
        transform=transform,
        confidence=confidence,
        inliers=evidence.inliers,
        rmse_m=evidence.rmse,
        overlap=evidence.overlap,
        inlier_ratio=evidence.inlier_ratio,
        conflict=evidence.conflict_ratio,
        agreement=evidence.agreement,
        ambiguity=ambiguity,
        z_ambiguity=z_ambiguity,
        covariance=cov,
        covariance_params=names,
        hypotheses=len(hypotheses),
        dof=3 if sliced else p.dof,
        seconds=time.perf_counter() - began,
        reason=None if aligned else reason,
        failed_checks=() if aligned else failed,
        method=method,
        geometric_ambiguity=geometric_ambiguity,
        conflict_extent_m=evidence.conflict_extent,
        objects=(
            _objects_record(vote, fit, ruled_out, unbacked, len(oa), len(ob)) if used else None
        ),
        covariance_centre=centre,
    )


def _slice(m: MapCloud, z: float) -> MapCloud:
    """The horizontal layer of `m` (its occupied and known voxels) containing height `z`."""
    k = int(np.floor(z / m.resolution))
    occ = m.occupied[np.floor(m.occupied[:, 2] / m.resolution).astype(np.int64) == k]
    if m.known is None or m.known_occupied is None:
        return MapCloud(m.resolution, occ, name=m.name)
    layer = vk.unpack(m.known)[:, 2] == k
    return MapCloud(m.resolution, occ, m.known[layer], m.known_occupied[layer], m.name)


def _z_zero(t: np.ndarray) -> np.ndarray:
    out = t.copy()
    out[2, 3] = 0.0
    return out


def _object_votes(
    t: np.ndarray, a: MapCloud, b: MapCloud, oa: Landmarks, ob: Landmarks
) -> ObjectEvidence:
    """Both ways: B's objects in A's map and A's objects in B's map under `t`, and class matches."""
    if len(oa) + len(ob) == 0:
        return ObjectEvidence()
    ev = objects_in_map(t, ob, a) + objects_in_map(np.linalg.inv(t), oa, b)
    return replace(ev, matched=landmark_matches(t, oa, ob))


def _backed(v: ObjectEvidence) -> bool:
    """Objects back a pose: at least 2 land on the other map's surfaces, few in its open space."""
    return v.supported >= 2 and v.contradicted <= MAX_OBJECT_CONFLICT * v.observed


def _ruled_out(v: ObjectEvidence) -> bool:
    """Objects contradict a pose: more than MAX_OBJECT_CONFLICT of the objects the other map
    observed land in its open space."""
    return v.contradicted > MAX_OBJECT_CONFLICT * v.observed


def _unbacked(rival: ObjectEvidence, best: ObjectEvidence, prefer_backed: int | None) -> bool:
    """The objects give the rival pose no ground against the best: the best has at least
    `prefer_backed` objects on the other map's surfaces (more than fall where it has not looked,
    and is not ruled out), the rival at most UNBACKED_SHARE as many, and most of the rival's
    objects fall where the other map has not looked (no evidence either way)."""
    if prefer_backed is None or best.supported < prefer_backed:
        return False
    if best.supported <= best.unknown or _ruled_out(best):
        return False
    return rival.supported <= UNBACKED_SHARE * best.supported and rival.unknown > rival.supported


def _resolve(
    ranked: list[_Candidate],
    votes: list[ObjectEvidence],
    ambiguity: float,
    prefer_backed: int | None = None,
) -> tuple[list[_Candidate], list[ObjectEvidence], float, int, int]:
    """Let objects settle what geometry cannot: poses the objects rule out are dropped, and when
    the best remaining pose is backed by objects the ambiguity is counted among the remaining
    poses only; with `prefer_backed`, rivals the objects give no ground against it (`_unbacked`)
    leave the count too. Returns the candidates, their votes, the ambiguity and how many were
    ruled out and how many left as unbacked."""
    keep = [i for i, v in enumerate(votes) if not _ruled_out(v)]
    if not keep or not _backed(votes[keep[0]]):
        return ranked, votes, ambiguity, 0, 0
    dropped = len(ranked) - len(keep)
    first = votes[keep[0]]
    rivals = [i for i in keep[1:] if not _unbacked(votes[i], first, prefer_backed)]
    unbacked = len(keep) - 1 - len(rivals)
    keep = [keep[0], *rivals]
    ranked, votes = [ranked[i] for i in keep], [votes[i] for i in keep]
    return ranked, votes, _ambiguity(ranked), dropped, unbacked


def _objection(
    vote: ObjectEvidence, fit: LandmarkFit, t: np.ndarray, b_points: np.ndarray, p: AlignParams
) -> str | None:
    """Why the objects refuse the pose `t` the geometry chose, or None when they do not: objects
    in the other map's open space, at least 2 objects known but fewer than 2 (or fewer than
    those falling where the other map has not looked) backing the pose (such a pose waits for
    more data: a wrong merge is worse than none), or a confident object fit elsewhere."""
    if _ruled_out(vote):
        return (
            f"objects land in the other map's open space: expected at most "
            f"{MAX_OBJECT_CONFLICT:.0%} of the objects it observed, found {vote.contradicted} of "
            f"{vote.observed}"
        )
    placed = vote.supported + vote.contradicted + vote.unknown
    if placed >= 2 and (vote.supported < 2 or vote.supported < vote.unknown):
        return (
            f"objects do not back the pose: expected at least 2 of the {placed} objects, and "
            f"more than land where the other map has not looked, on the other map's surfaces; "
            f"found {vote.supported} ({vote.unknown} unobserved)"
        )
    if fit.found and fit.inliers >= 3 and fit.ambiguity <= p.limits.max_ambiguity:
        lo, hi = b_points.min(axis=0), b_points.max(axis=0)
        corners = np.array([[x, y, lo[2]] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
        moved = _planar_moved(t, fit.transform, corners)
        if moved > 2.0:
            return (
                f"objects and geometry disagree: {fit.inliers} objects of matching classes put B "
                f"{moved:.1f} m away from the geometric pose (expected within 2.0 m)"
            )
    return None


def _objects_record(
    vote: ObjectEvidence, fit: LandmarkFit, ruled_out: int, unbacked: int, n_a: int, n_b: int
) -> dict[str, object]:
    return {
        "a": n_a,
        "b": n_b,
        "supported": vote.supported,
        "contradicted": vote.contradicted,
        "unobserved": vote.unknown,
        "matched": vote.matched,
        "fit_inliers": fit.inliers if fit.found else 0,
        "fit_rmse_m": round(fit.rmse, 4) if fit.found and math.isfinite(fit.rmse) else None,
        "fit_ambiguity": round(fit.ambiguity, 4) if fit.found else None,
        "poses_ruled_out": ruled_out,
        "poses_unbacked": unbacked,
    }


def _check(a: MapCloud, b: MapCloud, p: AlignParams) -> None:
    if p.dof not in (3, 4, 6):
        msg = f"dof: expected 3 (x, y, yaw), 4 (x, y, z, yaw) or 6, found {p.dof!r}"
        raise AlignmentError(msg)
    if p.prefer_backed is not None and p.prefer_backed < 2:
        msg = (
            "prefer_backed: expected None (off) or at least 2 objects on the other map's "
            f"surfaces, found {p.prefer_backed!r}"
        )
        raise AlignmentError(msg)
    for name, m in (("A", a), ("B", b)):
        if m.occupied.ndim != 2 or m.occupied.shape[1] != 3 or len(m.occupied) < 10:
            msg = (
                f"map {name} ({m.name}): expected at least 10 occupied voxels (N, 3), "
                f"found shape {m.occupied.shape}"
            )
            raise AlignmentError(msg)
        if not np.all(np.isfinite(m.occupied)):
            msg = f"map {name} ({m.name}): expected finite coordinates, found NaN or inf"
            raise AlignmentError(msg)


def _side(m: MapCloud, tree: cKDTree, walls: np.ndarray, cell: float) -> Side:
    """Evidence's view of a map: walls, and the columns it observed (with free space: every column
    with a known voxel; without: columns with occupied voxels)."""
    observed = (
        observed_columns(m.known, m.resolution, cell) if m.known is not None else m.occupied[:, :2]
    )
    return Side.build(tree, walls, observed, cell)


def _global_hypotheses(
    a: MapCloud,
    b: MapCloud,
    a_walls: np.ndarray,
    b_walls: np.ndarray,
    a_side: Side,
    cell: float,
    res: float,
    p: AlignParams,
    both_planar: bool,
) -> list[Hypothesis]:
    """Distinct planar poses from the yaw search, each with its best vertical offsets (dof 4, 6)."""
    a_free = (vk.unpack(a_side.observed)[:, :2] + 0.5) * cell
    planar_hyps = yaw_search(
        a_walls[:, :2],
        b_walls[:, :2],
        cell,
        a_free_xy=a_free,
        yaw_step_deg=p.yaw_step_deg,
        keep=p.hypotheses,
    )
    if p.dof == 3 and not both_planar:
        return planar_hyps
    a_thin = _thin(a.occupied, res, xy_cell=cell)
    out: list[Hypothesis] = []
    b_sample = _sample(b.occupied, 20000, np.random.default_rng(p.seed + 1))
    for h in planar_hyps:
        placed = apply(h.transform, b_sample)
        for dz, _ in z_offsets(a_thin, placed, cell, res, count=1 if both_planar else 2):
            t = h.transform.copy()
            t[2, 3] = dz
            out.append(Hypothesis(t, h.yaw, h.score))
    return out


def _refine_coarse(
    h: Hypothesis,
    a_coarse: np.ndarray,
    a_coarse_tree: cKDTree,
    a_side: Side,
    b_side: Side,
    b_coarse: np.ndarray,
    b_check: tuple[np.ndarray, np.ndarray],
    a_check: tuple[np.ndarray, np.ndarray],
    dof: int,
    cell: float,
    res: float,
    inlier_m: float,
) -> _Candidate:
    """ICP from a global hypothesis against a thinned A; evidence counted on both maps' walls."""
    fit = icp(
        b_coarse,
        a_coarse_tree,
        a_coarse,
        h.transform,
        dof,
        start_m=2.0 * cell,
        end_m=2.5 * res,
        iterations=24,
    )
    return _Candidate(
        fit.transform, evaluate(fit.transform, a_side, *b_check, b_side, *a_check, inlier_m)
    )


def _distinct(
    candidates: list[_Candidate], b_points: np.ndarray, distinct_m: float
) -> tuple[list[_Candidate], float]:
    """Distinct candidates best first, and the z ambiguity of the best.

    Candidates whose planar poses move B's extent less than `distinct_m` apart are one planar
    pose: of those the one with the most support (floors and ceilings included) sets z, and the
    z ambiguity is the support of a z more than `distinct_m` away over the best's.
    """
    lo, hi = b_points.min(axis=0), b_points.max(axis=0)
    corners = np.array([[x, y, lo[2]] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
    groups: list[list[_Candidate]] = []
    for c in sorted(candidates, key=lambda c: c.evidence.score, reverse=True):
        if c.evidence.inliers == 0:
            continue
        for g in groups:
            if _planar_moved(c.transform, g[0].transform, corners) <= distinct_m:
                g.append(c)
                break
        else:
            groups.append([c])
    if not groups:
        return [], 0.0
    ranked = []
    for g in groups:
        g.sort(key=lambda c: c.evidence.support, reverse=True)
        ranked.append(g[0])
    best_group = groups[0]
    z_amb = 0.0
    for c in best_group[1:]:
        if abs(c.transform[2, 3] - best_group[0].transform[2, 3]) > distinct_m:
            z_amb = max(z_amb, c.evidence.support / max(best_group[0].evidence.support, 1))
    return ranked, z_amb


def _ambiguity(ranked: list[_Candidate]) -> float:
    """Score of the second-best distinct planar pose over the best's (1 when the best scores
    nothing)."""
    best = ranked[0].evidence.score
    if best <= 0:
        return 1.0
    second = max(0.0, ranked[1].evidence.score) if len(ranked) > 1 else 0.0
    return second / best


def _planar_moved(t1: np.ndarray, t2: np.ndarray, corners: np.ndarray) -> float:
    p1 = corners[:, :2] @ t1[:2, :2].T + t1[:2, 3]
    p2 = corners[:, :2] @ t2[:2, :2].T + t2[:2, 3]
    return float(np.max(np.linalg.norm(p1 - p2, axis=1)))


def _covariance(
    t: np.ndarray,
    b_points: np.ndarray,
    a: MapCloud,
    a_tree: cKDTree,
    inlier_m: float,
    dof: int,
    both_planar: bool,
) -> tuple[np.ndarray, list[str], np.ndarray | None]:
    """The fit's covariance, its parameter names and the point its rotations are about."""
    moved = apply(t, b_points)
    d, idx = a_tree.query(moved, distance_upper_bound=inlier_m)
    ok = np.isfinite(d)
    if ok.sum() < 10:
        n = {3: 3, 4: 4, 6: 6}[dof]
        names = {
            3: ["x", "y", "yaw"],
            4: ["x", "y", "z", "yaw"],
            6: ["x", "y", "z", "roll", "pitch", "yaw"],
        }[dof]
        return np.eye(n) * 1e6, names, None
    normal = normals(a.occupied, a_tree, a.occupied[idx[ok]], both_planar)
    cov, names = covariance(moved[ok], a.occupied[idx[ok]], normal, dof)
    return cov, names, moved[ok].mean(axis=0)


def _sample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= count:
        return points
    return points[np.sort(rng.choice(len(points), count, replace=False))]


def _sample_masked(
    points: np.ndarray, mask: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    if len(points) <= count:
        return points, mask
    pick = np.sort(rng.choice(len(points), count, replace=False))
    return points[pick], mask[pick]


def _thin(points: np.ndarray, cell: float, xy_cell: float | None = None) -> np.ndarray:
    """One point per cell (xy cells of `xy_cell` when given, z cells of `cell`)."""
    scale = np.array([xy_cell or cell, xy_cell or cell, cell])
    keys = np.floor(points / scale).astype(np.int64)
    _, first = np.unique(vk.pack(keys), return_index=True)
    return points[np.sort(first)]


def _not_aligned(dof: int, hypotheses: int, seconds: float, reason: str) -> Alignment:
    names = {
        3: ["x", "y", "yaw"],
        4: ["x", "y", "z", "yaw"],
        6: ["x", "y", "z", "roll", "pitch", "yaw"],
    }[dof]
    return Alignment(
        False,
        np.eye(4),
        0.0,
        0,
        math.inf,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        np.eye(len(names)) * 1e6,
        names,
        hypotheses,
        dof,
        seconds,
        reason,
        ("search",),
    )


def _with_seconds(result: Alignment, seconds: float) -> Alignment:
    return replace(result, seconds=seconds)
