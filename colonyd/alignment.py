"""Alignments: transforms between agents' frames (own and offered) and the colony frame."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from colonyd.aligner import Aligner
from colonyd.errors import WireError
from colonyd.frames import Header, frame_of
from colonyd.layers import Layer
from protocol import AlignOffer
from protocol import ObjectCentroid as WireObject
from voxel.localisation import frame_error
from voxel.localisation.frame_error import PLANAR
from voxel.objects import ObjectCentroid
from voxel.registration import Alignment, AlignParams, Landmarks, MapCloud, align_clouds
from voxel.surface import delta_surface


@dataclass(frozen=True)
class Edge:
    """An accepted alignment: `transform` takes points of `target`'s frame into `source`'s;
    `covariance` (x y z roll pitch yaw) is its error as a small motion applied after it, in the
    source's frame, about the source's origin (`voxel.localisation.frame_error`)."""

    source: str
    target: str
    transform: np.ndarray  # (4, 4)
    confidence: float
    inliers: int
    rmse: float
    covariance: np.ndarray  # (6, 6)
    time: float

    def inverse(self) -> Edge:
        back = np.linalg.inv(self.transform)
        cov = self.covariance.copy()
        cov[np.ix_(PLANAR, PLANAR)] = frame_error.moved(frame_error.planar(cov), back)
        return Edge(
            self.target,
            self.source,
            back,
            self.confidence,
            self.inliers,
            self.rmse,
            cov,
            self.time,
        )


@dataclass(frozen=True)
class ColonyFrame:
    """The frame every daemon agrees on and each agent's frame in it (agents not connected to
    the root by accepted alignments have none)."""

    root: str
    transforms: dict[str, np.ndarray]  # agent -> (4, 4) taking its frame into the colony frame
    #: agent -> error (x, y, yaw variances, 3x3) of its transform, as a small motion in the
    #: colony frame about its origin: the errors of the alignments on its path to the root
    covariances: dict[str, np.ndarray] = field(default_factory=dict)

    def covariance(self, agent: str) -> np.ndarray:
        """The error of `agent`'s transform (zeros for the root, or without one)."""
        return self.covariances.get(agent, np.zeros((3, 3)))


def layer_cloud(layer: Layer) -> MapCloud:
    """A layer's known voxels as registration sees them (read under the layer's lock): its
    occupied voxels as their surface points (`voxel.surface.delta_surface`)."""
    full = layer.full()
    known = ~np.isnan(full.logodds)
    return MapCloud.from_keys(
        layer.resolution,
        full.keys[known],
        full.logodds[known] >= 0,
        layer.origin,
        surface=delta_surface(full)[known],
    )


def landmarks_of(objects: Sequence[ObjectCentroid | WireObject]) -> Landmarks:
    """Object centroids (own or a peer's list) as registration's landmarks."""
    return Landmarks.of([(o.class_id, np.asarray(o.position, float)) for o in objects])


def align_layers(
    own: Layer,
    peer: Layer,
    dof: int,
    own_objects: Sequence[ObjectCentroid | WireObject] = (),
    peer_objects: Sequence[ObjectCentroid | WireObject] = (),
    aligner: Aligner | None = None,
) -> Alignment:
    """Register `peer`'s layer to `own`'s by geometry and both object lists: the transform of
    the peer's frame into ours. The layers are read here; the registration itself runs in the
    `aligner`'s worker process when one is given (in this thread otherwise)."""
    a, b, params = layer_cloud(own), layer_cloud(peer), AlignParams(dof=dof)
    objects_a, objects_b = landmarks_of(own_objects), landmarks_of(peer_objects)
    if aligner is None:
        return align_clouds(a, b, params, objects_a=objects_a, objects_b=objects_b)
    return aligner.run(align_clouds, a, b, params, objects_a=objects_a, objects_b=objects_b)


def edge_of(own: str, peer: str, result: Alignment, scatter: np.ndarray | None = None) -> Edge:
    """The edge of an accepted registration, with an honest covariance
    (`frame_error.from_residuals`: the fit's shape, its residual's size, plus `scatter`, how far
    the previous estimate of this alignment was from this one)."""
    names = ["x", "y", "z", "roll", "pitch", "yaw"]
    cov = np.zeros((6, 6))
    if result.covariance.ndim == 2:
        for i, a in enumerate(result.covariance_params):
            for j, b in enumerate(result.covariance_params):
                cov[names.index(a), names.index(b)] = result.covariance[i, j]
    if "yaw" in result.covariance_params and math.isfinite(result.rmse_m):
        centre = result.covariance_centre
        cov[np.ix_(PLANAR, PLANAR)] = frame_error.from_residuals(
            frame_error.planar(cov),
            result.rmse_m,
            np.zeros(2) if centre is None else centre,
            scatter,
        )
    return Edge(
        own,
        peer,
        result.transform,
        float(result.confidence),
        int(result.inliers),
        float(result.rmse_m),
        cov,
        time.time(),
    )


def offer_of(edge: Edge, header: Header) -> AlignOffer:
    """The AlignOffer message of an own edge."""
    return AlignOffer(
        **header,
        target=edge.target,
        source_frame=frame_of(edge.source),
        target_frame=frame_of(edge.target),
        **AlignOffer.split_matrix(edge.transform),
        covariance=[float(x) for x in edge.covariance.ravel()],
        inliers=edge.inliers,
        matches=edge.inliers,
        rmse=edge.rmse,
        confidence=edge.confidence,
    )


