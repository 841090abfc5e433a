"""Per-origin layers (own and replicas, single writer each) and the fused view over them."""

from __future__ import annotations

import hashlib
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import TypeVar

import numpy as np

from colonyd.errors import WireError
from colonyd.grid import VoxelGrid, new_grid
from voxel import keys as vk
from voxel.blocks import BLOCK_SHAPES, CORE_CHANNELS, block_shifts, count_blocks
from voxel.delta import Delta

_T = TypeVar("_T")

#: Longest a snapshot of the own layer waits for the publisher to log the grid (`Layer.snapshot`).
UNLOGGED_WAIT_S = 5.0


def relabel(delta: Delta, from_version: int, to_version: int, time: float | None = None) -> Delta:
    """The same voxels with wire versions (layer sequence numbers) instead of grid versions.

    `time` replaces the delta's reference time (the origin sets it to the publication time, so a
    delta repaired through a range query still tells when it was made).
    """
    return Delta(
        resolution=delta.resolution,
        from_version=from_version,
        to_version=to_version,
        keys=delta.keys,
        logodds=delta.logodds,
        last_time=delta.last_time,
        channels=delta.channels,
        time=delta.time if time is None else time,
        surface_mask=delta.surface_mask,
    )


def delta_nbytes(delta: Delta) -> int:
    """Bytes held by the arrays of a delta."""
    return int(
        delta.keys.nbytes
        + delta.logodds.nbytes
        + delta.last_time.nbytes
        + sum(v.nbytes for v in delta.channels.values())
        + (0 if delta.surface_mask is None else delta.surface_mask.nbytes)
    )


#: Most voxels a replica's block holds (its shapes are BLOCK_SHAPES): N voxels fill >= N / this.
BLOCK_VOXELS = max(1 << sum(shifts) for shifts in BLOCK_SHAPES.values())


def replica_shape(keys: np.ndarray | Sequence[np.ndarray]) -> str:
    """Block shape an empty replica takes for its first voxels `keys` (N, 3), or those of several
    arrays together (a snapshot's parts): "planar" when they all lie in one z layer (a 2D
    scanner's map, a third of the memory of cubes), else "cube"."""
    parts = [keys] if isinstance(keys, np.ndarray) else list(keys)
    zs = [k[:, 2] for k in parts if len(k)]
    if not zs:
        return "cube"
    lo, hi = min(int(z.min()) for z in zs), max(int(z.max()) for z in zs)
    return "planar" if lo == hi else "cube"


@dataclass
class Applied:
    """What `Layer.offer` did with a delta."""

    outcome: str  # "applied" | "duplicate" | "stale-epoch" | "gap" | "reset"
    voxels: int = 0
    missing: tuple[int, int] | None = None  # (have, want) sequence range to repair
    drained: list[tuple[int, float]] = field(default_factory=list)  # (seq, created) applied


