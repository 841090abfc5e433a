"""Surface codes carried only where they changed (PROTOCOL.md §6, `surface`): round trips on real
kitchen deltas, exact replicas along every path a delta takes, and hostile bitmaps refused."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest

from colonyd.bench.wire import scenarios
from colonyd.frames import concat
from colonyd.layers import Layer
from colonyd.persistence import _pack_wal_delta, _unpack_wal_delta
from protocol import Receiver, encode
from protocol.deltacodec import decode_delta, encode_delta, fit_delta, split_delta
from protocol.errors import MalformedError, ProtocolError, RangeError
from protocol.messages import VoxelDelta
from tests.protocol.helpers import assert_delta_close
from tests.shared import SHARED_DATA
from voxel import keys as vk
from voxel import surface
from voxel.delta import Delta
from voxel.errors import DeltaError
from voxel.grid import VoxelGrid

RES = 0.1


def wire(delta: Delta) -> Delta:
    """`delta` after an encode and a decode, as a peer gets it."""
    return decode_delta(encode_delta(delta))


def carried(delta: Delta) -> np.ndarray:
    return np.ones(len(delta), bool) if delta.surface_mask is None else delta.surface_mask


def codes_at(delta: Delta, keys: np.ndarray) -> np.ndarray:
    """The codes `delta` (as made, every voxel's) holds for `keys`."""
    packed = vk.pack(delta.keys)
    order = np.argsort(packed)
    rows = order[np.searchsorted(packed[order], vk.pack(keys))]
    out: np.ndarray = delta.channels["surface"][rows]
    return out


def scans(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n scans of a wall (x about 2.03 m) seen from the origin: its points move a little from
    scan to scan, and now and then a lot (a mean a step away), so codes change in some scans
    and not in others while log-odds change in every one."""
    rng = np.random.default_rng(seed)
    side = np.arange(-0.295, 0.3, 0.01)
    yy, zz = np.meshgrid(side, side)
    out = []
    for i in range(n):
        jump = 0.03 if i % 3 == 2 else 0.0
        x = 2.0337 + jump + rng.normal(0.0, 0.004, yy.size)
        out.append((np.stack([x, yy.ravel(), zz.ravel()], axis=1), np.zeros(3)))
    return out


def origin_deltas(seed: int = 1, n: int = 8, sparse: bool = True) -> tuple[VoxelGrid, list[Delta]]:
    """An origin grid with the surface and its consecutive deltas, one per scan (the last one
    after a forget); `sparse`: codes only where they changed."""
    grid = VoxelGrid(RES, surface=True)
    grid.sparse_surface = sparse
    out = []
    for t, (pts, o) in enumerate(scans(seed, n)):
        v = grid.version
        grid.integrate(pts, o, time=float(t))
        out.append(grid.delta_since(v))
    v = grid.version
    grid.forget(now=float(n) + 100.0, after=50.0)  # everything forgotten: codes back to 0
    grid.integrate(*scans(seed + 1, 1)[0], time=float(n) + 101.0)
    out.append(grid.delta_since(v))
    return grid, out


def test_a_delta_carries_only_the_codes_that_changed_and_a_replica_stays_exact():
    grid, deltas = origin_deltas()
    replica = VoxelGrid(RES)
    partial = 0
    for d in deltas:
        back = wire(d)
        assert_delta_close(d, back)
        mask = carried(back)  # in wire order, as `back`'s voxels
        partial += int((~mask).sum())
        # a voxel without codes has the codes it had at the delta's from-version (the replica's)
        if (~mask).any() and replica.has_surface:
            keys = back.keys[~mask]
            np.testing.assert_array_equal(
                replica.channel_at_keys("surface", keys), codes_at(d, keys)
            )
        replica.apply(back)
    assert partial > 0, "expected deltas that leave some voxels' codes out"
    assert replica.content_equal(grid)
    # the dense form: every code, 0 for voxels not occupied, and the same replica's occupancy
    grid.sparse_surface = False
    full = grid.delta_since(0)
    assert full.surface_mask is None and not full.channels["surface"][~full.occupied].any()


def test_skipping_a_delta_that_changed_codes_would_leave_a_replica_wrong():
    """Why a replica applies deltas in order (or takes a snapshot): a later delta omits codes
    that changed in an earlier one."""
    _, deltas = origin_deltas()
    assert carried(deltas[0]).any() and not carried(deltas[1]).all()
    replica = VoxelGrid(RES)
    replica.apply(wire(deltas[1]))  # delta 0 skipped: its codes never arrive
    assert not replica.content_equal(grid_at(deltas, 2))
    replica.apply(wire(deltas[0]))  # late, and older: its voxels stay as delta 1 left them
    assert not replica.content_equal(grid_at(deltas, 2))


def layer_of(deltas: list[Delta], epoch: int = 1) -> Layer:
    """A replica layer fed `deltas` (wire versions i -> i + 1) after a codec round trip."""
    layer = Layer("r1", RES)
    for i, d in enumerate(deltas):
        layer.offer(epoch, i, i + 1, wire(d))
    return layer


def test_gap_repair_split_parts_snapshots_and_store_and_forward_stay_exact():
    grid, deltas = origin_deltas(seed=2)
    # gap: delta 2 arrives last (buffered, the range repairs it) -> exact
    layer = Layer("r1", RES)
    order = [0, 1, *range(3, len(deltas)), 2]
    for i in order:
        result = layer.offer(1, i, i + 1, wire(deltas[i]))
        assert result.outcome in ("applied", "gap")
    assert layer.seq == len(deltas) and layer.grid.content_equal(grid)
    # the same repaired from the origin's ring (a DeltaRangeRequest's reply)
    origin = layer_of(deltas)
    late = layer_of(deltas[:2])
    got = origin.range(2, len(deltas))
    assert got is not None
    for i, d in enumerate(got, start=2):
        late.offer(1, i, i + 1, wire(d))
    assert late.grid.content_equal(grid)
    # split into parts, each encoded alone, reassembled (concat) and applied
    parted = Layer("r1", RES)
    for i, d in enumerate(deltas):
        parts = [wire(p) for p in split_delta(d, 300)] if len(d) else [wire(d)]
        parted.offer(1, i, i + 1, concat(parts))
    assert parted.grid.content_equal(grid)
    # a snapshot of the origin, then the deltas after it
    fresh = Layer("r1", RES)
    mid = grid_at(deltas, 4)
    snap = wire(mid.delta_since(0))
    assert snap.surface_mask is None  # a replica's snapshot: every code as it holds them
    fresh.install_snapshot(1, 4, [snap])
    for i in range(4, len(deltas)):
        fresh.offer(1, i, i + 1, wire(deltas[i]))
    assert fresh.grid.content_equal(grid)
    own = wire(grid.delta_since(0))  # the origin's: codes of the voxels whose codes ever moved
    assert own.surface_mask is not None and not own.surface_mask.all()
    other = Layer("r1", RES)
    other.install_snapshot(1, len(deltas), [own])
    assert other.grid.content_equal(grid)
    # store and forward: a replica's snapshot and a replica's ring serve a third peer
    epoch, seq, chunks = layer.snapshot(50)
    third = Layer("r1", RES)
    third.install_snapshot(epoch, seq, [wire(c) for c in chunks])
    assert third.grid.content_equal(grid)


@pytest.mark.parametrize("sparse", [True, False])
def test_a_replicas_snapshot_serves_a_third_peer_exactly_from_either_kind_of_origin(sparse):
    grid, deltas = origin_deltas(seed=4, sparse=sparse)
    layer = layer_of(deltas[:5])
    epoch, seq, chunks = layer.snapshot(40)
    third = Layer("r1", RES)
    third.install_snapshot(epoch, seq, [wire(c) for c in chunks])
    for i in range(5, len(deltas)):  # then the origin's own deltas
        third.offer(1, i, i + 1, wire(deltas[i]))
    assert third.grid.content_equal(grid)
    if not sparse:  # a dense origin's deltas carry every code: 0 for voxels not occupied
        assert all(d.surface_mask is None for d in deltas)


def grid_at(deltas: list[Delta], k: int) -> VoxelGrid:
    """The origin as its first k deltas left it (its replica, which is exact)."""
    g = VoxelGrid(RES)
    for d in deltas[:k]:
        g.apply(d)
    return g


def test_the_write_ahead_log_keeps_which_codes_a_delta_carries():
    _, deltas = origin_deltas(seed=3)
    d = next(d for d in deltas if d.surface_mask is not None and not d.surface_mask.all())
    back = _unpack_wal_delta(msgpack.unpackb(msgpack.packb(_pack_wal_delta(d))))
    np.testing.assert_array_equal(back.surface_mask, d.surface_mask)
    np.testing.assert_array_equal(back.channels["surface"], d.channels["surface"])


@pytest.fixture(scope="module")
def kitchen() -> tuple[VoxelGrid, list[Delta]]:
    """The first real kitchen frames' deltas with the surface, as a daemon's own layer makes
    them."""
    found = [s for s in scenarios(SHARED_DATA) if s.name == "redkitchen50_0.05"]
    if not found:
        pytest.skip(f"no redkitchen-50 frames under {SHARED_DATA}")
    grid = VoxelGrid(0.05, surface=True)
    grid.sparse_surface = True
    out = []
    for i, frame in enumerate(found[0].frames()):
        if i == 6:
            break
        version = grid.version
        frame.integrate(grid, 1_700_000_000.0 + 0.1 * i)
        out.append(grid.delta_since(version))
    return grid, out


def test_real_kitchen_deltas_round_trip_and_their_replica_is_exact(kitchen):
    grid, deltas = kitchen
    replica = VoxelGrid(0.05)
    left_out = 0
    for i, d in enumerate(deltas):
        frame = encode(VoxelDelta(origin="r1", epoch=1, seq=i, time=1.0, frame_id="m", delta=d))
        back = Receiver().receive(frame)
        assert isinstance(back, VoxelDelta)
        assert_delta_close(d, back.delta)
        left_out += int((~carried(back.delta)).sum())
        replica.apply(back.delta)
    assert left_out > 0
    assert replica.content_equal(grid)
    assert_delta_close(grid.delta_since(0), wire(grid.delta_since(0)))


# ----------------------------------------------------------------------------- hostile bodies


def sparse_body() -> tuple[dict[str, Any], Delta]:
    """A 10-voxel delta body carrying codes for 3 of its voxels."""
    keys = np.stack([np.arange(10), np.zeros(10, int), np.zeros(10, int)], axis=1)
    codes = np.zeros((10, 3), np.int8)
    mask = np.zeros(10, bool)
    mask[[1, 4, 9]] = True
    codes[mask] = [[16, -16, 0], [32, 0, 127], [-127, 48, 0]]
    d = Delta(
        RES, 3, 4, keys, np.full(10, 0.5, np.float32), np.full(10, 1.0), {"surface": codes}, 1.0
    )
    d.surface_mask = mask
    Delta.__post_init__(d)
    return msgpack.unpackb(encode_delta(d)), d


def with_channel(body: dict[str, Any], entry: list[Any]) -> bytes:
    body = dict(body)
    body["ch"] = [entry]
    out: bytes = msgpack.packb(body)
    return out


def test_the_sparse_channel_decodes_to_its_codes_and_bitmap():
    body, d = sparse_body()
    (entry,) = body["ch"]
    assert entry[0] == "surface" and len(entry) == 4 and len(entry[2]) == 9 and len(entry[3]) == 2
    back = decode_delta(msgpack.packb(body))
    assert_delta_close(d, back)
    assert not back.channels["surface"][~back.surface_mask].any()


@pytest.mark.parametrize(
    ("mutate", "error", "match"),
    [
        (lambda e: [*e[:3], e[3][:1]], MalformedError, r"bitmap: expected 2 bytes, found 1"),
        (lambda e: [*e[:3], e[3] + b"\x00"], MalformedError, r"bitmap: expected 2 bytes, found 3"),
        (lambda e: [*e[:3], bytes([e[3][0], e[3][1] | 4])], MalformedError, "beyond the delta"),
        (lambda e: [*e[:2], e[2] + b"\x00\x00\x00", e[3]], MalformedError, "expected 9 bytes"),
        (lambda e: [*e[:2], e[2][:6], e[3]], MalformedError, "expected 9 bytes"),
        (lambda e: [*e[:3], bytes([e[3][0] | 1, e[3][1]])], MalformedError, "expected 12 bytes"),
        (lambda e: [*e[:2], b"\x80" + e[2][1:], e[3]], RangeError, "expected codes in"),
        (lambda e: [*e[:3], 5], MalformedError, "expected binary data"),
        (lambda e: [*e, b""], MalformedError, r"\[name, k, codes, bitmap\]"),
        (lambda e: ["hits", 0, b"\x00" * 20, e[3]], MalformedError, r"expected \[name, k, data\]"),
    ],
)
def test_hostile_bitmaps_and_codes_are_refused_with_what_was_expected(mutate, error, match):
    body, _ = sparse_body()
    data = with_channel(body, mutate(body["ch"][0]))
    with pytest.raises(error, match=match):
        decode_delta(data)


def test_a_refused_body_moves_no_window_and_leaves_the_replica_as_it_was():
    body, d = sparse_body()
    entry = body["ch"][0]
    bad_body = with_channel(body, [*entry[:3], bytes([entry[3][0], entry[3][1] | 4])])
    good = VoxelDelta(origin="r1", epoch=1, seq=5, time=1.0, frame_id="m", delta=d)
    bad = bytearray(encode(good, compression="none"))
    start = bytes(bad).index(encode_delta(d))
    frame = bytes(bad[:start]) + bad_body + bytes(bad[start + len(encode_delta(d)) :])
    receiver, layer = Receiver(), Layer("r1", RES)
    layer.offer(1, 0, 3, Delta(RES, 0, 3, np.zeros((0, 3)), [], []))
    before = layer.digest()
    with pytest.raises(ProtocolError):
        msg = receiver.receive(frame)
        layer.offer(1, 3, 4, msg.delta)  # pragma: no cover - the frame is refused above
    assert layer.digest() == before and layer.seq == 3
    msg = receiver.receive(encode(good))  # the same seq, well formed: taken
    assert isinstance(msg, VoxelDelta)
    layer.offer(1, 3, 4, msg.delta)
    assert layer.grid.channel_at_keys("surface", d.keys[d.surface_mask]).tolist() == [
        [16, -16, 0],
        [32, 0, 127],
        [-127, 48, 0],
    ]


def test_a_mask_needs_the_surface_channel_and_one_bool_per_voxel():
    keys, lo, t = np.zeros((2, 3)), np.zeros(2), np.zeros(2)
    with pytest.raises(DeltaError, match="surface_mask"):
        Delta(RES, 0, 1, keys, lo, t, surface_mask=np.ones(2, bool))
    codes = {"surface": np.zeros((2, 3), np.int8)}
    with pytest.raises(DeltaError, match="surface_mask"):
        Delta(RES, 0, 1, keys, lo, t, codes, surface_mask=np.ones(3, bool))
    with pytest.raises(DeltaError, match="surface_mask"):
        Delta(RES, 0, 1, keys, lo, t, codes, surface_mask=np.ones(2, np.uint8))
    assert surface.VERSION not in {"surface"}  # never a delta channel


def test_a_budget_never_cuts_a_voxel_whose_codes_the_delta_carries():
    """A free voxel whose codes changed (hit once, then missed) stays exact in a budget-cut
    delta: a later delta that finds it occupied again leaves its unchanged codes out."""
    rng = np.random.default_rng(6)
    n = 4000
    keys = rng.integers(-200, 200, (n, 3))
    keys = np.unique(keys, axis=0)
    n = len(keys)
    codes = np.zeros((n, 3), np.int8)
    mask = np.zeros(n, bool)
    mask[:7] = True
    codes[:7] = 16
    lo = np.full(n, -0.4, np.float32)  # all free: the budget summarises free space
    d = Delta(RES, 0, 1, keys, lo, np.full(n, 1.0), {"surface": codes}, 1.0, surface_mask=mask)
    exact, _summary = fit_delta(d, 600)
    assert len(exact) < n  # cut (free space summarised or left out)
    kept = {tuple(k) for k in exact.keys.tolist()}
    assert {tuple(k) for k in keys[mask].tolist()} <= kept


def test_an_origin_recovered_from_its_log_serves_every_code_it_holds(tmp_path):
    """Recovery replays the log into a grid without the surface (the daemon turns it on after),
    so with sparse codes the replayed codes kept no `surface_version`: once the restarted origin
    mapped again (the channel made then, 0 for them), a newcomer's snapshot (codes changed after
    version 0) left them out and the newcomer held 0 where the origin held codes."""
    from colonyd.persistence import StateStore

    store = StateStore(tmp_path, "a", RES)
    store.recover()
    grid = VoxelGrid(RES, surface=True)
    grid.sparse_surface = True
    published = 0
    for seq, (pts, o) in enumerate(scans(5, 4), 1):
        grid.integrate(pts, o, time=float(seq))
        store.append(seq, grid.delta_since(published))
        published = grid.version
    store.close()
    store = StateStore(tmp_path, "a", RES)
    own = store.recover().grid
    store.close()
    own.surface, own.sparse_surface = True, True  # as the daemon's configuration says
    assert own.content_equal(grid)
    pts, o = scans(6, 1)[0]
    own.integrate(pts[::3] + np.array([1.0, 0.0, 0.0]), o, time=10.0)  # maps on, elsewhere
    replica = VoxelGrid(RES)
    replica.apply(wire(own.delta_since(0)))  # a newcomer's snapshot
    assert replica.content_equal(own)
