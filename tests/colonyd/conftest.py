"""Fixtures for daemon tests: local colonies of real `colonyd` processes on loopback; their logs on
failure."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import Any

import pytest

from colonyd.bench.launcher import LocalColony, stop_all

#: Attribute of a test item holding the colonies its `make_colony` made.
_COLONIES = "_colonies_made"
#: Seconds given to running daemons to write their thread stacks after a failure, and how much
#: of each log's end is then attached (the stacks of ~20 threads come after its last lines).
STACKS_S = 1.0
STACKS_TAIL = 20_000


@pytest.fixture
def make_colony(
    tmp_path: Path, request: pytest.FixtureRequest
) -> Iterator[Callable[..., LocalColony]]:
    """Factory of LocalColony objects; every daemon is stopped at teardown, whatever happens, and a
    failed test's report carries the logs of every daemon it started."""
    made: list[LocalColony] = []
    setattr(request.node, _COLONIES, made)

    def make(name: str = "test", **kwargs: Any) -> LocalColony:
        colony = LocalColony(tmp_path / f"{name}-{len(made)}", colony=name, **kwargs)
        made.append(colony)
        return colony

    try:
        yield make
    finally:
        stop_all([d for colony in made for d in colony.daemons.values()])  # all colonies at once
        for colony in made:
            colony.close()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, Any, None]:
    """Attach the daemon logs of the colonies a failed test made to its report, with the thread
    stacks of every daemon still running (SIGUSR1: faulthandler writes them into its log), so a
    daemon that went quiet shows where it stood."""
    outcome = yield
    report = outcome.get_result()
    colonies: list[LocalColony] = getattr(item, _COLONIES, [])
    if report.failed and report.when == "call" and colonies:
        running = [d for colony in colonies for d in colony.daemons.values() if d.alive()]
        for d in running:
            d.signal(signal.SIGUSR1)
        if running:
            time.sleep(STACKS_S)
        for colony in colonies:
            logs = colony.logs(tail=STACKS_TAIL if running else 3000)
            report.sections.append((f"daemon logs of colony {colony.colony!r}", logs))
