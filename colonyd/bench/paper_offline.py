"""The paper experiment's two robots offline, deterministic: one robot alone and with the other's
map, for A/B of estimator changes without the live runs' timing chaos.

`python -m colonyd.bench.paper_offline --seed S [--world W] [--lidar-range R] [--rng N]
[--duration S] [--no-peer-covariance] [--offset-walk] [--peer-walk]
[--smooth [--joint [--joint-weighting W,...]]]
[--peer-points centres,means] [--json FILE]`

Each robot's sim source (the experiment's spec and seed, not paced) runs through its estimator
and maps from the estimate, as `colonyd localize` does. The peer's map (its estimated-pose voxel
grid at the end of its path) is put into the robot's frame by a fixture alignment, the true
transform between the two frames with a fixed error (3 cm, -5 cm, 0.5 degrees about the
robot's origin; its opposite for lidar-1) and the honest-error covariance measured live (6 cm,
12 cm, 1.2 degrees, docs/LOCALISATION.md), and given to the estimator from the middle of the
path (live first contact came at ~31 s of 60). Unless `--no-peer-covariance` (the
daemon's `colony_peer_pose`, on by default in both), the cut's covariance also holds the
peer's own pose uncertainty: its filter's covariance at the frame nearest in time to the
robot's contact (when the cut is made), as an error of its map about the cut's centre, moved
into the robot's frame. The simulator's truth builds that fixture and evaluates; no estimator
reads it (as the "perfect peer map" diagnosis in docs/LOCALISATION.md).
`--offset-walk` lets both robots' colony offsets walk with distance (`OffsetWalk`'s defaults;
`ScanParams.colony_walk`, off in the daemon). `--peer-walk` lets them walk by the peer's own
drift instead (`PeerDrift` over its filter's covariance and its estimated path, one report
a second up to the contact's time, as its Pose messages would have said;
`ScanParams.colony_peer_walk`), the constant walk only while the peer's reports are too few.
`--own-aliasing P` adds P times its map cell squared to each of depth-1's own-map matches'
x and y variances (`ScanParams.own_aliasing`: a false match one cell away with chance P;
0.042 measured, 25 of 600 frames, docs/BENCHMARKS.md "Is depth-1's sensor biased?"), in every
run of depth-1 (alone too).
`--smooth` also scores each run's smoothed trajectory (`PoseGraph` over what its filter fused,
docs/LOCALISATION.md): `<run>_smoothed` holds its ATE, the solve's CPU seconds, cost before and
after, iterations and edges.
`--joint` (with `--smooth`) also solves both robots' recorded graphs as one (`JointGraph`,
`joint`): each colony match lidar-1 fused becomes an inter-robot edge on its node, the frames'
transform and the depth-1 steps that hit the map cells its scan matched (`Provenance`), so the
solve may move depth-1's past poses (its map) too: `joint_smoothed` holds both robots' ATE;
`--joint-peer-inflate F,...` (diagnostic) solves it again with depth-1's own edges' covariance
times each F (keys `@peerF`), `--joint-inter-inflate F,...` with the inter edges' (`@interF`);
`--joint-alone` with lidar-1's own edges from its alone run (`@alone`).
`--joint-weighting W,...` (comma-separated, `WEIGHTINGS`; the first's keys plain, the others'
`@W`): how the inter edges are weighted, all without the truth: `matcher` (default) with the
scan matcher's covariance; `vce` with every group's (lidar-1's own edges, depth-1's own, the
inter edges) covariance scaled by variance component estimation (`JointGraph.solve(vce=True)`;
`factors` and `rounds` in the output); `cell` with the peer map's quantisation, its voxel size
squared over 12 in x and y, added to each inter edge's covariance (`quantisation`); `cell-vce`
both.
`--peer-points` (comma-separated: each, the first's keys plain, the others' `@means`): the
peer's map as its occupied voxels' centres (`centres`) or as their surface points (`means`: the
peer run's grid keeps the grid's `surface` channel, each voxel's mean hit position at its
estimated poses, and the cut takes its occupied voxels' published surface points through the
daemon's `colonymap.peer_surfaces`, as a daemon's colony map does a replica's).
`--rng` draws the scans' subsample with another seed: how far a run moves when nothing but
that changes (the noise to compare against).

Diagnostics (bounds, docs/BENCHMARKS.md "Bounds"; none changes the estimator's code):
`--perfect-peer` gives lidar-1 depth-1's map built from depth-1's true poses (the best map a
peer could give: truth builds this fixture, as it builds the alignment); `--exact-alignment`
puts the peer's map in without the fixture's error; `--contact F` gives the peer's map from
that fraction of the path on (0: from the start; default 0.5; comma-separated: each);
`--relax` (comma-separated: each) `nosuspend` never suspends the colony map for refusals,
`nogate` also fuses every colony match ungated, `inflate` adds (5 cm, 5 cm, 1 degree)^2 to
the filter's covariance before each colony match (what an honest state covariance of that
size would let through), `inflate-nosuspend` both; `--keyframes K` sizes lidar-1's local
map; `--lidar-noise M` sets lidar-1's range noise (standard deviation, m); `--lidar-only`
skips depth-1 with lidar-1's map; `--profile S` adds lidar-1's error every S seconds of path
(true position, fitted error, and, in its own frame from the first pose, the error along and
across its heading and in heading).
"""

