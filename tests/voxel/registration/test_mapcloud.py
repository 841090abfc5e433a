"""Map files as registration reads them: OctoMap, grid snapshots, PLY; known space; bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from voxel.errors import AlignmentError, FileFormatError
from voxel.grid import VoxelGrid
from voxel.octomap_io import write_bt
from voxel.ply import write_ply
from voxel.registration import MapCloud, load_map
from voxel.registration.mapcloud import FREE, OCCUPIED, UNKNOWN


def test_state_lookup_and_planar_flag() -> None:
    keys = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    cloud = MapCloud.from_keys(0.1, keys, np.array([True, False, True]))
    states = cloud.state_at(np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [0.5, 0.5, 0.5]]))
    assert states.tolist() == [OCCUPIED, FREE, UNKNOWN]
    assert cloud.planar and cloud.has_free_space
    assert not MapCloud(0.1, np.array([[0.0, 0, 0], [0, 0, 1.0]])).has_free_space


def test_load_bt_npz_and_ply_agree(tmp_path: Path) -> None:
    grid = VoxelGrid(0.1)
    pts = np.array([[1.0, 0.0, 0.2], [1.0, 0.5, 0.2], [0.0, 1.0, 0.2]])
    grid.integrate(pts, np.array([0.0, 0.0, 0.2]), time=0.0)
    grid.save(tmp_path / "g.npz")
    occ, free = grid.occupied_keys(), grid.free_keys()
    write_bt(
        tmp_path / "g.bt",
        0.1,
        np.concatenate([occ, free]),
        np.arange(len(occ) + len(free)) < len(occ),
    )
    write_ply(tmp_path / "g.ply", (occ + 0.5) * 0.1)
    clouds = [load_map(tmp_path / f"g.{ext}") for ext in ("npz", "bt", "ply")]
    for c in clouds:
        np.testing.assert_allclose(
            np.sort(c.occupied, axis=0), np.sort((occ + 0.5) * 0.1, axis=0), atol=1e-6
        )
    assert clouds[0].has_free_space and clouds[1].has_free_space and not clouds[2].has_free_space
    assert clouds[2].resolution > 0


def test_bad_map_files(tmp_path: Path) -> None:
    with pytest.raises(
        FileFormatError,
        match=r"nope\.bt: expected a map file \(\.bt, \.npz, \.ply\), found nothing",
    ):
        load_map(tmp_path / "nope.bt")
    (tmp_path / "m.txt").write_text("x")
    with pytest.raises(
        FileFormatError, match=r"expected a map file ending in \.bt, \.npz, \.ply, found '\.txt'"
    ):
        load_map(tmp_path / "m.txt")
    (tmp_path / "m.bt").write_bytes(b"not an octree")
    with pytest.raises(FileFormatError, match=r"m\.bt"):
        load_map(tmp_path / "m.bt")
    write_bt(tmp_path / "free.bt", 0.1, np.array([[0, 0, 0]]), np.array([False]))
    with pytest.raises(
        AlignmentError, match="expected a map with occupied voxels to align, found none"
    ):
        load_map(tmp_path / "free.bt")
