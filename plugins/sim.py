"""Simulated source: agents follow waypoint paths in a World; sensors are rendered by ray
casting."""

from __future__ import annotations

import itertools
import math
import time as clock
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
from pydantic import Field

from plugins.adapter import SensorAdapter, load_adapter
from plugins.cctv import CctvCamera, CctvFrame
from plugins.checks import intrinsics_from_fov, pose_matrix
from plugins.depth import DepthFrame
from plugins.errors import SourceSpecError
from plugins.lidar import Cloud, Scan
from plugins.observation import Observation
from plugins.odometry import odometry_noise_of
from plugins.spec import Options, SourceSpec, parse_options
from plugins.stream import SourceContext, StreamStats
from plugins.world import CLASSES, HALL_SCALE, WORLDS, Hits, Marker, World, get_world
from voxel.depth import pixel_rays
from voxel.localisation.odometry import WheelOdometer

#: Camera optical frame (x right, y down, z forward) in a body frame (x forward, y left, z up).
OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)

SENSORS = ("depth", "lidar2d", "lidar3d", "cctv")

#: A robot's body radius in plan (m): a moving agent's path keeps its centre at least this far
#: from every box and cylinder standing on the floor (tests/plugins/test_sim.py checks it).
ROBOT_RADIUS = 0.25


@dataclass(frozen=True)
class AgentSpec:
    """An agent: its sensor, its path (x, y waypoints, looped) or fixed pose, speed and frame
    rate."""

    name: str
    sensor: str
    waypoints: tuple[tuple[float, float], ...] = ()
    fixed: tuple[float, float, float, float, float] | None = None  # x, y, z, yaw, pitch (cctv)
    speed: float = 0.5  # m/s
    turn_rate: float = 1.0  # rad/s, turning in place at waypoints
    rate: float = 10.0  # frames per second
    marker: int = -1  # first of the 4 ArUco marker ids on the robot's sides (-1: none)


def look_at(
    eye: tuple[float, float, float], target: tuple[float, float, float]
) -> tuple[float, float, float, float, float]:
    """(x, y, z, yaw, pitch) of a camera at `eye` looking at `target` (pitch > 0 looks down)."""
    d = np.subtract(target, eye)
    return (*eye, math.atan2(d[1], d[0]), math.atan2(-d[2], math.hypot(d[0], d[1])))


#: The ArUco boards on a robot's four sides: side length, distance from the body's centre, height.
BOARD_LENGTH, BOARD_OFFSET, BOARD_HEIGHT = 0.24, 0.2, 0.7


def robot_markers(agent: AgentSpec) -> dict[int, np.ndarray]:
    """Marker id -> marker-to-body transform (OpenCV's marker frame: x right, y up, z out of the
    board) of the boards on a robot's front, left, back and right; none for agents without."""
    if agent.marker < 0:
        return {}
    out = {}
    for i in range(4):
        a = i * math.pi / 2
        z = np.array([math.cos(a), math.sin(a), 0.0])
        y = np.array([0.0, 0.0, 1.0])
        m = np.eye(4)
        m[:3, :3] = np.column_stack([np.cross(y, z), y, z])
        m[:3, 3] = BOARD_OFFSET * z + [0.0, 0.0, BOARD_HEIGHT]
        out[agent.marker + i] = m
    return out


def boards_at(agent: AgentSpec, body: np.ndarray) -> list[Marker]:
    """The robot's boards as world markers, its body at `body` (4x4, world frame)."""
    boards = []
    for marker_id, m in robot_markers(agent).items():
        w = body @ m
        boards.append(
            Marker(marker_id, tuple(w[:3, 3]), tuple(w[:3, 2]), BOARD_LENGTH, margin=0.15)
        )
    return boards


