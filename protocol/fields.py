"""Bounded msgpack and zstd primitives: bytes are checked before anything is allocated for them."""

from __future__ import annotations

import threading
from typing import Any, TypeVar

import msgpack
import zstandard

from protocol.errors import (
    DecompressionBombError,
    MalformedError,
    OversizedError,
    TruncatedError,
    UnknownTypeError,
)
from protocol.limits import Limits

#: zstd frames start with these four bytes.
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
#: zstd level of frame bodies: 5-15% smaller deltas than level 3, still > 40M voxels/s.
DEFAULT_LEVEL = 6
#: Most msgpack objects (scalars and containers) one body may hold, and deepest nesting.
MAX_OBJECTS = 1_000_000
MAX_DEPTH = 8

T = TypeVar("T")

# Bytes following a msgpack head byte whose size does not depend on the data: head -> extra bytes.
_FIXED = {
    0xC0: 0,
    0xC2: 0,
    0xC3: 0,  # nil, false, true
    0xCA: 4,
    0xCB: 8,  # float32, float64
    0xCC: 1,
    0xCD: 2,
    0xCE: 4,
    0xCF: 8,  # uint8..64
    0xD0: 1,
    0xD1: 2,
    0xD2: 4,
    0xD3: 8,  # int8..64
    0xD4: 2,
    0xD5: 3,
    0xD6: 5,
    0xD7: 9,
    0xD8: 17,  # fixext 1..16 (type byte + data)
}
# Heads followed by a big-endian length, then that many bytes: head -> (length bytes, extra).
_SIZED = {
    0xC4: (1, 0),
    0xC5: (2, 0),
    0xC6: (4, 0),
    0xD9: (1, 0),
    0xDA: (2, 0),
    0xDB: (4, 0),
    0xC7: (1, 1),
    0xC8: (2, 1),
    0xC9: (4, 1),
}  # bin8/16/32, str8/16/32, ext8/16/32
# Container heads followed by a big-endian count: head -> (count bytes, objects per entry).
_CONTAINER = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}


def _need_field(what: str, field: str, pos: int, width: int, n: int) -> None:
    """Raise TruncatedError unless a `width`-byte msgpack `field` field fits at `pos` of n bytes."""
    if pos + width > n:
        msg = f"{what}: msgpack {field} field at byte {pos} needs {width} bytes, found {n - pos}"
        raise TruncatedError(msg)


def scan_msgpack(
    data: bytes, what: str, max_objects: int = MAX_OBJECTS, max_depth: int = MAX_DEPTH
) -> None:
    """Check that `data` is exactly one complete msgpack object within object and depth bounds.

    Walks the structure without building it, so a hostile body cannot make the unpacker
    allocate millions of Python objects or recurse deeply.
    """
    n = len(data)
    pos = 0
    objects = 0
    stack = [1]
    while stack:
        if stack[-1] == 0:
            stack.pop()
            continue
        stack[-1] -= 1
        if pos >= n:
            msg = f"{what}: msgpack data ends at byte {n} inside an object; expected more bytes"
            raise TruncatedError(msg)
        head = data[pos]
        pos += 1
        objects += 1
        if objects > max_objects:
            msg = f"{what}: expected at most {max_objects} msgpack objects, found more"
            raise OversizedError(msg)
        count = 0
        if head <= 0x7F or head >= 0xE0:
            continue
        if head <= 0x8F:
            count = (head & 0x0F) * 2
        elif head <= 0x9F:
            count = head & 0x0F
        elif head <= 0xBF:
            pos += head & 0x1F
            continue
        elif head in _FIXED:
            pos += _FIXED[head]
            continue
        elif head in _SIZED:
            width, extra = _SIZED[head]
            _need_field(what, "length", pos, width, n)
            pos += width + extra + int.from_bytes(data[pos : pos + width], "big")
            continue
        elif head in _CONTAINER:
            width, per = _CONTAINER[head]
            _need_field(what, "count", pos, width, n)
            count = per * int.from_bytes(data[pos : pos + width], "big")
            pos += width
        else:
            msg = f"{what}: expected a msgpack type byte at byte {pos - 1}, found 0x{head:02x}"
            raise MalformedError(msg)
        if count:
            if count > n - pos:
                msg = (
                    f"{what}: msgpack container at byte {pos} announces {count} objects, only "
                    f"{n - pos} bytes follow"
                )
                raise TruncatedError(msg)
            if len(stack) > max_depth:
                msg = f"{what}: expected msgpack nesting depth <= {max_depth}, found deeper"
                raise MalformedError(msg)
            stack.append(count)
    if pos > n:
        msg = f"{what}: msgpack data announces {pos} bytes, found {n}"
        raise TruncatedError(msg)
    if pos < n:
        msg = f"{what}: expected {pos} bytes of msgpack, found {n - pos} trailing bytes"
        raise MalformedError(msg)


def _no_ext(code: int, data: bytes) -> Any:
    msg = f"msgpack extension types are not used by the protocol, found extension {code}"
    raise UnknownTypeError(msg)


def unpack(data: bytes, what: str, limits: Limits) -> Any:
    """Unpack one msgpack object from hostile `data` (scanned first), or raise a ProtocolError."""
    scan_msgpack(data, what)
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            ext_hook=_no_ext,
            max_str_len=max(limits.max_string, 1024),
            max_bin_len=len(data),
            max_array_len=limits.max_list,
            max_map_len=limits.max_list,
        )
    except UnknownTypeError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        msg = f"{what}: expected valid msgpack, found {type(exc).__name__}: {exc}"
        raise MalformedError(msg) from None


