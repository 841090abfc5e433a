"""Objects: the own layer's list (tracked clusters, sensor-identified objects) and peers' lists."""

from __future__ import annotations

import math
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from colonyd.errors import WireError
from colonyd.grid import VoxelGrid
from colonyd.layers import Layer
from plugins.observation import AGENT_LABEL, Observation
from protocol import ObjectCentroid as WireObject
from voxel.objects import (
    LabelledVoxels,
    ObjectCentroid,
    ObjectTracker,
    cluster_objects,
    labelled_voxels,
    moved,
)

#: Tracked clusters take ids from here up; below it are the ids sensors give (markers, instances).
CLUSTER_IDS = 1 << 40


@dataclass
class _Sighting:
    """Running mean and scatter of one identified object's world positions."""

    class_id: int
    count: int
    mean: np.ndarray
    m2: np.ndarray  # sum of squared deviations (3, 3)
    time: float
    #: mean of the sightings' own covariances (world frame; zero where the sensor gave none)
    shared: np.ndarray

    def covariance(self) -> np.ndarray:
        """The mean's error: its scatter over the sightings (10 cm from one) plus what every
        sighting's own error is (a fixed camera sees a marker from one place every time: the
        same error, which averaging does not remove), plus 1 cm."""
        scatter = self.m2 / self.count / self.count if self.count > 1 else np.eye(3) * 0.01
        out: np.ndarray = scatter + self.shared + np.eye(3) * 1e-4
        return out


class OwnObjects:
    """The objects of this daemon's own layer, in its frame.

    Objects with an identity from the sensor (an ArUco marker's id, a simulator's instance id, a
    detector's track) are averaged over their sightings; other class-labelled voxels are
    clustered (DBSCAN per class, `structure` classes such as walls and floors excluded) and
    tracked so that ids stay stable as the map grows. `refresh` gives the list when it changed.
    """

    def __init__(
        self,
        structure: frozenset[int],
        *,
        min_voxels: int = 20,
        link: float = 3.0,
        gate: float = 0.75,
        tolerance: float = 0.05,
    ) -> None:
        self.structure = structure
        self.min_voxels = min_voxels
        self.link = link
        self.tolerance = tolerance
        self._tracker = ObjectTracker(gate=gate, first_id=CLUSTER_IDS)
        self._sightings: dict[int, _Sighting] = {}
        self._lock = threading.Lock()
        #: The grid and version the tracker last saw (a weak reference: a replaced grid goes).
        self._grid: weakref.ref[VoxelGrid] | None = None
        self._version = -1
        self.current: list[ObjectCentroid] = []

    def observe(self, obs: Observation) -> None:
        """Fold the objects a sensor identified in `obs` into their running means (world frame)."""
        with self._lock:
            for det in obs.objects:
                if det.class_id in self.structure or not 0 <= det.object_id < CLUSTER_IDS:
                    continue
                if det.label.startswith(AGENT_LABEL):
                    continue  # another agent's marker: that agent, not an object of the map
                rot = obs.pose[:3, :3]
                p = rot @ det.position + obs.pose[:3, 3]
                own = (
                    np.zeros((3, 3))
                    if det.covariance is None
                    else rot @ np.asarray(det.covariance, np.float64) @ rot.T
                )
                s = self._sightings.get(det.object_id)
                if s is None:
                    self._sightings[det.object_id] = _Sighting(
                        det.class_id, 1, p, np.zeros((3, 3)), obs.time, own
                    )
                    continue
                s.count += 1
                step = p - s.mean
                s.mean = s.mean + step / s.count
                s.m2 = s.m2 + np.outer(step, p - s.mean)
                s.shared = s.shared + (own - s.shared) / s.count
                s.time = max(s.time, obs.time)

    def refresh(self, layer: Layer) -> list[ObjectCentroid] | None:
        """The object list of `layer` (the own layer) if it changed since the last refresh, else
        None. The layer's grid (which a snapshot install or a restore replaces), its version and
        its labelled voxels are read under the layer's lock, together: a grid replaced meanwhile
        is never read unlocked, and a new grid is clustered afresh even at the version the old
        one had. The clustering, and scikit-learn's first import (~1 s), run without the lock,
        so a snapshot served or a scan integrated meanwhile does not wait for them."""
        voxels: LabelledVoxels | None = None
        with layer.lock:
            grid, version = layer.grid, int(layer.grid.version)
            read = weakref.ref(grid)  # not the grid itself: a replaced grid may be freed
            changed = self._grid is None or self._grid() is not grid or version != self._version
            if changed:
                voxels = labelled_voxels(grid, exclude=self.structure)
            del grid
        found: list[ObjectCentroid] = []
        if changed:
            found = cluster_objects(voxels, min_voxels=self.min_voxels, link=self.link)
        with self._lock:
            tracked = self._tracker.update(found) if changed else self._tracker.objects
            if changed:
                self._grid, self._version = read, version
            identified = [
                ObjectCentroid(
                    object_id=oid,
                    class_id=s.class_id,
                    position=s.mean,
                    covariance=s.covariance(),
                    voxel_count=0,
                    probability=1.0,
                    time=s.time,
                )
                for oid, s in sorted(self._sightings.items())
            ]
        objects = identified + tracked
        if not moved(self.current, objects, self.tolerance):
            return None
        self.current = objects
        return objects


