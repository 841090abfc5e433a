"""`colonyd export`: the live fused map and layer maps of a running colony, as files."""

from __future__ import annotations

import logging
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from scipy.spatial import cKDTree

from voxel import keys as vk
from voxel.octomap_io import read_bt
from voxel.ply import read_ply


def test_export_fetches_the_fused_map_and_layers(make_colony, tmp_path, capfd):
    from colonyd.cli import launch

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
    # a's surface points (daemons keep them by default): b's replica of a's layer as it is and
    # in the fused map, not the voxels' centres
    points, _ = read_ply(out / "fused.ply")
    layer_points, _ = read_ply(out / "a.ply")
    np.testing.assert_allclose(
        points[np.lexsort(points.T)], layer_points[np.lexsort(layer_points.T)], atol=1e-6
    )
    centres = vk.keys_to_centers(fused.keys[fused.occupied], 0.1)
    # each point in a voxel (codes at +-127 put it on a face: float32), each voxel holds one
    off, _ = cKDTree(centres).query(points, p=np.inf)
    back, _ = cKDTree(points).query(centres, p=np.inf)
    assert len(points) == len(centres)
    assert off.max() < 0.05 + 1e-6 and back.max() < 0.05 + 1e-6 and off.mean() > 0.01
    # the errors' exit codes and messages, as the command line's `launch` gives them (in this
    # process: a new interpreter for each adds only its start-up)
    capfd.readouterr()
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level  # the command sets up logging: put it back
    try:
        with pytest.raises(SystemExit) as missing:
            launch([*base[3:], "--out", str(out), "--layer", "nobody"])
        err = capfd.readouterr().err
        assert missing.value.code == 1 and "holds no layer 'nobody': expected an agent id" in err
        assert "(its fused map's: a, b;" in err or "(its fused map's: a;" in err, err
        with pytest.raises(SystemExit) as unknown:
            launch([*base[3:], "--out", str(out), "--from", "nobody"])
        err = capfd.readouterr().err
        assert unknown.value.code == 1 and "daemon 'nobody' of colony namespace" in err
        assert "expected one of those that did: a, b" in err, err
        (tmp_path / "file").write_text("x")
        with pytest.raises(SystemExit) as bad:
            launch([*base[3:], "--out", str(tmp_path / "file")])
        err = capfd.readouterr().err
        assert bad.value.code == 3 and "expected a directory, found a file" in err
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def test_map_reply_carries_classes_and_points_and_the_ply_is_coloured_by_class_then_height(
    tmp_path,
):
    from colonyd.errors import StatusError
    from colonyd.export import CLASS_COLOURS, MapReply, decode_map, encode_map, write_maps

    keys = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 5], [0, 0, 20], [3, 3, 3]])
    logodds = np.array([1.0, 1.0, 1.0, 1.0, -1.0], np.float32)
    classes = np.array([3, 11, -1, -1, 2], np.int16)
    centres = vk.keys_to_centers(keys[:4], 0.1)
    points = centres + np.array([[0.01, -0.02, 0.03], [0, 0, -0.049], [0, 0, 0], [0.02, 0, 0]])
    reply = decode_map(
        encode_map(MapReply("a", None, "a.odom", 0.1, keys, logodds, ["a"], classes, points))
    )
    assert reply.classes is not None and reply.classes.tolist() == classes.tolist()
    assert reply.points is not None and np.abs(reply.points - points).max() < 1e-7
    plain = decode_map(encode_map(MapReply("a", None, "a.odom", 0.1, keys, logodds)))
    assert plain.classes is None and plain.points is None
    np.testing.assert_array_equal(plain.occupied_points(), centres)
    files = write_maps(reply, tmp_path, "map")
    at, colours = read_ply(files["map.ply"])
    assert colours is not None  # the occupied voxels only, at their points
    np.testing.assert_allclose(at, points, atol=1e-6)
    assert colours[0].tolist() == CLASS_COLOURS[3].tolist()
    assert colours[1].tolist() == CLASS_COLOURS[11 % len(CLASS_COLOURS)].tolist()
    assert colours[2].tolist() != colours[3].tolist()  # unlabelled: by height, low != high
    files = write_maps(plain, tmp_path, "plain")
    np.testing.assert_allclose(read_ply(files["plain.ply"])[0], centres, atol=1e-6)
    bad = encode_map(MapReply("a", None, "a.odom", 0.1, keys, logodds, [], classes[:3]))
    with pytest.raises(StatusError, match="expected 5 classes of 2 bytes, found 6 bytes"):
        decode_map(bad)
    body = msgpack.unpackb(encode_map(reply))
    for cut, message in (
        (body["surface"][:36], "expected 4 surface offsets of 12 bytes, found 36"),
        (np.full(12, np.nan, "<f4").tobytes(), "expected finite surface offsets, found NaN"),
        (np.full(12, 0.2, "<f4").tobytes(), r"within 0.136603 m per axis, found 0.2 m"),
    ):
        with pytest.raises(StatusError, match=message):
            decode_map(msgpack.packb({**body, "surface": cut}))


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