#: The largest translation (m, per axis: beyond the Earth, so that a site frame in projected
#: coordinates passes) and covariance entry (m², rad², m·rad; a standard deviation of 1000 km) an
#: AlignOffer may claim: beyond them an offer says nothing about robots' frames, and its error
#: propagated along the colony frame's tree (products with the translations) overflowed to inf,
#: which made every computation of the colony frame fail.
MAX_OFFER_M = 1e8
MAX_OFFER_COVARIANCE = 1e12


def edge_from_offer(msg: AlignOffer) -> Edge:
    """The edge a peer offers, after checking it is consistent and within `MAX_OFFER_M` and
    `MAX_OFFER_COVARIANCE`; else WireError."""
    position = np.abs(np.asarray(msg.position, float))
    covariance = np.abs(np.asarray(msg.covariance, float))
    if position.max() > MAX_OFFER_M or covariance.max() > MAX_OFFER_COVARIANCE:
        text = (
            f"expected a translation within {MAX_OFFER_M:g} m and covariance entries within "
            f"{MAX_OFFER_COVARIANCE:g}, found {position.max():.3g} m and {covariance.max():.3g}"
        )
        raise WireError("bad-align", text)
    if msg.target == msg.origin:
        raise WireError(
            "bad-align", f"expected an offer for another agent, found {msg.origin!r} itself"
        )
    if msg.source_frame != frame_of(msg.origin) or msg.target_frame != frame_of(msg.target):
        text = (
            f"expected frames {frame_of(msg.origin)!r} -> {frame_of(msg.target)!r}, found "
            f"{msg.source_frame!r} -> {msg.target_frame!r}"
        )
        raise WireError("bad-align", text)
    return Edge(
        msg.origin,
        msg.target,
        msg.matrix(),
        float(msg.confidence),
        int(msg.inliers),
        float(msg.rmse),
        np.asarray(msg.covariance, float).reshape(6, 6),
        msg.time,
    )


class Alignments:
    """Every alignment this daemon knows: per unordered pair, the latest offer of each of the two
    agents (an agent's new estimate replaces its old one; confidence 0 withdraws it); the pair's
    alignment is the more confident of the two (the newer on a tie). Bounded in the number of
    agents; the colony frame follows from them."""

    def __init__(self, max_agents: int = 256) -> None:
        self.max_agents = max_agents
        self._edges: dict[tuple[str, str], dict[str, Edge]] = {}  # pair -> offerer -> edge
        self._lock = threading.Lock()

    def admit(self, edge: Edge) -> None:
        """Raise WireError unless an edge between these agents may be kept."""
        with self._lock:
            agents = {a for pair in self._edges for a in pair}
            new = {edge.source, edge.target} - agents
            if len(agents) + len(new) > self.max_agents:
                text = f"expected alignments of at most {self.max_agents} agents, found more"
                raise WireError("too-many-layers", text)

    def put(self, edge: Edge) -> None:
        """Keep `edge` as its source's offer for the pair (confidence 0: withdraw that offer)."""
        a, b = sorted((edge.source, edge.target))
        stored = edge if (edge.source, edge.target) == (a, b) else edge.inverse()
        with self._lock:
            offers = self._edges.setdefault((a, b), {})
            if edge.confidence > 0:
                offers[edge.source] = stored
            else:
                offers.pop(edge.source, None)
                if not offers:
                    del self._edges[a, b]

    def edges(self) -> list[Edge]:
        """One edge per pair: the most confident offer (the newer on a tie)."""
        with self._lock:
            return [
                max(offers.values(), key=lambda e: (e.confidence, e.time))
                for offers in self._edges.values()
            ]

    def colony(self, agents: list[str], anchor: str | None = None) -> ColonyFrame:
        """The colony frame: the `anchor`'s frame if it is given, else the frame of the smallest
        agent id of the largest connected group; each agent reached by accepted alignments gets
        its transform along the most confident spanning tree (deterministic: every daemon that
        knows the same offers computes the same frame)."""
        edges = sorted(self.edges(), key=lambda e: (-e.confidence, e.source, e.target))
        nodes = sorted(set(agents) | {a for e in edges for a in (e.source, e.target)})
        parent = {a: a for a in nodes}

        def find(a: str) -> str:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        # a -> (b, transform taking b's frame into a's, its error in a's frame)
        tree: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {a: [] for a in nodes}
        for e in edges:  # Kruskal, most confident first
            ra, rb = find(e.source), find(e.target)
            if ra == rb:
                continue
            parent[ra] = rb
            back = e.inverse()
            # a peer's offer: finite (the protocol), maybe not a covariance: made one
            cov, cov_back = (
                frame_error.floored(frame_error.positive(frame_error.planar(x.covariance)))
                for x in (e, back)
            )
            tree[e.source].append((e.target, e.transform, cov))
            tree[e.target].append((e.source, back.transform, cov_back))
        groups: dict[str, list[str]] = {}
        for a in nodes:
            groups.setdefault(find(a), []).append(a)
        if anchor is not None and anchor in parent:
            root = anchor
        else:  # the largest group, the smallest id on a tie; its smallest id
            largest = min(groups.values(), key=lambda g: (-len(g), min(g)))
            root = min(largest)
        transforms = {root: np.eye(4)}
        covariances = {root: np.zeros((3, 3))}
        todo = [root]
        while todo:  # each edge (a -> b, T) takes b's frame into a's
            a = todo.pop()
            for b, t, cov in tree.get(a, []):
                if b not in transforms:
                    transforms[b] = transforms[a] @ t
                    covariances[b] = covariances[a] + frame_error.moved(cov, transforms[a])
                    todo.append(b)
        return ColonyFrame(root, transforms, covariances)