#: The sim worlds' agents. A moving agent's path keeps its body (a disc of ROBOT_RADIUS) clear
#: of every solid, aiming for 0.3-0.35 m from its centre to the nearest surface; in the office it
#: crosses between the rooms only through the doorway (x = 0, |y| < 0.6), along y = 0.
#: depth-1 and lidar-1 each tour both rooms on overlapping paths (they see common objects and
#: each other's areas); cctv-1 watches the west room's south half, cctv-2 the east room's north.
AGENTS: dict[str, dict[str, AgentSpec]] = {
    "room": {
        "depth-1": AgentSpec(
            "depth-1", "depth", ((-2.0, -2.0), (2.0, -2.0), (2.0, 0.5), (-2.0, 0.0)), marker=20
        ),
        "lidar-1": AgentSpec(
            "lidar-1", "lidar2d", ((-2.4, -2.2), (2.2, -2.2), (2.2, 2.2), (-2.4, 2.2)), marker=24
        ),
        "lidar3d-1": AgentSpec(
            "lidar3d-1",
            "lidar3d",
            ((0.0, -2.0), (1.9, 0.0), (0.0, 2.2), (-2.4, 2.3), (-2.3, 0.0)),
            marker=28,
        ),
        "cctv-1": AgentSpec(
            "cctv-1", "cctv", fixed=look_at((-2.8, -2.8, 2.3), (1.5, 1.5, 0.8)), rate=1.0
        ),
    },
    "office": {
        # North-east past the landmark at (-3, -2) (ahead at the start), east along y = 0
        # through the doorway, up to the east room's north-east, back west above the landmark
        # at (2, 1), through the doorway and west along y = 0.
        "depth-1": AgentSpec(
            "depth-1",
            "depth",
            (
                (-5.0, -2.6),
                (-3.5, -1.4),
                (-1.0, -1.0),
                (-1.0, 0.0),
                (3.0, 0.0),
                (4.9, 1.6),
                (0.8, 1.9),
                (0.8, 0.0),
                (-5.0, 0.0),
            ),
            marker=20,
        ),
        # East along y = 0 through the doorway, round the east room (south-east corner, west of
        # the bin at (5.2, 0.5), its north), back through the doorway and round the west room
        # (its 10 m north wall, above the box at (-3.9, 2.9)).
        "lidar-1": AgentSpec(
            "lidar-1",
            "lidar2d",
            (
                (-5.0, 0.0),
                (-1.0, 0.0),
                (2.5, 0.0),
                (3.3, -1.7),
                (4.9, -2.2),
                (5.0, -0.5),
                (4.3, 1.0),
                (3.5, 2.6),
                (0.8, 2.6),
                (0.8, 0.0),
                (-0.8, 0.0),
                (-0.8, 3.65),
                (-5.0, 3.65),
            ),
            marker=24,
        ),
        "lidar3d-1": AgentSpec(
            "lidar3d-1",
            "lidar3d",
            (
                (-4.0, -3.0),
                (-3.7, -1.5),
                (-0.8, 0.0),
                (0.8, 0.0),
                (2.5, -2.0),
                (4.8, 1.6),
                (3.0, 0.2),
                (0.8, 0.0),
                (-0.8, 0.0),
                (-1.6, -2.7),
            ),
            marker=28,
        ),
        "cctv-1": AgentSpec(
            "cctv-1", "cctv", fixed=look_at((-5.8, -3.8, 2.5), (-2.0, -1.0, 0.8)), rate=1.0
        ),
        "cctv-2": AgentSpec(
            "cctv-2", "cctv", fixed=look_at((5.8, 3.8, 2.5), (2.0, 1.0, 0.8)), rate=1.0
        ),
    },
}


def _scaled(agent: AgentSpec, scale: float) -> AgentSpec:
    """`agent` with its waypoints scaled by `scale` in plan (for a world scaled so)."""
    return replace(agent, waypoints=tuple((x * scale, y * scale) for x, y in agent.waypoints))


# The hall (plugins.world.hall_world: the office scaled by HALL_SCALE in plan, no dividing wall):
# the office's paths and CCTV poses scaled alike (the routes through the doorway kept), so both
# robots tour the same places in the same order, 1.5 times as far apart.
AGENTS["hall"] = {
    **{
        name: _scaled(agent, HALL_SCALE)
        for name, agent in AGENTS["office"].items()
        if agent.sensor != "cctv"
    },
    "cctv-1": AgentSpec(
        "cctv-1",
        "cctv",
        fixed=look_at((-5.8 * HALL_SCALE, -3.8 * HALL_SCALE, 2.5), (-3.0, -1.5, 0.8)),
        rate=1.0,
    ),
    "cctv-2": AgentSpec(
        "cctv-2",
        "cctv",
        fixed=look_at((5.8 * HALL_SCALE, 3.8 * HALL_SCALE, 2.5), (3.0, 1.5, 0.8)),
        rate=1.0,
    ),
}


