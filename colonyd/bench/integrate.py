"""Integration benchmark: our grid against OctoMap (pyoctomap) on identical point clouds."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from colonyd.bench.files import shared_data_dir, write_results
from colonyd.errors import ConfigError
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.sensor import SensorModel

# A furnished room: interior of the outer box, furniture as solid boxes (min corner, max corner).
# Surfaces sit off voxel boundaries (SHIFT) so float32 (OctoMap) and float64 (ours) agree on keys.
SHIFT = np.array([0.0131, 0.0217, 0.0093])
ROOM = (np.array([-4.0, -3.0, 0.0]) + SHIFT, np.array([4.0, 3.0, 2.8]) + SHIFT)
_FURNITURE = [
    (np.array([1.0, -1.0, 0.0]), np.array([2.2, 0.2, 0.75])),  # table
    (np.array([-2.5, 1.5, 0.0]), np.array([-1.5, 2.9, 1.9])),  # cupboard
    (np.array([2.8, 1.8, 0.0]), np.array([3.9, 2.9, 0.5])),  # bed
    (np.array([-0.4, -2.6, 0.0]), np.array([0.3, -1.9, 1.1])),  # chair
    (np.array([-3.2, -1.0, 0.8]), np.array([-2.9, 0.5, 1.6])),  # shelf on the wall
]
FURNITURE = [(lo + SHIFT, hi + SHIFT) for lo, hi in _FURNITURE]


def _ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray, inside: bool) -> np.ndarray:
    """Distance along unit rays d from o to a box's surface (exit when inside), inf if missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    if inside:
        return np.where(tmax > 0, tmax, np.inf)
    hit = (tmax >= np.maximum(tmin, 0.0)) & (tmin > 0)
    return np.where(hit, tmin, np.inf)


