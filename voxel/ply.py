"""PLY point files: binary little-endian x, y, z float32 with optional red, green, blue uchar."""

from __future__ import annotations

from os import PathLike
from pathlib import Path

import numpy as np

from voxel.errors import FileFormatError, InputError

StrPath = str | PathLike[str]

_MAX_HEADER_BYTES = 1 << 16
_END_HEADER = b"end_header\n"
_XYZ = ("x", "y", "z")
_RGB = ("red", "green", "blue")
#: PLY scalar property types and their little-endian numpy dtypes.
_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip


def write_ply(path: StrPath, centres: np.ndarray, colours: np.ndarray | None = None) -> None:
    """Write points (N, 3) and optional colours (N, 3) uint8 as a binary little-endian PLY file."""
    centres = np.asarray(centres)
    if centres.ndim != 2 or centres.shape[1] != 3 or not np.issubdtype(centres.dtype, np.number):
        msg = f"expected numeric centres of shape (N, 3), found {centres.dtype} {centres.shape}"
        raise InputError(msg) from None
    n = centres.shape[0]
    fields = [(name, "<f4") for name in _XYZ]
    if colours is not None:
        colours = np.asarray(colours)
        if colours.shape != (n, 3) or colours.dtype != np.uint8:
            msg = f"expected uint8 colours of shape ({n}, 3), found {colours.dtype} {colours.shape}"
            raise InputError(msg) from None
        fields += [(name, "u1") for name in _RGB]
    rows = np.empty(n, dtype=fields)
    for axis, name in enumerate(_XYZ):
        rows[name] = centres[:, axis]
    if colours is not None:
        for axis, name in enumerate(_RGB):
            rows[name] = colours[:, axis]
    properties = "".join(
        f"property {'float' if dtype == '<f4' else 'uchar'} {name}\n" for name, dtype in fields
    )
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment written by colony\n"
        f"element vertex {n}\n{properties}end_header\n"
    )
    Path(path).write_bytes(header.encode("ascii") + rows.tobytes())


def read_ply(path: StrPath) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) float64 and colours (N, 3) uint8 (None without them) of a binary PLY file."""
    raw = Path(path).read_bytes()
    if not raw.startswith(b"ply\n"):
        msg = f"{path}: expected a PLY file starting with 'ply', found {raw[:20]!r}"
        raise FileFormatError(msg) from None
    end = raw.find(_END_HEADER, 0, _MAX_HEADER_BYTES)
    if end < 0:
        msg = f"{path}: truncated header: expected 'end_header' within {_MAX_HEADER_BYTES} bytes"
        raise FileFormatError(msg) from None
    count, dtype = _parse_header(raw[4:end].decode("ascii", "replace"), path)
    body = raw[end + len(_END_HEADER) :]
    if len(body) != count * dtype.itemsize:
        msg = (
            f"{path}: expected {count * dtype.itemsize} bytes of data for {count} vertices, "
            f"found {len(body)}"
        )
        raise FileFormatError(msg) from None
    data = np.frombuffer(body, dtype=dtype, count=count)
    centres = np.stack([data[name].astype(np.float64) for name in _XYZ], axis=1)
    if not all(name in (dtype.names or ()) for name in _RGB):
        return centres, None
    colours = np.stack([data[name] for name in _RGB], axis=1)
    return centres, colours


def _parse_header(text: str, path: StrPath) -> tuple[int, np.dtype]:
    """Vertex count and row dtype of a PLY header (the lines between 'ply' and 'end_header')."""
    fmt = ""
    count = -1
    fields: list[tuple[str, str]] = []
    for line in text.splitlines():
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = " ".join(words[1:])
        elif words[0] == "element":
            if count >= 0 or len(words) != 3 or words[1] != "vertex" or not words[2].isdigit():
                msg = f"{path}: expected one 'element vertex N', found {line!r}"
                raise FileFormatError(msg) from None
            count = int(words[2])
        elif words[0] == "property" and count >= 0:
            if len(words) != 3 or words[1] not in _TYPES:
                types = sorted(_TYPES)
                msg = f"{path}: expected 'property TYPE NAME' with TYPE in {types}, found {line!r}"
                raise FileFormatError(msg) from None
            fields.append((words[2], _TYPES[words[1]]))
        else:
            msg = f"{path}: expected a PLY header line, found {line!r}"
            raise FileFormatError(msg) from None
    if fmt != "binary_little_endian 1.0":
        msg = f"{path}: expected 'format binary_little_endian 1.0', found {fmt!r}"
        raise FileFormatError(msg) from None
    names = [name for name, _ in fields]
    if count < 0 or any(name not in names for name in _XYZ) or len(set(names)) != len(names):
        msg = f"{path}: expected a vertex element with properties x, y, z, found {names}"
        raise FileFormatError(msg) from None
    for name, dtype in fields:
        if name in _RGB and dtype != "u1":
            msg = f"{path}: expected colour property {name!r} to be uchar, found {dtype}"
            raise FileFormatError(msg) from None
    return count, np.dtype(fields)
