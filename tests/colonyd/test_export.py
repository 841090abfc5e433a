"""`colonyd export`: the live fused map and layer maps of a running colony, as files."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

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
        capture_output=True,
        check=False,
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
        capture_output=True,
        check=False,
        text=True,
        timeout=60,
    )
    assert missing.returncode == 1 and "holds no layer 'nobody'" in missing.stderr
    (tmp_path / "file").write_text("x")
    bad = subprocess.run(
        [*base, "--out", str(tmp_path / "file")],
        capture_output=True,
        check=False,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 3 and "expected a directory, found a file" in bad.stderr


def test_map_reply_carries_classes_and_the_ply_is_coloured_by_class_then_height(tmp_path):
    from colonyd.errors import StatusError
    from colonyd.export import CLASS_COLOURS, decode_map, encode_map, write_maps
    from voxel.ply import read_ply

    keys = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 5], [0, 0, 20], [3, 3, 3]])
    logodds = np.array([1.0, 1.0, 1.0, 1.0, -1.0], np.float32)
    classes = np.array([3, 11, -1, -1, 2], np.int16)
    data = encode_map("a", None, "a.odom", 0.1, keys, logodds, ["a"], classes)
    reply = decode_map(data)
    assert reply.classes is not None and reply.classes.tolist() == classes.tolist()
    assert decode_map(encode_map("a", None, "a.odom", 0.1, keys, logodds, [])).classes is None
    files = write_maps(reply, tmp_path, "map")
    centres, colours = read_ply(files["map.ply"])
    assert len(centres) == 4 and colours is not None  # the occupied voxels only
    assert colours[0].tolist() == CLASS_COLOURS[3].tolist()
    assert colours[1].tolist() == CLASS_COLOURS[11 % len(CLASS_COLOURS)].tolist()
    assert colours[2].tolist() != colours[3].tolist()  # unlabelled: by height, low != high
    bad = encode_map("a", None, "a.odom", 0.1, keys, logodds, [], classes[:3])
    with pytest.raises(StatusError, match="expected 5 classes of 2 bytes, found 6 bytes"):
        decode_map(bad)


def test_export_with_nobody_there_says_where_it_looked(tmp_path):
    """No daemon at the endpoint: the error names it and says none was found (exit code 1)."""
    from colonyd.bench.launcher import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = ["export", "--no-multicast", "--connect", endpoint, "--colony", "nobody"]
    run = subprocess.run(
        [sys.executable, "-m", "colonyd", *args, "--out", str(tmp_path / "o")],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 1, run.stderr
    assert (
        f"no daemon of colony namespace 'nobody' answered within 5 s (looked through {endpoint}): "
        "expected a running colonyd there, found none"
    ) in run.stderr