class Path:
    """Body pose (x, y, yaw) along a looped waypoint path: turn in place, then drive straight.
    Back at the first waypoint it turns to its first heading, so every loop drives forwards as
    the first does."""

    def __init__(
        self, waypoints: tuple[tuple[float, float], ...], speed: float, turn_rate: float
    ) -> None:
        if len(waypoints) < 2:
            msg = f"waypoints: expected at least 2, found {len(waypoints)}"
            raise SourceSpecError(msg)
        pts = [np.asarray(p, np.float64) for p in waypoints] + [
            np.asarray(waypoints[0], np.float64)
        ]
        times, poses = [0.0], []
        yaw = math.atan2(*(pts[1] - pts[0])[::-1])
        poses.append((*pts[0], yaw))
        for a, b in itertools.pairwise(pts):
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            turn = (heading - yaw + math.pi) % (2 * math.pi) - math.pi
            if abs(turn) > 1e-9:
                yaw += turn
                times.append(times[-1] + abs(turn) / turn_rate)
                poses.append((*a, yaw))
            times.append(times[-1] + float(np.linalg.norm(b - a)) / speed)
            poses.append((*b, yaw))
        close = (poses[0][2] - yaw + math.pi) % (2 * math.pi) - math.pi  # to the first heading
        if abs(close) > 1e-9:
            yaw += close
            times.append(times[-1] + abs(close) / turn_rate)
            poses.append((*pts[0], yaw))
        self.times = np.array(times)
        self.poses = np.array(poses)
        self.period = float(self.times[-1])

    def __call__(self, t: float) -> tuple[float, float, float]:
        """(x, y, yaw) at time t (seconds), looping."""
        lap, s = divmod(t, self.period)
        x, y = (np.interp(s, self.times, self.poses[:, i]) for i in range(2))
        yaw = np.interp(s, self.times, self.poses[:, 2]) + lap * (
            self.poses[-1, 2] - self.poses[0, 2]
        )
        return float(x), float(y), float(yaw)


class Odometer:
    """Dead reckoning from noisy body-frame increments: scale noise, heading noise, heading
    drift."""

    def __init__(
        self,
        start: tuple[float, float, float],
        noise: float,
        drift: float,
        rng: np.random.Generator,
    ) -> None:
        self.truth = start
        self.estimate = np.array(start, np.float64)
        self.noise, self.drift, self.rng = noise, drift, rng

    def step(self, truth: tuple[float, float, float]) -> np.ndarray:
        """Advance to the true pose `truth`; returns the odometry estimate (x, y, yaw)."""
        x0, y0, a0 = self.truth
        x1, y1, a1 = truth
        c, s = math.cos(a0), math.sin(a0)
        dx, dy = c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0)
        da = a1 - a0
        dist = math.hypot(dx, dy)
        n = self.rng.normal(size=3)
        dx += n[0] * self.noise * dist
        dy += n[1] * self.noise * dist
        da += n[2] * self.noise * (abs(da) + 0.2 * dist) + self.drift * dist
        x, y, a = self.estimate
        c, s = math.cos(a), math.sin(a)
        self.estimate = np.array([x + c * dx - s * dy, y + s * dx + c * dy, a + da])
        self.truth = truth
        return self.estimate.copy()


@dataclass(frozen=True)
class Rig:
    """A sensor's rendering geometry: ray directions in the sensor frame and how to pack a
    reading."""

    directions: np.ndarray  # (M, 3) sensor frame, unnormalised for cameras (z = 1)
    mount: np.ndarray  # (4, 4) sensor in body frame
    shape: tuple[int, ...]
    K: np.ndarray | None = None  # cameras


