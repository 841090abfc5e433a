"""Memory: how many C-allocator arenas the daemon's threads share."""

from __future__ import annotations

import ctypes
import os
import sys

#: glibc's mallopt parameter for the most arenas (malloc.h).
M_ARENA_MAX = -8
#: Arenas a daemon runs with. glibc gives every thread that allocates its own arena, up to 8 per
#: core: the snapshot server's first large snapshot then faulted in ~27 MB of fresh pages (6,800
#: page faults, 75-150 ms of kernel time on the 2-core VM here) where memory other threads had
#: freed sat unused in their arenas. The daemon's threads take turns on the interpreter lock, so
#: sharing two arenas costs no waiting (docs/BENCHMARKS.md, catch-up).
ARENAS = 2


def limit_arenas(arenas: int = ARENAS) -> bool:
    """Limit the C allocator to `arenas` arenas for the threads started from now on; True if it
    took effect (glibc), False elsewhere (musl, macOS) or when MALLOC_ARENA_MAX already says."""
    if not sys.platform.startswith("linux") or "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, arenas) == 1)
