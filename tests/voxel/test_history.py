"""Tests of the history: which updates are recorded, with whose columns and which object ids."""

from __future__ import annotations

import numpy as np

from voxel import keys as vk
from voxel.grid import FREE_STATE, OCCUPIED, VoxelGrid
from voxel.history import History, ObjectTags, Observer
from voxel.occupancy import Changes, Evidence
from voxel.record import RECORD_DTYPE, SEEN_DTYPE
from voxel.sensor import SensorModel

RES = 0.1
ORIGIN = np.array([0.05, 0.05, 0.05])
WALL = np.array([[1.05, 0.05, 0.05]])


def test_unknown_to_free_goes_to_the_seen_log_and_unchanged_hits_are_not_recorded() -> None:
    grid = VoxelGrid(RES)
    grid.integrate(WALL, ORIGIN, time=0.0)
    assert len(grid.free_keys()) == 10 and grid.history.size == 1  # the hit: a record
    seen = grid.history.seen()  # the 10 voxels seen free for the first time: 20 bytes each
    assert seen.size == 10 and set(seen["time"]) == {0.0} and set(seen["version"]) == {1}
    assert sorted(seen["key"]) == sorted(vk.pack(grid.free_keys()))
    for t in range(1, 12):
        grid.integrate(WALL, ORIGIN, time=float(t))
    held = grid.history.size
    grid.integrate(WALL, ORIGIN, time=20.0)  # clamped already: nothing changes, nothing recorded
    assert grid.history.size == held
    grid.integrate(np.array([[2.05, 0.05, 0.05]]), ORIGIN, time=21.0)  # a miss on the occupied wall
    last = grid.voxel_history(WALL[0])[-1]
    assert last["time"] == 21.0 and last["state"] == OCCUPIED and not last["flip"]


def test_state_at_answers_free_space_from_when_it_became_free() -> None:
    """A voxel on a ray that became free at t=10 and was seen again later is free from t=10 on,
    with or without statistics (which re-stamp every touched voxel)."""
    for statistics in (False, True):
        grid = VoxelGrid(RES, statistics=statistics)
        for t in range(10, 20):
            grid.integrate(WALL, ORIGIN, time=float(t))
        ray = np.array([[0.55, 0.05, 0.05]])
        assert grid.state_at(ray, 9.999)[0] == -1
        assert [int(grid.state_at(ray, t)[0]) for t in (10.0, 11.0, 13.0, 19.0)] == [FREE_STATE] * 4
        assert vk.pack(vk.points_to_keys(ray, RES))[0] in vk.pack(grid.changed_between(9.0, 10.0))


def test_pages_cover_whole_versions_and_merge_into_an_equal_history() -> None:
    grid = VoxelGrid(RES)
    for t in range(6):
        wall = WALL + np.array([[0.0, 0.1 * t, 0.0]])
        grid.integrate(wall, ORIGIN, time=float(t), agent=f"robot-{t % 2}")
    src = grid.history
    replica = History()
    after, pages = 0, 0
    while True:
        page, to, more = src.page(after, max_records=15)
        versions = np.unique(page.records["version"])
        # whole versions, within the bound
        assert page.records.size + page.seen.size <= 15 or versions.size == 1
        assert replica.merge(page) == page.records.size + page.seen.size
        assert replica.merge(page) == 0  # a page taken twice adds nothing
        after, pages = to, pages + 1
        if not more:
            break
    assert pages > 2 and after == grid.version == replica.newest_version()
    keys = np.concatenate([src.view()["key"], src.seen()["key"]])
    for t in (-1.0, 0.0, 2.5, 5.0):
        np.testing.assert_array_equal(replica.state_at_all(keys, t), src.state_at_all(keys, t))
        np.testing.assert_array_equal(replica.flips_between(-1, t), src.flips_between(-1, t))
    got = replica.view()
    names = [replica.agents[a] for a in got["agent"]]
    assert names == [src.agents[a] for a in src.view()["agent"]]
    empty, to, more = src.page(after, 15)
    assert empty.records.size == 0 and to == after and not more


