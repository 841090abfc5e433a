"""Catch-up: the repair client that brings a peer's layer up to the best version the colony
reports."""

from __future__ import annotations

import logging
import math
import random
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import zenoh

from colonyd.errors import WireError
from colonyd.frames import Sender, concat
from colonyd.layers import BLOCK_VOXELS, Layer, Layers
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.replicas import Replicas
from colonyd.worker import Bounded, Worker
from protocol import (
    DeltaRangeReply,
    DeltaRangeRequest,
    HistoryReply,
    HistoryRequest,
    Message,
    ProtocolError,
    Receiver,
    SnapshotReply,
    SnapshotRequest,
)
from protocol.keyexpr import query_key
from voxel.delta import Delta

log = logging.getLogger(__name__)

#: Most parts of one reply a requester accepts (a snapshot of a full budget is far fewer).
MAX_REPLY_PARTS = 4096
#: Most holders of a layer asked in one repair.
MAX_SERVERS = 3
#: A snapshot that did not arrive whole within the query timeout is asked for again with the
#: timeout doubled, at most this many times over (a large layer served by a busy holder takes
#: longer than the timeout; asking again as briefly would never get it).
MAX_DOUBLINGS = 4
#: Most origins whose incomplete snapshots are remembered, and most holders resting.
MAX_SHORT = 1024

#: What `CatchUp._fetch_range` found: deltas taken, nothing newer held at our epoch (a snapshot
#: from that holder would bring nothing), the range no longer held (its snapshot is asked for),
#: part of a reply only (a slow holder: its snapshot is asked for, whose timeout doubles), or no
#: usable answer.
TAKEN, NOTHING_NEWER, NOT_HELD, PARTIAL, FAILED = (
    "taken",
    "nothing-newer",
    "not-held",
    "partial",
    "failed",
)


def snapshot_timeout(base_s: float, failures: int) -> float:
    """Query timeout of a snapshot request after `failures` incomplete ones in a row."""
    return base_s * (1 << min(failures, MAX_DOUBLINGS))


@dataclass
class Repair:
    """A request to bring the layer of `origin` up to the best version the colony reports."""

    origin: str
    servers: list[str]
    asked: float  # time.monotonic() when it was scheduled


class Replies(list[Any]):
    """The validated replies of one query, not yet accepted (no replay window moved): `CatchUp.take`
    accepts them once the reply as a whole passed its checks. `sizes` are their frames' bytes."""

    def __init__(self) -> None:
        super().__init__()
        self.sizes: list[int] = []


def reply_items(msg: Message) -> int:
    """Voxels a reply's delta holds (0 for a reply without one)."""
    delta = getattr(msg, "delta", None)
    return 0 if delta is None else len(delta)


def complete(msgs: list[Any], what: str) -> bool:
    """True if `msgs` are every part of one reply, each once."""
    if not msgs:
        return False
    parts = {m.parts for m in msgs}
    indices = {m.part for m in msgs}
    if len(parts) != 1 or len(indices) != len(msgs) or len(msgs) != parts.pop():
        log.info("incomplete %s reply: %d parts received", what, len(msgs))
        return False
    return True


