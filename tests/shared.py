"""What test files share: where the real recordings live (`../shared/data` beside the checkout,
never copied into it), a fresh interpreter's output, and a layer's snapshot asked for on a
thread."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def fresh_process(code: str, timeout: float = 60.0) -> str:
    """Standard output of `code` run by a new interpreter (nothing imported yet: what a module
    loads at import shows in its sys.modules); a failure raises with its output."""
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=timeout
    )
    assert run.returncode == 0, run.stdout + run.stderr
    return run.stdout


def ask_snapshot(layer: Any) -> tuple[threading.Thread, list[BaseException]]:
    """Ask `layer` for its snapshot on a thread of its own, as the layer server's worker does;
    the thread, started, and the TimeoutErrors the request ended with."""
    errors: list[BaseException] = []

    def ask() -> None:
        try:
            layer.snapshot(10**6)
        except TimeoutError as exc:
            errors.append(exc)

    waiting = threading.Thread(target=ask, daemon=True)
    waiting.start()
    return waiting, errors
