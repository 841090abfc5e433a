"""Shared builders for protocol tests: small deltas and one valid message of every type."""

from __future__ import annotations

import numpy as np

from protocol.messages import (
    AlignOffer,
    Announce,
    DeltaRangeReply,
    DeltaRangeRequest,
    Heartbeat,
    HistoryReply,
    HistoryRequest,
    LayerVersion,
    Message,
    ObjectCentroid,
    Objects,
    Pose,
    PoseFix,
    SensorInfo,
    SnapshotReply,
    SnapshotRequest,
    VoxelDelta,
)
from voxel.delta import Delta
from voxel.history import HistoryPage
from voxel.sensor import SensorModel

KEY = b"colony-test-key-0123456789abcdef"


def make_delta(
    rng: np.random.Generator,
    n: int = 200,
    *,
    spread: int = 40,
    channels: bool = True,
    time: float = 1000.0,
    resolution: float = 0.05,
) -> Delta:
    """A delta of up to `n` unique random voxels with mixed occupied/free/unknown values."""
    keys = np.unique(rng.integers(-spread, spread, size=(n, 3)), axis=0)
    rng.shuffle(keys)
    m = keys.shape[0]
    lo = rng.uniform(-2.0, 3.5, size=m).astype(np.float32)
    lo[rng.random(m) < 0.05] = np.nan
    last = time - rng.integers(0, 5, size=m) * 0.1
    ch: dict[str, np.ndarray] = {}
    if channels:
        ch = {
            "first_time": last - 3.0,
            "hits": rng.integers(0, 1000, size=m),
            "misses": rng.integers(0, 1000, size=m),
            "colour": rng.integers(0, 256, size=(m, 3)),
            "normal": rng.normal(size=(m, 3)),
            "class_ids": rng.integers(-1, 50, size=(m, 3)),
            "class_probs": rng.random(size=(m, 3)),
            "scalar:temperature": rng.normal(20, 5, size=m),
            "surface": rng.integers(-127, 128, size=(m, 3)),
        }
    return Delta(resolution, 10, 12, keys, lo, last, channels=ch, time=time)


def history_page(scans: int = 3, points: int = 40) -> tuple[HistoryPage, int]:
    """A page of a small grid's whole history and the highest version it covers."""
    from voxel.grid import VoxelGrid

    grid = VoxelGrid(0.1)
    rng = np.random.default_rng(11)
    for t in range(scans):
        origin = rng.uniform(-0.5, 0.5, 3)
        grid.integrate(origin + rng.normal(size=(points, 3)), origin, time=1.7e9 + t, agent="r1")
    page, to, _more = grid.history.page(0, 10**6)
    return page, to


