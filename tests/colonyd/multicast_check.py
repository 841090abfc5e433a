"""Run inside `unshare -n` only: two daemons find each other by multicast scouting on loopback."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from colonyd.bench.launcher import LocalColony


def main() -> int:
    # /proc/net/dev lists the interfaces of this process's network namespace (sysfs may not).
    lines = Path("/proc/net/dev").read_text().splitlines()[2:]
    interfaces = sorted(line.split(":")[0].strip() for line in lines)
    if interfaces != ["lo"]:
        print(f"refusing to run multicast outside a private network namespace: {interfaces}")
        return 2
    os.environ["COLONYD_MULTICAST_INTERFACE"] = "lo"
    with (
        tempfile.TemporaryDirectory() as tmp,
        LocalColony(Path(tmp), colony="mcast", multicast=True) as colony,
    ):
        colony.add("a", ["synthetic:scans=3,rate=4,points=100,seed=1"])
        colony.add("b", ["synthetic:scans=3,rate=4,points=100,seed=2"])
        seconds = colony.wait_converged(60)  # (two starts: slow on a loaded machine)
        print(f"converged by multicast discovery in {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