from __future__ import annotations

import argparse
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import print_and_append
from colonyd.bench.provenance import Provenance, quantile_steps
from colonyd.colonymap import peer_map_error, peer_surfaces
from colonyd.estimator import ScanEstimator, get_estimator
from colonyd.layers import Layer
from colonyd.mapping import integrate_observation
from colonyd.simrun import sim_spec
from plugins.observation import Observation
from plugins.source import open_source
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.localisation import se2
from voxel.localisation.colony_map import ColonyMap, colony_map
from voxel.localisation.drift import OffsetWalk, PeerDrift
from voxel.localisation.joint_graph import JointGraph
from voxel.localisation.metrics import absolute_trajectory_error
from voxel.localisation.pose_graph import PoseGraph
from voxel.occupancy import FREE_STATE, OCCUPIED

#: The fixture alignment's error (x, y, yaw about the robot's origin) and its covariance.
ALIGNMENT_ERROR = (0.03, -0.05, float(np.radians(0.5)))
ALIGNMENT_COVARIANCE = np.diag([0.06**2, 0.12**2, float(np.radians(1.2)) ** 2])
DURATION_S = 60.0
#: `--relax inflate`: added to the filter's (x, y, yaw) covariance before each colony match.
INFLATION = np.diag([0.05**2, 0.05**2, float(np.radians(1.0)) ** 2])
#: `--joint`: how many of the peer's steps stand for those that built a matched part of its map.
JOINT_NODES = 8
#: `--joint-weighting`: the inter edges with the matcher's covariance, scaled by variance
#: component estimation, with the peer map's quantisation added, or both.
WEIGHTINGS = ("matcher", "vce", "cell", "cell-vce")


RELAXED = ("none", "nosuspend", "nogate", "inflate", "inflate-nosuspend")
#: `--peer-points`: a peer's map as its voxels' centres, or as their surface points (each
#: voxel's mean hit position, the grid's `surface` channel).
PEER_POINTS = ("centres", "means")


def surfaces(grid: VoxelGrid, to_own: np.ndarray) -> np.ndarray:
    """The surface points of `grid`'s occupied voxels (a peer run's map, kept with
    `surface=True`), put into a robot's frame by `to_own`: the daemon's `peer_surfaces` on a
    layer holding it (an origin's occupied voxels publish the surface its replicas hold)."""
    if not grid.surface:
        msg = "peer points 'means': expected the peer's grid with its surface channel, found none"
        raise ValueError(msg)
    layer = Layer("peer", grid.resolution)
    layer.grid = grid
    return peer_surfaces([(layer, to_own)])[0]


def relax(estimator: ScanEstimator, how: str) -> None:
    """Diagnostic only: loosen how `estimator` takes colony matches. `nosuspend`: the colony
    map is never suspended for refusals; `nogate`: nor is any match gated (every one fused);
    `inflate`: the state covariance is widened by `INFLATION` before each colony match (gate
    and suspension as they are); `inflate-nosuspend`: both."""
    loc = estimator.localiser
    ekf = loc.ekf
    assert ekf is not None, "relax after the first step"
    if how in ("nosuspend", "nogate", "inflate-nosuspend"):
        loc.params = replace(loc.params, colony_refusals=1.0)
    if how == "nogate":
        plain = ekf.update_offset

        def ungated(pose: np.ndarray, covariance: np.ndarray, gate: float | None = None) -> bool:
            return plain(pose, covariance, gate=None)

        setattr(ekf, "update_offset", ungated)  # noqa: B010 - an instance's method, diagnostic
    if how.startswith("inflate"):
        update = loc._colony_update

        def widened(pts: np.ndarray, colony: ColonyMap) -> Any:
            ekf.kf.P = ekf.kf.P + INFLATION
            return update(pts, colony)

        setattr(loc, "_colony_update", widened)  # noqa: B010 - an instance's method, diagnostic


