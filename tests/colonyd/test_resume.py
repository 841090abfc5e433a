"""Recording positions: the stored record's encoding and validation, the resume decision, the
state directory keeping them with each grid version, and the estimator continuing its frame."""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest

from colonyd.estimator import ScanEstimator
from colonyd.persistence import StateStore
from colonyd.resume import (
    CONTENT,
    RECORD_VERSION,
    EstimatorState,
    Positions,
    SourcePosition,
    agrees,
    decide,
    decode,
    encode,
    fingerprint,
    resumes,
    stat_fingerprint,
)
from plugins.source import open_source
from voxel.localisation import se2


def _state() -> EstimatorState:
    cov = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.001], [0.0, 0.001, 0.003]])
    return EstimatorState(np.array([1.5, -2.0, 0.3]), cov, np.array([1.4, -2.1, 0.29]))


def _position(spec: str = "replay:/data/run.log", **kw: object) -> SourcePosition:
    fields: dict[str, object] = {
        "recording": {"size": 123, "mtime_ns": 456},
        "frames": 40,
        "frame": "/data/run.log:97",
        "done": False,
        "estimator": _state(),
    }
    fields.update(kw)
    return SourcePosition(spec, **fields)  # type: ignore[arg-type]


def _same(a: SourcePosition, b: SourcePosition) -> bool:
    head = (a.spec, a.recording, a.frames, a.frame, a.done) == (
        b.spec,
        b.recording,
        b.frames,
        b.frame,
        b.done,
    )
    if a.estimator is None or b.estimator is None:
        return head and a.estimator is b.estimator
    ea, eb = a.estimator, b.estimator
    odo = (ea.odometry is None and eb.odometry is None) or np.array_equal(ea.odometry, eb.odometry)
    return (
        head
        and np.array_equal(ea.pose, eb.pose)
        and np.array_equal(ea.covariance, eb.covariance)
        and bool(odo)
    )


@pytest.mark.parametrize("codec", ["json", "msgpack"])
def test_record_round_trips_through_json_and_msgpack(codec):
    positions = {
        "replay:/data/run.log": _position(),
        "replay:/data/b.log": _position("replay:/data/b.log", estimator=None, done=True),
        "replay:/data/c.log": _position(
            "replay:/data/c.log", estimator=EstimatorState(np.zeros(3), np.eye(3), None)
        ),
    }
    record = encode(positions)
    if codec == "json":
        raw = json.loads(json.dumps(record))
    else:
        raw = msgpack.unpackb(msgpack.packb(record, use_bin_type=True), raw=False)
    good, bad = decode(raw)
    assert bad == {}
    assert set(good) == set(positions)
    assert all(_same(good[k], positions[k]) for k in positions)


def test_nothing_stored_is_no_position_and_no_error():
    assert decode(None) == ({}, {})
    assert decode(encode({})) == ({}, {})


@pytest.mark.parametrize(
    ("raw", "says"),
    [
        ([1, 2], "expected a map of source positions, found list"),
        ({"v": 99, "sources": {}}, f"expected record version {RECORD_VERSION}, found 99"),
        ({"v": RECORD_VERSION, "sources": "x"}, "expected 'sources' to be a map"),
    ],
)
def test_a_bad_record_is_refused_whole_saying_what_was_expected(raw, says):
    good, bad = decode(raw)
    assert good == {} and says in bad["*"]


