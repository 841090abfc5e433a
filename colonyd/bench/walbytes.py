"""Write-ahead log bytes per own-delta record, with or without history; what zstd makes of it."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import zstandard

from colonyd.bench.files import room_and_carmen, write_results
from colonyd.mapping import integrate_observation
from colonyd.persistence import _HEAD, _delta_record
from voxel.grid import VoxelGrid

#: zstd level of the compression measured (not used by the log: see `_records`), the snapshots'.
ZSTD_LEVEL = 3

#: Scans per logged delta: one each (a slow sensor, or a fast publish rate) and one per five (a
#: 2D LiDAR at ~10 Hz published at 2 Hz, the default).
CADENCES = (1, 5)


def _records(spec: str, resolution: float, shape: str, every: int) -> dict[str, Any]:
    """Map `spec` as a daemon's own layer (surface on) and log a delta every `every` scans:
    each record's bytes as written, without and with its history, and what compressing the
    record (one zstd frame at `ZSTD_LEVEL`) would make of it and cost in CPU. The log does not
    compress: a record is written before its delta is published, so that CPU would be added to
    every delta's propagation (BENCHMARKS.md)."""
    from plugins.source import open_source

    grid = VoxelGrid(resolution, block_shape=shape)
    grid.surface = True  # as daemons keep it (Config.surface)
    source = open_source(spec, resolution=resolution)
    plain = with_history = compressed = records = entries = 0
    cpu = 0.0
    zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_content_size=True)
    published, seq = 0, 0
    for i, obs in enumerate(source, 1):
        integrate_observation(grid, obs, sensor=source.adapter.sensor_model, reliability=1.0)
        if i % every or grid.version == published:
            continue
        seq += 1
        delta = grid.delta_since(published)
        page = grid.history.since(published, grid.version)
        plain += len(_delta_record(seq, delta, None, None))
        record = _delta_record(seq, delta, None, page)
        with_history += len(record)
        began = time.process_time()
        compressed += _HEAD.size + len(zstd.compress(record[_HEAD.size :]))
        cpu += time.process_time() - began
        entries += page.records.size + page.seen.size
        records += 1
        published = grid.version
    return {
        "scans_per_delta": every,
        "records": records,
        "bytes_per_record_before": plain / records,
        "bytes_per_record_after": with_history / records,
        "history_entries_per_record": entries / records,
        "ratio": with_history / plain,
        f"bytes_per_record_zstd{ZSTD_LEVEL}": compressed / records,
        f"zstd{ZSTD_LEVEL}_ratio": compressed / with_history,
        f"zstd{ZSTD_LEVEL}_cpu_ms": 1000 * cpu / records,
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