class Layer:
    """One origin's layer: a grid, its (epoch, seq), recent deltas and out-of-order ones.

    Deltas are labelled with the layer's versions: a delta covering (prev, seq] takes the layer
    from seq `prev` to `seq`.
    """

    def __init__(
        self, origin: str, resolution: float, *, ring_size: int = 64, pending_size: int = 64
    ) -> None:
        self.origin = origin
        self.resolution = resolution
        self.grid: VoxelGrid = new_grid(resolution)
        self.epoch = 0
        self.seq = 0
        self.lock = threading.RLock()
        #: Guards `ring` alone (taken inside `lock` where both are), so that the own layer's
        #: publisher can remember a delta without waiting for a scan's integration.
        self.ring_lock = threading.Lock()
        self.ring: deque[tuple[int, int, Delta]] = deque(maxlen=ring_size)
        self.ring_bytes = 0
        self.ring_max_bytes = 64 << 20
        self.pending: dict[int, tuple[int, float, Delta]] = {}
        self.pending_size = pending_size
        self.updated = 0.0
        self.half_life: float | None = None  # the origin's decay (its heartbeats say)
        #: The own layer's grid version whose content is logged at `seq` (set by the daemon's
        #: publisher; None for a replica, whose content is all in its origin's log). A snapshot
        #: of the own layer holds logged content only (`snapshot`).
        self.logged: int | None = None
        #: Set while a snapshot waits for the publisher to log the grid (it publishes at once).
        self.nudge = threading.Event()
        self._waiting = 0  # snapshots waiting: the publisher's next delta captures the grid
        self._captured: tuple[int, int, Delta] | None = None  # (epoch, seq, whole grid) logged
        self._captures = 0
        #: Failed attempts of the publisher to log (`log_failed`) and the last one's reason: a
        #: snapshot waiting for logged content gives up at the first failure after it asked.
        self._failures = 0
        self._failure = ""
        self._logged_cond = threading.Condition(self.lock)

    def set_half_life(self, half_life: float | None) -> None:
        """Decay this layer as its origin does (so queries give the origin's occupancy)."""
        with self.lock:
            self.half_life = half_life
            self.grid.half_life = half_life

    def _new_grid(self, shape: str = "cube") -> VoxelGrid:
        grid = new_grid(self.resolution, shape)
        grid.half_life = self.half_life
        return grid

    # -- replica side ---------------------------------------------------------------------
    def offer(self, epoch: int, prev: int, seq: int, delta: Delta, created: float = 0.0) -> Applied:
        """Apply a delta covering (prev, seq] if it is next; buffer it if it comes early."""
        with self.lock:
            if epoch < self.epoch:
                return Applied("stale-epoch")
            reset = epoch > self.epoch
            if reset:
                self._reset(epoch)
            if seq <= self.seq:
                return Applied("duplicate")
            if prev > self.seq:
                held = sum(delta_nbytes(v[2]) for v in self.pending.values())
                if (
                    len(self.pending) >= self.pending_size
                    or held + delta_nbytes(delta) > self.ring_max_bytes
                ):
                    self.pending.clear()  # bounded: a range query or a snapshot repairs it
                self.pending[seq] = (prev, created, delta)
                return Applied("reset" if reset else "gap", missing=(self.seq, prev))
            n = self._apply(prev, seq, delta)
            result = Applied("applied", n, drained=[(seq, created)])
            self._drain(result)
            return result

    def _fit_blocks(self, keys: np.ndarray | Sequence[np.ndarray]) -> None:
        """An empty replica takes the block shape of its first voxels (`replica_shape`)."""
        parts = [keys] if isinstance(keys, np.ndarray) else list(keys)
        if any(len(k) for k in parts) and self.grid.store.sorted_keys.size == 0:
            shape = replica_shape(keys)
            if self.grid.store.shifts != block_shifts(shape):
                history = self.grid.history  # paged in already (HistorySync): kept
                self.grid = self._new_grid(shape)
                self.grid.history = history

    def _apply(self, prev: int, seq: int, delta: Delta) -> int:
        delta = relabel(delta, prev, seq)
        if len(delta):
            self._fit_blocks(delta.keys)
            self.grid.apply(delta)
        self.seq = seq
        self.updated = time.time()
        self.remember(prev, seq, delta)
        return len(delta)

    def remember(self, prev: int, seq: int, delta: Delta) -> None:
        """Keep a delta (labelled (prev, seq]) for range repair; bounded in count and bytes."""
        with self.ring_lock:
            if len(self.ring) == self.ring.maxlen:
                self.ring_bytes -= delta_nbytes(self.ring[0][2])
            self.ring.append((prev, seq, delta))
            self.ring_bytes += delta_nbytes(delta)
            while self.ring_bytes > self.ring_max_bytes and len(self.ring) > 1:
                self.ring_bytes -= delta_nbytes(self.ring.popleft()[2])

    def _drain(self, result: Applied) -> None:
        while self.pending:
            ready = [s for s, (p, *_rest) in self.pending.items() if p <= self.seq]
            if not ready:
                break
            for s in sorted(ready):
                p, created, delta = self.pending.pop(s)
                if s > self.seq:
                    result.voxels += self._apply(p, s, delta)
                    result.drained.append((s, created))
        if self.pending:
            result.missing = (self.seq, min(p for p, *_ in self.pending.values()))

    def _reset(self, epoch: int) -> None:
        history = self.grid.history if epoch == self.epoch else None  # same epoch: still valid
        self.grid = self._new_grid()
        if history is not None:
            self.grid.history = history
        self.epoch = epoch
        self.seq = 0
        with self.ring_lock:
            self.ring.clear()
            self.ring_bytes = 0
        self.pending.clear()

    def install_snapshot(self, epoch: int, seq: int, chunks: list[Delta]) -> int:
        """Replace the layer by a snapshot at (epoch, seq); later buffered deltas then apply."""
        grid, voxels = self.build_snapshot(seq, chunks)
        return self.commit_snapshot(epoch, seq, grid, voxels)

    def build_snapshot(self, seq: int, chunks: list[Delta]) -> tuple[VoxelGrid, int]:
        """A grid of a snapshot's `chunks` at `seq`, in the block shape they take (as an empty
        replica would: `_fit_blocks`), and the voxels applied: built apart from this layer
        (nothing of it changes, its lock is not held; `commit_snapshot` puts it in place)."""
        grid = self._new_grid(replica_shape([c.keys for c in chunks]))  # not concatenated
        n = 0
        for chunk in chunks:
            if len(chunk):
                grid.apply(relabel(chunk, 0, seq))
                n += len(chunk)
        return grid, n

    def commit_snapshot(self, epoch: int, seq: int, grid: VoxelGrid, voxels: int) -> int:
        """Replace the layer by a snapshot's `grid` of `voxels` (`build_snapshot`) at (epoch,
        seq), unless it holds as much already (then 0); later buffered deltas then apply."""
        with self.lock:
            if (epoch, seq) <= (self.epoch, self.seq):
                return 0
            pending = self.pending if epoch == self.epoch else {}
            history = self.grid.history if epoch == self.epoch else None  # same epoch: valid
            self._reset(epoch)
            grid.half_life = self.half_life  # (as its origin says now)
            if history is not None:
                grid.history = history
            self.grid = grid
            self.seq = seq
            self.updated = time.time()
            self.pending = {s: v for s, v in pending.items() if s > seq}
            self._drain(Applied("applied"))
            return voxels

    # -- serving side ---------------------------------------------------------------------
    def snapshot(
        self,
        chunk_voxels: int,
        marks: dict[str, float] | None = None,
        deadline: float = math.inf,
    ) -> tuple[int, int, list[Delta]]:
        """(epoch, seq, chunks) of the whole layer, wire-labelled (0, seq]; `marks` gets
        "locked" (time.monotonic() when the layer's lock was taken).

        The own layer's snapshot holds only what its log holds at `seq`: a grid that integrated
        more since its last logged delta waits for the publisher to log it (and capture the grid
        as logged), until `deadline` (time.monotonic(); at most `UNLOGGED_WAIT_S` from now):
        TimeoutError then, or as soon as the publisher fails to log after it asked
        (`log_failed`). A peer holding scans never logged at that seq would keep them for good
        once the origin, killed, recovered the seq without them in the same epoch."""
        with self.lock:
            if marks is not None:
                marks["locked"] = time.monotonic()
            epoch, seq, full = self._logged_full(min(deadline, time.monotonic() + UNLOGGED_WAIT_S))
        n = len(full)
        if n == 0:
            return epoch, seq, [relabel(full, 0, seq)]
        chunks = [
            relabel(full.select(slice(i, min(i + chunk_voxels, n))), 0, seq)
            for i in range(0, n, chunk_voxels)
        ]
        return epoch, seq, chunks

    def _logged_full(self, deadline: float) -> tuple[int, int, Delta]:
        """(epoch, seq, whole grid) as logged (the layer's lock held; see `snapshot`)."""
        seen, failures = self._captures, self._failures
        self._waiting += 1
        try:
            while self.logged is not None and int(self.grid.version) != self.logged:
                if self._captures != seen and self._captured is not None:
                    return self._captured
                if self._failures != failures:  # the publisher tried since, and could not log
                    msg = (
                        "the own layer's content could not be logged for its snapshot: "
                        f"{self._failure}"
                    )
                    raise TimeoutError(msg)
                left = deadline - time.monotonic()
                if left <= 0:
                    msg = "the own layer's content was not logged in time for its snapshot"
                    raise TimeoutError(msg)
                self.nudge.set()
                self._logged_cond.wait(left)
            return self.epoch, self.seq, self.grid.delta_since(0)
        finally:
            self._waiting -= 1
            if not self._waiting:
                self._captured = None  # (memory: the grid's size)

    def capture(self) -> Delta | None:
        """The own grid whole while a snapshot waits for logged content, else None (the
        publisher calls it with the layer's lock held, where it reads the version it logs)."""
        return self.grid.delta_since(0) if self._waiting else None

    def log_failed(self, why: str) -> None:
        """The publisher could not log the own grid (the state directory refuses writes):
        snapshots waiting for it give up now instead of at their deadline (each held the layer
        server's single worker `UNLOGGED_WAIT_S` while the directory refused writes)."""
        with self.lock:
            self._failures += 1
            self._failure = why
            self._logged_cond.notify_all()

    def mark_logged(self, version: int, captured: Delta | None = None) -> None:
        """The own grid's content at `version` is logged at `seq` (set before); `captured`: the
        grid at that version (`capture`), handed to the snapshots waiting for it."""
        with self.lock:
            self.logged = int(version)
            if captured is not None and self._waiting:
                self._captured = (self.epoch, self.seq, captured)
                self._captures += 1
            self._logged_cond.notify_all()

    def range(self, have: int, want: int) -> list[Delta] | None:
        """Recent deltas (labelled (prev, seq]) taking a replica from `have` to >= min(`want`,
        this layer's seq): [] if that is nothing, None if the ring no longer holds them."""
        with self.lock, self.ring_lock:
            want = min(want, self.seq)
            if have >= want:
                return []
            out: list[Delta] = []
            at = have
            for prev, seq, delta in self.ring:
                if seq <= at:
                    continue
                if prev > at:
                    return None
                out.append(delta)
                at = seq
                if at >= want:
                    return out
            return out if at >= want and out else None

    # -- queries --------------------------------------------------------------------------
    def blocks(self) -> int:
        """Voxel blocks allocated by this layer's grid (its memory; 64 voxels each)."""
        return int(self.grid.store.sorted_keys.size)

    def new_blocks(self, keys: np.ndarray | Sequence[np.ndarray], *, replace: bool = False) -> int:
        """Blocks that applying voxels at `keys` (one array, or several taken together: a
        snapshot's parts) would allocate, in the block shape this layer's grid has or (when it
        is empty, or `replace`d by a snapshot of `keys`) will take."""
        parts = [keys] if isinstance(keys, np.ndarray) else [k for k in keys if len(k)]
        if not any(len(k) for k in parts):
            return 0
        with self.lock:
            store = self.grid.store
            if replace or store.sorted_keys.size == 0:
                return count_blocks(parts, block_shifts(replica_shape(parts)))
            blocks = np.unique(np.concatenate([np.unique(store.split(k)[0]) for k in parts]))
            return int(np.count_nonzero(store.lookup(blocks) < 0))

    def known_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Keys and log-odds of the voxels known at time t (`VoxelGrid.known_at`: from the
        history this layer holds)."""
        with self.lock:
            return self.grid.known_at(t)

    def full(self) -> Delta:
        with self.lock:
            return self.grid.delta_since(0)

    def voxels(self) -> int:
        with self.lock:
            return int(self.grid.known_count())

    def digest(self) -> str:
        """Hash of every known voxel's key, log-odds, last time and channels, order-independent.

        Equal digests mean identical layers, bit for bit at the grid's stored precision (what
        `VoxelGrid.content_equal` compares).
        """
        full = self.full()
        known = ~np.isnan(full.logodds)
        packed = vk.pack(full.keys[known])
        order = np.flatnonzero(known)[np.argsort(packed, kind="stable")]
        h = hashlib.sha256()
        h.update(np.sort(packed).tobytes())
        h.update(full.logodds[order].tobytes())
        h.update(full.last_time[order].tobytes())
        for name in sorted(full.channels):
            h.update(name.encode() + b"\0")
            h.update(np.ascontiguousarray(full.channels[name][order]).tobytes())
        return h.hexdigest()[:16]


#: Most channels (beyond log-odds, version and time) a replica's grid holds: the protocol's most
#: in one delta. Each is an array as large as the layer, so ever new names (a `scalar:NAME` costs
#: a few bytes of wire) would grow a replica's memory outside the block budget.
MAX_REPLICA_CHANNELS = 32


def check_channels(layer: Layer, deltas: list[Delta], *, replace: bool = False) -> None:
    """Raise WireError("bad-channel") unless `layer`'s grid can hold the channels of `deltas`
    (with its own, unless a snapshot `replace`s it): class lists of its width (`class_k`), and
    at most `MAX_REPLICA_CHANNELS` channels together. Changes nothing."""
    store = layer.grid.store
    for d in deltas:
        for name in ("class_ids", "class_probs"):
            values = d.channels.get(name)
            if values is not None and values.shape[1:] != (store.class_k,):
                text = (
                    f"expected {name} of {store.class_k} classes a voxel (this replica's), "
                    f"found {values.shape[1] if values.ndim > 1 else 0}"
                )
                raise WireError("bad-channel", text)
    held = set() if replace else {n for n in store.channels if n not in CORE_CHANNELS}
    names = held.union(*(d.channels for d in deltas))
    if len(names) > MAX_REPLICA_CHANNELS:
        text = (
            f"expected at most {MAX_REPLICA_CHANNELS} channels in a replica, found {len(held)} "
            f"held and {len(names) - len(held)} new"
        )
        raise WireError("bad-channel", text)


class Layers:
    """All layers of a daemon by origin; the own layer is written by this daemon only.

    Peer layers are bounded: at most `max_layers` of them, holding at most `max_peer_blocks`
    voxel blocks together (`admit` refuses what would exceed either).
    """

    def __init__(
        self,
        own: str,
        resolution: float,
        *,
        ring_size: int = 64,
        max_layers: int = 256,
        max_peer_blocks: int = 100_000,
    ) -> None:
        self.own_id = own
        self.resolution = resolution
        self.ring_size = ring_size
        self.max_layers = max_layers
        self.max_peer_blocks = max_peer_blocks
        self._layers: dict[str, Layer] = {}
        self._lock = threading.Lock()
        #: Held from a peer delta's (or a range's) admission to its application, and to forget
        #: an agent: what `admit` found (room in the budget, a layer not forgotten) still holds
        #: when the delta is applied, whichever thread (inbox, catch-up) applies another meanwhile.
        self.apply_lock = threading.RLock()
        #: origins forgotten colony-wide (`forget_agent`): never held again, whoever offers them
        self.forgotten: set[str] = set()
        self.on_forget: Callable[[str], None] | None = None  # persists a new tombstone
        self.own = self.get(own)

    def admit(self, origin: str, deltas: list[Delta], *, replace: bool = False) -> None:
        """Raise WireError unless peer layer `origin` may take `deltas` (or be `replace`d by them,
        a snapshot): not our own layer, room for a new layer, the layer's resolution, and the
        peer block budget counted in the block shape the replica will use. Changes nothing."""
        if origin == self.own_id:
            raise WireError(
                "own-origin", f"expected another agent's layer, found our own {origin!r}"
            )
        if origin in self.forgotten:
            raise WireError("forgotten", f"expected a layer not forgotten, found {origin!r}'s")
        layer = self.find(origin)
        resolutions = {float(d.resolution) for d in deltas}
        if layer is None:
            if len(self.all()) > self.max_layers:
                text = f"expected at most {self.max_layers} peer layers, found another: {origin!r}"
                raise WireError("too-many-layers", text)
            bad = [r for r in resolutions if not 0 < r <= 10]
            if bad:
                raise WireError(
                    "bad-resolution", f"expected a resolution in (0, 10] m, found {bad[0]}"
                )
            layer = Layer(origin, deltas[0].resolution if deltas else self.resolution)
        bad = [r for r in resolutions if abs(r - layer.resolution) > 1e-12]
        if bad:
            raise WireError(
                "bad-resolution", f"expected resolution {layer.resolution}, found {bad[0]}"
            )
        check_channels(layer, deltas, replace=replace)
        used = sum(p.blocks() for p in self.all() if p.origin != self.own_id)
        keys = [d.keys for d in deltas]
        if replace:
            used -= layer.blocks()
            voxels = sum(len(k) for k in keys)
            if voxels > (self.max_peer_blocks - used) * BLOCK_VOXELS:  # too many to count blocks
                text = (
                    f"expected peer layers within {self.max_peer_blocks} blocks, found {used} "
                    f"held + a snapshot of {voxels} voxels for {origin!r}"
                )
                raise WireError("over-budget", text)
            new = layer.new_blocks(keys, replace=True)  # the parts together, not concatenated
        else:
            new = sum(layer.new_blocks(k) for k in keys)
        if used + new > self.max_peer_blocks:
            text = (
                f"expected peer layers within {self.max_peer_blocks} blocks, "
                f"found {used} held + {new} new for {origin!r}"
            )
            raise WireError("over-budget", text)

    def install_snapshot(
        self,
        origin: str,
        epoch: int,
        seq: int,
        chunks: list[Delta],
        accept: Callable[[], None] | None = None,
    ) -> int:
        """Replace peer layer `origin` by a snapshot of it (`admit`ted, `replace`): its grid is
        built with no lock held (a big layer takes seconds: the inbox goes on meanwhile), then
        committed under `apply_lock` once what the admission found still holds: the layer not
        forgotten since (a tombstone), room for it, its resolution, and the peer budget with the
        blocks the grid holds (another peer's delta may have taken the room). WireError
        otherwise, nothing changed. `accept` (the snapshot's frames accepted; it raises to
        refuse) is called under the lock once those checks passed, before the commit. The
        voxels installed (0: the layer holds as much already)."""
        layer = self.find(origin)
        resolution = float(chunks[0].resolution) if layer is None else layer.resolution
        builder = layer or Layer(origin, resolution, ring_size=self.ring_size)
        grid, voxels = builder.build_snapshot(seq, chunks)
        with self.apply_lock:
            if origin in self.forgotten:
                text = f"expected a layer not forgotten, found {origin!r}'s (forgotten meanwhile)"
                raise WireError("forgotten", text)
            layer = self.find(origin)
            if layer is None and len(self.all()) > self.max_layers:
                text = f"expected at most {self.max_layers} peer layers, found another: {origin!r}"
                raise WireError("too-many-layers", text)
            if layer is not None and abs(layer.resolution - resolution) > 1e-12:
                text = f"expected resolution {layer.resolution}, found {resolution}"
                raise WireError("bad-resolution", text)
            used = sum(p.blocks() for p in self.all() if p.origin not in (self.own_id, origin))
            blocks = int(grid.store.sorted_keys.size)
            if used + blocks > self.max_peer_blocks:
                text = (
                    f"expected peer layers within {self.max_peer_blocks} blocks, found {used} "
                    f"held (since the snapshot's admission) + {blocks} for {origin!r}'s snapshot"
                )
                raise WireError("over-budget", text)
            if accept is not None:
                accept()
            return self.get(origin, resolution).commit_snapshot(epoch, seq, grid, voxels)

    def get(self, origin: str, resolution: float | None = None) -> Layer:
        with self._lock:
            layer = self._layers.get(origin)
            if layer is None:
                layer = Layer(origin, resolution or self.resolution, ring_size=self.ring_size)
                self._layers[origin] = layer
            return layer

    def find(self, origin: str) -> Layer | None:
        with self._lock:
            return self._layers.get(origin)

    def all(self) -> list[Layer]:
        with self._lock:
            return list(self._layers.values())

    def half_lives(self) -> dict[str, float | None]:
        """origin -> the decay half-life of every layer held."""
        return {layer.origin: layer.grid.half_life for layer in self.all()}

    def versions(self) -> dict[str, tuple[int, int]]:
        """origin -> (epoch, seq) for every layer held."""
        return {layer.origin: (layer.epoch, layer.seq) for layer in self.all() if layer.seq > 0}

    def forget_agent(self, origin: str) -> bool:
        """Drop `origin`'s layer and keep it dropped (a tombstone that repair and every
        admission respect); never the own layer. True if it was new.

        Checked, taken and persisted (`on_forget`) under `apply_lock`: the inbox (tombstones in
        heartbeats) and the forget server forget on their own threads, and threads that checked
        before waiting for the lock each took the same agent as new, past the bound together.
        Nothing new (a tombstone known already, or the bound reached: the set only grows) is
        answered without the lock: every heartbeat carries the tombstones, and its thread would
        wait for a range or a snapshot being applied."""
        if origin == self.own_id or origin in self.forgotten:
            return False
        if len(self.forgotten) >= self.max_layers:
            return False
        with self.apply_lock:  # not between a delta's admission and its application
            if origin in self.forgotten:
                return False
            if len(self.forgotten) >= self.max_layers:
                return False  # bounded: a hostile flood of names cannot grow it without end
            self.forgotten.add(origin)
            self.drop(origin)
            if self.on_forget is not None:
                self.on_forget(origin)  # one writer of the set and its file at a time
        return True

    def drop(self, origin: str) -> None:
        """Forget a peer's layer (an untrusted or retired origin); never the own layer."""
        if origin != self.own_id:
            with self._lock:
                self._layers.pop(origin, None)


