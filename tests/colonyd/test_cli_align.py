"""`colonyd align` on real OctoMap crops, its JSON, and its exit codes on bad input."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from colonyd.bench.align import crop_keys
from colonyd.cli import EXIT_DATA, EXIT_OK, main
from tests.shared import SHARED_DATA
from voxel.octomap_io import read_bt, write_bt
from voxel.registration.transform import apply, rigid

OCTOMAP = SHARED_DATA / "octomap" / "geb079.bt"
needs_octomap = pytest.mark.skipif(
    not OCTOMAP.is_file(), reason=f"real OctoMap map not found at {OCTOMAP}"
)
KEYS = {
    "aligned",
    "transform",
    "x",
    "y",
    "z",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "confidence",
    "inliers",
    "rmse_m",
    "overlap",
    "method",
    "seconds",
}


@pytest.fixture(scope="module")
def crops(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[Path, Path, Path, np.ndarray, np.ndarray]:
    bt = read_bt(OCTOMAP)
    folder = tmp_path_factory.mktemp("crops")
    move = rigid(6.0, -13.0, 0.8, yaw=math.radians(-120.0))
    paths = []
    for name, lo, hi, m in (("a", 0.0, 0.6, None), ("b", 0.4, 1.0, move), ("far", 0.75, 1.0, move)):
        keys, occupied = crop_keys(bt.keys, bt.occupied, bt.resolution, lo, hi, m)
        write_bt(folder / f"{name}.bt", bt.resolution, keys, occupied)
        paths.append(folder / f"{name}.bt")
    b_keys, b_occ = crop_keys(bt.keys, bt.occupied, bt.resolution, 0.4, 1.0, move)
    b_points = (b_keys[b_occ] + 0.5) * bt.resolution
    return paths[0], paths[1], paths[2], move, b_points


@needs_octomap
def test_align_real_octomap_crops(crops, tmp_path: Path) -> None:
    a, b, _, move, b_points = crops
    out = tmp_path / "out" / "align.json"
    assert main(["align", str(a), str(b), "--json", str(out)]) == EXIT_OK
    result = json.loads(out.read_text())
    assert set(result) >= KEYS and result["aligned"] and "reason" not in result
    t = np.array(result["transform"])
    rms = np.sqrt(
        np.mean(np.sum((apply(t, b_points) - apply(np.linalg.inv(move), b_points)) ** 2, axis=1))
    )
    assert rms < 1.5 * 0.08
    assert abs(result["yaw_deg"] - 120.0) < 1.0 and abs(result["z"] + 0.8) < 0.08 * 1.5


@needs_octomap
def test_align_crops_that_do_not_overlap_is_not_aligned_and_exits_0(crops, tmp_path: Path) -> None:
    a, _, far, _, _ = crops
    out = tmp_path / "align.json"
    assert main(["align", str(a), str(far), "--dof", "3", "--json", str(out)]) == EXIT_OK
    result = json.loads(out.read_text())
    assert KEYS | {"reason"} <= set(result)
    assert result["aligned"] is False and result["reason"]


def test_bad_input_files_exit_with_the_data_code(tmp_path: Path) -> None:
    (tmp_path / "junk.bt").write_bytes(b"# Octomap OcTree binary file\nid OcTree\n")
    out = tmp_path / "o.json"
    for args, message in (
        (["missing.bt", "missing.bt"], "expected a map file"),
        ([str(tmp_path / "junk.bt"), str(tmp_path / "junk.bt")], "junk.bt"),
    ):
        proc = subprocess.run(
            [sys.executable, "-m", "colonyd", "align", *args, "--json", str(out)],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            timeout=60,
            check=False,
        )
        assert proc.returncode == EXIT_DATA, proc.stderr
        assert "voxel error" in proc.stderr and message in proc.stderr
    assert not out.exists()


def test_bad_dof_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["align", "a.bt", "b.bt", "--dof", "5", "--json", str(tmp_path / "o.json")])
    assert exc.value.code == 2
