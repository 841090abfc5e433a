"""Tests of the CARMEN log reader on the real Freiburg 079 log and on broken copies."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from plugins.carmen import CarmenSource, parse_flaser, read_lines
from plugins.checks import pose_matrix
from plugins.errors import ParseError, SourceError, SourceSpecError
from tests.shared import SHARED_DATA

DATA = SHARED_DATA
LOG = DATA / "carmen" / "freiburg-079-corrected.log.gz"
needs_log = pytest.mark.skipif(not LOG.is_file(), reason=f"real CARMEN log not found at {LOG}")


def first_flaser() -> str:
    with gzip.open(LOG, "rt") as f:
        return next(line for line in f if line.startswith("FLASER"))


@needs_log
def test_real_log_scans_and_poses() -> None:
    source = CarmenSource(LOG)
    assert len(source) == 4791
    first = next(iter(source))
    assert len(first) == 360 and first.no_return.sum() == 1  # one 81.91 m reading in the first scan
    np.testing.assert_allclose(np.linalg.norm(first.points[~first.no_return][0]), 1.65)
    np.testing.assert_allclose(first.origin, [0.00123601, -0.00106807, 0.0])
    np.testing.assert_allclose(first.points[:, 2], 0.0)
    assert first.time == pytest.approx(0.227623)
    # beam 0 points at theta - pi/2 (to the right of the robot)
    direction = first.points[0] / np.linalg.norm(first.points[0])
    np.testing.assert_allclose(direction[:2], [0.0, -1.0], atol=1e-12)
    assert first.frame.endswith(".log.gz:" + str(first.frame.split(":")[-1]))


@needs_log
def test_selection_and_odometry_poses() -> None:
    source = CarmenSource(LOG, start=100, stop=400, step=100, poses="odometry")
    scans = list(source)
    assert len(source) == len(scans) == 3
    for obs in scans:
        np.testing.assert_allclose(obs.pose, obs.odometry)


def test_parse_errors_name_file_line_and_field(tmp_path: Path) -> None:
    line = "FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 12.5 host 12.5"
    record = parse_flaser(line, "x.log", 7)
    np.testing.assert_allclose(record.ranges, [1.0, 2.0, 3.0])
    with pytest.raises(
        ParseError, match=r"x\.log:7: field 4 \(range 2\): expected a number, found 'abc'"
    ):
        parse_flaser(line.replace(" 2.0 ", " abc "), "x.log", 7)
    with pytest.raises(ParseError, match=r"x\.log:7: expected 14 fields for 3 beams .* found 10"):
        parse_flaser("FLASER 3 1.0 2.0 3.0 0 0 0 0 0", "x.log", 7)
    with pytest.raises(ParseError, match=r"field 2 \(beam count\): expected an integer, found 'x'"):
        parse_flaser("FLASER x", "x.log", 7)
    with pytest.raises(ParseError, match=r"field 6 \(x\): expected a finite number, found 'nan'"):
        parse_flaser("FLASER 3 1.0 2.0 3.0 nan 0 0 0 0 0 12.5 host 12.5", "x.log", 7)
    with pytest.raises(
        ParseError, match=r"field 3 \(range 1\): expected a non-negative range, found '-1.0'"
    ):
        parse_flaser(line.replace(" 1.0 ", " -1.0 "), "x.log", 7)


def test_bad_lines_are_skipped_and_counted(tmp_path: Path) -> None:
    good = "FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 {t} host {t}\n"
    log = tmp_path / "bad.log"
    log.write_text(
        "PARAM a b\n"
        + good.format(t=1)
        + "FLASER 3 1.0 oops 3.0 0 0 0 0 0 0 2 h 2\n"
        + good.format(t=3)
    )
    source = CarmenSource(log)
    scans = list(source)
    assert [obs.time for obs in scans] == [1.0, 3.0]
    assert source.stats.skipped == 1 and source.stats.reasons["ParseError"] == 1
    assert "bad.log:3: field 4 (range 2)" in source.stats.first_errors[0]
    with pytest.raises(ParseError, match=r"bad\.log:3: field 4"):
        list(CarmenSource(log, strict=True))


@needs_log
def test_truncated_gzip_keeps_the_scans_before_the_cut(tmp_path: Path) -> None:
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(LOG.read_bytes()[:200_000])
    source = CarmenSource(cut)
    scans = list(source)
    assert 10 < len(scans) < 4791
    assert source.stats.reasons["SourceError"] == 1
    assert "truncated or corrupt after line" in " ".join(source.stats.first_errors)
    with pytest.raises(
        SourceError,
        match=r"cut\.log\.gz: truncated or corrupt after line \d+: expected a complete gzip stream",
    ):
        list(read_lines(cut))


def test_bad_options(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="carmen log: expected a file, found nothing at"):
        CarmenSource(tmp_path / "missing.log")
    log = tmp_path / "a.log"
    log.write_text("")
    with pytest.raises(
        SourceSpecError, match="poses: expected 'reference' or 'odometry', found 'gps'"
    ):
        CarmenSource(log, poses="gps")
    for stop in (0, 3, -1):  # no scan selected: an empty map written as a success before
        with pytest.raises(
            SourceSpecError, match=f"start/stop: expected stop > start, found start 3, stop {stop}"
        ):
            CarmenSource(log, start=3, stop=stop)
    assert math.isfinite(CarmenSource(log).adapter.sensor_model.max_range)


@needs_log
def test_move_options_move_every_pose_rigidly() -> None:
    plain = list(CarmenSource(LOG, stop=3))
    moved = list(CarmenSource(LOG, stop=3, move_x=5.0, move_y=-2.0, move_yaw=90.0))
    for a, b in zip(plain, moved, strict=True):
        expect = np.array([-a.pose[1, 3] + 5.0, a.pose[0, 3] - 2.0])
        np.testing.assert_allclose(b.pose[:2, 3], expect, atol=1e-9)
        np.testing.assert_allclose(
            b.points_world()[:, :2],
            np.column_stack([-a.points_world()[:, 1] + 5.0, a.points_world()[:, 0] - 2.0]),
            atol=1e-9,
        )


@needs_log
@pytest.mark.parametrize("noise", [None, "realistic"])
def test_move_options_move_the_odometry_too(noise: str | None) -> None:
    """An estimator starts from the first odometry reading and maps from there: with the
    odometry left where it was, a localised agent's map ignored move_* (two daemons replaying
    the log with different moves aligned at the identity)."""
    move = pose_matrix(5.0, -2.0, 0.0, math.radians(90.0))
    plain = list(CarmenSource(LOG, stop=5, odometry_noise=noise))
    moved = list(
        CarmenSource(LOG, stop=5, odometry_noise=noise, move_x=5.0, move_y=-2.0, move_yaw=90.0)
    )
    for a, b in zip(plain, moved, strict=True):
        assert a.odometry is not None and b.odometry is not None
        np.testing.assert_allclose(b.odometry, move @ a.odometry, atol=1e-9)
        np.testing.assert_allclose(b.pose, move @ a.pose, atol=1e-9)
    # the motion between readings is the same: only the frame moved
    np.testing.assert_allclose(
        np.linalg.inv(moved[0].odometry) @ moved[-1].odometry,
        np.linalg.inv(plain[0].odometry) @ plain[-1].odometry,
        atol=1e-9,
    )


def test_move_options_must_be_finite(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    log.write_text("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 12.5 host 12.5\n")
    with pytest.raises(SourceSpecError, match="move_yaw: expected a finite number, found nan"):
        CarmenSource(log, move_yaw=float("nan"))
