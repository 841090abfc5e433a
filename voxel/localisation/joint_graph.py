"""Joint pose graph of two robots: a robot's matches against a peer's map tied to the peer's past
poses that built the map, so one solve can move both trajectories (inter-robot loop closures)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import scipy.sparse as sp

from voxel.errors import LocalisationError
from voxel.localisation.pose_graph import (
    PoseGraph,
    Term,
    _information,
    _wrap,
    gauss_newton,
    normal_equations,
    variance_components,
)

#: Step (m, rad) of the central differences that linearise the inter-robot edges.
STEP = 1e-6
#: The edge groups whose covariances variance component estimation scales (`JointGraph.solve`):
#: the robot's own edges, the peer's own edges, the inter-robot edges.
GROUPS = ("robot", "peer", "inter")
#: `JointGraph.solve(vce=True)`: re-solve until no group's factor moves by more than this
#: fraction, at most `VCE_ROUNDS` solves.
VCE_CHANGE = 0.05
VCE_ROUNDS = 8


def matrices(poses: np.ndarray) -> np.ndarray:
    """Homogeneous 3x3 matrices (..., 3, 3) of planar poses (..., 3)."""
    p = np.asarray(poses, np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    out = np.zeros((*p.shape[:-1], 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = c, -s, p[..., 0]
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = s, c, p[..., 1]
    out[..., 2, 2] = 1.0
    return out


def poses_of(m: np.ndarray) -> np.ndarray:
    """Planar poses (..., 3) of homogeneous 3x3 matrices (..., 3, 3)."""
    return np.stack([m[..., 0, 2], m[..., 1, 2], np.arctan2(m[..., 1, 0], m[..., 0, 0])], -1)


def _inverse(m: np.ndarray) -> np.ndarray:
    """Inverses of rigid 3x3 matrices (..., 3, 3)."""
    out = np.zeros_like(m)
    rt = np.swapaxes(m[..., :2, :2], -1, -2)
    out[..., :2, :2] = rt
    out[..., :2, 2] = -np.einsum("...ij,...j->...i", rt, m[..., :2, 2])
    out[..., 2, 2] = 1.0
    return out


def _diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b for poses (..., 3), the angle wrapped."""
    d: np.ndarray = a - b
    d[..., 2] = _wrap(d[..., 2])
    return d


@dataclass(frozen=True)
class JointSmoothed:
    """A solved joint graph: both robots' body poses, the transform (x, y, yaw) taking the
    peer's frame into the robot's, and the fit's cost before and after with its iterations."""

    robot: np.ndarray
    peer: np.ndarray
    transform: np.ndarray
    cost_before: float
    cost_after: float
    iterations: int
    #: With variance component estimation: each group's (`GROUPS`) covariance factor the last
    #: solve used, and how many solves it took.
    factors: dict[str, float] = field(default_factory=dict)
    rounds: int = 1


