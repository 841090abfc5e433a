"""The worked example of docs/PROTOCOL.md: a three-voxel delta frame, built by this code."""

from __future__ import annotations

import numpy as np

from protocol.codec import encode
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
