"""Membership: a liveliness token per daemon, join/leave events, and what each member reported."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Container
from dataclasses import dataclass, field

import numpy as np
import zenoh

from colonyd.errors import WireError
from colonyd.runtime import undeclare
from protocol import Heartbeat, KeyExprError, Pose
from protocol.keyexpr import alive_key, alive_subscription, parse_key
from voxel.localisation import frame_error, se2
from voxel.localisation.drift import OffsetWalk, PeerDrift

#: How long a starting daemon looks for a live member with its own agent id (peers reached
#: through gossip answer within ~0.1 s here).
PROBE_S = 0.3


def agent_alive(
    session: zenoh.Session, namespace: str, agent: str, seconds: float = PROBE_S
) -> bool:
    """True if a daemon with agent id `agent` holds its liveliness token in the colony now.

    Asked repeatedly for `seconds`, since `zenoh.open` returns before gossip completes the mesh.
    """
    deadline = time.monotonic() + seconds
    while True:
        left = deadline - time.monotonic()
        replies = session.liveliness().get(alive_key(namespace, agent), timeout=max(0.05, left))
        if any(reply.ok is not None for reply in replies):
            return True
        if left <= 0:
            return False
        time.sleep(min(0.05, max(0.0, left)))


@dataclass
class Member:
    """A peer as this daemon knows it."""

    agent: str
    alive: bool = True
    kind: str = "?"
    joined: float = field(default_factory=time.time)
    last_seen: float = field(default_factory=time.time)
    pose: list[float] = field(default_factory=list)
    pose_std_m: float | None = None  # position standard deviation of its last Pose message
    #: x, y, yaw covariance (its frame) of its last Pose message (validated by the inbox)
    pose_covariance: np.ndarray | None = None
    #: its drift along its path, from its Pose messages (`PeerDrift`: a walk of its map's error)
    drift: PeerDrift = field(default_factory=PeerDrift)
    layers: dict[str, tuple[int, int]] = field(default_factory=dict)
    #: an accepted heartbeat of it arrived (a liveliness token alone, which anyone who reaches
    #: the colony can declare, makes a member that is forgotten when the token goes)
    heard: bool = False


class Membership:
    """Tracks members from liveliness (join/leave) and heartbeats (kind, pose, layers).

    Bounded: a member known from its liveliness token alone is forgotten when the token goes
    (tokens are not authenticated: a stranger declaring and undeclaring made-up agent ids must not
    grow the table), at most `max_members` of them are kept while their tokens live (the oldest
    forgotten for a new one, `_room_for_token`), and at most `max_members` members were heard
    (`admit`: a heartbeat of a new agent beyond them makes room by forgetting the least recently
    seen member without a token, else it is refused). Members are bounded apart from layers: a
    member that holds no layer (a camera that publishes none, a command-line client) counts here
    only. Of the layers a heartbeat lists, `max_listed` are remembered (the sender's own first,
    then those this daemon holds, then in its order): at most `max_members` x `max_listed`
    entries, whatever a heartbeat lists (up to 4096).
    """

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        own: str,
        on_event: Callable[[str, str], None],
        max_members: int = 1024,
        *,
        max_listed: int = 4096,
    ) -> None:
        self.own = own
        self.max_members = max_members
        self.max_listed = max_listed
        self._on_event = on_event  # (agent, "join"|"leave"); must only enqueue
        self._lock = threading.Lock()
        self.members: dict[str, Member] = {}
        self._token = session.liveliness().declare_token(alive_key(namespace, own))
        self._sub = session.liveliness().declare_subscriber(
            alive_subscription(namespace), self._on_liveliness, history=True
        )

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            agent = parse_key(str(sample.key_expr)).origin
        except KeyExprError:
            return
        if agent == self.own:
            return
        joined = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            m = self.members.get(agent)
            if m is None and not joined:
                return  # the token of a member forgotten already
            if m is None:
                self._room_for_token()
                m = self.members[agent] = Member(agent)
            m.alive = joined
            m.last_seen = time.time()
            if joined:
                m.joined = m.last_seen
            elif not m.heard:
                del self.members[agent]  # a token alone, gone: nothing of it to keep
        self._on_event(agent, "join" if joined else "leave")

    def _room_for_token(self) -> None:
        """Make room for a new member known from its liveliness token alone (lock held): at
        most `max_members` such members are kept (tokens are not authenticated: a stranger
        holding ever more made-up tokens must not grow the table), the one whose token came
        first forgotten for a new one. A member heard (its heartbeat verified) is never
        forgotten for a token, and counts apart (`admit`)."""
        tokens = [x for x in self.members.values() if not x.heard]
        if len(tokens) >= self.max_members:
            del self.members[min(tokens, key=lambda x: x.joined).agent]

    def admit(self, agent: str) -> None:
        """Raise WireError unless a heartbeat of `agent` may be recorded (`heard`): a member
        already heard, or room for one more, or a heard member without a liveliness token that
        `heard` may forget to make room. Changes nothing."""
        with self._lock:
            self._room(agent)

    def _room(self, agent: str) -> Member | None:
        """The member `heard` forgets to make room for `agent` (None: no need): the least
        recently seen heard member without a liveliness token; WireError when every heard
        member holds one (lock held)."""
        m = self.members.get(agent)
        if m is not None and m.heard:
            return None
        heard = [x for x in self.members.values() if x.heard]
        if len(heard) < self.max_members:
            return None
        gone = [x for x in heard if not x.alive]
        if not gone:
            text = (
                f"expected heartbeats of at most {self.max_members} members, all alive, found "
                f"another: {agent!r}"
            )
            raise WireError("too-many-members", text)
        return min(gone, key=lambda x: x.last_seen)

    def heard(self, agent: str, hb: Heartbeat, held: Container[str] = ()) -> Member | None:
        """Record a (validated, `admit`ted) heartbeat; returns the member, or None when the room
        `admit` saw is gone: a token came back between the two for every heard member (then
        `agent` is not recorded: forgetting a live member for it would refuse that member's
        next heartbeats as one too many). Of the layers it lists, `max_listed` are remembered:
        the sender's own, then those in `held` (the peer layers this daemon holds, whose
        repairs need what members hold of them), then the rest in the sender's order."""
        with self._lock:
            try:
                evicted = self._room(agent)
            except WireError:
                return None
            if evicted is not None:  # the least recently seen member without a token
                del self.members[evicted.agent]
            m = self.members.get(agent)
            if m is None:  # alive only once its liveliness token is seen
                m = self.members[agent] = Member(agent, alive=False)
            m.heard = True
            m.last_seen = time.time()
            m.kind = hb.kind
            m.pose = list(hb.position) if hb.position is not None else []
            ranked = sorted(hb.layers, key=lambda e: (e.origin != agent, e.origin not in held))
            listed = ranked[: self.max_listed]
            m.layers = {entry.origin: (entry.epoch, entry.version) for entry in listed}
            return m

    def known(self, agent: str) -> bool:
        """True if `agent` is in the table (heard, or its liveliness token seen)."""
        with self._lock:
            return agent in self.members

    def find(self, agent: str) -> Member | None:
        """A copy of what is known of `agent`, or None."""
        with self._lock:
            m = self.members.get(agent)
            return None if m is None else Member(**vars(m))

    def posed(self, agent: str, msg: Pose) -> bool:
        """Record a (validated) Pose of a known member; False if the agent is not a member."""
        with self._lock:
            m = self.members.get(agent)
            if m is None:
                return False
            m.last_seen = time.time()
            m.pose = list(msg.position)
            cov = msg.covariance
            m.pose_std_m = float(max(0.0, cov[0] + cov[7] + cov[14]) ** 0.5)
            planar = frame_error.planar(np.array(cov))
            m.pose_covariance = 0.5 * (planar + planar.T)
            m.drift.add(se2.from_matrix(msg.matrix()), m.pose_covariance)
            return True

    def pose_covariances(self) -> dict[str, np.ndarray]:
        """Each member's x, y, yaw covariance (its frame) from its last Pose message."""
        with self._lock:
            return {
                a: m.pose_covariance
                for a, m in self.members.items()
                if m.pose_covariance is not None
            }

    def pose_drifts(self) -> dict[str, OffsetWalk]:
        """Each member's drift (a walk of its map's error) from its Pose messages, once known."""
        with self._lock:
            walks = {a: m.drift.walk() for a, m in self.members.items()}
        return {a: w for a, w in walks.items() if w is not None}

    def alive(self) -> list[str]:
        with self._lock:
            return [a for a, m in self.members.items() if m.alive]

    def table(self) -> list[Member]:
        with self._lock:
            return [Member(**vars(m)) for m in self.members.values()]

    def best(self, origin: str) -> tuple[int, int, list[str]]:
        """Highest (epoch, seq) any live member reports for `origin`, and who holds it."""
        with self._lock:
            best = (0, 0)
            holders: list[str] = []
            for a, m in self.members.items():
                if not m.alive or origin not in m.layers:
                    continue
                v = m.layers[origin]
                if v > best:
                    best, holders = v, [a]
                elif v == best:
                    holders.append(a)
        if origin in holders:  # ask the origin first
            holders.remove(origin)
            holders.insert(0, origin)
        return best[0], best[1], holders

    def holders(self, origin: str) -> list[tuple[tuple[int, int], str]]:
        """Every live member that reports `origin`'s layer with the (epoch, seq) it reports,
        highest first (the origin first among equals)."""
        with self._lock:
            found = [
                (m.layers[origin], a)
                for a, m in self.members.items()
                if m.alive and origin in m.layers
            ]
        return sorted(found, key=lambda h: (h[0], h[1] == origin), reverse=True)

    def close(self) -> None:
        undeclare(self._sub, self._token)