def layer_weights(
    weights: dict[str, float], origins: list[str], kinds: dict[str, str]
) -> dict[str, float]:
    """Each origin's reliability weight in the fused view: configured for its agent id, else for
    its kind (as its heartbeat says), else 1.0."""
    return {o: weights.get(o, weights.get(kinds.get(o, ""), 1.0)) for o in origins}


def fused(
    layers: list[Layer],
    resolution: float,
    transforms: dict[str, np.ndarray] | None = None,
    weights: dict[str, float] | None = None,
    at: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fused view: (keys (N,3), log-odds (N,)), the reliability-weighted sum over layers
    (`weights` by origin, 1.0 where none is given); with `at`, of the layers as they were at
    that time (`Layer.known_at`).

    Without `transforms`, every layer at `resolution` is taken as already in the local frame
    (identity). With them (origin -> 4x4 taking its frame into the colony frame), only the layers
    that have one are fused: each voxel's centre is moved into the colony frame and keyed at
    `resolution`; voxels of one layer that land in one key are averaged, then layers summed.
    """
    return FusedMap(at).view(layers, resolution, transforms, weights)


@dataclass(frozen=True)
class Labels:
    """A layer's labelled voxels in a fused view: where each lands (its packed key in the fused
    frame), and its most probable class with that probability (`best_class`)."""

    packed: np.ndarray  # (L,) int64
    classes: np.ndarray  # (L,) int16
    probs: np.ndarray  # (L,) float32


@dataclass(frozen=True)
class Part:
    """One layer's part of a fused view: packed keys in the fused frame and the mean log-odds of
    the layer's voxels that land in each."""

    packed: np.ndarray  # (K,) int64
    logodds: np.ndarray  # (K,) float64


