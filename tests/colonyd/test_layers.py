"""Per-origin layers: ordering, duplicates, gaps, epochs, snapshots, ranges, fused view."""

from __future__ import annotations

import time

import numpy as np
import pytest

from colonyd.errors import WireError
from colonyd.grid import new_grid
from colonyd.layers import SURFACE_REACH, FusedMap, Layer, Layers, fused, layer_weights
from tests.shared import ask_snapshot
from voxel import keys as vk
from voxel.delta import Delta


def deltas(n: int = 4):
    grid, out, v = new_grid(0.1), [], 0
    rng = np.random.default_rng(1)
    for _ in range(n):
        grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=1.0)
        out.append(grid.delta_since(v))
        v = grid.version
    return grid, out


def test_out_of_order_duplicates_and_gaps_converge():
    origin, ds = deltas()
    layer = Layer("o", 0.1)
    assert layer.offer(7, 0, 1, ds[0]).outcome == "applied"
    assert layer.offer(7, 0, 1, ds[0]).outcome == "duplicate"
    r = layer.offer(7, 2, 3, ds[2])
    assert r.outcome == "gap" and r.missing == (1, 2)
    assert layer.offer(7, 3, 4, ds[3]).outcome == "gap"
    r = layer.offer(7, 1, 2, ds[1])
    assert [s for s, _ in r.drained] == [2, 3, 4] and layer.seq == 4
    assert layer.grid.content_equal(origin)
    # the ring holds the deltas labelled with layer versions, ready to serve a range query
    assert [(d.from_version, d.to_version) for d in layer.range(1, 4)] == [(1, 2), (2, 3), (3, 4)]
    assert [len(d) for d in layer.range(0, 4)] == [len(d) for d in ds]
    # a range beyond the newest version ends at it; an empty one is nothing to send
    assert [d.to_version for d in layer.range(0, 9)] == [1, 2, 3, 4]
    assert layer.range(4, 9) == [] and layer.range(2, 2) == []
    short = Layer("o", 0.1, ring_size=2)
    for i, d in enumerate(ds):
        short.offer(7, i, i + 1, d)
    assert short.range(0, 4) is None and len(short.range(2, 4)) == 2  # no longer held: None
    assert layer.offer(6, 4, 5, ds[0]).outcome == "stale-epoch"


def _same(a, b) -> bool:
    da, db = a.delta_since(0), b.delta_since(0)
    ia, ib = np.lexsort(da.keys.T), np.lexsort(db.keys.T)
    return np.array_equal(da.keys[ia], db.keys[ib]) and np.array_equal(
        da.logodds[ia], db.logodds[ib]
    )


def test_snapshot_install_then_newer_epoch_resets():
    origin, ds = deltas()
    src = Layer("o", 0.1)
    for i, d in enumerate(ds):
        src.offer(3, i, i + 1, d)
    epoch, seq, chunks = src.snapshot(chunk_voxels=50)
    assert len(chunks) > 1 and seq == 4
    dst = Layer("o", 0.1)
    assert dst.install_snapshot(epoch, seq, chunks) == sum(len(c) for c in chunks)
    assert dst.digest() == src.digest() and dst.grid.content_equal(origin)
    r = dst.offer(4, 0, 1, ds[0])  # the origin lost its state: a new epoch starts over
    assert r.outcome == "applied" and dst.epoch == 4 and dst.seq == 1


def test_fused_view_sums_layers():
    a, b = Layer("a", 0.1), Layer("b", 0.1)
    _, ds = deltas(1)
    a.offer(1, 0, 1, ds[0])
    b.offer(1, 0, 1, ds[0])
    keys, lo = fused([a, b], 0.1)
    one_keys, one_lo = fused([a], 0.1)
    assert np.array_equal(keys, one_keys)
    np.testing.assert_allclose(lo, 2 * one_lo, rtol=1e-6)


