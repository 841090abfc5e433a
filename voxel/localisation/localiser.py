"""One agent's pose estimator for range sensors (paper Alg. 1-2): EKF predict from odometry, update
by scan-to-map matching."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from voxel.localisation import frame_error, se2
from voxel.localisation.colony_map import ColonyMap
from voxel.localisation.drift import OffsetWalk
from voxel.localisation.ekf import COLONY, MotionNoise, PlanarEkf
from voxel.localisation.pose_graph import PoseGraph
from voxel.localisation.scan_match import LocalMap, Match, MatchTarget, match, thin


@dataclass(frozen=True)
class ScanParams:
    """Parameters of `ScanLocaliser` (plain values; see `LocalMap` and `match`)."""

    keyframes: int = 100
    map_cell: float = 0.05
    key_distance: float = 0.25
    key_angle: float = 0.15
    scan_cell: float = 0.05  # thin each scan to one point per cell before matching
    max_points: int = 3000
    max_range: float = 30.0  # ignore returns beyond this for matching (they still map)
    max_distance: float = 0.5
    final_distance: float = 0.15
    iterations: int = 20
    inflation: float = 1.0  # times the matcher's covariance (`match`: honest without it)
    colony_min_matched: int = 60  # correspondences a match against the colony's map needs
    #: A colony match whose x or y variance exceeds this (m^2) constrains nothing: failed.
    colony_max_variance: float = 1.0
    #: Of the last `colony_window` matches against the colony's map, more than this share
    #: refused by the gate means that map disagrees with us (a wrong alignment, or a peer whose
    #: map drifted): it is not used again until the alignments change.
    colony_window: int = 20
    colony_refusals: float = 0.3
    #: The colony offset's random walk along the path (None: a rigid offset, the default
    #: until an A/B supports it; docs/BENCHMARKS.md "A peer map's error as a random walk").
    colony_walk: OffsetWalk | None = None
    #: Walk each colony map by its peers' own drift (`ColonyMap.walk`, from their reported
    #: pose covariances, `PeerDrift`) when it has one, else by `colony_walk` (off until an A/B
    #: supports it; docs/BENCHMARKS.md "A peer map's walk from its own drift").
    colony_peer_walk: bool = False
    #: Variance (m^2) added to each own-map match's x and y: a match that lands one map cell
    #: off (the scan's and map's lattices aliasing) with some chance, as a mixture's variance
    #: (chance times the cell squared). 0: the matcher's covariance alone (the default;
    #: docs/BENCHMARKS.md "A peer map's walk from its own drift").
    own_aliasing: float = 0.0
    #: Estimate each landmark's error (published minus true position) in the filter, keyed by
    #: its id, so that its sightings count its error once (`PlanarEkf.update_landmark` with a
    #: key; the default since its A/B); False: each sighting fused as independent, the
    #: published error counted every time (docs/BENCHMARKS.md "A landmark's error counted
    #: once").
    landmark_errors: bool = True
    #: Estimate the error of each alignment fixes and landmarks come through (a CCTV's frame,
    #: a peer's) as one state of the filter, keyed by its origin, counted once
    #: (`PlanarEkf.reset_frame`): the callers then give a fix's and a landmark's own covariance
    #: and the alignment (`Through`) apart. False: the alignment's error added to each (the
    #: default until its A/B; docs/BENCHMARKS.md "An alignment's error as one shared state").
    alignment_frames: bool = False
    history: int = 100  # (time, pose) of the last steps, to carry a late fix to the present
    fix_tolerance: float = 0.15  # seconds between a fix's stamp and the nearest step


@dataclass(frozen=True, eq=False)
class Through:
    """The alignment a fix or a landmark came through into this agent's frame: its origin (the
    frame the measurement was made in: a CCTV, a peer), the alignment's identity (its transform,
    rounded: a changed alignment is a new error) and its error's covariance (x, y, yaw: a small
    motion about this agent's origin, as `frame_error`'s). Compared and hashed by identity
    (its covariance is an array): the frame's key is (origin, alignment)."""

    origin: str
    alignment: bytes
    covariance: np.ndarray