@dataclass(frozen=True)
class Surfaces:
    """A layer's occupied voxels (`VoxelGrid.occupied_keys`) in a fused view: their packed keys
    in the fused frame and their surface points (`VoxelGrid.surface_points`) moved into it."""

    packed: np.ndarray  # (M,) int64
    points: np.ndarray  # (M, 3) float64


def contribution(
    layer: Layer, resolution: float, t: np.ndarray | None, at: float | None = None
) -> Part | None:
    """A layer's known voxels (at time `at` when given) keyed at `resolution` in the frame `t`
    takes it into (its own when None), averaged where several land in one key; None when it
    has none or cannot be keyed (another resolution without a transform)."""
    if t is None and abs(layer.resolution - resolution) > 1e-9:
        return None
    if at is None:
        full = layer.full()
        known = ~np.isnan(full.logodds)
        keys, lo = full.keys[known], full.logodds[known].astype(np.float64)
    else:
        keys, lo32 = layer.known_at(at)
        lo = lo32.astype(np.float64)
    if not len(keys):
        return None
    if t is None:
        return Part(vk.pack(keys), lo)
    packed, inv = np.unique(
        vk.pack(moved_keys(keys, layer.resolution, t, resolution)), return_inverse=True
    )
    return Part(packed, np.bincount(inv, weights=lo) / np.bincount(inv))