class Run:
    """One robot's path through its estimator: estimated and true sensor poses, its map."""

    def __init__(
        self,
        agent: str,
        seed: int,
        lidar_range: float,
        duration: float = DURATION_S,
        keyframes: int | None = None,
        lidar_noise: float | None = None,
        world: str = "office",
        walk: OffsetWalk | None = None,
        peer_walk: bool = False,
        aliasing: float = 0.0,
        smooth: bool = False,
    ) -> None:
        self.walk, self.peer_walk, self.aliasing = walk, peer_walk, aliasing
        self.smooth = smooth
        #: With `smooth`: the smoothed trajectory's ATE and what its solve took.
        self.smoothed: dict[str, Any] = {}
        self.smoothed_poses: list[np.ndarray] = []
        options = f"lidar_range={lidar_range:g}" if agent == "lidar-1" else ""
        if agent == "lidar-1" and lidar_noise is not None:
            options += f",range_noise={lidar_noise:g}"
        self.keyframes = keyframes
        self.spec = sim_spec(
            agent,
            duration,
            seed,
            world=world,
            odometry_noise="realistic",
            realtime=False,
            options=options,
        )
        self.estimates: list[np.ndarray] = []
        self.truths: list[np.ndarray] = []
        self.counts: dict[str, int] = {}
        self.covariances: list[np.ndarray] = []  # the filter's (x, y, yaw) covariance per frame
        self.times: list[float] = []  # the time of each frame with a covariance
        self.mount = np.eye(4)
        self.grid: VoxelGrid | None = None
        #: (trans, yaw) of each peer walk given with a cut (`--peer-walk`; None: not yet known)
        self.peer_walks: list[list[float] | None] = []
        #: The map keeps the grid's surface channel (`--peer-points means`).
        self.means = False
        #: `--joint`: keep which step hit each voxel (`provenance`), and each fused colony
        #: match's scan (body frame) and pose (`colony_scans`); `graph`: the filter's record.
        self.joint = False
        self.provenance: Provenance | None = None
        self.colony_scans: list[tuple[np.ndarray, np.ndarray]] = []
        self.graph: PoseGraph | None = None
        self.height = 0.0  # a 2D scan's height in the body frame
        self.peer_alignment: np.ndarray | None = None  # the last cut's (4x4, peer -> ours)

    def go(
        self,
        peer: Run | None = None,
        rng: int = 0,
        sign: float = 1.0,
        contact: float = 0.5,
        relaxed: str = "none",
        peer_covariance: bool = True,
        before: Callable[[Observation, ScanEstimator], None] | None = None,
        points: str = "centres",
        after: Callable[[Observation, ScanEstimator], None] | None = None,
    ) -> float:
        """Run the path (with `peer`'s map from `contact` of the path on, its alignment off by
        `sign` times `ALIGNMENT_ERROR`, its pose covariance in the cut's if `peer_covariance`,
        as `points` (`PEER_POINTS`); `relaxed`: see `relax`; `before`: called with each
        observation and the estimator before the estimator's step, from the second on;
        `after`: the same after it, as the daemon applies landmarks); the ATE."""
        source = open_source(self.spec, resolution=0.1)
        adapter = source.adapter
        shape = "planar" if adapter.kind == "lidar2d" else "cube"
        grid = VoxelGrid(0.1, block_shape=shape, surface=self.means)
        self.provenance = Provenance(grid.resolution) if self.joint else None
        self.colony_scans = []
        estimator: Any = None
        cut: ColonyMap | None = None
        frames = len(source)
        self.estimates, self.truths, self.covariances, self.times = [], [], [], []
        self.peer_walks = []
        for i, obs in enumerate(source):
            if estimator is None:
                estimator = get_estimator(adapter, obs)
                estimator.localiser.rng = np.random.default_rng(rng)
                if self.smooth and isinstance(estimator, ScanEstimator):
                    estimator.localiser.record = True
                if isinstance(estimator, ScanEstimator):
                    loc = estimator.localiser
                    loc.params = replace(
                        loc.params,
                        colony_walk=self.walk,
                        colony_peer_walk=self.peer_walk,
                        own_aliasing=0.0
                        if estimator.planar
                        else self.aliasing * loc.params.map_cell**2,
                    )
                if self.keyframes is not None:
                    estimator.localiser.local.frames = deque(maxlen=self.keyframes)
                if self.joint and peer is not None and isinstance(estimator, ScanEstimator):
                    self._keep_colony_scans(estimator)
            elif relaxed != "none" and i == 1:
                relax(estimator, relaxed)
            if peer is not None and i >= max(1, int(frames * contact)) and self.estimates:
                pose = self.estimates[-1]
                if cut is None or not cut.covers(pose[:2, 3], cut.radius - 2.0):
                    at = obs.time if peer_covariance else None
                    walk = peer.drift(obs.time) if self.peer_walk else None
                    if self.peer_walk:
                        self.peer_walks.append(
                            None if walk is None else [round(walk.trans, 4), round(walk.yaw, 4)]
                        )
                    cut = peer.cut_for(self, pose, estimator, sign, at, walk, points)
                estimator.colony = cut
            if before is not None and i > 0:
                before(obs, estimator)
            pose = estimator(obs)
            if after is not None and i > 0:
                after(obs, estimator)
            integrate_observation(
                grid,
                replace(obs, pose=pose),
                sensor=adapter.sensor_model,
                reliability=adapter.reliability,
            )
            if self.provenance is not None:
                self.provenance.add_observation(obs, pose, adapter.sensor_model, i)
            if obs.truth is None:
                msg = f"{self.spec}: expected the simulator's truth to evaluate, found none"
                raise ValueError(msg)
            self.estimates.append(pose)
            self.truths.append(obs.truth)
            if isinstance(estimator, ScanEstimator) and estimator.localiser.ekf is not None:
                self.covariances.append(estimator.localiser.ekf.covariance)
                self.times.append(obs.time)
        self.grid = grid
        if isinstance(estimator, ScanEstimator):
            self.mount = estimator.mount
            self.height = estimator.height
            self.graph = estimator.localiser.graph
            self.counts = {k: v for k, v in estimator.counts().items() if k.startswith("colony")}
            if estimator.localiser.graph is not None:
                self.smoothed = self._smoothed(estimator.localiser.graph)
        return absolute_trajectory_error(np.array(self.truths), np.array(self.estimates)).rmse

    def _keep_colony_scans(self, estimator: ScanEstimator) -> None:
        """Keep each colony match the filter fuses (and so its graph records, in order): the
        scan (body frame) and the matched pose (x, y, yaw)."""
        loc = estimator.localiser
        update = loc._colony_update

        def kept(pts: np.ndarray, colony: ColonyMap) -> Any:
            result, fused = update(pts, colony)
            if fused and loc.graph is not None:
                self.colony_scans.append((pts.copy(), se2.from_matrix(result.pose)))
            return result, fused

        setattr(loc, "_colony_update", kept)  # noqa: B010 - an instance's method, harness record

    def _smoothed(self, graph: PoseGraph) -> dict[str, Any]:
        """The graph's smoothed trajectory scored as the online one (sensor poses, ATE after the
        Umeyama fit against the truth: evaluation only), with the solve's cost and time."""
        began = time.process_time()
        result = graph.solve()
        seconds = time.process_time() - began
        poses = np.array([se2.to_matrix(p) @ self.mount for p in result.poses])
        self.smoothed_poses = list(poses)
        ate = absolute_trajectory_error(np.array(self.truths), poses).rmse
        return {
            "ate": round(ate, 4),
            "cpu_s": round(seconds, 2),
            "cost": [round(result.cost_before, 1), round(result.cost_after, 1)],
            "iterations": result.iterations,
            # the last colony offset (x, y in m, yaw in degrees), when there is one
            "offset": [round(float(v), 4) for v in result.offsets[-1][:2]]
            + [round(float(np.degrees(result.offsets[-1][2])), 3)]
            if len(result.offsets)
            else None,
            "edges": graph.edges(),
        }

    def perfect(self) -> None:
        """Diagnostic fixture: this robot's map built from its true poses (its estimates are
        the truth), the best map it could give a peer. No estimator runs."""
        source = open_source(self.spec, resolution=0.1)
        adapter = source.adapter
        shape = "planar" if adapter.kind == "lidar2d" else "cube"
        grid = VoxelGrid(0.1, block_shape=shape, surface=self.means)
        self.estimates, self.truths, self.covariances = [], [], []
        for obs in source:
            if obs.truth is None:
                msg = f"{self.spec}: expected the simulator's truth to build from, found none"
                raise ValueError(msg)
            integrate_observation(
                grid,
                replace(obs, pose=obs.truth),
                sensor=adapter.sensor_model,
                reliability=adapter.reliability,
            )
            self.estimates.append(obs.truth)
            self.truths.append(obs.truth)
        self.grid = grid

    def profile(
        self, every: float, rate: float = 10.0, smoothed: bool = False
    ) -> list[list[float]]:
        """Every `every` seconds of path: [t, true x, true y, fitted error, along, across,
        heading error in degrees] (evaluation only). The fitted error is the ATE's (after the
        Umeyama fit); along / across / heading are the body's error in its own frame from the
        first pose, along and across its true heading. `smoothed`: of the smoothed trajectory."""
        truths = np.array(self.truths)
        estimates = np.array(self.smoothed_poses if smoothed else self.estimates)
        fitted = absolute_trajectory_error(truths, estimates).errors
        frame = self.truths[0] @ np.linalg.inv(estimates[0])
        back, unmount = np.linalg.inv(frame), np.linalg.inv(self.mount)
        rows = []
        for i in range(0, len(truths), max(1, round(every * rate))):
            t = se2.from_matrix(back @ truths[i] @ unmount)
            e = t - se2.from_matrix(estimates[i] @ unmount)
            c, s = np.cos(t[2]), np.sin(t[2])
            rows.append(
                [
                    round(i / rate, 1),
                    round(float(truths[i][0, 3]), 2),
                    round(float(truths[i][1, 3]), 2),
                    round(float(fitted[i]), 3),
                    round(float(c * e[0] + s * e[1]), 3),
                    round(float(-s * e[0] + c * e[1]), 3),
                    round(float(np.degrees(se2.wrap(float(e[2])))), 2),
                ]
            )
        return rows

    def consistency(self) -> dict[str, float]:
        """How honest the filter's covariance was: the body pose error in the robot's own frame
        (truth put there by the first frame, evaluation only) against the covariance the filter
        claimed at each frame. `nees_mean`: mean normalised estimation error squared (3 when
        the covariance is honest, far above when overconfident); `nees_over`: share of frames
        above the 95 % chi-square bound (7.81; 0.05 when honest); `error_m` / `sigma_m`: median
        position error and claimed position standard deviation."""
        if len(self.covariances) != len(self.estimates) or not self.estimates:
            return {}
        frame = self.truths[0] @ np.linalg.inv(self.estimates[0])  # the robot's frame, world
        back, unmount = np.linalg.inv(frame), np.linalg.inv(self.mount)
        nees, errors, sigmas = [], [], []
        for est, truth, cov in zip(self.estimates, self.truths, self.covariances, strict=True):
            e = se2.from_matrix(back @ truth @ unmount) - se2.from_matrix(est @ unmount)
            e[2] = se2.wrap(float(e[2]))
            nees.append(float(e @ np.linalg.solve(cov + 1e-12 * np.eye(3), e)))
            errors.append(float(np.hypot(e[0], e[1])))
            sigmas.append(float(np.sqrt(cov[0, 0] + cov[1, 1])))
        n = np.array(nees[1:] or nees)
        return {
            "nees_mean": round(float(n.mean()), 2),
            "nees_over": round(float((n > 7.81).mean()), 3),
            "error_m": round(float(np.median(errors)), 4),
            "sigma_m": round(float(np.median(sigmas)), 4),
        }

    def drift(self, until: float, every: float = 1.0) -> OffsetWalk | None:
        """This run's drift (`PeerDrift`) from its estimated poses and its filter's covariances
        up to time `until`, one report each `every` seconds (its Pose messages)."""
        drift, last = PeerDrift(), -np.inf
        for t, estimate, cov in zip(self.times, self.estimates, self.covariances, strict=False):
            if t > until:
                break
            if t - last >= every:
                drift.add(se2.from_matrix(estimate), cov)
                last = t
        return drift.walk()

    def cut_for(
        self,
        robot: Run,
        pose: np.ndarray,
        estimator: ScanEstimator,
        sign: float,
        at: float | None = None,
        walk: OffsetWalk | None = None,
        points: str = "centres",
    ) -> ColonyMap:
        """This run's map near `robot`'s pose, in its frame through the fixture alignment; its
        covariance the alignment's, plus (at time `at`) this run's pose covariance then, as the
        error of its map about the cut's centre (`colonymap.peer_map_error`); `walk`: this
        run's drift (`drift`); `points`: its occupied voxels as their centres or (`means`) as
        their surface points (`surfaces`)."""
        assert self.grid is not None, "run the peer first"
        grid = self.grid
        ours = self.truths[0] @ np.linalg.inv(self.estimates[0])  # our frame in the world
        theirs = robot.truths[0] @ np.linalg.inv(robot.estimates[0])
        m = se2.to_matrix(sign * np.array(ALIGNMENT_ERROR)) @ np.linalg.inv(theirs) @ ours
        back = np.linalg.inv(m)
        robot.peer_alignment = m
        if points == "means":
            peer_points = surfaces(grid, m)
        elif points == "centres":
            centres = vk.keys_to_centers(grid.occupied_keys(), grid.resolution)
            peer_points = centres @ m[:3, :3].T + m[:3, 3]
        else:
            msg = f"peer points: expected one of {PEER_POINTS}, found {points!r}"
            raise ValueError(msg)

        def free(points: np.ndarray) -> np.ndarray:
            state = grid.state(points @ back[:3, :3].T + back[:3, 3])
            out: np.ndarray = (state == FREE_STATE) & (state != OCCUPIED)
            return out

        covariance = ALIGNMENT_COVARIANCE
        if at is not None and self.covariances:
            i = int(np.argmin(np.abs(np.array(self.times) - at)))
            covariance = covariance + peer_map_error(self.covariances[i], m, pose[:2, 3])
        planar = estimator.planar
        return colony_map(
            peer_points,
            cell=0.05 if planar else 0.1,
            max_points=50_000 if planar else 20_000,
            planar=planar,
            height=estimator.height,
            centre=pose[:2, 3],
            radius=min(estimator.sensor_range, 30.0) + 2.0,
            sources=("peer",),
            covariance=covariance,
            alignment=b"fixture",
            free=free,
            step=grid.resolution,
            walk=walk,
        )


