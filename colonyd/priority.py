"""Priority of a run's helper processes, relative to the run's own niceness."""

from __future__ import annotations

import contextlib
import os


def below_us(pid: int, by: int = 10) -> None:
    """Give process `pid` our niceness plus `by` (at most 19): it takes what we leave of the CPU.
    Relative to ours, so a demo started under `nice -n 15` keeps its replays below itself."""
    with contextlib.suppress(OSError):  # not permitted here: it keeps our priority
        os.setpriority(os.PRIO_PROCESS, pid, min(19, os.getpriority(os.PRIO_PROCESS, 0) + by))


def as_us(pid: int) -> None:
    """Give process `pid` our niceness again, where permitted (lowering niceness needs
    privileges). Never above our priority: an absolute 0 here took a replay of a demo run under
    `nice -n 15` (as root) out of the niceness its user gave."""
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0))
