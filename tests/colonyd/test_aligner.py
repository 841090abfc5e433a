"""The aligner's worker process: results come back; closing ends an attempt under way."""

from __future__ import annotations

import os
import threading
import time

import pytest

from colonyd.aligner import AUTOGROUP, AUTOGROUP_NICE, NICE, Aligner
from colonyd.errors import StoppedError


def _autogroup() -> str:
    with open(AUTOGROUP) as f:
        return f.read()


def test_work_runs_in_another_process_and_close_interrupts_it():
    import os

    aligner = Aligner()
    try:
        assert aligner.run(os.getpid) != os.getpid()
        # registration yields the cores to the daemon's threads: niceness, and on Linux the
        # idle policy (a waking thread of any session preempts it)
        assert aligner.run(os.nice, 0) == os.nice(0) + NICE
        if hasattr(os, "SCHED_IDLE"):
            assert aligner.run(os.sched_getscheduler, 0) == os.SCHED_IDLE
            # in a session of its own, weighing least where CPU is shared by session
            assert aligner.run(os.getsid, 0) != os.getsid(0)
            if os.path.exists(AUTOGROUP):
                assert aligner.run(_autogroup).split()[-1] == str(AUTOGROUP_NICE)
        assert aligner.run(divmod, 7, 2) == (3, 1)
        with pytest.raises(ZeroDivisionError):  # the worker's error, raised here (same worker)
            aligner.run(divmod, 1, 0)
        failed: list[BaseException] = []

        def slow() -> None:
            try:
                aligner.run(time.sleep, 30)
            except BaseException as exc:  # noqa: BLE001 - the interrupted call's error is the point
                failed.append(exc)

        t = threading.Thread(target=slow)
        t.start()
        time.sleep(1.0)
        began = time.monotonic()
        aligner.close()
        t.join(10)
        assert not t.is_alive() and time.monotonic() - began < 5
        assert isinstance(failed[0], StoppedError), failed
        with pytest.raises(StoppedError, match="closed"):
            aligner.run(divmod, 1, 1)
    finally:
        aligner.close()


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling policies only")
def test_session_niceness_is_the_configured_one_or_no_session_of_its_own():
    # `align_session_nice`: the worker's share where CPU is shared by session (docs/DAEMON.md)
    lowest = Aligner(session_nice=19)
    same = Aligner(session_nice=None)
    try:
        if os.path.exists(AUTOGROUP):
            assert lowest.run(_autogroup).split()[-1] == "19"
        assert lowest.run(os.getsid, 0) != os.getsid(0)
        # no session of its own: the idle policy and niceness only, in the daemon's session
        assert same.run(os.getsid, 0) == os.getsid(0)
        assert same.run(os.sched_getscheduler, 0) == os.SCHED_IDLE
        assert same.run(os.nice, 0) == os.nice(0) + NICE
    finally:
        lowest.close()
        same.close()
