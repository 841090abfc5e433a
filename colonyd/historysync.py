"""History sync: pages the history of every peer layer from a holder into its replica."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from colonyd.catchup import MAX_SERVERS, CatchUp, complete
from colonyd.errors import WireError
from colonyd.layers import Layer, Layers
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.worker import Throttle, held_text
from protocol import HistoryReply, HistoryRequest, ProtocolError
from voxel.errors import InputError
from voxel.history import HistoryPage

log = logging.getLogger(__name__)

#: Most pages one layer takes per round (the rest waits for the next round).
MAX_PAGES_PER_ROUND = 16
#: Fewest history entries a peer layer may keep, however many layers share the budget.
MIN_LAYER_ENTRIES = 10_000
#: Seconds between checks for layers whose pushed pages came before the replica held them.
ARRIVAL_CHECK_S = 1.0
#: Most origins whose dropped pushed pages are remembered (a hostile peer cannot invent many).
MAX_DROPPED = 256


def join_pages(msgs: list[HistoryReply]) -> HistoryPage | None:
    """The records of every part of one reply (parts share the agent table), or None if the
    parts disagree on it."""
    pages = [m.records for m in sorted(msgs, key=lambda m: m.part) if m.records is not None]
    if not pages:
        return None
    agents = pages[0].agents
    if any(p.agents != agents for p in pages):
        return None
    return HistoryPage(
        np.concatenate([p.records for p in pages]),
        agents,
        np.concatenate([p.seen for p in pages]),
    )


class HistorySync:
    """Every `period_s`, each peer layer asks a holder (its origin first) for the history
    records newer than the newest it holds, page by page (HistoryRequest, docs/PROTOCOL.md).
    With pushes (`offer`), a page that leaves a gap makes it pull at once, and a page that came
    before the replica held its layer (dropped) makes it pull that layer once the layer arrives,
    even when `period_s` is 0 (periodic pulls off). Peer layers keep at most `budget` history
    entries together (records and seen-log entries each), split evenly: past its share a layer
    drops its oldest."""

    def __init__(
        self,
        layers: Layers,
        catchup: CatchUp,
        metrics: Metrics,
        *,
        period_s: float,
        budget: int = 2_000_000,
        page_records: int = 200_000,
        stop: threading.Event,
    ) -> None:
        self.layers = layers
        self.catchup = catchup
        self.metrics = metrics
        self.period_s = period_s
        self.budget = budget
        self.page_records = page_records
        self.stop = stop
        self.membership: Membership | None = None
        self._thread = threading.Thread(target=self._loop, name="history-sync", daemon=True)
        self._log = Throttle()  # refused pages: a holder may send the same one every round
        #: a pushed page left a gap: pull at once, even when `period_s` is 0 (pulls off)
        self._repair = threading.Event()
        #: origin -> epoch of a pushed page dropped because the replica did not hold the layer
        #: (or not that epoch) yet: pulled once it does
        self._dropped: dict[str, int] = {}
        self._dropped_lock = threading.Lock()

    def start(self, membership: Membership) -> None:
        self.membership = membership
        self._thread.start()

    def close(self) -> None:
        self._repair.set()  # wakes the loop, which then sees `stop`
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        next_pull = time.monotonic() + self.period_s
        while not self.stop.is_set():
            wait = ARRIVAL_CHECK_S
            if self.period_s > 0:
                wait = min(wait, max(0.0, next_pull - time.monotonic()))
            gap = self._repair.wait(wait)
            if self.stop.is_set():
                return
            self._repair.clear()
            arrived = self._arrived()
            periodic = self.period_s > 0 and time.monotonic() >= next_pull
            if periodic:
                next_pull = time.monotonic() + self.period_s
            if gap or periodic:
                todo = self.layers.all()
            elif arrived:
                todo = arrived  # pulls off: only the layers whose pushed pages were dropped
            else:
                continue
            if not periodic:
                self.metrics.add("history_repairs")
            for layer in todo:
                if self.stop.is_set():
                    return
                if layer.origin == self.layers.own_id or layer.seq == 0:
                    continue
                try:
                    with self.metrics.activity.timed("history-pull"):
                        self.pull(layer)
                except Exception:
                    log.exception("history sync of %s failed", layer.origin)

    def dropped(self, origin: str, epoch: int) -> None:
        """A pushed page of `origin`'s layer at `epoch` came before this replica held that layer
        (or that epoch of it) and was dropped: its history is pulled once the layer arrives."""
        self.metrics.add("history_dropped")
        with self._dropped_lock:
            if origin in self._dropped or len(self._dropped) < MAX_DROPPED:
                self._dropped[origin] = max(epoch, self._dropped.get(origin, 0))

    def _arrived(self) -> list[Layer]:
        """The layers whose pushed pages were dropped and which the replica now holds (at that
        epoch or a later one), each forgotten from then on (pulled once); origins forgotten
        colony-wide are let go."""
        out = []
        with self._dropped_lock:
            for origin, epoch in list(self._dropped.items()):
                layer = self.layers.find(origin)
                if layer is not None and layer.seq > 0 and layer.epoch >= epoch:
                    out.append(layer)
                    del self._dropped[origin]
                elif origin in self.layers.forgotten:
                    del self._dropped[origin]
        return out

    def share(self) -> int:
        """History entries (records, and seen-log entries alike) each peer layer may keep: the
        budget split evenly among the peer layers held; each keeps its newest."""
        peers = max(1, len(self.layers.all()) - 1)
        return max(MIN_LAYER_ENTRIES, self.budget // peers)

    def offer(self, layer: Layer, epoch: int, after: int, page: HistoryPage) -> int:
        """Merge `page` (records of versions above `after` of `layer` at `epoch`) into the
        replica's history, within its share of the budget, unless it is of another epoch (a later
        one than the replica holds: pulled once the replica holds it) or leaves a gap (versions
        between the newest held and `after`: a pull fills it, at once, even with periodic pulls
        off).
        Returns records and entries taken."""
        with layer.lock:
            history = layer.grid.history
            if layer.epoch != epoch:
                if epoch > layer.epoch:
                    self.dropped(layer.origin, epoch)
                return 0
            if after > history.newest_version():  # a page before this one was missed
                self._repair.set()
                return 0
            history.capacity = self.share()  # past it, the oldest are dropped
            n = history.merge(page)
        self.metrics.add("history_records", n)
        return n

    def admit(self, layer: Layer, epoch: int, after: int, page: HistoryPage) -> None:
        """Raise WireError ("bad-history") unless `offer` can merge `page` (it would take the
        history's agent table past its bound); a page `offer` would leave aside (another epoch,
        a gap) passes. Changes nothing: the frames that brought the page are accepted after."""
        with layer.lock:
            history = layer.grid.history
            if layer.epoch != epoch or after > history.newest_version():
                return
            try:
                history.admit(page)
            except InputError as exc:
                raise WireError("bad-history", str(exc)) from exc

    def servers(self, origin: str) -> list[str]:
        """Who to ask for `origin`'s history: live holders of its newest version, origin first."""
        if self.membership is None:
            return [origin]
        _epoch, _seq, holders = self.membership.best(origin)
        return (holders or [origin])[:MAX_SERVERS]

    def pull(self, layer: Layer) -> int:
        """Page `layer`'s history from a holder until it has no more; returns records taken."""
        taken = 0
        for server in self.servers(layer.origin):
            for _ in range(MAX_PAGES_PER_ROUND):
                with layer.lock:
                    after, epoch = layer.grid.history.newest_version(), layer.epoch
                request = HistoryRequest(
                    **self.catchup.sender.header(),
                    layer=layer.origin,
                    request_id=self.catchup.new_request_id(),
                    from_version=after,
                    max_records=self.page_records,
                    max_part_bytes=self.catchup.part_bytes,
                )
                msgs = self.catchup.ask(server, "history", layer.origin, request, HistoryReply)
                if not complete(msgs, "history"):
                    break
                heads = {(m.layer_epoch, m.from_version, m.to_version, m.more) for m in msgs}
                if len(heads) != 1:
                    self.metrics.reject("bad-parts")
                    break
                got_epoch, start, _to, more = heads.pop()
                if got_epoch != epoch or start != after:
                    break  # another epoch of the layer (or none held): nothing to take here
                page = join_pages(msgs)
                try:
                    if page is not None:
                        self.admit(layer, epoch, after, page)
                    self.catchup.take(msgs)  # only now: a page refused moved no window
                except (ProtocolError, WireError) as exc:
                    self.metrics.reject(exc.reason)
                    log.warning("history of %s from %s refused: %s", layer.origin, server, exc)
                    break
                if page is not None:
                    try:
                        taken += self.offer(layer, epoch, after, page)
                    except InputError as exc:  # a page the replica cannot take (from the network)
                        self.metrics.reject("invalid")
                        if (held := self._log.allow("invalid")) is not None:
                            log.warning(
                                "refused a history page of %s from %s: %s%s",
                                layer.origin,
                                server,
                                exc,
                                held_text(held),
                            )
                        break  # the next holder, if any
                if not more:
                    return taken
            else:
                return taken
        return taken