def quantisation(resolution: float) -> np.ndarray:
    """The covariance (x, y, yaw) a map of voxel centres of `resolution` adds to a pose matched
    against it: a wall's centres are off by one shared fraction of a cell, uniform, so every
    patch of it errs alike and the matcher's many patches do not average it away (yaw: none)."""
    variance = resolution**2 / 12.0
    return np.diag([variance, variance, 0.0])


def joint(
    robot: Run,
    peer: Run,
    count: int = JOINT_NODES,
    peer_inflation: float = 1.0,
    inter_inflation: float = 1.0,
    own: Run | None = None,
    weighting: str = "matcher",
) -> dict[str, Any]:
    """`--joint`: both runs' recorded graphs solved as one (`JointGraph`), `robot`'s fused
    colony matches as inter-robot edges on the `count` steps of `peer` standing for those that
    hit the map cells its matched scan fell on (`Provenance`, `quantile_steps`), the transform's
    prior the cut's alignment with `ALIGNMENT_COVARIANCE`; `peer_inflation`, `inter_inflation`:
    `JointGraph`'s (diagnostics); `own`: the robot's own edges from this run of the same
    steps instead (its alone run: `--joint-alone`), the colony matches still `robot`'s. Both
    smoothed trajectories' ATE (Umeyama fit against the truth: evaluation only), the solve's CPU
    time, cost and edges; `weighting` (`WEIGHTINGS`): how the inter edges are weighted, with
    the factors variance component estimation found."""
    if weighting not in WEIGHTINGS:
        msg = f"joint: expected a weighting of {WEIGHTINGS}, found {weighting!r}"
        raise ValueError(msg)
    graph, record = (robot if own is None else own).graph, peer.graph
    colony = None if robot.graph is None else robot.graph.colony_edges()
    if graph is None or record is None or peer.provenance is None or robot.peer_alignment is None:
        msg = "joint: expected both runs recorded (--smooth) and the peer's map given, found not"
        raise ValueError(msg)
    if robot.graph is None or robot.graph.nodes != graph.nodes:
        msg = "joint: expected the own edges' run to have the colony run's steps, found not"
        raise ValueError(msg)
    m = robot.peer_alignment
    floor = None
    if weighting.startswith("cell"):
        assert peer.grid is not None, "the peer ran"
        floor = quantisation(peer.grid.resolution)
    began = time.process_time()
    solver = JointGraph(
        graph,
        record,
        se2.from_matrix(m),
        ALIGNMENT_COVARIANCE,
        peer_inflation=peer_inflation,
        inter_inflation=inter_inflation,
        inter_floor=floor,
    )
    back = np.linalg.inv(m)
    unmatched = 0
    if colony is not None:
        nodes, poses, information = colony
        if len(nodes) != len(robot.colony_scans):
            msg = f"joint: {len(nodes)} colony edges, {len(robot.colony_scans)} scans kept"
            raise ValueError(msg)
        for node, z, info, (pts, pose) in zip(
            nodes, poses, information, robot.colony_scans, strict=True
        ):
            world = se2.to_matrix(pose)
            seen = pts @ (back @ world)[:3, :3].T + (back @ world)[:3, 3]
            weights = peer.provenance.steps_near(seen, robot.height - float(m[2, 3]))
            steps, w = quantile_steps(weights, count)
            if len(steps) == 0:
                unmatched += 1
                continue
            solver.add_inter(int(node), z, np.linalg.pinv(info, hermitian=True), steps, w)
    result = solver.solve(vce=weighting.endswith("vce"))
    seconds = time.process_time() - began
    ours = np.array([se2.to_matrix(p) @ robot.mount for p in result.robot])
    theirs = np.array([se2.to_matrix(p) @ peer.mount for p in result.peer])
    error = se2.from_matrix(m) - result.transform
    found: dict[str, Any] = {}
    if result.factors:  # the covariance factors variance component estimation settled on
        found = {
            "factors": {k: round(v, 3) for k, v in result.factors.items()},
            "rounds": result.rounds,
        }
    return {
        "lidar": round(absolute_trajectory_error(np.array(robot.truths), ours).rmse, 4),
        "depth": round(absolute_trajectory_error(np.array(peer.truths), theirs).rmse, 4),
        "cpu_s": round(seconds, 2),
        "cost": [round(result.cost_before, 1), round(result.cost_after, 1)],
        "iterations": result.iterations,
        "inter": solver.edges(),
        "unmatched": unmatched,
        # how far the solve moved the transform from the alignment (x, y in m, yaw in degrees)
        "transform_moved": [round(float(v), 4) for v in error[:2]]
        + [round(float(np.degrees(se2.wrap(float(error[2])))), 3)],
        **found,
    }


