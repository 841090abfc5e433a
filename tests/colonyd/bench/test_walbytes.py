"""The write-ahead log bytes bench: what a record's history adds and what compression would take
off, on a short simulated run."""

from __future__ import annotations

from colonyd.bench.walbytes import _records
from voxel.record import RECORD_DTYPE, SEEN_DTYPE


def test_the_history_adds_its_entries_bytes_to_each_record() -> None:
    for every in (1, 2):
        r = _records("sim:world=room,agent=depth-1,frames=4", 0.1, "cube", every)
        assert r["records"] == 4 // every and r["ratio"] > 1.0
        added = r["bytes_per_record_after"] - r["bytes_per_record_before"]
        entries = r["history_entries_per_record"]
        # each entry raw (a record 53 bytes, a seen entry 20), plus the field names and table
        assert SEEN_DTYPE.itemsize * entries < added < RECORD_DTYPE.itemsize * entries + 100
        # compressed (measured, not written so): smaller than the record without its history
        assert 0 < r["bytes_per_record_zstd3"] < r["bytes_per_record_before"]
        assert r["zstd3_ratio"] == r["bytes_per_record_zstd3"] / r["bytes_per_record_after"]
        assert r["zstd3_cpu_ms"] > 0
