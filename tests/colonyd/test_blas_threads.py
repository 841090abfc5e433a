"""colonyd keeps numpy's BLAS to one thread (its spinning workers cost a robot's cores)."""

from __future__ import annotations

import json
import os
import subprocess
import sys


def test_a_colonyd_process_runs_one_blas_thread() -> None:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    code = (
        "import colonyd, json, numpy\n"
        "from threadpoolctl import threadpool_info\n"
        "print(json.dumps([p['num_threads'] for p in threadpool_info()"
        " if p['internal_api'] == 'openblas']))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    threads = json.loads(out.stdout)
    assert threads, "numpy's OpenBLAS was not found"
    assert threads == [1] * len(threads)
