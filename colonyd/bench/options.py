"""Command-line options the benchmarks share."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence


def names(allowed: Sequence[str]) -> Callable[[str], list[str]]:
    """An argparse `type`: comma-separated names, each one of `allowed`, as a list (an error
    naming what was expected and what was found otherwise)."""

    def parse(text: str) -> list[str]:
        found = text.split(",")
        if not set(found) <= set(allowed):
            msg = f"expected names of {tuple(allowed)}, found {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return found

    return parse


def alignment_option(parser: argparse.ArgumentParser, what: str) -> None:
    """The benches' `--alignment`: the error of the alignment `what` come through added to
    each (noise, the daemon's) or one state of the filter, counted once (state)."""
    parser.add_argument(
        "--alignment",
        choices=("noise", "state"),
        default="noise",
        help=f"the error of the alignment {what} come through: added to each (noise, the "
        "daemon's) or one state of the filter, counted once (state: ScanParams.alignment_frames)",
    )