def test_replica_of_a_planar_layer_takes_planar_blocks():
    origin = new_grid(0.05, "planar")
    a = np.linspace(-2.0, 2.0, 361)
    pts = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * 4.0 + [0.01, 0.02, 0.0123]
    origin.integrate(pts, np.array([0.01, 0.02, 0.0123]), time=1.0)
    planar = Layer("p", 0.05)
    assert planar.offer(1, 0, 1, origin.delta_since(0)).outcome == "applied"
    assert planar.grid.store.shifts == origin.store.shifts and planar.grid.content_equal(origin)
    # new blocks are counted in the replica's own block shape: applying again allocates none
    assert planar.new_blocks(origin.delta_since(0).keys) == 0
    _, seq, chunks = planar.snapshot(chunk_voxels=100)
    copy = Layer("p", 0.05)
    # the parts are counted together as the blocks they will fill, in the shape they will take
    assert copy.new_blocks([c.keys for c in chunks], replace=True) == origin.store.count
    copy.install_snapshot(1, seq, chunks)
    assert copy.grid.store.shifts == (3, 3, 0) and copy.grid.content_equal(origin)
    assert copy.new_blocks([c.keys for c in chunks]) == 0
    _, ds = deltas(1)
    three_d = Layer("c", 0.1)
    three_d.offer(1, 0, 1, ds[0])
    assert three_d.grid.store.shifts == (2, 2, 2)


def _planar_map() -> object:
    grid = new_grid(0.05, "planar")
    a = np.linspace(-3.0, 3.0, 1081)
    pts = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * 6.0 + [0.01, 0.02, 0.0123]
    grid.integrate(pts, np.array([0.01, 0.02, 0.0123]), time=1.0)
    return grid


def test_budget_counts_a_planar_snapshot_in_planar_blocks():
    origin = _planar_map()
    chunks = Layer("p", 0.05)
    chunks.grid = origin
    _, seq, parts = chunks.snapshot(chunk_voxels=5000)
    blocks = int(origin.store.sorted_keys.size)  # what the replica will allocate
    Layers("me", 0.05, max_peer_blocks=blocks).admit("p", parts, replace=True)
    with pytest.raises(WireError, match=f"within {blocks - 1} blocks") as info:
        Layers("me", 0.05, max_peer_blocks=blocks - 1).admit("p", parts, replace=True)
    assert info.value.reason == "over-budget"
    layers = Layers("me", 0.05, max_peer_blocks=blocks)  # the same for deltas into a new layer
    layers.admit("p", [origin.delta_since(0)])
    layers.get("p").install_snapshot(1, seq, parts)
    assert layers.get("p").blocks() == blocks


def test_admission_changes_nothing_and_refuses_our_own_layer():
    _, ds = deltas(1)
    layers = Layers("me", 0.1, max_layers=1, max_peer_blocks=10_000)
    layers.admit("p", ds)
    assert layers.find("p") is None  # admission creates no layer
    with pytest.raises(WireError, match="found our own 'me'"):
        layers.admit("me", ds)
    layers.get("p").offer(1, 0, 1, ds[0])
    coarse = Delta(0.2, 1, 2, ds[0].keys, ds[0].logodds, ds[0].last_time)
    with pytest.raises(WireError, match=r"expected resolution 0\.1, found 0\.2"):
        layers.admit("p", [coarse])
    with pytest.raises(WireError, match="at most 1 peer layers") as info:
        layers.admit("q", ds)
    assert info.value.reason == "too-many-layers"


def test_layer_weights_by_agent_then_kind_scale_the_fused_view():
    weights = layer_weights({"cctv": 0.5, "b": 2.0}, ["a", "b", "c"], {"a": "cctv", "b": "cctv"})
    assert weights == {"a": 0.5, "b": 2.0, "c": 1.0}  # agent id first, then kind, else 1.0
    a, b = Layer("a", 0.1), Layer("b", 0.1)
    _, ds = deltas(1)
    a.offer(1, 0, 1, ds[0])
    b.offer(1, 0, 1, ds[0])
    _, lo = fused([a, b], 0.1, weights=weights)
    _, one = fused([a], 0.1)
    np.testing.assert_allclose(lo, 2.5 * one, rtol=1e-6)


def _labelled_layer(origin: str, points: np.ndarray, cls: int, prob: float) -> Layer:
    """A layer whose origin saw `points` (from above) labelled `cls` with probability `prob`."""
    from colonyd.layers import Layer

    grid = new_grid(0.1)
    n = len(points)
    grid.integrate(
        points,
        np.array([0.05, 0.05, 3.05]),
        time=1.0,
        class_ids=np.full(n, cls, np.int64),
        class_probs=np.full(n, prob, np.float32),
    )
    layer = Layer(origin, 0.1)
    layer.offer(1, 0, 1, grid.delta_since(0))
    return layer