def to_wire(objects: list[ObjectCentroid]) -> list[WireObject]:
    """Objects as the protocol's Objects list."""
    return [
        WireObject(
            object_id=o.object_id,
            class_id=o.class_id,
            position=(float(o.position[0]), float(o.position[1]), float(o.position[2])),
            covariance=[float(x) for x in np.asarray(o.covariance).ravel()],
            voxel_count=o.voxel_count,
            time=float(o.time),
        )
        for o in objects
    ]


#: Most objects the lists of all peers hold together (~2 KB each decoded: ~130 MB). A list holds
#: up to 16,384 (the protocol's most) and up to 256 peers send one: without a bound, a few hundred
#: KB of wire each, they would hold ~8 GB. Shared fairly: once full, the longest lists are trimmed
#: to an equal share (`fair_level`), so that every peer keeps at least the bound over the peers
#: holding lists (256 robots: 256 objects each, more for those next to peers with fewer).
MAX_PEER_OBJECTS = 65_536

#: Objects the lists of all peers together may bring per second, and one peer's at once (one
#: full list): decoding a list costs ~22 us an object on the inbox's one thread (0.4 s for
#: 16,384), so a peer sending full lists back to back held the inbox (deltas, heartbeats) to
#: itself. The rate is shared by the peers sending lists now (`SENDING_S`; those back at a full
#: allowance take none of it, those idle with one not full take 1/`IDLE_WEIGHT` of a share), each
#: peer's share at most `PEER_OBJECTS_PER_S`: alone, a peer may send 8192 objects a second
#: (~0.18 s of the inbox's second; the peers together ~0.36 s at most); beside three others
#: sending as much, 4096 (2000 objects at every `objects_s` = 0.5 s refresh pass). Past its
#: allowance a peer's lists are refused before their body is parsed (`too-often`) until it has
#: earned it back. A list is a peer's whole current list, so a refused one is made good by the
#: next (the daemon repeats an unchanged list).
OBJECTS_PER_S = 16_384.0
#: The most of `OBJECTS_PER_S` one peer's share may be: a full list at every refresh of the
#: default `objects_s` (2 s), 2000 objects every 0.5 s twice over; a peer flooding alone takes
#: no more of the inbox (it took all of `OBJECTS_PER_S`: ~0.36 s of every second).
PEER_OBJECTS_PER_S = 8192.0
OBJECTS_BURST = 16_384
#: Most peers whose allowance is remembered (those back at a full allowance are forgotten first).
MAX_ALLOWANCES = 4096
#: A peer counts as sending lists (a full share of `OBJECTS_PER_S`) for this long after its last
#: list was charged or refused (`PeerObjects.allow`): the default `objects_s` refresh (2 s) with
#: room. Counting every peer whose allowance was not full again, a flood's peers (deep in debt,
#: earning a tenth of the rate each) kept their shares ~20 s after their last list: 13 of a busy
#: member's next 20 lists were refused. Now, `SENDING_S` after a flood's last list, plus a busy
#: member's debt (at most one of its lists) at `PEER_OBJECTS_PER_S` (0.25 s for 2000 objects),
#: its lists pass as before the flood.
SENDING_S = 3.0
#: An idle peer whose allowance is not full (no list charged or tried within `SENDING_S`) earns
#: 1/IDLE_WEIGHT of a sending peer's share and counts as much in sharing the rate, so the peers
#: together never earn more than `OBJECTS_PER_S` (an idle peer earning a full share uncounted,
#: peers taking turns could each come back full) and a peer in debt that stopped trying still
#: earns its way out. Up to 16 idle peers leave a peer sending alone its whole
#: `PEER_OBJECTS_PER_S`.
IDLE_WEIGHT = 16
#: Least time between two sharings of the rate that `PeerObjects.allow` makes.
RESHARE_S = 0.05


