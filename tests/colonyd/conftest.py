"""Fixtures for daemon tests: local colonies of real `colonyd` processes on loopback."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from colonyd.bench.launcher import LocalColony


@pytest.fixture
def make_colony(tmp_path: Path) -> Iterator[Callable[..., LocalColony]]:
    """Factory of LocalColony objects; every daemon is stopped at teardown, whatever happens."""
    made: list[LocalColony] = []

    def make(name: str = "test", **kwargs: Any) -> LocalColony:
        colony = LocalColony(tmp_path / f"{name}-{len(made)}", colony=name, **kwargs)
        made.append(colony)
        return colony

    try:
        yield make
    finally:
        for colony in made:
            colony.close()


def logs(colony: LocalColony) -> str:
    """All daemon logs of a colony, for assertion messages."""
    out = []
    for d in colony.daemons.values():
        if d.log_path.exists():
            out.append(f"--- {d.agent}\n" + d.log_path.read_text()[-3000:])
    return "\n".join(out)
