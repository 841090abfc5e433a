"""Tests of the sub-voxel surface channel: running means of hit positions, replicas, snapshots."""

from __future__ import annotations

import numpy as np
import pytest

from voxel import keys as vk
from voxel import surface
from voxel.delta import Delta
from voxel.errors import DeltaError
from voxel.grid import VoxelGrid

RES = 0.1
WALL_X = 2.0337  # 3.37 cm into its voxel [2.0, 2.1): the centre (2.05) is 16.3 mm off


def noisy_wall(rng: np.random.Generator, sigma: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """A scan of the plane x = WALL_X (1 m x 1 m) with range noise along x, from the origin."""
    side = np.arange(-0.495, 0.5, 0.01)  # 10 points across each voxel, centred
    yy, zz = np.meshgrid(side, side)
    x = WALL_X + rng.normal(0.0, sigma, yy.size)
    return np.stack([x, yy.ravel(), zz.ravel()], axis=1), np.zeros(3)


def wall_voxels(grid: VoxelGrid) -> np.ndarray:
    """Occupied keys of the wall's voxel layer (x key 20), away from its edges."""
    keys = grid.occupied_keys()
    inner = (keys[:, 0] == 20) & (np.abs(keys[:, 1:] + 0.5).max(axis=1) < 4)
    return keys[inner]


def test_surface_points_lie_on_the_wall_where_centres_do_not(kernel_path):
    grid = VoxelGrid(RES, surface=True)
    rng = np.random.default_rng(1)
    for t in range(10):
        pts, origin = noisy_wall(rng)
        grid.integrate(pts, origin, time=float(t))
    keys = wall_voxels(grid)
    assert len(keys) >= 40
    surf = grid.surface_points(keys)
    centres = vk.keys_to_centers(keys, RES)
    # the centres are 16.3 mm behind the wall, the running means on it to ~0.5 mm; what is
    # published is their code (-41.4 of 1/254 voxel) rounded to a multiple of PUBLISH_STEP 16:
    # -48, 2.6 mm off the wall (within half a step, 3.15 mm at 10 cm)
    assert np.allclose(centres[:, 0] - WALL_X, 0.0163, atol=1e-6)
    assert np.allclose(surf[:, 0], 2.05 - 48 / surface.WIRE_SCALE * RES, rtol=0, atol=1e-12)
    means = grid.channel_at_keys("surface_mean", keys)[:, 0] * (RES / surface.STORE_SCALE)
    assert np.abs(centres[:, 0] + means - WALL_X).max() < 0.0008
    # along the wall the points fill each voxel evenly: the mean is its centre (to half a code)
    assert np.abs(surf[:, 1:] - centres[:, 1:]).max() < RES / 508
    # the occupied voxels' surface is what occupied_surface gives
    assert np.array_equal(grid.occupied_surface(), grid.surface_points(grid.occupied_keys()))
    # free and unknown voxels: their centres
    free = grid.free_keys()[:5]
    assert np.array_equal(grid.surface_points(free), vk.keys_to_centers(free, RES))
    far = np.array([[500, 500, 500]])
    assert np.array_equal(grid.surface_points(far), vk.keys_to_centers(far, RES))


def test_without_the_channel_surface_points_are_centres():
    grid = VoxelGrid(RES, surface=False)
    pts, origin = noisy_wall(np.random.default_rng(2))
    grid.integrate(pts, origin, time=0.0)
    assert "surface" not in grid.store.channels
    keys = grid.occupied_keys()
    assert np.array_equal(grid.surface_points(keys), vk.keys_to_centers(keys, RES))


def test_two_scans_weigh_equally_whatever_their_point_counts():
    grid = VoxelGrid(RES, surface=True)
    origin = np.zeros(3)
    # scan 1: three points at x offset +0.02 m in voxel key (20, 0, 0); scan 2: one at -0.01 m
    a = np.array([[2.07, 0.03, 0.05], [2.07, 0.05, 0.05], [2.07, 0.07, 0.05]])
    b = np.array([[2.04, 0.05, 0.05]])
    grid.integrate(a, origin, time=0.0)
    key = np.array([[20, 0, 0]])

    def mean() -> np.ndarray:
        offset = grid.channel_at_keys("surface_mean", key)[0] * (RES / surface.STORE_SCALE)
        return vk.keys_to_centers(key, RES)[0] + offset

    def published_x() -> int:
        return int(grid.channel_at_keys("surface", key)[0, 0])

    assert np.allclose(mean(), [2.07, 0.05, 0.05], atol=2e-6)
    # published: 0.2 voxel is code 50.8, 51, to the step of 16: 48 (y and z: the centre, 0)
    assert published_x() == 48
    assert np.allclose(grid.surface_points(key)[0], [2.05 + 48 / 2540, 0.05, 0.05], atol=1e-12)
    grid.integrate(b, origin, time=1.0)
    # the running mean of two scans, one sample each: (2.07 + 2.04) / 2
    assert np.allclose(mean(), [2.055, 0.05, 0.05], atol=2e-6)
    # 0.05 voxel: code 12.7, 13, to the step: 16 (the voxel's log-odds changed: it is sent anyway)
    assert published_x() == 16
    assert int(grid.channel_at_keys("surface_weight", key)[0]) == 2


def test_published_codes_are_rounded_to_the_step():
    codes = np.array([0, 7, 8, 9, 24, 119, 120, 127, -127, -121, -8, -9])
    want = [0, 0, 0, 16, 32, 112, 127, 127, -127, -127, 0, -16]  # halves to even; +-128: +-127
    got = surface.publish(codes)
    assert got.dtype == np.int8 and got.tolist() == want


def test_a_mean_that_moves_follows_alone_a_step_away_and_at_once_when_sent_anyway(kernel_path):
    from voxel.blocks import BlockStore

    store = BlockStore()
    blocks, offsets = store.split(np.array([[3, 4, 5]]))
    slots = store.ensure(blocks)
    one = np.zeros(1, dtype=np.int64)

    def scan(x: float, sent: bool) -> tuple[bool, int]:
        """One scan's points with mean offset x voxel on the x axis; (moved, published code)."""
        sums = np.array([[x, 0.0, 0.0]])
        moved = surface.fuse_surface(store, slots, offsets, one, sums, np.ones(1), np.array([sent]))
        return bool(moved[0]), int(store.channel("surface")[slots[0], offsets[0], 0])

    assert scan(0.1, False) == (True, 32)  # first hit: code 25 (0.1 voxel) -> 32
    assert scan(0.2, False) == (False, 32)  # mean 0.15: code 38, rounds to 32: nothing new
    assert scan(0.3, False) == (True, 48)  # mean 0.2: code 51, 19 from 32: follows alone
    assert scan(0.3, False) == (False, 48)  # mean 0.225: code 57, 9 from 48: stays
    assert scan(0.3, True) == (True, 64)  # mean 0.24: code 61, sent anyway: follows, 64
    assert scan(0.24, True) == (False, 64)  # mean 0.24: code 61, still 64: nothing new


def test_a_change_below_publish_codes_takes_no_new_version():
    grid = VoxelGrid(RES, surface=True)
    origin = np.zeros(3)
    pts = np.array([[2.07, 0.05, 0.05]])
    for t in range(10):
        grid.integrate(pts, origin, time=float(t))  # occupied, then clamped: nothing new
    v = grid.version
    grid.integrate(pts + np.array([1e-5, 0, 0]), origin, time=10.0)  # moves the mean by 1 um
    assert grid.version == v and len(grid.delta_since(v)) == 0
    far = pts + np.array([0.028, 0, 0])  # 0.48 voxel from the centre; the mean was 0.2 (code 51)
    for t in (11.0, 12.0):  # the means of 12 and 13 scans: 0.223 and 0.243 (codes 57 and 62)
        grid.integrate(far, origin, time=t)
        assert grid.version == v and len(grid.delta_since(v)) == 0  # < 16 codes from 48
    grid.integrate(far, origin, time=13.0)  # 14 scans: 0.26 voxel, code 66: 18 from 48
    delta = grid.delta_since(v)
    assert grid.version == v + 1 and delta.keys.tolist() == [[20, 0, 0]]
    assert delta.channels["surface"][0].tolist() == [64, 0, 0]  # to the step of 16


def test_replica_reproduces_the_surface_within_the_wire_quantum():
    origin = VoxelGrid(RES, surface=True)
    rng = np.random.default_rng(3)
    replica = VoxelGrid(RES, surface=False)
    v = 0
    for t in range(4):
        pts, o = noisy_wall(rng)
        origin.integrate(pts, o, time=float(t))
        replica.apply(origin.delta_since(v))
        v = origin.version
    keys = origin.occupied_keys()
    assert np.array_equal(replica.surface_points(keys), origin.surface_points(keys))
    assert replica.content_equal(origin)
    full = origin.delta_since(0)
    sent = full.channels
    assert "surface" in sent and "surface_weight" not in sent and "surface_mean" not in sent
    assert not sent["surface"][~full.occupied].any()  # free voxels travel as 0 0 0
    assert sent["surface"][full.occupied].any()
    # the published codes are multiples of PUBLISH_STEP (or +-127) and follow the running means
    # within PUBLISH_CODES
    means = origin.channel_at_keys("surface_mean", keys) / surface.STORE_STEP
    codes = origin.channel_at_keys("surface", keys).astype(np.int64)
    assert np.all((codes % surface.PUBLISH_STEP == 0) | (np.abs(codes) == surface.WIRE_MAX))
    assert np.abs(means - codes).max() < surface.PUBLISH_CODES + 0.5


def test_snapshot_keeps_the_surface_and_its_weights(tmp_path):
    grid = VoxelGrid(RES, surface=True)
    pts, o = noisy_wall(np.random.default_rng(4))
    grid.integrate(pts, o, time=0.0)
    grid.save(tmp_path / "g.npz")
    back = VoxelGrid.load(tmp_path / "g.npz")
    keys = grid.occupied_keys()
    assert back.surface and np.array_equal(back.surface_points(keys), grid.surface_points(keys))
    assert np.array_equal(
        back.channel_at_keys("surface_weight", keys), grid.channel_at_keys("surface_weight", keys)
    )


def test_forget_clears_the_surface():
    grid = VoxelGrid(RES, surface=True)
    pts, o = noisy_wall(np.random.default_rng(5))
    grid.integrate(pts, o, time=0.0)
    keys = grid.occupied_keys()
    grid.forget(now=100.0, after=10.0)
    assert np.array_equal(grid.surface_points(keys), vk.keys_to_centers(keys, RES))


@pytest.mark.parametrize("bad", [-128, 128, 300])
def test_delta_refuses_codes_outside_the_half_cell(bad):
    with pytest.raises(DeltaError, match="surface codes must lie in"):
        Delta(RES, 0, 1, np.zeros((1, 3)), [1.0], [0.0], {"surface": np.array([[0, bad, 0]])})
    with pytest.raises(DeltaError, match="finite"):
        Delta(RES, 0, 1, np.zeros((1, 3)), [1.0], [0.0], {"surface": np.array([[0, np.nan, 0]])})


def test_both_paths_give_the_same_surface_to_a_stored_quantum(monkeypatch):
    from voxel import kernels

    pytest.importorskip("numba")
    grids = []
    for on in (False, True):
        monkeypatch.setattr(kernels._switch, "on", on)
        assert on == kernels.warm()
        grid = VoxelGrid(RES, surface=True)
        rng = np.random.default_rng(7)
        for t in range(3):
            pts, o = noisy_wall(rng)
            grid.integrate(pts, o, time=float(t))
        grids.append(grid)
    numpy_grid, compiled = grids
    keys = numpy_grid.occupied_keys()
    assert np.array_equal(keys, compiled.occupied_keys())
    a = numpy_grid.channel_at_keys("surface_mean", keys).astype(np.int64)
    b = compiled.channel_at_keys("surface_mean", keys).astype(np.int64)
    assert np.abs(a - b).max() <= 1  # the compiled path sums repeated keys' points apart
    assert numpy_grid.content_equal(compiled)


def test_the_compiled_fusion_is_the_numpy_fusion_bit_for_bit(monkeypatch):
    from voxel import kernels
    from voxel.blocks import BlockStore

    pytest.importorskip("numba")
    rng = np.random.default_rng(8)
    keys = np.unique(rng.integers(-20, 20, (300, 3)), axis=0)
    inverse = rng.integers(0, len(keys), 2000)
    sums = rng.uniform(-0.5, 0.5, (2000, 3)) * 3
    counts = rng.integers(1, 4, 2000)
    sent = [rng.random(len(keys)) < 0.3 for _ in range(5)]  # carried anyway by each scan's delta
    out = []
    for on in (False, True):
        monkeypatch.setattr(kernels._switch, "on", on)
        assert on == kernels.warm()
        store = BlockStore()
        blocks, offsets = store.split(keys)
        slots = store.ensure(np.unique(blocks))[np.searchsorted(np.unique(blocks), blocks)]
        moved = [
            surface.fuse_surface(store, slots, offsets, inverse, sums / k, counts, sent[i])
            for i, k in enumerate((1.0, 1.01, 2.0, 2.0, 0.5))
        ]
        out.append((moved, {n: store.channels[n].copy() for n in ("surface", "surface_mean")}))
    (m_np, ch_np), (m_c, ch_c) = out
    assert all(np.array_equal(a, b) for a, b in zip(m_np, m_c, strict=True))
    assert m_np[0].all() and not m_np[3].all()  # new voxels publish; a repeated scan mostly not
    for name in ch_np:
        assert np.array_equal(ch_np[name], ch_c[name]), name