def make_rig(sensor: str) -> tuple[Rig, dict[str, Any]]:
    """Ray directions, mount and adapter parameters of a simulated sensor."""
    if sensor in ("depth", "cctv"):
        w, h, fov = (
            (160, 120, math.radians(70)) if sensor == "depth" else (640, 480, math.radians(75))
        )
        K = intrinsics_from_fov(w, h, fov)
        d = pixel_rays(K, w, h)
        if sensor == "depth":
            return Rig(d, pose_matrix(0.1, 0.0, 0.5, 0.0) @ OPTICAL, (h, w), K), {
                "K": K,
                "max_range": 8.0,
            }
        return Rig(d, OPTICAL, (h, w), K), {"K": K, "max_range": 10.0}
    if sensor == "lidar2d":
        n, span = 360, math.radians(270)
        a = -span / 2 + span / (n - 1) * np.arange(n)
        d = np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
        params = {
            "beams": n,
            "angle_min": -span / 2,
            "angle_increment": span / (n - 1),
            "range_max": 12.0,
        }
        return Rig(d, pose_matrix(0.0, 0.0, 0.3, 0.0), (n,)), params
    if sensor == "lidar3d":
        rings, cols = 16, 512
        el = np.radians(np.linspace(-15, 15, rings))[:, None]
        az = np.linspace(-math.pi, math.pi, cols, endpoint=False)[None, :]
        d = np.stack(
            [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)],
            axis=-1,
        )
        return Rig(d.reshape(-1, 3), pose_matrix(0.0, 0.0, 0.8, 0.0), (rings, cols)), {
            "range_max": 30.0
        }
    msg = f"sensor: expected one of {list(SENSORS)}, found {sensor!r}"
    raise SourceSpecError(msg)


def render(
    world: World,
    sensor: str,
    rig: Rig,
    pose: np.ndarray,
    rng: np.random.Generator,
    range_noise: float,
    boards: list[Marker] | None = None,
    hits: Hits | None = None,
) -> Scan | Cloud | DepthFrame | CctvFrame:
    """A raw reading of `sensor` at sensor pose `pose` (world frame), rendered by ray casting;
    `boards`: markers on robots, drawn into camera images only (robots are not in the scene);
    `hits`: the scene's hits of the rig's rays from `pose` when the caller has them (a fixed
    camera's are the same every frame: casting its 640 x 480 rays is most of a frame's work)."""
    directions = rig.directions @ pose[:3, :3].T
    if hits is None:
        hits = world.cast(pose[:3, 3], directions)
    t = hits.t
    if range_noise > 0:
        t = t + rng.normal(scale=range_noise, size=t.shape)
    if sensor == "lidar2d":
        return Scan(ranges=np.where(np.isfinite(t), t, np.inf))
    if sensor == "lidar3d":
        keep = np.isfinite(t)
        incidence = np.abs(
            np.einsum("ij,ij->i", hits.normal[keep], directions[keep])
        )  # Lambertian return
        return Cloud(points=rig.directions[keep] * t[keep, None], intensity=incidence)
    h, w = rig.shape
    depth = (
        np.where(np.isfinite(t), t, np.nan).reshape(h, w).astype(np.float32)
    )  # z = t for z = 1 rays
    assert rig.K is not None  # camera rigs carry their intrinsics
    colour = world.render_colour(rig.K, pose, (h, w), directions, hits, boards)
    if sensor == "depth":
        labels = hits.class_id.reshape(h, w)
        normals = (hits.normal @ pose[:3, :3]).reshape(h, w, 3)
        return DepthFrame(depth=depth, colour=colour, labels=labels, normals=normals)
    return CctvFrame(image=colour, depth=depth)


class SimOptions(Options):
    """Options of `sim:`."""

    world: str = Field("office", description=f"simulated world: {', '.join(sorted(WORLDS))}")
    agent: str = Field(
        "lidar-1",
        description="agent, with its sensor and path: "
        + "; ".join(f"{w}: {', '.join(sorted(a))}" for w, a in sorted(AGENTS.items())),
    )
    seed: int = Field(0, description="seed of the odometry and range noise")
    frames: int = Field(
        100, ge=1, description="frames to deliver (>= 1), at the agent's rate in simulated time"
    )
    noise: float = Field(0.02, description="odometry noise, relative to the distance travelled")
    drift: float = Field(0.0, description="odometry heading drift, radians per metre")
    odometry_noise: str | None = Field(
        None,
        description="wheel odometry noise model instead of noise and "
        "drift: none, low, realistic, high or trans/rot/rot_per_m/scale_bias/"
        "yaw_bias (docs/LOCALISATION.md)",
    )
    range_noise: float = Field(
        0.01, description="range noise of the sensor, metres (standard deviation)"
    )
    start: str = Field(
        "origin",
        description="where pose guesses start: origin (the identity) or "
        "world (the true start pose)",
    )
    realtime: bool = Field(False, description="pace frames at the agent's rate in wall-clock time")
    epoch: float | None = Field(
        None,
        description="shared clock: Unix time at which every agent's path starts; frames are "
        "paced in wall-clock time (late ones skipped, as a moving robot would), observation "
        "times are Unix times, and a CCTV agent sees the robots where they are then",
    )
    keep_late: bool = Field(
        False,
        description="with epoch: deliver the frames a reader is late for, late, instead of "
        "skipping them (every frame is mapped: a loaded machine slows a run down instead of "
        "thinning it out)",
    )
    robots: str = Field(
        "",
        description="'+'-separated robots of this world that a CCTV agent sees (their ArUco "
        "boards), e.g. lidar-1+depth-1; needs epoch",
    )
    lidar_range: float | None = Field(
        None,
        gt=0,
        description="range of a LiDAR agent's sensor in metres (default 12 for 2D, 30 for 3D): "
        "a short-range scanner (e.g. 4) sees little of a room, as cheap ones do",
    )
    markers: bool = Field(
        False,
        description="a depth agent detects the world's ArUco markers in its colour image and "
        "reports them as identified objects (landmarks, docs/LOCALISATION.md)",
    )


