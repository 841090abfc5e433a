"""Voxel keys: packing and choosing one row per distinct key."""

from __future__ import annotations

import numpy as np
import pytest

from voxel import keys as vk


@pytest.mark.parametrize(
    ("n", "span"), [(1, 1), (50, 2), (20_000, 15), (20_000, 3000), (5000, 2**20)]
)
def test_one_per_key_picks_exactly_one_row_of_every_distinct_key(n, span):
    rng = np.random.default_rng(n + span)
    keys = rng.integers(-span, span, size=(3, n))
    distinct = set(map(tuple, keys.T.tolist()))
    for rows in (
        keys,
        keys.astype(np.float64),
    ):  # float rows of exact integers: floored coordinates
        chosen = vk.one_per_key(rows)
        picked = [tuple(k) for k in keys[:, chosen].T.tolist()]
        assert len(picked) == len(set(picked)) == len(distinct)
        assert set(picked) == distinct
        # the last row of each key, in order (the compiled beam sorting picks the same)
        last = {key: i for i, key in enumerate(map(tuple, keys.T.tolist()))}
        assert chosen.tolist() == sorted(last.values())


def test_pack_round_trips_the_whole_key_space():
    keys = np.array([[vk.KEY_MIN, 0, vk.KEY_MAX], [-1, 1, 0], [vk.KEY_MAX, vk.KEY_MIN, -7]])
    np.testing.assert_array_equal(vk.unpack(vk.pack(keys)), keys)
    assert np.all(np.diff(vk.pack(np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0]]))) > 0)


@pytest.mark.parametrize(("n", "spread"), [(10, 5), (5000, 3), (100_000, 30), (100_000, 10**6)])
def test_unique_packed_is_numpy_unique_with_inverse(n: int, spread: int) -> None:
    # dense boxes are counted, sparse ones (and few keys) sorted: the same answer either way
    keys = np.random.default_rng(n + spread).integers(-spread, spread, (n, 3))
    packed = vk.pack(keys)
    ub, inv = vk.unique_packed(packed)
    ref, ref_inv = np.unique(packed, return_inverse=True)
    np.testing.assert_array_equal(ub, ref)
    np.testing.assert_array_equal(inv, ref_inv.reshape(-1))


@pytest.mark.parametrize("shape", ["cube", "planar", "slab"])
@pytest.mark.parametrize(("n", "spread"), [(0, 1), (10, 5), (50_000, 40), (5000, 10**6)])
def test_count_blocks_is_the_number_of_distinct_blocks(shape: str, n: int, spread: int) -> None:
    # dense boxes are marked, sparse ones sorted: the same count either way
    from voxel.blocks import block_shifts, count_blocks, split_keys

    keys = np.random.default_rng(n + spread).integers(-spread, spread, (n, 3))
    shifts = block_shifts(shape)
    assert count_blocks(keys, shifts) == np.unique(split_keys(keys, shifts)[0]).size
    # the parts of a snapshot together, overlapping blocks and an empty part included
    parts = [keys[: n // 3], keys[n // 4 :], keys[:0]]
    assert count_blocks(parts, shifts) == count_blocks(keys, shifts)
