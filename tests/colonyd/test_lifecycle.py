"""Daemon lifecycle under real processes: sd_notify, SIGHUP reload, SIGTERM, colony key, demo."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path


def test_notify_watchdog_reload_and_clean_sigterm(make_colony, tmp_path):
    colony = make_colony("life")
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(30)  # a loaded machine starts a daemon slowly
    d = colony.add("a", ["synthetic:scans=2,rate=4,points=100"], start=False)
    d.env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "600000"}
    try:
        d.start()
        got = [sock.recv(512).decode()]
        assert got[0].startswith("READY=1"), got
        got.append(sock.recv(512).decode())
        assert got[-1] == "WATCHDOG=1"
        d.signal(signal.SIGHUP)
        deadline = time.monotonic() + 10
        while "RELOADING=1" not in got and time.monotonic() < deadline:
            got.append(sock.recv(512).decode())
        assert "RELOADING=1" in got
        t0 = time.monotonic()
        d.signal(signal.SIGTERM)
        while "STOPPING=1" not in got:
            got.append(sock.recv(512).decode())
        assert d.proc.wait(10) == 0
        assert time.monotonic() - t0 < 5
        text = d.log_path.read_text()
        assert "reloaded" in text and "stopped in" in text  # with the time of each step
    finally:
        sock.close()


def test_start_up_ends_warm_with_its_objects_frozen_out_of_the_collector(make_colony):
    colony = make_colony("warm")
    colony.add("a", ["synthetic:scans=4,rate=4,points=100"])
    reports = colony.wait_status(lambda r: r[0].get("warm"), 60, ["a"], samples=True)
    report = reports[0]
    assert report["warm"], "start-up (kernels, first-use imports) did not end within 60 s"
    # frozen after start-up, and again once the kernels and first-use imports were in
    assert report["heap_freezes"] >= 2
    passes = [name for name, *_ in report["metrics"]["activity"] if name.startswith("gc")]
    threads = set(report["metrics"]["threads"].values())
    assert {"gossip-inbox", "publisher"} <= threads  # by kernel thread id, as perf names them
    assert all(name in ("gc0", "gc1", "gc2") for name in passes)


def test_colony_key_closes_the_colony(make_colony):
    colony = make_colony("keyed", extra=["--colony-key", "correct horse battery staple"])
    colony.add("a", ["synthetic:scans=3,rate=4,points=100,seed=1"])
    colony.add("b", ["synthetic:scans=3,rate=4,points=100,seed=2"])
    intruder = colony.add("x", ["synthetic:scans=3,rate=4,points=100,seed=3"], start=False)
    intruder.args = [
        a for a in intruder.args if a not in ("--colony-key", "correct horse battery staple")
    ]
    intruder.start()
    colony.wait_converged(30, ["a", "b"])
    reports = {
        r["agent"]: r
        for r in colony.wait_status(
            lambda rs: all(
                r["metrics"]["rejected"].get("auth", 0) > 0 for r in rs if r["agent"] in ("a", "b")
            ),
            agents=("a", "b"),
        )
    }
    for agent in ("a", "b"):
        assert "x" not in reports[agent]["layers"]
        assert reports[agent]["metrics"]["rejected"].get("auth", 0) > 0
    # A member restarting with its state keeps its epoch and continues its frame numbers
    # (reserved on disk), so the others' replay windows accept it.
    a = colony.daemons["a"]
    a.stop()
    a.args = [
        x if not x.startswith("synthetic:") else "synthetic:scans=2,rate=4,points=100,seed=4"
        for x in a.args
    ]
    a.start()
    colony.wait_converged(30, ["a", "b"])
    b = colony.reports(["b"])["b"]
    assert b["metrics"]["rejected"].get("replay", 0) == 0, b["metrics"]["rejected"]


def test_demo_runs_and_writes_maps(tmp_path):
    import json

    import cv2
    import numpy as np

    out = tmp_path / "demo-out"
    # 5 s of mapping, and no waiting for alignment after it (nothing below asserts alignment;
    # the aligned colony is test_align_live's): the replays alone still run, and are checked.
    demo = ["demo", "--out", str(out), "--duration", "5", "--align-wait", "0"]
    run = subprocess.run(
        [sys.executable, "-m", "colonyd", *demo],
        check=False,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["robots"]) == {"depth-1", "lidar-1", "cctv-1", "lidar3d-1"}
    for agent, robot in summary["robots"].items():
        if robot["ate_m"] is not None:
            assert robot["ate_m"] < 0.1, (agent, robot)  # the estimate, against the sim's truth
        assert robot["bytes_sent_per_s"] > 0
        if agent != "cctv-1":  # each robot's same-seed replay alone, and its dead reckoning
            assert 0 < robot["ate_alone_m"] < 0.5 and robot["ate_odometry_m"] > 0, (agent, robot)
    # Each robot with both figures gets its "alone -> in the colony" line. (A robot with fewer
    # than 3 recorded poses in this short run has no ATE, and no line: seen once in CI.)
    gains = [
        f"{r['carries']} robot ({agent}): ATE"
        for agent, r in summary["robots"].items()
        if r["ate_m"] is not None and r["ate_alone_m"] is not None
    ]
    assert gains and all(g in run.stdout for g in gains), (gains, run.stdout)
    assert "alone ->" in run.stdout
    from voxel.ply import read_ply

    _, colours = read_ply(out / "map.ply")  # coloured: by class, and by height where unlabelled
    assert colours is not None and len(np.unique(colours, axis=0)) > 5
    assert summary["late_joiner_catch_up_s"] is not None  # lidar3d-1 caught up
    assert summary["map"]["occupied"] > 100 and summary["colony_frame"] in summary["robots"]
    assert (out / "map.bt").stat().st_size > 0 and (out / "map.ply").stat().st_size > 0
    for picture in ("colony.png", "pose-error.png"):
        image = cv2.imread(str(out / picture))
        assert image is not None and image.std() > 10, picture  # not blank
    assert (out / "trajectories" / "depth-1.estimate.tum").stat().st_size > 0
    assert "joined halfway and caught up" in run.stdout
    # Every member's map, aligned or not (an unaligned one in its own frame, not fused).
    written = {p.stem for p in (out / "layers").glob("*.bt")}
    assert written == set(summary["robots"]), (written, run.stdout)
    assert "demo at " in run.stdout  # not a terminal: progress lines instead of the live table


def _children(pid: int) -> set[int]:
    """Processes whose parent is `pid` (from /proc)."""
    kids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.add(int(stat.parent.name))
    return kids


def test_sigterm_to_the_demo_stops_its_daemons_and_replays(tmp_path):
    """A CI timeout or `kill` ends the demo through its clean-up: no daemon (each in a session of
    its own) is left running."""
    demo = subprocess.Popen(
        [sys.executable, "-m", "colonyd", "demo", "--out", str(tmp_path / "o"), "--duration", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    kids: set[int] = set()
    alive: set[int] = set()
    try:
        assert demo.stdout is not None
        for line in demo.stdout:  # not a terminal: the first progress line once members joined
            if line.startswith("demo at "):
                break
        kids = _children(demo.pid)
        assert len(kids) >= 3, kids  # the daemons (the replays alone come after the colony)
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(60) == 130
        deadline = time.monotonic() + 10
        alive = kids
        while alive and time.monotonic() < deadline:
            alive = {k for k in alive if Path(f"/proc/{k}").exists()}
            time.sleep(0.2)
    finally:
        leftover = kids | _children(demo.pid)
        if demo.poll() is None:
            demo.kill()
        for k in leftover:  # do not leave them to the next test
            if Path(f"/proc/{k}").exists():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(k, signal.SIGKILL)
    assert not alive, f"left running after SIGTERM: {alive}"


def _netns_available() -> bool:
    import shutil

    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return False
    probe = subprocess.run(["unshare", "-n", "true"], check=False, capture_output=True, timeout=10)
    return probe.returncode == 0


def test_multicast_discovery_in_a_private_network_namespace():
    import pytest

    if not _netns_available():
        pytest.skip("unshare -n (a private network namespace) is not permitted here")
    script = (
        "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && "
        f"exec {sys.executable} -m tests.colonyd.multicast_check"
    )
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    run = subprocess.run(
        ["unshare", "-n", "sh", "-c", script],
        check=False,
        capture_output=True,
        text=True,
        timeout=90,
        cwd=root,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "converged by multicast discovery" in run.stdout
