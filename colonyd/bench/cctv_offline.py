"""The paper experiment's CCTV offline, deterministic: its fixes' error against the sim's truth,
and lidar-1 with its fixes, with the colony maps its alignment brings, or both, separated.

`python -m colonyd.bench.cctv_offline --seed S [--world office|hall] [--duration S] [--lag S]
[--fix-model M] [--peer-points centres,means] [--json FILE]`

cctv-1 renders its view (the experiment's seed; the robots' boards where they are at each
frame's time) and detects the boards as its daemon does; each detection it would send
(confidence >= `MIN_FIX_CONFIDENCE`) is a fix: the body pose in its frame, the covariance
`colonyd.fixes.fix_covariance` gives. Its error against the robot's true pose is printed per
robot (`fix_errors`: evaluation only). Then each robot runs its sim source through its estimator
(as `paper_offline`), and receives the fixes `--lag` seconds after their stamp, as the daemon
applies them: before its frame is aligned with the CCTV's, a fix is a sighting
(`frame_from_sightings` on the robot's own estimates at the stamps, `sightings_covariance`,
the edge offered to the colony frame, `Alignments.colony` with the CCTV as anchor); after, it is
put into the robot's frame (`fix_in_own_frame`) and fused (`ScanLocaliser.fix`). depth-1 runs
first with the fixes (as live; with `alone` among the variants, first without them); lidar-1
then runs four ways: `alone`; `fixes` (fixes fused, no
colony map); `map` (the colony map its alignment brings, depth-1's final map and the CCTV's,
cut and given as the daemon's `ColonyMaps` would from the moment both robots are aligned; the
fixes only align it); `both` (as live); `map-depth` and `map-cctv`: `map` with depth-1's
map alone or the CCTV's alone (`--cctv-map raw`: the CCTV's raw depth points instead of its
voxel centres, a diagnostic; `--peer-points means`: depth-1's and the CCTV's maps as their
occupied voxels' surface points, their grids keeping the grid's `surface` channel, taken as the
daemon's colony map takes a replica's (`paper_offline.surfaces`); comma-separated: each, keys of
the others with `@means`; raw wins over means for the CCTV's map). `--fix-model`: old, the
daemon's fixes; fitted, the daemon's with `fix_covariance`'s fitted model (docs/BENCHMARKS.md
"The CCTV's claimed covariances"); angle, with its angle model ("The fix's claim by the board's
angle"); new and shared, alternatives measured against it (`model_fixes`,
`fix_in_own_frame`'s `count` and `bias`).
Truth renders and evaluates; no estimator reads it.

Not as live: depth-1 gets no colony map (only fixes); lidar-1 gets depth-1's final map (live,
the map as it grows); the CCTV's colour image has no noise and the paths are scripted, so its
fixes are the same in every seed (only the robots' odometry and range noise change).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.alignment import Alignments, ColonyFrame, Edge
from colonyd.bench.files import print_and_append
from colonyd.bench.options import alignment_option, names
from colonyd.bench.paper_offline import PEER_POINTS, Run, surfaces
from colonyd.colonymap import PeerError, alignment_error, cut_error, peer_map_error
from colonyd.estimator import ScanEstimator
from colonyd.fixes import (
    FIX_MODEL,
    YAW_PER_M,
    FixCounter,
    fix_covariance,
    fix_in_own_frame,
    sightings_covariance,
    through,
)
from colonyd.mapping import integrate_observation
from plugins.cctv import CctvCamera
from plugins.observation import AGENT_LABEL, Observation
from plugins.sim import AGENTS, SimSource
from plugins.sim import Path as SimPath
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.localisation import frame_error, se2
from voxel.localisation.colony_map import ColonyMap, colony_map
from voxel.localisation.ekf import PlanarEkf
from voxel.localisation.scan_match import thin
from voxel.localisation.sightings import frame_from_sightings
from voxel.occupancy import FREE_STATE, OCCUPIED

CCTV = "cctv-1"
ROBOTS = ("lidar-1", "depth-1")
#: The daemon's `MIN_FIX_CONFIDENCE` (colonyd.daemon; not imported: it pulls in Zenoh).
MIN_FIX_CONFIDENCE = 0.15
#: The daemon's `SIGHTING_CONFIDENCE` and its colony-map margin (`colonymap.MARGIN_M`).
SIGHTING_CONFIDENCE = 0.5
MARGIN_M = 2.0
#: `--fix-model shared`: the CCTV's systematic position error (m) shared by its fixes (their
#: mean error against the truth, -1.6 / -1.3 cm for lidar-1's, measured here), counted with the
#: alignment's; the k-th fix through one alignment carries k(k+1) times both, so that any
#: number of fixes tells the filter at most once what they share (sum of 1/(k(k+1)) < 1).
SHARED_BIAS = 0.02
VARIANTS = ("alone", "fixes", "map", "both", "map-depth", "map-cctv")


@dataclass(frozen=True)
class Fix:
    """One fix the CCTV would send: the robot's body pose (4x4, the CCTV's frame), its 6x6
    covariance, when, which board, how confident; and the robot's true body pose then (x, y,
    yaw, the CCTV's frame = the world's: evaluation only)."""

    target: str
    stamp: float
    body: np.ndarray
    covariance: np.ndarray
    marker: int
    confidence: float
    range_m: float
    truth: np.ndarray
    incidence: float = 0.0  # the board's normal against the camera's ray (rad)


def cctv_view(
    seed: int,
    duration: float,
    world: str = "office",
    surface: bool = False,
    model: str = FIX_MODEL,
) -> tuple[list[Fix], VoxelGrid, np.ndarray]:
    """cctv-1's fixes over `duration` s of the experiment's seed `seed` (their covariance by
    `fix_covariance`'s `model`), its map (keeping the
    grid's surface channel with `surface`, for `--peer-points means`), and its raw depth points
    near a 2D scanner's height (0-0.6 m), thinned to 2 cm (`--cctv-map raw`)."""
    agents = AGENTS[world]
    frames = max(2, int(agents[CCTV].rate * duration))
    source = SimSource(
        world=world,
        agent=CCTV,
        seed=100 * seed + 3,
        frames=frames,
        epoch=0.0,  # a shared clock long past: no pacing, stamps are path times
        keep_late=True,
        robots="+".join(ROBOTS),
    )
    paths = {r: SimPath(agents[r].waypoints, agents[r].speed, agents[r].turn_rate) for r in ROBOTS}
    grid = VoxelGrid(0.1, surface=surface)
    adapter = source.adapter
    assert isinstance(adapter, CctvCamera)  # cctv-1's
    fixes = []
    raw = []
    for obs in source:
        integrate_observation(grid, obs, sensor=adapter.sensor_model, reliability=1.0)
        pts = obs.points if obs.no_return is None else obs.points[~obs.no_return]
        pts = pts @ obs.pose[:3, :3].T + obs.pose[:3, 3]
        raw.append(thin(pts[np.abs(pts[:, 2] - 0.3) < 0.3], 0.02))
        for det in obs.objects:
            if not det.label.startswith(AGENT_LABEL) or det.probability < MIN_FIX_CONFIDENCE:
                continue
            target = det.label[len(AGENT_LABEL) :]
            body = obs.pose @ det.pose
            ray = body[:2, 3] - obs.pose[:2, 3]  # the daemon's (`_send_fixes`)
            range_m = float(np.linalg.norm(det.pose[:3, 3]))
            incidence = adapter.board_incidence(det)
            fixes.append(
                Fix(
                    target,
                    obs.time,
                    body,
                    fix_covariance(range_m, ray=ray, model=model, incidence=incidence),
                    det.object_id,
                    det.probability,
                    range_m,
                    np.array(paths[target](obs.time)),
                    incidence,
                )
            )
    return fixes, grid, thin(np.concatenate(raw), 0.02) if raw else np.zeros((0, 3))


def model_fixes(fixes: list[Fix], robot: str, model: str) -> list[Fix]:
    """The fixes `robot` gets, in time order: `model` old, every board with the daemon's
    covariance; new and shared, the most confident board per image (two boards of one robot in
    one image are solved from the same moment, their errors alike: as two fixes, the filter
    counts one sighting twice) with a yaw error of `YAW_PER_M` per metre of range."""
    mine = [f for f in fixes if f.target == robot]
    if model not in ("old", "fitted", "angle"):
        best: dict[float, Fix] = {}
        for f in mine:
            if f.stamp not in best or f.confidence > best[f.stamp].confidence:
                best[f.stamp] = f
        mine = [replace(f, covariance=fix_covariance(f.range_m, YAW_PER_M)) for f in best.values()]
    return sorted(mine, key=lambda f: f.stamp)


def fix_errors(fixes: list[Fix]) -> dict[str, float]:
    """Evaluation: the fixes' error against the truth (x, y in the world, yaw) and against the
    covariance they claim: mean error (bias) in x and y, RMS position and yaw errors, the mean
    NEES of position (2 when honest), of yaw (1) and of the whole (3), the largest yaw error."""
    if not fixes:
        return {"n": 0}
    errors, nees_xy, nees_yaw, nees = [], [], [], []
    for f in fixes:
        e = se2.from_matrix(f.body) - f.truth
        e[2] = se2.wrap(float(e[2]))
        cov = frame_error.planar(f.covariance)
        errors.append(e)
        nees_xy.append(float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2])))
        nees_yaw.append(float(e[2] ** 2 / cov[2, 2]))
        nees.append(float(e @ np.linalg.solve(cov, e)))
    err = np.array(errors)
    return {
        "n": len(fixes),
        "images": len({f.stamp for f in fixes}),
        "bias_x_m": round(float(err[:, 0].mean()), 4),
        "bias_y_m": round(float(err[:, 1].mean()), 4),
        "rms_xy_m": round(float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1)))), 4),
        "rms_yaw_deg": round(math.degrees(float(np.sqrt(np.mean(err[:, 2] ** 2)))), 2),
        "max_yaw_deg": round(math.degrees(float(np.abs(err[:, 2]).max())), 2),
        "nees_xy": round(float(np.median(nees_xy)), 2),
        "nees_xy_mean": round(float(np.mean(nees_xy)), 2),
        "nees_yaw_mean": round(float(np.mean(nees_yaw)), 2),
        "nees_mean": round(float(np.mean(nees)), 2),
    }