class CatchUp:
    """One repair at a time per origin, on one worker: a range of recent deltas from a holder
    when it has them, else the holder's snapshot of the whole layer."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        replicas: Replicas,
        sender: Sender,
        receiver: Receiver,
        metrics: Metrics,
        *,
        query_timeout_s: float = 5.0,
        part_bytes: int = 4 << 20,
        stop: threading.Event | None = None,
    ) -> None:
        self.session = session
        self.namespace = namespace
        self.replicas = replicas
        self.layers: Layers = replicas.layers
        self.sender = sender
        self.receiver = receiver
        self.metrics = metrics
        self.query_timeout_s = query_timeout_s
        self.part_bytes = part_bytes
        #: Most voxels the replies of one snapshot or range query may hold together: what the
        #: peer budget holds (a layer's snapshot or range beyond it is refused by `Layers.admit`
        #: anyway): a few bytes of zstd decode to millions of voxels, and 4096 parts of them must
        #: not pile up decoded before that refusal.
        self.max_voxels = self.layers.max_peer_blocks * BLOCK_VOXELS
        self.membership: Membership | None = None
        self._rng = random.Random()
        self._repairing: set[str] = set()
        #: Origin -> snapshot requests in a row that did not arrive whole (`snapshot_timeout`).
        self._short: dict[str, int] = {}
        #: Holder -> time.monotonic() until which it is not asked (`_rest`): a holder whose query
        #: gave nothing usable rests as long as that query took, whatever layer a repair is for.
        self._resting: dict[str, float] = {}
        self._lock = threading.Lock()
        self._worker: Worker[Repair] = Worker(
            "gossip-repair",
            self._repair,
            Bounded(1024),
            describe=lambda rep: f"repair of {rep.origin}",
            done=self._done,
            stop=stop,
            activity=metrics.activity,
        )

    def start(self, membership: Membership) -> None:
        self.membership = membership
        self._worker.start()

    def close(self) -> None:
        self._worker.close()

    def request(self, origin: str, servers: list[str]) -> None:
        """Bring `origin`'s layer up to date, asking `servers` first; no-op while it is under
        way."""
        if origin in self.layers.forgotten:
            return  # a tombstone: never repaired back
        with self._lock:
            if origin in self._repairing:
                return
            self._repairing.add(origin)
        # a full queue forgets it (done below)
        self._worker.put(Repair(origin, servers, time.monotonic()))

    def idle(self) -> bool:
        """True when no repair is queued or under way."""
        with self._lock:
            return not self._repairing

    def new_request_id(self) -> int:
        """A fresh random request id (u63)."""
        return self._rng.getrandbits(63)

    def _done(self, rep: Repair) -> None:
        with self._lock:
            self._repairing.discard(rep.origin)

    # -- the worker -----------------------------------------------------------------------
    def _repair(self, rep: Repair) -> None:
        servers = list(rep.servers)
        want_epoch, want_seq = 0, 0
        layer = self.layers.find(rep.origin)
        if self.membership is not None:
            want_epoch, want_seq, _ = self.membership.best(rep.origin)
            # the best first, then any other with more than we hold (a claim nobody can serve
            # must not hide the real holders)
            have = (layer.epoch, layer.seq) if layer else (0, 0)
            holders = [a for v, a in self.membership.holders(rep.origin) if v > have]
            servers = holders + [s for s in servers if s not in holders]
        now = time.monotonic()
        awake = [s for s in servers if self._resting.get(s, 0.0) <= now]
        if len(awake) < len(servers):
            self.metrics.add("repair_holders_resting", len(servers) - len(awake))
        for server in awake[:MAX_SERVERS]:
            if self._worker.stop.is_set():
                return
            have = (layer.epoch, layer.seq) if layer else (0, 0)
            if want_epoch and (want_epoch, want_seq) <= have and not (layer and layer.pending):
                return
            if layer and layer.seq > 0 and want_epoch in (0, layer.epoch):
                t0 = time.monotonic()
                found = self._fetch_range(server, rep.origin, layer, want_seq)
                if found == TAKEN:
                    self._resting.pop(server, None)
                    layer = self.layers.find(rep.origin)
                    if layer is not None and not layer.pending:
                        return
                elif found == NOTHING_NEWER:  # (a heartbeat claimed more than it holds)
                    self._resting.pop(server, None)
                    continue
                elif found == FAILED:
                    self._rest(server, t0)
                    continue
                if found != PARTIAL:  # (a partial range's holder rests for both queries)
                    t0 = time.monotonic()
            else:
                t0 = time.monotonic()
            if self._fetch_snapshot(server, rep.origin, rep.asked):
                self._resting.pop(server, None)
                return
            self._rest(server, t0)

    def _rest(self, server: str, since: float) -> None:
        """`server` gave nothing usable to a query sent at `since`: it is not asked again, for
        any layer, for as long as that query took. A member whose heartbeat lists made-up
        layers (or claims versions it does not hold) while its queryable never answers gets
        at most about half of the one repair worker's time, not a query timeout per layer."""
        now = time.monotonic()
        if len(self._resting) >= MAX_SHORT:
            self._resting = {s: t for s, t in self._resting.items() if t > now}
            if len(self._resting) >= MAX_SHORT:
                self._resting.clear()
        self._resting[server] = now + (now - since)
        self.metrics.add("repair_holders_rested")

    def ask(
        self,
        server: str,
        query: str,
        layer: str,
        request: SnapshotRequest | DeltaRangeRequest | HistoryRequest,
        cls: type[SnapshotReply] | type[DeltaRangeReply] | type[HistoryReply],
        marks: dict[str, float] | None = None,
        timeout_s: float | None = None,
    ) -> Replies:
        """Send a request frame to `server`'s queryable; the replies of type `cls` for `layer`
        and this request (every other reply is rejected and counted), validated but not accepted:
        the caller checks them as a whole, then `take`s them (a refused reply moves no replay
        window). `marks`, if given, gets
        "first" (time.monotonic() of the first reply) and "decode_s" (seconds decoding);
        `timeout_s` overrides the query timeout, which the request carries (`timeout_ms`)."""
        timeout = self.query_timeout_s if timeout_s is None else timeout_s
        # the request says how long we wait: a holder stops working for it after that
        request = request.model_copy(update={"timeout_ms": min(int(timeout * 1000), 0xFFFF_FFFF)})
        replies = self.session.get(
            query_key(self.namespace, server, query, layer),  # type: ignore[arg-type]
            payload=self.sender.encode(request),
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        out = Replies()
        frames: set[tuple[str, int, int]] = set()  # (origin, epoch, seq) of the replies taken
        decode_s = 0.0
        held = 0  # voxels of the replies taken
        # (history pages are not capped here: a single version goes whole, however large)
        cap = math.inf if cls is HistoryReply else self.max_voxels
        full = False  # a reply went past `cap`: the rest is refused undecoded
        refused: Counter[str] = Counter()
        for reply in replies:
            if reply.ok is None:
                continue
            t = time.monotonic()
            if marks is not None:
                marks.setdefault("first", t)
            raw = reply.ok.payload.to_bytes()
            try:
                if len(out) >= MAX_REPLY_PARTS:
                    raise WireError("oversized", f"expected at most {MAX_REPLY_PARTS} replies")
                if len(raw) > request.max_part_bytes:
                    text = (
                        f"expected reply frames of at most {request.max_part_bytes} bytes (the "
                        f"request's max_part_bytes), found {len(raw)}"
                    )
                    raise WireError("oversized", text)
                if full:
                    text = (
                        f"expected replies holding at most {cap} voxels together, found more in "
                        f"the {len(out)} taken and the one past them: the rest refused undecoded"
                    )
                    raise WireError("over-budget", text)
                # (a reply behind the replay window passes: its request id proves it fresh)
                msg = self.receiver.decode(raw, key_expr=str(reply.ok.key_expr), answer=True)
                if not (
                    isinstance(msg, cls)
                    and msg.layer == layer
                    and msg.request_id == request.request_id
                ):
                    text = (
                        f"expected a {cls.KIND} for layer {layer!r}, request "
                        f"{request.request_id}, found a {msg.KIND}"
                    )
                    raise WireError("bad-reply", text)
                n = reply_items(msg)
                if held + n > cap:  # the layer's budget could never take them all
                    full = True
                    text = (
                        f"expected replies holding at most {cap} voxels together, found {held} "
                        f"taken + {n} in part {msg.part} of {msg.parts}"
                    )
                    raise WireError("over-budget", text)
                frame = (msg.origin, msg.epoch, msg.seq)
                if frame in frames:  # peeked, not recorded: a copy passes `decode`
                    text = f"expected each reply frame once, found seq {msg.seq} again"
                    raise WireError("replay", text)
                frames.add(frame)
                held += n
                out.append(msg)
                out.sizes.append(len(raw))
            except (ProtocolError, WireError) as exc:
                self.metrics.reject(exc.reason)
                if not refused:  # one warning per query: a flood of replies floods no log
                    log.warning("rejected a %s reply from %s: %s", query, server, exc)
                refused[exc.reason] += 1
            decode_s += time.monotonic() - t
        if refused.total() > 1:
            log.warning(
                "rejected %d %s replies from %s in all (%s)",
                refused.total(),
                query,
                server,
                ", ".join(f"{reason} {n}" for reason, n in sorted(refused.items())),
            )
        if marks is not None:
            marks["decode_s"] = decode_s
        return out

    def take(self, replies: Replies) -> None:
        """Accept the replies of one query that passed every check (their replay windows move,
        their bytes count), oldest frame first; ProtocolError (counted) if one was accepted
        meanwhile on another thread."""
        pairs = zip(replies, replies.sizes, strict=True)
        for msg, size in sorted(pairs, key=lambda r: (r[0].epoch, r[0].seq)):
            self.receiver.accept(msg, answer=True)
            self.metrics.add("bytes_received", size)

    def _fetch_range(self, server: str, origin: str, layer: Layer, want: int) -> str:
        """Deltas of `origin`'s layer above ours from `server`: `TAKEN`, `NOTHING_NEWER`,
        `NOT_HELD`, `PARTIAL` or `FAILED`."""
        want = max(want, max((p for p, *_ in layer.pending.values()), default=0), layer.seq + 1)
        rid = self._rng.getrandbits(63)
        request = DeltaRangeRequest(
            **self.sender.header(),
            layer=origin,
            request_id=rid,
            from_version=layer.seq,
            to_version=want,
            max_part_bytes=self.part_bytes,
        )
        msgs = self.ask(server, "deltas", origin, request, DeltaRangeReply)
        self.metrics.add("range_repairs")
        if not complete(msgs, "range"):
            return PARTIAL if msgs else FAILED
        if not all(m.complete for m in msgs):
            return NOT_HELD
        groups: dict[tuple[int, int], list[tuple[int, Delta]]] = {}
        for m in msgs:
            if m.delta is not None:
                d = m.delta
                groups.setdefault((d.from_version, d.to_version), []).append((m.part, d))
        epochs = {m.layer_epoch for m in msgs}
        if len(epochs) != 1:
            self.metrics.reject("bad-parts")
            return FAILED
        epoch = epochs.pop()
        try:
            deltas = [
                concat([d for _, d in sorted(groups[versions], key=lambda x: x[0])])
                for versions in sorted(groups, key=lambda v: v[1])
            ]
            # admitted, taken and applied with no other delta applied in between (the inbox
            # applies live ones on its thread): what the admission found still holds, and a
            # holder whose range passed it is not refused (and rested) for another's delta
            with self.layers.apply_lock:
                self.replicas.admit(origin, epoch, deltas)  # all of them, before any is taken
                self.take(msgs)
                for delta in deltas:
                    # a gap it leaves is this repair's own: `_repair` goes on to a snapshot
                    self.replicas.offer(origin, epoch, delta, admitted=True, via="range")
        except (ProtocolError, WireError) as exc:
            self.metrics.reject(exc.reason)
            log.warning("range reply from %s refused: %s", server, exc)
            return FAILED
        if deltas:
            return TAKEN
        return NOTHING_NEWER if epoch == layer.epoch else NOT_HELD  # another epoch: snapshot

    def _fetch_snapshot(self, server: str, origin: str, asked: float) -> bool:
        cpu0, process0 = time.thread_time(), time.process_time()
        marks = {"asked": asked, "request": time.monotonic()}
        rid = self._rng.getrandbits(63)
        request = SnapshotRequest(
            **self.sender.header(), layer=origin, request_id=rid, max_part_bytes=self.part_bytes
        )
        short = self._short.get(origin, 0)
        timeout = snapshot_timeout(self.query_timeout_s, short)
        msgs = self.ask(server, "snapshot", origin, request, SnapshotReply, marks, timeout)
        marks["received"] = time.monotonic()
        if not complete(msgs, "snapshot"):
            # nothing at all came too: a holder makes and encodes a big layer's whole snapshot
            # before its first part, and sends nothing once our timeout has passed (a silent
            # holder rests as long as the query took: `_rest`)
            if len(self._short) >= MAX_SHORT:
                self._short.clear()  # origins a hostile heartbeat made up: bounded
            self._short[origin] = short + 1
            log.info(
                "no whole snapshot of %s from %s within %.1f s; next time %.1f s",
                origin,
                server,
                timeout,
                snapshot_timeout(self.query_timeout_s, short + 1),
            )
            return False
        self._short.pop(origin, None)
        states = {(m.layer_epoch, m.delta.from_version, m.delta.to_version) for m in msgs}
        if len(states) != 1:
            self.metrics.reject("bad-snapshot")
            return False
        epoch, start, seq = states.pop()
        if epoch <= 0 or start != 0:
            self.metrics.reject("bad-snapshot")
            return False
        chunks = [m.delta for m in sorted(msgs, key=lambda m: m.part)]
        try:
            self.replicas.admit(origin, epoch, chunks, replace=True)
        except (ProtocolError, WireError) as exc:
            self.metrics.reject(exc.reason)
            log.warning("snapshot of %s from %s refused: %s", origin, server, exc)
            return False
        marks["admitted"] = time.monotonic()
        try:  # built apart, then taken and committed under the apply lock if its admission
            # still holds (a tombstone or another peer's delta may have come meanwhile): only
            # then are its frames accepted, a refused snapshot moved no window
            voxels = self.layers.install_snapshot(
                origin, epoch, seq, chunks, accept=lambda: self.take(msgs)
            )
        except (ProtocolError, WireError) as exc:
            self.metrics.reject(exc.reason)
            log.warning("snapshot of %s from %s refused at its install: %s", origin, server, exc)
            return False
        marks["installed"] = time.monotonic()
        marks["cpu_s"] = time.thread_time() - cpu0
        marks["process_cpu_s"] = time.process_time() - process0  # every thread's
        dt = marks["installed"] - marks["request"]
        self.metrics.add("snapshots_installed")
        self.metrics.catchup(origin, voxels, dt, marks)
        log.info(
            "caught up %s from %s: %d voxels at seq %d in %.3f s (%s)",
            origin,
            server,
            voxels,
            seq,
            dt,
            timeline(marks),
        )
        return True


def timeline(marks: dict[str, float]) -> str:
    """`marks` (time.monotonic() by step, and durations ending in "_s") as the milliseconds of
    each step after the first, in order: "first +12.3 ms, received +45.6 ms, ..."."""
    points = sorted((t, k) for k, t in marks.items() if not k.endswith("_s"))
    if not points:
        return ""
    t0 = points[0][0]
    steps = [f"{k} +{(t - t0) * 1000:.1f} ms" for t, k in points[1:]]
    steps += [f"{k} {v * 1000:.1f} ms" for k, v in marks.items() if k.endswith("_s")]
    return ", ".join(steps)