class JointGraph:
    """Two robots' pose graphs (their own edges: odometry, own-map matches, priors), one
    transform T between their frames (prior: the alignment the robot put the peer's map in its
    frame with, and that alignment's covariance), and inter-robot edges in place of the robot's
    colony edges (its rigid map offsets are dropped).

    An inter edge is a robot pose matched against the peer's map at robot node x: the map near
    there was built by peer nodes j (weights w_j, summing to 1) at the peer's online estimates
    y_j°, so it is off, in the robot's frame, by b_j = A y_j° y_j^-1 T^-1 (A the alignment, y_j
    the peer node's smoothed pose): the matched pose is z = x + sum_j w_j (b_j x - x), as
    `PoseGraph`'s own-map match moves a node by its keyframes' errors. At the start (T = A,
    y = y°) every b_j is the identity. The solve moves the robot's nodes, the peer's nodes (so
    its map) and T together. `peer_inflation`: the peer's own edges' covariances times this (a
    diagnostic of how stiff its graph is; 1: as its filter fused them); `inter_inflation`: the
    inter edges' covariances times this (diagnostic; 1: the matcher's); `inter_floor`: a
    covariance (3x3) added to every inter edge's before that (an error the matcher's leaves
    out: the peer map's quantisation). Reads no reference."""

    def __init__(
        self,
        robot: PoseGraph,
        peer: PoseGraph,
        alignment: np.ndarray,
        covariance: np.ndarray,
        peer_inflation: float = 1.0,
        inter_inflation: float = 1.0,
        inter_floor: np.ndarray | None = None,
    ) -> None:
        if not (peer_inflation > 0 and inter_inflation > 0):
            msg = (
                "joint graph: expected positive inflations, found "
                f"{peer_inflation!r}, {inter_inflation!r}"
            )
            raise LocalisationError(msg)
        self.inter_inflation = float(inter_inflation)
        self.inter_floor = (
            np.zeros((3, 3)) if inter_floor is None else np.asarray(inter_floor, np.float64)
        )
        if self.inter_floor.shape != (3, 3):
            msg = f"joint graph: expected a 3x3 inter floor, found {self.inter_floor.shape}"
            raise LocalisationError(msg)
        self.robot, self.peer = robot, peer
        self.peer_inflation = float(peer_inflation)
        self.alignment = np.asarray(alignment, np.float64).reshape(3)
        self._prior = _information(covariance)
        # inter edges by their number of peer nodes G: (node, peer nodes (G,), weights (G,),
        # z (3,), information (3, 3))
        self._inter: dict[int, list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]]
        self._inter = {}

    def add_inter(
        self,
        node: int,
        pose: np.ndarray,
        covariance: np.ndarray,
        peer_nodes: np.ndarray,
        weights: np.ndarray,
    ) -> None:
        """An inter-robot edge: the robot's `node` matched at `pose` (x, y, yaw, its frame) with
        `covariance` against the peer's map built by `peer_nodes` (G,) with `weights` (G,)."""
        ids = np.asarray(peer_nodes, np.int64).reshape(-1)
        w = np.asarray(weights, np.float64).reshape(-1)
        if (
            len(ids) == 0
            or len(ids) != len(w)
            or not 0 <= node < self.robot.nodes
            or ids.min() < 0
            or ids.max() >= self.peer.nodes
            or not (w >= 0).all()
            or not math.isclose(float(w.sum()), 1.0, rel_tol=1e-6)
        ):
            msg = (
                "joint graph: expected a robot node, G >= 1 known peer nodes and G weights >= 0 "
                f"summing to 1, found node {node}, peer nodes {ids}, weights {w}"
            )
            raise LocalisationError(msg)
        z = np.asarray(pose, np.float64).reshape(3)
        noise = np.asarray(covariance, np.float64) + self.inter_floor
        info = _information(noise * self.inter_inflation)
        self._inter.setdefault(len(ids), []).append((node, ids, w, z, info))

    def edges(self) -> int:
        """How many inter-robot edges."""
        return sum(len(g) for g in self._inter.values())

    def solve(
        self, iterations: int = 20, tolerance: float = 1e-7, vce: bool = False
    ) -> JointSmoothed:
        """Both trajectories and the transform minimising the joint cost, from the robots' online
        estimates and the alignment (Gauss-Newton, `gauss_newton`). With `vce`, each group of
        edges (`GROUPS`) has its covariances scaled by a factor estimated from the data (a
        posteriori variance component estimation, `variance_components`): at each solution a
        factor becomes itself times the group's cost over its redundancy, and the graph is
        solved again from there until no factor moves by more than `VCE_CHANGE` (at most
        `VCE_ROUNDS` solves). The transform's prior keeps its covariance."""
        a, b = self.robot.nodes, self.peer.nodes
        x = np.concatenate(
            [np.array(self.robot.online), np.array(self.peer.online), self.alignment[None]]
        )
        factors = dict.fromkeys(GROUPS, 1.0)
        first: float | None = None
        done = rounds = 0
        cost = 0.0
        for rounds in range(1, (VCE_ROUNDS if vce else 1) + 1):
            linearised = partial(self._linearised, factors=dict(factors))
            x, before, cost, done = gauss_newton(linearised, x, a + b + 1, iterations, tolerance)
            first = before if first is None else first
            if not vce:
                break
            groups, others = self._terms(x, factors)
            found = variance_components(groups, others, 3 * (a + b + 1))
            new = dict(factors)
            for name, (omega, redundancy, _) in found.items():
                if redundancy > 0.5:  # a group the solve absorbs whole says nothing of its noise
                    new[name] = factors[name] * omega / redundancy
            if max(abs(new[k] / factors[k] - 1.0) for k in GROUPS) <= VCE_CHANGE:
                break
            if rounds < VCE_ROUNDS:
                factors = new
        assert first is not None
        return JointSmoothed(
            x[:a],
            x[a : a + b],
            x[a + b],
            first,
            cost,
            done,
            factors if vce else {},
            rounds,
        )

    def _linearised(
        self, x: np.ndarray, factors: dict[str, float]
    ) -> tuple[float, sp.csr_matrix, np.ndarray]:
        """The cost, normal matrix and gradient at `x`, each group weighted by its factor."""
        groups, others = self._terms(x, factors)
        size = 3 * (self.robot.nodes + self.peer.nodes + 1)
        return normal_equations([t for g in groups.values() for t in g] + others, size)

    def _terms(
        self, x: np.ndarray, factors: dict[str, float]
    ) -> tuple[dict[str, list[Term]], list[Term]]:
        """The edges linearised at `x` by group (`GROUPS`), each group's information divided by
        its factor, and the rest (the transform's prior)."""
        a, b = self.robot.nodes, self.peer.nodes
        none = np.zeros((0, 3))
        groups: dict[str, list[Term]] = {}
        groups["robot"] = [
            (blocks, r, info / factors["robot"])
            for blocks, r, info in self.robot.terms(x[:a], none, shared=False)
        ]
        scale = self.peer_inflation * factors["peer"]
        groups["peer"] = [
            ([(ids + a, j) for ids, j in blocks], r, info / scale)
            for blocks, r, info in self.peer.terms(x[a : a + b], none, shared=False)
        ]
        t = a + b
        prior, jac = _numeric(self._prior_residual, x[t][None])
        others: list[Term] = [([(np.array([t]), jac)], prior, self._prior[None])]
        online = np.array(self.peer.online)
        groups["inter"] = []
        for group in self._inter.values():
            blocks, r, info = self._inter_term(x[:a], x[a : a + b], x[t], online, group, a, t)
            groups["inter"].append((blocks, r, info / factors["inter"]))
        return groups, others

    def _prior_residual(self, transform: np.ndarray) -> np.ndarray:
        """The map's offset A T^-1 (zero when T is the alignment), per row of `transform`."""
        return poses_of(matrices(self.alignment) @ _inverse(matrices(transform)))

    def _inter_term(
        self,
        robot: np.ndarray,
        peer: np.ndarray,
        transform: np.ndarray,
        online: np.ndarray,
        group: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
        first_peer: int,
        transform_id: int,
    ) -> Term:
        """Inter edges with G peer nodes each: residual x + sum_j w_j (b_j x - x) - z, blocks on
        the robot node, the G peer nodes and T (central differences)."""
        node = np.array([g[0] for g in group])
        ids = np.stack([g[1] for g in group])  # (E, G)
        w = np.stack([g[2] for g in group])
        z = np.stack([g[3] for g in group])
        info = np.stack([g[4] for g in group])
        e_count, g_count = ids.shape
        fixed = matrices(self.alignment) @ matrices(online[ids])  # A y° (E, G, 3, 3)

        def parts(x: np.ndarray, t: np.ndarray, y: np.ndarray) -> np.ndarray:
            """w_j (b_j x - x) (E, G, 3)."""
            b = fixed @ _inverse(matrices(y)) @ _inverse(matrices(t))[:, None]
            moved = poses_of(b @ matrices(x)[:, None])
            out: np.ndarray = w[..., None] * _diff(moved, np.repeat(x[:, None], g_count, 1))
            return out

        x, t, y = robot[node], np.tile(transform, (e_count, 1)), peer[ids]
        r = x + parts(x, t, y).sum(1) - z
        r[:, 2] = _wrap(r[:, 2])
        jx = np.zeros((e_count, 3, 3))
        jt = np.zeros((e_count, 3, 3))
        jy = np.zeros((e_count, g_count, 3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = STEP
            jx[:, :, k] = _diff(
                x + d + parts(x + d, t, y).sum(1), x - d + parts(x - d, t, y).sum(1)
            ) / (2 * STEP)
            jt[:, :, k] = _diff(parts(x, t + d, y).sum(1), parts(x, t - d, y).sum(1)) / (2 * STEP)
            jy[:, :, :, k] = _diff(parts(x, t, y + d), parts(x, t, y - d)) / (2 * STEP)
        blocks = [(node, jx), (np.full(e_count, transform_id), jt)]
        blocks += [(first_peer + ids[:, g], jy[:, g]) for g in range(g_count)]
        return blocks, r, info


def _numeric(f: Callable[[np.ndarray], np.ndarray], v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """f(v) (E, 3) and its Jacobian (E, 3, 3) by central differences, for rows v (E, 3)."""
    r = _wrapped(f(v))
    jac = np.zeros((len(v), 3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = STEP
        jac[:, :, k] = _diff(f(v + d), f(v - d)) / (2 * STEP)
    return r, jac


def _wrapped(r: np.ndarray) -> np.ndarray:
    out = np.asarray(r, np.float64).copy()
    out[..., 2] = _wrap(out[..., 2])
    return out
