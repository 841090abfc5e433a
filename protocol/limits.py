"""Decoder limits: the most a single message may make the decoder read or allocate."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    """Upper bounds enforced on every decoded message before anything is allocated for it."""

    #: Largest frame accepted from the network (envelope + body + tag).
    max_message_bytes: int = 32 << 20
    #: Largest body after decompression.
    max_body_bytes: int = 64 << 20
    #: Largest Heartbeat body (before and after decompression): the largest valid one (4096
    #: layers and 4096 forgotten agents of the longest names) packs to ~0.8 MB. A heartbeat's
    #: key is in its body, so this is what a stranger's may make a receiver read.
    max_heartbeat_bytes: int = 1 << 20
    #: Most voxels (exact voxels plus summary cells) in one delta.
    max_voxels: int = 4_000_000
    #: Most voxels a free-space summary may expand to when a receiver expands it.
    max_expanded_voxels: int = 16_000_000
    #: Most channels in one delta, and the longest top-k class list per voxel.
    max_channels: int = 32
    max_class_k: int = 16
    #: Longest string (names, ids) and list (sensors, objects, capabilities) in a message body.
    max_string: int = 256
    max_list: int = 65_536
    #: Largest zstd window a compressed body may ask for.
    max_window_bytes: int = 8 << 20


#: The limits a decoder uses unless given others.
DEFAULT_LIMITS = Limits()