class SimSource:
    """Deterministic simulated stream of one agent's observations (seeded), with ground truth.

    Options: `SimOptions` (`colonyd sources`).
    """

    def __init__(
        self,
        *,
        world: str = "office",
        agent: str = "lidar-1",
        seed: int = 0,
        frames: int = 100,
        noise: float = 0.02,
        drift: float = 0.0,
        range_noise: float = 0.01,
        start: str = "origin",
        realtime: bool = False,
        odometry_noise: str | None = None,
        lidar_range: float | None = None,
        markers: bool = False,
        epoch: float | None = None,
        keep_late: bool = False,
        robots: str = "",
        spec: str = "",
    ) -> None:
        self.world = get_world(world)
        agents = AGENTS[self.world.name]
        if agent not in agents:
            msg = f"agent: expected one of {sorted(agents)} in world {world!r}, found {agent!r}"
            raise SourceSpecError(msg)
        if start not in ("origin", "world"):
            msg = f"start: expected 'origin' or 'world', found {start!r}"
            raise SourceSpecError(msg)
        if frames < 1:  # none: an empty map, written as if it were one
            msg = f"frames: expected a whole number >= 1, found {frames}"
            raise SourceSpecError(msg)
        self.agent = agents[agent]
        names = [r for r in robots.split("+") if r]
        unknown = [r for r in names if r not in agents or agents[r].marker < 0]
        if unknown:
            movers = sorted(a for a, s in agents.items() if s.marker >= 0)
            msg = (
                f"robots: expected robots of world {world!r} ({', '.join(movers)}), found {unknown}"
            )
            raise SourceSpecError(msg)
        if names and (self.agent.sensor != "cctv" or epoch is None):
            msg = (
                f"robots: expected a CCTV agent with an epoch, found agent {agent!r}, epoch {epoch}"
            )
            raise SourceSpecError(msg)
        self.robots = [agents[r] for r in names]
        self.epoch, self.keep_late = epoch, keep_late
        self.spec = spec or f"sim:world={world},agent={agent}"
        self.seed, self.frames, self.noise, self.drift = seed, frames, noise, drift
        self.range_noise, self.start, self.realtime = range_noise, start, realtime
        self.odometry_noise = odometry_noise_of(odometry_noise)
        self.rig, params = make_rig(self.agent.sensor)
        params["noise"] = range_noise
        if lidar_range is not None:
            if self.agent.sensor not in ("lidar2d", "lidar3d"):
                msg = f"lidar_range: expected a LiDAR agent, found {agent!r} ({self.agent.sensor})"
                raise SourceSpecError(msg)
            params["range_max"] = float(lidar_range)
        if self.agent.sensor == "cctv":
            assert self.agent.fixed is not None  # every cctv agent is defined with a fixed pose
            x, y, z, yaw, pitch = self.agent.fixed
            params["pose"] = pose_matrix(x, y, z, yaw, pitch) @ OPTICAL
            params["marker_classes"] = {
                m.marker_id: CLASSES["landmark"] for m in self.world.markers
            }
            params["dictionary"] = self.world.dictionary
            if self.world.markers:
                params["marker_length"] = self.world.markers[0].length
            params["agent_markers"] = {
                marker_id: (robot.name, mount, BOARD_LENGTH)
                for robot in self.robots
                for marker_id, mount in robot_markers(robot).items()
            }
        else:
            params["mount"] = self.rig.mount
        if markers:
            if self.agent.sensor != "depth":
                msg = f"markers: expected a depth agent, found {agent!r} ({self.agent.sensor})"
                raise SourceSpecError(msg)
            params["markers"] = self.world.dictionary
            params["marker_classes"] = {
                m.marker_id: CLASSES["landmark"] for m in self.world.markers
            }
            if self.world.markers:
                params["marker_length"] = self.world.markers[0].length
        self.adapter: SensorAdapter = load_adapter(self.agent.sensor, **params)
        self.stats = StreamStats()
        self.ground_truth: list[tuple[float, np.ndarray]] = []

    def __len__(self) -> int:
        return self.frames

    def __iter__(self) -> Iterator[Observation]:
        rng = np.random.default_rng(self.seed)
        agent = self.agent
        fixed = agent.sensor == "cctv"
        path = None if fixed else Path(agent.waypoints, agent.speed, agent.turn_rate)
        start = (0.0, 0.0, 0.0) if path is None else path(0.0)
        odometer = (
            Odometer(start, self.noise, self.drift, rng)
            if self.odometry_noise is None
            else WheelOdometer(np.array(start), self.odometry_noise, rng)
        )
        to_agent = (
            np.eye(4)
            if self.start == "world" or fixed
            else np.linalg.inv(pose_matrix(start[0], start[1], 0.0, start[2]))
        )
        self.ground_truth = []
        robots = [(r, Path(r.waypoints, r.speed, r.turn_rate)) for r in self.robots]
        began = clock.monotonic()
        scene: Hits | None = None
        i = -1
        while i + 1 < self.frames:
            i += 1
            if self.epoch is not None and not self.keep_late:  # a shared clock: where everyone is
                i = max(i, int((clock.time() - self.epoch) * agent.rate))
                if i >= self.frames:
                    break
            if self.epoch is not None:
                while (wait := self.epoch + i / agent.rate - clock.time()) > 0:
                    clock.sleep(min(wait, 0.5))
            t = i / agent.rate
            boards = [
                b
                for robot, (x, y, yaw) in ((r, p(t)) for r, p in robots)
                for b in boards_at(robot, pose_matrix(x, y, 0.0, yaw))
            ]
            if path is None:  # a fixed camera: the adapter loaded for "cctv" is a CctvCamera
                truth_sensor = cast(CctvCamera, self.adapter).pose
                body_guess = None
                odometry = None
                if scene is None:  # the static scene seen from a fixed pose: cast it once
                    rays = self.rig.directions @ truth_sensor[:3, :3].T
                    scene = self.world.cast(truth_sensor[:3, 3], rays)
            else:
                x, y, yaw = path(t)
                estimate = odometer.step((x, y, yaw))
                body_truth = pose_matrix(x, y, 0.0, yaw)
                truth_sensor = body_truth @ self.rig.mount
                body_guess = to_agent @ pose_matrix(estimate[0], estimate[1], 0.0, estimate[2])
                odometry = body_guess
            reading = render(
                self.world,
                agent.sensor,
                self.rig,
                truth_sensor,
                rng,
                self.range_noise,
                boards,
                scene,
            )
            stamp = t if self.epoch is None else self.epoch + t
            obs = self.adapter.observe(
                reading, pose=body_guess, time=stamp, odometry=odometry, frame=f"{self.spec}#{i}"
            )
            obs = _with_truth(obs, truth_sensor)
            self.ground_truth.append((stamp, truth_sensor))
            self.stats.delivered += 1
            if self.realtime and self.epoch is None:
                delay = began + t - clock.monotonic()
                if delay > 0:
                    clock.sleep(delay)
            yield obs


def _with_truth(obs: Observation, truth: np.ndarray) -> Observation:
    return replace(obs, truth=truth)


def open_sim(spec: SourceSpec, context: SourceContext) -> SimSource:
    """The `sim:` source of a parsed spec."""
    return SimSource(
        **parse_options(SimOptions, spec.options, spec.text).model_dump(), spec=spec.text
    )