@dataclass(frozen=True)
class Step:
    """What one step did: the estimated body pose (x, y, yaw), the match (if any) and whether it was
    fused."""

    pose: np.ndarray
    match: Match | None
    fused: bool
    colony: Match | None = None  # the match against the colony's map, when there was one
    colony_fused: bool = False


class ScanLocaliser:
    """Pose of a ground agent with a 2D or 3D range sensor, in its own odometry frame.

    Each step: predict with the odometry increment (or widen without odometry), match the scan
    against the agent's own recent map from the predicted pose, fuse the matched pose relative to
    the keyframes it was matched against (`PlanarEkf.update_relative`: the map was placed by the
    estimate, so it measures only the error grown since; gated by its Mahalanobis distance);
    when a `ColonyMap` is given (aligned peers' maps in this agent's frame), match the scan
    against it too and fuse that as a pose measured against a map whose error (the
    alignment's, `ColonyMap.covariance`) the filter estimates with the pose
    (`PlanarEkf.update_offset`: the alignment's error is counted once, not once per scan; gated
    the same way: a bad alignment is refused, not followed); then add the scan to the local
    map when it is a keyframe, its error to the filter's state (`PlanarEkf.add_keyframe`).
    Reads only odometry, the scan and the peers' maps: never a reference pose.

    With `record` set before the first step, every step and every update the filter fuses is
    also kept in `graph` (a `PoseGraph`, with the covariance the filter used), whose `solve`
    gives the smoothed trajectory. Off by default: the graph grows with every step.
    """

    def __init__(
        self,
        *,
        planar: bool,
        params: ScanParams | None = None,
        motion: MotionNoise | None = None,
        sensor: np.ndarray | None = None,
    ) -> None:
        self.params = params or ScanParams()
        #: The sensor's position in the body frame: the side of a surface the scan sees.
        self.sensor = np.zeros(3) if sensor is None else np.asarray(sensor, np.float64).reshape(3)
        p = self.params
        self.local = LocalMap(
            planar=planar,
            keyframes=p.keyframes,
            cell=p.map_cell,
            key_distance=p.key_distance,
            key_angle=p.key_angle,
        )
        self.motion = motion
        self.ekf: PlanarEkf | None = None
        self.last_odometry: np.ndarray | None = None
        self.rng = np.random.default_rng(0)
        self.colony_accepted = self.colony_rejected = self.colony_failed = 0
        self.colony_suspended = 0
        self._colony_outcomes: deque[bool] = deque(maxlen=self.params.colony_window)
        self._distrusted: bytes | None = None  # the alignment of a colony map that disagreed
        self._offset_of: bytes | None = None  # the alignment whose error the filter estimates
        #: per origin the alignment whose error the filter estimates (`Through`)
        self._frames_of: dict[str, bytes] = {}
        self._graph_offsets: dict[Hashable, int] = {}  # the graph's offset variable per frame
        self._travel = np.zeros(2)  # m driven and rad turned since the last colony match
        self.fix_accepted = self.fix_rejected = self.fix_stale = 0
        self.landmark_accepted = self.landmark_rejected = 0
        self.history: deque[tuple[float, np.ndarray]] = deque(maxlen=self.params.history)
        self.record = False
        self.graph: PoseGraph | None = None

    def step(
        self,
        points_body: np.ndarray,
        odometry: np.ndarray | None,
        colony: ColonyMap | None = None,
        time: float | None = None,
    ) -> Step:
        """Advance with one scan (N, 3) in the body frame and the odometry pose (x, y, yaw) read
        with it; `colony`: the aligned peers' map near the agent, in its frame; `time`: when the
        scan was taken (kept with the pose, for `fix`)."""
        p = self.params
        pts = np.asarray(points_body, np.float64)
        pts = pts[np.linalg.norm(pts[:, :2], axis=1) <= p.max_range]
        pts = thin(pts, p.scan_cell)
        if len(pts) > p.max_points:
            pts = pts[self.rng.choice(len(pts), p.max_points, replace=False)]
        result: Match | None = None
        fused = False
        if self.ekf is None:
            start = np.zeros(3) if odometry is None else np.asarray(odometry, np.float64)
            self.ekf = PlanarEkf(start, motion=self.motion)
            if self.record:
                self.graph = PoseGraph(self.ekf.pose, self.ekf.covariance)
        else:
            increment = None
            if odometry is not None and self.last_odometry is not None:
                increment = se2.relative(self.last_odometry, np.asarray(odometry, np.float64))
            before = self.ekf.pose
            self.ekf.predict(increment)
            if self.graph is not None:
                self.graph.step(*self.ekf.motion_step(increment))
            if p.colony_walk is not None or p.colony_peer_walk:
                moved = se2.relative(before, self.ekf.pose)
                self._travel += (math.hypot(moved[0], moved[1]), abs(float(moved[2])))
            result = self._match(pts, self.local)
            if result.ok and result.labels is not None and result.information is not None:
                fused = self.ekf.update_relative(
                    se2.from_matrix(result.pose),
                    result.covariance + np.diag([p.own_aliasing, p.own_aliasing, 0.0]),
                    result.labels,
                    result.information,
                )
                if fused and self.graph is not None:
                    self.graph.add_match(
                        se2.from_matrix(result.pose),
                        result.covariance,
                        result.labels,
                        result.information,
                    )
        colony_match: Match | None = None
        colony_fused = False
        if colony is not None and colony.tree is not None:
            if self._distrusted is not None and colony.alignment == self._distrusted:
                self.colony_suspended += 1
            else:
                self._distrusted = None
                colony_match, colony_fused = self._colony_update(pts, colony)
        self.last_odometry = None if odometry is None else np.asarray(odometry, np.float64).copy()
        pose = self.ekf.pose
        if self.graph is not None:
            self.graph.place(pose)
        if time is not None:
            self.history.append((float(time), pose))
        m = se2.to_matrix(pose)
        if self.local.wants(m):
            key = self.local.add(
                pts @ m[:3, :3].T + m[:3, 3], m, m[:3, :3] @ self.sensor + m[:3, 3]
            )
            if key is not None:
                self.ekf.add_keyframe(key)
                if self.graph is not None:
                    self.graph.add_keyframe(key, pose)
                self.ekf.keep_keyframes(self.local.ids)
        return Step(pose, result, fused, colony_match, colony_fused)

    def pose_at(self, stamp: float) -> np.ndarray | None:
        """The estimate (x, y, yaw) of the recent step nearest `stamp`, if one is within
        `fix_tolerance` seconds of it."""
        if not self.history:
            return None
        times = np.array([t for t, _ in self.history])
        i = int(np.argmin(np.abs(times - stamp)))
        if abs(times[i] - stamp) > self.params.fix_tolerance:
            return None
        pose: np.ndarray = self.history[i][1].copy()
        return pose

    def ahead(self, stamp: float) -> bool:
        """True when `stamp` is later than the last step by more than `fix_tolerance`: a fix
        from a sensor that is ahead of this agent (it maps late), to be fused once it gets there."""
        return bool(self.history) and stamp > self.history[-1][0] + self.params.fix_tolerance

    def fix(
        self,
        pose: np.ndarray,
        covariance: np.ndarray,
        stamp: float,
        through: Through | None = None,
    ) -> bool | None:
        """Fuse an absolute measurement of the body pose (x, y, yaw) in this agent's frame, taken
        at `stamp` (a CCTV saw the agent's marker): carried to the present by the estimated motion
        since the step nearest `stamp`, its covariance widened by the filter's motion noise over
        that motion, and gated like every update. With `through`, the fix came through that
        alignment, whose error the filter estimates as one state per origin (`covariance` is
        the fix's own, without the alignment's): measured as the true pose moved by that error
        (`PlanarEkf.update_frame`). None (and nothing changes) when `stamp` is not within
        `fix_tolerance` of a recent step."""
        then = self.pose_at(stamp)
        if self.ekf is None or then is None:
            self.fix_stale += 1
            return None
        motion = se2.relative(then, self.ekf.pose)
        z = se2.compose(np.asarray(pose, np.float64), motion)
        m = self.ekf.motion
        d = math.hypot(motion[0], motion[1])
        widen = np.diag(
            [m.trans**2 * d, m.trans**2 * d, m.rot**2 * abs(motion[2]) + m.rot_per_m**2 * d]
        )
        r = np.asarray(covariance, np.float64) + widen
        key = None if through is None else self._through(through)
        fused = self.ekf.update(z, r) if key is None else self.ekf.update_frame(key, z, r)
        if fused:
            self.fix_accepted += 1
            if self.graph is not None:
                if key is None:
                    self.graph.add_absolute(z, r)
                else:
                    self.graph.add_colony(z, r, self._graph_offsets[key])
                self.graph.place(self.ekf.pose)
        else:
            self.fix_rejected += 1
        return fused

    def landmark(
        self,
        seen: np.ndarray,
        seen_covariance: np.ndarray,
        landmark: np.ndarray,
        landmark_covariance: np.ndarray,
        key: int | None = None,
        through: Through | None = None,
    ) -> bool | None:
        """Fuse a landmark (paper Alg. 3): an identified object (id `key`) seen at `seen` (x, y,
        body frame, now) whose position `landmark` (x, y, this agent's frame) the colony knows
        (`PlanarEkf.update_landmark`, gated; with `landmark_errors` its error is estimated
        under `key`, counted once, and the pose graph, when recording, keeps the landmark as
        a variable too). With `through`, the landmark came through that alignment, whose error
        the filter estimates as one state per origin, shared with the fixes through it
        (`landmark_covariance` is the landmark's own, without the alignment's). The pose
        graph does not model that frame for landmarks: it keeps the landmark with the
        alignment's error added to its covariance, as without `through`. None before the
        first step."""
        if self.ekf is None:
            return None
        yaw = float(self.ekf.pose[2])
        keyed = key if self.params.landmark_errors else None
        frame = None if through is None else self._through(through)
        fused = self.ekf.update_landmark(
            seen, seen_covariance, landmark, landmark_covariance, key=keyed, frame=frame
        )
        if fused:
            self.landmark_accepted += 1
            if self.graph is not None:
                shared = np.zeros((2, 2))
                if through is not None:
                    xy = np.asarray(landmark, np.float64).reshape(2)
                    shared = frame_error.at(through.covariance, xy)[:2, :2]
                self.graph.add_landmark(
                    seen,
                    seen_covariance,
                    landmark,
                    np.asarray(landmark_covariance, np.float64) + shared,
                    yaw,
                    key=keyed,
                )
                self.graph.place(self.ekf.pose)
        else:
            self.landmark_rejected += 1
        return fused

    def _through(self, through: Through) -> Hashable:
        """The filter's frame for the alignment `through` (its key): a new error, zero with the
        alignment's covariance, when the origin's alignment changed or the filter dropped it
        (`PlanarEkf.reset_frame`); else widened by the growth of its claim (`widen_frame`).
        The pose graph, when recording, follows (`reset_offset`, `walk_offset`)."""
        assert self.ekf is not None  # the first step made it
        key = ("alignment", through.origin)
        graph = self.graph
        if self.ekf.frame(key) is None or self._frames_of.get(through.origin) != through.alignment:
            self.ekf.reset_frame(key, through.covariance)
            self._frames_of[through.origin] = through.alignment
            if graph is not None:
                self._graph_offsets[key] = graph.reset_offset(through.covariance)
        else:
            noise = self.ekf.widen_frame(key, through.covariance)
            if graph is not None and np.any(noise):
                self._graph_offsets[key] = graph.walk_offset(noise, self._graph_offsets[key])
        return key

    def _match(self, pts: np.ndarray, target: LocalMap | ColonyMap, **extra: Any) -> Match:
        """The scan matched (x, y, yaw) against `target` from the current estimate (for the own
        map: where the estimate appears in the newest keyframe's map, which the filter may have
        corrected since it was placed)."""
        assert self.ekf is not None  # the first step made it
        start = self.ekf.pose
        if target is self.local and self.ekf.keyframes:
            start = self.ekf.seen_from(self.ekf.keyframes[-1])
        return self.match_from(pts, target, start, **extra)

    def match_from(
        self, pts: np.ndarray, target: MatchTarget, start: np.ndarray, **extra: Any
    ) -> Match:
        """The scan (body frame, thinned) matched (x, y, yaw) against `target` from the body pose
        `start` (x, y, yaw), with this localiser's matching parameters."""
        p = self.params
        return match(
            pts,
            target,
            se2.to_matrix(start),
            dof=3,
            max_distance=p.max_distance,
            final_distance=p.final_distance,
            iterations=p.iterations,
            inflation=p.inflation,
            sensor=self.sensor,
            **extra,
        )

    def walk_of(self, colony: ColonyMap) -> OffsetWalk | None:
        """How fast `colony`'s error may wander along the path: its peers' own drift when
        `colony_peer_walk` and the cut has one, else the constant `colony_walk` (None: rigid)."""
        p = self.params
        if p.colony_peer_walk and colony.walk is not None:
            return colony.walk
        return p.colony_walk

    def _colony_update(self, pts: np.ndarray, colony: ColonyMap) -> tuple[Match, bool]:
        """Match the scan against the colony's map from the current estimate; fuse it, gated."""
        p = self.params
        assert self.ekf is not None  # the first step made it
        result = self._match(pts, colony, min_matched=p.colony_min_matched)
        if not result.ok or np.max(np.diag(result.covariance)[:2]) > p.colony_max_variance:
            self.colony_failed += 1  # too few pairs, or they constrain nothing (all normals up)
            return result, False
        if self.ekf.offset is None or self._offset_of != colony.alignment:
            self.ekf.reset_offset(colony.covariance)  # new alignments: a new error to estimate
            self._offset_of = colony.alignment
            if self.graph is not None:
                self._graph_offsets[COLONY] = self.graph.reset_offset(colony.covariance)
        else:  # the same alignments; a peer that drifted or got lost since widens their error
            grown = [self.ekf.widen_offset(colony.covariance)]
            walk = self.walk_of(colony)
            travel = float(self._travel[0]) + (
                0.0 if walk is None else walk.lever * self._travel[1]
            )
            if walk is not None and travel > 0.0:  # and so does the way here
                grown.append(self.ekf.walk_offset(walk.noise(travel), self.ekf.pose[:2]))
            noise = sum(grown[1:], grown[0])
            if self.graph is not None and np.any(noise):
                self._graph_offsets[COLONY] = self.graph.walk_offset(
                    noise, self._graph_offsets[COLONY]
                )
        self._travel = np.zeros(2)
        fused = self.ekf.update_offset(se2.from_matrix(result.pose), result.covariance)
        if fused:
            self.colony_accepted += 1
            if self.graph is not None:
                self.graph.add_colony(
                    se2.from_matrix(result.pose), result.covariance, self._graph_offsets[COLONY]
                )
        else:
            self.colony_rejected += 1
        outcomes = self._colony_outcomes
        outcomes.append(fused)
        if len(outcomes) >= p.colony_window // 2 and (
            outcomes.count(False) > p.colony_refusals * len(outcomes)
        ):
            self._distrusted = colony.alignment
            outcomes.clear()
        return result, fused