def _names(allowed: tuple[str, ...]) -> Callable[[str], list[str]]:
    """An argparse type: a comma-separated list of names from `allowed`."""

    def parse(text: str) -> list[str]:
        out = text.split(",")
        for how in out:
            if how not in allowed:
                msg = f"expected comma-separated names of {allowed}, found {how!r}"
                raise argparse.ArgumentTypeError(msg)
        return out

    return parse


_relaxed = _names(RELAXED)
_points = _names(PEER_POINTS)
_weightings = _names(WEIGHTINGS)


def _fractions(text: str) -> list[float]:
    out = [float(x) for x in text.split(",")]
    if not all(0.0 <= x < 1.0 for x in out):
        msg = f"expected comma-separated fractions in [0, 1), found {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return out


def _positives(text: str) -> list[float]:
    out = [float(x) for x in text.split(",")]
    if not all(np.isfinite(x) and x > 0 for x in out):
        msg = f"expected comma-separated positive numbers, found {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.paper_offline")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--lidar-range", type=float, default=4.0)
    parser.add_argument("--rng", type=int, default=0, help="seed of the scans' subsample")
    parser.add_argument(
        "--world",
        choices=("office", "hall"),
        default="office",
        help="the sim world (default office; hall: the sparse one, docs/LOCALISATION.md)",
    )
    parser.add_argument("--duration", type=float, default=DURATION_S, help="seconds of path")
    parser.add_argument(
        "--peer-covariance",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add the peer's pose covariance to its map's (the daemon's colony_peer_pose; "
        "default on, as the daemon's)",
    )
    parser.add_argument(
        "--offset-walk",
        action="store_true",
        help="the colony offset as a random walk with distance (OffsetWalk; off in the daemon)",
    )
    parser.add_argument(
        "--peer-walk",
        action="store_true",
        help="the colony offset's walk from the peer's own drift (PeerDrift; with "
        "--offset-walk, the constant until the peer's reports suffice)",
    )
    parser.add_argument(
        "--own-aliasing",
        type=float,
        default=0.0,
        help="chance of depth-1's own-map match one map cell off, as variance (0: none)",
    )
    parser.add_argument(
        "--smooth",
        action="store_true",
        help="also each run's smoothed trajectory (PoseGraph over what the filter fused): "
        "its ATE, solve CPU time, cost and edges as <run>_smoothed",
    )
    parser.add_argument(
        "--peer-points",
        type=_points,
        default=["centres"],
        help=f"comma-separated, of {PEER_POINTS}: the peer's map as its voxels' centres "
        "(default) or their surface points (the grid's surface channel, as the daemon's "
        "colony map); each, the first's keys plain, the others' with @<name>",
    )
    parser.add_argument(
        "--joint",
        action="store_true",
        help="with --smooth: also both robots' graphs solved as one (JointGraph), lidar-1's "
        "colony matches tied to depth-1's steps that built the matched map: joint_smoothed",
    )
    parser.add_argument(
        "--joint-weighting",
        type=_weightings,
        default=["matcher"],
        help=f"comma-separated, of {WEIGHTINGS}: how a --joint solve weights the inter edges "
        "(default the matcher's covariance; vce: variance component estimation; cell: plus the "
        "peer map's quantisation; cell-vce: both); the first's keys plain, the others' @W",
    )
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    diag = parser.add_argument_group("diagnostics (bounds; truth builds fixtures only)")
    diag.add_argument(
        "--perfect-peer", action="store_true", help="depth-1's map from its true poses"
    )
    diag.add_argument(
        "--contact",
        type=_fractions,
        default=[0.5],
        help="comma-separated fractions of the path before the peer's map",
    )
    diag.add_argument(
        "--relax", type=_relaxed, default=["none"], help=f"comma-separated, of {RELAXED}"
    )
    diag.add_argument("--keyframes", type=int, help="lidar-1's local map size (default 100)")
    diag.add_argument(
        "--lidar-noise", type=float, help="lidar-1's range noise in m (the sim's default 0.01)"
    )
    diag.add_argument(
        "--exact-alignment", action="store_true", help="the peer's map without alignment error"
    )
    diag.add_argument("--lidar-only", action="store_true", help="skip depth-1 with lidar-1's map")
    diag.add_argument(
        "--joint-peer-inflate",
        type=_positives,
        default=[1.0],
        help="comma-separated: depth-1's own edges' covariance times each in a --joint solve "
        "(the first's key plain, the others' @peerF)",
    )
    diag.add_argument(
        "--joint-alone",
        action="store_true",
        help="also a --joint solve with lidar-1's own edges from its alone run (same steps; the "
        "colony matches from its run with the map): @alone",
    )
    diag.add_argument(
        "--joint-inter-inflate",
        type=_positives,
        default=[1.0],
        help="comma-separated: the inter-robot edges' covariance times each in a --joint solve "
        "(the first's key plain, the others' @interF)",
    )
    diag.add_argument("--profile", type=float, help="lidar-1's error every this many seconds")
    args = parser.parse_args(argv)
    if args.joint and (not args.smooth or args.perfect_peer):
        parser.error("--joint needs --smooth and depth-1's estimated map (not --perfect-peer)")

    def robot(agent: str) -> Run:
        seed = 100 * args.seed + (1 if agent == "lidar-1" else 2)
        keyframes = args.keyframes if agent == "lidar-1" else None
        noise = args.lidar_noise if agent == "lidar-1" else None
        walk = OffsetWalk() if args.offset_walk else None
        return Run(
            agent,
            seed,
            args.lidar_range,
            args.duration,
            keyframes,
            noise,
            args.world,
            walk,
            args.peer_walk,
            args.own_aliasing,
            args.smooth,
        )

    lidar, depth = robot("lidar-1"), robot("depth-1")
    lidar.means = depth.means = "means" in args.peer_points
    depth.joint = args.joint
    out: dict[str, Any] = {"seed": args.seed, "lidar_range": args.lidar_range, "rng": args.rng}
    out["peer_covariance"] = args.peer_covariance
    for name in (
        "perfect_peer",
        "contact",
        "relax",
        "keyframes",
        "duration",
        "exact_alignment",
        "lidar_noise",
        "world",
        "offset_walk",
        "peer_walk",
        "own_aliasing",
        "smooth",
        "peer_points",
        "joint",
        "joint_peer_inflate",
        "joint_inter_inflate",
        "joint_alone",
        "joint_weighting",
    ):
        if getattr(args, name) != parser.get_default(name):
            out[name] = getattr(args, name)
    out["lidar_alone"] = round(lidar.go(rng=args.rng), 4)
    out["lidar_alone_consistency"] = lidar.consistency()
    if lidar.smoothed:
        out["lidar_alone_smoothed"] = lidar.smoothed
    if args.profile:
        out["lidar_alone_profile"] = lidar.profile(args.profile)
        if lidar.smoothed_poses:
            out["lidar_alone_smoothed_profile"] = lidar.profile(args.profile, smoothed=True)
    if args.perfect_peer:
        depth.perfect()
    else:
        out["depth_alone"] = round(depth.go(rng=args.rng), 4)
        out["depth_alone_consistency"] = depth.consistency()
        if depth.smoothed:
            out["depth_alone_smoothed"] = depth.smoothed
    for points in [] if args.lidar_only else args.peer_points:
        end = "" if points == args.peer_points[0] else f"@{points}"
        with_lidar = robot("depth-1")
        out[f"depth_with_lidar{end}"] = round(
            with_lidar.go(lidar, rng=args.rng, peer_covariance=args.peer_covariance, points=points),
            4,
        )
        out[f"depth_counts{end}"] = with_lidar.counts
        out[f"depth_with_lidar_consistency{end}"] = with_lidar.consistency()
        if with_lidar.smoothed:
            out[f"depth_with_lidar_smoothed{end}"] = with_lidar.smoothed
        if args.peer_walk:  # lidar-1's drift as depth-1 got it: first and last cut's
            out[f"depth_peer_walk{end}"] = with_lidar.peer_walks[:1] + with_lidar.peer_walks[-1:]
    sign = 0.0 if args.exact_alignment else -1.0
    variants = [(p, c, h) for p in args.peer_points for c in args.contact for h in args.relax]
    for points, contact, how in variants:  # with the same peer run (the first: plain keys)
        tail = "" if (contact, how) == (args.contact[0], args.relax[0]) else f"@{how}@{contact:g}"
        tail += "" if points == args.peer_points[0] else f"@{points}"
        with_depth = robot("lidar-1")
        with_depth.joint = args.joint
        out[f"lidar_with_depth{tail}"] = round(
            with_depth.go(depth, args.rng, sign, contact, how, args.peer_covariance, points=points),
            4,
        )
        out[f"lidar_counts{tail}"] = with_depth.counts
        out[f"lidar_with_depth_consistency{tail}"] = with_depth.consistency()
        if with_depth.smoothed:
            out[f"lidar_with_depth_smoothed{tail}"] = with_depth.smoothed
        inter = args.joint_inter_inflate[0]  # the plain key's and every @peerF's
        weighting = args.joint_weighting[0]  # the plain key's, every @peerF's and @interF's
        for inflate in args.joint_peer_inflate if args.joint else []:
            at = "" if inflate == args.joint_peer_inflate[0] else f"@peer{inflate:g}"
            out[f"joint_smoothed{tail}{at}"] = joint(
                with_depth,
                depth,
                peer_inflation=inflate,
                inter_inflation=inter,
                weighting=weighting,
            )
        if args.joint and args.joint_alone:
            out[f"joint_smoothed{tail}@alone"] = joint(
                with_depth, depth, own=lidar, weighting=weighting
            )
        peer = args.joint_peer_inflate[0]  # every @interF's and @W's
        for inflate in args.joint_inter_inflate[1:] if args.joint else []:
            out[f"joint_smoothed{tail}@inter{inflate:g}"] = joint(
                with_depth, depth, peer_inflation=peer, inter_inflation=inflate, weighting=weighting
            )
        for weighted in args.joint_weighting[1:] if args.joint else []:
            out[f"joint_smoothed{tail}@{weighted}"] = joint(
                with_depth, depth, peer_inflation=peer, inter_inflation=inter, weighting=weighted
            )
        if args.peer_walk:
            out[f"lidar_peer_walk{tail}"] = with_depth.peer_walks[:1] + with_depth.peer_walks[-1:]
        if args.profile:
            out[f"lidar_with_depth_profile{tail}"] = with_depth.profile(args.profile)
            if with_depth.smoothed_poses:
                out[f"lidar_with_depth_smoothed_profile{tail}"] = with_depth.profile(
                    args.profile, smoothed=True
                )
    print_and_append(out, args.json)
    return out


if __name__ == "__main__":
    main()
