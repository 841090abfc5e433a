"""Bounded per-voxel observation history: who saw what, when, with what evidence."""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from voxel import kernels
from voxel import keys as vk
from voxel.errors import InputError
from voxel.occupancy import FREE_STATE, Changes, Evidence
from voxel.raycast import FREE, HIT
from voxel.record import RECORD_DTYPE, SEEN_DTYPE

#: Smallest record buffer and seen log a history keeps allocated (entries): buffers grow by
#: doubling from it and shrink back to it (`drop_keys`), so an empty or mostly forgotten
#: history costs ~50 KB, not the 4.8 MB a 65,536-entry floor held.
MIN_BUFFER = 1024
#: Most agents a history's table holds from merged pages (a page may bring 4096 at a time, and
#: records code them in 16 bits): a holder sending pages of ever new agent names must not grow
#: it without end. A layer's records are its origin's scans: one agent, or a few.
MAX_AGENTS = 4096
#: Log-odds `last_at` reports for a voxel known only from the seen log (OctoMap's first miss).
FIRST_MISS = np.float32(-0.40625)  # log(0.4 / 0.6) on the quantum grid

#: Column names of a record, in storage order.
RECORD_COLUMNS: tuple[str, ...] = tuple(RECORD_DTYPE.names or ())
#: Columns renamed since format 3 (old name -> new name).
RENAMED_V3 = {"experience": "error"}
#: Record columns of snapshots written before records carried the grid version (format 3).
RECORD_DTYPE_V3 = np.dtype(
    [
        (next((old for old, new in RENAMED_V3.items() if new == n), n), RECORD_DTYPE[n])
        for n in RECORD_COLUMNS
        if n != "version"
    ]
)


def _columns(n: int, alloc: Callable[..., np.ndarray] = np.zeros) -> dict[str, np.ndarray]:
    """One array of `n` entries per column of the seen log (SEEN_DTYPE)."""
    names = SEEN_DTYPE.names or ()
    return {name: alloc(n, dtype=SEEN_DTYPE[name]) for name in names}


@dataclass(frozen=True)
class Observer:
    """Who made one scan, when, and how far to trust it: the columns every record of it shares."""

    time: float  # seconds, whole milliseconds
    agent: int  # History.agent_code of the agent
    sensor: int  # voxel.sensor.SENSOR_KINDS code
    reliability: float  # recorded r (the scan's evidence uses the sensor's reliability alone)
    error: float
    bias: float
    version: int = 0  # the grid version of the scan