class Cctv:
    """The daemon's fix path for one robot's run (`Run.go`'s `before`): the fixes delivered
    `lag` s after their stamp, sightings until the robot's frame is aligned with the CCTV's,
    then (if `fuse`) fused; from the moment `peer` (the other robot's run and edge) and this
    robot are both aligned, (if `peer_map`) the colony map of `peer`'s and the CCTV's maps, as
    their voxels' centres or (`points` means) their surface points (`paper_offline.surfaces`:
    both grids must keep the surface channel)."""

    def __init__(
        self,
        robot: str,
        fixes: list[Fix],
        lag: float,
        *,
        fuse: bool = True,
        cctv_grid: VoxelGrid | None = None,
        peer: tuple[str, Run, Edge, float] | None = None,
        model: str = "old",
        cctv_points: np.ndarray | None = None,
        points: str = "centres",
        drift: bool = False,
        state: bool = False,
    ) -> None:
        self.robot = robot
        self.model = model
        self.drift = drift  # the alignment from sightings counts our pose's error then
        self.state = state  # the alignment's error a state of the filter (`alignment_frames`)
        self.estimator: ScanEstimator | None = None
        self.counter = FixCounter()
        self.queue = model_fixes(fixes, robot, model)
        self.lag, self.fuse = lag, fuse
        self.cctv_grid, self.peer = cctv_grid, peer
        self.cctv_points = cctv_points  # the CCTV's surfaces as raw points, not voxel centres
        if points not in PEER_POINTS:
            msg = f"peer points: expected one of {PEER_POINTS}, found {points!r}"
            raise ValueError(msg)
        self.points = points
        self.kept: list[tuple[np.ndarray, np.ndarray]] = []
        self.edge: Edge | None = None
        self.aligned_at: float | None = None
        self.fused = self.refused = self.stale = 0
        self.cut: ColonyMap | None = None
        self.map_from: float | None = None

    def frame(self) -> ColonyFrame:
        alignments = Alignments()
        for edge in (self.edge, None if self.peer is None else self.peer[2]):
            if edge is not None:
                alignments.put(edge)
        return alignments.colony([*ROBOTS, CCTV], anchor=CCTV)

    def __call__(self, obs: Observation, estimator: ScanEstimator) -> None:
        loc = estimator.localiser
        if loc.params.alignment_frames != self.state:
            loc.params = replace(loc.params, alignment_frames=self.state)
        self.estimator = estimator
        while self.queue and self.queue[0].stamp + self.lag <= obs.time - 1e-6:
            fix = self.queue.pop(0)
            frame = self.frame()
            key = self.counter.key(frame, self.robot, CCTV)
            if key is None:
                self._sighted(fix, loc.pose_at(fix.stamp), obs.time, loc.ekf)
                continue
            if not self.fuse:
                continue
            count = 1 if self.model in ("old", "fitted", "angle") else self.counter.next(CCTV, key)
            bias = 0.0
            if self.model == "shared":  # k(k+1): together at most once the shared error
                count, bias = count * (count + 1), SHARED_BIAS
            framed = estimator.framed
            own = fix_in_own_frame(
                frame, self.robot, CCTV, fix.body, fix.covariance, count, bias, not framed
            )
            assert own is not None
            via = through(frame, self.robot, CCTV) if framed else None
            result = estimator.fix(own[0], own[1], fix.stamp, via)
            if result is None:
                self.stale += 1
            elif result:
                self.fused += 1
                self.counter.fused(CCTV, key)
            else:
                self.refused += 1
        if (self.peer is not None or self.cctv_grid is not None) and self.edge is not None:
            self._colony(obs, estimator)

    def _sighted(
        self, fix: Fix, then: np.ndarray | None, now: float, ekf: PlanarEkf | None
    ) -> None:
        if then is None:
            return
        self.kept.append((se2.from_matrix(fix.body), then))
        seen, believed = np.array([a for a, _ in self.kept]), np.array([b for _, b in self.kept])
        fit = frame_from_sightings(seen, believed)
        if not fit.ok:
            return
        drift = None if ekf is None or not self.drift else (then, ekf.covariance)
        cov = sightings_covariance(fit.rmse, fit.spread, believed, drift)
        self.edge = Edge(
            self.robot, CCTV, fit.transform, SIGHTING_CONFIDENCE, len(seen), fit.rmse, cov, now
        )
        self.aligned_at = now
        self.kept.clear()

    def _colony(self, obs: Observation, estimator: ScanEstimator) -> None:
        assert self.edge is not None
        start = self.edge.time if self.peer is None else max(self.peer[3], self.edge.time)
        if obs.time < start:
            return
        self.map_from = start if self.map_from is None else self.map_from
        loc = estimator.localiser
        assert loc.ekf is not None
        pose = loc.ekf.pose
        if self.cut is not None and self.cut.covers(pose[:2], self.cut.radius - MARGIN_M):
            estimator.colony = self.cut
            return
        frame = self.frame()
        to_own = np.linalg.inv(frame.transforms[self.robot])
        peers: list[tuple[str, VoxelGrid, np.ndarray]] = []
        if self.peer is not None:
            name, run = self.peer[0], self.peer[1]
            peers.append((name, _grid(run), to_own @ frame.transforms[name]))
        if self.cctv_grid is not None:
            peers.append((CCTV, self.cctv_grid, to_own @ frame.transforms[CCTV]))
        errors = {}
        for origin, _, m in peers:
            reported = None
            if self.peer is not None and origin == self.peer[0] and self.peer[1].covariances:
                run = self.peer[1]
                i = int(np.argmin(np.abs(np.array(run.times) - obs.time)))
                reported = run.covariances[i]
            posed = np.zeros((3, 3)) if reported is None else peer_map_error(reported, m, pose)
            errors[origin] = PeerError(alignment_error(frame, self.robot, origin), posed, reported)
        centres = np.concatenate([self._points(origin, g, m) for origin, g, m in peers])

        def free(points: np.ndarray) -> np.ndarray:
            known_free = np.zeros(len(points), bool)
            occupied = np.zeros(len(points), bool)
            for _, g, m in peers:
                back = np.linalg.inv(m)
                state = g.state(points @ back[:3, :3].T + back[:3, 3])
                known_free |= state == FREE_STATE
                occupied |= state == OCCUPIED
            out: np.ndarray = known_free & ~occupied
            return out

        self.cut = colony_map(
            centres,
            cell=0.05 if estimator.planar else 0.1,
            max_points=50_000 if estimator.planar else 20_000,
            planar=estimator.planar,
            height=estimator.height,
            centre=pose[:2],
            radius=min(estimator.sensor_range, 30.0) + MARGIN_M,
            sources=tuple(o for o, _, _ in peers),
            covariance=cut_error(errors),
            alignment=b"cctv",
            free=free,
            step=0.1,
        )
        estimator.colony = self.cut

    def _points(self, origin: str, grid: VoxelGrid, to_own: np.ndarray) -> np.ndarray:
        """`origin`'s map in the robot's frame (`to_own`): the CCTV's raw points if given, else
        the occupied voxels' centres or (`points` means) their surface points."""
        if origin == CCTV and self.cctv_points is not None:
            pts = self.cctv_points
        elif self.points == "centres":
            pts = vk.keys_to_centers(grid.occupied_keys(), grid.resolution)
        else:
            return surfaces(grid, to_own)
        out: np.ndarray = pts @ to_own[:3, :3].T + to_own[:3, 3]
        return out


