"""A node of a robot's ROS 2 graph on rmw_zenoh: publishers with their tokens and attachments."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh
import zenoh.ext

from plugins import rmw

log = logging.getLogger(__name__)


class RosPublisher:
    """One ROS 2 publisher: a Zenoh (advanced, when transient-local) publisher on the topic's key,
    its MP liveliness token and a 33-byte attachment on every message.

    Transient-local keeps the last `depth` messages for late subscribers (rmw_zenoh's
    AdvancedPublisher cache, found by their `detect_late_publishers`). `block` makes a congested
    link slow the publisher down instead of dropping (big clouds, maps).
    """

    def __init__(
        self,
        node: RosNode,
        topic: str,
        ros_type: str,
        *,
        reliable: bool = True,
        transient_local: bool = False,
        depth: int = 10,
        block: bool = False,
    ) -> None:
        self.topic, self.ros_type = topic, ros_type
        self.type_hash = rmw.type_hash(ros_type) if node.type_hashes else rmw.NO_HASH
        session, domain = node.session, node.domain
        key = rmw.data_key(domain, topic, ros_type, self.type_hash)
        qos = rmw.qos_text(reliable=reliable, transient_local=transient_local, depth=depth)
        token = rmw.endpoint_token(
            domain,
            node.zid,
            node.node_id,
            node.next_id(),
            rmw.PUBLISHER,
            node.namespace,
            node.name,
            topic,
            ros_type,
            self.type_hash,
            qos,
        )
        self.gid = rmw.gid_of(token)
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        reliability = zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT
        if transient_local:
            self._pub: Any = zenoh.ext.declare_advanced_publisher(
                session,
                key,
                congestion_control=congestion,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(max_samples=depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=0.5
                )
                if reliable
                else None,
            )
        else:
            self._pub = session.declare_publisher(
                key, congestion_control=congestion, reliability=reliability
            )
        self._token = session.liveliness().declare_token(token)
        self._seq = 0
        self._lock = threading.Lock()
        self.key = key

    def publish(self, msg: Any) -> int:
        """Serialise `msg` (a rosbags message of this publisher's type) and put it; its bytes."""
        payload = bytes(rmw.typestore().serialize_cdr(msg, self.ros_type))
        self.put(payload)
        return len(payload)

    def put(self, payload: bytes) -> None:
        """Put ready CDR bytes with the next attachment."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        attachment = rmw.Attachment(seq, time.time_ns(), self.gid).encode()
        self._pub.put(payload, attachment=attachment)

    def close(self) -> None:
        for entity in (self._token, self._pub):
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - closing: whatever it was, go on
                log.debug("undeclare: %s", exc)


class RosNode:
    """A ROS 2 node on an open Zenoh session: its NN token and a counter of entity ids.

    `type_hashes=False` writes `TypeHashNotSupported` where keys and tokens carry a type hash, as
    Humble's rmw_zenoh does (its subscribers match nothing else).
    """

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        domain: int = 0,
        namespace: str = "",
        *,
        type_hashes: bool = True,
    ) -> None:
        self.session, self.name, self.domain, self.namespace = session, name, domain, namespace
        self.type_hashes = type_hashes
        self.zid = str(session.zid())
        self.node_id = 0
        self._ids = 0
        self._token = session.liveliness().declare_token(
            rmw.node_token(domain, self.zid, self.node_id, namespace, name)
        )
        self.publishers: list[RosPublisher] = []

    def next_id(self) -> int:
        self._ids += 1
        return self._ids

    def publisher(self, topic: str, ros_type: str, **qos: Any) -> RosPublisher:
        """A publisher of this node (closed with it)."""
        pub = RosPublisher(self, topic, ros_type, **qos)
        self.publishers.append(pub)
        return pub

    def close(self) -> None:
        for pub in self.publishers:
            pub.close()
        try:
            self._token.undeclare()
        except Exception as exc:  # noqa: BLE001 - closing: whatever it was, go on
            log.debug("undeclare: %s", exc)