#: msgpack heads of a str (fixstr, str8, str16, str32) and of a bin (bin8, bin16, bin32).
_STR_HEADS = frozenset([*range(0xA0, 0xC0), 0xD9, 0xDA, 0xDB])
_BIN_HEADS = frozenset([0xC4, 0xC5, 0xC6])


def map_bin(data: bytes, key: str, what: str, limits: Limits) -> bytes | None:
    """The bin value of `key` (its last, as `unpack` keeps it) in the msgpack map `data`, read
    without building anything else: the map's other values are skipped by msgpack's own
    unpacker, and a value of `key` that is not a bin is None. MalformedError for data that is
    not a map of string keys (what `unpack` refuses too)."""
    if not data or not (0x80 <= data[0] <= 0x8F or data[0] in (0xDE, 0xDF)):
        head = f"0x{data[0]:02x}" if data else "nothing"
        msg = f"{what}: expected a msgpack map, found {head}"
        raise MalformedError(msg)
    unpacker = msgpack.Unpacker(
        raw=False,
        ext_hook=_no_ext,
        max_buffer_size=max(len(data), 1),
        max_str_len=max(limits.max_string, 1024),
        max_bin_len=len(data),
        max_array_len=limits.max_list,
        max_map_len=limits.max_list,
    )
    unpacker.feed(data)
    found: bytes | None = None
    try:
        for _ in range(unpacker.read_map_header()):
            if data[unpacker.tell()] not in _STR_HEADS:
                msg = f"{what}: expected string map keys, found byte 0x{data[unpacker.tell()]:02x}"
                raise MalformedError(msg)
            name = unpacker.unpack()
            if name == key and data[unpacker.tell()] in _BIN_HEADS:
                found = unpacker.unpack()
            else:
                unpacker.skip()
                found = None if name == key else found
    except (ValueError, TypeError, IndexError, msgpack.UnpackException) as exc:
        msg = f"{what}: expected valid msgpack, found {type(exc).__name__}: {exc}"
        raise MalformedError(msg) from None
    return found


def pack(obj: Any) -> bytes:
    """msgpack encoding of `obj` (binary strings as bin, floats as float64)."""
    packed: bytes = msgpack.packb(obj, use_bin_type=True)
    return packed


def field(obj: dict[str, Any], name: str, kind: type[T] | tuple[type, ...], what: str) -> T:
    """`obj[name]` checked to be of `kind`, else MalformedError saying what was found."""
    if name not in obj:
        msg = f"{what}: expected field {name!r}, found fields {sorted(map(str, obj))[:16]}"
        raise MalformedError(msg)
    value = obj[name]
    if (isinstance(value, bool) and kind in (int, float)) or not isinstance(value, kind):
        expected = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        msg = f"{what}: field {name!r} must be {expected}, found {type(value).__name__}"
        raise MalformedError(msg)
    return value  # type: ignore[return-value]


def as_map(obj: Any, what: str) -> dict[str, Any]:
    """`obj` if it is a msgpack map, else MalformedError."""
    if not isinstance(obj, dict):
        msg = f"{what}: expected a msgpack map, found {type(obj).__name__}"
        raise MalformedError(msg)
    return obj


_LOCAL = threading.local()


def compress(data: bytes, level: int = DEFAULT_LEVEL) -> bytes:
    """One zstd frame of `data` with its content size in the frame header (thread-safe)."""
    cache = getattr(_LOCAL, "compressors", None)
    if cache is None:
        cache = _LOCAL.compressors = {}
    cctx = cache.get(level)
    if cctx is None:
        cctx = cache[level] = zstandard.ZstdCompressor(level=level, write_content_size=True)
    return cctx.compress(data)


def decompress(data: bytes, limits: Limits, what: str = "body") -> bytes:
    """Decompress one zstd frame; refuse frames without a content size or above the limit."""
    if len(data) < 6 or data[:4] != ZSTD_MAGIC:
        msg = (
            f"{what}: expected a zstd frame (magic {ZSTD_MAGIC.hex()}), found "
            f"{bytes(data[:4]).hex() or 'nothing'}"
        )
        raise MalformedError(msg)
    try:
        params = zstandard.get_frame_parameters(data)
    except zstandard.ZstdError as exc:
        msg = f"{what}: expected a valid zstd frame header, found {exc}"
        raise MalformedError(msg) from None
    size = params.content_size
    if size >= zstandard.CONTENTSIZE_ERROR:  # unknown or error
        msg = f"{what}: expected a zstd frame that declares its content size, found none"
        raise MalformedError(msg)
    if size > limits.max_body_bytes:
        msg = (
            f"{what}: expected at most {limits.max_body_bytes} decompressed bytes, frame declares "
            f"{size}"
        )
        raise DecompressionBombError(msg)
    if params.window_size > limits.max_window_bytes:
        msg = (
            f"{what}: expected a zstd window <= {limits.max_window_bytes} bytes, found "
            f"{params.window_size}"
        )
        raise DecompressionBombError(msg)
    dctx = zstandard.ZstdDecompressor(max_window_size=max(limits.max_window_bytes, 1 << 10))
    try:
        out = dctx.decompress(data, max_output_size=size, allow_extra_data=False)
    except zstandard.ZstdError as exc:
        msg = f"{what}: expected a valid zstd frame of {size} bytes, found {exc}"
        raise MalformedError(msg) from None
    if len(out) != size:
        msg = f"{what}: zstd frame declares {size} bytes, found {len(out)}"
        raise MalformedError(msg)
    return out