def render(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Range along each unit direction from `origin` inside the furnished room."""
    r = _ray_box(origin, dirs, ROOM[0], ROOM[1], inside=True)
    for lo, hi in FURNITURE:
        r = np.minimum(r, _ray_box(origin, dirs, lo, hi, inside=False))
    return r


def camera_pose(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) looking at target."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = position
    return pose


KINECT = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def depth_frame(pose: np.ndarray, k: np.ndarray = KINECT, w: int = 640, h: int = 480, max_depth: float = 5.0,
                noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """A synthetic depth image (metres, 0 = no reading beyond max_depth) of the room."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, dtype=float)], -1).reshape(-1, 3)
    world_dirs = rays @ pose[:3, :3].T
    norms = np.linalg.norm(world_dirs, axis=1)
    rng = render(pose[:3, 3], world_dirs / norms[:, None])
    z = rng / norms
    if noise:
        z = z + np.random.default_rng(seed).normal(scale=noise, size=z.shape) * z * z
    z[~np.isfinite(z) | (z > max_depth)] = 0.0
    return z.reshape(h, w)


def depth_points(depth: np.ndarray, pose: np.ndarray, k: np.ndarray = KINECT) -> np.ndarray:
    """World points of the valid pixels of a depth image."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def lidar2d_scan(origin: np.ndarray, beams: int = 1081, fov: float = math.radians(270), max_range: float = 30.0):
    """A planar scan; returns (endpoints, no_return mask); no-return beams point at max range."""
    a = np.linspace(-fov / 2, fov / 2, beams)
    dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    r = render(origin, dirs)
    nr = ~np.isfinite(r) | (r > max_range)
    r = np.where(nr, max_range, r)
    return origin + dirs * r[:, None], nr


def lidar3d_scan(origin: np.ndarray, rings: int = 64, cols: int = 1024, max_range: float = 30.0,
                 fov_up: float = 2.0, fov_down: float = -24.8):
    """A spinning 3D LiDAR scan in an open courtyard made of the room scaled x6 (points within 30 m)."""
    el = np.radians(np.linspace(fov_down, fov_up, rings))
    az = np.linspace(-math.pi, math.pi, cols, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    scale = np.array([6.0, 6.0, 3.0])
    r = render(origin / scale, dirs / scale)
    # render() works on a unit-direction parameter; rescale distances back to metres.
    r = r * np.linalg.norm(dirs / scale, axis=1) / np.linalg.norm(dirs / scale, axis=1) ** 2
    nr = ~np.isfinite(r) | (r > max_range)
    r = np.where(nr, max_range, r)
    return origin + dirs * r[:, None], nr


@dataclass
class Frame:
    points: np.ndarray
    origin: np.ndarray
    no_return: np.ndarray | None = None


@dataclass
class Scenario:
    name: str
    resolution: float
    max_range: float
    frames: Callable[[], Iterator[Frame]]
    block_shape: str = "cube"  # planar for a 2D scanner's layer, as `colonyd map` chooses
    default: bool = True  # run unless scenarios are named (slow ones are opt-in)


def _synthetic_depth() -> Iterator[Frame]:
    pose = camera_pose(np.array([-3.0, -2.0, 1.4]), np.array([2.0, 1.0, 0.6]))
    depth = depth_frame(pose)
    yield Frame(depth_points(depth, pose), pose[:3, 3].copy())


def _lidar2d() -> Iterator[Frame]:
    origin = np.array([-1.0, 0.5, 0.3123])
    pts, nr = lidar2d_scan(origin)
    yield Frame(pts, origin, nr)


def _lidar3d() -> Iterator[Frame]:
    origin = np.array([0.5, -0.7, 1.8])
    pts, nr = lidar3d_scan(origin)
    yield Frame(pts, origin, nr)


def _redkitchen(shared_data: Path) -> Callable[[], Iterator[Frame]]:
    def frames() -> Iterator[Frame]:
        import cv2

        folder = shared_data / "redkitchen-50" / "frames"
        k = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
        for path in sorted(folder.glob("frame-*.depth.png")):
            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
            raw[(raw == 0) | (raw == 65535)] = 0
            pose = np.loadtxt(str(path).replace(".depth.png", ".pose.txt"))
            yield Frame(depth_points(raw / 1000.0, pose, k), pose[:3, 3].copy())

    return frames


def _carmen(shared_data: Path) -> Callable[[], Iterator[Frame]]:
    def frames() -> Iterator[Frame]:
        from plugins.carmen import CarmenSource

        log = shared_data / "carmen" / "freiburg-079-corrected.log.gz"
        for obs in CarmenSource(log, max_range=CARMEN_RANGE, stop=400, step=4):
            pose = obs.pose
            yield Frame(obs.points @ pose[:3, :3].T + pose[:3, 3], pose[:3, 3].copy(), obs.no_return)

    return frames


#: Range used for the real 2D laser log (its SICK scanner reports up to 80 m).
CARMEN_RANGE = 30.0


def scenarios(shared_data: Path | None) -> list[Scenario]:
    out = [
        Scenario("depth_640x480_0.05", 0.05, 5.0, _synthetic_depth),
        Scenario("depth_640x480_0.10", 0.10, 5.0, _synthetic_depth),
        Scenario("lidar2d_1081_0.05", 0.05, 30.0, _lidar2d, "planar"),
        Scenario("lidar3d_64x1024_0.10", 0.10, 30.0, _lidar3d),
        # OctoMap needs ~1 min and 11 GB for this one, and reading its tree back ~20 min: opt-in.
        Scenario("lidar3d_64x1024_0.05", 0.05, 30.0, _lidar3d, default=False),
    ]
    if shared_data is not None and (shared_data / "redkitchen-50" / "frames").is_dir():
        out.append(Scenario("redkitchen50_0.05", 0.05, 5.0, _redkitchen(shared_data)))
    if shared_data is not None and (shared_data / "carmen" / "freiburg-079-corrected.log.gz").is_file():
        out.append(Scenario("carmen079_100x360_0.05", 0.05, CARMEN_RANGE, _carmen(shared_data), "planar"))
    return out


def octomap_sets(tree, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Finest-level keys of pyoctomap's occupied and free leaves (pruned leaves expanded)."""
    occ: list[np.ndarray] = []
    free: list[np.ndarray] = []
    by_size: dict[int, np.ndarray] = {}
    for leaf in tree.begin_leafs():
        c = np.asarray(leaf.getCoordinate(), dtype=np.float64)
        s = leaf.getSize()
        n = round(s / resolution)
        lo = np.floor((c - s / 2) / resolution + 0.5).astype(np.int64)
        if n not in by_size:
            r = np.arange(n)
            by_size[n] = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        (occ if tree.isNodeOccupied(leaf) else free).append(by_size[n] + lo)
    empty = np.empty((0, 3), dtype=np.int64)
    return (np.concatenate(occ) if occ else empty), (np.concatenate(free) if free else empty)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    pa, pb = vk.pack(a), vk.pack(b)
    inter = np.intersect1d(pa, pb).size
    union = np.union1d(pa, pb).size
    return 1.0 if union == 0 else inter / union


def _time_ours(frames: list[Frame], resolution: float, sensor: SensorModel,
               block_shape: str = "cube") -> tuple[VoxelGrid, list[float]]:
    grid = VoxelGrid(resolution, block_shape=block_shape)
    times = []
    for i, f in enumerate(frames):
        t0 = time.perf_counter()
        grid.integrate(f.points, f.origin, time=float(i), sensor=sensor, no_return=f.no_return)
        times.append((time.perf_counter() - t0) * 1e3)
    return grid, times


def _time_octomap(frames: list[Frame], resolution: float, max_range: float, discretize: bool):
    import pyoctomap

    tree = pyoctomap.OcTree(resolution)
    times = []
    for f in frames:
        pts = f.points
        if f.no_return is not None:
            # OctoMap clears beams longer than max range up to max range: push no-returns beyond it.
            d = pts - f.origin
            pts = np.where(f.no_return[:, None], f.origin + d * 2.0, pts)
        t0 = time.perf_counter()
        tree.insertPointCloud(np.ascontiguousarray(pts), f.origin, max_range, False, discretize)
        times.append((time.perf_counter() - t0) * 1e3)
    return tree, times


#: Timed runs per side and round for a fast single frame, after one untimed run.
BLOCK_RUNS = 3
#: A run slower than this (ms) is timed as it comes, without a warm-up run.
SLOW_RUN_MS = 1000.0


def run_scenario(sc: Scenario, repeats: int) -> dict:
    frames = list(sc.frames())
    sensor = SensorModel(max_range=sc.max_range)
    per_frame = len(frames) > 1
    sides: dict[object, Callable[[], tuple[object, list[float]]]] = {
        "ours": lambda: _time_ours(frames, sc.resolution, sensor, sc.block_shape),
        False: lambda: _time_octomap(frames, sc.resolution, sc.max_range, False),
        True: lambda: _time_octomap(frames, sc.resolution, sc.max_range, True),
    }
    samples: dict[object, list[float]] = {key: [] for key in sides}
    maps: dict[object, tuple[np.ndarray, np.ndarray, float]] = {}  # OctoMap: occupied, free, bytes/node
    grid: VoxelGrid | None = None
    # Rounds alternate the sides so a slow spell of a shared machine slows both alike. In a round
    # each side runs as it would in a running process: a fast single frame gets one untimed run
    # first (the other side's allocations leave cold caches and returned memory behind), then
    # BLOCK_RUNS timed runs; a sequence's frames run back to back, timed per frame. OctoMap's
    # slow default mode on a sequence runs once. Only one OctoMap tree lives at a time: its
    # voxel sets are read from the first round's tree, which is then dropped.
    for r in range(repeats):
        for key, measure in sides.items():
            if per_frame and r > 0 and key is False:
                continue
            built, t = measure()
            first = statistics.median(t)
            if not (per_frame or first > SLOW_RUN_MS):
                built = None
                for _ in range(BLOCK_RUNS):
                    built, t = measure()
                    samples[key].append(t[0])
            else:
                samples[key].append(first)
            if key == "ours":
                grid = built
            elif key not in maps:
                occupied, free = octomap_sets(built, sc.resolution)
                maps[key] = (occupied, free, built.memoryUsage() / max(1, built.size()))
            del built
    assert grid is not None
    ours = samples["ours"]
    octo = {disc: samples[disc] for disc in (False, True)}
    ours_ms = statistics.median(ours)
    best_disc = min((False, True), key=lambda d: statistics.median(octo[d]))
    octomap_ms = statistics.median(octo[best_disc])
    occ, free, per_node = maps[False]  # OctoMap's own default (every ray) is the reference map
    occ_d, free_d, _ = maps[True]
    return {
        "scenario": sc.name,
        "resolution": sc.resolution,
        "block_shape": sc.block_shape,
        "points": int(sum(len(f.points) for f in frames)),
        "frames": len(frames),
        "ours_ms": round(ours_ms, 2),
        "octomap_ms": round(octomap_ms, 2),
        "octomap_mode": "discretize" if best_disc else "default",
        "octomap_default_ms": round(statistics.median(octo[False]), 2),
        "octomap_discretize_ms": round(statistics.median(octo[True]), 2),
        "speedup": round(octomap_ms / ours_ms, 2),
        "occupied_agreement": round(iou(grid.occupied_keys(), occ), 4),
        "free_agreement": round(iou(grid.free_keys(), free), 4),
        "occupied_agreement_discretize": round(iou(grid.occupied_keys(), occ_d), 4),
        "free_agreement_discretize": round(iou(grid.free_keys(), free_d), 4),
        "bytes_per_known_voxel": round(grid.nbytes() / max(1, grid.known_count()), 2),
        "octomap_bytes_per_node": round(per_node, 2),
        "timing": "per-frame median" if per_frame else f"median of {len(ours)} runs",
    }


def run_integrate_bench(out_json: Path, shared_data: Path | None, repeats: int = 5,
                        only: list[str] | None = None) -> list[dict]:
    """Run the default scenarios (or those named in `only`), write the JSON list to out_json and return it."""
    known = scenarios(shared_data_dir(shared_data))
    unknown = sorted(set(only or ()) - {sc.name for sc in known})
    if unknown:
        msg = f"unknown scenario(s) {unknown}; expected some of {[sc.name for sc in known]}"
        raise ConfigError(msg)
    results = [run_scenario(sc, repeats) for sc in known if (sc.name in only if only else sc.default)]
    write_results(out_json, results)
    return results
