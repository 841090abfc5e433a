"""Ray traversal against a per-ray reference, and grids with different block shapes."""

from __future__ import annotations

import numpy as np
import pytest

from voxel import keys as vk
from voxel.blocks import join_keys, shape_for, split_keys
from voxel.errors import InputError
from voxel.grid import VoxelGrid
from voxel.raycast import FREE, HIT, ray_keys, trace
from voxel.sensor import SensorModel

RES = 0.1


def _reference(origin: np.ndarray, hits: np.ndarray, clear_ends: np.ndarray) -> tuple[set, set]:
    """Free and hit voxel keys of one scan, one ray at a time: every voxel a ray passes before
    its end voxel is free, hit voxels win; rays go to hit voxel centres and to the clear ends."""
    hit_keys = {tuple(k) for k in vk.points_to_keys(hits, RES)}
    centres = vk.keys_to_centers(np.array(sorted(hit_keys)).reshape(-1, 3), RES)
    free: set = set()
    for end in np.concatenate([centres, clear_ends]):
        path = ray_keys(origin, end, RES)
        free.update(tuple(k) for k in path[:-1])
    return free - hit_keys, hit_keys


def _traced(origin, hits, clear_ends, shifts) -> tuple[set, set]:
    tr = trace(origin, vk.points_to_keys(hits, RES).T, clear_ends, RES, shifts)
    b, o = np.nonzero(tr.cells)
    keys = join_keys(tr.blocks[b], o, shifts)
    vals = tr.cells[b, o]
    return {tuple(k) for k in keys[vals == FREE]}, {tuple(k) for k in keys[vals == HIT]}


@pytest.mark.parametrize("shifts", [(2, 2, 2), (3, 3, 0), (0, 1, 3)])
def test_trace_visits_exactly_the_voxels_of_each_ray(shifts, kernel_path):
    rng = np.random.default_rng(11)
    origin = rng.uniform(
        -0.05, 0.05, size=3
    )  # irrational-looking: no ray passes exactly through an edge
    # Long and short rays in every direction, some ending in the origin voxel, several per voxel.
    hits = origin + rng.normal(size=(4000, 3)) * rng.choice([0.05, 0.5, 3.0], size=(4000, 1))
    dirs = rng.normal(size=(300, 3))
    clear_ends = origin + dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * 4.0
    free, hit = _traced(origin, hits, clear_ends, shifts)
    ref_free, ref_hit = _reference(origin, hits, clear_ends)
    assert hit == ref_hit
    assert free == ref_free


def test_trace_of_a_planar_scan_stays_in_its_layer():
    origin = np.array([0.21, -0.33, 0.3123])
    a = np.linspace(-2.3, 2.3, 1081)
    hits = (
        origin
        + np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
        * np.linspace(0.5, 6.0, a.size)[:, None]
    )
    free, hit = _traced(origin, hits, np.empty((0, 3)), (3, 3, 0))
    ref_free, ref_hit = _reference(origin, hits, np.empty((0, 3)))
    assert (free, hit) == (ref_free, ref_hit)
    assert {k[2] for k in free | hit} == {3}


def test_split_and_join_keys_round_trip_in_every_shape():
    keys = np.random.default_rng(2).integers(-5000, 5000, size=(1000, 3))
    for shifts in [(2, 2, 2), (3, 3, 0), (1, 0, 3)]:
        blocks, offsets = split_keys(keys, shifts)
        assert offsets.max() < 1 << sum(shifts)
        np.testing.assert_array_equal(join_keys(blocks, offsets, shifts), keys)


def _scans(seed: int):
    rng = np.random.default_rng(seed)
    for i in range(4):
        origin = rng.normal(size=3) * 0.3
        pts = origin + rng.normal(size=(2000, 3)) * [2.0, 2.0, 0.05 if i % 2 else 1.0]
        yield pts, origin, rng.integers(0, 255, size=(2000, 3), dtype=np.uint8)


