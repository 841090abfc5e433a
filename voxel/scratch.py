"""Scratch buffers of the traversal, kept zeroed per thread and reused across scans."""

from __future__ import annotations

import threading

import numpy as np

#: Largest buffer kept between scans (bytes); a larger one is allocated for its scan and dropped.
KEEP_BYTES = 32 << 20


class _Held(threading.local):
    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}


_held = _Held()


def take(name: str, size: int, dtype: type[np.generic]) -> np.ndarray:
    """A zeroed 1-D array of at least `size` items (a whole number of 8-byte words), this
    thread's kept one when large enough. The caller owns it until `give` returns it zeroed; a
    buffer not given back (an exception in between) is simply dropped."""
    buf = _held.buffers.pop(name, None)
    if buf is None or buf.dtype != dtype or buf.size < size:
        if buf is not None and buf.dtype == dtype:
            size = max(size, buf.size + buf.size // 2)  # grow geometrically
        item = np.dtype(dtype).itemsize
        words = -(-size * item // 8)
        buf = np.zeros(words * 8 // item, dtype=dtype)
    return buf


def give(name: str, buf: np.ndarray) -> None:
    """Keep `buf` (all zero again) for this thread's next `take`, unless it is too large."""
    if buf.nbytes <= KEEP_BYTES:
        _held.buffers[name] = buf


def held_bytes() -> int:
    """Bytes of the buffers this thread keeps."""
    return sum(int(b.nbytes) for b in _held.buffers.values())
