"""Write-ahead log bytes per own-delta record: with and without its history, plain, compressed."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from colonyd.bench.files import room_and_carmen, write_results
from colonyd.mapping import integrate_observation
from colonyd.persistence import _HEAD, _delta_record, _record_body
from voxel.grid import VoxelGrid

#: Scans per logged delta: one each (a slow sensor, or a fast publish rate) and one per five (a
#: 2D LiDAR at ~10 Hz published at 2 Hz, the default).
CADENCES = (1, 5)


def _records(spec: str, resolution: float, shape: str, every: int) -> dict[str, Any]:
    """Map `spec` as a daemon's own layer (surface on) and log a delta every `every` scans:
    each record's bytes as written (compressed, with its history), and its plain msgpack bytes
    without and with the history (the records of older colonyds), with the CPU of writing it."""
    from plugins.source import open_source

    grid = VoxelGrid(resolution, block_shape=shape)
    grid.surface = True  # as daemons keep it (Config.surface)
    source = open_source(spec, resolution=resolution)
    plain = with_history = written = records = entries = 0
    cpu = 0.0
    published, seq = 0, 0
    for i, obs in enumerate(source, 1):
        integrate_observation(grid, obs, sensor=source.adapter.sensor_model, reliability=1.0)
        if i % every or grid.version == published:
            continue
        seq += 1
        delta = grid.delta_since(published)
        page = grid.history.since(published, grid.version)
        plain += len(_record_body(_delta_record(seq, delta, None, None)[_HEAD.size :]))
        began = time.process_time()
        record = _delta_record(seq, delta, None, page)
        cpu += time.process_time() - began
        written += len(record) - _HEAD.size
        with_history += len(_record_body(record[_HEAD.size :]))
        entries += page.records.size + page.seen.size
        records += 1
        published = grid.version
    return {
        "scans_per_delta": every,
        "records": records,
        "bytes_per_record_before": plain / records,
        "bytes_per_record_after": with_history / records,
        "bytes_per_record_written": written / records,
        "history_entries_per_record": entries / records,
        "ratio": with_history / plain,
        "written_ratio": written / plain,
        "record_cpu_ms": 1000 * cpu / records,
    }


def run_wal_bench(out_json: Path, shared_data: Path | None) -> list[dict[str, Any]]:
    """Each scenario at each cadence: write-ahead log bytes per record, before and after."""
    results = []
    for name, spec, resolution, shape in room_and_carmen(
        shared_data, 20, ("carmen-079-100", "stop=100")
    ):
        for every in CADENCES:
            began = time.perf_counter()
            result = {"scenario": name, "source": spec, "resolution": resolution}
            result |= _records(spec, resolution, shape, every)
            result["seconds"] = time.perf_counter() - began
            results.append(result)
    write_results(out_json, results)
    return results
