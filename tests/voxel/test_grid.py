"""Tests of the voxel grid: occupancy, free space, channels, history, forgetting, deltas,
snapshots."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxel import keys as vk
from voxel.blocks import BlockStore
from voxel.errors import DeltaError, FileFormatError, InputError
from voxel.grid import FREE_STATE, OCCUPIED, UNKNOWN, VoxelGrid
from voxel.sensor import SensorModel, logodds

RES = 0.1


def wall_scan(x: float = 2.013, n: int = 41, z: float = 0.0117) -> tuple[np.ndarray, np.ndarray]:
    """Points on the plane x = const seen from near the origin."""
    ys = np.linspace(-1.0, 1.0, n) + 0.0031
    zs = np.linspace(-1.0, 1.0, n) + z
    yy, zz = np.meshgrid(ys, zs)
    pts = np.stack([np.full(yy.size, x), yy.ravel(), zz.ravel()], axis=1)
    return pts, np.array([0.0123, 0.0071, 0.0049])


def test_wall_is_occupied_space_before_is_free_behind_unknown():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan()
    report = grid.integrate(pts, origin, time=1.0)
    assert report.hits == pts.shape[0] and report.invalid == 0
    assert grid.state(np.array([[2.05, 0.0, 0.0]]))[0] == OCCUPIED
    assert grid.state(np.array([[1.0, 0.0, 0.0]]))[0] == FREE_STATE
    assert grid.state(np.array([[3.0, 0.0, 0.0]]))[0] == UNKNOWN
    assert math.isnan(grid.occupancy(np.array([[3.0, 0.0, 0.0]]))[0])
    # log-odds are stored on a 1/32 grid: 0.7 and 0.4 within that quantum
    assert grid.occupancy(np.array([[2.05, 0.0, 0.0]]))[0] == pytest.approx(0.7, abs=2e-3)
    assert grid.occupancy(np.array([[1.0, 0.0, 0.0]]))[0] == pytest.approx(0.4, abs=2e-3)
    occ = grid.occupied_keys()
    assert np.all(occ[:, 0] == 20)


def test_matches_octomap_discretized_update(kernel_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    from colonyd.bench.integrate import iou, octomap_sets

    rng = np.random.default_rng(3)
    origin = np.array([0.031, -0.017, 0.4])
    pts = origin + rng.normal(size=(3000, 3)) * 1.5
    grid = VoxelGrid(RES)
    grid.integrate(pts, origin, time=0.0)
    keys = np.unique(vk.points_to_keys(pts, RES), axis=0)
    tree = pyoctomap.OcTree(RES)
    tree.insertPointCloud(vk.keys_to_centers(keys, RES), origin, -1.0, False, True)
    occ, free = octomap_sets(tree, RES)
    assert iou(grid.occupied_keys(), occ) == 1.0
    assert iou(grid.free_keys(), free) > 0.99


def test_repeated_hits_clamp_and_misses_clear():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan()
    for t in range(10):
        grid.integrate(pts, origin, time=float(t))
    lo = grid.logodds_at_keys(vk.points_to_keys(pts[:1], RES))[0]
    assert lo == pytest.approx(logodds(0.97), abs=1 / 64)
    assert lo * 32 == int(lo * 32)  # a multiple of the 1/32 quantum
    # The wall moves back: the old wall voxels are now passed by rays and get cleared.
    far, _ = wall_scan(x=3.013)
    for t in range(10, 30):
        grid.integrate(far, origin, time=float(t))
    centre = pts[len(pts) // 2 : len(pts) // 2 + 1]
    assert grid.state(centre)[0] == FREE_STATE
    assert grid.state(far[len(far) // 2 :][:1])[0] == OCCUPIED


def test_reliability_scales_evidence():
    pts, origin = wall_scan()
    a, b = VoxelGrid(RES), VoxelGrid(RES)
    a.integrate(pts, origin, time=0.0)
    b.integrate(pts, origin, time=0.0, reliability=0.5)
    k = vk.points_to_keys(pts[:1], RES)
    assert b.logodds_at_keys(k)[0] == pytest.approx(logodds(0.7) / 2, abs=1 / 64)
    assert a.logodds_at_keys(k)[0] == pytest.approx(logodds(0.7), abs=1 / 64)


def test_invalid_points_are_counted_not_fatal():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan(n=5)
    bad = np.vstack([pts, [[np.nan, 0, 0], [np.inf, 1, 1], origin]])
    report = grid.integrate(bad, origin, time=0.0)
    assert report.invalid == 3
    assert report.hits == pts.shape[0]


def test_max_range_and_no_return_clear_without_hit():
    grid = VoxelGrid(RES)
    origin = np.array([0.011, 0.013, 0.017])
    sensor = SensorModel(max_range=1.5)
    pts = np.array([[4.0, 0.0, 0.0], [0.0, 0.9, 0.0]])
    report = grid.integrate(pts, origin, time=0.0, sensor=sensor, no_return=np.array([False, True]))
    assert report.cleared == 2 and report.hits == 0
    assert grid.state(np.array([[1.2, 0.0, 0.0]]))[0] == FREE_STATE
    beam = (pts[1] - origin) / np.linalg.norm(pts[1] - origin)
    assert grid.state((origin + 1.2 * beam)[None])[0] == FREE_STATE
    assert grid.state(np.array([[2.5, 0.0, 0.0]]))[0] == UNKNOWN
    assert len(grid.occupied_keys()) == 0
    # Without a max range a no-return beam cannot be used: counted as dropped.
    report = VoxelGrid(RES).integrate(pts, origin, time=0.0, no_return=np.array([True, True]))
    assert report.dropped == 2


def test_rich_channels_colour_classes_normals_scalars():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan(n=3)
    n = pts.shape[0]
    grid.integrate(
        pts,
        origin,
        time=0.0,
        colours=np.tile([200, 100, 0], (n, 1)).astype(np.uint8),
        normals=np.tile([-1.0, 0.0, 0.0], (n, 1)),
        class_ids=np.full(n, 7),
        class_probs=np.full(n, 0.9),
        scalars={"temperature": np.full(n, 20.0)},
    )
    grid.integrate(
        pts,
        origin,
        time=1.0,
        colours=np.tile([100, 100, 100], (n, 1)).astype(np.uint8),
        class_ids=np.full(n, 3),
        class_probs=np.full(n, 0.5),
        scalars={"temperature": np.full(n, 30.0)},
    )
    k = vk.points_to_keys(pts[:1], RES)
    assert grid.channel_at_keys("colour", k)[0].tolist() == [150, 100, 50]
    assert grid.channel_at_keys("scalar:temperature", k)[0] == pytest.approx(25.0)
    np.testing.assert_allclose(grid.channel_at_keys("normal", k)[0], [-1, 0, 0])
    ids = grid.channel_at_keys("class_ids", k)[0].tolist()
    probs = grid.channel_at_keys("class_probs", k)[0]
    assert 7 in ids and 3 in ids
    assert probs[ids.index(7)] == pytest.approx(0.3 * 0.9 * 0.7)
    assert probs[ids.index(3)] == pytest.approx(0.3 * 0.5)
    with pytest.raises(InputError, match="never been written"):
        grid.channel_at_keys("scalar:humidity", k)


def test_history_state_at_and_changes():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan()
    grid.integrate(pts, origin, time=10.0, agent="robot-a", object_ids=np.full(len(pts), 5))
    far, _ = wall_scan(x=3.013)
    for t in range(11, 20):
        grid.integrate(far, origin, time=float(t), agent="robot-b")
    p = pts[len(pts) // 2 :][:1]
    hist = grid.voxel_history(p[0])
    assert hist.size >= 2
    assert grid.history.agents[hist["agent"][0]] == "robot-a"
    assert hist["object_id"][0] == 5
    assert hist["state"][0] == 1 and hist["state"][-1] == 0
    assert grid.state_at(p, 9.0)[0] == UNKNOWN
    assert grid.state_at(p, 10.0)[0] == OCCUPIED
    assert grid.state_at(p, 19.0)[0] == FREE_STATE
    changed = vk.pack(grid.changed_between(10.5, 19.0))
    assert vk.pack(vk.points_to_keys(p, RES))[0] in changed
    assert vk.pack(vk.points_to_keys(far[:1], RES))[0] in changed


def test_history_is_bounded_per_voxel_and_in_total():
    grid = VoxelGrid(RES, history_capacity=5000, history_per_voxel=4)
    pts, origin = wall_scan()
    for t in range(20):
        grid.integrate(pts, origin, time=float(t))
    assert grid.history.size <= 5000
    assert grid.voxel_history(pts[0]).size <= 4


def test_forgetting_decays_and_frees_blocks():
    grid = VoxelGrid(RES, half_life=10.0)
    pts, origin = wall_scan()
    grid.integrate(pts, origin, time=0.0)
    p = pts[:1]
    lo0 = grid.logodds_at_keys(vk.points_to_keys(p, RES), now=0.0)[0]
    lo1 = grid.logodds_at_keys(vk.points_to_keys(p, RES), now=10.0)[0]
    assert lo1 == pytest.approx(lo0 / 2, rel=1e-4)
    assert grid.occupancy(p, now=10.0)[0] < grid.occupancy(p, now=0.0)[0]
    blocks = len(grid.store.used_slots())
    freed = grid.forget(now=200.0)
    assert freed == blocks and len(grid.store.used_slots()) == 0
    assert grid.state(p)[0] == UNKNOWN


def test_decayed_evidence_reads_unknown_before_it_is_forgotten():
    grid = VoxelGrid(RES, half_life=10.0)
    pts, origin = wall_scan()
    grid.integrate(pts, origin, time=0.0)
    p = pts[:1]
    assert grid.state(p, now=10.0)[0] == OCCUPIED
    assert grid.state(p, now=60.0)[0] == UNKNOWN  # 0.85 / 2^6 < FORGET_EPSILON
    assert len(grid.occupied_keys()) > 0 and grid.store.used_slots().size > 0


def test_forgetting_bumps_versions_replicates_and_returns_memory():
    """Forget 90 % of a layer: a replica that follows its deltas drops the same voxels and
    computes the same decayed occupancy; allocated bytes (not counters) drop >= 80 %."""
    grid = VoxelGrid(RES, half_life=30.0)
    rng = np.random.default_rng(5)
    for t in range(9):  # nine old scans far away
        origin = np.array([20.0 * t, 0.0, 0.0])
        grid.integrate(origin + rng.normal(size=(4000, 3)) * 3, origin, time=float(t))
    replica = VoxelGrid(RES, half_life=30.0)
    replica.apply(grid.delta_since(0))
    seen = grid.version
    origin = np.array([200.0, 0.0, 0.0])
    grid.integrate(origin + rng.normal(size=(4000, 3)) * 3, origin, time=99.0)  # one recent
    before, known = grid.allocated_bytes(), grid.known_count()
    freed = grid.forget(now=100.0, after=50.0)
    assert freed > 0 and grid.version > seen + 1
    assert grid.known_count() < 0.2 * known
    replica.apply(grid.delta_since(seen))
    assert replica.content_equal(grid) and replica.known_count() == grid.known_count()
    probe = vk.keys_to_centers(grid.occupied_keys()[:50], RES)
    np.testing.assert_array_equal(replica.occupancy(probe), grid.occupancy(probe))
    grid.settle(grid.version)  # the delta that carries the forgotten voxels was taken
    assert grid.allocated_bytes() <= 0.2 * before
    assert replica.allocated_bytes() <= 0.2 * before
    assert grid.history.view()["key"].size < 0.2 * known  # their history went with them


def test_ray_and_box_queries():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan()
    grid.integrate(pts, origin, time=0.0)
    hit = grid.cast_ray(origin, np.array([1.0, 0.0, 0.0]), 5.0)
    assert hit is not None and hit[0] == pytest.approx(2.05)
    assert grid.cast_ray(origin, np.array([-1.0, 0.0, 0.0]), 5.0) is None
    box = grid.occupied_in_box(np.array([1.9, -0.2, -0.2]), np.array([2.2, 0.2, 0.2]))
    assert len(box) == 16 and np.all(np.abs(box[:, 1]) <= 0.2)
    with pytest.raises(InputError, match="non-zero direction"):
        grid.cast_ray(origin, np.zeros(3), 1.0)


def test_input_errors_say_what_was_expected():
    grid = VoxelGrid(RES)
    with pytest.raises(InputError, match=r"shape \(N, 3\), found \(4,\)"):
        grid.integrate(np.zeros(4), np.zeros(3), time=0.0)
    with pytest.raises(InputError, match="origin must be 3 finite numbers"):
        grid.integrate(np.zeros((1, 3)), np.array([np.nan, 0, 0]), time=0.0)
    with pytest.raises(InputError, match="colours must have shape"):
        grid.integrate(np.ones((2, 3)), np.zeros(3), time=0.0, colours=np.zeros((3, 3)))
    with pytest.raises(InputError, match="reliability"):
        grid.integrate(np.ones((2, 3)), np.zeros(3), time=0.0, reliability=0.0)
    with pytest.raises(InputError, match="resolution must be a positive"):
        VoxelGrid(-1.0)
    with pytest.raises(InputError, match=r"prob_hit must be above 0\.5"):
        SensorModel(prob_hit=0.3)
    with pytest.raises(InputError, match="intrinsics must be a 3x3"):
        grid.integrate_depth(np.ones((4, 4)), np.eye(2), np.eye(4), time=0.0)


def test_depth_image_plane_comes_back_at_its_distance():
    grid = VoxelGrid(0.02)
    k = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 1.513)
    depth[0, 0] = 0.0  # no reading
    depth[1, 1] = np.nan
    report = grid.integrate_depth(depth, k, np.eye(4), time=0.0)
    assert report.points == 48 * 64 - 2
    occ = vk.keys_to_centers(grid.occupied_keys(), 0.02)
    assert np.all(np.abs(occ[:, 2] - 1.51) < 0.011)
    assert grid.state(np.array([[0.0, 0.0, 1.0]]))[0] == FREE_STATE


def _random_scans(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    scans = []
    for _ in range(n):
        origin = rng.uniform(-0.5, 0.5, 3)
        pts = origin + rng.normal(size=(200, 3)) * rng.uniform(0.3, 1.5)
        scans.append((pts, origin))
    return scans


def _grid_with_deltas(seed: int, n: int) -> tuple[VoxelGrid, list]:
    grid = VoxelGrid(RES)
    deltas = []
    for i, (pts, origin) in enumerate(_random_scans(seed, n)):
        v = grid.version
        grid.integrate(
            pts, origin, time=float(i), colours=np.full((len(pts), 3), 10 * i, dtype=np.uint8)
        )
        deltas.append(grid.delta_since(v))
    return grid, deltas


def test_delta_since_zero_rebuilds_the_grid():
    grid, _ = _grid_with_deltas(1, 4)
    copy = VoxelGrid(RES)
    copy.apply(grid.delta_since(0))
    assert copy.content_equal(grid)
    assert copy.version == grid.version
    assert len(grid.delta_since(grid.version)) == 0


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), perm_seed=st.integers(0, 10_000), dups=st.integers(0, 3))
def test_apply_is_idempotent_and_order_independent(seed: int, perm_seed: int, dups: int):
    grid, deltas = _grid_with_deltas(seed, 4)
    rng = np.random.default_rng(perm_seed)
    sequence = deltas + [deltas[i] for i in rng.integers(0, len(deltas), dups)]
    rng.shuffle(sequence)
    replica = VoxelGrid(RES)
    for d in sequence:
        replica.apply(d)
    assert replica.content_equal(grid)


def test_apply_rejects_foreign_resolution():
    _, deltas = _grid_with_deltas(2, 1)
    with pytest.raises(DeltaError, match=r"resolution 0\.1 does not match the grid's 0\.2"):
        VoxelGrid(0.2).apply(deltas[0])


def test_snapshot_round_trip_is_lossless(tmp_path):
    grid, _ = _grid_with_deltas(5, 3)
    grid.integrate(*wall_scan(), time=9.0, scalars={"t": np.ones(41 * 41)})
    path = tmp_path / "grid.npz"
    grid.save(path)
    back = VoxelGrid.load(path)
    assert back.content_equal(grid)
    assert back.version == grid.version
    assert back.history.size == grid.history.size
    np.testing.assert_array_equal(back.history.view(), grid.history.view())


def test_snapshot_errors(tmp_path):
    import io

    import zstandard

    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a snapshot at all")
    with pytest.raises(FileFormatError, match="expected a zstd-compressed colony-voxel-snapshot"):
        VoxelGrid.load(bad)
    truncated = tmp_path / "trunc.npz"
    grid, _ = _grid_with_deltas(5, 1)
    grid.save(truncated)
    truncated.write_bytes(truncated.read_bytes()[:200])
    with pytest.raises(FileFormatError, match="not a readable colony-voxel-snapshot"):
        VoxelGrid.load(truncated)
    other = tmp_path / "other.npz"
    buf = io.BytesIO()
    np.savez(buf, x=np.zeros(3))
    other.write_bytes(zstandard.ZstdCompressor().compress(buf.getvalue()))
    with pytest.raises(FileFormatError, match="expected a colony-voxel-snapshot file"):
        VoxelGrid.load(other)


def _rewrite_meta(path, history_v3: bool = False, **changes) -> None:
    """Re-save a snapshot with its metadata changed (or keys removed when given None); with
    `history_v3`, its history records without the version column (format 3)."""
    import io
    import json

    import zstandard

    raw = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(path.read_bytes())).read()
    with np.load(io.BytesIO(raw)) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(bytes(arrays["meta"]).decode())
    for key, value in changes.items():
        if value is None:
            meta.pop(key, None)
        else:
            meta[key] = value
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    if history_v3:
        from voxel.history import RECORD_DTYPE_V3, RENAMED_V3

        old = arrays["history"]
        arrays.pop("history_seen", None)  # format 3 had no seen log
        arrays["history"] = np.zeros(old.size, RECORD_DTYPE_V3)
        for name in RECORD_DTYPE_V3.names:
            arrays["history"][name] = old[RENAMED_V3.get(name, name)]
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(zstandard.ZstdCompressor().compress(buf.getvalue()))


def test_snapshot_versions_and_block_shapes(tmp_path):
    grid, _ = _grid_with_deltas(6, 2)
    path = tmp_path / "g.npz"
    grid.save(path)
    _rewrite_meta(path, version=2, block_shape=None)  # written before block shapes existed
    back = VoxelGrid.load(path)
    assert back.store.shifts == (2, 2, 2) and back.content_equal(grid)
    grid.save(path)
    _rewrite_meta(path, history_v3=True, version=3)  # records before they carried the version
    back = VoxelGrid.load(path)
    assert back.history.size == grid.history.size and back.history.newest_version() == 0
    np.testing.assert_array_equal(back.history.view()["key"], grid.history.view()["key"])
    _rewrite_meta(path, version=3, block_shape=5)
    with pytest.raises(FileFormatError, match="not a readable colony-voxel-snapshot"):
        VoxelGrid.load(path)
    _rewrite_meta(path, block_shape=[4, 4, 3])
    with pytest.raises(FileFormatError, match="block sides must be three of 1, 2, 4, 8 voxels"):
        VoxelGrid.load(path)
    _rewrite_meta(path, version=9)
    with pytest.raises(
        FileFormatError, match="expected format colony-voxel-snapshot v2/3/4, found"
    ):
        VoxelGrid.load(path)


def test_bt_export_loads_in_octomap_with_the_same_occupied_set(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    from colonyd.bench.integrate import iou, octomap_sets

    grid = VoxelGrid(RES)
    for i, (pts, origin) in enumerate(_random_scans(7, 3)):
        grid.integrate(pts, origin, time=float(i))
    path = tmp_path / "map.bt"
    grid.write_bt(path)
    tree = pyoctomap.OcTree(RES)
    assert tree.readBinary(str(path))
    occ, free = octomap_sets(tree, RES)
    assert iou(occ, grid.occupied_keys()) == 1.0
    assert iou(free, grid.free_keys()) == 1.0
    back = VoxelGrid.from_bt(path)
    assert iou(back.occupied_keys(), grid.occupied_keys()) == 1.0


def test_ply_export_has_occupied_centres_and_colours(tmp_path):
    from voxel.ply import read_ply

    grid = VoxelGrid(RES)
    pts, origin = wall_scan(n=5)
    grid.integrate(pts, origin, time=0.0, colours=np.full((len(pts), 3), 9, dtype=np.uint8))
    grid.write_ply(tmp_path / "m.ply")
    centres, colours = read_ply(tmp_path / "m.ply")
    assert len(centres) == len(grid.occupied_keys())
    assert colours is not None and np.all(colours == 9)


def test_stored_values_are_on_the_wire_grid():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan(n=5)
    grid.integrate(pts, origin, time=1.23456, reliability=0.77)
    d = grid.delta_since(0)
    assert np.all(d.last_time == 1.235)
    finite = d.logodds[~np.isnan(d.logodds)]
    np.testing.assert_array_equal(finite * 32, np.rint(finite * 32))


def test_times_are_exact_across_a_moved_time_base():
    grid = VoxelGrid(RES)
    pts, origin = wall_scan(n=5)
    grid.integrate(pts, origin, time=1_700_000_000.123)
    far, _ = wall_scan(x=3.013, n=5)
    later = 1_700_000_000.123 + 60 * 86400  # beyond the 49-day window of the first base
    grid.integrate(far, origin, time=later)
    d = grid.delta_since(0)
    assert d.last_time.max() == round(later * 1000) / 1000
    old = d.last_time[d.last_time < later]
    assert old.size and np.all(old >= later - 50 * 86400)  # older voxels clamp to the moved base
    replica = VoxelGrid(RES)
    replica.apply(d)
    assert replica.content_equal(grid)
    per_voxel = sum(
        a.dtype.itemsize * int(np.prod(a.shape[2:])) for a in grid.store.channels.values()
    )
    assert per_voxel == 12  # log-odds, version, time


def test_the_store_shrinks_once_half_its_slots_are_free() -> None:
    store = BlockStore(capacity=64)
    slots = store.ensure(np.arange(1000, dtype=np.int64))
    cap = store.capacity
    store.release(slots[:400])
    assert not store.shrink()  # 600 of 1000 held: more than half
    store.release(slots[400:520])
    assert store.shrink() and store.capacity < 0.7 * cap
    assert store.lookup(np.array([519, 520, 999])).tolist()[0] == -1
    assert (store.lookup(np.arange(520, 1000)) >= 0).all()


def test_the_block_index_is_the_same_on_both_paths(kernel_path) -> None:
    # BlockStore.ensure: the compiled merge walk (sorted, unique keys, no free slot to reuse)
    # and numpy give the same slots and index; unsorted keys and reused slots take numpy.
    rng = np.random.default_rng(3)
    store = BlockStore(capacity=64)
    seen: dict[int, int] = {}
    for n in (0, 5, 300, 40, 1000, 0, 200):
        keys = np.unique(rng.integers(-5000, 5000, n))
        slots = store.ensure(keys)
        for k, s in zip(keys.tolist(), slots.tolist(), strict=True):
            assert seen.setdefault(k, s) == s  # a held block keeps its slot
        assert sorted(set(seen.values())) == list(range(len(seen)))  # new slots in key order
        np.testing.assert_array_equal(store.sorted_keys, sorted(seen))
        np.testing.assert_array_equal(store.sorted_slots, [seen[k] for k in sorted(seen)])
        np.testing.assert_array_equal(store.slot_keys[store.sorted_slots], store.sorted_keys)
    shuffled = rng.permutation(np.unique(rng.integers(-6000, 6000, 300)))
    slots = store.ensure(shuffled)  # unsorted: the numpy path
    np.testing.assert_array_equal(store.slot_keys[slots], shuffled)
    store.release(slots[:10])
    again = store.ensure(np.sort(shuffled[:20]))  # free slots to reuse: the numpy path
    np.testing.assert_array_equal(store.slot_keys[again], np.sort(shuffled[:20]))
    assert set(slots[:10].tolist()) <= set(again.tolist())
