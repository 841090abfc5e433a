"""Where benchmarks find the shared recordings and how they write their JSON results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def shared_data_dir(given: Path | None) -> Path | None:
    """`given`, else the checkout's sibling `../shared/data` when it exists, else None."""
    if given is not None:
        return Path(given)
    candidate = Path(__file__).resolve().parents[3] / "shared" / "data"
    return candidate if candidate.is_dir() else None


def write_results(out_json: Path, results: list[dict[str, Any]]) -> None:
    """Write a benchmark's result list as indented JSON, creating the folder."""
    out_json = Path(out_json)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(results, indent=2) + "\n")
