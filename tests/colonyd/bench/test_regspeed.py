"""The registration CPU bench: a pair recorded twice compares identical, a changed field is named,
and the timed A/B of a checkout against itself reports every case and the worker's imports."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from colonyd.bench import regspeed


def _corpus(tmp_path: Path) -> Path:
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    a, _ = regspeed.sim_map("office", "lidar-1", 40)
    b, _ = regspeed.sim_map("office", "lidar-1", 20)
    regspeed._save(corpus / "office_lidar40_lidar20.npz", a, b, 3)
    return corpus


def test_recordings_compare_identical_and_a_changed_field_is_named(tmp_path: Path) -> None:
    corpus = _corpus(tmp_path)
    first, second = tmp_path / "first.pkl", tmp_path / "second.pkl"
    regspeed.record(corpus, first)
    regspeed.record(corpus, second)
    assert regspeed.compare(first, second) == []
    results = pickle.loads(second.read_bytes())
    case = results["office_lidar40_lidar20"]
    assert case["aligned"], case  # a sub-map of the same path: aligned, near the identity
    case["transform"] = np.asarray(case["transform"]) + 1e-12
    second.write_bytes(pickle.dumps(results))
    (line,) = regspeed.compare(first, second)
    assert line.startswith("office_lidar40_lidar20.transform: max abs diff 1e-12")


def test_bench_times_both_checkouts_and_the_workers_imports(tmp_path: Path) -> None:
    corpus = _corpus(tmp_path)
    result = regspeed.bench(
        corpus, regspeed.HERE, repeats=1, rounds=1, import_case="office_lidar40_lidar20"
    )
    (case,) = result["cases"].values()
    assert case["samples"] == 1 and case["main_median_s"] > 0 and case["branch_median_s"] > 0
    assert result["sim_median_sum_main_s"] > 0 and isinstance(result["sim_change"], float)
    for side in ("main", "branch"):  # registration never loads scipy.ndimage
        assert result["imports"][side]["scipy.ndimage"] is False
        assert result["imports"][side]["second_call"] > 0