def fair_level(counts: list[int], total: int) -> int | None:
    """The largest level L such that the `counts` cut to L (min(count, L) each) sum to at most
    `total` (max-min fair shares), or None if they fit uncut."""
    if sum(counts) <= total:
        return None
    left, n = total, len(counts)
    for i, c in enumerate(sorted(counts)):
        level = left // (n - i)
        if level < c:
            return level
        left -= c
    return None  # (not reached: they would fit)


class PeerObjects:
    """The latest object list each peer published (a full list replaces the previous one), for
    at most `max_origins` peers (a hostile peer cannot invent many), holding at most
    `max_objects` objects together (the longest trimmed to a fair share)."""

    def __init__(
        self,
        max_origins: int = 256,
        max_objects: int = MAX_PEER_OBJECTS,
        *,
        per_s: float = OBJECTS_PER_S,
        peer_per_s: float = PEER_OBJECTS_PER_S,
        burst: int = OBJECTS_BURST,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_origins = max_origins
        self.max_objects = max_objects
        self.per_s = per_s
        self.peer_per_s = peer_per_s
        self.burst = burst
        self._clock = clock
        self._lists: dict[str, tuple[float, list[WireObject]]] = {}
        #: origin -> (objects it may still send, clock then): `allow` and `charge`
        self._allowance: dict[str, tuple[float, float]] = {}
        #: origin -> clock of its last list charged, or tried (`allow`) once it was charged
        self._sent: dict[str, float] = {}
        #: objects a second a peer sending lists earns back: `per_s` over the peers sending
        #: theirs (`SENDING_S`; idle ones not full at 1/`IDLE_WEIGHT`), at most `peer_per_s`
        self._rate = min(per_s, peer_per_s)
        #: origin -> objects a second it earns back until the next `_share` (absent: `_rate`)
        self._rates: dict[str, float] = {}
        self._recheck = math.inf  # clock when a sending peer turns idle: shared anew then
        self._shared = -math.inf  # clock of the last `_share`
        self._lock = threading.Lock()

    def _earned(self, origin: str, now: float) -> float:
        left, then = self._allowance.get(origin, (float(self.burst), now))
        rate = self._rates.get(origin, self._rate)
        return min(float(self.burst), left + (now - then) * rate)

    def _share(self, now: float) -> None:
        """Bring every allowance to `now` at the rate it earned, then share `per_s` anew: a full
        share (at most `peer_per_s`) to each peer not back at a full allowance that sent within
        `SENDING_S`, 1/`IDLE_WEIGHT` of one to each other peer not back at it (the rates sum to
        at most `per_s` until the next sharing, whoever turns idle or fills up meanwhile)."""
        self._allowance = {o: (self._earned(o, now), now) for o in self._allowance}
        short = [o for o, (left, _) in self._allowance.items() if left < self.burst]
        sending = [o for o in short if now - self._sent.get(o, -math.inf) < SENDING_S]
        weight = len(sending) + (len(short) - len(sending)) / IDLE_WEIGHT
        self._rate = min(self.peer_per_s, self.per_s / max(1.0, weight))
        self._rates = {o: self._rate / IDLE_WEIGHT for o in short}
        self._rates.update((o, self._rate) for o in sending)
        self._recheck = min((self._sent[o] + SENDING_S for o in sending), default=math.inf)
        self._shared = now

    def rate(self) -> float:
        """Objects a second each peer sending lists earns back now."""
        with self._lock:
            return self._rate

    def allow(self, origin: str) -> None:
        """WireError (`too-often`) unless `origin` may send a list now: it has not spent more
        than its allowance (its share of `per_s` objects a second, at most `peer_per_s`, `burst`
        at once). Changes no allowance. A peer charged before counts as sending (`SENDING_S`)
        while it tries, refused or not (a peer in debt earns its full share while it waits);
        the claim is not authenticated yet, but at worst it keeps a peer not back at a full
        allowance counted, as every such peer was. The rate is shared anew then, and once a
        sending peer turned idle, at most every `RESHARE_S` (a stranger's claims cost little)."""
        with self._lock:
            now = self._clock()
            if origin in self._allowance:
                if now - self._sent.get(origin, -math.inf) >= SENDING_S:  # idle, trying again
                    self._recheck = min(self._recheck, self._shared + RESHARE_S)
                self._sent[origin] = now
            if now >= self._recheck:
                self._share(now)
            left = self._earned(origin, now)
            rate = self._rates.get(origin, self._rate)
        if left <= 0:
            text = (
                f"expected at most {rate:g} listed objects a second from {origin!r} "
                f"({self.per_s:g} shared by the peers sending lists, at most "
                f"{self.peer_per_s:g} each, {self.burst} at once), found "
                f"it {-left:.0f} objects past its allowance"
            )
            raise WireError("too-often", text)

    def charge(self, origin: str, count: int) -> None:
        """`origin` (authenticated: its frame was decoded) sent a list of `count` objects: they
        are taken from its allowance, kept or not (decoding them cost the same); it counts as
        sending for `SENDING_S` and the rate is shared anew (`_share`)."""
        with self._lock:
            now = self._clock()
            left = self._earned(origin, now) - count
            if origin not in self._allowance and len(self._allowance) >= MAX_ALLOWANCES:
                full = [o for o in self._allowance if self._earned(o, now) >= self.burst]
                for o in full or list(self._allowance)[: MAX_ALLOWANCES // 2]:
                    del self._allowance[o]
                    self._sent.pop(o, None)
            self._allowance[origin] = (left, now)
            self._sent[origin] = now
            self._share(now)  # the others brought to now at their old rates first

    def admit(self, origin: str, member: Callable[[str], bool] = lambda _: True) -> None:
        """Raise WireError unless a list of `origin` may be kept (replacing its previous one):
        a peer already holding one, or room for one more, made if need be by forgetting the
        lists of agents no longer `member`s (else agents come and gone, or made up, would keep
        every later member's list out for good)."""
        with self._lock:
            if origin not in self._lists and len(self._lists) >= self.max_origins:
                for o in [o for o in self._lists if not member(o)]:
                    del self._lists[o]
            if origin not in self._lists and len(self._lists) >= self.max_origins:
                text = (
                    f"expected object lists of at most {self.max_origins} peers, "
                    f"found another: {origin!r}"
                )
                raise WireError("too-many-layers", text)

    def put(self, origin: str, objects: list[WireObject]) -> int:
        """Keep `origin`'s list (replacing its previous one); past `max_objects` together, the
        longest lists, this one included, are cut to their first objects down to a fair share
        (`fair_level`). Returns the objects cut (from every list)."""
        with self._lock:
            self._lists[origin] = (time.time(), list(objects))
            level = fair_level([len(v[1]) for v in self._lists.values()], self.max_objects)
            if level is None:
                return 0
            cut = 0
            for o, (t, listed) in self._lists.items():
                if len(listed) > level:
                    cut += len(listed) - level
                    self._lists[o] = (t, listed[:level])
            return cut

    def drop(self, origin: str) -> None:
        with self._lock:
            self._lists.pop(origin, None)

    def get(self, origin: str) -> list[WireObject]:
        with self._lock:
            entry = self._lists.get(origin)
            return list(entry[1]) if entry else []

    def origins(self) -> list[str]:
        with self._lock:
            return sorted(self._lists)