def test_record_writes_one_row_per_change_with_the_observer_columns() -> None:
    history = History(capacity=100)
    keys = vk.pack(np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]]))
    changes = [
        Changes(
            keys,
            np.array([np.nan, 0.4, -0.4], np.float32),
            np.array([0.85, -0.01, 0.4], np.float32),
            np.array([True, False, True]),
            np.empty(0, np.int64),
        )
    ]
    observer = Observer(
        time=2.5,
        agent=history.agent_code("robot-a"),
        sensor=3,
        reliability=0.5,
        error=1.0,
        bias=-0.25,
    )
    tags = ObjectTags.of(
        np.array([[4, 5, 6], [7, 8, 9]]), np.array([0, 1, 1]), np.array([11, -1, 12])
    )
    history.record(changes, observer, Evidence.of(SensorModel(), 0.5), tags)
    rec = history.view()
    assert rec["key"].tolist() == keys.tolist()
    assert rec["state"].tolist() == [OCCUPIED, FREE_STATE, OCCUPIED]
    assert rec["flip"].tolist() == [True, True, True]
    assert rec["object_id"].tolist() == [-1, 11, 12] and rec["object_prob"].tolist() == [
        0.0,
        1.0,
        1.0,
    ]
    np.testing.assert_allclose(
        rec["evidence"],
        [0.5 * np.log(0.7 / 0.3), 0.5 * np.log(0.4 / 0.6), 0.5 * np.log(0.7 / 0.3)],
        rtol=1e-6,
    )
    assert (
        set(rec["time"]) == {2.5}
        and set(rec["bias"]) == {-0.25}
        and set(rec["reliability"]) == {0.5}
    )
    assert history.agents == ["robot-a"]


