"""The columns of a history record and of the seen log (numpy dtypes)."""

from __future__ import annotations

import numpy as np

#: Columns of a history record, in storage order.
RECORD_DTYPE = np.dtype(
    [
        ("key", np.int64),  # packed voxel key
        ("time", np.float64),
        ("agent", np.uint16),  # index into History.agents
        ("sensor", np.uint8),  # voxel.sensor.SENSOR_KINDS code
        ("evidence", np.float32),  # log-odds update applied
        ("logodds", np.float32),  # log-odds after the update
        ("state", np.int8),  # -1 unknown, 0 free, 1 occupied, after the update
        ("flip", np.bool_),  # the state changed with this record
        ("object_id", np.int32),  # -1 when none
        ("object_prob", np.float32),
        ("error", np.float32),  # e: the agent's pose error estimate at integration, metres
        ("reliability", np.float32),  # r: sensor model x the agent's configured reliability
        ("bias", np.float32),  # b: the agent's bias estimate (docs/VOXEL.md, "Provenance")
        ("version", np.uint32),  # the origin grid's version that made the record (one per scan)
    ]
)
#: Entries of the seen log: a voxel that went unknown -> free, and the scan that saw it.
SEEN_DTYPE = np.dtype([("key", np.int64), ("time", np.float64), ("version", np.uint32)])