def test_planar_blocks_hold_the_same_map_in_less_memory(tmp_path):
    cube, planar = VoxelGrid(RES), VoxelGrid(RES, block_shape="planar")
    for i, (pts, origin, colours) in enumerate(_scans(4)):
        for g in (cube, planar):
            g.integrate(
                pts, origin, time=float(i), colours=colours, no_return=np.arange(len(pts)) % 7 == 0
            )
    assert planar.content_equal(cube) and cube.content_equal(planar)
    np.testing.assert_array_equal(
        np.sort(planar.history.view()["key"]), np.sort(cube.history.view()["key"])
    )
    # a planar scan: one layer of voxels fills flat blocks, a quarter of cubes at best
    flat_cube, flat = VoxelGrid(0.05), VoxelGrid(0.05, block_shape="planar")
    origin = np.array([0.0, 0.0, 0.3123])
    a = np.linspace(-2.3, 2.3, 1081)
    pts = origin + np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * 5.0
    for g in (flat_cube, flat):
        g.integrate(pts, origin, time=0.0)
    assert flat.content_equal(flat_cube)
    assert flat.nbytes() / flat.known_count() < 0.5 * flat_cube.nbytes() / flat_cube.known_count()
    path = tmp_path / "flat.npz"
    flat.save(path)
    back = VoxelGrid.load(path)
    assert back.store.shifts == (3, 3, 0) and back.content_equal(flat)


def test_block_shape_errors_say_what_was_expected():
    with pytest.raises(InputError, match=r"block shape must be one of .*'cube'.*found 'flat'"):
        VoxelGrid(RES, block_shape="flat")
    with pytest.raises(InputError, match="three of 1, 2, 4, 8 voxels, found \\(4, 4, 3\\)"):
        VoxelGrid(RES, block_shape=(4, 4, 3))


@pytest.mark.parametrize("limit", [20_000, 600])
def test_a_box_too_large_for_one_scratch_volume_is_split_and_merged(
    monkeypatch, limit, kernel_path
):
    import voxel.raycast as rc

    monkeypatch.setattr(rc, "DENSE_LIMIT", limit)  # small limits force wedges, then sparse tracing
    rng = np.random.default_rng(5)
    origin = rng.uniform(-0.05, 0.05, size=3)
    hits = origin + rng.normal(size=(3000, 3)) * [2.0, 2.0, 0.4]
    dirs = rng.normal(size=(200, 3))
    clear_ends = origin + dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * 3.0
    keys = vk.points_to_keys(hits, RES).T
    tr = trace(origin, keys, clear_ends, RES, (2, 2, 2), want_inverse=True)
    b, o = np.nonzero(tr.cells)
    found = join_keys(tr.blocks[b], o, (2, 2, 2))
    vals = tr.cells[b, o]
    ref_free, ref_hit = _reference(origin, hits, clear_ends)
    assert {tuple(k) for k in found[vals == HIT]} == ref_hit
    assert {tuple(k) for k in found[vals == FREE]} == ref_free
    assert np.all(np.diff(tr.blocks) > 0)  # merged: each block once, in key order
    np.testing.assert_array_equal(tr.hit_keys[tr.inverse], keys.T)  # each point finds its voxel


def test_rays_along_an_axis_and_ends_on_voxel_faces(kernel_path):
    # origin and ends on voxel faces, rays along the axes and in coordinate planes: every fixed
    # coordinate is folded, nothing leaves the one-layer box of a planar scan
    origin = np.array([0.3, 0.2, 0.5]) * RES * 2
    ends = []
    for d in np.eye(3):
        for s in (1, -1):
            for length in (0.35, 1.0, 2.05):
                ends.append(origin + s * d * length)
    ends = np.array(ends)
    for shifts in [(2, 2, 2), (3, 3, 0)]:
        free, hit = _traced(origin, ends, np.empty((0, 3)), shifts)
        assert (free, hit) == _reference(origin, ends, np.empty((0, 3)))
    flat = ends[np.abs(ends[:, 2] - origin[2]) < 1e-12]
    free, hit = _traced(origin, flat, flat[:2] * 1.5, (3, 3, 0))
    assert (free, hit) == _reference(origin, flat, flat[:2] * 1.5)