def test_fused_classes_take_the_most_probable_label_over_layers_and_frames():
    from colonyd.layers import best_class

    box = np.array([[0.05, 0.05, 1.05], [0.15, 0.05, 1.05]])
    a = _labelled_layer("a", box, 3, 0.6)
    b = _labelled_layer("b", box, 4, 0.9)  # more sure: wins where both label a voxel
    c = _labelled_layer("c", box - [1.0, 0.0, 0.0], 5, 0.99)  # 1 m off in its own frame
    shift = np.eye(4)
    shift[0, 3] = 1.0  # c's frame into ours
    transforms = {"a": np.eye(4), "b": np.eye(4), "c": shift}
    keys, _ = fused([a, b, c], 0.1, transforms)
    classes = FusedMap().classes([a, b, c], 0.1, keys, transforms)
    hit = {tuple(k): int(x) for k, x in zip(keys.tolist(), classes.tolist(), strict=True)}
    assert hit[(0, 0, 10)] == 5 and hit[(1, 0, 10)] == 5  # c's 0.99, moved into our frame
    classes_ab = FusedMap().classes([a, b], 0.1, keys)
    hit = {tuple(k): int(x) for k, x in zip(keys.tolist(), classes_ab.tolist(), strict=True)}
    assert hit[(0, 0, 10)] == 4 and hit[(1, 0, 10)] == 4
    free = [k for k in hit if k[2] > 10]  # the rays' free voxels above the box: unlabelled
    assert free and all(hit[k] == -1 for k in free)
    cls, prob = best_class(a.full())
    assert set(cls.tolist()) == {-1, 3} and prob[cls == 3].min() > 0 and (prob[cls < 0] == 0).all()


def _wall_layer(origin: str, wall: np.ndarray, *, surface: bool, res: float = 0.1) -> Layer:
    """A layer whose origin saw `wall` (N, 3) from (0, 0, 0.3) in 3 scans, keeping the surface
    channel or not, as gossip delivers it."""
    from protocol.deltacodec import decode_delta, encode_delta
    from voxel.grid import VoxelGrid

    grid = VoxelGrid(res, surface=surface)
    for t in range(3):
        grid.integrate(wall, np.array([0.0, 0.0, 0.3]), time=float(t))
    layer = Layer(origin, res)
    layer.offer(1, 0, 1, decode_delta(encode_delta(grid.delta_since(0))))
    return layer


