"""History benchmark: history bytes per record on the wire, replica temporal queries against the
origin's on sampled (voxel, t) pairs, and allocated bytes after forgetting."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import room_and_carmen, write_results
from colonyd.mapping import integrate_observation
from protocol.codec import decode, encode
from protocol.limits import Limits
from protocol.messages import HistoryReply
from voxel import keys as vk
from voxel.grid import VoxelGrid

#: Decoder limits for the benchmark's large pages.
BENCH_LIMITS = Limits(max_message_bytes=1 << 30, max_body_bytes=1 << 30)
#: Records per page, as the daemon's server sends them at most.
PAGE_RECORDS = 200_000


def _origin(spec: str, resolution: float, block_shape: str) -> VoxelGrid:
    from plugins.source import open_source

    grid = VoxelGrid(resolution, block_shape=block_shape)
    source = open_source(spec, resolution=resolution)
    for obs in source:
        integrate_observation(
            grid, obs, sensor=source.adapter.sensor_model, reliability=1.0, agent="origin"
        )
    return grid


def _replicate(origin: VoxelGrid) -> tuple[VoxelGrid, int, int, int]:
    """A replica that takes the origin's content as a delta and its history page by page as
    HistoryReply frames (encoded, decoded); returns it, frames, frame bytes and records."""
    replica = VoxelGrid(origin.resolution, block_shape="cube")
    replica.apply(origin.delta_since(0))
    after, frames, nbytes, records = 0, 0, 0, 0
    while True:
        page, to, more = origin.history.page(after, PAGE_RECORDS)
        msg = HistoryReply(
            origin="origin", time=time.time(), layer="origin", request_id=1, layer_epoch=1,
            from_version=after, to_version=to, more=more, records=page,
        )  # fmt: skip
        frame = encode(msg)
        back = decode(frame, limits=BENCH_LIMITS)
        assert isinstance(back, HistoryReply)
        if back.records is not None:
            replica.history.merge(back.records)
        frames, nbytes, records = (
            frames + 1,
            nbytes + len(frame),
            records + page.records.size + page.seen.size,
        )
        after = to
        if not more:
            return replica, frames, nbytes, records


def _compare(origin: VoxelGrid, replica: VoxelGrid, pairs: int, seed: int) -> dict[str, Any]:
    """state_at on random (voxel, t) pairs and changed_between on random windows, both grids."""
    rng = np.random.default_rng(seed)
    rec = origin.history.view()
    t0, t1 = float(rec["time"].min()), float(rec["time"].max())
    keys = vk.unpack(rng.choice(np.unique(rec["key"]), size=pairs))
    times = rng.uniform(t0 - 1.0, t1 + 1.0, size=pairs)
    centres = vk.keys_to_centers(keys, origin.resolution)
    equal = 0
    for t in np.unique(np.round(times, 1)):  # one query per distinct time, all its voxels
        sel = np.round(times, 1) == t
        a, b = origin.state_at(centres[sel], float(t)), replica.state_at(centres[sel], float(t))
        equal += int(np.count_nonzero(a == b))
    windows, same = 50, 0
    for _ in range(windows):
        lo, hi = np.sort(rng.uniform(t0 - 1.0, t1 + 1.0, size=2))
        a = vk.pack(origin.changed_between(lo, hi))
        b = vk.pack(replica.changed_between(lo, hi))
        same += int(np.array_equal(np.sort(a), np.sort(b)))
    return {
        "pairs": pairs,
        "state_at_equal": equal / pairs,
        "changed_between_windows": windows,
        "changed_between_equal": same / windows,
    }


def _forgetting(origin: VoxelGrid) -> dict[str, Any]:
    """Forget every voxel but those of the newest tenth of the time span: allocated bytes."""
    grid = origin
    rec = grid.history.view()
    t0, t1 = float(rec["time"].min()), float(rec["time"].max())
    known = grid.known_count()
    before = grid.allocated_bytes()
    replica = VoxelGrid(grid.resolution, block_shape="cube")
    replica.apply(grid.delta_since(0))
    seen = grid.version
    grid.forget(now=t1, after=(t1 - t0) * 0.1)
    replica.apply(grid.delta_since(seen))
    grid.settle(grid.version)
    return {
        "known_before": known,
        "known_after": grid.known_count(),
        "forgotten_share": 1 - grid.known_count() / max(known, 1),
        "allocated_before": before,
        "allocated_after": grid.allocated_bytes(),
        "allocated_drop": 1 - grid.allocated_bytes() / before,
        "replica_equal": replica.content_equal(grid),
    }


def run_history_bench(out_json: Path, shared_data: Path | None) -> list[dict[str, Any]]:
    """Each scenario: map a source, replicate content and history through frames, compare
    temporal queries, then forget and measure allocated bytes."""
    results = []
    for name, spec, resolution, shape in room_and_carmen(
        shared_data, 8, ("carmen-079-step20", "step=20")
    ):
        began = time.perf_counter()
        origin = _origin(spec, resolution, shape)
        replica, frames, nbytes, records = _replicate(origin)
        result: dict[str, Any] = {
            "scenario": name,
            "source": spec,
            "resolution": resolution,
            "history_records": records,
            "history_frames": frames,
            "history_bytes_per_record": nbytes / max(records, 1),
            **_compare(origin, replica, pairs=20_000, seed=1),
            "forgetting": _forgetting(origin),
            "seconds": time.perf_counter() - began,
        }
        results.append(result)
    write_results(out_json, results)
    return results