def test_no_object_tags_without_object_ids_or_hits() -> None:
    assert ObjectTags.of(np.zeros((2, 3), np.int64), np.array([0, 1]), None) is None
    assert (
        ObjectTags.of(np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
        is None
    )


def test_dropping_keys_returns_the_buffers_memory_down_to_what_is_held() -> None:
    """Forgetting 90 % of the voxels frees 90 % of the history's allocated bytes: the record
    buffer and the seen log shrink to what they hold (no 65,536-entry floor, which held 4.8 MB
    of a mostly forgotten 079 layer), and an empty history costs little."""
    h = History()
    assert h.allocated_bytes() < 100_000
    keys = np.arange(100_000, dtype=np.int64)
    for v in range(10):
        part = keys[v * 10_000 : (v + 1) * 10_000]
        h.append(part[::2], time=float(v), version=v + 1)
        h._log_seen(part[1::2], float(v), v + 1)
    before = h.allocated_bytes()
    assert h.drop_keys(keys[10_000:]) == 90_000
    assert h.size == 5_000 and h.seen_size == 5_000
    assert h.allocated_bytes() <= 0.15 * before
    h.append(keys[:3], time=11.0, version=11)  # it grows again from there
    assert h.size == 5_003


def _versions_of_10k(versions: int) -> History:
    """A history of `versions` versions, each 10,000 records of agent "a" (keys 10,000 v ...)
    and 10,000 seen entries (those keys + 100,000), version v + 1 at time v."""
    origin = History()
    agent = origin.agent_code("a")
    keys = np.arange(versions * 10_000, dtype=np.int64)
    for v in range(versions):
        part = keys[v * 10_000 : (v + 1) * 10_000]
        origin.append(part, time=float(v), version=v + 1, agent=agent)
        origin._log_seen(part + 100_000, float(v), v + 1)
    return origin


def test_merging_past_the_capacity_keeps_the_newest() -> None:
    """A replica whose history budget is below the origin's keeps the newest records and seen
    entries, however large the page (the daemon's peer history budget relies on it)."""
    origin = _versions_of_10k(3)
    page, to, more = origin.page(0, 1_000_000)
    assert to == 3 and not more
    replica = History(capacity=12_000)
    assert replica.merge(page) == 24_000
    assert replica.size <= 12_000 and replica.seen_size <= 12_000
    assert replica.newest_version() == 3
    assert set(replica.view()["version"]) <= {2, 3} and 3 in set(replica.seen()["version"])


def test_lowering_the_capacity_returns_memory_at_the_next_merge() -> None:
    """More peer layers share the daemon's history budget: a layer whose share shrinks gives
    the excess back when it next takes records."""
    origin, replica = _versions_of_10k(4), History()
    page, to, _ = origin.page(0, 60_000)  # versions 1-3 (20,000 entries each)
    replica.merge(page)
    big = replica.allocated_bytes()
    replica.capacity = 12_000
    replica.merge(origin.page(to, 1_000_000)[0])
    assert replica.size <= 12_000 and replica.seen_size <= 12_000
    assert replica.allocated_bytes() <= 12_000 * (RECORD_DTYPE.itemsize + SEEN_DTYPE.itemsize)
    assert replica.allocated_bytes() < big / 2


def test_replay_takes_back_what_since_gave_in_order_with_the_same_agent_codes() -> None:
    """A history rebuilt from a snapshot's and the pages of its later versions (the write-ahead
    log's, `since`) equals the one that wrote them: records in order, agent codes, seen log;
    entries held of a replayed version (a scan that changed nothing) are replaced, not doubled."""
    grid = VoxelGrid(RES)
    for t in range(3):
        grid.integrate(
            WALL + np.array([[0.0, 0.1 * t, 0.0]]), ORIGIN, time=float(t), agent=f"r-{t % 2}"
        )
    snap = History()
    snap.load(grid.history.view().copy(), list(grid.history.agents), grid.history.seen())
    cut = grid.version
    pages = []
    for t in range(3, 7):
        before = grid.version
        grid.integrate(
            WALL + np.array([[0.0, 0.1 * t, 0.0]]), ORIGIN, time=float(t), agent=f"r-{t % 3}"
        )
        pages.append((before, grid.history.since(before, grid.version)))
    src = grid.history
    assert src.agents == ["r-0", "r-1", "r-2"]
    # the snapshot also held the first replayed version's records already (replaced)
    held = src.view()[src.view()["version"] == cut + 1][:2]
    snap.append(held["key"], **{n: held[n] for n in held.dtype.names if n != "key"})
    for before, page in pages:
        assert snap.replay(page, before) == page.records.size + page.seen.size
    assert np.array_equal(snap.view(), src.view())
    assert np.array_equal(snap.seen(), src.seen())
    assert snap.agents == src.agents
    assert snap.replay(pages[-1][1], grid.version) == 0  # versions held: nothing taken


def test_replaying_past_the_capacity_keeps_the_newest() -> None:
    origin = _versions_of_10k(3)
    small = History(capacity=12_000)
    assert small.replay(origin.since(0, 3), 0) == 24_000
    assert small.size <= 12_000 and small.seen_size <= 12_000
    assert small.newest_version() == 3 and set(small.view()["version"]) <= {2, 3}


def test_since_takes_the_same_entries_in_version_order_or_not() -> None:
    """`since` bisects while versions come in order, and reads every entry once a compaction
    (which orders records by time) left them out of order: the same entries either way."""
    h = History(capacity=4000, per_voxel=2)
    agent = h.agent_code("a")
    rng = np.random.default_rng(3)
    for v in range(1, 41):
        keys = rng.integers(0, 300, 150)
        t = float(rng.uniform(0, 100))  # times not in version order
        h.append(keys, time=t, version=v, agent=agent)
        h._log_seen(keys + 1000, t, v)

    def brute(hist: History, after: int, upto: int) -> tuple[np.ndarray, np.ndarray]:
        rec, seen = hist.view(), hist.seen()
        return (
            rec[(rec["version"] > after) & (rec["version"] <= upto)],
            seen[(seen["version"] > after) & (seen["version"] <= upto)],
        )

    assert h.dropped and not h._records_ordered and h._seen_ordered
    fresh = History()
    fresh.load(h.view()[np.argsort(h.view()["version"], kind="stable")], h.agents, h.seen())
    assert fresh._records_ordered
    for hist in (h, fresh):
        for after, upto in ((0, 40), (10, 20), (39, 40), (40, 40), (5, 3)):
            page = hist.since(after, upto)
            rec, seen = brute(hist, after, upto)
            assert np.array_equal(page.records, rec) and np.array_equal(page.seen, seen)


def test_replay_replaces_held_versions_in_or_out_of_version_order() -> None:
    """Entries of the replayed versions held already go whether the versions are in order (the
    tail is cut) or not (after a compaction: every entry is read)."""
    page_src = History()
    agent = page_src.agent_code("a")
    page_src.append(np.array([40, 50, 51]), time=9.0, version=np.array([4, 5, 5]), agent=agent)
    page_src._log_seen(np.array([140, 150]), np.array([9.0, 9.0]), np.array([4, 5]))
    page = page_src.since(3, 5)
    for order in ([1, 2, 3, 4], [3, 1, 4, 2]):
        versions = np.array(order, dtype=np.uint32)
        records = np.zeros(4, RECORD_DTYPE)
        records["key"], records["version"] = versions * 10, versions
        seen = np.zeros(4, SEEN_DTYPE)
        seen["key"], seen["version"] = versions * 10 + 100, versions
        h = History()
        h.load(records, ["a"], seen)
        assert h._records_ordered == (order == [1, 2, 3, 4])
        assert h.replay(page, 3) == 5
        kept = [k for k in order if k <= 3]
        assert list(h.view()["key"]) == [10 * k for k in kept] + [40, 50, 51]
        assert list(h.seen()["key"]) == [10 * k + 100 for k in kept] + [140, 150]