def _entry(**change: object) -> dict[str, object]:
    entry = encode({"s": _position("s")})["sources"]["s"]
    for key, value in change.items():
        if key.startswith("estimator."):
            entry["estimator"][key.split(".")[1]] = value
        else:
            entry[key] = value
    return entry


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"frames": -1}, "'frames': expected a whole number >= 0, found -1"),
        ({"frames": True}, "'frames': expected a whole number >= 0, found True"),
        ({"frames": 2.5}, "'frames': expected a whole number >= 0, found 2.5"),
        ({"frame": 7}, "'frame': expected the last frame's name (text), found 7"),
        ({"done": "yes"}, "'done': expected true or false, found 'yes'"),
        ({"recording": {"size": -3}}, "'recording': expected a map of name to count >= 0"),
        ({"recording": None}, "'recording': expected a map of name to count >= 0, found None"),
        ({"estimator": [1, 2]}, "'estimator': expected a map or null, found list"),
        ({"estimator.pose": [1, 2]}, "estimator pose (x, y, yaw): expected 3 finite numbers"),
        ({"estimator.pose": [1, float("nan"), 0]}, "expected 3 finite numbers, found [1, nan"),
        ({"estimator.covariance": "big"}, "estimator covariance (3x3): expected 9 finite"),
        (
            {"estimator.covariance": [[1, 1, 0], [0, 1, 0], [0, 0, 1]]},
            "estimator covariance: expected symmetric and >= 0",
        ),
        (
            {"estimator.covariance": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]},
            "estimator covariance: expected symmetric and >= 0",
        ),
        ({"estimator.odometry": [0, 0]}, "estimator odometry (x, y, yaw): expected 3 finite"),
    ],
)
def test_a_bad_entry_is_refused_alone_saying_what_was_expected_and_found(change, says):
    raw = {"v": RECORD_VERSION, "sources": {"bad": _entry(**change), "good": _entry()}}
    good, bad = decode(raw)
    assert set(good) == {"good"} and set(bad) == {"bad"}
    assert says in bad["bad"], bad["bad"]


def test_only_recordings_resume():
    assert resumes("replay:/data/run.log,stop=5")
    assert not resumes("sim:agent=lidar-1")
    assert not resumes("synthetic:scans=3")
    assert not resumes("nonsense")


def test_decision():
    spec = "replay:/data/run.log"
    rec = {"size": 123, "mtime_ns": 456}
    stored = {spec: _position(spec)}
    go = decide(spec, rec, stored, {})
    assert (go.frames, go.done, go.level) == (40, False, "info")
    assert go.estimator is stored[spec].estimator
    assert "resumes after frame 40 (/data/run.log:97)" in go.message
    done = decide(spec, rec, {spec: _position(spec, done=True)}, {})
    assert done.done and "not read again" in done.message
    changed = decide(spec + ",stop=9", rec, stored, {})
    assert (changed.frames, changed.level) == (0, "warning")
    assert f"the spec changed (the layer holds {spec}'s frames)" in changed.message
    other = decide(spec, {"size": 999, "mtime_ns": 456}, stored, {})
    assert other.frames == 0 and "the recording changed" in other.message
    assert "expected {'size': 123, 'mtime_ns': 456}, found {'size': 999" in other.message
    refused = decide(spec, rec, {}, {spec: "'frames': expected ..."})
    assert (refused.frames, refused.level) == (0, "error") and "unusable" in refused.message
    assert decide(spec, rec, {}, {"*": "bad"}).level == "error"
    new = decide(spec, rec, {}, {})
    assert (new.frames, new.level) == (0, "info")


