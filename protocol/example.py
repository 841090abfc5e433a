"""The worked example of docs/PROTOCOL.md: a three-voxel delta frame, built by this code."""

from __future__ import annotations

import msgpack
import numpy as np

from protocol.codec import encode
from protocol.deltacodec import encode_delta
from protocol.messages import VoxelDelta
from voxel.delta import Delta

#: Colony key of the authenticated variant of the example (32 ASCII bytes).
EXAMPLE_KEY = b"0123456789abcdef0123456789abcdef"


def example_message() -> VoxelDelta:
    """Robot "r1" reports three voxels of one block: one became occupied, two are free."""
    delta = Delta(
        resolution=0.05,
        from_version=41,
        to_version=42,
        keys=np.array([[2, 3, 4], [2, 3, 3], [2, 3, 2]]),
        logodds=np.array([0.85, -0.4, -0.4], dtype=np.float32),
        last_time=np.array([1_700_000_000.5, 1_700_000_000.5, 1_700_000_000.25]),
        channels={"hits": np.array([1, 0, 0], dtype=np.uint16)},
        time=1_700_000_000.5,
    )
    return VoxelDelta(
        origin="r1", epoch=1, seq=7, time=1_700_000_000.5, frame_id="map", delta=delta
    )


def example_frame(key: bytes | None = None) -> bytes:
    """The example message as an uncompressed frame (authenticated with `key` if given)."""
    return encode(example_message(), key=key, compression="none")


def hexdump(data: bytes, width: int = 16) -> str:
    """Offset + hex bytes, `width` per line."""
    return "\n".join(f"{i:04x}  {data[i : i + width].hex(' ')}" for i in range(0, len(data), width))


def example_surface_delta() -> Delta:
    """The example's delta with surface codes (16, -32, 127) carried for voxel (2, 3, 4) alone:
    the free voxels' codes did not change since version 41 (PROTOCOL.md §6, `surface`)."""
    delta = example_message().delta
    codes = np.array([[16, -32, 127], [0, 0, 0], [0, 0, 0]], dtype=np.int8)
    return Delta(
        resolution=delta.resolution,
        from_version=delta.from_version,
        to_version=delta.to_version,
        keys=delta.keys,
        logodds=delta.logodds,
        last_time=delta.last_time,
        channels={**delta.channels, "surface": codes},
        time=delta.time,
        surface_mask=np.array([True, False, False]),
    )


def example_surface_channel() -> bytes:
    """The msgpack bytes of `example_surface_delta`'s `surface` channel entry, as encoded."""
    body = msgpack.unpackb(encode_delta(example_surface_delta()))
    entry = next(e for e in body["ch"] if e[0] == "surface")
    out: bytes = msgpack.packb(entry)
    return out
