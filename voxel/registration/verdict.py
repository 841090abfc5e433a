"""Whether an alignment is trusted: hard checks on the evidence, ambiguity and covariance, and one
confidence number. A wrong merge is worse than none, so any failed check means *not aligned*."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from voxel.registration.evidence import Evidence


@dataclass(frozen=True)
class Thresholds:
    """Limits a trusted alignment must meet."""

    min_inliers: int = 150  # matching B sample points
    min_agreement: float = (
        0.3  # confirmed minus contradicted share of overlapping wall points, both ways
    )
    min_inlier_ratio: float = (
        0.45  # confirmed share of overlapping wall points, in the worse direction
    )
    max_conflict: float = (
        0.3  # contradicted share (in the other map's open space), in the worse direction
    )
    max_near_miss: float = (
        0.3  # walls next to (not on) the other map's walls, in the worse direction
    )
    min_support_ratio: float = 0.45  # confirmed share of all overlapping B points, floors included
    max_ambiguity: float = 0.5  # second-best distinct planar pose's score over the best's
    max_z_ambiguity: float = 0.7  # support of the best other height over the best height's
    max_translation_std_m: float = 0.05
    max_yaw_std_deg: float = 0.5
    min_confidence: float = 0.1


@dataclass(frozen=True)
class Verdict:
    """Aligned or not, the confidence in [0, 1], and why not."""

    aligned: bool
    confidence: float
    reason: str | None
    failed: tuple[str, ...] = ()  # names of every check that failed (reason: the first's message)


def judge(
    best: Evidence,
    ambiguity: float,
    z_ambiguity: float,
    cov: np.ndarray,
    names: list[str],
    limits: Thresholds,
) -> Verdict:
    """The verdict on the best pose given its evidence, the ambiguity ratios (planar and in
    height) and its covariance."""
    var = dict(zip(names, np.diag(cov), strict=True))
    t_std = math.sqrt(max(var.get(n, 0.0) for n in ("x", "y", "z")))
    yaw_std = math.degrees(math.sqrt(var["yaw"]))
    # Each factor is 0 at its check's limit and 1 with a clear margin; the confidence is their
    # geometric mean, so a failed check always means confidence 0 and a pass counts by its margin.
    factors = (
        _ramp(best.inliers, limits.min_inliers, 3 * limits.min_inliers),
        _ramp(best.agreement, limits.min_agreement, limits.min_agreement + 0.3),
        _ramp(best.worst_inlier_ratio, limits.min_inlier_ratio, limits.min_inlier_ratio + 0.2),
        _ramp(-best.worst_conflict_ratio, -limits.max_conflict, -limits.max_conflict * 0.4),
        _ramp(-ambiguity, -limits.max_ambiguity, -limits.max_ambiguity * 0.4),
        _ramp(-z_ambiguity, -limits.max_z_ambiguity, -limits.max_z_ambiguity * 0.6),
        _ramp(best.support_ratio, limits.min_support_ratio, limits.min_support_ratio + 0.2),
        _ramp(-best.worst_near_miss_ratio, -limits.max_near_miss, -limits.max_near_miss * 0.4),
    )
    confidence = float(np.prod(factors)) ** (1.0 / len(factors))
    checks = [
        (
            "inliers",
            best.inliers >= limits.min_inliers,
            (
                f"too few matching voxels: expected at least {limits.min_inliers}, "
                f"found {best.inliers}"
            ),
        ),
        (
            "agreement",
            best.agreement >= limits.min_agreement,
            (
                "the maps disagree where they overlap: expected confirmed minus contradicted "
                f"walls of at least {limits.min_agreement:.0%}, found {best.agreement:.0%} "
                f"({best.inlier_ratio:.0%} confirmed, {best.conflict_ratio:.0%} in the other map's "
                "open space)"
            ),
        ),
        (
            "confirmed",
            best.worst_inlier_ratio >= limits.min_inlier_ratio,
            (
                "one map's walls are not confirmed by the other: expected at least "
                f"{limits.min_inlier_ratio:.0%} in each direction, "
                f"found {best.worst_inlier_ratio:.0%}"
            ),
        ),
        (
            "contradicted",
            best.worst_conflict_ratio <= limits.max_conflict,
            (
                "walls land in the other map's open space: expected at most "
                f"{limits.max_conflict:.0%} in each direction, found "
                f"{best.worst_conflict_ratio:.0%}"
            ),
        ),
        (
            "near_miss",
            best.worst_near_miss_ratio <= limits.max_near_miss,
            (
                "walls land next to the other map's walls, not on them: expected at most "
                f"{limits.max_near_miss:.0%} near misses in each direction, found "
                f"{best.worst_near_miss_ratio:.0%} (a pose slid along repeated structure?)"
            ),
        ),
        (
            "support",
            best.support_ratio >= limits.min_support_ratio,
            (
                "walls agree but floors and ceilings do not: expected at least "
                f"{limits.min_support_ratio:.0%} of all overlapping voxels to match, found "
                f"{best.support_ratio:.0%} (a height offset --dof 3 cannot model?)"
            ),
        ),
        (
            "ambiguity",
            ambiguity <= limits.max_ambiguity,
            (
                f"ambiguous: a distinct pose scores {ambiguity:.0%} of the best (expected at most "
                f"{limits.max_ambiguity:.0%}); e.g. a symmetric corridor, repeated rooms or maps "
                "of different places"
            ),
        ),
        (
            "z_ambiguity",
            z_ambiguity <= limits.max_z_ambiguity,
            (
                f"ambiguous in height: another height is supported {z_ambiguity:.0%} as well as "
                f"the best (expected at most {limits.max_z_ambiguity:.0%})"
            ),
        ),
        (
            "constrained",
            t_std <= limits.max_translation_std_m and yaw_std <= limits.max_yaw_std_deg,
            (
                "the geometry does not constrain every direction: expected standard deviations "
                f"within {limits.max_translation_std_m} m and {limits.max_yaw_std_deg} deg, found "
                f"{t_std:.3g} m and {yaw_std:.3g} deg"
            ),
        ),
        (
            "confidence",
            confidence >= limits.min_confidence,
            f"confidence {confidence:.2f} below {limits.min_confidence}",
        ),
    ]
    failed = [(name, reason) for name, ok, reason in checks if not ok]
    if len(failed) > 1:  # the confidence check only speaks when every other check passed
        failed = [(name, reason) for name, reason in failed if name != "confidence"]
    if failed:
        return Verdict(False, 0.0, failed[0][1], tuple(name for name, _ in failed))
    return Verdict(True, confidence, None)


def _ramp(value: float, lo: float, hi: float) -> float:
    """0 at or below lo, 1 at or above hi, linear between."""
    if hi <= lo:
        return 1.0 if value >= hi else 0.0
    return float(min(1.0, max(0.0, (value - lo) / (hi - lo))))
