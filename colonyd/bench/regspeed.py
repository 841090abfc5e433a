"""Registration CPU: a fixed corpus of map pairs aligned by two checkouts (main's and this one), the
results compared field by field and the CPU per `align_clouds` call timed, interleaved.

`python -m colonyd.bench.regspeed build --corpus DIR [--shared-data D]` writes the corpus (sim
office and hall partial maps, CARMEN halves, OctoMap crops, negatives; one .npz per pair);
`record --corpus DIR --out FILE [--code ROOT]` aligns every pair once with the code at ROOT
(default: this checkout) and pickles the results; `compare A B` says which results differ;
`bench --corpus DIR --main ROOT [--branch ROOT] [--repeats N] [--rounds R] [--json FILE]` times
both checkouts in alternating child processes (process CPU per call; median and min per case)
and the CPU a fresh registration process spends importing what registration loads on first use.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parents[2]
#: (name, world, agent A, frames A, agent B, frames B, dof, with objects): the sim pairs, the
#: paper experiment's robots (office and hall) and the tests' office pairs.
SIM_PAIRS = (
    ("office_depth200_lidar3d30_objects", "office", "depth-1", 200, "lidar3d-1", 30, 4, True),
    ("office_depth200_lidar3d30", "office", "depth-1", 200, "lidar3d-1", 30, 4, False),
    ("office_lidar3d120_lidar120_slice", "office", "lidar3d-1", 120, "lidar-1", 120, 4, False),
    ("office_lidar150_depth150_objects", "office", "lidar-1", 150, "depth-1", 150, 4, True),
    ("hall_lidar150_depth150_objects", "hall", "lidar-1", 150, "depth-1", 150, 4, True),
    ("hall_lidar300_depth300_objects", "hall", "lidar-1", 300, "depth-1", 300, 4, True),
    ("hall_depth300_lidar3d150_objects", "hall", "depth-1", 300, "lidar3d-1", 150, 4, True),
)
#: The pass rule's cases: the sim pairs (what a live colony's workers align).
SIM_PREFIXES = ("office_", "hall_")


def sim_map(world: str, agent: str, frames: int) -> tuple[Any, Any]:
    """`agent`'s map of the sim `world` after `frames` frames (noise off), as
    registration takes it: a MapCloud at 0.1 m and its objects as Landmarks."""
    from colonyd.mapping import integrate_observation
    from plugins.source import open_source
    from voxel.grid import VoxelGrid
    from voxel.objects import extract_objects
    from voxel.registration import MapCloud
    from voxel.registration.landmarks import Landmarks

    src = open_source(f"sim:world={world},agent={agent},frames={frames},noise=0", resolution=0.1)
    grid = VoxelGrid(0.1, block_shape="planar" if agent == "lidar-1" else "cube")
    for obs in src:
        integrate_observation(grid, obs, sensor=src.adapter.sensor_model, reliability=1.0)
    d = grid.delta_since(0)
    known = ~np.isnan(d.logodds)
    cloud = MapCloud.from_keys(0.1, d.keys[known], d.logodds[known] >= 0, agent)
    objs = extract_objects(grid, exclude=frozenset({1, 2}), min_voxels=20, link=3.0)
    return cloud, Landmarks.of([(o.class_id, o.position) for o in objs])


def _save(path: Path, a: Any, b: Any, dof: int, oa: Any = None, ob: Any = None) -> None:
    arrays: dict[str, Any] = {"dof": dof}
    for tag, m in (("a", a), ("b", b)):
        arrays[f"{tag}_res"] = m.resolution
        arrays[f"{tag}_occ"] = m.occupied
        if m.known is not None:
            arrays[f"{tag}_known"] = m.known
            arrays[f"{tag}_known_occ"] = m.known_occupied
    for tag, o in (("a", oa), ("b", ob)):
        if o is not None:
            arrays[f"o{tag}_pos"], arrays[f"o{tag}_cls"] = o.positions, o.classes
    np.savez(path, **arrays)


def build(corpus: Path, shared_data: Path | None) -> None:
    """Write every pair of the corpus into `corpus` (one .npz each)."""
    from colonyd.bench.align import (
        OCTOMAP,
        CarmenHalves,
        _bt_cloud,
        _crop_cloud,
        _moved_cloud,
        random_move_2d,
    )
    from colonyd.bench.files import shared_data_dir
    from colonyd.mapping import map_source
    from voxel import keys as vk
    from voxel.octomap_io import read_bt
    from voxel.registration import load_map
    from voxel.registration.transform import rigid

    corpus.mkdir(parents=True, exist_ok=True)
    maps: dict[tuple[str, str, int], tuple[Any, Any]] = {}
    for name, world, ag_a, fr_a, ag_b, fr_b, dof, objects in SIM_PAIRS:
        for key in ((world, ag_a, fr_a), (world, ag_b, fr_b)):
            if key not in maps:
                maps[key] = sim_map(*key)
        (a, oa), (b, ob) = maps[world, ag_a, fr_a], maps[world, ag_b, fr_b]
        _save(corpus / f"{name}.npz", a, b, dof, oa if objects else None, ob if objects else None)
        print("built", name, flush=True)
    data = shared_data_dir(shared_data)
    if data is None:
        print("no shared data: the sim pairs only", flush=True)
        return
    work = Path(tempfile.mkdtemp(prefix="regspeed-"))
    halves = CarmenHalves(data / "carmen/freiburg-079-corrected.log.gz", work, 4)
    a, _ = halves.first()
    for seed in (0, 1):
        b, _, _ = halves.second(random_move_2d(seed))
        _save(corpus / f"carmen_halves_{seed}.npz", a, b, 3)
    bt = read_bt(data / OCTOMAP)
    rng = np.random.default_rng(1000)
    move = rigid(
        rng.uniform(-20, 20),
        rng.uniform(-20, 20),
        rng.uniform(-2, 2),
        yaw=math.radians(rng.uniform(-180, 180)),
    )
    _save(
        corpus / "octomap_crops_0.npz",
        _bt_cloud(bt, 0.0, 0.6, None),
        _bt_cloud(bt, 0.4, 1.0, move),
        4,
    )
    x, y, yaw = random_move_2d(100)
    move = rigid(x, y, yaw=math.radians(yaw))
    out = work / "sim_office"
    map_source("sim:world=office,agent=lidar-1,frames=300", 0.05, out, progress=False)
    office = load_map(out / "grid.npz")
    _save(corpus / "negative_079_vs_sim_office.npz", a, _moved_cloud(office, move), 3)
    assert a.known is not None
    keys = vk.unpack(a.known)
    _save(
        corpus / "negative_079_halves_no_overlap.npz",
        _crop_cloud(a, keys, 0.0, 0.4, None),
        _crop_cloud(a, keys, 0.6, 1.0, move),
        3,
    )
    _save(
        corpus / "negative_octomap_no_overlap.npz",
        _bt_cloud(bt, 0.0, 0.35, None),
        _bt_cloud(bt, 0.65, 1.0, move),
        4,
    )
    print("built the real-data pairs", flush=True)


def _load(path: Path) -> tuple[Any, Any, Any, Any, int]:
    from voxel.registration import MapCloud
    from voxel.registration.landmarks import Landmarks

    z = np.load(path)
    clouds, objects = [], []
    for tag in ("a", "b"):
        known = z.get(f"{tag}_known", None)
        known_occ = z.get(f"{tag}_known_occ", None)
        clouds.append(MapCloud(float(z[f"{tag}_res"]), z[f"{tag}_occ"], known, known_occ, tag))
        objects.append(
            Landmarks(z[f"o{tag}_pos"], z[f"o{tag}_cls"]) if f"o{tag}_pos" in z else None
        )
    return clouds[0], clouds[1], objects[0], objects[1], int(z["dof"])


def _align(path: Path) -> Any:
    from voxel.registration import AlignParams, align_clouds

    a, b, oa, ob, dof = _load(path)
    return align_clouds(a, b, AlignParams(dof=dof), objects_a=oa, objects_b=ob)


def _fields(result: Any) -> dict[str, Any]:
    out = dict(vars(result))
    out.pop("seconds")
    return out


def record(corpus: Path, out: Path) -> None:
    """Align every pair once; pickle {case: the Alignment's fields but its seconds}."""
    results = {p.stem: _fields(_align(p)) for p in sorted(corpus.glob("*.npz"))}
    out.write_bytes(pickle.dumps(results))


def _same(x: Any, y: Any) -> tuple[bool, float]:
    """Bit-identical, and the largest absolute difference of numbers (0 when identical)."""
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        xa, ya = np.asarray(x), np.asarray(y)
        if xa.shape != ya.shape:
            return False, math.inf
        same = bool(np.array_equal(xa, ya, equal_nan=True))
        diff = np.abs(xa.astype(float) - ya.astype(float))
        return same, float(np.nanmax(diff)) if diff.size and not same else 0.0
    if isinstance(x, float) and isinstance(y, float):
        same = x == y or (math.isnan(x) and math.isnan(y))
        return same, 0.0 if same else abs(x - y)
    return x == y, 0.0 if x == y else math.inf


def compare(path_a: Path, path_b: Path) -> list[str]:
    """Lines naming every field that differs between two recordings (empty: bit-identical)."""
    ra, rb = pickle.loads(path_a.read_bytes()), pickle.loads(path_b.read_bytes())
    lines = []
    if set(ra) != set(rb):
        lines.append(f"cases differ: {sorted(set(ra) ^ set(rb))}")
    for case in sorted(set(ra) & set(rb)):
        for key in ra[case]:
            same, diff = _same(ra[case][key], rb[case].get(key))
            if not same:
                lines.append(f"{case}.{key}: max abs diff {diff:.3g}")
    return lines


#: A child's preamble: the checkout at `root` first on the path, this file loaded by its path (a
#: checkout of main has no copy of it).
_BOOT = """
import importlib.util, json, pathlib, sys, time
sys.path.insert(0, {root!r})
spec = importlib.util.spec_from_file_location("regspeed", {me!r})
rs = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rs)
"""

_TIMER = """
print(json.dumps(rs._align_timed(pathlib.Path({corpus!r}), {repeats})))
"""

_IMPORTS = """
t0 = time.process_time()
import voxel.registration
t1 = time.process_time()
path = pathlib.Path({case!r})
t2 = time.process_time(); rs._align(path); t3 = time.process_time(); rs._align(path)
t4 = time.process_time()
print(json.dumps({{"package": t1 - t0, "first_call": t3 - t2, "second_call": t4 - t3,
                   "scipy.ndimage": "scipy.ndimage" in sys.modules}}))
"""


def _align_timed(corpus: Path, repeats: int) -> dict[str, list[float]]:
    """CPU seconds (process time) of each pair's `align_clouds` call, `repeats` times, after one
    untimed call of each (imports and caches warm)."""
    cases = sorted(corpus.glob("*.npz"))
    from voxel.registration import AlignParams, align_clouds

    loaded = {p.stem: _load(p) for p in cases}
    out: dict[str, list[float]] = {k: [] for k in loaded}
    for rep in range(repeats + 1):
        for k, (a, b, oa, ob, dof) in loaded.items():
            t0 = time.process_time()
            align_clouds(a, b, AlignParams(dof=dof), objects_a=oa, objects_b=ob)
            if rep:
                out[k].append(time.process_time() - t0)
    return out


def _child(root: str, script: str) -> dict[str, Any]:
    boot = _BOOT.format(root=root, me=str(Path(__file__).resolve()))
    done = subprocess.run(
        [sys.executable, "-c", boot + script], capture_output=True, text=True, check=True, cwd="/"
    )
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def bench(
    corpus: Path,
    main_root: Path,
    repeats: int,
    rounds: int,
    import_case: str,
    branch_root: Path = HERE,
) -> dict[str, Any]:
    """CPU per call of both checkouts, alternating child processes, `rounds` each."""
    roots = {"main": str(main_root.resolve()), "branch": str(branch_root.resolve())}
    times: dict[str, dict[str, list[float]]] = {"main": {}, "branch": {}}
    imports: dict[str, list[dict[str, Any]]] = {"main": [], "branch": []}
    for r in range(rounds):
        for side in ("main", "branch") if r % 2 == 0 else ("branch", "main"):
            got = _child(roots[side], _TIMER.format(corpus=str(corpus), repeats=repeats))
            for case, v in got.items():
                times[side].setdefault(case, []).extend(v)
            imports[side].append(
                _child(roots[side], _IMPORTS.format(case=str(corpus / f"{import_case}.npz")))
            )
            print(f"round {r} {side} done", flush=True)
    cases = {}
    for case in sorted(times["main"]):
        m, b = times["main"][case], times["branch"][case]
        cases[case] = {
            "main_median_s": round(statistics.median(m), 4),
            "main_min_s": round(min(m), 4),
            "branch_median_s": round(statistics.median(b), 4),
            "branch_min_s": round(min(b), 4),
            "median_change": round(statistics.median(b) / statistics.median(m) - 1.0, 3),
            "samples": len(m),
        }
    sim = [c for c in cases if c.startswith(SIM_PREFIXES)]
    sim_main = sum(cases[c]["main_median_s"] for c in sim)
    sim_branch = sum(cases[c]["branch_median_s"] for c in sim)
    import_summary = {
        side: {
            key: round(statistics.median(float(x[key]) for x in v), 4)
            for key in ("package", "first_call", "second_call")
        }
        | {
            "first_call_extra": round(
                statistics.median(float(x["first_call"] - x["second_call"]) for x in v), 4
            ),
            "scipy.ndimage": v[0]["scipy.ndimage"],
        }
        for side, v in imports.items()
    }
    return {
        "repeats": repeats,
        "rounds": rounds,
        "cases": cases,
        "sim_median_sum_main_s": round(sim_main, 4),
        "sim_median_sum_branch_s": round(sim_branch, 4),
        "sim_change": round(sim_branch / sim_main - 1.0, 3),
        "imports": import_summary,
        "import_case": import_case,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("build")
    p.add_argument("--corpus", type=Path, required=True)
    p.add_argument("--shared-data", type=Path, default=None)
    p = sub.add_parser("record")
    p.add_argument("--corpus", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--code", type=Path, default=None)
    p = sub.add_parser("compare")
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p = sub.add_parser("bench")
    p.add_argument("--corpus", type=Path, required=True)
    p.add_argument("--main", type=Path, required=True)
    p.add_argument("--branch", type=Path, default=HERE, help="default: this checkout")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--import-case", default="office_lidar150_depth150_objects")
    p.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.cmd == "build":
        build(args.corpus, args.shared_data)
    elif args.cmd == "record":
        if args.code is not None:
            boot = _BOOT.format(root=str(args.code.resolve()), me=str(Path(__file__).resolve()))
            script = (
                f"rs.record(pathlib.Path({str(args.corpus.resolve())!r}), "
                f"pathlib.Path({str(args.out.resolve())!r}))"
            )
            subprocess.run([sys.executable, "-c", boot + script], check=True, cwd="/")
        else:
            record(args.corpus, args.out)
    elif args.cmd == "compare":
        lines = compare(args.a, args.b)
        print("\n".join(lines) if lines else "identical: every field of every case")
        sys.exit(1 if lines else 0)
    else:
        result = bench(
            args.corpus, args.main, args.repeats, args.rounds, args.import_case, args.branch
        )
        result["command"] = "python -m colonyd.bench.regspeed " + " ".join(sys.argv[1:])
        text = json.dumps(result, indent=1)
        print(text)
        if args.json is not None:
            args.json.write_text(text + "\n")


if __name__ == "__main__":
    main()
