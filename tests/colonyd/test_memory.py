"""A daemon's threads share at most `ARENAS` C-allocator arenas (glibc), counted by malloc_info."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

_CODE = """
import ctypes, sys, threading
import numpy as np
from colonyd.memory import limit_arenas
if sys.argv[1] == "limit":
    assert limit_arenas()
held = []
together = threading.Barrier(8)  # none exits (freeing its arena for the next) before all allocated
def work():
    held.append([np.ones(8192) for _ in range(16)])  # 64 KB each: from the thread's arena
    together.wait()
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads:
    t.start()
for t in threads:
    t.join()
libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
f = libc.fopen(sys.argv[2].encode(), b"w")
libc.malloc_info(0, f)
libc.fclose(f)
"""


def _arenas(tmp_path, mode: str) -> int:
    out = tmp_path / f"{mode}.xml"
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    subprocess.run([sys.executable, "-c", _CODE, mode, str(out)], env=env, check=True)
    return out.read_text().count("<heap nr=")


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
    reason="glibc only",
)
def test_threads_share_at_most_the_arenas_the_daemon_limits_to(tmp_path) -> None:
    from colonyd.memory import ARENAS

    assert _arenas(tmp_path, "default") > ARENAS  # what the limit changes: a new one per thread
    assert _arenas(tmp_path, "limit") <= ARENAS
