"""What test files share: where the real recordings live (`../shared/data` beside the checkout,
never copied into it), and a fresh interpreter's output."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def fresh_process(code: str, timeout: float = 60.0) -> str:
    """Standard output of `code` run by a new interpreter (nothing imported yet: what a module
    loads at import shows in its sys.modules); a failure raises with its output."""
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=timeout
    )
    assert run.returncode == 0, run.stdout + run.stderr
    return run.stdout
