"""The alignment benchmark runs end to end on a few seeds and reports what issue 11 asks for."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from colonyd.bench.align import run_align_bench
from colonyd.errors import ConfigError
from tests.shared import SHARED_DATA

DATA = SHARED_DATA
needs_data = pytest.mark.skipif(
    not (DATA / "carmen").is_dir() or not (DATA / "octomap").is_dir(),
    reason=f"shared recordings not found at {DATA}",
)
ROW = {"case", "seed", "expect", "aligned", "confidence", "reason", "seconds"}
POSITIVE = ROW | {
    "within_target",
    "confident_wrong",
    "rms_m",
    "yaw_err_deg",
    "inliers",
    "rmse_m",
    "overlap",
}
BASELINE = {
    "baseline_merged",
    "baseline_within_target",
    "baseline_confident_wrong",
    "baseline_rms_m",
    "baseline_confidence",
    "baseline_seconds",
}


@needs_data
def test_short_benchmark_run_writes_every_case_with_its_command(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    result = run_align_bench(
        out,
        DATA,
        seeds=1,
        octomap_seeds=1,
        negative_seeds=1,
        carmen_step=8,
        octomap="octomap/geb079.bt",
        command="colonyd bench align --seeds 1 ...",
    )
    assert json.loads(out.read_text()) == result
    assert result["command"] == "colonyd bench align --seeds 1 ..."
    cases = {row["case"]: row for row in result["cases"]}
    assert set(cases) == {
        "carmen079_halves",
        "octomap_crops_20pct",
        "negative_079_vs_sim_office",
        "negative_079_vs_sim_room",
        "negative_079_halves_no_overlap",
        "negative_octomap_crops_no_overlap",
    }
    assert set(cases["carmen079_halves"]) >= POSITIVE | BASELINE
    assert set(cases["octomap_crops_20pct"]) >= POSITIVE
    assert set(cases["negative_079_vs_sim_room"]) >= ROW
    for line in result["summary"]:
        assert line["ours_confident_wrong"] == 0, line
    assert cases["carmen079_halves"]["aligned"] and cases["carmen079_halves"]["within_target"]


def test_missing_recordings_are_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"expected the shared recordings .* found .*nowhere"):
        run_align_bench(tmp_path / "x.json", tmp_path / "nowhere")
