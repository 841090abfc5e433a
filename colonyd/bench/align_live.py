"""Live alignment: real daemons on loopback mapping the sim office from unknown start poses.

Each agent's daemon maps `sim:world=...,agent=...` (poses start at the identity: the agents do not
know where they are in the world); the colony aligns their layers and agrees on one colony
frame. The simulator's true start poses are read here only to evaluate: the pairwise error of
the colony frame, the time from an agent's join to its frame being in the colony frame on every
daemon, and the share of the fused map's occupied voxels within one voxel of the true surfaces.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.launcher import LocalColony
from voxel import keys as vk

#: Targets of issue 11.
PAIR_M, PAIR_DEG, ON_SURFACE = 0.10, 2.0, 0.95

DEFAULT_AGENTS = (("office", "depth-1"), ("office", "lidar3d-1"), ("office", "lidar-1"))


def true_start(world: str, agent: str) -> np.ndarray:
    """The sim's true start pose of `agent` (its frame in the world): evaluation only."""
    from plugins.checks import pose_matrix
    from plugins.sim import AGENTS, Path

    spec = AGENTS[world][agent]
    if spec.fixed is not None:
        return np.eye(4)  # fixed agents (cctv) map in the world frame
    x, y, yaw = Path(spec.waypoints, spec.speed, spec.turn_rate)(0.0)
    return pose_matrix(x, y, 0.0, yaw)


def surface_fraction(
    keys: np.ndarray, resolution: float, to_world: np.ndarray, world: str
) -> float:
    """Share of the occupied voxels `keys` (in a frame that `to_world` takes into the world) whose
    voxel or one of its 26 neighbours holds a true surface of `world`."""
    from plugins.world import get_world

    if len(keys) == 0:
        return 0.0
    truth = vk.points_to_keys(get_world(world).surface_points(resolution / 4), resolution)
    truth = np.unique(truth, axis=0)
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near = np.unique(vk.pack((truth[:, None, :] + offsets[None, :, :]).reshape(-1, 3)))
    centres = vk.keys_to_centers(np.asarray(keys, np.int64), resolution)
    moved = centres @ to_world[:3, :3].T + to_world[:3, 3]
    return float(np.isin(vk.pack(vk.points_to_keys(moved, resolution)), near).mean())


