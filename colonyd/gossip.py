"""Gossip: wires the publisher, inbox, catch-up and layer server of one daemon together.

Everything on the wire is the colony protocol (`protocol/`, docs/PROTOCOL.md): VoxelDelta on
`<origin>/delta`, Heartbeat on `<origin>/heartbeat`, Objects on `<origin>/objects`, AlignOffer on
`<origin>/align`, PoseFix on `<origin>/fix`, pushed HistoryReply on `<origin>/history` (opt-in),
SnapshotRequest/Reply, DeltaRangeRequest/Reply and
HistoryRequest/Reply through the `<server>/snapshot/<layer>`, `<server>/deltas/<layer>` and
`<server>/history/<layer>` queryables. Layer versions on the wire are the origin's delta sequence
numbers; history versions are the origin's grid versions.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

from colonyd.alignment import Alignments, Edge
from colonyd.catchup import CatchUp
from colonyd.frames import Sender
from colonyd.historysync import HistorySync
from colonyd.inbox import Inbox
from colonyd.layers import Layers
from colonyd.layerserver import LayerServer
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.objects import PeerObjects
from colonyd.publisher import Publisher
from colonyd.replicas import Replicas
from protocol import HistoryReply, ObjectCentroid, OwnOriginError, PoseFix, Receiver
from voxel.delta import Delta


class Gossip:
    """Own deltas out; peers' deltas, heartbeats and catch-up in; range and snapshot served."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        layers: Layers,
        sender: Sender,
        receiver: Receiver,
        metrics: Metrics,
        *,
        epoch: int,
        on_own_origin: Callable[[OwnOriginError], None] | None = None,
        on_fix: Callable[[PoseFix], None] | None = None,
        inbox_size: int = 256,
        inbox_bytes: int = 128 << 20,
        drop_rate: float = 0.0,
        query_timeout_s: float = 5.0,
        chunk_voxels: int = 250_000,
        part_bytes: int = 4 << 20,
        history_sync_s: float = 5.0,
        peer_history_entries: int = 2_000_000,
        history_push: bool = False,
        max_members: int = 1024,
    ) -> None:
        self.stop = threading.Event()  # one stop for every worker: they wind down together
        replicas = Replicas(layers, metrics)
        self.peer_objects = PeerObjects(max_members)  # cameras list objects, with no layer
        self.alignments = Alignments(layers.max_layers)
        self.publisher = Publisher(
            session, namespace, layers, sender, metrics, epoch=epoch, part_bytes=part_bytes
        )
        self.catchup = CatchUp(
            session,
            namespace,
            replicas,
            sender,
            receiver,
            metrics,
            query_timeout_s=query_timeout_s,
            part_bytes=part_bytes,
            stop=self.stop,
        )
        self.layers = layers
        self.history_push = history_push
        self.history = HistorySync(
            layers,
            self.catchup,
            metrics,
            period_s=history_sync_s,
            budget=peer_history_entries,
            stop=self.stop,
        )
        self.inbox = Inbox(
            session,
            namespace,
            replicas,
            receiver,
            metrics,
            self.peer_objects,
            self.alignments,
            request_repair=self.catchup.request,
            send_heartbeat=self.publisher.hb_now.set,
            on_own_origin=on_own_origin,
            on_fix=on_fix,
            on_history=self._take_history if history_push else None,
            admit_history=self._admit_history,
            size=inbox_size,
            max_bytes=inbox_bytes,
            drop_rate=drop_rate,
            stop=self.stop,
        )
        self.server = LayerServer(
            session,
            namespace,
            layers,
            sender,
            receiver,
            metrics,
            epoch=epoch,
            chunk_voxels=chunk_voxels,
            part_bytes=part_bytes,
            stop=self.stop,
        )
        self.hb_now = self.publisher.hb_now  # set on a join: send our heartbeat without waiting

    def start(self, membership: Membership) -> None:
        self.inbox.start(membership)
        self.server.start()
        self.catchup.start(membership)
        self.history.start(membership)

    def close(self) -> None:
        self.stop.set()
        self.inbox.close()
        self.server.close()
        self.catchup.close()
        self.history.close()
        self.publisher.close()

    def on_member_event(self, agent: str, event: str) -> None:
        """Liveliness join or leave (on a Zenoh thread: only enqueues)."""
        self.inbox.on_member_event(agent, event)

    def publish_own(
        self,
        prev: int,
        seq: int,
        delta: Delta,
        created: float,
        encoded: tuple[Delta, list[bytes]] | None = None,
        marks: dict[str, float] | None = None,
    ) -> int:
        """Publish an own delta (already logged); returns the bytes sent."""
        return self.publisher.publish_own(prev, seq, delta, created, encoded, marks)

    def push_history(self, upto: int) -> int:
        """With history push on, publish the own history records not pushed yet, of versions
        up to `upto` (what the log holds)."""
        return self.publisher.push_history(upto) if self.history_push else 0

    def _admit_history(self, msg: HistoryReply) -> None:
        """WireError unless `_take_history` can take a peer's pushed history (inbox thread,
        before the frame is accepted)."""
        layer = self.layers.find(msg.origin)
        if msg.records is not None and layer is not None and layer.seq > 0:
            self.history.admit(layer, msg.layer_epoch, msg.from_version, msg.records)

    def _take_history(self, msg: HistoryReply) -> None:
        """A peer's pushed history (inbox thread): into its replica when it follows on; one
        that came before the replica held the layer is remembered, and the layer pulled once it
        arrives."""
        if msg.records is None:
            return
        layer = self.layers.find(msg.origin)
        if layer is None or layer.seq == 0:
            self.history.dropped(msg.origin, msg.layer_epoch)  # pulled once the layer arrives
            return
        self.history.offer(layer, msg.layer_epoch, msg.from_version, msg.records)

    def encode_own(
        self, prev: int, seq: int, delta: Delta, created: float
    ) -> tuple[Delta, list[bytes]]:
        """Frames of an own delta, made before it is logged (nothing sent)."""
        return self.publisher.encode_own(prev, seq, delta, created)

    def publish_objects(self, objects: list[ObjectCentroid]) -> None:
        """Publish the own layer's object list."""
        self.publisher.publish_objects(objects)

    def publish_align(self, edge: Edge) -> None:
        """Keep an own alignment and offer it to the colony."""
        self.alignments.put(edge)
        self.publisher.publish_align(edge)

    def heartbeat(self, kind: str, pose: list[float]) -> None:
        """Publish what this daemon is and holds."""
        self.publisher.heartbeat(kind, pose)