@pytest.mark.parametrize(
    ("flat_below", "scan_ratio"), [(3000, 1.0), (40, 1.0), (1, 1.0), (40, 0.0), (40, np.inf)]
)
def test_the_compiled_sweep_visits_what_the_numpy_sweep_visits(monkeypatch, flat_below, scan_ratio):
    # Both paths must give bit-identical traversals, also where the numpy sweep switches from
    # stepping runs to enumerating them (FLAT_BELOW) at some step of the longest runs, and
    # whichever way the compiled one finds the touched blocks (SCAN_RATIO 0: as it marks cells;
    # inf: by reading the box after).
    pytest.importorskip("numba")
    import voxel.raycast as rc
    from voxel import kernels

    monkeypatch.setattr(rc, "FLAT_BELOW", flat_below)
    monkeypatch.setattr(rc, "SCAN_RATIO", scan_ratio)
    rng = np.random.default_rng(flat_below)
    for shifts in [(2, 2, 2), (3, 3, 0), (0, 1, 3)]:
        origin = rng.uniform(-0.05, 0.05, size=3)
        scale = rng.choice([0.05, 0.5, 3.0], size=(2000, 1)) * [1.0, 1.0, 0.3]
        hits = origin + rng.normal(size=(2000, 3)) * scale
        hits[::50, 2] = origin[2]  # rays in the origin's layer: a fixed axis folded in
        dirs = rng.normal(size=(200, 3))
        clear_ends = origin + dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * 4.0
        keys = vk.points_to_keys(hits, RES).T
        out = []
        for flag in ("0", "1"):
            monkeypatch.setattr(kernels._switch, "on", flag == "1")
            out.append(trace(origin, keys, clear_ends, RES, shifts, want_inverse=True))
        assert kernels.trace() is not None
        numpy_tr, compiled_tr = out
        np.testing.assert_array_equal(compiled_tr.blocks, numpy_tr.blocks)
        np.testing.assert_array_equal(compiled_tr.cells, numpy_tr.cells)
        np.testing.assert_array_equal(compiled_tr.hit_keys, numpy_tr.hit_keys)
        np.testing.assert_array_equal(compiled_tr.inverse, numpy_tr.inverse)


def test_slab_blocks_hold_a_3d_lidar_scan_in_less_memory():
    """Long, thin, nearly level rays at fine resolution fill a quarter of 4x4x4 cubes; 4x4x1
    slabs hold the same scan in far less memory per known voxel."""
    origin = np.array([0.01, 0.02, 1.8])
    elev, azim = np.meshgrid(np.radians(np.linspace(-15, 5, 16)), np.linspace(-np.pi, np.pi, 256))
    d = np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)], -1)
    d = d.reshape(-1, 3)
    r = np.where(d[:, 2] < 0, np.minimum(1.8 / np.maximum(-d[:, 2], 1e-9), 12.0), 12.0)
    pts = origin + d * r[:, None]  # a ground plane, and clear rays to 12 m
    cube, slab = VoxelGrid(0.05), VoxelGrid(0.05, block_shape="slab")
    for g in (cube, slab):
        g.integrate(pts, origin, time=0.0, sensor=SensorModel(max_range=10.0))
    assert slab.store.shifts == (2, 2, 0) and shape_for("lidar3d") == "slab"
    assert shape_for("lidar2d") == "planar" and shape_for("depth") == "cube"
    assert abs(slab.known_count() - cube.known_count()) <= 1e-3 * cube.known_count()
    assert np.array_equal(
        np.sort(vk.pack(slab.occupied_keys())), np.sort(vk.pack(cube.occupied_keys()))
    )
    per_slab = slab.nbytes() / slab.known_count()
    assert per_slab < 0.8 * cube.nbytes() / cube.known_count()
