"""Tests of voxel.ply: binary PLY point files with and without colours, and error paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from voxel.errors import FileFormatError, InputError
from voxel.ply import read_ply, write_ply


def _points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 10.0, (n, 3)), rng.integers(0, 256, (n, 3), dtype=np.uint8)


def _write_raw(path: Path, header: str, data: bytes = b"") -> Path:
    path.write_bytes(header.encode("ascii") + data)
    return path


XYZ_HEADER = (
    "ply\nformat {fmt}\nelement vertex {n}\n"
    "property float x\nproperty float y\nproperty float z\nend_header\n"
)


def test_round_trip_with_colours(tmp_path: Path) -> None:
    centres, colours = _points(1000)
    path = tmp_path / "points.ply"
    write_ply(path, centres, colours)
    raw = path.read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert raw.endswith(np.float32(centres[-1, 2]).tobytes() + colours[-1].tobytes())
    got, got_colours = read_ply(path)
    assert got.dtype == np.float64
    assert got.shape == (1000, 3)
    np.testing.assert_array_equal(got, centres.astype(np.float32))
    np.testing.assert_array_equal(got_colours, colours)


def test_round_trip_without_colours(tmp_path: Path) -> None:
    centres, _ = _points(10)
    path = tmp_path / "points.ply"
    write_ply(path, centres)
    header_end = path.read_bytes().index(b"end_header\n") + len(b"end_header\n")
    assert path.stat().st_size == header_end + 10 * 12
    got, got_colours = read_ply(path)
    np.testing.assert_array_equal(got, centres.astype(np.float32))
    assert got_colours is None


def test_empty_cloud_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    write_ply(path, np.empty((0, 3)), np.empty((0, 3), np.uint8))
    got, got_colours = read_ply(path)
    assert got.shape == (0, 3)
    assert got_colours is not None
    assert got_colours.shape == (0, 3)


def test_reads_other_property_layouts(tmp_path: Path) -> None:
    rows = np.array(
        [(1.5, 7, -2.0, 4.25, 10, 20, 30), (0.0, 8, 1.0, -3.5, 40, 50, 60)],
        dtype=[("x", "<f8"), ("i", "<i4"), ("y", "<f8"), ("z", "<f8"),
               ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )  # fmt: skip
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment from elsewhere\nelement vertex 2\n"
        "property double x\nproperty int i\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path = _write_raw(tmp_path / "other.ply", header, rows.tobytes())
    centres, colours = read_ply(path)
    np.testing.assert_array_equal(centres, [[1.5, -2.0, 4.25], [0.0, 1.0, -3.5]])
    np.testing.assert_array_equal(colours, [[10, 20, 30], [40, 50, 60]])


def test_not_a_ply_file_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(tmp_path / "not.ply", "OFF\n3 0 0\n")
    with pytest.raises(FileFormatError, match=r"not.ply: expected a PLY file starting with 'ply'"):
        read_ply(path)


def test_missing_end_header_is_rejected(tmp_path: Path) -> None:
    path = _write_raw(
        tmp_path / "cut.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
    )
    with pytest.raises(FileFormatError, match=r"truncated header: expected 'end_header'"):
        read_ply(path)


@pytest.mark.parametrize("fmt", ["ascii 1.0", "binary_big_endian 1.0"])
def test_other_formats_are_rejected(tmp_path: Path, fmt: str) -> None:
    path = _write_raw(tmp_path / "fmt.ply", XYZ_HEADER.format(fmt=fmt, n=0))
    with pytest.raises(
        FileFormatError, match=rf"expected 'format binary_little_endian 1.0', found '{fmt}'"
    ):
        read_ply(path)


def test_truncated_data_is_rejected(tmp_path: Path) -> None:
    data = np.zeros(3 * 3, "<f4").tobytes()[:-1]
    path = _write_raw(
        tmp_path / "short.ply", XYZ_HEADER.format(fmt="binary_little_endian 1.0", n=3), data
    )
    with pytest.raises(
        FileFormatError, match=r"expected 36 bytes of data for 3 vertices, found 35"
    ):
        read_ply(path)


def test_trailing_data_is_rejected(tmp_path: Path) -> None:
    data = np.zeros(3 * 3 + 1, "<f4").tobytes()
    path = _write_raw(
        tmp_path / "long.ply", XYZ_HEADER.format(fmt="binary_little_endian 1.0", n=3), data
    )
    with pytest.raises(
        FileFormatError, match=r"expected 36 bytes of data for 3 vertices, found 40"
    ):
        read_ply(path)


VERTEX_XYZ = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
BAD_HEADERS = [
    (VERTEX_XYZ[:-17], r"with properties x, y, z, found \['x', 'y'\]"),
    (
        "element vertex 1\nproperty list uchar int vertex_indices\n",
        r"expected 'property TYPE NAME'",
    ),
    ("element face 0\n", r"expected one 'element vertex N', found 'element face 0'"),
    (VERTEX_XYZ + "property float red\n", r"expected colour property 'red' to be uchar, found <f4"),
    ("property float x\n", r"expected a PLY header line, found 'property float x'"),
]


@pytest.mark.parametrize(("body", "match"), BAD_HEADERS)
def test_unsupported_headers_are_rejected(tmp_path: Path, body: str, match: str) -> None:
    header = f"ply\nformat binary_little_endian 1.0\n{body}end_header\n"
    path = _write_raw(tmp_path / "header.ply", header)
    with pytest.raises(FileFormatError, match=match):
        read_ply(path)


def test_write_rejects_bad_input(tmp_path: Path) -> None:
    centres, colours = _points(4)
    with pytest.raises(
        InputError, match=r"expected numeric centres of shape \(N, 3\), found float64 \(4, 2\)"
    ):
        write_ply(tmp_path / "bad.ply", centres[:, :2])
    with pytest.raises(
        InputError, match=r"expected uint8 colours of shape \(4, 3\), found int64 \(4, 3\)"
    ):
        write_ply(tmp_path / "bad.ply", centres, colours.astype(np.int64))
    with pytest.raises(
        InputError, match=r"expected uint8 colours of shape \(4, 3\), found uint8 \(3, 3\)"
    ):
        write_ply(tmp_path / "bad.ply", centres, colours[:3])