class ObjectTags(NamedTuple):
    """Object id of each hit voxel of one scan that carries one (the last point of a voxel wins)."""

    keys: np.ndarray  # (U,) packed voxel keys, sorted
    ids: np.ndarray  # (U,) int64 object id per key, -1 none

    @classmethod
    def of(
        cls, hit_keys: np.ndarray, inverse: np.ndarray | None, object_ids: np.ndarray | None
    ) -> ObjectTags | None:
        """Tags of hit voxel keys (U, 3) in packed order from each hit point's row and object id."""
        if object_ids is None or inverse is None or hit_keys.shape[0] == 0:
            return None
        per_voxel = np.full(hit_keys.shape[0], -1, dtype=np.int64)
        per_voxel[inverse] = object_ids
        return cls(vk.pack(hit_keys), per_voxel)

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Object id (int32, -1 none) and probability (1 where tagged) of packed keys."""
        obj_id = np.full(keys.size, -1, dtype=np.int32)
        obj_p = np.zeros(keys.size, dtype=np.float32)
        pos = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        found = self.keys[pos] == keys
        obj_id[found] = self.ids[pos[found]]
        obj_p[found & (obj_id >= 0)] = 1.0
        return obj_id, obj_p


@dataclass(frozen=True)
class HistoryPage:
    """Records of a history (RECORD_DTYPE) whose `agent` column indexes `agents`; the unit a layer's
    history travels in."""

    records: np.ndarray
    agents: list[str]
    seen: np.ndarray = field(default_factory=lambda: np.zeros(0, SEEN_DTYPE))  # SEEN_DTYPE


class History:
    """A columnar log of observations, bounded per voxel and in total.

    Appends are vectorised; when the log is full it is compacted: each voxel keeps its newest
    `per_voxel` records, then the oldest records overall are dropped down to 3/4 of capacity.
    """

    def __init__(self, capacity: int = 2_000_000, per_voxel: int = 16) -> None:
        self.capacity = capacity
        self.per_voxel = per_voxel
        self.records = np.zeros(0, dtype=RECORD_DTYPE)
        self._buf = np.zeros(min(capacity, MIN_BUFFER), dtype=RECORD_DTYPE)
        self.size = 0
        self.agents: list[str] = []
        self._agent_index: dict[str, int] = {}
        self.dropped = 0
        #: The seen log: voxels that went unknown -> free (20 bytes each instead of a record),
        #: bounded by `capacity` too (oldest entries dropped first). Held as one array per
        #: SEEN_DTYPE column: a scan appends ~10^4-10^5 entries, and contiguous columns take
        #: them ~10x faster than the fields of a 20-byte record.
        self._seen = _columns(0)
        self.seen_size = 0
        #: True while the records' (the seen log's) versions never decrease in the order held:
        #: new scans' entries come in version order; a compaction, which orders records by
        #: time, may break it. `since` then finds a delta's versions by bisection at the tail
        #: instead of reading every record (~80 ms under the layer's lock at 2 M records).
        self._records_ordered = True
        self._seen_ordered = True

    def agent_code(self, agent: str) -> int:
        code = self._agent_index.get(agent)
        if code is None:
            code = len(self.agents)
            self.agents.append(agent)
            self._agent_index[agent] = code
        return code

    def append(self, keys: np.ndarray, **columns: object) -> None:
        """Append one record per packed key; columns are arrays of the same length or scalars."""
        n = int(np.asarray(keys).shape[0])
        if n == 0:
            return
        block = self._room(n)
        block["key"] = keys
        block["object_id"] = -1
        for name, value in columns.items():
            block[name] = value
        self._records_ordered = self._records_ordered and _follows(
            self._buf["version"][: self.size], block["version"]
        )
        self.size += n

    def _room(self, n: int) -> np.ndarray:
        """The buffer's next `n` records (a view; compacted or grown as needed), not yet
        counted in `size`."""
        if self.size + n > self._buf.shape[0]:
            if self.size + n > self.capacity:
                self._compact(incoming=n)
            if self.size + n > self._buf.shape[0]:
                grown = np.zeros(
                    min(max(self._buf.shape[0] * 2, self.size + n), max(self.capacity, n)),
                    dtype=RECORD_DTYPE,
                )
                grown[: self.size] = self._buf[: self.size]
                self._buf = grown
        return self._buf[self.size : self.size + n]

    def record(
        self,
        changes: list[Changes],
        observer: Observer,
        evidence: Evidence,
        objects: ObjectTags | None,
    ) -> None:
        """Append one scan's records: every hit voxel and every voxel whose state flipped.

        `changes` are the occupancy update's chunks (appended one by one, as the update made
        them): hits, and voxels whose state changed or that are or were occupied.
        """
        compiled = kernels.records()
        shared = (
            observer.time,
            observer.agent,
            observer.sensor,
            evidence.raw[FREE],
            evidence.raw[HIT],
            observer.error,
            observer.reliability,
            observer.bias,
            observer.version,
        )
        no_tags = np.zeros(0, dtype=np.int32)
        for ch in changes:
            self._log_seen(ch.seen, observer.time, observer.version)
            n = int(ch.keys.size)
            if n == 0:
                continue
            block = self._room(n)
            if self.size and self._buf["version"][self.size - 1] > observer.version:
                self._records_ordered = False
            if compiled is not None:
                tags = (
                    (no_tags, no_tags.view(np.float32))
                    if objects is None
                    else objects.lookup(ch.keys)
                )
                compiled(self._buf, self.size, ch.keys, ch.before, ch.after, ch.hit, *tags, shared)
                self.size += n
                continue
            block["key"] = ch.keys
            block["time"] = observer.time
            block["agent"] = observer.agent
            block["sensor"] = observer.sensor
            block["evidence"] = evidence.raw[FREE]
            block["evidence"][ch.hit] = evidence.raw[HIT]
            block["logodds"] = ch.after
            state = ch.after >= 0
            block["state"] = state  # OCCUPIED (1) or FREE_STATE (0)
            with np.errstate(invalid="ignore"):
                block["flip"] = np.isnan(ch.before) | ((ch.before >= 0) != state)
            if objects is None:
                block["object_id"] = -1
                block["object_prob"] = 0.0
            else:
                block["object_id"], block["object_prob"] = objects.lookup(ch.keys)
            block["error"] = observer.error
            block["reliability"] = observer.reliability
            block["bias"] = observer.bias
            block["version"] = observer.version
            self.size += n

    def _log_seen(
        self, keys: np.ndarray, time: float | np.ndarray, version: int | np.ndarray
    ) -> None:
        """Append seen entries: one time and version for all, or one each."""
        n = int(keys.size)
        if n == 0:
            return
        cols = self._seen
        size = self.seen_size
        if size + n > self.capacity:  # drop the oldest quarter (appended in order)
            keep = max(0, min(size, (self.capacity * 3) // 4 - n))
            for col in cols.values():
                col[:keep] = col[size - keep : size]
            self.dropped += size - keep
            self.seen_size = size = keep
            if cols["key"].shape[0] > max(self.capacity, n):  # the bound was lowered
                cols = {k: c[: max(self.capacity, n)].copy() for k, c in cols.items()}
        if size + n > cols["key"].shape[0]:
            # Uninitialised: only the first seen_size entries are ever read, each written whole
            # (zeroing 1.3 MB was most of a fresh grid's first small scan).
            grown = _columns(
                min(
                    max(cols["key"].shape[0] * 2, size + n, MIN_BUFFER),
                    max(self.capacity, n),
                ),
                np.empty,
            )
            for k, c in grown.items():
                c[:size] = cols[k][:size]
            cols = grown
        self._seen = cols
        cols["key"][size : size + n] = keys
        cols["time"][size : size + n] = time
        cols["version"][size : size + n] = version
        self._seen_ordered = self._seen_ordered and _follows(
            cols["version"][:size], cols["version"][size : size + n]
        )
        self.seen_size = size + n

    def seen(self) -> np.ndarray:
        """The seen log (SEEN_DTYPE, a copy; oldest first)."""
        out = np.empty(self.seen_size, dtype=SEEN_DTYPE)
        for k, c in self._seen.items():
            out[k] = c[: self.seen_size]
        return out

    def _seen_column(self, name: str) -> np.ndarray:
        """One column of the seen log (a view)."""
        return self._seen[name][: self.seen_size]

    def _seen_at(self, t: float) -> np.ndarray:
        """Packed keys (sorted, unique) seen as free at or before time t."""
        return np.unique(self._seen_column("key")[self._seen_column("time") <= t])

    def _compact(self, incoming: int) -> None:
        rec = self._buf[: self.size]
        order = np.lexsort((-rec["time"], rec["key"]))  # by key, newest first
        rec = rec[order]
        starts = np.r_[0, np.flatnonzero(np.diff(rec["key"])) + 1]
        rank = np.arange(rec.size) - np.repeat(starts, np.diff(np.r_[starts, rec.size]))
        rec = rec[rank < self.per_voxel]
        target = max(0, min(rec.size, (self.capacity * 3) // 4 - incoming))
        if rec.size > target:
            newest = np.argsort(rec["time"], kind="stable")[rec.size - target :]
            rec = rec[np.sort(newest)]
        self.dropped += self.size - rec.size
        rec = rec[np.argsort(rec["time"], kind="stable")]
        if self._buf.shape[0] > self.capacity:  # the bound was lowered: return the excess
            self._buf = np.zeros(max(self.capacity, rec.size + incoming), dtype=RECORD_DTYPE)
        self._buf[: rec.size] = rec
        self.size = rec.size
        self._records_ordered = _follows(rec["version"][:0], rec["version"])

    def view(self) -> np.ndarray:
        """All records currently held (a view; oldest appended first)."""
        return self._buf[: self.size]

    def of_voxel(self, key: int) -> np.ndarray:
        """Records of one packed voxel key, oldest first, at most `per_voxel`."""
        rec = self.view()
        mine = rec[rec["key"] == key]
        mine = mine[np.argsort(mine["time"], kind="stable")]
        newest: np.ndarray = mine[-self.per_voxel :].copy()
        return newest

    def state_at(self, keys: np.ndarray, t: float) -> np.ndarray:
        """State (-1/0/1) of packed keys after the last record at or before time t; -1 if none."""
        keys = np.asarray(keys, dtype=np.int64)
        rec = self.view()
        rec = rec[rec["time"] <= t]
        out = np.full(keys.shape[0], -1, dtype=np.int8)
        if rec.size == 0 or keys.size == 0:
            return out
        order = np.lexsort((rec["time"], rec["key"]))
        rk = rec["key"][order]
        rs = rec["state"][order]
        pos = np.searchsorted(rk, keys, side="right") - 1
        ok = (pos >= 0) & (rk[np.maximum(pos, 0)] == keys)
        out[ok] = rs[pos[ok]]
        return out

    def state_at_all(self, keys: np.ndarray, t: float) -> np.ndarray:
        """`state_at`, and free for voxels without a record at or before t that the seen log
        has seen free by then."""
        keys = np.asarray(keys, dtype=np.int64)
        out = self.state_at(keys, t)
        none = out == -1
        if none.any() and self.seen_size:
            seen = self._seen_at(t)
            if seen.size:
                pos = np.minimum(np.searchsorted(seen, keys[none]), seen.size - 1)
                free = seen[pos] == keys[none]
                out[np.flatnonzero(none)[free]] = FREE_STATE
        return out

    def last_at(self, t: float) -> np.ndarray:
        """The last record at or before time t of every voxel that has one (sorted by key)."""
        rec = self.view()
        rec = rec[rec["time"] <= t]
        rec = rec[np.lexsort((rec["time"], rec["key"]))]
        last = np.r_[rec["key"][1:] != rec["key"][:-1], True] if rec.size else np.zeros(0, bool)
        out: np.ndarray = rec[last]
        seen = self._seen_at(t) if self.seen_size else np.empty(0, np.int64)
        seen = seen[~np.isin(seen, out["key"], assume_unique=True)]
        if seen.size:  # known only from the seen log: free, at the first miss's log-odds
            extra = np.zeros(seen.size, dtype=RECORD_DTYPE)
            extra["key"], extra["logodds"], extra["state"] = seen, FIRST_MISS, FREE_STATE
            out = np.concatenate([out, extra])
        return out

    def flips_between(self, t0: float, t1: float) -> np.ndarray:
        """Packed keys whose state changed in (t0, t1]."""
        rec = self.view()
        m = rec["flip"] & (rec["time"] > t0) & (rec["time"] <= t1)
        when = self._seen_column("time")
        fresh = self._seen_column("key")[(when > t0) & (when <= t1)]
        return np.unique(np.concatenate([rec["key"][m], fresh]))

    def drop_keys(self, keys: np.ndarray) -> int:
        """Drop every record of packed `keys` (voxels forgotten: unknown again) and return the
        buffer's memory when it is mostly empty. Returns records dropped."""
        rec = self.view()
        # one sort of the keys serves both look-ups: np.isin hashed every key on each call
        # (~1.5 s for a forget of 1.5 M voxels, even against an empty column)
        wanted = np.sort(np.asarray(keys, dtype=np.int64).reshape(-1))
        gone = _member(rec["key"], wanted)
        n = int(np.count_nonzero(gone))
        if n:
            kept = rec[~gone]
            self._buf[: kept.size] = kept
            self.size = kept.size
        if self.size * 2 < self._buf.shape[0] and self._buf.shape[0] > MIN_BUFFER:
            self._buf = self._buf[: max(self.size + self.size // 4, MIN_BUFFER)].copy()
        gone_seen = _member(self._seen_column("key"), wanted)
        if gone_seen.any():
            left = int(np.count_nonzero(~gone_seen))
            for col in self._seen.values():
                col[:left] = col[: self.seen_size][~gone_seen]
            self.seen_size = left
        held = self._seen["key"].shape[0]
        if self.seen_size * 2 < held and held > MIN_BUFFER:
            cut = max(self.seen_size + self.seen_size // 4, MIN_BUFFER)
            self._seen = {k: c[:cut].copy() for k, c in self._seen.items()}
        return n + int(np.count_nonzero(gone_seen))

    def allocated_bytes(self) -> int:
        """Bytes of the record buffer (its capacity, not only the records held)."""
        return int(self._buf.nbytes + sum(c.nbytes for c in self._seen.values()))

    def newest_version(self) -> int:
        """Highest grid version among the records and seen entries held (0 without any)."""
        versions = [
            int(a.max()) for a in (self.view()["version"], self._seen_column("version")) if a.size
        ]
        return max(versions, default=0)

    def page(
        self, after: int, max_records: int, upto: int | None = None
    ) -> tuple[HistoryPage, int, bool]:
        """Records and seen entries of versions above `after` (and not above `upto`, when
        given), oldest version first, in whole versions: as many as fit `max_records` together
        (at least one version). Returns the page, the highest version it covers (`after` when
        empty) and whether later versions remain."""
        rec, seen = self.view(), self.seen()
        rec, seen = rec[rec["version"] > after], seen[seen["version"] > after]
        if upto is not None:
            rec, seen = rec[rec["version"] <= upto], seen[seen["version"] <= upto]
        if rec.size + seen.size == 0:
            return HistoryPage(rec.copy(), list(self.agents), seen.copy()), after, False
        # entries per version (versions are small consecutive integers): O(n), no sort
        lo = min(int(a.min()) for a in (rec["version"], seen["version"]) if a.size)
        hi = max(int(a.max()) for a in (rec["version"], seen["version"]) if a.size)
        counts = np.bincount(rec["version"].astype(np.int64) - lo, minlength=hi - lo + 1)
        counts += np.bincount(seen["version"].astype(np.int64) - lo, minlength=hi - lo + 1)
        total = np.cumsum(counts)
        fits = int(np.searchsorted(total, max_records, side="right"))  # versions that fit
        to = lo + max(fits, int(np.flatnonzero(counts)[0]) + 1) - 1  # at least one version
        to = min(to, hi)
        rec = rec[rec["version"] <= to]
        seen = seen[seen["version"] <= to]
        rec = rec[np.argsort(rec["version"], kind="stable")]
        seen = seen[np.argsort(seen["version"], kind="stable")]
        return HistoryPage(rec, list(self.agents), seen), to, to < hi

    def since(self, after: int, upto: int) -> HistoryPage:
        """Every record and seen entry of versions in (`after`, `upto`], in the order held, with
        the whole agent table: what one own delta's versions added (its write-ahead log record,
        `replay`). Unbounded, unlike `page`."""
        rec = self.view()
        v = rec["version"]
        if self._records_ordered:  # a strided view: bisection reads ~40 of its entries
            lo = bisect.bisect_right(v, after)
            rec = rec[lo : bisect.bisect_right(v, upto, lo)].copy()
        else:
            rec = rec[(v > after) & (v <= upto)]
        v = self._seen_column("version")
        if self._seen_ordered:
            bounds = np.array([after, upto], dtype=v.dtype)  # of its type: no cast of the column
            take: slice | np.ndarray = slice(*np.searchsorted(v, bounds, side="right"))
        else:
            take = (v > after) & (v <= upto)
        part = {k: c[: self.seen_size][take] for k, c in self._seen.items()}
        seen = np.empty(part["key"].size, dtype=SEEN_DTYPE)
        for k, c in part.items():
            seen[k] = c
        return HistoryPage(rec, list(self.agents), seen)

    def replay(self, page: HistoryPage, after: int) -> int:
        """Take back, at recovery, the entries of versions above `after` of a page `since` made
        of this history: its agent table is registered in order first (the codes stay those of
        the history that wrote it), entries held of those versions are replaced (records of
        scans that changed nothing, made before the version was taken), then the page's are
        appended in its order. The bounds hold as for new scans. Returns entries taken."""
        codes = np.array([self.agent_code(a) for a in page.agents], dtype=np.uint16)
        held = self.view()["version"]
        if self._records_ordered:  # the usual case: cut the tail, read nothing else
            self.size = bisect.bisect_right(held, after)
        elif not (kept := held <= after).all():
            rec = self.view()[kept]
            self._buf[: rec.size] = rec
            self.size = rec.size
        held = self._seen_column("version")
        if self._seen_ordered:
            self.seen_size = int(np.searchsorted(held, np.array(after, held.dtype), "right"))
        elif not (kept := held <= after).all():
            left = int(np.count_nonzero(kept))
            for col in self._seen.values():
                col[:left] = col[: self.seen_size][kept]
            self.seen_size = left
        rec = page.records[page.records["version"] > after]
        if rec.size:
            if int(rec["agent"].max()) >= codes.size:
                msg = (
                    f"history page: expected agent codes below {codes.size} (its table), "
                    f"found {int(rec['agent'].max())}"
                )
                raise InputError(msg)
            if rec.size > self.capacity:  # more than the bound: its newest only
                self.dropped += rec.size - self.capacity
                rec = rec[rec.size - self.capacity :]
            cols = {n: rec[n] for n in RECORD_COLUMNS if n != "key"}
            cols["agent"] = codes[rec["agent"]]
            self.append(rec["key"], **cols)
        seen = page.seen[page.seen["version"] > after]
        if seen.size > self.capacity:
            self.dropped += seen.size - self.capacity
            seen = seen[seen.size - self.capacity :]
        if seen.size:
            self._log_seen(seen["key"], seen["time"], seen["version"])
        return int(rec.size + seen.size)

    def admit(self, page: HistoryPage) -> None:
        """Raise InputError unless `merge` can take `page`: the agents its new records name
        would keep the agent table within `MAX_AGENTS`. Changes nothing."""
        rec = page.records[page.records["version"] > self.newest_version()]
        if not rec.size:
            return
        used = np.unique(rec["agent"])
        new = {page.agents[i] for i in used if page.agents[i] not in self._agent_index}
        if len(self.agents) + len(new) > MAX_AGENTS:
            msg = (
                f"history page: expected at most {MAX_AGENTS} agents in a history, found "
                f"{len(self.agents)} held and {len(new)} new"
            )
            raise InputError(msg)

    def merge(self, page: HistoryPage) -> int:
        """Append the records and seen entries of a page (another holder's) whose versions are
        newer than everything held; agent codes are translated to this history's. The bound
        holds: past `capacity` the oldest go first. Returns records and entries taken."""
        self.admit(page)
        newest = self.newest_version()
        rec = page.records[page.records["version"] > newest]
        seen = page.seen[page.seen["version"] > newest]
        if rec.size:
            used = np.unique(rec["agent"])
            codes = np.zeros(len(page.agents), dtype=np.uint16)
            codes[used] = [self.agent_code(page.agents[i]) for i in used]
            rec = rec.copy()
            rec["agent"] = codes[rec["agent"]]
            rec = rec[np.argsort(rec["version"], kind="stable")]
            if rec.size > self.capacity:  # more than the bound: its newest only
                self.dropped += rec.size - self.capacity
                rec = rec[rec.size - self.capacity :]
            self.append(rec["key"], **{n: rec[n] for n in RECORD_COLUMNS if n != "key"})
        seen = seen[np.argsort(seen["version"], kind="stable")]
        if seen.size > self.capacity:
            self.dropped += seen.size - self.capacity
            seen = seen[seen.size - self.capacity :]
        for version in np.unique(seen["version"]):
            part = seen[seen["version"] == version]
            self._log_seen(part["key"], float(part["time"][0]), int(version))
        return int(rec.size + seen.size)

    def load(self, records: np.ndarray, agents: list[str], seen: np.ndarray | None = None) -> None:
        """Replace the content with saved records, agent table and seen log."""
        seen = np.zeros(0, SEEN_DTYPE) if seen is None else seen
        self._seen = _columns(max(seen.size, MIN_BUFFER))
        for k, c in self._seen.items():
            c[: seen.size] = seen[k]
        self.seen_size = seen.size
        self._buf = np.zeros(max(records.size, min(self.capacity, MIN_BUFFER)), dtype=RECORD_DTYPE)
        self._buf[: records.size] = records
        self.size = records.size
        self.agents = list(agents)
        self._agent_index = {a: i for i, a in enumerate(self.agents)}
        self._records_ordered = _follows(records["version"][:0], records["version"])
        self._seen_ordered = _follows(seen["version"][:0], seen["version"])


def _follows(held: np.ndarray, new: np.ndarray) -> bool:
    """True when versions `new` never decrease and none is below the last of `held`."""
    if new.size == 0:
        return True
    if held.size and held[-1] > new.min():
        return False
    return bool(np.all(new[1:] >= new[:-1]))


def _member(values: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """np.isin(values, sorted_keys) by binary search in the sorted keys."""
    if values.size == 0 or sorted_keys.size == 0:
        return np.zeros(values.shape, dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, values), sorted_keys.size - 1)
    return np.asarray(sorted_keys[pos] == values)
