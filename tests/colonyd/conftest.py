"""Fixtures for daemon tests: local colonies of real `colonyd` processes on loopback; their logs on
failure."""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import Any

import pytest

from colonyd.bench.launcher import LocalColony, stop_all

#: Attribute of a test item holding the colonies its `make_colony` made.
_COLONIES = "_colonies_made"


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
    """Attach the daemon logs of the colonies a failed test made to its report."""
    outcome = yield
    report = outcome.get_result()
    colonies: list[LocalColony] = getattr(item, _COLONIES, [])
    if report.failed and report.when == "call" and colonies:
        for colony in colonies:
            report.sections.append((f"daemon logs of colony {colony.colony!r}", colony.logs()))
