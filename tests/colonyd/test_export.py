"""`colonyd export`: the live fused map and layer maps of a running colony, as files."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from voxel.octomap_io import read_bt


def test_export_fetches_the_fused_map_and_layers(make_colony, tmp_path):
    colony = make_colony("export")
    colony.add("a", ["synthetic:scans=4,rate=8,points=200,seed=1"])
    colony.add("b")
    colony.wait_converged(30)
    base = [
        sys.executable,
        "-m",
        "colonyd",
        "export",
        "--colony",
        "export",
        "--namespace",
        colony.namespace,
        "--no-multicast",
        "--connect",
        colony.daemons["b"].endpoint,
    ]
    out = tmp_path / "maps"
    run = subprocess.run(
        [*base, "--out", str(out), "--from", "b"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    assert "fused map in frame a.odom" in run.stdout  # a's frame is the colony frame (root)
    fused, layer = read_bt(out / "fused.bt"), read_bt(out / "a.bt")
    assert fused.occupied.sum() > 100
    order_f, order_l = np.lexsort(fused.keys.T), np.lexsort(layer.keys.T)
    assert np.array_equal(fused.keys[order_f], layer.keys[order_l])
    assert np.array_equal(fused.occupied[order_f], layer.occupied[order_l])
    assert (out / "fused.ply").stat().st_size > 0 and (out / "a.ply").exists()
    missing = subprocess.run(
        [*base, "--out", str(out), "--layer", "nobody"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert missing.returncode == 1 and "holds no layer 'nobody'" in missing.stderr
    (tmp_path / "file").write_text("x")
    bad = subprocess.run(
        [*base, "--out", str(tmp_path / "file")],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 1 and "expected a directory, found a file" in bad.stderr
