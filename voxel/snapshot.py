"""Lossless grid snapshots: an .npz archive wrapped in zstd, with metadata, block keys, channels,
history."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np
import zstandard

from voxel.blocks import BlockStore
from voxel.errors import FileFormatError
from voxel.history import RECORD_DTYPE_V3, RENAMED_V3, History
from voxel.record import RECORD_DTYPE, SEEN_DTYPE

FORMAT = "colony-voxel-snapshot"
FORMAT_VERSION = 4
#: Versions `load_grid` reads; version 2 predates block shapes (its blocks are cubes), versions
#: 2 and 3 history records without the grid version (read as version 0: kept, never served).
READABLE_VERSIONS = (2, 3, 4)
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


class SnapshotGrid(Protocol):
    """What a snapshot holds of a grid (`voxel.grid.VoxelGrid` is one)."""

    resolution: float
    half_life: float | None
    statistics: bool
    surface: bool
    store: BlockStore
    history: History
    version: int
    now: float
    time_base_ms: int | None


G = TypeVar("G", bound=SnapshotGrid)


def save_grid(grid: SnapshotGrid, path: Path) -> None:
    """Write `grid` to `path` atomically (temporary file, fsync, rename).

    The file is a zstd frame around a NumPy .npz archive, so `np.load` cannot open it directly
    whatever its name (`colonyd map` keeps `grid.npz` for existing files and scripts): read it
    with `load_grid`, or decompress it first (`zstandard.ZstdDecompressor().stream_reader(fh)`).
    """
    st = grid.store
    slots = st.used_slots()
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "resolution": grid.resolution,
        "half_life": grid.half_life,
        "statistics": grid.statistics,
        "surface": grid.surface,
        "class_k": st.class_k,
        "block_shape": [1 << x for x in st.shifts],
        "grid_version": grid.version,
        "now": grid.now,
        "time_base_ms": grid.time_base_ms,
        "channels": sorted(st.channels),
        "agents": grid.history.agents,
        "history_capacity": grid.history.capacity,
        "history_per_voxel": grid.history.per_voxel,
    }
    arrays = {
        "meta": np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
        "block_keys": st.slot_keys[slots],
        "slot_version": st.slot_version[slots],
        "history": grid.history.view(),
        "history_seen": grid.history.seen(),
    }
    for name, arr in st.channels.items():
        arrays[f"ch/{name}"] = arr[slots]
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with open(tmp, "wb") as fh:
        with zstandard.ZstdCompressor(level=3).stream_writer(fh, closefd=False) as zfh:
            zfh.write(buf.getbuffer())
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def load_grid(path: Path, make_grid: Callable[..., G]) -> G:
    """Read a snapshot written by `save_grid` into the grid `make_grid(resolution, **settings)`
    returns."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(4)
            if raw != ZSTD_MAGIC:
                msg = (
                    f"{path}: expected a zstd-compressed {FORMAT} file, found leading bytes {raw!r}"
                )
                raise FileFormatError(msg)
            fh.seek(0)
            payload = zstandard.ZstdDecompressor().stream_reader(fh).read()
        with np.load(io.BytesIO(payload), allow_pickle=False) as data:
            files = set(data.files)
            if "meta" not in files:
                msg = (
                    f"{path}: expected a {FORMAT} file with a 'meta' entry, "
                    f"found entries {sorted(files)[:5]}"
                )
                raise FileFormatError(msg)
            meta = json.loads(bytes(data["meta"]).decode())
            if meta.get("format") != FORMAT or meta.get("version") not in READABLE_VERSIONS:
                msg = (
                    f"{path}: expected format {FORMAT} v{'/'.join(map(str, READABLE_VERSIONS))}, "
                    f"found {meta.get('format')!r} v{meta.get('version')!r}"
                )
                raise FileFormatError(msg)
            settings = {"surface": bool(meta["surface"])} if "surface" in meta else {}
            grid = make_grid(
                meta["resolution"],
                half_life=meta["half_life"],
                statistics=meta["statistics"],
                **settings,
                class_k=meta["class_k"],
                history_capacity=meta["history_capacity"],
                history_per_voxel=meta["history_per_voxel"],
                block_shape=tuple(meta.get("block_shape", (4, 4, 4))),
            )
            keys = data["block_keys"]
            slots = grid.store.ensure(keys)
            grid.store.slot_version[slots] = data["slot_version"]
            for name in meta["channels"]:
                arr = data[f"ch/{name}"]
                target = grid.store.channel(name)
                if arr.shape[1:] != target.shape[1:] or arr.shape[0] != keys.shape[0]:
                    msg = (
                        f"{path}: channel {name!r} expected shape ({keys.shape[0]}, "
                        f"{target.shape[1:]}), found {arr.shape}"
                    )
                    raise FileFormatError(msg)
                target[slots] = arr
            hist = data["history"]
            if hist.dtype == RECORD_DTYPE_V3 and meta["version"] < 4:
                old = hist
                hist = np.zeros(old.size, dtype=RECORD_DTYPE)
                for name in RECORD_DTYPE_V3.names or ():
                    hist[RENAMED_V3.get(name, name)] = old[name]
            if hist.dtype != RECORD_DTYPE:
                msg = f"{path}: history records have dtype {hist.dtype}, expected {RECORD_DTYPE}"
                raise FileFormatError(msg)
            seen = data["history_seen"] if "history_seen" in files else None
            if seen is not None and seen.dtype != SEEN_DTYPE:
                msg = f"{path}: seen log has dtype {seen.dtype}, expected {SEEN_DTYPE}"
                raise FileFormatError(msg)
            grid.history.load(hist, meta["agents"], seen)
            grid.version = int(meta["grid_version"])
            grid.now = float(meta["now"])
            grid.time_base_ms = meta["time_base_ms"]
            return grid
    except FileFormatError:
        raise
    except (
        OSError,
        ValueError,
        TypeError,
        KeyError,
        zipfile.BadZipFile,
        json.JSONDecodeError,
        EOFError,
        zstandard.ZstdError,
    ) as exc:
        msg = f"{path}: not a readable {FORMAT} file ({type(exc).__name__}: {exc})"
        raise FileFormatError(msg) from None