def sample_messages(rng: np.random.Generator | None = None) -> list[Message]:
    """One valid message of every type (small deltas)."""
    rng = rng or np.random.default_rng(7)
    common = {"origin": "robot-1", "epoch": 3, "seq": 41, "time": 1_700_000_000.25}
    delta = make_delta(rng, 60)
    page, page_to = history_page()
    return [
        Announce(
            **common,
            kind="ground",
            frame_id="robot-1.map",
            resolution=0.05,
            software="colony 0.1.0",
            sensors=[SensorInfo.from_model("front", SensorModel(kind="depth", max_range=5.0))],
            capabilities=["snapshot", "deltas"],
        ),
        Pose(
            **common,
            frame_id="robot-1.map",
            position=(1.0, 2.0, 0.5),
            orientation=(0.0, 0.0, 0.6, 0.8),
            covariance=[0.01 * (i % 7 == 0) for i in range(36)],
        ),
        VoxelDelta(**common, frame_id="robot-1.map", delta=delta),
        Objects(
            **common,
            frame_id="robot-1.map",
            objects=[
                ObjectCentroid(
                    object_id=5,
                    class_id=2,
                    class_name="chair",
                    position=(1.0, 0.5, 0.4),
                    covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.02],
                    voxel_count=120,
                    time=1_700_000_000.0,
                ),
            ],
        ),
        AlignOffer(
            **common,
            target="robot-2",
            source_frame="robot-1.map",
            target_frame="robot-2.map",
            position=(0.5, -1.0, 0.0),
            orientation=(0.0, 0.0, 0.0, 1.0),
            matches=4,
            inliers=3,
            rmse=0.04,
            pairs=[(5, 9), (6, 11)],
        ),
        SnapshotRequest(**common, layer="robot-2", request_id=77, timeout_ms=5000),
        SnapshotReply(
            **common,
            layer="robot-1",
            request_id=77,
            frame_id="robot-1.map",
            layer_epoch=1_700_000_000_123_456,
            part=0,
            parts=2,
            delta=make_delta(rng, 40),
        ),
        DeltaRangeRequest(**common, layer="robot-1", request_id=78, from_version=10, to_version=12),
        DeltaRangeReply(
            **common,
            layer="robot-1",
            request_id=78,
            frame_id="robot-1.map",
            layer_epoch=0,
            complete=False,
        ),
        DeltaRangeReply(
            **common,
            layer="robot-1",
            request_id=79,
            frame_id="robot-1.map",
            layer_epoch=5,
            delta=make_delta(rng, 30),
        ),
        Heartbeat(
            **common,
            kind="ground",
            frame_id="robot-1.map",
            position=(1.0, 2.0, 0.5),
            layers=[
                LayerVersion(origin="robot-1", epoch=3, version=17),
                LayerVersion(origin="robot-2", epoch=1_700_000_000_123_456, version=4),
            ],
        ),
        PoseFix(
            **common,
            target="robot-2",
            frame_id="robot-1.map",
            stamp=1_700_000_000.0,
            position=(2.0, -1.0, 0.0),
            orientation=(0.0, 0.0, 0.6, 0.8),
            covariance=[0.0025 * (i % 7 == 0) for i in range(36)],
            marker_id=24,
            confidence=0.7,
        ),
        HistoryRequest(**common, layer="robot-2", request_id=80, from_version=6, max_records=900),
        HistoryReply(
            **common,
            layer="robot-2",
            request_id=80,
            layer_epoch=4,
            from_version=0,
            to_version=page_to,
            more=True,
            part=1,
            parts=2,
            records=page,
        ),
    ]


def sorted_view(delta: Delta) -> tuple[np.ndarray, Delta]:
    """(order, delta) with voxels sorted by key, to compare deltas regardless of voxel order."""
    from voxel.keys import pack

    order = np.argsort(pack(delta.keys), kind="stable")
    return order, delta.select(order)


def assert_delta_close(a: Delta, b: Delta, *, q: float = 2.0**-5) -> None:
    """`b` is `a` after a codec round trip: same keys, states, channels; log-odds within q."""
    _, sa = sorted_view(a)
    _, sb = sorted_view(b)
    assert sa.keys.shape == sb.keys.shape
    np.testing.assert_array_equal(sa.keys, sb.keys)
    np.testing.assert_array_equal(np.isnan(sa.logodds), np.isnan(sb.logodds))
    np.testing.assert_array_equal(sa.occupied, sb.occupied)
    finite = ~np.isnan(sa.logodds)
    assert np.all(np.abs(sa.logodds[finite] - sb.logodds[finite]) <= q + 1e-6)
    np.testing.assert_allclose(sa.last_time, sb.last_time, atol=5e-4, rtol=0)
    assert (b.resolution, b.from_version, b.to_version, b.time) == (
        a.resolution,
        a.from_version,
        a.to_version,
        a.time,
    )
    assert set(sa.channels) == set(sb.channels)
    ma = np.ones(len(sa), bool) if sa.surface_mask is None else sa.surface_mask
    mb = np.ones(len(sb), bool) if sb.surface_mask is None else sb.surface_mask
    if "surface" in sa.channels:
        np.testing.assert_array_equal(ma, mb)  # codes carried for the same voxels
    for name, values in sa.channels.items():
        if name == "surface":
            np.testing.assert_array_equal(values[ma], sb.channels[name][mb])
        elif name == "first_time":
            np.testing.assert_allclose(values, sb.channels[name], atol=5e-4, rtol=0)
        else:
            np.testing.assert_array_equal(values, sb.channels[name])