def pose_error(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (m) and yaw (deg) of found relative to truth."""
    e = np.linalg.inv(truth) @ found
    return float(np.linalg.norm(e[:3, 3])), abs(math.degrees(math.atan2(e[1, 0], e[0, 0])))


def fused_maps(colony: LocalColony, timeout: float = 30.0) -> dict[str, Any]:
    """Every daemon's fused map (in its colony frame), by agent."""
    from colonyd.export import query_maps

    return {r.agent: r for r in query_maps(colony.session(), colony.namespace, "", timeout)}


def run_live(
    base: Path,
    agents: tuple[tuple[str, str], ...] = DEFAULT_AGENTS,
    *,
    frames: int = 120,
    noise: float = 0.0,
    resolution: float = 0.1,
    align_s: float = 1.0,
    realtime: bool = False,
    timeout: float = 120.0,
    names: tuple[str, ...] | None = None,
    localise: bool = True,
) -> dict[str, Any]:
    """Start one daemon per (world, agent), wait for maps to converge and the colony frame to
    settle, and evaluate. Agents of other worlds than the first agent's are the negatives: they
    must stay out of the colony frame. `localise` False: the daemons map from the sim's
    odometry, no estimator (exact with `noise` 0: its scan matching was most of their CPU)."""
    world = agents[0][0]
    names = names or tuple(f"{w[0]}{i}-{a}" for i, (w, a) in enumerate(agents))
    out: dict[str, Any] = {
        "agents": {n: {"world": w, "agent": a} for n, (w, a) in zip(names, agents, strict=True)},
        "frames": frames,
        "noise": noise,
        "resolution": resolution,
        "align_s": align_s,
        "realtime": realtime,
        "localise": localise,
    }
    positives = [n for n, (w, _) in zip(names, agents, strict=True) if w == world]
    colony = LocalColony(base, colony="alignlive")
    try:
        joined: dict[str, float] = {}
        for name, (w, a) in zip(names, agents, strict=True):
            spec = f"sim:world={w},agent={a},frames={frames},noise={noise}"
            if realtime:
                spec += ",realtime=true"
            d = colony.add(name, [spec], start=False, extra=["--resolution", str(resolution)])
            d.env = {"COLONYD_ALIGN_S": str(align_s), "COLONYD_OBJECTS_S": "0.5"}
            if not localise:
                d.env["COLONYD_LOCALISE"] = "false"
            d.start()
            joined[name] = time.monotonic()
        t0 = time.monotonic()
        aligned_at: dict[str, float] = {}
        converged = False
        reports: list[dict[str, Any]] = []
        while time.monotonic() - t0 < timeout:
            reports = colony.status()
            frames_seen = [r["colony_frame"] for r in reports]
            now = time.monotonic()
            answered = {r["agent"] for r in reports} == set(names)
            everyone = answered and len(frames_seen[0]["agents"]) > 1
            for name in names:  # aligned: in the colony frame of every daemon
                if everyone and all(name in f["agents"] for f in frames_seen):
                    aligned_at.setdefault(name, now)
            if not converged:
                converged = colony.converged()[0] if not colony._still_mapping(None)[0] else False
            # (ends on a round every daemon answered: the figures below read that round)
            settled = answered and all(n in aligned_at for n in positives)
            if converged and settled and _agree(frames_seen):
                break
            time.sleep(0.5)
        out["seconds"] = round(time.monotonic() - t0, 1)
        out["converged"] = converged
        frames_seen = [r["colony_frame"] for r in reports]
        out["same_frame_everywhere"] = _agree(frames_seen)
        frame = frames_seen[0] if frames_seen else {"root": None, "agents": {}}
        out["root"] = frame["root"]
        out["colony_frame_agents"] = sorted(frame["agents"])
        out["join_to_aligned_s"] = {
            n: round(aligned_at[n] - joined[n], 1) if n in aligned_at else None for n in names
        }
        starts = {n: true_start(w, a) for n, (w, a) in zip(names, agents, strict=True)}
        pairs = []
        for i, x in enumerate(positives):
            for y in positives[i + 1 :]:
                if x in frame["agents"] and y in frame["agents"]:
                    found = np.linalg.inv(np.array(frame["agents"][x])) @ np.array(
                        frame["agents"][y]
                    )
                    t_err, yaw_err = pose_error(found, np.linalg.inv(starts[x]) @ starts[y])
                    pairs.append(
                        {"pair": [x, y], "error_m": round(t_err, 4), "error_deg": round(yaw_err, 3)}
                    )
                else:
                    pairs.append({"pair": [x, y], "error_m": None, "error_deg": None})
        out["pairs"] = pairs
        out["attempts"] = {
            r["agent"]: {
                peer: {
                    k: a.get(k)
                    for k in (
                        "aligned",
                        "method",
                        "confidence",
                        "inliers",
                        "ambiguity",
                        "geometric_ambiguity",
                        "objects",
                        "reason",
                    )
                }
                for peer, a in r["alignments"].items()
            }
            for r in reports
        }
        out["negatives_unaligned"] = all(
            n not in f["agents"] for n in names if n not in positives for f in frames_seen
        )
        fused = fused_maps(colony)
        root = fused.get(frame["root"]) if frame["root"] else None
        if root is not None and frame["root"] in starts:
            occupied = root.keys[root.logodds > 0]
            out["fused_layers"] = root.layers
            out["fused_occupied"] = len(occupied)
            out["fused_on_surface"] = round(
                surface_fraction(occupied, root.resolution, starts[frame["root"]], world), 4
            )
        out["targets"] = {"pair_m": PAIR_M, "pair_deg": PAIR_DEG, "on_surface": ON_SURFACE}
        return out
    finally:
        colony.close()


def _agree(frames: list[dict[str, Any]], tol: float = 1e-3) -> bool:
    if not frames:
        return False
    first = frames[0]
    for f in frames[1:]:
        if f["root"] != first["root"] or set(f["agents"]) != set(first["agents"]):
            return False
        for a, t in f["agents"].items():
            if not np.allclose(np.array(t), np.array(first["agents"][a]), atol=tol):
                return False
    return True


def run_align_live_bench(
    out_json: Path,
    *,
    frames: int = 120,
    drifts: tuple[float, ...] = (0.0, 0.02),
    realtime: bool = True,
    timeout: float = 180.0,
    command: str | None = None,
) -> dict[str, Any]:
    """The live scenario with drift-free and default-drift odometry (`noise` of the sim), plus
    a negative agent from another world; writes the JSON result to `out_json`."""
    agents = (*DEFAULT_AGENTS, ("room", "lidar3d-1"))
    runs = []
    for noise in drifts:
        with tempfile.TemporaryDirectory(prefix="align-live-") as tmp:
            runs.append(
                run_live(
                    Path(tmp),
                    agents,
                    frames=frames,
                    noise=noise,
                    realtime=realtime,
                    timeout=timeout,
                )
            )
    summary = [
        {
            "noise": r["noise"],
            "pairs": {"/".join(p["pair"]): [p["error_m"], p["error_deg"]] for p in r["pairs"]},
            "join_to_aligned_s": r["join_to_aligned_s"],
            "fused_on_surface": r.get("fused_on_surface"),
            "same_frame_everywhere": r["same_frame_everywhere"],
            "negatives_unaligned": r["negatives_unaligned"],
        }
        for r in runs
    ]
    result = {"command": command, "summary": summary, "runs": runs}
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(result, indent=2))
    return result
