"""Tests of voxel.octomap_io: round trips, agreement with OctoMap, real maps and error paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.shared import SHARED_DATA
from voxel.errors import FileFormatError, InputError
from voxel.keys import pack
from voxel.octomap_io import read_bt, read_bt_leaves, write_bt

pyoctomap = pytest.importorskip("pyoctomap")

DATA = SHARED_DATA / "octomap"
REAL_MAPS = {"fr_079.bt": 0.05, "geb079.bt": 0.08}


def _sorted_packed(keys: np.ndarray) -> np.ndarray:
    return np.sort(pack(keys))


def _expand(keys: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Sorted packed finest-level keys covered by leaves (minimum-corner key, depth)."""
    parts = [np.empty(0, dtype=np.int64)]
    for d in np.unique(depth):
        side = np.arange(1 << (16 - int(d)))
        offsets = np.stack(np.meshgrid(side, side, side, indexing="ij"), axis=-1).reshape(-1, 3)
        voxels = (keys[depth == d][:, None, :] + offsets[None, :, :]).reshape(-1, 3)
        parts.append(pack(voxels))
    return np.sort(np.concatenate(parts))


def _octomap_leaves(tree: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leaves of a pyoctomap tree: minimum-corner keys (our convention), depth, occupied."""
    res = tree.getResolution()
    rows = [
        (*leaf.getCoordinate(), leaf.getDepth(), tree.isNodeOccupied(leaf.current_node))
        for leaf in tree.begin_leafs()
    ]
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    depth = table[:, 3].astype(np.int64)
    half = (1 << (16 - depth)) / 2.0
    keys = np.round(table[:, :3] / res - half[:, None]).astype(np.int64)
    return keys, depth, table[:, 4].astype(bool)


def _octomap_voxels(path: Path) -> tuple[float, int, np.ndarray, int]:
    """Resolution, node count, sorted packed occupied voxels and free count, read by OctoMap."""
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    keys, depth, occupied = _octomap_leaves(tree)
    n_free = int(np.sum(8 ** (16 - depth[~occupied])))
    return tree.getResolution(), tree.size(), _expand(keys[occupied], depth[occupied]), n_free


def _random_map(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random occupied and free voxels around the origin, plus a solid and a free 16^3 block."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    solid, empty = grid + np.array([32, -64, 0]), grid + np.array([-48, 16, -16])
    scattered = np.unique(rng.integers(-400, 400, size=(6000, 3)), axis=0)
    in_blocks = np.isin(pack(scattered), pack(np.concatenate([solid, empty])))
    scattered = scattered[~in_blocks]
    keys = np.concatenate([scattered, solid, empty])
    occupied = np.concatenate(
        [
            rng.random(scattered.shape[0]) < 0.5,
            np.ones(len(solid), bool),
            np.zeros(len(empty), bool),
        ]
    )
    return keys, occupied


def _write_raw(path: Path, header: str, data: bytes = b"") -> Path:
    path.write_bytes(header.encode("ascii") + data)
    return path


HEADER = "# Octomap OcTree binary file\nid OcTree\nsize {size}\nres {res}\ndata\n"


def test_round_trip_keeps_occupied_and_free_voxels(tmp_path: Path) -> None:
    keys, occupied = _random_map(0)
    path = tmp_path / "map.bt"
    write_bt(path, 0.1, keys, occupied)
    bt = read_bt(path)
    assert bt.resolution == 0.1
    assert bt.keys.dtype == np.int64
    assert bt.occupied.dtype == np.bool_
    np.testing.assert_array_equal(
        _sorted_packed(bt.keys[bt.occupied]), _sorted_packed(keys[occupied])
    )
    np.testing.assert_array_equal(
        _sorted_packed(bt.keys[~bt.occupied]), _sorted_packed(keys[~occupied])
    )
    leaves = read_bt_leaves(path)
    assert leaves.keys.shape[0] < keys.shape[0]  # the two 16^3 blocks were pruned
    assert set(np.unique(leaves.depth).tolist()) == {12, 16}


def test_round_trip_of_extreme_and_duplicate_keys(tmp_path: Path) -> None:
    keys = np.array([[-32768, -32768, -32768], [32767, 32767, 32767], [0, -1, 5], [0, -1, 5]])
    occupied = np.array([False, True, False, True])
    path = tmp_path / "edges.bt"
    write_bt(path, 0.25, keys, occupied)
    bt = read_bt(path)
    order = np.argsort(pack(bt.keys))
    np.testing.assert_array_equal(bt.keys[order], keys[[0, 2, 1]])
    np.testing.assert_array_equal(bt.occupied[order], [False, True, True])  # occupied wins


def test_empty_map_round_trips_and_loads_in_octomap(tmp_path: Path) -> None:
    path = tmp_path / "empty.bt"
    write_bt(path, 0.2, np.empty((0, 3), np.int64), np.empty(0, bool))
    bt = read_bt(path)
    assert bt.resolution == 0.2
    assert bt.keys.shape == (0, 3)
    assert bt.occupied.shape == (0,)
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    assert tree.size() == 0
    assert tree.getResolution() == 0.2


def test_octomap_reads_our_file_with_the_same_voxels(tmp_path: Path) -> None:
    keys, occupied = _random_map(1)
    path = tmp_path / "ours.bt"
    write_bt(path, 0.05, keys, occupied)
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    assert tree.getResolution() == 0.05
    leaf_keys, depth, leaf_occupied = _octomap_leaves(tree)
    occ = _expand(leaf_keys[leaf_occupied], depth[leaf_occupied])
    free = _expand(leaf_keys[~leaf_occupied], depth[~leaf_occupied])
    np.testing.assert_array_equal(occ, _sorted_packed(keys[occupied]))
    np.testing.assert_array_equal(free, _sorted_packed(keys[~occupied]))


def test_we_read_a_tree_written_by_octomap(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    angle = rng.uniform(0.0, 2.0 * np.pi, 3000)
    height = rng.uniform(-1.0, 2.0, 3000)
    wall = np.column_stack([4.0 * np.cos(angle), 3.0 * np.sin(angle), height])
    floor = np.column_stack([rng.uniform(-3.5, 3.5, (1000, 2)), np.full(1000, -1.05)])
    tree = pyoctomap.OcTree(0.1)
    tree.insertPointCloud(np.concatenate([wall, floor]), np.array([0.3, -0.2, 0.5]))
    path = tmp_path / "octomap.bt"
    assert tree.writeBinary(str(path))
    keys, depth, occupied = _octomap_leaves(tree)
    assert occupied.any()
    assert (~occupied).any()
    assert (depth < 16).any()

    leaves = read_bt_leaves(path)
    ours = set(
        zip(
            pack(leaves.keys).tolist(), leaves.depth.tolist(), leaves.occupied.tolist(), strict=True
        )
    )
    theirs = set(zip(pack(keys).tolist(), depth.tolist(), occupied.tolist(), strict=True))
    assert ours == theirs
    bt = read_bt(path)
    assert bt.resolution == 0.1
    np.testing.assert_array_equal(
        _sorted_packed(bt.keys[bt.occupied]), _expand(keys[occupied], depth[occupied])
    )
    np.testing.assert_array_equal(
        _sorted_packed(bt.keys[~bt.occupied]), _expand(keys[~occupied], depth[~occupied])
    )


@pytest.mark.parametrize("name", sorted(REAL_MAPS))
def test_real_map_loads_and_re_exports(name: str, tmp_path: Path) -> None:
    if not DATA.is_dir():
        pytest.skip(f"real OctoMap maps not found: {DATA} is missing")
    # (OctoMap's reading of this map only: under xdist the other map's test may run elsewhere)
    res, size, occ, n_free = _octomap_voxels(DATA / name)
    bt = read_bt(DATA / name)
    assert bt.resolution == REAL_MAPS[name] == res
    n_occupied = int(bt.occupied.sum())
    assert 100_000 < n_occupied < bt.keys.shape[0]
    np.testing.assert_array_equal(_sorted_packed(bt.keys[bt.occupied]), occ)
    assert np.count_nonzero(~bt.occupied) == n_free

    # Re-exported, the tree is OctoMap's own to the byte: the same node count and resolution in
    # the header, the same data (OctoMap reading files we write is test_octomap_reads_our_file).
    path = tmp_path / name
    write_bt(path, bt.resolution, bt.keys, bt.occupied)
    ours, theirs = (_header_and_data(p) for p in (path, DATA / name))
    assert ours[0] == theirs[0] == {"id": "OcTree", "size": str(size), "res": str(res)}
    assert ours[1] == theirs[1]


def _header_and_data(path: Path) -> tuple[dict[str, str], bytes]:
    """A .bt file's header fields (comments left out) and its data bytes."""
    raw = path.read_bytes()
    head, data = raw.split(b"\ndata\n", 1)
    lines = [ln.split(" ", 1) for ln in head.decode("ascii").splitlines() if not ln.startswith("#")]
    return {k: v for k, v in lines}, data


def test_expansion_beyond_max_voxels_is_refused(tmp_path: Path) -> None:
    keys, occupied = _random_map(3)
    path = tmp_path / "map.bt"
    write_bt(path, 0.1, keys, occupied)
    with pytest.raises(
        FileFormatError, match=r"expected at most max_voxels=1000 voxels .* found \d+"
    ):
        read_bt(path, max_voxels=1000)


def _valid_file(tmp_path: Path) -> bytes:
    path = tmp_path / "valid.bt"
    write_bt(path, 0.1, np.array([[0, 0, 0], [5, -3, 2]]), np.array([True, False]))
    return path.read_bytes()


def test_truncated_file_is_rejected(tmp_path: Path) -> None:
    raw = _valid_file(tmp_path)
    path = tmp_path / "truncated.bt"
    path.write_bytes(raw[:-3])
    with pytest.raises(FileFormatError, match=r"truncated.bt: truncated tree data: expected more"):
        read_bt(path)


def test_header_without_data_line_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(tmp_path / "short.bt", "# Octomap OcTree binary file\nid OcTree\nsize 3\n")
    with pytest.raises(FileFormatError, match=r"truncated header: expected a 'data' line"):
        read_bt(path)


def test_trailing_garbage_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "trailing.bt"
    path.write_bytes(_valid_file(tmp_path) + b"\x00\x00\x00")
    with pytest.raises(
        FileFormatError, match=r"expected the file to end after the tree .* found 3 more"
    ):
        read_bt(path)


def test_wrong_first_line_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "wrong.bt"
    path.write_bytes(b"# Octomap OcTree file\nid OcTree\nsize 0\nres 0.1\ndata\n")
    with pytest.raises(
        FileFormatError,
        match=r"expected the first line to start with '# Octomap OcTree binary file'",
    ):
        read_bt(path)


def test_wrong_tree_id_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(
        tmp_path / "colour.bt", HEADER.replace("OcTree\n", "ColorOcTree\n").format(size=0, res=0.1)
    )
    with pytest.raises(FileFormatError, match=r"expected 'id OcTree', found 'ColorOcTree'"):
        read_bt(path)


@pytest.mark.parametrize("res", ["0", "-0.1", "nan", "inf", "abc"])
def test_bad_resolution_is_rejected(tmp_path: Path, res: str) -> None:
    path = _write_raw(tmp_path / "res.bt", HEADER.format(size=0, res=res))
    with pytest.raises(
        FileFormatError, match=rf"expected 'res' to be a resolution > 0, found '{res}'"
    ):
        read_bt(path)


def test_bad_size_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(tmp_path / "size.bt", HEADER.format(size=-4, res=0.1))
    with pytest.raises(
        FileFormatError, match=r"expected 'size' to be a node count >= 0, found '-4'"
    ):
        read_bt(path)


def test_node_count_mismatch_is_rejected(tmp_path: Path) -> None:
    raw = _valid_file(tmp_path)
    start = raw.index(b"data\n") + 5
    path = _write_raw(tmp_path / "count.bt", HEADER.format(size=7, res=0.1), raw[start:])
    with pytest.raises(
        FileFormatError, match=r"expected 7 tree nodes \(header 'size'\), found \d+"
    ):
        read_bt(path)


def test_tree_deeper_than_sixteen_levels_is_rejected(tmp_path: Path) -> None:
    data = b"\x03\x00" * 17 + b"\x02\x00"  # child 0 inner 17 times, then one occupied leaf
    path = _write_raw(tmp_path / "deep.bt", HEADER.format(size=19, res=0.1), data)
    with pytest.raises(
        FileFormatError, match=r"expected a tree of 16 levels, found inner nodes at depth 17"
    ):
        read_bt(path)


def test_data_for_an_empty_tree_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(tmp_path / "empty.bt", HEADER.format(size=0, res=0.1), b"\x02\x00")
    with pytest.raises(FileFormatError, match=r"expected no tree data for 'size 0', found 2 bytes"):
        read_bt(path)


@pytest.mark.parametrize(
    ("resolution", "keys", "occupied", "match"),
    [
        (
            0.0,
            np.zeros((1, 3), np.int64),
            np.ones(1, bool),
            r"expected a finite resolution > 0, found 0.0",
        ),
        (
            0.1,
            np.zeros((1, 2), np.int64),
            np.ones(1, bool),
            r"expected integer keys of shape \(N, 3\)",
        ),
        (
            0.1,
            np.zeros((1, 3)),
            np.ones(1, bool),
            r"expected integer keys of shape \(N, 3\), found float64",
        ),
        (
            0.1,
            np.zeros((2, 3), np.int64),
            np.ones(1, bool),
            r"expected a bool occupied mask of shape \(2,\)",
        ),
        (
            0.1,
            np.array([[0, 32768, 0]]),
            np.ones(1, bool),
            r"expected keys in \[-32768, 32767\].* found 1 outside",
        ),
    ],
)
def test_write_rejects_bad_input(
    tmp_path: Path, resolution: float, keys: np.ndarray, occupied: np.ndarray, match: str
) -> None:
    with pytest.raises(InputError, match=match):
        write_bt(tmp_path / "bad.bt", resolution, keys, occupied)