def _grid(run: Run) -> VoxelGrid:
    assert run.grid is not None, "run the peer first"
    return run.grid


def alignment_truth(cctv: Cctv, run: Run) -> dict[str, float] | None:
    """Evaluation: how far the sightings' alignment is from the true transform of the world
    (the CCTV's frame) into the robot's, as a motion about the robot's origin, and at the
    sightings' place (the robot's first pose seen); with `--alignment state`, the error the
    filter estimated for it at the end (x, y, yaw about the robot's origin, the fixes moved by
    it: `PlanarEkf.update_frame`) and its standard deviations."""
    if cctv.edge is None:
        return None
    frame = run.truths[0] @ np.linalg.inv(run.estimates[0])  # the robot's frame in the world
    d = frame_error.difference(np.linalg.inv(frame), cctv.edge.transform)
    cov = frame_error.planar(cctv.edge.covariance)
    ekf = None if cctv.estimator is None else cctv.estimator.localiser.ekf
    state = None if ekf is None else ekf.frame(("alignment", CCTV))
    estimated = {}
    if state is not None:
        sd = np.sqrt(np.diag(state.covariance))
        estimated = {
            "estimated_x_m": round(float(state.value[0]), 4),
            "estimated_y_m": round(float(state.value[1]), 4),
            "estimated_yaw_deg": round(math.degrees(float(state.value[2])), 3),
            "estimated_sd_m": round(float(sd[0]), 4),
            "estimated_yaw_sd_deg": round(math.degrees(float(sd[2])), 3),
        }
    return estimated | {
        "at_s": round(cctv.edge.time, 2),
        "x_m": round(float(d[0]), 4),
        "y_m": round(float(d[1]), 4),
        "yaw_deg": round(math.degrees(float(d[2])), 3),
        "nees": round(float(d @ np.linalg.solve(cov, d)), 2),
        "claimed_sd_m": round(float(np.sqrt(cov[0, 0])), 4),
        "claimed_yaw_deg": round(math.degrees(float(np.sqrt(cov[2, 2]))), 3),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.cctv_offline")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--world", choices=("office", "hall"), default="office")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of path")
    parser.add_argument("--lidar-range", type=float, default=4.0)
    parser.add_argument("--lag", type=float, default=0.5, help="s from a fix's stamp to its use")
    parser.add_argument(
        "--variants",
        type=names(VARIANTS),
        default=",".join(VARIANTS),
        help=f"comma-separated runs of lidar-1, of {VARIANTS}",
    )
    parser.add_argument(
        "--fix-model",
        choices=("old", "fitted", "angle", "new", "shared"),
        default="old",
        help="old: the daemon's fixes (every board, its fix model, the alignment's error in "
        "each); fitted: old with fix_covariance's fitted model; angle: old with its angle model "
        "(the fitted one grown with the board's incidence); new: the most confident board "
        "per image, 1 degree per metre of range in yaw, the k-th fix through one alignment "
        "with k times its error; shared: new, with the camera's bias shared and k(k+1) times",
    )
    parser.add_argument(
        "--cctv-map",
        choices=("voxels", "raw"),
        default="voxels",
        help="diagnostic: the CCTV's map in lidar-1's colony map as its voxels (as "
        "--peer-points says) or as its raw depth points (surfaces not quantised to the voxels)",
    )
    parser.add_argument(
        "--peer-points",
        type=names(PEER_POINTS),
        default="centres",
        help=f"comma-separated, of {PEER_POINTS}: depth-1's and the CCTV's maps as their voxels' "
        "centres (default) or their surface points (the grid's surface channel, as the "
        "daemon's colony map); each, keys of the others with @<name>",
    )
    parser.add_argument(
        "--sightings",
        choices=("residual", "drift"),
        default="residual",
        help="the alignment from sightings claims its fit's residual alone (residual: the "
        "daemon's) or also the robot's own pose error when seen (drift: failed its A/B, "
        "docs/BENCHMARKS.md 'An alignment from sightings counting the robot's drift')",
    )
    alignment_option(parser, "the fixes")
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)
    variants = args.variants
    if args.alignment == "state" and args.fix_model in ("new", "shared"):
        # (their counts and the camera's shared bias ride on the alignment's error per fix)
        parser.error(
            f"--fix-model {args.fix_model}: expected old or fitted with --alignment state (the "
            "alignment's error is then a state, not added to each fix)"
        )
    modes = args.peer_points
    fixes, cctv_grid, cctv_raw = cctv_view(
        args.seed,
        args.duration,
        args.world,
        surface="means" in modes,
        model=args.fix_model if args.fix_model in ("fitted", "angle") else FIX_MODEL,
    )
    out: dict[str, Any] = {"seed": args.seed, "duration": args.duration, "lag": args.lag}
    out["world"] = args.world
    out["fix_model"] = args.fix_model
    out["sightings"] = args.sightings
    out["alignment"] = args.alignment
    state = args.alignment == "state"
    if args.cctv_map != "voxels":
        out["cctv_map"] = args.cctv_map
    if modes != ["centres"]:
        out["peer_points"] = modes
    for robot in ROBOTS:
        out[f"fix_errors_{robot}"] = fix_errors(model_fixes(fixes, robot, args.fix_model))

    def run(agent: str) -> Run:
        seed = 100 * args.seed + (1 if agent == "lidar-1" else 2)
        return Run(agent, seed, args.lidar_range, args.duration, world=args.world)

    if "alone" in variants:  # depth-1 without the fixes, for comparison
        out["depth_alone"] = round(run("depth-1").go(), 4)
    depth = run("depth-1")
    depth.means = "means" in modes
    drift = args.sightings == "drift"
    depth_cctv = Cctv("depth-1", fixes, args.lag, model=args.fix_model, drift=drift, state=state)
    out["depth_with_fixes"] = round(depth.go(before=depth_cctv), 4)
    out["depth_fixes"] = [depth_cctv.fused, depth_cctv.refused, depth_cctv.stale]
    out["depth_alignment"] = alignment_truth(depth_cctv, depth)
    if depth_cctv.edge is None:
        variants = [v for v in variants if v in ("alone", "fixes")]
    runs = [(v, p) for v in variants for p in (["centres"] if v in ("alone", "fixes") else modes)]
    for variant, points in runs:
        lidar = run("lidar-1")
        if variant == "alone":
            out["lidar_alone"] = round(lidar.go(), 4)
            out["lidar_alone_consistency"] = lidar.consistency()
            continue
        key = f"lidar_{variant}" + ("" if points == modes[0] else f"@{points}")
        assert depth_cctv.edge is not None or variant == "fixes"
        peer = (
            None
            if variant in ("fixes", "map-cctv") or depth_cctv.edge is None
            else ("depth-1", depth, depth_cctv.edge, depth_cctv.edge.time)
        )
        hook = Cctv(
            "lidar-1",
            fixes,
            args.lag,
            fuse=variant in ("fixes", "both"),
            cctv_grid=None if variant in ("fixes", "map-depth") else cctv_grid,
            peer=peer,
            model=args.fix_model,
            cctv_points=cctv_raw if args.cctv_map == "raw" else None,
            points=points,
            drift=drift,
            state=state,
        )
        out[key] = round(lidar.go(before=hook), 4)
        out[f"{key}_fixes"] = [hook.fused, hook.refused, hook.stale]
        out[f"{key}_counts"] = lidar.counts
        out[f"{key}_consistency"] = lidar.consistency()
        out[f"{key}_map_from"] = hook.map_from
        out["lidar_alignment"] = alignment_truth(hook, lidar)
    print_and_append(out, args.json)
    return out


if __name__ == "__main__":
    main()
