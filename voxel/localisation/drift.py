"""Drift: how fast a peer map's error may change along a path (the colony offset's random walk),
as one constant or from the growth of a peer's reported pose covariance per metre it drove."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from voxel.localisation import se2
from voxel.localisation.ekf import checked_pose


@dataclass(frozen=True)
class OffsetWalk:
    """How fast a peer map's error may change along the agent's path: the colony offset as a
    random walk with the distance travelled since the last colony match (`PlanarEkf.walk_offset`),
    so a correction learnt at one place is trusted less at the next.

    The defaults are one constant for every peer, fixed before its A/B from a drifted peer
    (docs/LOCALISATION.md, "Known limit: a peer map's error is not rigid"): a drifted peer's
    map is off by 5-12 cm, differently place by place (depth-1's in the sim office: its error
    where it mapped each place); two places a few metres apart differ by ~5-10 cm, i.e. a
    standard deviation of ~6 cm after 4 m: `trans` = 0.03 m per sqrt(m) in x and y. Its
    heading error varies less than its position's (the matcher holds heading to a fraction of a
    degree per match): ~1 degree after 4 m, `yaw` = 0.01 rad per sqrt(m), a third of the
    odometry model's `rot_per_m`. A turn brings another part of the peer's map into view
    without travel: counted as `lever` m of travel per radian (1 m: a quarter turn counts as
    1.6 m). `PeerDrift` makes one per peer from what it reports."""

    trans: float = 0.03  # m per sqrt(m of travel)
    yaw: float = 0.01  # rad per sqrt(m of travel)
    lever: float = 1.0  # m of travel per rad of turn

    def noise(self, travel: float) -> np.ndarray:
        """The walk's covariance (x, y, yaw about the agent) over `travel` m."""
        return np.diag([self.trans**2, self.trans**2, self.yaw**2]) * travel


#: Bounds of a walk made from a peer's reports (`PeerDrift.walk`), m and rad per sqrt(m).
#: Floor: a peer whose reported covariance does not grow still mapped into 5-10 cm cells
#: from scans matched to ~1 cm; its map is not trusted to hold its shape between places
#: better than 1 cm and 0.1 degree per 4 m. Cap: 20 cm and ~3.4 degrees per 4 m, where the
#: next place's error is as good as unconstrained by the last (the matcher's reach is 0.5 m,
#: the gate refuses beyond ~3 sigma): beyond it the filter's numbers only grow.
FLOOR = OffsetWalk(trans=0.005, yaw=0.001)
CAP = OffsetWalk(trans=0.1, yaw=0.03)


class PeerDrift:
    """A peer's drift along its path, from its Pose reports: the growth of its reported
    position and heading variances per metre it drove, as the density of a random walk of
    its map's error (`OffsetWalk`).

    The rule (fixed before its A/B, docs/LOCALISATION.md "A peer map's walk from its own
    drift"): a peer's map at a place holds the peer's pose error when it mapped there, so two
    places it mapped `s` m of its path apart differ by the error it accumulated over those
    `s` m: what its filter's covariance grows by over them, when nothing absolute corrected it.
    So each report adds (path s, translation variance (P_xx + P_yy) / 2, heading variance
    P_yawyaw), s the peer's path so far (its reported positions, in its own frame, plus
    `lever` m per radian turned, as the receiving agent's travel is counted); the density is
    the least-squares slope of each variance against s over the reports kept (robust to the
    sawtooth of odometry growth and matches; a fix or a loop closure that shrinks the
    peer's covariance pulls it down); its square root, clipped to [`FLOOR`, `CAP`], is the
    walk. None until the reports span `min_path` m of path and `min_reports` reports: too little
    to tell (the receiving agent then uses its constant walk, if any). The peer's covariance
    is taken as it reports it: an overconfident peer reports too slow a drift."""

    def __init__(
        self,
        *,
        lever: float = 1.0,
        min_path: float = 2.0,
        min_reports: int = 3,
        reports: int = 1000,
    ) -> None:
        self.lever, self.min_path, self.min_reports = lever, min_path, min_reports
        self._rows: deque[tuple[float, float, float]] = deque(maxlen=reports)
        self._last: np.ndarray | None = None
        self._path = 0.0

    def add(self, pose: np.ndarray, covariance: np.ndarray) -> None:
        """One report: the peer's pose (x, y, yaw, its frame) and its covariance (3x3)."""
        p, c = checked_pose(pose, covariance, "peer drift")
        if self._last is not None:
            step = se2.relative(self._last, p)
            self._path += math.hypot(step[0], step[1]) + self.lever * abs(float(step[2]))
        self._last = p
        self._rows.append((self._path, 0.5 * float(c[0, 0] + c[1, 1]), float(c[2, 2])))

    @property
    def path(self) -> float:
        """Metres of the peer's path (turns by `lever`) since its first report."""
        return self._path

    def walk(self) -> OffsetWalk | None:
        """The peer's drift as a walk density, or None while too little is known."""
        if len(self._rows) < self.min_reports:
            return None
        rows = np.array(self._rows)
        s = rows[:, 0] - rows[:, 0].mean()
        span = float(rows[-1, 0] - rows[0, 0])
        if span < self.min_path or float(s @ s) <= 0.0:
            return None
        slopes = s @ (rows[:, 1:] - rows[:, 1:].mean(axis=0)) / float(s @ s)
        trans = math.sqrt(max(float(slopes[0]), 0.0))
        yaw = math.sqrt(max(float(slopes[1]), 0.0))
        return OffsetWalk(
            trans=min(max(trans, FLOOR.trans), CAP.trans),
            yaw=min(max(yaw, FLOOR.yaw), CAP.yaw),
            lever=self.lever,
        )


def widest(walks: list[OffsetWalk]) -> OffsetWalk | None:
    """The walk of a cut made of several peers' maps: the fastest (by translation, then
    heading), as a cut's error is its worst peer's (`colonyd.colonymap.cut_error`)."""
    return max(walks, key=lambda w: (w.trans, w.yaw)) if walks else None
