"""colonyd package: the daemon, its command line and its benchmarks."""

import os

# numpy's OpenBLAS starts one worker thread per core, and after a matrix product (a scan's
# points times its rotation) that thread spins for ~4 ms before it sleeps: on a robot's few cores
# the spin takes a core from the mapping, the replicas and other daemons for no gain on 3x3
# products (measured: a depth frame's integration, 2.2 ms on its own thread, cost the process
# 6.2 ms of CPU one time in two). One BLAS thread, unless the user chose otherwise; this must be
# set before numpy is first imported, which this package's import precedes in every entry point.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