def labels(layer: Layer, resolution: float, t: np.ndarray | None) -> Labels | None:
    """A layer's known voxels that hold a class (`VoxelGrid.best_classes`, as `best_class`
    finds it), keyed at `resolution` in the frame `t` takes it into (its own when None); None
    when it holds none or cannot be keyed (another resolution without a transform)."""
    if t is None and abs(layer.resolution - resolution) > 1e-9:
        return None
    with layer.lock:
        keys, classes, probs = layer.grid.best_classes()  # in `contribution`'s order
    if not len(keys):
        return None
    if t is not None:  # row by row as `contribution` moves them: the same keys
        keys = moved_keys(keys, layer.resolution, t, resolution)
    return Labels(vk.pack(keys), classes, probs)


def surfaces(layer: Layer, resolution: float, t: np.ndarray | None) -> Surfaces | None:
    """A layer's occupied voxels and their surface points in the frame `t` takes it into (its
    own when None), keyed at `resolution`; None when the layer keeps no surface channel."""
    with layer.lock:
        if not layer.grid.has_surface:
            return None
        keys = layer.grid.occupied_keys()
        points = layer.grid.surface_points(keys)
    if t is not None:
        keys = moved_keys(keys, layer.resolution, t, resolution)
        points = points @ t[:3, :3].T + t[:3, 3]
    return Surfaces(vk.pack(keys), points)