def _touch(path: Path, hours: int = 1) -> None:
    """Move `path`'s modification time `hours` later, its bytes left as they are."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + hours * 3_600 * 10**9))


def _starts_afresh(
    spec: str, stored: SourcePosition, frames: list[str], caplog: pytest.LogCaptureFixture
) -> Positions:
    """Positions recovered with `stored` for `spec`, started: every frame of the recording is
    read again (the warnings are in `caplog`)."""
    positions = Positions(encode({spec: stored}), [spec])
    with caplog.at_level(logging.WARNING, logger="colonyd.resume"):
        rest = positions.start(open_source(spec), threading.Event())
    assert rest is not None and [o.frame for o in rest] == frames
    return positions


def test_fingerprint_of_a_file_a_folder_and_nothing(tmp_path):
    f = tmp_path / "run.log"
    f.write_text("FLASER\n")
    first = fingerprint(f"replay:{f},stop=3")
    assert first["size"] == 7 and set(first) == {"size", CONTENT}
    f.write_text("FLASER 1\n")
    assert fingerprint(f"replay:{f}") != first
    folder = tmp_path / "scene"
    folder.mkdir()
    (folder / "a.png").write_bytes(b"12")
    (folder / "b.png").write_bytes(b"345")
    assert fingerprint(f"replay:{folder}")["files"] == 2
    assert fingerprint(f"replay:{folder}")["size"] == 5
    assert fingerprint(f"replay:{tmp_path / 'missing'}") == {}


def test_fingerprint_is_the_content_not_the_times(tmp_path):
    f = tmp_path / "run.log"
    f.write_bytes(b"FLASER 1 2 3\n")
    spec = f"replay:{f}"
    first = fingerprint(spec)
    _touch(f)  # touched, or copied without keeping times: the same recording
    assert fingerprint(spec) == first
    copy = tmp_path / "copy.log"
    shutil.copyfile(f, copy)
    assert fingerprint(f"replay:{copy}") == first
    f.write_bytes(b"FLASER 1 2 4\n")  # the same size, another byte
    assert fingerprint(spec)["size"] == first["size"] and fingerprint(spec) != first


def test_a_folder_fingerprint_covers_every_file_below_it(tmp_path):
    root = tmp_path / "scene"
    (root / "frames").mkdir(parents=True)
    (root / "camera-intrinsics.txt").write_text("585 0 320\n")
    for i in range(3):
        (root / "frames" / f"frame-{i:06d}.depth.png").write_bytes(bytes([i]) * 10)
    spec = f"replay:{root}"
    first = fingerprint(spec)
    assert (first["files"], first["size"]) == (4, 40)
    for q in root.rglob("*"):
        _touch(q)
    assert fingerprint(spec) == first
    inside = root / "frames" / "frame-000001.depth.png"
    inside.write_bytes(b"x" * 10)  # a frame's bytes, in the folder's folder
    changed = fingerprint(spec)
    assert (changed["files"], changed["size"]) == (4, 40) and changed != first
    inside.write_bytes(bytes([1]) * 10)
    assert fingerprint(spec) == first
    inside.rename(root / "frames" / "frame-000009.depth.png")  # the same bytes, another frame
    assert fingerprint(spec) != first
    inside = root / "frames" / "frame-000009.depth.png"
    inside.rename(root / "frames" / "frame-000001.depth.png")
    assert fingerprint(spec) == first
    # frames linked from elsewhere (as the reader finds them): their bytes count
    (root / "frames").rename(tmp_path / "elsewhere")
    (root / "frames").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    assert fingerprint(spec) == first
    (tmp_path / "elsewhere" / "frame-000002.depth.png").write_bytes(b"y" * 10)
    assert fingerprint(spec) != first


def _scene(root: Path) -> str:
    """A small 7-Scenes-like folder (`frames/` below it); its `replay:` spec."""
    (root / "frames").mkdir(parents=True)
    (root / "camera-intrinsics.txt").write_text("585 0 320\n")
    for i in range(3):
        (root / "frames" / f"frame-{i:06d}.depth.png").write_bytes(bytes([i]) * 10)
    return f"replay:{root}"


def test_a_folder_fingerprint_walks_a_link_back_up_once(tmp_path):
    """A link to a folder holding it (`latest -> .`, `up -> ..`) is not walked again: followed,
    one such link made the walk go 40 levels deep until the system refused the path (ELOOP), so
    the fingerprint was {} (a recording that cannot be read: it started afresh at every restart,
    its evidence counted again); two made it 2^40 paths long, and the source never started."""
    root = tmp_path / "scene"
    spec = _scene(root)
    first = fingerprint(spec)
    (root / "latest").symlink_to(".", target_is_directory=True)
    assert fingerprint(spec) == first
    (root / "frames" / "up").symlink_to("..", target_is_directory=True)
    assert fingerprint(spec) == first
    (root / "frames" / "frame-000001.depth.png").write_bytes(b"x" * 10)
    assert fingerprint(spec) not in (first, {})


def test_a_folder_fingerprint_leaves_out_what_is_not_a_file(tmp_path):
    """A dangling link, a named pipe or a device below a recording holds no bytes the reader
    reads: it is no part of the fingerprint. A dangling link made it {} (the recording never
    resumed, its evidence counted again at every restart; sizes and times read it as a
    recording); a pipe was opened and read: the source waited for a writer for good."""
    root = tmp_path / "scene"
    spec = _scene(root)
    first = fingerprint(spec)
    (root / "frames" / "gone").symlink_to(tmp_path / "nowhere")
    assert fingerprint(spec) == first
    (root / "loop").symlink_to(root / "loop")  # a link to itself: ELOOP, as dangling
    assert fingerprint(spec) == first
    (root / "null").symlink_to(os.devnull)  # a device: never a recording's bytes
    assert fingerprint(spec) == first
    os.mkfifo(root / "frames" / "pipe")
    assert fingerprint(spec) == first


def test_a_folder_fingerprint_leaves_out_a_file_it_may_not_read(tmp_path):
    """A file below a recording that this daemon may not read (the service runs as its own
    user; a file left by another, mode 0600) is no part of what it replays: left out. It made
    the fingerprint {} (a recording that cannot be read): stored so, the position was taken at
    the restart for one of an older colonyd, compared by size and time, and the recording was
    read afresh at every restart, its evidence already in the layer counted again."""
    root = Path(tempfile.mkdtemp(prefix="colony-fingerprint-"))  # where another user may look
    try:
        root.chmod(0o755)
        spec = _scene(root)
        first = fingerprint(spec)
        secret = root / "frames" / "secret.txt"
        secret.write_text("not yours")
        secret.chmod(0o600)
        if os.geteuid() == 0:  # root reads anything: look as another user
            os.seteuid(65534)
            try:
                theirs = fingerprint(spec)
            finally:
                os.seteuid(0)
            assert fingerprint(spec) not in (first, {})  # read, it is part of the recording
        else:
            secret.chmod(0)
            theirs = fingerprint(spec)
        assert theirs == first
    finally:
        shutil.rmtree(root)


def test_a_folder_fingerprint_takes_any_file_name(tmp_path):
    """A file name that is not UTF-8 (bytes as the system keeps them) raised UnicodeEncodeError,
    a ValueError out of `Positions.start`: the source failed and was never read."""
    root = tmp_path / "scene"
    spec = _scene(root)
    first = fingerprint(spec)
    odd = os.fsdecode(bytes(root / "frames") + b"/note-\xff.txt")
    Path(odd).write_bytes(b"1")
    second = fingerprint(spec)
    assert second not in (first, {}) and (second["files"], second["size"]) == (5, 41)
    Path(odd).write_bytes(b"2")
    assert fingerprint(spec) not in (second, {})


def test_a_position_stored_by_size_and_time_is_matched_by_them(tmp_path, caplog):
    """An older colonyd stored {size, mtime_ns}: the same size and time resume (as that colonyd
    would have), another time starts afresh with the warning; the position stored from then on
    is by content."""
    path = _carmen(tmp_path)
    spec = f"replay:{path}"
    frames = [o.frame for o in open_source(spec)]
    old = SourcePosition(spec, stat_fingerprint(spec), 3, frames[2], False, None)
    assert set(old.recording) == {"size", "mtime_ns"}
    positions = Positions(encode({spec: old}), [spec])
    rest = positions.start(open_source(spec), threading.Event())
    assert rest is not None and [o.frame for o in rest] == frames[3:]
    assert positions.resumed[spec] == 3
    assert positions.position(spec) is not None
    assert positions.record()["sources"][spec]["recording"] == fingerprint(spec)
    _touch(path)
    positions = _starts_afresh(spec, old, frames, caplog)
    assert spec not in positions.resumed
    assert "the recording changed since its position was stored" in caplog.text
    assert "a position stored by an older colonyd" in caplog.text


def test_a_recording_touched_resumes_and_one_changed_starts_afresh(tmp_path, caplog):
    path = _carmen(tmp_path)
    spec = f"replay:{path}"
    frames = [o.frame for o in open_source(spec)]
    stored = SourcePosition(spec, fingerprint(spec), 3, frames[2], False, None)
    _touch(path)
    positions = Positions(encode({spec: stored}), [spec])
    rest = positions.start(open_source(spec), threading.Event())
    assert rest is not None and [o.frame for o in rest] == frames[3:]
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    lines[2] = lines[2].replace("8.000", "7.999", 1)
    path.write_text("".join(lines))
    assert path.stat().st_size == len(text)  # the same size, one reading changed
    _starts_afresh(spec, stored, frames, caplog)
    assert "the recording changed since its position was stored" in caplog.text
    assert "older colonyd" not in caplog.text


def test_agrees():
    a = _state()
    assert agrees(a, a)
    moved = EstimatorState(a.pose + np.array([0.01, 0, 0]), a.covariance, a.odometry)
    assert not agrees(a, moved)
    wrapped = EstimatorState(a.pose + np.array([0, 0, 2 * math.pi]), a.covariance, a.odometry)
    assert agrees(a, wrapped)


# ---------------------------------------------------------------- kept with the layer's versions


def test_positions_come_back_with_the_grid_version_they_were_stored_with(tmp_path):
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot")
    grid = store.recover().grid
    rng = np.random.default_rng(0)
    published = 0
    for seq in range(1, 5):
        grid.integrate(rng.uniform(-2, 2, (50, 3)), np.zeros(3), time=float(seq))
        record = encode({"s": _position("s", frames=seq)})
        if seq == 2:
            store.snapshot(grid, seq - 1, published, encode({"s": _position("s", frames=1)}))
        if seq % 2:
            store.append(seq, grid.delta_since(published), sources=record)
        else:
            store.write(seq, grid.delta_since(published), record)
            store.sync()
        published = grid.version
    grid.integrate(rng.uniform(-2, 2, (50, 3)), np.zeros(3), time=9.0)  # never logged
    store.close()
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot")
    rec = store.recover()
    good, bad = decode(rec.sources)
    assert bad == {} and good["s"].frames == 4 and rec.seq == 4
    rec.grid.integrate(rng.uniform(-2, 2, (50, 3)), np.zeros(3), time=5.0)
    store.snapshot(rec.grid, 4, sources=encode({"s": _position("s", frames=5)}))
    store.close()
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot")
    assert decode(store.recover().sources)[0]["s"].frames == 5  # from snapshot.json
    store.close()


def test_a_record_without_positions_leaves_none(tmp_path):
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    grid.integrate(np.ones((5, 3)), np.zeros(3), time=1.0)
    store.snapshot(grid, 1, sources=encode({"s": _position("s")}))
    grid.integrate(np.ones((5, 3)) * 2, np.zeros(3), time=2.0)
    store.append(2, grid.delta_since(1))  # as an older colonyd wrote it
    store.close()
    store = StateStore(tmp_path, "a", 0.1)
    assert store.recover().sources is None  # unknown: the recordings start afresh
    store.close()
    fresh = StateStore(tmp_path / "new", "a", 0.1)
    assert fresh.recover().sources is None
    fresh.close()


# ---------------------------------------------------------------- resuming a real recording


def _carmen(tmp_path: Path, scans: int = 8) -> Path:
    """A small CARMEN log: a robot driving along x in a corridor, FLASER lines with odometry."""
    lines = []
    angles = -math.pi / 2 + np.arange(180) * math.pi / 180
    for i in range(scans):
        x = 0.2 * i
        ranges = np.minimum(np.abs(1.5 / np.maximum(np.abs(np.sin(angles)), 1e-3)), 8.0)
        fields = [f"{r:.3f}" for r in ranges]
        pose = f"{x:.3f} 0.000 0.000"
        lines.append(f"FLASER 180 {' '.join(fields)} {pose} {pose} {i * 0.1:.3f} host 0.0")
    path = tmp_path / "run.log"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_positions_pass_over_the_stored_frames_and_check_the_last_one(tmp_path):
    path = _carmen(tmp_path)
    spec = f"replay:{path}"
    source = open_source(spec)
    frames = [o.frame for o in source]
    stored = SourcePosition(spec, fingerprint(spec), 3, frames[2], False, None)
    positions = Positions(encode({spec: stored}), [spec])
    passed: list[str] = []
    rest = positions.start(open_source(spec), threading.Event(), lambda o: passed.append(o.frame))
    assert rest is not None and passed == frames[:3]
    assert [o.frame for o in rest] == frames[3:]
    assert positions.resumed[spec] == 3
    # a position naming another frame than the recording has there: afresh, logged
    wrong = SourcePosition(spec, fingerprint(spec), 3, frames[5], False, None)
    positions = Positions(encode({spec: wrong}), [spec])
    rest = positions.start(open_source(spec), threading.Event())
    assert rest is not None and [o.frame for o in rest] == frames
    assert positions.position(spec).frames == 0  # type: ignore[union-attr]
    # read to its end: nothing to read
    done = SourcePosition(spec, fingerprint(spec), 8, frames[7], True, None)
    positions = Positions(encode({spec: done}), [spec])
    assert positions.start(open_source(spec), threading.Event()) is None
    assert positions.record()["sources"][spec]["done"] is True


def test_positions_record_only_configured_recordings(tmp_path):
    path = _carmen(tmp_path)
    spec = f"replay:{path}"
    record = encode({spec: _position(spec), "replay:/gone.log": _position("replay:/gone.log")})
    positions = Positions(record, [spec, "synthetic:scans=3"])
    assert set(positions.record()["sources"]) == {spec}
    positions.advance("synthetic:scans=3", 5, "x", None)  # not a started recording: ignored
    assert set(positions.record()["sources"]) == {spec}


def test_a_restored_estimator_continues_from_the_stored_pose_not_the_odometry(tmp_path):
    path = _carmen(tmp_path, scans=12)
    obs = list(open_source(f"replay:{path},poses=odometry"))
    whole = ScanEstimator(True, np.eye(4))
    poses = [se2.from_matrix(whole(o)) for o in obs]
    half = ScanEstimator(True, np.eye(4))
    for o in obs[:6]:
        half(o)
    state = half.state()
    assert state is not None and np.allclose(state.pose, poses[5])
    # as if the filter had corrected its pose 0.3 m to the left of the odometry's: the
    # restored estimator goes on from there, where a new one would start from the odometry
    corrected = EstimatorState(
        state.pose + np.array([0.0, 0.3, 0.0]), state.covariance, state.odometry
    )
    resumed = ScanEstimator(True, np.eye(4))
    resumed.restore(corrected)
    for o, want in zip(obs[6:], poses[6:], strict=True):
        d = se2.from_matrix(resumed(o)) - want - np.array([0.0, 0.3, 0.0])
        assert abs(d[0]) < 0.05 and abs(d[1]) < 0.05 and abs(d[2]) < 0.02, d
    assert ScanEstimator(True, np.eye(4)).state() is None


def test_a_position_stored_when_the_recording_was_unreadable_is_not_called_older(tmp_path, caplog):
    """A position stored with an empty fingerprint (the recording could not be read then) is not
    an older colonyd's: the recording, readable now, starts afresh and the warning says why."""
    path = _carmen(tmp_path)
    spec = f"replay:{path}"
    frames = [o.frame for o in open_source(spec)]
    stored = SourcePosition(spec, {}, 3, frames[2], False, None)
    _starts_afresh(spec, stored, frames, caplog)
    assert "it could not be read when the position was stored" in caplog.text
    assert "older colonyd" not in caplog.text
