"""Tests of recording format detection."""

from __future__ import annotations

from pathlib import Path

import pytest

from plugins.errors import SourceError
from plugins.replay import detect_format
from tests.shared import SHARED_DATA

DATA = SHARED_DATA


@pytest.mark.skipif(not DATA.is_dir(), reason=f"real data not found at {DATA}")
def test_real_recordings_are_recognised() -> None:
    assert detect_format(DATA / "redkitchen-50") == "7scenes"
    assert detect_format(DATA / "redkitchen-50" / "frames") == "7scenes"
    assert detect_format(DATA / "carmen" / "freiburg-079-corrected.log.gz") == "carmen"


def test_layouts_by_marker_files(tmp_path: Path) -> None:
    (tmp_path / "tum").mkdir()
    (tmp_path / "tum" / "depth.txt").write_text("")
    (tmp_path / "bag2").mkdir()
    (tmp_path / "bag2" / "metadata.yaml").write_text("")
    (tmp_path / "run.bag").write_bytes(b"#ROSBAG V2.0\n")
    assert detect_format(tmp_path / "tum") == "tum"
    assert detect_format(tmp_path / "bag2") == "rosbag"
    assert detect_format(tmp_path / "run.bag") == "rosbag"


def test_unknown_recordings_say_what_was_expected(tmp_path: Path) -> None:
    with pytest.raises(
        SourceError, match="replay: expected a recording file or folder, found nothing at"
    ):
        detect_format(tmp_path / "missing")
    with pytest.raises(SourceError, match="expected a 7-Scenes folder"):
        detect_format(tmp_path)
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    with pytest.raises(
        SourceError, match=r"notes\.txt: expected a CARMEN log \(FLASER lines\) or a ROS bag"
    ):
        detect_format(text)


def test_a_folder_holding_a_log_names_the_file_to_give(tmp_path: Path) -> None:
    """`replay:carmen/` (the folder, not the log in it): the error says which path to give."""
    (tmp_path / "run.log.gz").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("not a recording")
    with pytest.raises(SourceError, match=r"found none of them; it holds run.log.gz: give the "):
        detect_format(tmp_path)
    with pytest.raises(SourceError, match=rf"\(replay:{tmp_path / 'run.log.gz'}\)$"):
        detect_format(tmp_path)


@pytest.mark.parametrize("name", ["flat.log", "flat.log.gz"])
def test_a_file_without_line_breaks_is_refused_without_reading_it_whole(
    tmp_path: Path, name: str
) -> None:
    """64 MiB without a line break (a sparse or binary file given as a log): detection reads at
    most one bounded line of it and says what it expected; the CARMEN reader stops at the first
    line longer than `MAX_LINE`. Read whole, the line took the file's size in memory (a 40 GB
    file filled the machine's memory)."""
    import gzip
    import tracemalloc

    from plugins.carmen import MAX_LINE, read_lines

    path = tmp_path / name
    size = 64 << 20
    if name.endswith(".gz"):
        with gzip.open(path, "wb", compresslevel=1) as f:
            f.write(b"PARAM " + b"0" * size)
    else:
        with open(path, "wb") as f:
            f.write(b"PARAM ")
            f.truncate(size)  # sparse: zero bytes, no line break
    tracemalloc.start()
    try:
        with pytest.raises(SourceError, match=r"expected a CARMEN log \(FLASER lines\)"):
            detect_format(path)
        with pytest.raises(
            SourceError, match=rf"line 1: expected a line of at most {MAX_LINE} characters"
        ):
            list(read_lines(path))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * MAX_LINE < size // 4, peak