def moved_keys(
    keys: np.ndarray, layer_resolution: float, t: np.ndarray, resolution: float
) -> np.ndarray:
    """Keys at `resolution` of the centres of voxels `keys` (N, 3, at `layer_resolution`) moved
    by `t` (4x4): where a layer's voxels land in a fused view."""
    centres = vk.keys_to_centers(keys, layer_resolution) @ t[:3, :3].T + t[:3, 3]
    return vk.points_to_keys(centres, resolution)


@dataclass(frozen=True)
class Outputs:
    """A fused view and what a reply or the ROS 2 outputs send of it: its keys (N, 3) and
    log-odds (N,), each voxel's class (N,; None when not asked) and the occupied voxels'
    (`logodds >= 0`) surface points (M, 3)."""

    keys: np.ndarray
    logodds: np.ndarray
    classes: np.ndarray | None
    points: np.ndarray


class FusedMap:
    """The fused view and its outputs kept up to date layer by layer: a layer's part (its
    voxels keyed in the fused frame, `contribution`), its labelled voxels (`labels`, computed
    on the first `classes` that needs them) and its occupied voxels' surface points
    (`surfaces`) are computed again only when its version (epoch, seq, the grid's version and
    half-life) or its transform into the fused frame changed, so a view of a colony where one
    layer grew costs one layer's work plus the final sum."""

    def __init__(self, at: float | None = None) -> None:
        self.at = at  # the layers as they were at this time (their history); None: now
        self._parts: dict[str, tuple[tuple[object, ...], Part | None]] = {}
        self._labels: dict[str, tuple[tuple[object, ...], Labels | None]] = {}
        self._surfaces: dict[str, tuple[tuple[object, ...], Surfaces | None]] = {}
        self._lock = threading.Lock()
        #: Layer parts, labels and surfaces computed (not taken from the cache), by kind.
        self.counts = {"parts": 0, "labels": 0, "surfaces": 0}

    @property
    def computed(self) -> int:
        """Layer parts, labels and surfaces computed (not taken from the cache)."""
        return sum(self.counts.values())

    def outputs(
        self,
        layers: list[Layer],
        resolution: float,
        transforms: dict[str, np.ndarray] | None = None,
        weights: dict[str, float] | None = None,
        *,
        classes: bool = True,
    ) -> Outputs:
        """The view (`view`), each voxel's class (`classes`, when asked) and the occupied
        voxels' surface points (`surface`), finding the view's voxels by one index."""
        packed, lo = self._view(layers, resolution, transforms, weights)
        keys = vk.unpack(packed)
        index = KeyIndex.of_packed(packed)
        labelled = self._classes(layers, resolution, index, transforms) if classes else None
        occupied = lo >= 0
        points = self._surface(
            layers, resolution, keys[occupied], index.subset(occupied), transforms
        )
        return Outputs(keys, lo, labelled, points)

    def view(
        self,
        layers: list[Layer],
        resolution: float,
        transforms: dict[str, np.ndarray] | None = None,
        weights: dict[str, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fused view (as `fused` describes it) of `layers`."""
        packed, lo = self._view(layers, resolution, transforms, weights)
        return vk.unpack(packed), lo

    def classes(
        self,
        layers: list[Layer],
        resolution: float,
        keys: np.ndarray,
        transforms: dict[str, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Per voxel of a fused view's `keys` (`view` of the same layers, resolution and
        transforms): the most probable class over the labelled voxels of every layer that land
        in it, -1 where none does (everywhere in a view of the past)."""
        return self._classes(layers, resolution, KeyIndex(keys), transforms)

    def surface(
        self,
        layers: list[Layer],
        resolution: float,
        keys: np.ndarray,
        transforms: dict[str, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Points (N, 3) of a fused view's voxel `keys` (as `fused_surface` describes them)."""
        return self._surface(layers, resolution, keys, KeyIndex(keys), transforms)

    def _view(
        self,
        layers: list[Layer],
        resolution: float,
        transforms: dict[str, np.ndarray] | None,
        weights: dict[str, float] | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fused view's packed keys (sorted) and log-odds."""
        packed_parts, lo_parts = [], []
        with self._lock:
            self._keep(layers)
            for layer, t in placed_layers(layers, resolution, transforms):
                part = self._part(layer, resolution, t)
                if part is None:
                    continue
                packed_parts.append(part.packed)
                lo_parts.append(part.logodds * (weights or {}).get(layer.origin, 1.0))
        if not packed_parts:
            return np.empty(0, np.int64), np.empty(0, np.float32)
        packed = np.concatenate(packed_parts)
        lo = np.concatenate(lo_parts)
        uniq, inv = np.unique(packed, return_inverse=True)
        total = np.bincount(inv, weights=lo, minlength=uniq.shape[0])
        return uniq, total.astype(np.float32)

    def _classes(
        self,
        layers: list[Layer],
        resolution: float,
        index: KeyIndex,
        transforms: dict[str, np.ndarray] | None,
    ) -> np.ndarray:
        out = np.full(len(index), -1, np.int16)
        if not len(index) or self.at is not None:  # the history keeps no classes
            return out
        targets, classes, probs = [], [], []
        with self._lock:
            self._keep(layers)
            for layer, t in placed_layers(layers, resolution, transforms):
                compute = partial(labels, layer, resolution, t)
                held = self._held(self._labels, "labels", layer, resolution, t, compute)
                if held is None or not len(held.packed):
                    continue
                rows, hit = index.rows(held.packed)
                targets.append(rows)
                classes.append(held.classes[hit])
                probs.append(held.probs[hit])
        if not targets:
            return out
        target, cls, prob = np.concatenate(targets), np.concatenate(classes), np.concatenate(probs)
        best = np.lexsort((-prob, target))  # per target voxel, the most probable class first
        first = np.unique(target[best], return_index=True)[1]
        out[target[best][first]] = cls[best][first]
        return out

    def _surface(
        self,
        layers: list[Layer],
        resolution: float,
        keys: np.ndarray,
        index: KeyIndex,
        transforms: dict[str, np.ndarray] | None,
    ) -> np.ndarray:
        out = vk.keys_to_centers(np.asarray(keys, np.int64).reshape(-1, 3), resolution)
        sums, counts = np.zeros_like(out), np.zeros(len(index))
        with self._lock:
            self._keep(layers)
            for layer, t in placed_layers(layers, resolution, transforms):
                compute = partial(surfaces, layer, resolution, t)
                part = self._held(self._surfaces, "surfaces", layer, resolution, t, compute)
                if part is None:
                    continue
                rows, hit = index.rows(part.packed)
                for axis in range(3):
                    sums[:, axis] += np.bincount(
                        rows, weights=part.points[hit, axis], minlength=len(index)
                    )
                counts += np.bincount(rows, minlength=len(index))
        some = counts > 0
        means = sums[some] / counts[some, None]
        near = np.abs(means - out[some]).max(axis=1, initial=0.0) <= SURFACE_REACH * resolution
        out[np.flatnonzero(some)[near]] = means[near]
        return out

    def _keep(self, layers: list[Layer]) -> None:
        """Forget the parts of layers no longer held."""
        held = {layer.origin for layer in layers}
        for cache in (self._parts, self._labels, self._surfaces):
            for origin in set(cache) - held:
                del cache[origin]

    def _part(self, layer: Layer, resolution: float, t: np.ndarray | None) -> Part | None:
        compute = partial(contribution, layer, resolution, t, self.at)
        return self._held(self._parts, "parts", layer, resolution, t, compute)

    def _held(
        self,
        cache: dict[str, tuple[tuple[object, ...], _T]],
        kind: str,
        layer: Layer,
        resolution: float,
        t: np.ndarray | None,
        compute: Callable[[], _T],
    ) -> _T:
        """`cache`'s value for `layer` in the frame `t` at `resolution`, computed again when
        the layer's version or that frame changed."""
        with layer.lock:
            grid = layer.grid
            tag = (
                layer.epoch,
                layer.seq,
                grid.version,
                grid.half_life,
                layer.resolution,
                resolution,
                None if t is None else np.asarray(t, float).tobytes(),
            )
            held = cache.get(layer.origin)
            if held is None or held[0] != tag:
                held = (tag, compute())
                cache[layer.origin] = held
                self.counts[kind] += 1
        return held[1]


def best_class(full: Delta) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel of a layer's delta: its most probable class (-1: none) and that probability."""
    n = len(full.keys)
    ids, probs = full.channels.get("class_ids"), full.channels.get("class_probs")
    if ids is None or probs is None:
        return np.full(n, -1, np.int16), np.zeros(n, np.float32)
    ids, probs = ids.reshape(n, -1), probs.reshape(n, -1)
    column = probs.argmax(axis=1)
    rows = np.arange(n)
    classes = ids[rows, column].astype(np.int16)
    return classes, np.where(classes >= 0, probs[rows, column], 0.0).astype(np.float32)


class KeyIndex:
    """Rows of a fused view's voxel keys (N, 3), found by key."""

    def __init__(self, keys: np.ndarray) -> None:
        self._hold(vk.pack(np.asarray(keys, np.int64).reshape(-1, 3)))

    @classmethod
    def of_packed(cls, packed: np.ndarray) -> KeyIndex:
        """The index of packed keys (N,) (`voxel.keys.pack`)."""
        index = cls.__new__(cls)
        index._hold(packed)
        return index

    def subset(self, mask: np.ndarray) -> KeyIndex:
        """The index of the keys where `mask` (N,) holds, in their order."""
        return KeyIndex.of_packed(self.packed[mask])

    def _hold(self, packed: np.ndarray) -> None:
        self.packed = packed
        if bool(np.all(packed[1:] > packed[:-1])):  # a view's keys: sorted already
            self.order: np.ndarray | None = None
            self.ordered = packed
        else:
            self.order = np.argsort(packed)
            self.ordered = packed[self.order]

    def __len__(self) -> int:
        return len(self.packed)

    def rows(self, packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For packed keys (M,): the rows of those among them that are held, and a mask (M,)
        of which are."""
        if not len(self.ordered):
            return np.empty(0, np.int64), np.zeros(len(packed), bool)
        at = np.minimum(np.searchsorted(self.ordered, packed), len(self.ordered) - 1)
        hit = self.ordered[at] == packed
        found = at[hit]
        return (found if self.order is None else self.order[found]), hit


def placed_layers(
    layers: list[Layer], resolution: float, transforms: dict[str, np.ndarray] | None
) -> list[tuple[Layer, np.ndarray | None]]:
    """The layers a fused view (`fused`) holds, with the transform into its frame (None: the
    layer is in it already, at `resolution`)."""
    out: list[tuple[Layer, np.ndarray | None]] = []
    for layer in layers:
        t = None if transforms is None else transforms.get(layer.origin)
        if transforms is not None and t is None:
            continue
        if t is None and abs(layer.resolution - resolution) > 1e-9:
            continue
        out.append((layer, t))
    return out


#: How far (voxels of the fused view, per axis) a fused voxel's surface point may lie from its
#: centre: a layer's voxel moved into the fused frame lands where its centre falls (half a
#: voxel), and its own surface point, up to half a voxel per axis from that centre, turns with
#: it (sqrt(3)/2). A layer coarser than the view could reach further: such points are not shown.
SURFACE_REACH = 0.5 + 0.5 * np.sqrt(3.0)


def fused_surface(
    layers: list[Layer],
    resolution: float,
    keys: np.ndarray,
    transforms: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """Points (N, 3) of a fused view's voxel `keys` (`fused` with the same layers, resolution
    and transforms), what its point outputs show: per voxel, the mean of the surface points
    (`VoxelGrid.surface_points`) of the occupied voxels that land in it of the layers holding
    the surface channel, moved into the fused frame; the voxel's centre where none does (all
    centres when no layer holds it) or where that mean lies beyond `SURFACE_REACH` (a coarser
    layer's). One layer in its own frame gives its `surface_points`."""
    return FusedMap().surface(layers, resolution, keys, transforms)