def test_changes_of_an_unchanged_fused_map_are_none():
    """A history keeps a voxel's log-odds as of its last state change: a voxel one layer hit
    once (+0.84) and another saw free ten times (-0.41 at its flip, -2.0 now) is occupied in
    the fused map from history and free in the live one. `colonyd changes` compared the map
    at --since with the live map and reported it as disappeared from an unchanged colony."""
    from colonyd.export import MapReply, changes_between, diff_maps
    from colonyd.grid import new_grid
    from colonyd.layers import Layer, fused

    a, b = Layer("a", 0.1), Layer("b", 0.1)
    a.grid, b.grid = new_grid(0.1), new_grid(0.1)
    a.grid.integrate(np.array([[2.05, 0.05, 0.05]]), np.zeros(3), time=1.0)
    for i in range(10):
        b.grid.integrate(np.array([[4.05, 0.05, 0.05]]), np.zeros(3), time=1.0 + i)

    def fetch(at: float | None) -> MapReply:
        keys, lo = fused([a, b], 0.1, at=at)
        return MapReply("a", None, "a.odom", 0.1, keys, lo.astype(np.float32))

    live = diff_maps(fetch(20.0), fetch(None), 20.0)  # what the command did: not like with like
    assert [20, 0, 0] in live.disappeared.tolist()
    changes = changes_between(fetch, 20.0, 30.0)
    assert len(changes.appeared) == len(changes.disappeared) == 0
    a.grid.integrate(np.array([[0.55, 0.05, 0.05]]), np.zeros(3), time=25.0)  # a real change
    changes = changes_between(fetch, 20.0, 30.0)
    assert changes.appeared.tolist() == [[5, 0, 0]] and len(changes.disappeared) == 0


def test_export_writes_the_layers_not_aligned_in_their_own_frames(make_colony, tmp_path):
    """Two robots whose maps are not aligned (no alignment attempts here): the export wrote the
    fused map and the root's layer only, and said nothing of the other robot's map."""
    colony = make_colony("apart")
    for agent, seed in (("a", 1), ("c", 2)):
        d = colony.add(agent, [f"synthetic:scans=3,rate=8,points=200,seed={seed}"], start=False)
        d.env["COLONYD_ALIGN_S"] = "0"
        d.start()
    colony.wait_converged(30)
    from protocol.keyexpr import EXPORT, status_selector

    asked: list[str] = []  # "<agent asked>?<parameters>" of every export query

    def spy(query) -> None:
        who = str(query.key_expr).split("/")[-2]
        asked.append(f"{who}?{query.parameters}" if str(query.parameters) else who)
        query.drop()

    spying = colony.session().declare_queryable(status_selector(colony.namespace, EXPORT), spy)
    out = tmp_path / "maps"
    run = subprocess.run(
        [
            sys.executable, "-m", "colonyd", "export", "--colony", "apart",
            "--namespace", colony.namespace, "--no-multicast",
            "--connect", colony.daemons["a"].endpoint, "--out", str(out), "--from", "a",
        ],
        capture_output=True, check=False, text=True, timeout=60,
    )  # fmt: skip
    spying.undeclare()
    assert run.returncode == 0, run.stderr
    # each layer asked of that daemon alone (every holder of a replica sent its copy), and the
    # fused map not asked again after the first layer (every daemon computed and sent its own
    # again for each layer not aligned; the spy may miss the very first query, made while the
    # command's session still learns where queryables are)
    layer_queries = [i for i, x in enumerate(asked) if "layer=" in x]
    assert sorted(asked[i] for i in layer_queries) == ["a?layer=a", "a?layer=c"], asked
    assert "*" not in asked[layer_queries[0] :], asked
    assert sorted(p.name for p in out.iterdir()) == ["a.bt", "a.ply", "fused.bt", "fused.ply",
                                                     "unaligned"]  # fmt: skip
    assert sorted(p.name for p in (out / "unaligned").iterdir()) == ["c.bt", "c.ply"]
    assert "not in the fused map: c (each in its own frame in unaligned/)" in run.stdout
    c = read_bt(out / "unaligned" / "c.bt")
    assert c.occupied.sum() > 50  # c's own map, as its origin holds it