def test_fused_surface_is_the_layers_surface_points_and_centres_without_them():
    """A fused view's points (ROS 2 cloud, export, PLYs): each occupied voxel at the surface
    points of the layers that keep them, moved into the fused frame; the centres where none
    does (they were the centres everywhere, 37 mm off this wall)."""
    from colonyd.layers import fused_surface

    x = np.linspace(-1.0, 1.0, 201)
    wall = np.column_stack([x, np.full(x.size, 2.013), np.full(x.size, 0.3)])
    mine = _wall_layer("a", wall, surface=True)
    plain = _wall_layer("b", wall, surface=False)
    # c saw the same wall turned by -90 degrees in its own frame: (x, y) -> (y, -x)
    turned = _wall_layer("c", wall[:, [1, 0, 2]] * [1, -1, 1], surface=True)
    yaw = np.eye(4)
    yaw[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # c's frame into ours: +90 degrees
    transforms = {"a": np.eye(4), "b": np.eye(4), "c": yaw}
    # c's voxels land one key over at the wall's ends: the fused voxel (x key 10) that b's
    # voxel alone (no surface channel) lands in keeps its centre
    for layers, centred in (([mine, plain], 0), ([turned, plain], 1), ([mine, turned, plain], 0)):
        keys, lo = fused(layers, 0.1, transforms)
        occupied = keys[lo >= 0]
        points = fused_surface(layers, 0.1, occupied, transforms)
        on_wall = occupied[:, 1] == 20
        at_centre = (points == vk.keys_to_centers(occupied, 0.1)).all(axis=1)
        assert on_wall.sum() >= 21 and (at_centre & on_wall).sum() == centred
        assert np.abs(points[on_wall & ~at_centre, 1] - 2.013).max() < 0.001
        free_centres = fused_surface(layers, 0.1, keys[lo < 0], transforms)  # none lands there
        np.testing.assert_array_equal(free_centres, vk.keys_to_centers(keys[lo < 0], 0.1))
    keys, lo = fused([plain], 0.1, transforms)
    occupied = keys[lo >= 0]
    centres = fused_surface([plain], 0.1, occupied, transforms)
    np.testing.assert_array_equal(centres, vk.keys_to_centers(occupied, 0.1))
    assert fused_surface([mine], 0.1, np.zeros((0, 3), np.int64)).shape == (0, 3)  # none occupied
    own = mine.grid.occupied_keys()  # one layer in its own frame: its surface points
    np.testing.assert_array_equal(fused_surface([mine], 0.1, own), mine.grid.surface_points(own))
    # a 0.4 m layer's wall voxel (y 2.0-2.4) lands where its centre falls (y key 22): its
    # surface point 2.013 m is 0.24 m from that voxel's centre, beyond SURFACE_REACH: not shown
    coarse = _wall_layer("d", wall, surface=True, res=0.4)
    keys, lo = fused([coarse], 0.1, {"d": np.eye(4)})
    occupied = keys[lo >= 0]
    points = fused_surface([coarse], 0.1, occupied, {"d": np.eye(4)})
    off = np.abs(points - vk.keys_to_centers(occupied, 0.1)).max(axis=1)
    assert len(occupied) and off.max() <= SURFACE_REACH * 0.1


def test_live_fused_view_recomputes_only_what_changed():
    a, b = Layer("a", 0.1), Layer("b", 0.1)
    _, ds = deltas(3)
    a.offer(1, 0, 1, ds[0])
    b.offer(1, 0, 1, ds[1])
    moved = {"a": np.eye(4), "b": np.eye(4)}
    moved["b"][:3, 3] = [1.0, -0.5, 0.0]
    live = FusedMap()
    first = live.view([a, b], 0.1, moved)
    assert live.computed == 2
    again = live.view([a, b], 0.1, moved)
    assert live.computed == 2  # nothing changed: nothing recomputed
    assert all(np.array_equal(x, y) for x, y in zip(first, again, strict=True))
    b.offer(1, 1, 2, ds[2])  # b grew
    grown = live.view([a, b], 0.1, moved)
    assert live.computed == 3
    fresh = fused([a, b], 0.1, moved)
    assert np.array_equal(grown[0], fresh[0]) and np.array_equal(grown[1], fresh[1])
    assert not np.array_equal(grown[0], first[0])
    moved["a"] = moved["b"].copy()  # a's alignment changed
    live.view([a, b], 0.1, moved)
    assert live.computed == 4
    _, lo = live.view([a], 0.1, moved, weights={"a": 0.5})  # b left, a weighted: no work
    assert live.computed == 4
    np.testing.assert_allclose(lo, 0.5 * fused([a], 0.1, moved)[1], rtol=1e-6)


def test_live_fused_outputs_are_computed_once_and_follow_a_layer_and_its_alignment():
    """The live map's classes and surface points are each layer's, computed once per layer
    version and alignment: asked again with nothing changed, it computes nothing; after a
    peer's alignment changed, and after that peer's layer grew, they equal those computed
    afresh (a new `FusedMap`), not the ones it held."""
    from voxel.grid import VoxelGrid

    x = np.linspace(-1.0, 1.0, 201)
    wall = np.column_stack([x, np.full(x.size, 2.013), np.full(x.size, 0.3)])
    turned = wall[:, [1, 0, 2]] * [1, -1, 1]  # b saw it turned by -90 degrees in its own frame
    grids = {o: VoxelGrid(0.1, surface=True) for o in "ab"}
    layers = [Layer("a", 0.1), Layer("b", 0.1)]

    def see(origin: str, points: np.ndarray, cls: int, prob: float, seq: int) -> None:
        grid, n = grids[origin], len(points)
        before = grid.version
        labels = {"class_ids": np.full(n, cls), "class_probs": np.full(n, prob, np.float32)}
        grid.integrate(points, np.array([0.0, 0.0, 0.3]), time=float(seq), **labels)
        layers["ab".index(origin)].offer(1, seq - 1, seq, grid.delta_since(before))

    see("a", wall, 3, 0.6, 1)
    see("b", turned, 4, 0.9, 1)  # more sure: its class wins where both land
    yaw = np.eye(4)
    yaw[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # b's frame into ours: +90 degrees
    moved = yaw.copy()
    moved[0, 3] = 0.25  # b's alignment, corrected: 2.5 voxels further along the wall

    def outputs(live: FusedMap, transforms: dict[str, np.ndarray]) -> list[np.ndarray]:
        keys, lo = live.view(layers, 0.1, transforms)
        classes = live.classes(layers, 0.1, keys, transforms)
        points = live.surface(layers, 0.1, keys[lo >= 0], transforms)
        together = live.outputs(layers, 0.1, transforms)  # one index for both: the same
        assert same([keys, lo, classes, points], list(vars(together).values()))
        expected = reference(transforms)  # and what they should be, computed apart
        np.testing.assert_array_equal(keys, expected[0])
        np.testing.assert_allclose(lo, expected[1], rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(classes, expected[2])
        np.testing.assert_allclose(points, expected[3], atol=1e-9)
        return [keys, lo, classes, points]

    def reference(transforms: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The fused view from the agents' own grids, voxel by voxel in plain Python: each
        grid's voxel centres moved into the fused frame and keyed at 0.1 m; per key a grid's
        mean log-odds, summed over the grids; the class of the most probable labelled voxel
        landing there; an occupied key's point the mean of the surface points of the grids'
        occupied voxels landing there (moved), where within SURFACE_REACH of its centre."""
        total: dict[tuple[int, ...], float] = {}
        best: dict[tuple[int, ...], tuple[float, int]] = {}
        near: dict[tuple[int, ...], list[np.ndarray]] = {}
        for origin, grid in grids.items():
            t = transforms[origin]
            full = grid.delta_since(0)
            centres = vk.keys_to_centers(full.keys, 0.1) @ t[:3, :3].T + t[:3, 3]
            own: dict[tuple[int, ...], list[float]] = {}
            n = len(full.keys)
            ids = full.channels["class_ids"].reshape(n, -1)
            probs = full.channels["class_probs"].reshape(n, -1)
            for i, key in enumerate(map(tuple, vk.points_to_keys(centres, 0.1).tolist())):
                if not np.isnan(full.logodds[i]):
                    own.setdefault(key, []).append(float(full.logodds[i]))
                for cls, prob in zip(ids[i].tolist(), probs[i].tolist(), strict=True):
                    if cls >= 0 and prob > best.get(key, (-1.0, -1))[0]:
                        best[key] = (prob, cls)
            for key, values in own.items():
                total[key] = total.get(key, 0.0) + sum(values) / len(values)
            occupied = grid.occupied_keys()
            moved = vk.keys_to_centers(occupied, 0.1) @ t[:3, :3].T + t[:3, 3]
            surface = grid.surface_points(occupied) @ t[:3, :3].T + t[:3, 3]
            landed = map(tuple, vk.points_to_keys(moved, 0.1).tolist())
            for key, point in zip(landed, surface, strict=True):
                near.setdefault(key, []).append(point)
        order = sorted(total, key=lambda k: int(vk.pack(np.array([k]))[0]))
        keys = np.array(order, np.int64).reshape(-1, 3)
        lo = np.array([total[k] for k in order])
        classes = np.array([best.get(k, (0.0, -1))[1] for k in order])
        points = vk.keys_to_centers(keys[lo >= 0], 0.1)
        for row, key in enumerate(k for k in order if total[k] >= 0):
            if key in near:
                mean = np.mean(near[key], axis=0)
                if np.abs(mean - points[row]).max() <= SURFACE_REACH * 0.1:
                    points[row] = mean
        return [keys, lo, classes, points]

    def same(x: list[np.ndarray], y: list[np.ndarray]) -> bool:
        return all(np.array_equal(u, v) for u, v in zip(x, y, strict=True))

    live = FusedMap()
    first = outputs(live, {"a": np.eye(4), "b": yaw})
    assert same(first, outputs(FusedMap(), {"a": np.eye(4), "b": yaw}))
    assert live.counts == {"parts": 2, "labels": 2, "surfaces": 2}  # each layer's
    assert same(first, outputs(live, {"a": np.eye(4), "b": yaw})) and live.computed == 6
    second = outputs(live, {"a": np.eye(4), "b": moved})
    assert live.computed == 9  # b's again, a's held
    assert same(second, outputs(FusedMap(), {"a": np.eye(4), "b": moved}))
    see("b", turned + np.array([0.0, 0.0, 0.1]), 5, 0.95, 2)  # b grew: the next row, another class
    third = outputs(live, {"a": np.eye(4), "b": moved})
    assert live.computed == 12
    assert same(third, outputs(FusedMap(), {"a": np.eye(4), "b": moved})) and 5 in third[2]


def test_the_ros_outputs_compute_no_classes_until_a_reply_asks():
    """The ROS 2 outputs (view and points, no classes) leave the layers' labels uncomputed; the
    first reply that asks for classes computes them once, and they follow a layer that grew."""
    box = np.array([[0.05, 0.05, 1.05], [0.15, 0.05, 1.05]])
    beside = box + np.array([0.3, 0.0, 0.0])
    layers = [_labelled_layer("a", box, 3, 0.6), _labelled_layer("b", beside, 4, 0.9)]
    live = FusedMap()
    ros = live.outputs(layers, 0.1, classes=False)
    assert ros.classes is None and live.counts == {"parts": 2, "labels": 0, "surfaces": 2}
    live.outputs(layers, 0.1, classes=False)
    assert live.counts["labels"] == 0
    reply = live.outputs(layers, 0.1)
    assert live.counts == {"parts": 2, "labels": 2, "surfaces": 2}
    assert reply.classes is not None and set(reply.classes.tolist()) == {-1, 3, 4}
    assert np.array_equal(reply.points, ros.points) and np.array_equal(reply.keys, ros.keys)
    live.outputs(layers, 0.1)
    assert live.counts["labels"] == 2  # held
    grown = _labelled_layer("a", np.concatenate([box, box + np.array([0.0, 0.5, 0.0])]), 7, 0.7)
    layers[0].offer(1, 1, 2, grown.full())
    again = live.outputs(layers, 0.1)
    assert live.counts["labels"] == 3 and 7 in again.classes
    assert np.array_equal(again.classes, FusedMap().outputs(layers, 0.1).classes)


def test_the_publisher_sends_an_own_delta_while_a_scan_holds_the_grid_lock():
    """Numbering, remembering and putting an own delta never wait for the mapping thread (which
    holds the own layer's lock while it integrates a scan); a range query still sees it."""
    import threading

    from colonyd.frames import Sender
    from colonyd.metrics import Metrics
    from colonyd.publisher import Publisher
    from colonyd.runtime import open_session, zenoh_config

    _, ds = deltas(2)
    layers = Layers("me", 0.1)
    own = layers.own
    own.epoch = 3
    session = open_session(zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"]))
    held, release = threading.Event(), threading.Event()

    def integrate() -> None:
        with own.lock:
            held.set()
            release.wait(10)

    mapping = threading.Thread(target=integrate)
    try:
        pub = Publisher(session, "t", layers, Sender("me", 3), Metrics(), epoch=3)
        mapping.start()
        assert held.wait(5)
        marks: dict[str, float] = {}
        t0 = time.monotonic()
        sent = pub.publish_own(0, 1, ds[0], 1.0, marks=marks)
        assert time.monotonic() - t0 < 2.0 and sent > 0
        stages = [m for m in marks if "." not in m]  # "m.cpu", "m.runq": the thread's clocks
        assert own.seq == 1 and stages == ["numbered", "encoded", "put", "sent"]
        release.set()
        mapping.join()
        assert [(d.from_version, d.to_version) for d in own.range(0, 1)] == [(0, 1)]
    finally:
        release.set()
        session.close()


def test_the_publisher_pushes_the_history_of_versions_not_logged_when_it_was_built():
    """History push: the own history held when the publisher is built is for replicas to page
    up to the version logged (`Layer.logged`); versions integrated after it (a source that mapped
    before the publisher was built) are in no pushed frame yet. The publisher started above
    them (at the history's newest version) and never pushed their records."""
    from colonyd.frames import Sender
    from colonyd.metrics import Metrics
    from colonyd.publisher import Publisher
    from colonyd.runtime import open_session, zenoh_config

    layers = Layers("me", 0.1)
    own = layers.own
    rng = np.random.default_rng(5)
    for t in range(3):
        own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=float(t + 1))
    own.epoch, own.seq, own.logged = 3, 1, 1  # version 1 logged at seq 1; 2 and 3 not yet
    history = own.grid.history
    unlogged, _, _ = history.page(1, 10**6, upto=3)
    want = int(unlogged.records.size + unlogged.seen.size)
    session = open_session(zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"]))
    try:
        pub = Publisher(session, "t", layers, Sender("me", 3), Metrics(), epoch=3)
        sent = pub.push_history(3)  # the publisher logged versions 2 and 3 at seq 2
        assert sent == want > 0, (sent, want)
        assert pub.history_pushed == 3 and pub.push_history(3) == 0
    finally:
        session.close()


def test_an_own_snapshot_holds_what_is_logged_and_waits_for_the_publisher():
    """The own layer's snapshot is of its grid as logged at its seq: with scans integrated
    since, it waits for the publisher's next delta and takes the grid captured with it."""
    import threading

    own = Layer("me", 0.1)
    rng = np.random.default_rng(3)
    own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=1.0)
    own.seq, own.logged = 1, int(own.grid.version)
    logged = own.grid.delta_since(0)
    _, _, chunks = own.snapshot(10**6)  # nothing integrated since: at once
    assert len(chunks[0]) == len(logged)
    own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=2.0)  # not logged
    with pytest.raises(TimeoutError, match="not logged in time"):
        own.snapshot(10**6, deadline=time.monotonic() + 0.05)
    assert own.capture() is None and own._captured is None  # nobody waits: nothing kept
    got: list = []
    waiting = threading.Thread(target=lambda: got.append(own.snapshot(10**6)))
    waiting.start()
    assert own.nudge.wait(5.0)  # the publisher is asked to log at once
    with own.lock:  # the publisher's turn: the version it logs and the grid with it
        version, captured = int(own.grid.version), own.capture()
    own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=3.0)  # after: not in it
    own.seq = 2  # logged and numbered
    own.mark_logged(version, captured)
    waiting.join(5.0)
    _epoch, seq, chunks = got[0]
    assert seq == 2 and captured is not None and len(chunks[0]) == len(captured)
    replica = new_grid(0.1)
    replica.apply(chunks[0])
    expected = new_grid(0.1)
    expected.apply(captured)
    assert replica.content_equal(expected) and not replica.content_equal(own.grid)
    # a replica's layer (its content all in its origin's log) is served as held
    assert Layer("o", 0.1).logged is None


def test_an_own_snapshot_gives_up_when_the_publisher_cannot_log(monkeypatch):
    """A snapshot of unlogged content waits for one attempt of the publisher, not its full
    wait: while the state directory refuses writes, each one held the layer server's single
    worker for `UNLOGGED_WAIT_S` (range and history queries of every layer queued behind it).
    The wait here is unbounded: a snapshot that ignored the failure would never return."""
    import threading

    from colonyd import layers as layers_mod

    monkeypatch.setattr(layers_mod, "UNLOGGED_WAIT_S", 1e6)  # (a lock takes no inf)
    own = Layer("me", 0.1)
    rng = np.random.default_rng(4)
    own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=1.0)
    own.seq, own.logged = 1, int(own.grid.version)
    own.grid.integrate(rng.uniform(-1, 1, (100, 3)), np.zeros(3), time=2.0)  # not logged
    waiting, errors = ask_snapshot(own)
    assert own.nudge.wait(5.0)  # the publisher is asked to log: its attempt fails
    own.log_failed("cannot append seq 2: No space left on device")
    waiting.join(10.0)
    assert not waiting.is_alive() and len(errors) == 1
    assert "No space left on device" in str(errors[0])
    # the publisher logs again: a snapshot then waits for it and holds it
    own.nudge.clear()
    got: list = []
    waiting = threading.Thread(target=lambda: got.append(own.snapshot(10**6)), daemon=True)
    waiting.start()
    assert own.nudge.wait(5.0)
    with own.lock:
        version, captured = int(own.grid.version), own.capture()
    own.seq = 2
    own.mark_logged(version, captured)
    waiting.join(10.0)
    assert not waiting.is_alive() and got and got[0][1] == 2
