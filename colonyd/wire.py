"""Gossip wire format of the daemon: framed, authenticated, size-bounded msgpack + zstd messages."""

from __future__ import annotations

import hashlib
import io
import math
import threading
from typing import Any

import msgpack
import numpy as np
import zstandard

from colonyd.errors import WireError
from protocol.auth import TAG_BYTES, compute_tag, verify_tag
from protocol.errors import AuthError
from voxel.delta import Delta, channel_spec

MAGIC = b"CLD"
VERSION = 1
FLAG_AUTH = 1
KINDS = ("delta", "hb", "snap", "range", "none")
_LOCAL = threading.local()  # zstd contexts are not thread-safe: one per thread


def _compressor() -> zstandard.ZstdCompressor:
    zc = getattr(_LOCAL, "zc", None)
    if zc is None:
        zc = _LOCAL.zc = zstandard.ZstdCompressor(level=1)
    return zc


class Codec:
    """Encodes and validates messages; with a key, signs them and rejects unsigned ones.

    Tags are protocol.auth's HMAC-SHA256 under sha256(colony key).
    """

    def __init__(self, key: str | None = None, max_bytes: int = 64 << 20) -> None:
        self._key = hashlib.sha256(key.encode()).digest() if key else None
        self.max_bytes = int(max_bytes)

    def encode(self, message: dict[str, Any]) -> bytes:
        """Frame `message` (a dict with "t" in KINDS; Delta values allowed under "delta")."""
        body = dict(message)
        if isinstance(body.get("delta"), Delta):
            body["delta"] = _pack_delta(body["delta"])
        raw = msgpack.packb(body, use_bin_type=True)
        comp = _compressor().compress(raw)
        flags = FLAG_AUTH if self._key else 0
        head = MAGIC + bytes([VERSION, flags])
        if self._key:
            return head + compute_tag(self._key, head + comp) + comp
        return head + comp

    def decode(self, data: bytes) -> dict[str, Any]:
        """Validate and decode; raises WireError(reason, ...) for anything hostile or broken."""
        if len(data) < 5 or data[:3] != MAGIC:
            raise WireError("bad-magic", f"expected a colonyd message, found {bytes(data[:8])!r}")
        if data[3] != VERSION:
            raise WireError("bad-version", f"expected wire version {VERSION}, found {data[3]}")
        flags = data[4]
        body = data[5:]
        if self._key:
            if not flags & FLAG_AUTH or len(body) < TAG_BYTES:
                raise WireError("unauthenticated", "expected a signed message, found none")
            tag, body = body[:TAG_BYTES], body[TAG_BYTES:]
            try:
                verify_tag(self._key, data[:5] + body, tag)
            except AuthError:
                raise WireError("bad-signature",
                                "message signature does not match the colony key") from None
        elif flags & FLAG_AUTH:
            body = body[TAG_BYTES:]
        raw = self._decompress(body)
        try:
            msg = msgpack.unpackb(raw, raw=False, strict_map_key=True, max_bin_len=self.max_bytes)
        except Exception as exc:
            raise WireError("bad-msgpack", f"payload is not msgpack: {exc}") from None
        if not isinstance(msg, dict) or msg.get("t") not in KINDS:
            found = msg.get("t") if isinstance(msg, dict) else type(msg).__name__
            raise WireError("bad-kind", f"expected a message kind in {KINDS}, found {found!r}")
        if "delta" in msg:
            msg["delta"] = _unpack_delta(msg["delta"])
        return msg

    def _decompress(self, body: bytes) -> bytes:
        try:
            reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(body))
            out = reader.read(self.max_bytes + 1)
        except zstandard.ZstdError as exc:
            raise WireError("bad-compression", f"payload is not zstd: {exc}") from None
        if len(out) > self.max_bytes:
            raise WireError("oversized", f"expected at most {self.max_bytes} bytes decoded, found more")
        return out


def _pack_delta(delta: Delta) -> dict[str, Any]:
    return {
        "r": float(delta.resolution),
        "f": int(delta.from_version),
        "v": int(delta.to_version),
        "tm": float(delta.time),
        "n": len(delta),
        "k": np.ascontiguousarray(delta.keys, dtype="<i8").tobytes(),
        "l": np.ascontiguousarray(delta.logodds, dtype="<f4").tobytes(),
        "lt": np.ascontiguousarray(delta.last_time, dtype="<f8").tobytes(),
        "c": {
            name: [list(arr.shape[1:]), np.ascontiguousarray(arr).tobytes()]
            for name, arr in delta.channels.items()
        },
    }


def _array(raw: Any, dtype: np.dtype, shape: tuple[int, ...], what: str) -> np.ndarray:
    if not isinstance(raw, bytes):
        raise WireError("bad-delta", f"delta field {what} must be bytes, found {type(raw).__name__}")
    want = dtype.itemsize * math.prod(shape)
    if len(raw) != want:
        raise WireError("bad-delta", f"delta field {what} must be {want} bytes, found {len(raw)}")
    return np.frombuffer(raw, dtype=dtype.newbyteorder("<")).reshape(shape).astype(dtype)


def _unpack_delta(d: Any) -> Delta:
    if not isinstance(d, dict):
        raise WireError("bad-delta", f"delta must be a map, found {type(d).__name__}")
    try:
        n = int(d["n"])
        res, f, v, tm = float(d["r"]), int(d["f"]), int(d["v"]), float(d["tm"])
        channels_raw = d.get("c", {})
    except (KeyError, TypeError, ValueError) as exc:
        raise WireError("bad-delta", f"delta header incomplete: {exc!r}") from None
    if n < 0 or not (math.isfinite(res) and res > 0) or f < 0 or v < f:
        raise WireError("bad-delta", f"delta header invalid: n={n} res={res} versions {f}->{v}")
    keys = _array(d.get("k"), np.dtype(np.int64), (n, 3), "keys")
    logodds = _array(d.get("l"), np.dtype(np.float32), (n,), "logodds")
    last_time = _array(d.get("lt"), np.dtype(np.float64), (n,), "last_time")
    channels: dict[str, np.ndarray] = {}
    if not isinstance(channels_raw, dict):
        raise WireError("bad-delta", "delta channels must be a map")
    for name, item in channels_raw.items():
        try:
            dtype, tail = channel_spec(str(name))
            shape_tail, raw = item
            shape_tail = tuple(int(s) for s in shape_tail)
        except Exception as exc:
            raise WireError("bad-delta", f"delta channel {name!r} invalid: {exc}") from None
        if len(shape_tail) != len(tail) or any(s < 0 or s > 64 for s in shape_tail):
            raise WireError("bad-delta", f"delta channel {name!r} has shape {shape_tail}")
        channels[str(name)] = _array(raw, dtype, (n, *shape_tail), f"channel {name}")
    try:
        return Delta(res, f, v, keys, logodds, last_time, channels, tm)
    except ValueError as exc:
        raise WireError("bad-delta", str(exc)) from None
