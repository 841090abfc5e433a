"""Output folders: made when missing; a file in the way or no permission is a clear error."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from colonyd.errors import ConfigError


def output_dir(path: Path, flag: str) -> Path:
    """`path` as a writable folder (created with its parents), or ConfigError naming `flag`."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        msg = f"{flag}: expected a directory, found a file: {path}"
        raise ConfigError(msg)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        msg = f"{flag}: cannot create the directory {path}: {exc.strerror}"
        raise ConfigError(msg) from None
    if not os.access(path, os.W_OK | os.X_OK):
        msg = f"{flag}: expected a writable directory, found {path} not writable"
        raise ConfigError(msg)
    return path


@contextmanager
def run_output(path: Path, flag: str) -> Iterator[Path]:
    """`output_dir` for a run that may fail before it writes: when the block raises, the
    folders made here (`path` and the parents it lacked) are removed again if still empty, so a
    run that wrote nothing leaves nothing behind; a folder that existed stays."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()]
    output_dir(path, flag)
    try:
        yield path
    except BaseException:
        for folder in made:  # deepest first
            try:
                folder.rmdir()
            except OSError:  # not empty (something was written), or gone: leave it
                break
        raise
